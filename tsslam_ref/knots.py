"""Non-uniform cumulative cubic B-spline on split SO(3) x R^3: the cumulative basis of a general knot vector.

Extends TS-SLAM §III-B (Eq. 5-7) and §III-C (Eq. 8-9) from equally spaced knots to any strictly
increasing knot vector (the paper's Sec. V names fixed intervals as its limitation).  The pose,
v, a (world) and ω, ω̇ (body) come from the same cumulative recursion as the uniform spline
(:func:`spline.evaluate_weights`); only the weights B_j and their time derivatives differ: each
segment has its own basis matrix, built from its six surrounding knots by the Cox-de Boor
recursion (the non-uniform cubic basis matrix of Qin 2000, "General matrix representations for
B-splines"), and its own time scale, the segment length h.

Knot vector (convention-free): ``knots`` κ_0..κ_{N+1}, N + 2 strictly increasing float64 times for
N ≥ 4 control points.  Segment s = 0..N−4 covers [κ_{s+2}, κ_{s+3}] and uses control points
s..s+3 and knots κ_s..κ_{s+5}; the domain is the closed [κ_2, κ_{N−1}].  (In standard B-spline
terms κ is the clamped-free knot vector τ_1..τ_{N+2} of degree 3; τ_0 and τ_{N+3} never affect
the curve on its domain.)  Equally spaced knots κ_j = t0 + (j + o − 2)Δt give the uniform spline
of :mod:`tsslam_ref.spline` with first-segment offset o (paper 2, basalt 0).

Time lookup: s = the number of interior knots κ_3..κ_{N−2} that are ≤ t (float64 comparisons
are exact), u = (t − κ_{s+2}) / h_s with h_s = κ_{s+3} − κ_{s+2}; the ends follow the uniform
rule (closed domain, END_ULPS of float64 rounding accepted, other times raise ValueError).

Layer 1 (math): imports ``spline``.  User doc: docs/spline.md, "Non-uniform knots".
"""

from typing import Tuple

import numpy as np
import torch

from tsslam_ref import spline
from tsslam_ref.spline import CumulativeWeights, SplineSample, TimesLike


def check_knots(knots, n_ctrl: int) -> np.ndarray:
    """The knot vector as a (N + 2,) float64 array; ValueError naming the problem otherwise.

    Needs N ≥ 4 control points, exactly N + 2 finite knots, strictly increasing, float64 (or Python
    floats: float32 knots raise TypeError, :func:`spline.check_float64_seconds`).
    """
    spline.check_float64_seconds("knots", knots)
    values = np.asarray(knots.detach().cpu() if isinstance(knots, torch.Tensor) else knots, dtype=np.float64)
    if n_ctrl < 4:
        raise ValueError(f"a cubic B-spline needs at least 4 control points, got n_ctrl={n_ctrl}")
    if values.ndim != 1 or values.shape[0] != n_ctrl + 2:
        raise ValueError(f"knots must be a 1-D vector of n_ctrl + 2 = {n_ctrl + 2} times (s), got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"knots must be finite, got {float(values[~np.isfinite(values)][0])!r} at index "
                         f"{int(np.flatnonzero(~np.isfinite(values))[0])}")
    steps = np.diff(values)
    if np.any(steps <= 0):
        j = int(np.flatnonzero(steps <= 0)[0])
        raise ValueError(f"knots must be strictly increasing, got knots[{j}] = {float(values[j])!r} s and "
                         f"knots[{j + 1}] = {float(values[j + 1])!r} s")
    j = int(np.argmin(steps))
    spline.check_resolvable(float(steps[j]), max(abs(values[j]), abs(values[j + 1])))
    return values


def uniform_knots(n_ctrl: int, dt: float, t0: float, convention: str = "paper") -> np.ndarray:
    """(N + 2,) equally spaced knots giving the uniform spline (dt, t0, convention) of :mod:`spline`.

    Raises what :func:`spline.valid_time_range` raises for (n_ctrl, dt, t0, convention): ValueError for
    n_ctrl < 4 (or not an integer), dt ≤ 0, a non-finite dt or t0, TypeError for float32 dt or t0.
    """
    if isinstance(n_ctrl, bool) or not isinstance(n_ctrl, (int, np.integer)):
        raise ValueError(f"a cubic B-spline needs at least 4 control points, got n_ctrl={n_ctrl!r}")
    spline.valid_time_range(n_ctrl, dt, t0, convention)  # the uniform spline's own checks
    offset = spline.first_segment_offset(convention)
    return float(t0) + float(dt) * (np.arange(n_ctrl + 2, dtype=np.float64) + offset - 2)


def knots_from_boundaries(boundaries, spacing: float) -> np.ndarray:
    """(m + 5,) knot vector whose m intervals are [e_n, e_n+1) of the (m + 1,) ``boundaries`` (s).

    The valid range [κ_2, κ_{N-1}] is [e_0, e_m] (N = m + 3 control points); the two knots
    before and the two after are ``spacing`` (s) apart, as the SLAM trajectory continues its knots.
    """
    spline.check_float64_seconds("boundaries", boundaries)
    spline.check_float64_seconds("spacing", spacing)
    boundaries = np.asarray(boundaries, dtype=np.float64).reshape(-1)
    if boundaries.shape[0] < 2:
        raise ValueError(f"need at least 2 interval boundaries, got {boundaries.shape[0]}")
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0 s, got {spacing}")
    before = boundaries[0] - spacing * np.array([2.0, 1.0])
    after = boundaries[-1] + spacing * np.array([1.0, 2.0])
    return check_knots(np.concatenate([before, boundaries, after]), boundaries.shape[0] + 2)


def start_weights(knot_vector) -> Tuple[float, float]:
    """(B̃_1, B̃_2): the cumulative weights of control points 1 and 2 at the domain start κ_2.

    At a knot the cubic B-spline has three non-zero basis functions (Cox-de Boor),
    N_0 = (κ_3 − κ_2)² / ((κ_3 − κ_1)(κ_3 − κ_0)),  N_2 = (κ_2 − κ_1)² / ((κ_4 − κ_1)(κ_3 − κ_1)),
    N_1 = 1 − N_0 − N_2, so B̃_1 = N_1 + N_2 = 1 − N_0 and B̃_2 = N_2.  Equal spacing: (5/6, 1/6).
    Read from :func:`cumulative_weights` of segment 0 at u = 0 (the same basis as the curve).
    knot_vector: at least its first six knots κ_0..κ_5 (s).
    """
    spline.check_float64_seconds("knot_vector", knot_vector)
    knots = torch.as_tensor(np.asarray(knot_vector, dtype=np.float64)[:6])
    weights = cumulative_weights(knots, torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.float64)).value
    return float(weights[0, 0]), float(weights[0, 1])


def valid_time_range(knots: np.ndarray) -> Tuple[float, float]:
    """Closed domain [κ_2, κ_{N−1}] in s of a checked knot vector."""
    return float(knots[2]), float(knots[-3])


def greville_times(knots: np.ndarray) -> np.ndarray:
    """(N,) float64 time each control point dominates (its Greville abscissa, s) on a (N + 2,) knot vector.

    Control point k acts on [κ_{k−1}, κ_{k+3}]; its abscissa is (κ_k + κ_{k+1} + κ_{k+2}) / 3, the
    time the spline of a linear motion puts it at (control points on a line at these times give
    that line exactly).  Equally spaced knots: κ_{k+1}, the uniform spline's peak time.
    """
    spline.check_float64_seconds("knots", knots)
    knots = np.asarray(knots, dtype=np.float64)
    return (knots[:-2] + knots[1:-1] + knots[2:]) / 3.0


def _polynomial_times_linear(poly: torch.Tensor, root: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Coefficients (..., 4) of poly(u)·(u − root)·scale, powers 1, u, u², u³ (degree stays ≤ 3)."""
    shifted = torch.cat([torch.zeros_like(poly[..., :1]), poly[..., :-1]], dim=-1)  # u·poly
    return (shifted - root[..., None] * poly) * scale[..., None]


def cumulative_basis_matrix(local_knots: torch.Tensor) -> torch.Tensor:
    """Each segment's cumulative basis matrix from its six knots, in its own u.

    Args:
        local_knots: (S, 6) knots x_0..x_5 of segments [x_2, x_3] in units of the segment
            length with x_2 = 0, x_3 = 1 (:func:`segment_local_knots`).

    Returns:
        (S, 4, 4) matrices, rows B_0..B_3 (cumulative: B_j = Σ_{m≥j} N_m, B_0 = 1), columns the
        powers 1, u, u², u³; for x = (−2, −1, 0, 1, 2, 3) the uniform C of :mod:`spline`.

    Cox-de Boor on polynomials: N_{i,p} = (u − x_i)/(x_{i+p} − x_i) N_{i,p−1}
    + (x_{i+p+1} − u)/(x_{i+p+1} − x_{i+1}) N_{i+1,p−1}, starting from N_{2,0} = 1 on [x_2, x_3].
    """
    x = local_knots
    one = torch.ones_like(x[..., 0])
    funcs = {2: torch.stack([one, 0 * one, 0 * one, 0 * one], dim=-1)}  # degree 0: index -> (S, 4)
    for p in (1, 2, 3):
        new = {}
        for i in range(2 - p, 3):
            total = torch.zeros_like(funcs[2])
            if i in funcs:  # rising part, (u − x_i)/(x_{i+p} − x_i)
                total = total + _polynomial_times_linear(funcs[i], x[..., i], 1.0 / (x[..., i + p] - x[..., i]))
            if i + 1 in funcs:  # falling part, (x_{i+p+1} − u)/(x_{i+p+1} − x_{i+1})
                scale = -1.0 / (x[..., i + p + 1] - x[..., i + 1])
                total = total + _polynomial_times_linear(funcs[i + 1], x[..., i + p + 1], scale)
            new[i] = total
        funcs = new
    plain = torch.stack([funcs[i] for i in (-1, 0, 1, 2)], dim=-2)  # (S, 4, 4): N_0..N_3
    return plain.flip(-2).cumsum(-2).flip(-2)  # row j = Σ_{m≥j} N_m


def segment_local_knots(knots: torch.Tensor, segment: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """(M, 6) knots κ_s..κ_{s+5} around each sample's segment in units of h_s, origin κ_{s+2}; (M,) h_s."""
    window = segment[:, None] + torch.arange(6, device=segment.device)  # (M, 6)
    around = knots[window]  # (M, 6) s
    start, length = around[:, 2], around[:, 3] - around[:, 2]
    return (around - start[:, None]) / length[:, None], length


def cumulative_weights(knots: torch.Tensor, segment: torch.Tensor, u: torch.Tensor,
                       derivatives: int = 0) -> CumulativeWeights:
    """B_1..B_3 and their first / second time derivatives at (segment, u): (M, 3, 1) each.

    d/dt = (1/h_s) d/du, so Ḃ = B'(u)/h_s and B̈ = B''(u)/h_s² with each segment's own h_s.
    """
    local, length = segment_local_knots(knots, segment)
    matrix = cumulative_basis_matrix(local)[:, 1:, :]  # (M, 3, 4): B_1..B_3

    def rows(order: int) -> torch.Tensor:
        monomials = spline.basis_monomials(u, order)  # (M, 4)
        return (matrix @ monomials[:, :, None]) / length[:, None, None] ** order  # (M, 3, 1)

    return CumulativeWeights(rows(0), rows(1) if derivatives >= 1 else None, rows(2) if derivatives >= 2 else None)


def locate(times: TimesLike, knots: np.ndarray):
    """(segment (M,) int64, u (M,) float64, times.shape) on a checked knot vector; ValueError off the domain."""
    t_min, t_max = valid_time_range(knots)
    times64 = spline.times_float64(times)
    shape = times64.shape
    flat = times64.reshape(-1)
    knots_t = torch.as_tensor(knots, dtype=torch.float64, device=flat.device)
    with torch.no_grad():
        plain = flat.detach()
        low = t_min - spline.end_tolerance(t_min, knots[0])
        high = t_max + spline.end_tolerance(t_max, knots[0])
        bad = ~((plain >= low) & (plain <= high))  # NaN is bad too
        if bool(bad.any()):
            first_bad = float(plain[bad.nonzero()[0, 0]])
            raise ValueError(f"time {first_bad!r} s is outside the spline domain [{t_min!r}, {t_max!r}] s "
                             f"(n_ctrl={len(knots) - 2}, non-uniform knots, closed interval)")
        segment = torch.searchsorted(knots_t[3:-3].contiguous(), plain.contiguous(), right=True)  # interior knots <= t
    u = (flat - knots_t[segment + 2]) / (knots_t[segment + 3] - knots_t[segment + 2])  # differentiable in t
    return segment, u, shape


def evaluate(control_rotations: torch.Tensor, control_translations: torch.Tensor, times: TimesLike, knots,
             derivatives: int = 0) -> SplineSample:
    """Pose (and derivatives) of the non-uniform spline at query times.

    Args:
        control_rotations: (..., N, 3, 3); control_translations: (..., N, 3) world, m.
        times: any shape, s (float64).  knots: (N + 2,) strictly increasing times, s.
        derivatives: 0 pose; 1 adds velocity_world and omega_body; 2 adds acceleration_world and
            omegadot_body.

    Returns:
        :class:`spline.SplineSample`, fields (..., *times.shape, 3[, 3]).

    Raises:
        ValueError: bad knots (named), a time outside [κ_2, κ_{N−1}], malformed shapes.
    """
    n_ctrl = spline.check_control_points(control_rotations, control_translations)
    knots = check_knots(knots, n_ctrl)
    if derivatives not in (0, 1, 2):
        raise ValueError(f"derivatives must be 0, 1 or 2, got {derivatives}")
    segment, u, shape = locate(times, knots)
    dtype, device = control_translations.dtype, control_translations.device
    knots_t = torch.as_tensor(knots, dtype=torch.float64, device=device)
    weights = cumulative_weights(knots_t, segment.to(device), u.to(device), derivatives)
    weights = CumulativeWeights(*(None if w is None else w.to(dtype) for w in weights))
    sample = spline.evaluate_weights(control_rotations, control_translations, segment, weights, derivatives)
    return spline.reshape_sample(sample, control_translations.shape[:-2], shape)
