"""Spline conformance kit, the maths: read an input, evaluate it, compare a candidate with a reference.

TS-SLAM §III-B/§III-C, Eq. (5)-(9): lets another implementation (C++, JAX, a port of this package)
check itself against ours with shared test vectors (tsslam_ref/assets/spline_vectors).  The command
line is :mod:`tsslam_ref.spline_kit` (it imports this module; this module never imports it).

Side module.  Imports ``spline``, ``knots`` and ``geometry`` (``se3_spline`` and ``spline_jacobians``
inside the functions that need them).  What a failed check probably means (hints) is
:mod:`tsslam_ref.conformance_hints`, which imports this module.

Input keys: ``convention`` ("paper" | "basalt"), ``dt`` and ``t0`` (s), ``rotvecs`` (N x 3, rad),
``translations`` (N x 3, m), ``times`` (M, s); optional ``representation`` ("split", the default,
or "se3" for the joint SE(3) spline, :mod:`tsslam_ref.se3_spline`).  Non-uniform knots: the key
``knots`` (N + 2 strictly increasing times, s; :mod:`tsslam_ref.knots`) replaces ``convention``,
``dt`` and ``t0`` (split representation only, no Jacobians).  Output keys: ``times`` (M),
``R`` (M x 3 x 3), ``p``, ``v``, ``a`` (M x 3, world), ``omega_body``, ``omegadot_body`` (M x 3,
body), all float64.  With Jacobians (``evaluate --jacobians``, :mod:`tsslam_ref.spline_jacobians`):
``J_first`` (M, first active control index) and ``J_R``, ``J_p``, ``J_v``, ``J_a``,
``J_omega_body``, ``J_omegadot_body`` (M x 4 x 3 x 3).  A vector file holds the input keys and the
output keys together.

Error definition (one, used everywhere): per quantity q, error = max over times and components of
|cand − ref|; scale = max |ref| over the quantity; the quantity passes when
error ≤ atol + rtol · scale (defaults :data:`DEFAULT_ATOL`, :data:`DEFAULT_RTOL`: between float64
and float32 rounding).  "scaled error" = error / scale.  A candidate may leave out the reference's
last time (t_max, which a half-open domain drops) and no other.
"""

import json
import math
from typing import Dict, Optional, Sequence

import numpy as np
import torch

from tsslam_ref import knots, spline
from tsslam_ref.geometry import so3_exp, so3_log

INPUT_KEYS = ("convention", "dt", "t0", "rotvecs", "translations", "times")
MAX_DT = 1e6
"""The longest knot spacing an input may give, seconds (11.6 days; far beyond any trajectory)."""
OPTIONAL_INPUT_KEYS = ("representation", "knots")
REPRESENTATIONS = ("split", "se3")
OUTPUT_KEYS = ("R", "p", "v", "a", "omega_body", "omegadot_body")
OUTPUT_SHAPES = {"R": (3, 3), "p": (3,), "v": (3,), "a": (3,), "omega_body": (3,), "omegadot_body": (3,)}
DEFAULT_ATOL = 1e-10
DEFAULT_RTOL = 1e-10
"""Default tolerances, far from both roundings (measured on the shipped vectors, docs/spline.md): correct
float64 formulations differ from ours by at most 4e-14 of the scale; float32 arithmetic by 7e-8 to 9e-7
and float64 values stored as float32 by 3e-8 to 6e-8 (rtol 1e-7 would pass the latter)."""
ROTATION_STEP_LIMIT = math.pi - 1e-6
"""Largest relative rotation (rad) between consecutive control points the kit accepts.  At π the
principal Log is ambiguous (Log(R) and −Log(R) are both valid; two correct implementations then
give different curves), and within ~1e-6 rad of π float64 rotation matrices no longer decide the
sign reliably.  Insert a control point (halve Δt) instead."""
TIME_MATCH = 4.0 * np.finfo(np.float64).eps
"""Candidate and reference times match when they differ by at most this times max(1, |t|)."""


class ConformanceError(ValueError):
    """Malformed input or output file, or a refused value (exit code 2)."""


def _array(data: dict, key: str, shape_tail: Sequence[int], source: str) -> np.ndarray:
    if key not in data:
        raise ConformanceError(f"{source}: missing key {key!r}")
    try:
        value = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ConformanceError(f"{source}: key {key!r} is not a numeric array ({error})") from None
    if value.ndim != 1 + len(shape_tail) or tuple(value.shape[1:]) != tuple(shape_tail):
        wanted = " x ".join(["M"] + [str(n) for n in shape_tail])
        raise ConformanceError(f"{source}: key {key!r} must be {wanted}, got shape {value.shape}")
    if not np.all(np.isfinite(value)):
        row = int(np.flatnonzero(~np.isfinite(value.reshape(value.shape[0], -1)).all(axis=1))[0])
        times = data.get("times") if key != "times" else None
        at = f", t = {times[row]!r} s" if isinstance(times, list) and row < len(times) else ""
        raise ConformanceError(f"{source}: key {key!r} contains non-finite values (first at row {row}{at})")
    return value


def _check_seconds(data: dict, key: str, source: str) -> None:
    """ConformanceError when the time value ``data[key]`` (from Python, not JSON, whose numbers are
    float64) is float32 or narrower: its digits are gone before the kit's cast to float64."""
    try:
        spline.check_float64_seconds(f"{source}: key {key!r}", data.get(key))
    except TypeError as error:
        raise ConformanceError(str(error)) from None


def _scalar(data: dict, key: str, source: str) -> float:
    if key not in data:
        raise ConformanceError(f"{source}: missing key {key!r}")
    _check_seconds(data, key, source)
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConformanceError(f"{source}: key {key!r} must be a finite number, got {value!r}")
    return float(value)


def check_tolerances(atol: float, rtol: float) -> None:
    """ConformanceError unless both tolerances are finite and ≥ 0."""
    for name, value in (("--atol", atol), ("--rtol", rtol)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ConformanceError(f"{name} must be a finite number >= 0, got {value!r}")


def load_json(path: str) -> dict:
    """Read a JSON object; ConformanceError naming the file on failure."""
    try:
        with open(path, "r", encoding="utf-8") as handle:
            data = json.load(handle)
    except OSError as error:
        raise ConformanceError(f"{path}: cannot read ({error.strerror})") from None
    except json.JSONDecodeError as error:
        raise ConformanceError(f"{path}: invalid JSON at line {error.lineno}: {error.msg}") from None
    except ValueError as error:
        raise ConformanceError(f"{path}: invalid JSON ({error})") from None
    if not isinstance(data, dict):
        raise ConformanceError(f"{path}: top level must be a JSON object")
    return data


def rotation_steps(rotvecs: np.ndarray) -> np.ndarray:
    """(N−1,) angles in rad of R_{k−1}ᵀ R_k for (N, 3) rotation vectors."""
    rotations = so3_exp(torch.as_tensor(rotvecs, dtype=torch.float64))
    relative = rotations[:-1].transpose(-1, -2) @ rotations[1:]
    return torch.linalg.vector_norm(so3_log(relative), dim=-1).numpy()


def parse_input(data: dict, source: str = "input") -> dict:
    """Validate the input keys; returns representation, convention, dt, t0 and float64 arrays.

    Raises ConformanceError naming the key: malformed values, fewer than 4 control points, or a
    rotation step ≥ :data:`ROTATION_STEP_LIMIT` (the message names the pair and the angle).
    """
    if "knots" in data:
        return _parse_knot_input(data, source)
    convention = data.get("convention")
    if convention not in spline.CONVENTIONS:
        raise ConformanceError(f"{source}: key 'convention' must be one of {spline.CONVENTIONS}, got {convention!r}")
    representation = data.get("representation", "split")
    if representation not in REPRESENTATIONS:
        raise ConformanceError(f"{source}: key 'representation' must be one of {REPRESENTATIONS}, got {representation!r}")
    dt = _scalar(data, "dt", source)
    if not 0 < dt <= MAX_DT:  # 1e300 overflowed in the acceleration's 1 / dt**2, a traceback
        raise ConformanceError(f"{source}: key 'dt' must be in (0, {MAX_DT:g}] seconds, got {dt}")
    parsed = {"representation": representation, "convention": convention, "dt": dt, "t0": _scalar(data, "t0", source),
              "knots": None}
    return _parse_control_points(data, source, parsed)


def _parse_knot_input(data: dict, source: str) -> dict:
    """A non-uniform input: key 'knots' (N + 2 strictly increasing times, s) instead of dt, t0, convention."""
    extra = [key for key in ("dt", "t0", "convention") if key in data]
    if extra:
        raise ConformanceError(f"{source}: key 'knots' replaces 'dt', 't0' and 'convention'; remove {extra}")
    if data.get("representation", "split") != "split":
        raise ConformanceError(f"{source}: key 'knots' needs \"representation\": \"split\", got "
                               f"{data.get('representation')!r}")
    _check_seconds(data, "knots", source)
    knot_vector = _array(data, "knots", (), source)
    parsed = {"representation": "split", "convention": None, "dt": None, "t0": float(knot_vector[0]) if
              knot_vector.size else None, "knots": knot_vector}
    parsed = _parse_control_points(data, source, parsed)
    try:
        knots.check_knots(knot_vector, parsed["rotvecs"].shape[0])
    except ValueError as error:
        raise ConformanceError(f"{source}: key 'knots': {error}") from None
    return parsed


def _parse_control_points(data: dict, source: str, parsed: dict) -> dict:
    """Add rotvecs, translations and times to ``parsed``; ConformanceError naming the key."""
    parsed["rotvecs"] = _array(data, "rotvecs", (3,), source)
    parsed["translations"] = _array(data, "translations", (3,), source)
    _check_seconds(data, "times", source)
    parsed["times"] = _array(data, "times", (), source)
    if parsed["rotvecs"].shape[0] != parsed["translations"].shape[0]:
        raise ConformanceError(f"{source}: 'rotvecs' and 'translations' must have the same length")
    if parsed["rotvecs"].shape[0] < 4:
        raise ConformanceError(f"{source}: key 'rotvecs' needs at least 4 control points")
    if np.abs(parsed["rotvecs"]).max() > 1e6:
        row = int(np.flatnonzero(np.abs(parsed["rotvecs"]).max(axis=1) > 1e6)[0])
        raise ConformanceError(f"{source}: key 'rotvecs' row {row} has a component above 1e6 rad "
                               f"({np.abs(parsed['rotvecs'][row]).max():.3g}); float64 cannot represent its "
                               f"rotation (write the rotation vector with norm <= pi)")
    steps = rotation_steps(parsed["rotvecs"])
    if not np.all(np.isfinite(steps)):
        raise ConformanceError(f"{source}: key 'rotvecs' gives non-finite rotations")
    if steps.max() >= ROTATION_STEP_LIMIT:
        k = int(np.argmax(steps))
        raise ConformanceError(
            f"{source}: key 'rotvecs': control points {k} and {k + 1} are {float(steps[k])!r} rad apart; the kit needs "
            f"every step < pi - 1e-6 rad (at pi Log is ambiguous and two correct splines differ); insert a "
            f"control point between them")
    return parsed


def evaluate_parsed(parsed: dict, times: Optional[np.ndarray] = None) -> Dict[str, np.ndarray]:
    """Float64 outputs (arrays) of a parsed input at ``times`` (default: its own times).

    Raises ValueError for a time outside the domain.
    """
    times = parsed["times"] if times is None else times
    rotations = so3_exp(torch.as_tensor(parsed["rotvecs"]))
    translations = torch.as_tensor(parsed["translations"])
    if parsed["knots"] is not None:
        sample = knots.evaluate(rotations, translations, times, parsed["knots"], derivatives=2)
    elif parsed["representation"] == "se3":
        from tsslam_ref import se3_spline

        sample = se3_spline.evaluate(rotations, translations, times, parsed["dt"], parsed["t0"],
                                     parsed["convention"], derivatives=2)
    else:
        sample = spline.evaluate(rotations, translations, times, parsed["dt"], parsed["t0"],
                                 parsed["convention"], derivatives=2)
    values = [sample.rotation, sample.translation, sample.velocity_world, sample.acceleration_world,
              sample.omega_body, sample.omegadot_body]
    return {key: value.detach().cpu().numpy() for key, value in zip(OUTPUT_KEYS, values)}


def domain(parsed: dict):
    """(t_min, t_max) s, the closed domain of a parsed input (its knots, or n, dt, t0 and convention)."""
    if parsed["knots"] is not None:
        return knots.valid_time_range(parsed["knots"])
    return spline.valid_time_range(parsed["rotvecs"].shape[0], parsed["dt"], parsed["t0"], parsed["convention"])


def _first_outside(parsed: dict) -> str:
    """' index m' of the first time outside the closed domain of a parsed input ('' if none is)."""
    t_min, t_max = domain(parsed)
    outside = np.flatnonzero(~((parsed["times"] >= t_min) & (parsed["times"] <= t_max)))
    return f" index {int(outside[0])}" if outside.size else ""


JACOBIAN_KEYS = ("J_R", "J_p", "J_v", "J_a", "J_omega_body", "J_omegadot_body")
JACOBIAN_SHAPE = (4, 3, 3)


def evaluate_input(data: dict, source: str = "input", jacobians: bool = False) -> Dict[str, object]:
    """Evaluate a raw input dict in float64; returns the inputs echoed plus the output keys (lists),
    and with ``jacobians`` the Jacobian keys (split representation only).

    Raises ConformanceError (malformed, or non-finite results) or ValueError (a time outside the
    domain).
    """
    parsed = parse_input(data, source)
    try:
        outputs = evaluate_parsed(parsed)
    except ValueError as error:  # a time outside the domain
        raise ConformanceError(f"{source}: key 'times'{_first_outside(parsed)}: {error}") from None
    if jacobians:
        if parsed["representation"] != "split" or parsed["knots"] is not None:
            raise ConformanceError(f"{source}: Jacobians are available for \"representation\": \"split\" with "
                                   f"uniform knots only")
        from tsslam_ref import spline_jacobians

        blocks = spline_jacobians.jacobians(so3_exp(torch.as_tensor(parsed["rotvecs"])),
                                            torch.as_tensor(parsed["translations"]), parsed["times"],
                                            parsed["dt"], parsed["t0"], parsed["convention"])
        outputs["J_first"] = blocks["first"].numpy()
        outputs.update({key: blocks[key].numpy() for key in JACOBIAN_KEYS})
    for key, value in outputs.items():
        if not np.all(np.isfinite(value)):
            raise ConformanceError(f"{source}: evaluation gave non-finite {key!r}; check 'rotvecs' and "
                                   f"'translations' (values too large for float64?)")
    timing = ({"knots": parsed["knots"].tolist()} if parsed["knots"] is not None else
              {"convention": parsed["convention"], "dt": parsed["dt"], "t0": parsed["t0"]})
    result = {"representation": parsed["representation"], **timing, "rotvecs": parsed["rotvecs"].tolist(),
              "translations": parsed["translations"].tolist(), "times": parsed["times"].tolist()}
    result.update({key: value.tolist() for key, value in outputs.items()})
    return result


# ------------------------------------------------------------------------------------------------
# Comparison


def _printed_shorter(reference: float, candidate: float) -> bool:
    """Whether ``candidate`` is ``reference`` printed with 6 to 16 significant digits, or 3 to 12
    decimals, and read back."""
    shorter = [f"{reference:.{digits}g}" for digits in range(6, 17)] + [f"{reference:.{d}f}" for d in range(3, 13)]
    return any(float(text) == candidate for text in shorter)


def match_times(ref_times: np.ndarray, cand_times: np.ndarray, candidate_name: str) -> np.ndarray:
    """(M_cand,) index into the reference times of each candidate time.

    Every candidate time must equal a reference time up to :data:`TIME_MATCH` (relative);
    the candidate may leave reference times out (:func:`compare` accepts only t_max, for a half-open domain).
    Raises ConformanceError naming the first candidate time without a partner.
    """
    order = np.argsort(ref_times, kind="stable")
    sorted_times = ref_times[order]
    position = np.clip(np.searchsorted(sorted_times, cand_times), 1, max(len(sorted_times) - 1, 1))
    left, right = sorted_times[position - 1], sorted_times[np.minimum(position, len(sorted_times) - 1)]
    pick_right = np.abs(right - cand_times) < np.abs(left - cand_times)
    nearest = np.where(pick_right, position, position - 1)
    nearest = np.clip(nearest, 0, len(sorted_times) - 1)
    gap = np.abs(sorted_times[nearest] - cand_times)
    unmatched = np.flatnonzero(gap > TIME_MATCH * np.maximum(1.0, np.abs(cand_times)))
    if unmatched.size:
        m = int(unmatched[0])
        digits = (" (the reference's time written with too few digits: write times with 17 significant digits, "
                  "repr() or %.17g, so they read back as the same float64)"
                  if _printed_shorter(float(sorted_times[nearest[m]]), float(cand_times[m])) else "")
        raise ConformanceError(f"{candidate_name}: time {float(cand_times[m])!r} (index {m}) is not among the "
                               f"reference times (nearest {float(sorted_times[nearest[m]])!r}){digits}; evaluate at "
                               f"the reference's times")
    return order[nearest]


def segment_and_u(parsed: Optional[dict], times: np.ndarray):
    """(segment index (M,), u (M,)) of times in the reference spline, or (None, None)."""
    if parsed is None:
        return None, None
    if parsed["knots"] is not None:
        segment, u, _ = knots.locate(times, parsed["knots"])
        return segment.numpy(), u.numpy()
    offset = 2 if parsed["convention"] == "paper" else 0
    first = spline.active_control_indices(times, parsed["rotvecs"].shape[0], parsed["dt"], parsed["t0"],
                                          parsed["convention"])[..., 0].numpy()
    s = (times - parsed["t0"]) / parsed["dt"] - offset
    return first + offset, s - first


JACOBIAN_ALL_KEYS = ("J_first",) + JACOBIAN_KEYS


def _jacobian_key_problem(data: dict) -> Optional[str]:
    """None when ``data`` holds all of :data:`JACOBIAN_ALL_KEYS` or no ``J_*`` key; otherwise what is
    missing and which ``J_*`` keys are unknown (a partial or misspelt set)."""
    present = [key for key in data if isinstance(key, str) and key.lower().startswith("j_")]
    if not present:
        return None
    missing = [key for key in JACOBIAN_ALL_KEYS if key not in data]
    unknown = [key for key in present if key not in JACOBIAN_ALL_KEYS]
    if not missing and not unknown:
        return None
    parts = ([f"missing {', '.join(missing)}"] if missing else []) + (
        [f"unknown key(s) {', '.join(unknown)}"] if unknown else [])
    return f"{'; '.join(parts)} (the Jacobian keys are {', '.join(JACOBIAN_ALL_KEYS)})"


def _jacobians_to_check(reference: dict, candidate: dict, index: np.ndarray, times: np.ndarray,
                        reference_name: str, candidate_name: str):
    """(quantity -> row shape to compare, the first time of another active window or None, notes,
    Jacobian status, the reference's J_first at the matched times or None, a key-set failure or None):
    the Jacobians are checked when both files hold them; a note says so when only one does; a
    candidate with some but not all Jacobian keys, or an unknown ``J_*`` key, fails when the
    reference holds them.  Status: None (the reference holds none), "checked" or "unchecked"."""
    shapes, window, notes, first, key_failure = dict(OUTPUT_SHAPES), None, [], None, None
    problem = _jacobian_key_problem(reference)
    if problem:
        raise ConformanceError(f"{reference_name}: incomplete Jacobians: {problem}")
    ref_has = all(key in reference for key in JACOBIAN_ALL_KEYS)
    cand_problem = _jacobian_key_problem(candidate)
    cand_has = cand_problem is None and all(key in candidate for key in JACOBIAN_ALL_KEYS)
    if cand_problem and ref_has:
        key_failure = f"{candidate_name} holds an incomplete set of Jacobians: {cand_problem}"
    elif cand_problem:
        notes.append(f"{candidate_name} holds an incomplete set of Jacobians ({cand_problem}); {reference_name} "
                     f"holds none, so they were not checked")
    if cand_has and ref_has:
        shapes.update({key: JACOBIAN_SHAPE for key in JACOBIAN_KEYS})
        first = _rows_of(reference, "J_first", (), reference_name, len(reference["times"]))[index]
        cand_first = _rows_of(candidate, "J_first", (), candidate_name, len(times))
        fractional = np.flatnonzero(cand_first != np.round(cand_first))
        if fractional.size:
            raise ConformanceError(f"{candidate_name}: key 'J_first' row {fractional[0]} is "
                                   f"{float(cand_first[fractional[0]])!r}; expected an integer control-point index")
        window = _window_mismatch(first, cand_first, times)
    elif cand_has:
        notes.append(f"{reference_name} holds no Jacobians; the candidate's were not checked (the shipped "
                     f"vector with Jacobians is jacobians_paper_dt0.25)")
    elif ref_has and not cand_problem:
        notes.append(f"{candidate_name} holds no Jacobians ({', '.join(JACOBIAN_ALL_KEYS)}); only the "
                     f"pose and its derivatives were checked")
    status = None if not ref_has else "checked" if cand_has else "unchecked"
    return shapes, window, notes, status, first, key_failure


def compare(reference: dict, candidate: dict, atol: float = DEFAULT_ATOL, rtol: float = DEFAULT_RTOL,
            reference_name: str = "reference", candidate_name: str = "candidate") -> dict:
    """Compare a candidate's outputs with a reference's at the candidate's times.

    Returns a report dict: ``rows`` (per quantity: quantity, error, scale, scaled, bound, ok and, at
    the worst time: index, time, segment, u, ref, cand), ``matched`` (candidate index -> reference
    index), ``missing`` (reference times the candidate left out), ``dropped`` (those before the
    reference's last time: any fails the check), ``window`` (None, or the first time whose
    ``J_first`` differs: index, time, ref, cand), ``notes`` (list of str: Jacobians not checked and
    why), ``jacobians`` (None when the reference holds no Jacobians, else "checked" or "unchecked":
    the candidate holds none), ``jacobian_keys`` (None, or why the candidate's set of Jacobian keys
    fails: some missing, or an unknown ``J_*`` key), ``J_first`` (the reference's at the matched
    times, None when the Jacobians are not compared), ``atol``, ``rtol``, ``knots`` (the
    reference's knot vector, None when uniform or unknown),
    ``refs`` and ``cands`` (quantity -> (M, ...) arrays at the matched times), ``parsed`` (the
    reference's parsed input, None for a bare output file), ``ok``.  Times are the reference's at
    the matched indices (equal to the candidate's up to :data:`TIME_MATCH`).  Hints for a failed
    check: :func:`tsslam_ref.conformance_hints.check`.  Raises ConformanceError on malformed files
    or bad tolerances.
    """
    check_tolerances(atol, rtol)
    ref_times = _array(reference, "times", (), reference_name)
    cand_times = _array(candidate, "times", (), candidate_name)
    if cand_times.size == 0:
        raise ConformanceError(f"{candidate_name}: key 'times' is empty")
    index = match_times(ref_times, cand_times, candidate_name)
    missing = np.setdiff1d(np.unique(ref_times), ref_times[index])  # reference times the candidate left out
    dropped = missing[missing < ref_times.max()]  # only t_max may be left out (a half-open domain)
    times = ref_times[index]  # in the reference's domain even where a candidate time is a few eps outside
    try:
        parsed = parse_input(reference, reference_name)
    except ConformanceError:
        parsed = None  # a bare output file: no segment / u, fewer hints
    segment, u = segment_and_u(parsed, times)
    refs, cands, rows = {}, {}, []
    shapes, window, notes, jacobians, first, key_failure = _jacobians_to_check(reference, candidate, index, times,
                                                                               reference_name, candidate_name)
    for key, shape_tail in shapes.items():
        ref = _rows_of(reference, key, shape_tail, reference_name, len(ref_times))
        cand = _rows_of(candidate, key, shape_tail, candidate_name, len(cand_times))
        ref = ref[index]
        refs[key], cands[key] = ref, cand
        per_time = np.abs(cand - ref).reshape(len(cand), -1).max(axis=1)  # (M,)
        worst = int(np.argmax(per_time))
        error, scale = float(per_time[worst]), float(np.abs(ref).max(initial=0.0))
        bound = atol + rtol * scale
        rows.append({"quantity": key, "error": error, "scale": scale,
                     "scaled": error / scale if scale > 0 else error, "bound": bound, "ok": error <= bound,
                     "index": worst, "time": float(times[worst]),
                     "segment": None if segment is None else int(segment[worst]),
                     "u": None if u is None else float(u[worst]),
                     "ref": ref[worst].tolist(), "cand": cand[worst].tolist(), "per_time": per_time})
    return {"rows": rows, "matched": index, "missing": missing, "dropped": dropped, "times": times,
            "window": window, "notes": notes, "atol": atol, "rtol": rtol, "jacobians": jacobians,
            "jacobian_keys": key_failure, "J_first": first,
            "knots": None if parsed is None else parsed["knots"], "refs": refs, "cands": cands, "parsed": parsed,
            "ok": window is None and key_failure is None and not dropped.size and all(row["ok"] for row in rows)}


def _rows_of(data: dict, key: str, shape_tail: tuple, source: str, n_times: int) -> np.ndarray:
    """``data[key]`` as an array with one row per time; ConformanceError naming both counts."""
    values = _array(data, key, shape_tail, source)
    if values.shape[0] != n_times:
        raise ConformanceError(f"{source}: key {key!r} has {values.shape[0]} rows but 'times' has {n_times}")
    return values


def _window_mismatch(first_ref: np.ndarray, first_cand: np.ndarray, times: np.ndarray) -> Optional[dict]:
    """The first time whose active window (``J_first``) differs, or None: a failed check, since the
    Jacobian blocks of different windows belong to different control points."""
    differ = np.flatnonzero(first_ref != first_cand)
    if not differ.size:
        return None
    m = int(differ[0])
    return {"index": m, "time": float(times[m]), "ref": int(first_ref[m]), "cand": int(first_cand[m]),
            "count": int(differ.size)}
