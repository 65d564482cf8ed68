"""Curve approximation (TS-SLAM §III-D, Eq. (11)): spline control points from discrete poses.

:func:`fit_control_points` solves Eq. (11) for the free control points of a spline layout,
:func:`fit_trajectory` lays a spline over a whole discrete trajectory, and
:func:`first_control_point` / :func:`pin_first_control_point` hold the curve's start pose fixed
(the gauge of local and global BA).

Layer 1 (math).  Imports :mod:`tsslam_ref.spline` (the curve), :mod:`tsslam_ref.knots` (non-uniform
knots), :mod:`tsslam_ref.trajectory` and :mod:`tsslam_ref.geometry`.
Taught in notebooks/01_bspline_trajectory.ipynb; docs/spline.md is the user doc.
"""

import math
from typing import Optional, Tuple

import numpy as np
import torch

from tsslam_ref import knots as knots_module
from tsslam_ref.geometry import so3_exp, so3_log
from tsslam_ref.spline import (CumulativeWeights, evaluate_weights, first_segment_offset, locate_segments,
                               time_in_domain, uniform_weights)
from tsslam_ref.times import check_float64_seconds, float64_seconds
from tsslam_ref.trajectory import BSplineTrajectory


def control_point_times(n_ctrl: int, dt: float, t0: float, convention: str = "paper",
                        knots: Optional[np.ndarray] = None) -> np.ndarray:
    """(N,) float64 time at which each control point dominates the curve (its basis peak).

    paper: t_{k+1} = t0 + (k+1)Δt; basalt: t_{k−1}.  Initialising R_k, t_k from the pose at these
    times avoids a one-Δt lag of the curve (docs/spline.md).  With a (N + 2,) knot vector
    (:mod:`tsslam_ref.knots`) instead: its Greville abscissae (:func:`knots.greville_times`).
    """
    if knots is not None:
        return knots_module.greville_times(knots_module.check_knots(knots, n_ctrl))
    check_float64_seconds("t0", t0)
    check_float64_seconds("dt", dt)
    offset = first_segment_offset(convention)
    return float(t0) + dt * (np.arange(n_ctrl, dtype=np.float64) + offset - 1)


def initial_control_points_from_poses(
    times: np.ndarray, target_poses: torch.Tensor, dt: float, t0: float, n_ctrl: int, convention: str = "paper",
    knots: Optional[np.ndarray] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Initial control points from discrete poses: nearest-in-time rotation, linearly interpolated
    translation, both at :func:`control_point_times` (constant extrapolation beyond the data).

    Args:
        times: (K,) float64 seconds; target_poses: (K, 4, 4) camera-to-world.

    Returns:
        rotations (N, 3, 3), translations (N, 3) in target_poses' dtype and device.
    """
    check_float64_seconds("times", times)
    times = np.asarray(times, dtype=np.float64)
    order = np.argsort(times)
    ctrl_times = control_point_times(n_ctrl, dt, t0, convention, knots)
    nearest = order[np.abs(times[order][None, :] - ctrl_times[:, None]).argmin(axis=1)]  # (N,)
    rotations = target_poses[torch.as_tensor(nearest, device=target_poses.device), :3, :3]
    positions = target_poses[:, :3, 3].detach().cpu().double().numpy()[order]  # (K, 3)
    translations = np.stack([np.interp(ctrl_times, times[order], positions[:, c]) for c in range(3)], -1)
    return rotations.clone(), torch.as_tensor(translations).to(target_poses)


def fit_control_points(
    times: np.ndarray,
    target_poses: torch.Tensor,
    dt: float,
    t0: float,
    n_ctrl: int,
    init_rotations: Optional[torch.Tensor] = None,
    init_translations: Optional[torch.Tensor] = None,
    fixed: Optional[torch.Tensor] = None,
    iters: int = 100,
    convention: str = "paper",
    tolerance: float = 1e-12,
    knots: Optional[np.ndarray] = None,
    report: Optional[dict] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Curve approximation, Eq. (11): control points whose spline best matches discrete poses.

    minimise Σ_k ‖Log(R_kᵀ R(t_k))‖² + ‖t_k − t(t_k)‖² over the free control points.

    Method: Levenberg-Marquardt (float64, Jacobian by ``torch.func.jacrev``) on a tangent increment
    per free control point, R_j ← Exp(δ_j) R_j (left) and t_j ← t_j + τ_j; the translation part is
    linear, so one step solves it.  A point no time touches keeps its initial value (damping).
    Stops after ``iters`` steps, at a step norm below ``tolerance`` or when no damped step helps.

    Initialisation (when no init is given): :func:`initial_control_points_from_poses`, i.e. each
    control point from the pose at the time it dominates (paper: t_{k+1}), not at its own knot
    time t_k, which would make the curve lag by one Δt.

    Args:
        times: (K,) float64 seconds, all inside the spline domain.
        target_poses: (K, 4, 4) camera-to-world poses.
        dt, t0, n_ctrl, convention: the spline layout.
        init_rotations, init_translations: (N, 3, 3), (N, 3) starting values (required for
            fixed points); missing ones come from the poses.
        fixed: (N,) bool mask of control points kept at their initial value.
        iters: maximum LM iterations; ``report``, a dict, receives ``"iterations"``: those run.
        knots: (N + 2,) knot vector of a non-uniform spline (:mod:`tsslam_ref.knots`), for dt, t0, convention.

    Returns:
        rotations (N, 3, 3), translations (N, 3) in target_poses' dtype and device (detached).

    Differs from: Eq. (11) sums unsquared norms; we square them (same minimiser for exact data, less robust).
    """
    times = float64_seconds(times, "times").reshape(-1)  # dt and t0 are checked by the segment rule
    if target_poses.shape != (times.shape[0], 4, 4):
        raise ValueError(f"target_poses must be ({times.shape[0]}, 4, 4) to match times, got {tuple(target_poses.shape)}")
    out_dtype, device = target_poses.dtype, target_poses.device
    first, weights = _segment_weights(times, n_ctrl, dt, t0, convention, knots, device)  # raises off the domain
    fixed = _fixed_mask(fixed, n_ctrl, device)
    rotations, translations = _starting_control_points(times, target_poses, dt, t0, n_ctrl, convention,
                                                       init_rotations, init_translations, fixed, knots)
    free = (~fixed).nonzero().reshape(-1)  # (F,)
    iterations = 0
    if free.shape[0] > 0:
        residuals = _pose_residuals(target_poses, free, first, weights)
        rotations, translations, iterations = _levenberg_marquardt(residuals, rotations, translations, free, iters,
                                                                   tolerance)
    if report is not None:
        report["iterations"] = iterations
    return rotations.to(out_dtype), translations.to(out_dtype)


def _segment_weights(times: np.ndarray, n_ctrl: int, dt: float, t0: float, convention: str,
                     knots: Optional[np.ndarray], device: torch.device) -> Tuple[torch.Tensor, CumulativeWeights]:
    """Each time's segment (K,) int64 and its cumulative weights B_1..B_3 ((K, 3, 1) float64 on
    ``device``), fixed during the fit: uniform (dt, t0, convention) or from the knot vector;
    ValueError off the domain."""
    if knots is None:
        first, u, _ = locate_segments(times, n_ctrl, dt, t0, convention)
        return first, uniform_weights(u.to(device=device, dtype=torch.float64), dt, 0)
    knots = knots_module.check_knots(knots, n_ctrl)
    first, u, _ = knots_module.locate(times, knots)
    knots_t = torch.as_tensor(knots, dtype=torch.float64, device=device)
    return first, knots_module.cumulative_weights(knots_t, first.to(device), u.to(device), 0)


def _fixed_mask(fixed: Optional[torch.Tensor], n_ctrl: int, device: torch.device) -> torch.Tensor:
    """(N,) bool mask of control points kept at their initial value (None = none fixed)."""
    if fixed is None:
        fixed = torch.zeros(n_ctrl, dtype=torch.bool)
    fixed = torch.as_tensor(fixed, dtype=torch.bool).reshape(-1).to(device)
    if fixed.shape[0] != n_ctrl:
        raise ValueError(f"fixed mask must have n_ctrl={n_ctrl} entries, got {fixed.shape[0]}")
    return fixed


def _starting_control_points(times: np.ndarray, target_poses: torch.Tensor, dt: float, t0: float, n_ctrl: int,
                             convention: str, init_rotations: Optional[torch.Tensor],
                             init_translations: Optional[torch.Tensor], fixed: torch.Tensor,
                             knots: Optional[np.ndarray] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """The LM start, float64 copies: the given values, else :func:`initial_control_points_from_poses`.

    Returns rotations (N, 3, 3) and translations (N, 3); fixed points require given values.
    """
    device, work = target_poses.device, torch.float64
    guess_R, guess_p = initial_control_points_from_poses(times, target_poses.detach(), dt, t0, n_ctrl, convention,
                                                         knots)
    if bool(fixed.any()) and (init_rotations is None or init_translations is None):
        raise ValueError("fixed control points need init_rotations and init_translations")
    rotations = (init_rotations if init_rotations is not None else guess_R).detach().to(device, work).clone()
    translations = (init_translations if init_translations is not None else guess_p).detach().to(device, work).clone()
    return rotations, translations


def _pose_residuals(target_poses: torch.Tensor, free: torch.Tensor, first: torch.Tensor, weights: CumulativeWeights):
    """Eq. (11)'s residual function for :func:`_levenberg_marquardt`.

    The returned function maps control points and (F, 6) increments [δ, τ] of the free ones to the
    (K*6,) stacked rotation residuals Log(R_kᵀ R(t_k)) and translation residuals t_k − t(t_k).
    """
    target_R = target_poses[:, :3, :3].detach().to(torch.float64)
    target_p = target_poses[:, :3, 3].detach().to(torch.float64)

    def residuals(rotations: torch.Tensor, translations: torch.Tensor, increments: torch.Tensor) -> torch.Tensor:
        R = rotations.index_copy(0, free, so3_exp(increments[:, :3]) @ rotations[free])
        p = translations.index_copy(0, free, translations[free] + increments[:, 3:])
        sample = evaluate_weights(R, p, first, weights, 0)
        rot_res = so3_log(target_R.transpose(-1, -2) @ sample.rotation)  # (K, 3)
        return torch.cat([rot_res, target_p - sample.translation], dim=-1).reshape(-1)

    return residuals


def _levenberg_marquardt(residual_fn, rotations: torch.Tensor, translations: torch.Tensor, free: torch.Tensor,
                         iters: int, tolerance: float) -> Tuple[torch.Tensor, torch.Tensor, int]:
    """Levenberg-Marquardt over the free control points' increments, left increments on SO(3).

    ``residual_fn(rotations, translations, increments (F, 6))`` -> (K*6,).  Damping starts at 1e-6
    (times diag(JᵀJ) + 1e-9 I), x10 on a rejected step, /10 on an accepted one; stops after
    ``iters`` steps, when no step lowers the cost, or when the step norm is below ``tolerance``.
    Returns the control points and the iterations run (Jacobians evaluated).
    """
    work, device, n_free = rotations.dtype, rotations.device, free.shape[0]

    def residuals(increments: torch.Tensor) -> torch.Tensor:
        return residual_fn(rotations, translations, increments)

    damping = 1e-6
    zero = torch.zeros(n_free, 6, dtype=work, device=device)
    iterations = 0
    for iterations in range(1, iters + 1):
        r = residuals(zero)
        J = torch.func.jacrev(residuals)(zero).reshape(r.shape[0], -1)  # (K*6, F*6)
        JtJ, Jtr = J.T @ J, J.T @ r
        cost = float(r @ r)
        while True:
            H = JtJ + damping * (torch.diag(torch.diagonal(JtJ)) + 1e-9 * torch.eye(JtJ.shape[0], dtype=work, device=device))
            step = -torch.linalg.solve(H, Jtr).reshape(n_free, 6)
            new_cost = float((residuals(step) ** 2).sum())
            if new_cost <= cost or damping > 1e10:
                break
            damping *= 10.0
        if new_cost > cost:
            break
        damping = max(damping / 10.0, 1e-12)
        rotations = rotations.index_copy(0, free, so3_exp(step[:, :3]) @ rotations[free])
        translations = translations.index_copy(0, free, translations[free] + step[:, 3:])
        if float(torch.linalg.vector_norm(step)) < tolerance:
            break
    return rotations, translations, iterations


def fit_trajectory(
    times: np.ndarray, poses: torch.Tensor, dt: float, convention: str = "paper", iters: int = 100,
    boundaries: Optional[np.ndarray] = None,
) -> BSplineTrajectory:
    """The spline of knot spacing ``dt`` closest to a whole discrete trajectory (Eq. (11), every point free).

    Layout as in the system: the domain starts at the first time, t0 = t_first − 2Δt (paper
    convention; basalt t0 = t_first), and N = 3 + ⌈(t_last − t_first)/Δt⌉ control points (at least 4)
    so that it reaches the last time (within ``evaluate``'s closed domain: a last time exactly
    k Δt after the first sits on its end, outside the loop's half-open ``covers``).  Puts any
    discrete trajectory - the Co-SLAM baseline's, ground truth - on the curve TS-SLAM uses
    (benchmarks/bench_system.py's offline control row).  The Levenberg-Marquardt system is dense,
    (6K x 6N) for K poses: meant for hundreds of frames.

    Args:
        times: (K,) float64 seconds, increasing; poses: (K, 4, 4) camera-to-world.
        boundaries: optional (m + 1,) interval boundaries e_0 = times[0] < ... < e_m, e_m > times[-1]
            (s), e.g. from :func:`tsslam_ref.knot_policy.place_knots`: a non-uniform spline with
            these intervals (m + 3 control points; ``dt`` spaces the knots outside them).

    Returns:
        the fitted :class:`trajectory.BSplineTrajectory` (poses' dtype and device).
    """
    check_float64_seconds("times", times)
    check_float64_seconds("dt", dt)
    if boundaries is not None:
        return _fit_on_boundaries(np.asarray(times, dtype=np.float64).reshape(-1), poses, dt, convention, iters,
                                  boundaries)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if times.shape[0] < 2 or not np.all(np.diff(times) > 0):
        raise ValueError(f"fit_trajectory needs at least 2 strictly increasing times, got {times.shape[0]} "
                         f"({'not increasing' if times.shape[0] >= 2 else 'too few'})")
    offset = first_segment_offset(convention)
    if not dt > 0:
        raise ValueError(f"knot spacing dt must be > 0 s, got {dt}")
    intervals = max(1, math.ceil((times[-1] - times[0]) / dt - 1e-9))  # k dt up to rounding: k intervals
    n_ctrl, t0 = 3 + intervals, float(times[0]) - offset * dt
    if not time_in_domain(times[-1:], n_ctrl, dt, t0, convention)[0]:  # a last time just past k dt: one more
        n_ctrl += 1
    rotations, translations = fit_control_points(times, poses, dt, t0, n_ctrl, iters=iters, convention=convention)
    return BSplineTrajectory(rotations, translations, dt, t0, convention)


def _fit_on_boundaries(times: np.ndarray, poses: torch.Tensor, dt: float, convention: str, iters: int,
                       boundaries) -> BSplineTrajectory:
    """:func:`fit_trajectory` on a knot vector built from interval boundaries (s)."""
    knot_vector = knots_module.knots_from_boundaries(boundaries, dt)
    if not (knot_vector[2] <= times[0] and times[-1] < knot_vector[-3]):
        raise ValueError(f"the boundaries span [{knot_vector[2]!r}, {knot_vector[-3]!r}) s but the times run "
                         f"from {times[0]!r} to {times[-1]!r} s")
    n_ctrl, knot_offset = knot_vector.shape[0] - 2, first_segment_offset(convention) - 2
    rotations, translations = fit_control_points(times, poses, dt, 0.0, n_ctrl, iters=iters, knots=knot_vector)
    return BSplineTrajectory(rotations, translations, dt, float(knot_vector[-knot_offset]), convention,
                             knots=knot_vector, knot_offset=knot_offset)


def first_control_point(
    control_rotations: torch.Tensor,
    control_translations: torch.Tensor,
    start_rotation: torch.Tensor,
    start_translation: torch.Tensor,
    weights: Optional[Tuple[float, float]] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Control point 0 that makes the curve start at a given pose, from control points 1 and 2.

    At the start of the domain (first segment, u = 0) the cumulative weights are
    B̃(0) = (1, 5/6, 1/6, 0), so with d_j = Log(R_{j−1}ᵀ R_j)

        t(t_min) = (t_0 + 4 t_1 + t_2) / 6,   R(t_min) = R_0 Exp(5/6 d_1) Exp(1/6 d_2).

    Solving for control point 0 (R_0 = R_1 Exp(−d_1), so R_0 Exp(5/6 d_1) = R_1 Exp(−d_1 / 6)):

        t_0 = 6 t_start − 4 t_1 − t_2,   R_0 = R_1 Exp(6 Log(R_1ᵀ R_start Exp(−d_2 / 6))).

    Same formula for both index conventions (it is the first segment's start either way).  The
    Log in it is −d_1/6, so the factor 6 inverts Exp while |d_1| < π, i.e. while control points 0
    and 1 are less than 180° apart (a knot interval's rotation is far less).  Differentiable in
    control points 1 and 2, which is how local and global BA keep frame 0's pose fixed while every
    other control point moves (the gauge Co-SLAM fixes by holding keyframe 0).

    Non-uniform knots (:mod:`tsslam_ref.knots`): with the start weights (B̃_1, B̃_2) of
    :func:`tsslam_ref.knots.start_weights` and N_0 = 1 − B̃_1 in place of (5/6, 1/6) and 1/6,

        t_0 = (t_start − (B̃_1 − B̃_2) t_1 − B̃_2 t_2) / N_0,   R_0 = R_1 Exp(Log(R_1ᵀ R_start Exp(−B̃_2 d_2)) / N_0).

    Args:
        control_rotations: (N, 3, 3), N >= 3 (only rows 1 and 2 are read).
        control_translations: (N, 3).
        start_rotation: (3, 3) and start_translation: (3,), the pose the curve must start at.
        weights: (B̃_1, B̃_2) at the domain start; None: equally spaced knots, (5/6, 1/6).

    Returns:
        R_0 (3, 3), t_0 (3,) in the control points' dtype.
    """
    if control_rotations.shape[0] < 3:
        raise ValueError(f"first_control_point needs control points 1 and 2, got {control_rotations.shape[0]} points")
    rotation_1, rotation_2 = control_rotations[1], control_rotations[2]
    start_rotation = start_rotation.to(control_rotations)
    d_2 = so3_log(rotation_1.transpose(-1, -2) @ rotation_2)  # (3,)
    start_translation = start_translation.to(control_translations)
    if weights is None:  # the uniform formula, kept literally so that uniform runs keep their numbers bit for bit
        target = start_rotation @ so3_exp(-d_2 / 6.0)  # = R_1 Exp(-d_1 / 6)
        rotation_0 = rotation_1 @ so3_exp(6.0 * so3_log(rotation_1.transpose(-1, -2) @ target))
        translation_0 = 6.0 * start_translation - 4.0 * control_translations[1] - control_translations[2]
        return rotation_0, translation_0
    weight_1, weight_2 = weights
    weight_0 = 1.0 - weight_1  # N_0, the plain weight of point 0
    target = start_rotation @ so3_exp(-weight_2 * d_2)  # = R_1 Exp(-N_0 d_1)
    rotation_0 = rotation_1 @ so3_exp(so3_log(rotation_1.transpose(-1, -2) @ target) / weight_0)
    translation_0 = (start_translation - (weight_1 - weight_2) * control_translations[1]
                     - weight_2 * control_translations[2]) / weight_0
    return rotation_0, translation_0


def pin_first_control_point(
    control_rotations: torch.Tensor, control_translations: torch.Tensor, start_pose: Optional[torch.Tensor],
    weights: Optional[Tuple[float, float]] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """The control points with point 0 replaced by :func:`first_control_point` for ``start_pose``.

    Args:
        control_rotations: (N, 3, 3); control_translations: (N, 3).
        start_pose: (4, 4) camera-to-world pose the curve must start at, or None (nothing changes;
            neither does anything with fewer than 3 points).
        weights: the start weights of non-uniform knots (:func:`tsslam_ref.knots.start_weights`), None when uniform.

    Returns:
        (N, 3, 3), (N, 3), differentiable in control points 1 and 2.
    """
    if start_pose is None or control_rotations.shape[0] < 3:
        return control_rotations, control_translations
    rotation_0, translation_0 = first_control_point(control_rotations, control_translations,
                                                    start_pose[:3, :3], start_pose[:3, 3], weights)
    return (torch.cat([rotation_0.unsqueeze(0), control_rotations[1:]], dim=0),
            torch.cat([translation_0.unsqueeze(0), control_translations[1:]], dim=0))
