"""Spline conformance kit, the diagnosis: what a failed check probably means.

TS-SLAM §III-B/§III-C, Eq. (5)-(9), as compared by :mod:`tsslam_ref.conformance`.  From the pattern
of a failed comparison's errors, name the likely mistake, mostly by evaluating the reference with
that mistake made on purpose and asking whether the candidate equals it: angular rates in the
world frame, rotations stored transposed, derivatives off by a power of Δt, the joint SE(3) spline
instead of the split one, the transposed basis matrix or the non-cumulative one, an index
convention shifted by whole segments (or t0 not subtracted), times rounded to whole nanoseconds
(basalt-headers' int64 ns), with non-uniform knots the uniform basis on each segment or control
points shifted by one against the knots, for the joint SE(3) spline world-side increments;
otherwise the size of the errors (float32 or float64 rounding, when they sit at many times) and
where they sit (only next to knots, only at the domain's ends), and which of R, omega, omegadot
fail.

Jacobians (when both files hold them): blocks transposed, in reverse order, of the opposite sign,
off by a power of Δt, or for a right perturbation instead of the left one
(of the control rotations, the output rotation or both).

Side module.  Imports ``conformance``, ``knots``, ``se3_spline``, ``spline`` and ``geometry``.
"""

from fractions import Fraction
from typing import Dict, List, Optional

import numpy as np
import torch

from tsslam_ref import conformance, knots, se3_spline, spline
from tsslam_ref.geometry import so3_exp

FLOAT32_LEVEL = 1e-8  # a failing candidate's largest scaled error from here to 3e-5: float32-level, say so
NANOSECOND_MATCH = 1e-11
"""A candidate equals the reference at nanosecond-rounded times when every quantity agrees with that
evaluation to this fraction of its scale: below the rounding's own effect on the shipped vectors
(per quantity 1.9e-10 to 4.3e-8 of the scale) and far above float64 noise (1e-14)."""


def check(reference: dict, candidate: dict, atol: float = conformance.DEFAULT_ATOL,
          rtol: float = conformance.DEFAULT_RTOL, reference_name: str = "reference",
          candidate_name: str = "candidate") -> dict:
    """:func:`conformance.compare`, plus ``hints`` (list of one-line str; empty when it passed)."""
    report = conformance.compare(reference, candidate, atol, rtol, reference_name, candidate_name)
    report["hints"] = [] if report["ok"] else diagnose(report)
    return report


def _close(candidate: np.ndarray, model: np.ndarray, tolerance: float = 1e-6) -> bool:
    """candidate equals model up to ``tolerance`` of max |model| at every time (same shape)."""
    return candidate.shape == model.shape and bool(_close_rows(candidate, model, tolerance).all())


def _close_rows(candidate: np.ndarray, model: np.ndarray, tolerance: float = 1e-6) -> np.ndarray:
    """(M,) bool: each time's row of candidate equals model's up to ``tolerance`` of max |model|."""
    scale = max(float(np.abs(model).max(initial=0.0)), 1e-300)
    return np.abs(candidate - model).reshape(len(model), -1).max(axis=1, initial=0.0) <= tolerance * scale


NON_CUMULATIVE = np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]]) / 6.0
"""The uniform cubic B-spline's non-cumulative matrix, p(u) = [1, u, u², u³] M [P_k..P_{k+3}]ᵀ (rows:
powers of u): its weights put in the cumulative sum in place of B_j are the common mistake."""


def _weighted_cumulative_translation(parsed: dict, times: np.ndarray,
                                     matrix: Optional[np.ndarray] = None) -> np.ndarray:
    """p(t) of the cumulative sum with the weights [1, u, u², u³] @ ``matrix`` (default Cᵀ: the basis
    matrix transposed, B = Cᵀ [1, u, u², u³]ᵀ, the common typo); (M, 3)."""
    first = spline.active_control_indices(times, parsed["rotvecs"].shape[0], parsed["dt"], parsed["t0"],
                                          parsed["convention"])[..., 0].numpy()
    offset = 2 if parsed["convention"] == "paper" else 0
    u = (times - parsed["t0"]) / parsed["dt"] - offset - first
    monomials = np.stack([np.ones_like(u), u, u * u, u * u * u], -1)  # (M, 4)
    basis = np.asarray(spline.CUMULATIVE_BASIS) / 6.0 if matrix is None else matrix  # the hint: Cᵀ instead of C
    weights = monomials @ basis  # (M, 4)
    points = parsed["translations"]
    deltas = points[first[:, None] + np.arange(1, 4)] - points[first[:, None] + np.arange(0, 3)]  # (M, 3, 3)
    return points[first] + (weights[:, 1:, None] * deltas).sum(1)


def _frame_hints(failing: set, refs: Dict[str, np.ndarray], cands: Dict[str, np.ndarray]) -> List[str]:
    """Angular rates given in the world frame instead of the body frame; rotations transposed."""
    hints = []
    for key in ("omega_body", "omegadot_body"):
        if key in failing and _close(cands[key], np.einsum("mij,mj->mi", refs["R"], refs[key])):
            hints.append(f"{key}: the candidate equals R @ {key}, the WORLD-frame value; the kit wants the body "
                         f"frame ([omega]x = R^T dR/dt), i.e. omega_body = R^T omega_world")
    if "R" in failing and _close(cands["R"], np.swapaxes(refs["R"], 1, 2)):
        hints.append("R: the candidate is the reference's TRANSPOSE, world-to-body; the kit wants body-to-world "
                     "(camera-to-world) rotations, R = Exp(rotvecs) as given")
    return hints


def _time_scale_hints(failing: set, refs, cands, parsed: Optional[dict]) -> List[str]:
    """v, a (and omega, omegadot) off by a power of dt (uniform knots only)."""
    if parsed is None or parsed["dt"] is None:
        return []
    hints, dt = [], parsed["dt"]
    for key, order in (("v", 1), ("a", 2), ("omega_body", 1), ("omegadot_body", 2)):
        if key not in failing:
            continue
        for power in (-2, -1, 1, 2):
            if dt != 1.0 and _close(cands[key], refs[key] * dt ** power):
                hints.append(f"{key}: the candidate is the reference times dt^{power} (dt = {dt}); a time "
                             f"derivative of order {order} needs 1/dt^{order} (chain rule, du/dt = 1/dt)")
                break
    return hints


def _bad_times(failing: set, rows: dict) -> np.ndarray:
    """(M,) bool: the times at which any failing quantity is outside its bound."""
    bad = np.zeros(len(next(iter(rows.values()))["per_time"]), dtype=bool)
    for key in failing:
        bad |= rows[key]["per_time"] > rows[key]["bound"]
    return bad


SPREAD_SHARE = 0.25
"""Rounding (float32, times rounded) leaves errors at most times; with errors at fewer than this
share of the times the rounding hints offer no looser tolerance: a bug at a few times is a bug."""


def _precision_hint(failing: set, rows: dict) -> List[str]:
    """Every quantity off by rounding-sized errors at many times: float32 level, or between float64
    and float32."""
    scaled = [row["scaled"] for row in rows.values()]
    largest = max(scaled)
    if not failing or largest >= 3e-5 or sum(value > 1e-12 for value in scaled) < 4:
        return []
    share = _bad_times(failing, rows).mean()
    few = (f"; but the errors sit at only {100 * share:.0f} % of the times: look at those before any looser "
           f"tolerance" if share < SPREAD_SHARE else "")
    if largest >= FLOAT32_LEVEL:
        advice = few or "; compute in float64, or check with --rtol 1e-5 if float32 is intended"
        return [f"errors at the float32 level across the quantities (largest {largest:.1e} of the scale; float32 "
                f"keeps about 6e-8, float64 1e-16): float32 arithmetic or float32 outputs?, or float64 that loses "
                f"digits to large absolute times (knots or t0 near 1e9 s keep about 1e-7 s: form t - t0 before "
                f"anything else){advice}"]
    advice = few or "; check those with --rtol 1e-7"
    return [f"errors between float64 rounding (1e-14 of the scale) and float32's (6e-8) across the quantities "
            f"(largest {largest:.1e}): times rounded before evaluation (whole nanoseconds, as basalt-headers' "
            f"int64 ns, give up to 4.3e-8 on the shipped vectors{advice})?, or a small-angle series (Exp, Log, "
            f"J_r) used up to too large an angle?"]


def _representation_hint(failing: set, cands, parsed: Optional[dict], times: np.ndarray) -> List[str]:
    """Joint SE(3) instead of split (or the reverse): only p, v, a differ (values only) and p equals
    the other representation's."""
    failing = failing & set(conformance.OUTPUT_KEYS)
    if not (failing and failing <= {"p", "v", "a"} and {"p", "v", "a"} & failing):
        return []
    if parsed is None or parsed["knots"] is not None:
        return []
    swapped = dict(parsed, representation="split" if parsed["representation"] == "se3" else "se3")
    if not _close(cands["p"], conformance.evaluate_parsed(swapped, times)["p"]):
        return []
    return ["p equals the JOINT SE(3) spline of the same control points (PyPose pp.bspline, Sophus) "
            "but this vector is split SO(3) x R^3" if parsed["representation"] == "split" else
            "p equals the SPLIT SO(3) x R^3 spline but this vector is JOINT SE(3) "
            "(\"representation\": \"se3\")"]


def _translation_coupling_hint(failing: set, parsed: Optional[dict]) -> List[str]:
    """p, v and a all fail while R, omega, omegadot pass, and no other hint explains it: the
    translation is coupled to the rotation differently (given when nothing more specific is found)."""
    if failing & set(conformance.OUTPUT_KEYS) != {"p", "v", "a"}:
        return []
    if parsed is not None and parsed["representation"] == "se3":
        return ["p, v and a differ while R, omega, omegadot agree: this vector is JOINT SE(3), whose translation "
                "is coupled to the rotation: T(t) = T_k prod Exp(B_j xi_j) with Exp(rho, phi) = [Exp(phi), "
                "V(phi) rho] and xi_j = Log(T_{k+j-1}^-1 T_{k+j}) (rho = V(phi)^-1 R_{k+j-1}^T (p_{k+j} - p_{k+j-1})); "
                "check V(phi) in Exp and Log, or a split spline against this joint one"]
    return ["p, v and a differ while R, omega, omegadot agree: the translation may be coupled differently, "
            "e.g. a JOINT SE(3) spline (PyPose, Sophus) against a split one, whose p is the B-spline of the "
            "translations alone"]


def _end_times_hint(failing: set, rows: dict, parsed: dict, times: np.ndarray) -> List[str]:
    """Errors only at the domain's end times (clamped, shifted or half-open code)."""
    if not failing:
        return []
    t_min, t_max = conformance.domain(parsed)
    position = (times - t_min) / (t_max - t_min)  # 0 at t_min, 1 at t_max (t - t0 first: large stamps)
    at_end = (position < 1e-6) | (position > 1 - 1e-6)
    bad = _bad_times(failing, rows)
    if not bad.any() or (bad & ~at_end).any() or at_end.all():
        return []
    return [f"errors only at the domain's end times ({int(bad.sum())} of the {int(at_end.sum())} times at t_min or "
            f"t_max): evaluate there on the end segment's polynomial, u = 0 at t_min and u = 1 at t_max (a closed "
            f"domain), and a time that lies within rounding outside the domain (accepted up to 4 eps |t|) with u "
            f"just outside [0, 1], extrapolated: do not clamp the time or u, nor move t_max inside"]


def _knot_rule_hint(failing: set, rows: dict, parsed: dict, times: np.ndarray) -> List[str]:
    """Errors only at times next to a knot."""
    _, u = conformance.segment_and_u(parsed, times)
    near_knot = np.minimum(np.abs(u), np.abs(1.0 - u)) < 1e-4
    if not (failing and near_knot.any()):
        return []
    bad_anywhere = np.zeros(len(times), dtype=bool)
    for key in failing:
        bad_anywhere |= rows[key]["per_time"] > rows[key]["bound"]
    if bad_anywhere.any() and not (bad_anywhere & ~near_knot).any():
        return [f"errors only at times within 1e-4 segments of a knot ({int(bad_anywhere.sum())} of "
                f"{int(near_knot.sum())} such times, nowhere else): the knot rule; the segment of t is floor((t - t0)/dt) of the "
                f"exact float64 values (a time 1e-6 segments before a knot is in the earlier segment), "
                f"t_max is the end of the last segment"]
    return []


SHIFT_SHARE = 0.9
"""A shifted model (index convention, control points against knots) is named when it equals the
candidate at this share of the times where it is defined: code that clamps its index at a domain
end breaks the shift at a few."""


def _pose_rows_equal(cands, inside: np.ndarray, model: Dict[str, np.ndarray]) -> np.ndarray:
    """(inside.sum(),) bool: the candidate's p and R at the ``inside`` times equal ``model``'s."""
    return _close_rows(cands["p"][inside], model["p"]) & _close_rows(cands["R"][inside], model["R"])


def _shifted_model_matches(cands, inside: np.ndarray, model: dict, model_times: np.ndarray,
                           least: int) -> Optional[np.ndarray]:
    """The rows where the candidate's pose equals ``model`` evaluated at ``model_times`` (both taken
    where ``inside``), when at least ``least`` rows are inside and SHIFT_SHARE of them agree; else None."""
    if inside.sum() < least:
        return None
    same = _pose_rows_equal(cands, inside, conformance.evaluate_parsed(model, model_times[inside]))
    return same if same.mean() >= SHIFT_SHARE else None


def _convention_hint(failing: set, cands, parsed: dict, times: np.ndarray) -> List[str]:
    """An index convention shifted by whole segments (uniform knots only)."""
    if parsed["knots"] is not None or "p" not in failing:
        return []
    n, dt, t0 = parsed["rotvecs"].shape[0], parsed["dt"], parsed["t0"]
    t_min, t_max = spline.valid_time_range(n, dt, t0, parsed["convention"])
    for shift in (-2, -1, 1, 2):
        shifted = times + shift * dt
        inside = (shifted >= t_min) & (shifted <= t_max)
        same = _shifted_model_matches(cands, inside, parsed, shifted, least=max(3, len(times) // 4))
        if same is not None:
            t0_steps = t0 / dt
            forgotten = (f", or t0 not subtracted (t0 = {t0:g} s is {t0_steps:g} dt)"
                         if t0 != 0 and abs(t0_steps - shift) < 1e-6 else "")
            return [f"the candidate at t equals the reference at t {'+' if shift > 0 else '-'} {abs(shift)} dt "
                    f"({int(same.sum())} of {same.size} times where that is inside the domain): "
                    f"an index convention shifted by {abs(shift)} segment(s) (paper: segment [t_i, t_i+1) uses "
                    f"control points i-2..i+1; basalt and Sommer et al.: i..i+3; Lovegrove-style: i-1..i+2)"
                    f"{forgotten}"]
    return []


def _transposed_basis_hint(failing: set, cands, parsed: dict, times: np.ndarray) -> List[str]:
    """The basis matrix transposed, or the non-cumulative matrix in the cumulative form (uniform
    knots, split representation)."""
    if "p" in failing and parsed["representation"] == "split" and parsed["knots"] is None:
        if _close(cands["p"], _weighted_cumulative_translation(parsed, times)):
            return ["p equals the spline with the TRANSPOSED basis matrix: B(u) = C [1, u, u^2, u^3]^T with "
                    "rows of C = (6,0,0,0), (5,3,-3,1), (1,3,3,-2), (0,0,0,1) over 6"]
        if _close(cands["p"], _weighted_cumulative_translation(parsed, times, NON_CUMULATIVE)):
            return ["p equals the cumulative sum weighted by the NON-CUMULATIVE basis (M = 1/6 [[1,4,1,0], "
                    "[-3,0,3,0], [3,-6,3,0], [-1,3,-3,1]], whose weights multiply the control points themselves): "
                    "the cumulative form's B_j(u) = sum of the non-cumulative weights j..3, i.e. B(u) = C [1, u, "
                    "u^2, u^3]^T with rows of C = (6,0,0,0), (5,3,-3,1), (1,3,3,-2), (0,0,0,1) over 6"]
    return []


def _uniform_basis_per_segment(parsed: dict, times: np.ndarray) -> Dict[str, np.ndarray]:
    """Outputs with the UNIFORM cumulative basis on every segment of a knot vector: segment s's four
    control points, u = (t - k_{s+2}) / h_s and time derivatives over h_s (the common mistake)."""
    segment, _ = conformance.segment_and_u(parsed, times)
    knot_vector = parsed["knots"]
    outputs = {key: np.zeros((len(times),) + conformance.OUTPUT_SHAPES[key]) for key in conformance.OUTPUT_KEYS}
    for s in np.unique(segment):
        rows = segment == s
        start, length = float(knot_vector[s + 2]), float(knot_vector[s + 3] - knot_vector[s + 2])
        local = dict(parsed, knots=None, rotvecs=parsed["rotvecs"][s:s + 4],
                     translations=parsed["translations"][s:s + 4], dt=length, t0=start, convention="basalt")
        for key, value in conformance.evaluate_parsed(local, np.clip(times[rows], start, start + length)).items():
            outputs[key][rows] = value
    return outputs


def _knot_vector_hints(failing: set, cands, parsed: dict, times: np.ndarray) -> List[str]:
    """Non-uniform knots: the uniform basis on each segment, or the control points shifted by one
    against the knots (segment s using points s + 1..s + 4 or s - 1..s + 2)."""
    if parsed["knots"] is None or not failing & set(conformance.OUTPUT_KEYS):
        return []
    uniform = _uniform_basis_per_segment(parsed, times)
    if all(_close(cands[key], uniform[key]) for key in ("R", "p")):
        return ["R and p equal the UNIFORM cumulative basis on each segment (u = (t - k_{s+2}) / h_s): a "
                "non-uniform segment's basis comes from its six knots k_s..k_{s+5} (Cox-de Boor), not from the "
                "uniform matrix C"]
    knot_vector, points, rotvecs = parsed["knots"], parsed["translations"], parsed["rotvecs"]
    for shift, shifted in ((1, dict(parsed, rotvecs=rotvecs[1:], translations=points[1:], knots=knot_vector[:-1])),
                           (-1, dict(parsed, rotvecs=rotvecs[:-1], translations=points[:-1], knots=knot_vector[1:]))):
        if len(shifted["rotvecs"]) < 4:
            continue
        t_min, t_max = knots.valid_time_range(shifted["knots"])
        inside = (times >= t_min) & (times <= t_max)
        same = _shifted_model_matches(cands, inside, shifted, times, least=max(3, len(times) // 2))
        if same is not None:
            return [f"the candidate equals the reference with the control points shifted by {shift:+d} against the "
                    f"knots ({int(same.sum())} of {same.size} times where that is defined): segment s, on "
                    f"[k_{{s+2}}, k_{{s+3}}], uses control points s..s+3 and the knots k_s..k_{{s+5}}"]
    return []


def _world_twist_pose(parsed: dict, times: np.ndarray) -> Dict[str, np.ndarray]:
    """R, p of the joint SE(3) spline built on WORLD-side increments Log(T_{j} T_{j-1}^-1), composed on
    the right as the body-side ones are (the mistake); uniform knots."""
    rotations = so3_exp(torch.as_tensor(parsed["rotvecs"]))
    points = torch.as_tensor(parsed["translations"])
    relative_R = rotations[1:] @ rotations[:-1].transpose(-1, -2)
    relative_p = points[1:] - (relative_R @ points[:-1].unsqueeze(-1)).squeeze(-1)
    twists = se3_spline.se3_log(relative_R, relative_p)  # (N-1, 6)
    first, u, _ = spline.locate_segments(times, len(points), parsed["dt"], parsed["t0"], parsed["convention"])
    xi = twists[first[:, None] + torch.arange(3)]
    R, p = se3_spline.pose_at_segment(u.to(points.dtype), rotations[first], points[first], xi)
    return {"R": R.numpy(), "p": p.numpy()}


def _se3_side_hint(failing: set, cands, parsed: dict, times: np.ndarray) -> List[str]:
    """Joint SE(3): the world-side increment in place of the body-side one."""
    if parsed["representation"] != "se3" or parsed["knots"] is not None or not {"R", "p"} & failing:
        return []
    model = _world_twist_pose(parsed, times)
    if not all(_close(cands[key], model[key]) for key in ("R", "p")):
        return []
    return ["R and p equal the joint SE(3) spline with WORLD-side increments xi_j = Log(T_{k+j} T_{k+j-1}^-1) "
            "composed on the right: the increments are body-side, xi_j = Log(T_{k+j-1}^-1 T_{k+j})"]


def _rotation_part_hints(failing: set, rows: dict) -> List[str]:
    """Patterns of the rotation's recursion (Eq. 6 and 9): which of R, omega, omegadot fail (the
    values only: Jacobians that fail along with them do not hide the pattern); by rounding-sized
    errors, the storage rather than the formula."""
    failing = failing & set(conformance.OUTPUT_KEYS)
    rotational = [{"R"}, {"omegadot_body"}, {"R", "omega_body", "omegadot_body"}]
    largest = max((rows[key]["scaled"] for key in failing), default=0.0)
    if failing in rotational and largest < 3e-5:
        return [f"only {', '.join(sorted(failing))} fail, by rounding-sized errors (largest {largest:.1e} of the "
                f"scale; float32 keeps about 6e-8): stored or converted in float32, or a small-angle series used "
                f"too far? Compute and write them in float64"]
    if failing == {"R", "omega_body", "omegadot_body"}:
        return ["R, omega and omegadot fail while p, v and a pass: the rotation's composition; R(t) = R_k "
                "A_1 A_2 A_3 with A_j = Exp(B_j d_j) and d_j = Log(R_{k+j-1}^T R_{k+j}): increments on the RIGHT "
                "(body side), not Exp(B_j d_j) R on the left, and d_j in this order; or the control rotations "
                "read in another convention (rotvecs are rotation vectors, rad; a quaternion built from them "
                "with its components in another order, w-first against w-last, gives this pattern too)"]
    if failing == {"R"}:
        return ["only R fails while omega and omegadot pass (their recursion is right): R's own product, "
                "R(t) = R_k A_1 A_2 A_3 with the A_j on the RIGHT (not A_3 A_2 A_1 R_k), or R converted to the "
                "output in another convention (a quaternion with its components in another order, w-first "
                "against w-last; the kit wants the 3x3 matrix, camera-to-world)"]
    if failing == {"omegadot_body"}:
        return ["only omegadot fails: check its recursion term by term: it uses the UPDATED omega, omega^(j+1) "
                "= A_j^T omega^(j) + Bdot_j d_j, then omegadot^(j+1) = Bdot_j omega^(j+1) x d_j + A_j^T "
                "omegadot^(j) + Bddot_j d_j (the cross term's sign and order: omega^(j+1) x d_j, plus)"]
    return []


_ROTATION_JACOBIANS = ("J_R", "J_omega_body", "J_omegadot_body")
_JACOBIAN_ORDER = {"J_v": 1, "J_a": 2, "J_omega_body": 1, "J_omegadot_body": 2}


def _jacobian_models(key: str, refs, parsed: Optional[dict], first: Optional[np.ndarray]):
    """(model (M, 4, 3, 3), what it means) for the common mistakes in Jacobian ``key``: the reference
    with that mistake made on purpose."""
    ref = refs[key]
    models = [(np.swapaxes(ref, -1, -2), "each 3x3 block is the TRANSPOSE of the reference's: block [m][i][row][col] "
               "has row = output component, col = perturbation component (a column-major dump, e.g. Eigen's "
               "default storage, writes it transposed)"),
              (ref[:, ::-1], "the 4 blocks are in REVERSE order: block [m][i] belongs to control point "
               "J_first[m] + i (i = 0 the first active point)"),
              (-ref, "the NEGATIVE of the reference: a sign flipped (the kit perturbs R_k <- Exp(delta) R_k, "
               "P_k <- P_k + tau and reads the output as R(t) <- Exp(eps) R(t))")]
    dt = None if parsed is None else parsed["dt"]
    if key in _JACOBIAN_ORDER and dt is not None and dt != 1.0:
        order = _JACOBIAN_ORDER[key]
        models += [(ref * dt**power, f"the reference times dt^{power} (dt = {dt}): the Jacobian of a time "
                    f"derivative of order {order} carries its 1/dt^{order} too (du/dt = 1/dt)")
                   for power in (1, 2, -1, -2)]
    if key in _ROTATION_JACOBIANS and parsed is not None and first is not None:
        rotations = so3_exp(torch.as_tensor(parsed["rotvecs"])).numpy()[first[:, None].astype(int) + np.arange(4)]
        models.append((ref @ rotations, "RIGHT perturbation of the control rotations, R_k <- R_k Exp(delta): the kit "
                       "perturbs on the LEFT, R_k <- Exp(delta) R_k (J_kit = J_right R_k^T)"))
        if key == "J_R":
            transposed = np.swapaxes(refs["R"], 1, 2)[:, None]  # (M, 1, 3, 3) R(t)^T
            models.append((transposed @ ref, "RIGHT perturbation of the output rotation, R(t) <- R(t) Exp(eps): "
                           "the kit reads R(t) <- Exp(eps) R(t) (J_kit = R(t) J_right)"))
            models.append((transposed @ ref @ rotations, "RIGHT perturbation of both the control rotations and the "
                           "output rotation: the kit perturbs both on the LEFT (J_kit = R(t) J_right R_k^T)"))
    return models


def _jacobian_hints(failing: set, refs, cands, parsed: Optional[dict], first: Optional[np.ndarray]) -> List[str]:
    """Failing Jacobian blocks that equal the reference with a common mistake made: one hint per
    mistake, naming the blocks that show it."""
    found: Dict[str, List[str]] = {}
    for key in conformance.JACOBIAN_KEYS:
        if key not in failing:
            continue
        for model, meaning in _jacobian_models(key, refs, parsed, first):
            if _close(cands[key], model) and not _close(model, refs[key]):  # a mistake that changes nothing is none
                found.setdefault(meaning, []).append(key)
                break
    return [f"{', '.join(keys)}: {meaning}" for meaning, keys in found.items()]


def _whole_nanoseconds(seconds: float) -> int:
    """The float64 value of ``seconds`` rounded to whole nanoseconds, exactly (no float64 product)."""
    return round(Fraction(float(seconds)) * 10**9)


def _nanosecond_hint(failing: set, cands, parsed: Optional[dict], times: np.ndarray) -> List[str]:
    """Times held as int64 nanoseconds (basalt-headers): t, t0 and dt each rounded to whole ns."""
    if not failing or parsed is None or parsed["knots"] is not None:
        return []
    t0_ns, dt = _whole_nanoseconds(parsed["t0"]), _whole_nanoseconds(parsed["dt"]) * 1e-9
    relative = np.array([_whole_nanoseconds(t) - t0_ns for t in times], dtype=np.float64) * 1e-9
    t_min, t_max = spline.valid_time_range(parsed["rotvecs"].shape[0], dt, 0.0, parsed["convention"])
    inside = (relative >= t_min) & (relative <= t_max)  # stamps a few ulps outside are extrapolated: left out
    if inside.sum() < len(times) // 2:
        return []
    model = conformance.evaluate_parsed(dict(parsed, t0=0.0, dt=dt), relative[inside])
    if not all(_close(cands[key][inside], model[key], NANOSECOND_MATCH) for key in conformance.OUTPUT_KEYS):
        return []
    return ["the candidate equals the reference evaluated with t, t0 and dt rounded to whole nanoseconds "
            "(int64 ns, as basalt-headers): correct for such code, whose u moves by up to 0.5 ns / dt; check it "
            "with --rtol 1e-7"]


def diagnose(report: dict) -> List[str]:
    """Hints naming the likely mistake from the pattern of errors of a :func:`conformance.compare`
    report (list of one-line strings; fewer for a bare output file as reference)."""
    rows = {row["quantity"]: row for row in report["rows"]}
    failing = {key for key, row in rows.items() if not row["ok"]}
    times, refs, cands, parsed = report["times"], report["refs"], report["cands"], report["parsed"]
    hints = _frame_hints(failing, refs, cands) + _time_scale_hints(failing, refs, cands, parsed)
    ends = [] if parsed is None else _end_times_hint(failing, rows, parsed, times)
    hints += ends or _nanosecond_hint(failing, cands, parsed, times) or _precision_hint(failing, rows)
    hints += _representation_hint(failing, cands, parsed, times) + _rotation_part_hints(failing, rows)
    if parsed is not None:
        hints += _knot_rule_hint(failing, rows, parsed, times) + _convention_hint(failing, cands, parsed, times)
        hints += _transposed_basis_hint(failing, cands, parsed, times)
        hints += _knot_vector_hints(failing, cands, parsed, times) + _se3_side_hint(failing, cands, parsed, times)
    hints = hints or _translation_coupling_hint(failing, parsed)  # only when nothing more specific matched
    return hints + _jacobian_hints(failing, refs, cands, parsed, report.get("J_first"))
