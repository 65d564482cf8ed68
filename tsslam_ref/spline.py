"""Uniform cubic B-spline trajectory on split SO(3) x R^3, cumulative form.

TS-SLAM §III-B, Eq. (5) ``eq:bspline_p`` (translation), Eq. (6) ``eq:bspline_r`` (rotation), Eq. (7)
(d_j), the unnumbered B(u), C, Ḃ(u), B̈(u); §III-C Eq. (8) ``eq_jeck`` (a(t)) and Eq. (9)
``eq_rot_jeck`` (the ω / ω̇ recursion).  Curve approximation, §III-D Eq. (11), is in
:mod:`tsslam_ref.spline_fit`.

Layer 1 (math).  Imports layer 0 (``geometry``, ``times``); looks the names moved to
``spline_fit`` up there on first use.  Taught in notebooks/01_bspline_trajectory.ipynb.
Sources: Sommer et al. 2020 "Efficient derivative computation for cumulative B-splines on Lie groups";
basalt-headers ``so3_spline.h`` / ``rd_spline.h`` @a585db3 (same recursion, body frame).  docs/spline.md is the user doc;
the conformance kit's reference (tsslam_ref/assets/spline_kit.md) lists formulas and golden values.

Index conventions (s = (t − t0)/Δt, control point k sits at t_k = t0 + kΔt, n = n_ctrl ≥ 4):

* ``"paper"`` (default): segment [t_i, t_{i+1}) uses control points i−2..i+1;
  valid times [t0 + 2Δt, t0 + (n−1)Δt].
* ``"basalt"``: segment [t_i, t_{i+1}) uses control points i..i+3; valid times [t0, t0 + (n−3)Δt].

Both give the same curve with paper time = basalt time + 2Δt.  **The domain is closed**: t_max
maps to the last segment at u = 1 (like PyPose; basalt and kontiki are half-open and reject t_max).

Segment rule (exact on what it is given): the float64 numbers t, t0 and Δt are the times.  The
segment is i = floor((t − t0)/Δt) − offset of the *exact* rational quotient, u = s − i with
s = (t − t0)/Δt − offset in float64.  floor of the float64 quotient is already exact unless it
lies within 8 eps of an integer; only those times (knots, in practice) are redone with
``fractions.Fraction``.  A knot time that float64 puts 1e-17 before the knot is therefore in the
previous segment at u = 1 (the curve is C², so only a and ω̇ notice, by Δjerk times the
distance, i.e. nothing), and a time 3e-6 segments before a knot is in the previous segment at
u = 1 − 3e-6, as exact arithmetic says.  No tolerance moves a time to another segment.
Special cases, the domain ends only: the index is clamped to the last segment, so t_max gives u = 1
(closed domain); a time within the float64 rounding of an end (END_ULPS ulps of the ends'
magnitude, :func:`time_in_domain`) is accepted and continues the end segment by that much.  Other
times raise ValueError naming the time and the domain.  Times, t0 and Δt must be float64 (or
Python floats): float32 ones raise TypeError.

Rotation steps: the principal Log is ambiguous at a relative rotation of π between consecutive
control points (the two choices give different curves); :func:`evaluate` does not check this,
the conformance kit refuses such input (``conformance.ROTATION_STEP_LIMIT``).

Not an interpolant: with the paper convention the curve near t_i is dominated by
control point i−1, so control point k "belongs" to time t_{k+1} (basalt: t_{k−1}).

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| R_k | ``control_rotations`` / ``rot_cp`` | (..., N, 3, 3) | body→world | - |
| t_k (translation) | ``control_translations`` / ``trans_cp`` | (..., N, 3) | world | m |
| t (time) | ``times`` | any shape, float64 | - | s |
| Δt, t0 | ``dt``, ``t0`` | python float | - | s |
| u | ``u`` | (M,) | - | 1 (segment fraction) |
| B, Ḃ·Δt, B̈·Δt² | ``basis(u, 0/1/2)`` | (M, 4) | - | 1 |
| d_j = Log(R_{j−1}ᵀ R_j) | ``d`` | (..., N−1, 3) | body | rad |
| A_j = Exp(B_j d_j) | ``A`` | (..., M, 3, 3) | - | - |
| R(t), t(t) | ``rotation``, ``translation`` | (..., M, 3, 3), (..., M, 3) | world | -, m |
| v, a | ``velocity_world``, ``acceleration_world`` | (..., M, 3) | world | m/s, m/s² |
| ω, ω̇ | ``omega_body``, ``omegadot_body`` | (..., M, 3) | body | rad/s, rad/s² |

Here M stands for ``times.shape`` (the outputs carry the query shape).
"""

from fractions import Fraction
from typing import NamedTuple, Optional, Tuple, Union

import numpy as np
import torch

from tsslam_ref.geometry import so3_exp, so3_log
from tsslam_ref.times import check_float64_seconds  # noqa: F401  (re-exported: knots, conformance)

# 6 C: the cumulative cubic basis matrix C of §III-B times 6 (rows B_0..B_3, columns powers 1, u, u², u³).
CUMULATIVE_BASIS = (
    (6.0, 0.0, 0.0, 0.0),
    (5.0, 3.0, -3.0, 1.0),
    (1.0, 3.0, 3.0, -2.0),
    (0.0, 0.0, 0.0, 1.0),
)

END_ULPS = 4.0
"""Float64 rounding allowed at the domain ends, in ulps of the ends' magnitude: t0 + kΔt computed
in float64 is within one ulp of the exact end, and a caller's own t0 = t_first − 2Δt adds another."""

CONVENTIONS = ("paper", "basalt")

_FIRST_SEGMENT_OFFSET = {"paper": 2, "basalt": 0}
"""Knot index of the first valid time: segment i uses control points i − offset .. i − offset + 3."""

TimesLike = Union[float, np.ndarray, torch.Tensor]


class SplineSample(NamedTuple):
    """Spline outputs at query times; fields not requested are None.

    rotation (..., M, 3, 3) body→world; translation (..., M, 3) world [m];
    velocity_world, acceleration_world (..., M, 3) [m/s, m/s²];
    omega_body, omegadot_body (..., M, 3) body frame [rad/s, rad/s²].
    """

    rotation: torch.Tensor
    translation: torch.Tensor
    velocity_world: Optional[torch.Tensor] = None
    acceleration_world: Optional[torch.Tensor] = None
    omega_body: Optional[torch.Tensor] = None
    omegadot_body: Optional[torch.Tensor] = None


# --------------------------------------------------------------------------------------------
# Basis


def basis(u: torch.Tensor, order: int = 0) -> torch.Tensor:
    """Cumulative cubic basis B(u) = C [1, u, u², u³]ᵀ and its u-derivatives.

    order 0: B(u); order 1: dB/du = Ḃ(u)·Δt = C [0, 1, 2u, 3u²]ᵀ; order 2: d²B/du² = B̈(u)·Δt²
    = C [0, 0, 2, 6u]ᵀ; order 3: d³B/du³ = C [0, 0, 0, 6]ᵀ (jerk, used in tests).  Divide by
    Δt^order to get the paper's time derivatives.

    Args:
        u: (...) segment fractions (any float dtype/device; a python float is accepted).
        order: derivative order in u, 0..3.

    Returns:
        (..., 4) basis values [B_0, B_1, B_2, B_3] in u's dtype and device.

    Example:
        >>> basis(torch.tensor(0.0, dtype=torch.float64)) * 6
        tensor([6., 5., 1., 0.], dtype=torch.float64)
    """
    monomials = basis_monomials(u, order)  # (..., 4)
    C = torch.tensor(CUMULATIVE_BASIS, dtype=monomials.dtype, device=monomials.device) / 6.0
    return monomials @ C.T  # (..., 4)


def basis_monomials(u: torch.Tensor, order: int = 0) -> torch.Tensor:
    """(..., 4) the order-th u-derivative of [1, u, u², u³] (order 0..3); a basis matrix times it gives the basis."""
    u = torch.as_tensor(u)
    if not u.is_floating_point():
        u = u.to(torch.get_default_dtype())
    one, zero = torch.ones_like(u), torch.zeros_like(u)
    if order == 0:
        powers = [one, u, u * u, u * u * u]
    elif order == 1:
        powers = [zero, one, 2.0 * u, 3.0 * u * u]
    elif order == 2:
        powers = [zero, zero, 2.0 * one, 6.0 * u]
    elif order == 3:
        powers = [zero, zero, zero, 6.0 * one]
    else:
        raise ValueError(f"basis order must be 0, 1, 2 or 3, got {order}")
    return torch.stack(powers, dim=-1)  # (..., 4)


# --------------------------------------------------------------------------------------------
# Time domain


def first_segment_offset(convention: str) -> int:
    """o, the knot index of the first valid time (paper 2, basalt 0); ValueError for another convention."""
    if convention not in _FIRST_SEGMENT_OFFSET:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    return _FIRST_SEGMENT_OFFSET[convention]


def valid_time_range(n_ctrl: int, dt: float, t0: float, convention: str = "paper") -> Tuple[float, float]:
    """Closed valid time interval [t_min, t_max] in seconds (Python floats) for ``n_ctrl`` control points.

    paper: [t0 + 2Δt, t0 + (n−1)Δt]; basalt: [t0, t0 + (n−3)Δt].

    Raises:
        ValueError: n_ctrl < 4, a non-finite dt or t0, dt ≤ 0 or an unknown convention.  TypeError:
        float32 dt or t0.
    """
    offset = first_segment_offset(convention)
    if n_ctrl < 4:
        raise ValueError(f"a cubic B-spline needs at least 4 control points, got n_ctrl={n_ctrl}")
    for name, value in (("dt", dt), ("t0", t0)):
        check_float64_seconds(name, value)
        if not np.isfinite(float(value)):
            raise ValueError(f"{name} must be a finite number of seconds, got {float(value)!r}")
    if not dt > 0:
        raise ValueError(f"knot spacing dt must be > 0 s, got {float(dt)!r}")
    dt, t0 = float(dt), float(t0)
    check_resolvable(dt, t0)
    return t0 + offset * dt, t0 + (offset + n_ctrl - 3) * dt


MIN_INTERVAL_ULPS = 1024.0
"""An interval must span at least this many float64 ulps of its time stamps (u resolved to 1e-3)."""


def check_resolvable(interval: float, time: float) -> None:
    """ValueError when an interval of ``interval`` s near ``time`` s is too short for float64 times
    to place u in it (below MIN_INTERVAL_ULPS ulps of |time|: at 1.5e9 s, 2.4e-4 s)."""
    floor = MIN_INTERVAL_ULPS * np.spacing(abs(float(time)))
    if not interval >= floor:
        raise ValueError(f"a knot interval of {interval!r} s is too short for times near {float(time)!r} s: float64 "
                         f"resolves {np.spacing(abs(float(time))):.3g} s there, so it needs >= {floor:.3g} s; "
                         f"subtract a reference time from the stamps first")


def times_float64(times: TimesLike) -> torch.Tensor:
    """Times as a float64 tensor (keeps autograd and device of a tensor input); TypeError for
    floating times narrower than float64 (:func:`check_float64_seconds`)."""
    check_float64_seconds("times", times)
    if isinstance(times, torch.Tensor):
        return times.to(torch.float64)
    return torch.as_tensor(np.asarray(times).astype(np.float64))


def end_tolerance(t_end: float, t0: float) -> float:
    """Seconds of float64 rounding allowed at a domain end t_end = t0 + kΔt (END_ULPS ulps of the
    larger of |t_end| and |t0|)."""
    return END_ULPS * np.finfo(np.float64).eps * max(abs(t_end), abs(t0))


def time_in_domain(times: TimesLike, n_ctrl: int, dt: float, t0: float, convention: str = "paper"):
    """Inside the closed domain [t_min, t_max]: boolean, times' shape (numpy for numpy or float
    input, a tensor for a tensor).

    The ends are the float64 values of :func:`valid_time_range`, widened by their own float64
    rounding (:func:`end_tolerance`); the same rule for absolute stamps and relative times
    (1.2e-6 s at ends near a 1.3e9 s stamp, 5e-17 s at ends near 0.06 s).  NaN is outside.
    """
    check_float64_seconds("times", times)  # a float32 time compares as a time up to a minute away
    t_min, t_max = valid_time_range(n_ctrl, dt, t0, convention)
    if not isinstance(times, torch.Tensor):
        times = np.asarray(times, dtype=np.float64)
    return (times >= t_min - end_tolerance(t_min, t0)) & (times <= t_max + end_tolerance(t_max, t0))


def _exact_floor_quotient(flat: torch.Tensor, dt: float, t0: float) -> torch.Tensor:
    """floor((t − t0)/Δt) of the float64 numbers t, t0, Δt taken as exact rationals, (M,) int64.

    q = fl(fl(t − t0)/Δt) is within 2 eps·|q| of the exact quotient, so floor(q) is exact unless q
    lies within 8 eps·max(|q|, 1) of an integer; only those times (in practice: knot times) are
    redone in exact rational arithmetic (``fractions.Fraction``).
    """
    q = (flat - float(t0)) / float(dt)  # (M,) float64
    k = torch.floor(q)
    nearest = torch.round(q)
    band = 8.0 * torch.finfo(torch.float64).eps * torch.clamp(q.abs(), min=1.0)
    ambiguous = ((q - nearest).abs() <= band).nonzero().reshape(-1)
    if ambiguous.numel():
        t0_exact, dt_exact = Fraction(float(t0)), Fraction(float(dt))
        times_list, knots = flat[ambiguous].tolist(), nearest[ambiguous].tolist()
        exact = [knot if Fraction(t) - t0_exact >= int(knot) * dt_exact else knot - 1
                 for t, knot in zip(times_list, knots)]
        k = k.index_put((ambiguous,), torch.as_tensor(exact, dtype=k.dtype, device=k.device))
    return k.to(torch.int64)


def locate_segments(times: TimesLike, n_ctrl: int, dt: float, t0: float, convention: str):
    """Segment lookup: (first control index (M,) int64, u (M,) float64, times.shape).

    The segment is the floor of the exact (t − t0)/Δt minus the offset (module docstring),
    clamped to the segments so that t_max gives u = 1; u = s − segment with
    s = (t − t0)/Δt − offset in float64 (differentiable w.r.t. a times tensor).
    Raises ValueError naming the first out-of-domain time.
    """
    t_min, t_max = valid_time_range(n_ctrl, dt, t0, convention)
    offset = _FIRST_SEGMENT_OFFSET[convention]
    times64 = times_float64(times)
    shape = times64.shape
    flat = times64.reshape(-1)  # (M,)
    s = (flat - float(t0)) / float(dt) - offset  # (M,) float64, 0 at t_min
    n_segments = n_ctrl - 3
    with torch.no_grad():
        plain = flat.detach()
        bad = ~time_in_domain(plain, n_ctrl, dt, t0, convention)  # NaN is bad too
        if bool(bad.any()):
            first_bad = float(plain[bad.nonzero()[0, 0]])
            raise ValueError(
                f"time {first_bad!r} s is outside the spline domain [{t_min!r}, {t_max!r}] s "
                f"(n_ctrl={n_ctrl}, dt={dt}, t0={t0}, convention={convention!r}, closed interval)"
            )
        first = (_exact_floor_quotient(plain, dt, t0) - offset).clamp_(0, n_segments - 1)  # (M,)
    u = s - first.to(s.dtype)  # (M,), differentiable w.r.t. times
    return first, u, shape


def active_control_indices(
    times: TimesLike, n_ctrl: int, dt: float, t0: float, convention: str = "paper"
) -> torch.Tensor:
    """Indices of the 4 control points that shape the spline at each time.

    Args:
        times: any shape, seconds (float64 array or tensor).

    Returns:
        (*times.shape, 4) int64 tensor, consecutive indices k..k+3 (device of a tensor input).

    Raises:
        ValueError: a time outside the closed domain (see :func:`valid_time_range`).
    """
    first, _, shape = locate_segments(times, n_ctrl, dt, t0, convention)
    window = first[:, None] + torch.arange(4, device=first.device)  # (M, 4)
    return window.reshape(*shape, 4)


# --------------------------------------------------------------------------------------------
# Evaluation


def knot_rotation_differences(control_rotations: torch.Tensor) -> torch.Tensor:
    """Eq. (7): d_j = Log(R_{j−1}ᵀ R_j) for every consecutive pair, computed once.

    Args:
        control_rotations: (..., N, 3, 3).

    Returns:
        (..., N−1, 3) rotation vectors in rad (body frame of R_{j−1}).

    Differs from: the paper writes d_j ∈ se(3); in the split representation it is so(3)
    (split representation).
    """
    relative = control_rotations[..., :-1, :, :].transpose(-1, -2) @ control_rotations[..., 1:, :, :]
    return so3_log(relative)  # (..., N-1, 3)


class CumulativeWeights(NamedTuple):
    """Cumulative basis weights B_1..B_3 of each sample and their time derivatives.

    value (M, 3) dimensionless; rate (M, 3) in 1/s; curvature (M, 3) in 1/s² (None where
    not needed).  The uniform spline fills them from :func:`basis` and Δt
    (:func:`uniform_weights`), the non-uniform one from each segment's knots (:mod:`tsslam_ref.knots`).
    """

    value: torch.Tensor
    rate: Optional[torch.Tensor] = None
    curvature: Optional[torch.Tensor] = None


def uniform_weights(u: torch.Tensor, dt: float, derivatives: int = 0) -> CumulativeWeights:
    """B(u), Ḃ = B'(u)/Δt and B̈ = B''(u)/Δt² of the uniform basis, j = 1..3: each (M, 3, 1)."""
    value = basis(u, 0)[:, 1:, None]  # (M, 3, 1): B_1..B_3
    rate = basis(u, 1)[:, 1:, None] / dt if derivatives >= 1 else None
    curvature = basis(u, 2)[:, 1:, None] / dt**2 if derivatives >= 2 else None
    return CumulativeWeights(value, rate, curvature)


def _gather_windows(control_rotations: torch.Tensor, control_translations: torch.Tensor, first_index: torch.Tensor):
    """d_j and Δp_j = t_{k+j} − t_{k+j−1} (translations), j = 1..3, of each window: (..., M, 3, 3) each.

    Only the knot pairs some sample needs are used (each Log computed once, then gathered).
    """
    device = control_translations.device
    lo = int(first_index.min()) if first_index.numel() else 0
    hi = int(first_index.max()) if first_index.numel() else 0
    used_rotations = control_rotations[..., lo:hi + 4, :, :]  # (..., hi-lo+4, 3, 3)
    used_translations = control_translations[..., lo:hi + 4, :]  # (..., hi-lo+4, 3)
    window = (first_index - lo)[:, None] + torch.arange(3, device=device)  # (M, 3): pair j = 1..3
    d = knot_rotation_differences(used_rotations)  # (..., hi-lo+3, 3): one Log per knot pair
    delta_p = used_translations[..., 1:, :] - used_translations[..., :-1, :]  # (..., hi-lo+3, 3)
    return d[..., window, :], delta_p[..., window, :]  # [..., m, j-1, :] = d_j, Δp_j


def _angular_recursion(A: torch.Tensor, d: torch.Tensor, B_dot: torch.Tensor, B_ddot: Optional[torch.Tensor]):
    """Eq. (9): ω^(4), ω̇^(4) (body) from A_j (..., M, 3, 3, 3), d_j (..., M, 3, 3), Ḃ, B̈ (M, 3, 1).

    ω̇ is None when B̈ is None.
    """
    A_T = A.transpose(-1, -2)
    omega = torch.zeros_like(d[..., 0, :])  # ω^(1)
    omega_dot = None if B_ddot is None else torch.zeros_like(omega)  # ω̇^(1)
    for j in range(3):
        d_j = d[..., j, :]  # (..., M, 3)
        omega = (A_T[..., j, :, :] @ omega.unsqueeze(-1)).squeeze(-1) + B_dot[:, j] * d_j
        if B_ddot is not None:
            omega_dot = (
                B_dot[:, j] * torch.linalg.cross(omega, d_j)
                + (A_T[..., j, :, :] @ omega_dot.unsqueeze(-1)).squeeze(-1)
                + B_ddot[:, j] * d_j
            )
    return omega, omega_dot


def evaluate_weights(
    control_rotations: torch.Tensor,
    control_translations: torch.Tensor,
    first_index: torch.Tensor,
    weights: CumulativeWeights,
    derivatives: int = 0,
) -> SplineSample:
    """Evaluate given each sample's first control index and its cumulative weights (no domain logic).

    Eq. (5) t(t) = t_{k} + Σ_{j=1..3} B_j (t_{k+j} − t_{k+j−1});
    Eq. (6) R(t) = R_{k} Π_{j=1..3} Exp(B_j d_j);
    Eq. (8) a = Σ B̈_j Δp_j (v likewise with Ḃ; Δp_j the control-point translation differences);
    Eq. (9) ω^(j+1) = A_jᵀ ω^(j) + Ḃ_j d_j, ω̇^(j+1) = Ḃ_j ω^(j+1) × d_j + A_jᵀ ω̇^(j) + B̈_j d_j,
    with ω^(1) = ω̇^(1) = 0; ω^(4), ω̇^(4) are body-frame.  The same for a uniform and a
    non-uniform knot vector: only the weights differ.

    Args:
        control_rotations: (..., N, 3, 3); control_translations: (..., N, 3).
        first_index: (M,) int64 in [0, N−4].
        weights: :class:`CumulativeWeights`, fields (M, 3) or (M, 3, 1); rate needed for
            derivatives ≥ 1, curvature for 2.
        derivatives: 0 pose only; 1 adds v and ω; 2 adds a and ω̇.

    Returns:
        :class:`SplineSample` with leading shape (..., M).
    """
    if derivatives not in (0, 1, 2):
        raise ValueError(f"derivatives must be 0, 1 or 2, got {derivatives}")
    dtype, device = control_translations.dtype, control_translations.device
    first_index = first_index.to(device)
    B, B_dot, B_ddot = (None if w is None else w.to(device=device, dtype=dtype).reshape(-1, 3, 1) for w in weights)
    d, delta_p = _gather_windows(control_rotations, control_translations, first_index)
    translation = control_translations[..., first_index, :] + (B * delta_p).sum(-2)  # (..., M, 3)
    A = so3_exp(B * d)  # (..., M, 3, 3, 3): A_j = Exp(B_j d_j)
    rotation = control_rotations[..., first_index, :, :] @ A[..., 0, :, :] @ A[..., 1, :, :] @ A[..., 2, :, :]
    velocity = acceleration = omega = omega_dot = None
    if derivatives >= 1:
        velocity = (B_dot * delta_p).sum(-2)  # (..., M, 3)
        if derivatives >= 2:
            acceleration = (B_ddot * delta_p).sum(-2)  # (..., M, 3)
        omega, omega_dot = _angular_recursion(A, d, B_dot, B_ddot if derivatives >= 2 else None)
    return SplineSample(rotation, translation, velocity, acceleration, omega, omega_dot)


def evaluate_segments(
    control_rotations: torch.Tensor,
    control_translations: torch.Tensor,
    first_index: torch.Tensor,
    u: torch.Tensor,
    dt: float,
    derivatives: int = 0,
) -> SplineSample:
    """Uniform spline given the first control index of each 4-point window and u (no domain logic).

    :func:`evaluate_weights` with the uniform weights B(u), B'(u)/Δt, B''(u)/Δt².  Here
    k = first_index (k = i−2 in the paper's indexing).  Used by :func:`evaluate`; also lets
    tests take one-sided limits at knots.

    Args:
        control_rotations: (..., N, 3, 3); control_translations: (..., N, 3).
        first_index: (M,) int64 in [0, N−4].
        u: (M,) segment fractions (cast to the control points' dtype).
        dt: knot spacing in s.
        derivatives: 0 pose only; 1 adds v and ω; 2 adds a and ω̇.

    Returns:
        :class:`SplineSample` with leading shape (..., M).
    """
    if derivatives not in (0, 1, 2):
        raise ValueError(f"derivatives must be 0, 1 or 2, got {derivatives}")
    u = u.to(device=control_translations.device, dtype=control_translations.dtype)
    weights = uniform_weights(u, dt, derivatives)
    return evaluate_weights(control_rotations, control_translations, first_index, weights, derivatives)


def check_control_points(control_rotations: torch.Tensor, control_translations: torch.Tensor,
                         batched: bool = True) -> int:
    """N, once the control points are tensors (..., N, 3, 3) and (..., N, 3) of one dtype (``batched``
    False: (N, 3, 3) and (N, 3)); TypeError or ValueError naming what was given otherwise."""
    for name, value in (("control_rotations", control_rotations), ("control_translations", control_translations)):
        if not isinstance(value, torch.Tensor) or value.dtype not in (torch.float32, torch.float64):  # f16: 1e-2 off
            got = f"a tensor of {value.dtype}" if isinstance(value, torch.Tensor) else type(value).__name__
            raise TypeError(f"{name} must be a float32 or float64 torch tensor, got {got} (use torch.as_tensor)")
    shape, lead = tuple(control_rotations.shape), "..., " if batched else ""
    if shape[-2:] != (3, 3) or len(shape) < 3 or not (batched or len(shape) == 3):
        hint = (" (rotation matrices: convert quaternions or rotation vectors first, e.g. geometry.so3_exp)"
                if len(shape) == 2 else "" if batched else " (one spline: no batch dimension)")
        raise ValueError(f"control_rotations must be ({lead}N, 3, 3), got {shape}{hint}")
    if control_translations.shape[-1:] != (3,) or control_translations.shape[:-1] != shape[:-2]:
        raise ValueError(f"control_translations must be ({lead}N, 3) matching control_rotations {shape}, "
                         f"got {tuple(control_translations.shape)}")
    if control_rotations.dtype != control_translations.dtype:
        raise ValueError(f"control rotations ({control_rotations.dtype}) and translations "
                         f"({control_translations.dtype}) must share a dtype")
    return shape[-3]


def evaluate(
    control_rotations: torch.Tensor,
    control_translations: torch.Tensor,
    times: TimesLike,
    dt: float,
    t0: float,
    convention: str = "paper",
    derivatives: int = 0,
) -> SplineSample:
    """Pose (and derivatives) of the spline at query times: Eq. (5)-(9), see :func:`evaluate_segments`.

    Args:
        control_rotations: (..., N, 3, 3) rotation matrices R_k (parametrise them as you like,
            e.g. Exp(δ_k) R_k0); differentiable.
        control_translations: (..., N, 3) translations t_k in m, world frame; differentiable.
        times: any shape, seconds; float64 numpy array, python float or tensor (cast to float64
            before t0 is subtracted; a float64 tensor may require grad).
        dt, t0: knot spacing and time of control point 0, seconds (python floats).
        convention: "paper" (segment i uses i−2..i+1) or "basalt" (i..i+3).
        derivatives: 0 pose only; 1 adds velocity_world and omega_body; 2 adds
            acceleration_world and omegadot_body.

    Returns:
        :class:`SplineSample`, each field (..., *times.shape, 3[, 3]) in the control points'
        dtype and device; unrequested fields are None.

    Raises:
        ValueError: "time ... is outside the spline domain [t_min, t_max]" (closed interval),
            malformed shapes, N < 4, unknown convention.
    """
    n_ctrl = check_control_points(control_rotations, control_translations)
    first, u, shape = locate_segments(times, n_ctrl, dt, t0, convention)
    sample = evaluate_segments(control_rotations, control_translations, first, u, dt, derivatives)
    return reshape_sample(sample, control_translations.shape[:-2], shape)


def reshape_sample(sample: SplineSample, batch: Tuple[int, ...], shape: Tuple[int, ...]) -> SplineSample:
    """Fields (*batch, M, ...) reshaped to (*batch, *shape, ...), M = prod(shape); None stays None."""

    def _reshape(value: Optional[torch.Tensor], tail: Tuple[int, ...]) -> Optional[torch.Tensor]:
        return None if value is None else value.reshape(*batch, *shape, *tail)

    return SplineSample(
        _reshape(sample.rotation, (3, 3)),
        *(_reshape(value, (3,)) for value in sample[1:]),
    )
