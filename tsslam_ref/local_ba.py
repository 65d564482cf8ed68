"""Local bundle adjustment over a sliding window of B-spline control points.

TS-SLAM Sec. III-D "Local Bundle Adjustment" and Fig. 4.  Every ``dt`` of sequence time (one
control-point interval) the mapping step runs, coarse to fine:

1. **Curve approximation** (Eq. 11, :func:`curve_approximation`): the new control point
   Phi_{i+1} from the tracked poses {T_i^k} of the newest interval [t_i, t_{i+1}), by least
   squares on ||Log(R_i^k^T R(t_i^k))|| and ||t_i^k - t(t_i^k)||.
2. **Refinement with the map frozen** (:func:`refine_window`): the ``M`` newest control points on
   the rays of every frame inside the window plus the dynamics regulariser L_DR sampled uniformly
   inside the window (Eq. 10).
3. **Joint refinement** (:func:`joint_window`): the window's keyframes (every fifth frame), the
   window's control points and the map optimised together.

Deviations (ours; measurements in docs/system.md, "Choices the paper leaves open"):

* the first interval is a constant-velocity fit (:func:`constant_velocity_control_points`);
* a new point starts at the extrapolated control polygon and the ``local_ba.fit_controls`` newest
  points are fitted, not the new one alone ("The curve approximation rings");
* control point 0 follows points 1 and 2 (:data:`N_ANCHOR_CONTROLS`), the gauge;
* stage 3 is off by default, ``local_ba.joint_iters = 0`` ("TS-SLAM's ATE on clean synthetic data");
* the curve approximation's Levenberg-Marquardt fit runs on the CPU whatever the map's device: its
  many small float64 operations are each a kernel launch on a GPU (one H200: 655 ms per fit, against
  about 130-180 ms on two CPU cores; README, "On a GPU").

Index convention: the paper's (:mod:`tsslam_ref.trajectory`).  Control point k sits at t0 + k dt
and shapes times [t_{k-1}, t_{k+3}); the window of the ``M`` newest points N-M..N-1 therefore
acts on [t_{N-M-1}, t_{N-1}) (Fig. 4: the RGB-D observations in [t_{i+1-M}, t_{i+1})).

Ablations of paper Table V: ``local_ba.use_spline=False`` ("w/o B-S.",
:func:`refine_discrete_window`) runs the window stages on discrete per-frame poses;
``local_ba.enabled=False`` ("w/o LBA") keeps only the extrapolated control point;
``local_ba.use_dynamics=False`` ("w/o DR") drops L_DR.

Variable intervals: every time range here comes from the trajectory's own knot times
(:meth:`trajectory.BSplineTrajectory.knot_time`).  With non-uniform knots the window is held in
time, not in points (:func:`window_size`): it takes the fewest newest control points, at least
``M``, whose range spans ``M dt`` seconds, so short intervals add points to the window instead of
shrinking the stretch of frames it refines (docs/system.md, "Adaptive knots").

Layer 3 (optimiser): uses trajectory, knots, spline_fit, losses (its settings type), bundle; never
tracking or global_ba.
Taught in notebooks/06_local_ba.ipynb.
"""

from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch

from . import knots as knots_module
from . import spline_fit
from .bundle import BAStats, DiscretePoses, KeyframeDatabase, SplinePoses, dynamics_term, joint_optimization, slotted
from .config import DynamicsConfig, LocalBAConfig
from .geometry import orthonormalize, so3_exp, so3_log
from .losses import RenderLossSettings
from .render import RayBatch
from .times import float64_seconds
from .trajectory import BSplineTrajectory


N_ANCHOR_CONTROLS = 1
"""Control points never free in BA: point 0 follows points 1 and 2 so that the curve keeps starting
at frame 0's pose (:attr:`trajectory.BSplineTrajectory.start_pose`,
:func:`spline_fit.first_control_point`), the gauge Co-SLAM fixes by holding keyframe 0 (docs/system.md,
"Choices the paper leaves open")."""


def window_size(trajectory: BSplineTrajectory, window: int) -> int:
    """M, the number of control points in the window: ``window`` with uniform knots; with
    non-uniform knots the fewest newest points, at least ``window``, whose range [t_{N-M-1}, t_{N-1})
    spans ``window`` x dt seconds (dt: ``trajectory.dt``, the configured spacing), so that the
    window refines as long a stretch of frames as a uniform one does (all points when they span less)."""
    if trajectory.uniform:
        return window
    return intervals_spanning(trajectory, trajectory.n_ctrl - 1, window, trajectory.n_ctrl - N_ANCHOR_CONTROLS)


def intervals_spanning(trajectory: BSplineTrajectory, end_knot: int, count: int, most: int) -> int:
    """The fewest m >= ``count`` (at most ``most``) with t_end - t_{end-m} >= ``count`` x dt
    (dt: ``trajectory.dt``): how many intervals ending at knot ``end_knot`` span as many seconds as
    ``count`` uniform ones.  :func:`window_size` and :func:`fit_size` hold their stretch in time with it."""
    end, span, size = trajectory.knot_time(end_knot), count * trajectory.dt, count
    while size < most and end - trajectory.knot_time(end_knot - size) < span - 1e-9:
        size += 1
    return size


def window_controls(trajectory: BSplineTrajectory, window: int) -> List[int]:
    """Indices of the :func:`window_size` newest control points, never the ``N_ANCHOR_CONTROLS`` oldest."""
    return list(range(max(N_ANCHOR_CONTROLS, trajectory.n_ctrl - window_size(trajectory, window)), trajectory.n_ctrl))


def window_time_range(trajectory: BSplineTrajectory, window: int) -> Tuple[float, float]:
    """Times (s) shaped by the window's control points, clipped to the domain: [t_{N-M-1}, t_{N-1})
    (M = :func:`window_size`)."""
    start, end = trajectory.domain()
    first = max(N_ANCHOR_CONTROLS, trajectory.n_ctrl - window_size(trajectory, window))
    return max(start, trajectory.knot_time(first - 1)), end


def extrapolate_control_point(trajectory: BSplineTrajectory) -> Tuple[torch.Tensor, torch.Tensor]:
    """(3, 3), (3,): the control polygon continued at constant velocity,
    R_N = R_{N-1} R_{N-2}^T R_{N-1}, t_N = 2 t_{N-1} - t_{N-2} (the last point when N < 2).

    R_N is projected back onto SO(3) (:func:`geometry.orthonormalize`).  The curve approximation
    fits each new point by left increments Exp(δ) R, which keep whatever R_N's columns carry off
    SO(3), and the next point is built from this one: without the projection the drift of float32
    products (about 1e-7) grows by 1 + √2 ≈ 2.4 per control point (e_N ≈ 2 e_{N-1} + e_{N-2}):
    measured max |RᵀR − I| of 1e-6 at point 6, 1e-3 at point 13, 2 at point 21 and 4e38 at point 26.
    """
    rotations, translations = trajectory.control_rotations, trajectory.control_translations
    if trajectory.n_ctrl < 2:
        return rotations[-1].clone(), translations[-1].clone()
    r_prev, r_last = rotations[-2], rotations[-1]
    t_prev, t_last = translations[-2], translations[-1]
    return orthonormalize(r_last @ r_prev.transpose(-1, -2) @ r_last), 2.0 * t_last - t_prev


def constant_velocity_control_points(trajectory: BSplineTrajectory, times: np.ndarray, poses: torch.Tensor
                                     ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Four control points whose spline is the least-squares constant-velocity fit of the poses.

    With P_k = c + v dt (k - 1) and R_k = R_first Exp((k - 1) w dt) the paper-convention spline
    is exactly p(t) = c + v (t - t_first), R(t) = R_first Exp(w (t - t_first)) (a cubic B-spline
    reproduces a linear function of time, and equal rotation steps give a constant rate), so
    fitting the velocity v and the body rate w to the first interval's poses is a linear,
    well-conditioned problem, whereas four free points fitted to one segment's noisy poses swing
    far off (a cubic extrapolated from a fraction of a second of data).  The line starts at the
    first pose (c = p_first, R_first its rotation): the spline then passes exactly through frame
    0's pose, which anchors the map as in Co-SLAM; the trajectory's ``start_pose`` keeps it there.

    Args:
        trajectory: the empty trajectory (its timing).
        times: (K,) float64 s, the first interval's frames (the first is frame 0).
        poses: (K, 4, 4) their camera-to-world poses.

    Returns:
        (4, 3, 3) rotations and (4, 3) translations in the poses' dtype.
    """
    first_time = trajectory.interval(0)[0]
    elapsed = torch.as_tensor(float64_seconds(times, "times") - first_time, device=poses.device)  # (K,)
    positions = poses[:, :3, 3].double()  # (K, 3)
    offset = positions[0]  # c: the line starts at the first pose
    first_rotation = poses[0, :3, :3].double()
    rotvecs = so3_log(first_rotation.transpose(-1, -2).unsqueeze(0) @ poses[:, :3, :3].double())  # (K, 3) body
    weight = elapsed.square().sum()  # least squares through the origin: x = sum(e y) / sum(e^2)
    if float(weight) > 0:
        velocity = (elapsed[:, None] * (positions - offset)).sum(0) / weight
        rate = (elapsed[:, None] * rotvecs).sum(0) / weight
    else:
        velocity = rate = torch.zeros(3, dtype=torch.float64, device=poses.device)
    translations = offset + line_at_control_points(trajectory, velocity)  # (4, 3)
    rotations = first_rotation @ so3_exp(line_at_control_points(trajectory, rate))  # (4, 3, 3)
    return rotations.to(poses.dtype), translations.to(poses.dtype)


def line_at_control_points(trajectory: BSplineTrajectory, rate: torch.Tensor) -> torch.Tensor:
    """(4, 3) float64: ``rate`` (3,) times each of the first four control points' time after the
    first frame, where a line's control points sit: (k - 1) dt when uniform, else the Greville
    abscissae of the trajectory's own knots minus the first interval's start
    (:func:`knots.greville_times`)."""
    if trajectory.uniform:
        k = torch.arange(4, dtype=torch.float64, device=rate.device)[:, None] - 1.0  # (4, 1)
        return rate * trajectory.dt * k  # this order of products, as the uniform loop always had
    greville = knots_module.greville_times(trajectory.knot_vector(4)) - trajectory.interval(0)[0]
    return rate * torch.as_tensor(greville, dtype=torch.float64, device=rate.device)[:, None]


def curve_approximation(trajectory: BSplineTrajectory, times: np.ndarray, poses: torch.Tensor,
                        local_ba: LocalBAConfig, fit: bool = True,
                        free_controls: Optional[int] = None, report: Optional[dict] = None) -> BSplineTrajectory:
    """Add the control point of the next interval, Eq. (11).

    First interval: the four points of :func:`constant_velocity_control_points`, and frame 0's
    pose becomes the start pose.  Later: the new point is the extrapolated control polygon
    (:func:`extrapolate_control_point`), then the ``local_ba.fit_controls`` newest points are
    fitted to the poses by Levenberg-Marquardt (:func:`spline_fit.fit_control_points`), the older ones
    fixed, and point 0 is re-pinned to the start pose.  Eq. (11) fits the new point alone; why we
    fit more: docs/system.md, "The curve approximation rings".

    Args:
        trajectory: the trajectory so far.
        times: (K,) float64 timestamps of the frames to fit (:func:`fit_time_range`).
        poses: (K, 4, 4) their camera-to-world poses (tracked, or spline-refined for older frames).
        local_ba: uses ``fit_iters`` and ``fit_controls``.
        fit: False only extrapolates (the "w/o LBA" ablation).
        free_controls: how many newest points to fit (default ``local_ba.fit_controls``; the loop
            passes :func:`fit_size`).
        report: a dict that receives ``"iterations"``, the Levenberg-Marquardt iterations run
            (0 when nothing is fitted).

    Returns:
        A new trajectory with 4 control points (first interval) or one more, detached.
    """
    poses, times = poses.detach(), float64_seconds(times, "times")
    free_controls = local_ba.fit_controls if free_controls is None else int(free_controls)
    if free_controls < 0:
        raise ValueError(f"free_controls must be >= 0, got {free_controls}")
    start_pose = trajectory.start_pose
    if report is not None:
        report["iterations"] = 0
    if trajectory.n_ctrl == 0:
        if len(times) == 0:
            raise ValueError("the first spline interval holds no frame")
        rotations, translations = constant_velocity_control_points(trajectory, times, poses)
        start_pose = poses[0].clone()
    else:
        new_rotation, new_translation = extrapolate_control_point(trajectory)
        rotations = torch.cat([trajectory.control_rotations, new_rotation.unsqueeze(0)], dim=0)
        translations = torch.cat([trajectory.control_translations, new_translation.unsqueeze(0)], dim=0)
        if fit and len(times) > 0:
            fixed = torch.ones(rotations.shape[0], dtype=torch.bool)
            fixed[max(rotations.shape[0] - free_controls, 0):] = False  # 0 frees none (fixed[-0:] is all)
            fixed[:N_ANCHOR_CONTROLS] = True
            device = rotations.device  # fitted on the CPU (module docstring); nothing moves on a CPU run
            rotations, translations = spline_fit.fit_control_points(
                times, poses.cpu(), trajectory.dt, trajectory.t0, rotations.shape[0],
                init_rotations=rotations.cpu(), init_translations=translations.cpu(), fixed=fixed,
                iters=local_ba.fit_iters, convention=trajectory.convention,
                knots=None if trajectory.uniform else trajectory.knot_vector(rotations.shape[0]), report=report)
            rotations, translations = spline_fit.pin_first_control_point(rotations.to(device), translations.to(device),
                                                                         start_pose, trajectory.start_weights())
    return BSplineTrajectory(rotations.detach().to(poses.dtype), translations.detach().to(poses.dtype),
                             trajectory.dt, trajectory.t0, trajectory.convention, start_pose, **trajectory.timing())


def fit_size(trajectory: BSplineTrajectory, n: int, fit_controls: int) -> int:
    """How many newest intervals (ending with interval n) the curve approximation fits, and how many
    newest control points it frees: ``fit_controls`` with uniform knots; with non-uniform knots the
    fewest, at least ``fit_controls``, that span ``fit_controls`` x dt seconds (dt: ``trajectory.dt``),
    at most every point but the anchor.  ``trajectory``: before interval n's point is added.  Held
    in time for the reason :func:`window_size` is: short intervals free more points instead of
    fitting fewer frames."""
    if trajectory.uniform:
        return fit_controls
    return intervals_spanning(trajectory, trajectory.interval_start_knot(n) + 1, fit_controls,
                              trajectory.n_ctrl + 1 - N_ANCHOR_CONTROLS)


def fit_time_range(trajectory: BSplineTrajectory, n: int, local_ba: LocalBAConfig) -> Tuple[float, float]:
    """[start, end) in s of the frames :func:`curve_approximation` fits when mapping interval ``n``:
    interval n and the :func:`fit_size` - 1 before it (``local_ba.fit_controls`` - 1 with uniform knots)."""
    size = fit_size(trajectory, n, local_ba.fit_controls)
    first_start = trajectory.knot_time_before(trajectory.interval_start_knot(n), size - 1)
    end = trajectory.interval(n)[1]
    return max(trajectory.interval(0)[0], first_start), end


def window_dynamics_range(trajectory: BSplineTrajectory, local_ba: LocalBAConfig) -> Optional[Tuple[float, float]]:
    """Where local BA samples L_DR: the window's time range, or None with ``local_ba.use_dynamics`` off."""
    return window_time_range(trajectory, local_ba.window) if local_ba.use_dynamics else None


def refine_window(field_model: torch.nn.Module, trajectory: BSplineTrajectory, frame_times: np.ndarray,
                  frame_rays: Sequence[RayBatch], local_ba: LocalBAConfig, dynamics: DynamicsConfig,
                  loss_settings: RenderLossSettings, generator: Optional[torch.Generator] = None
                  ) -> Tuple[BSplineTrajectory, BAStats]:
    """Stage 2: the window's control points on the window frames' rays, map frozen, L_DR in the window.

    Args:
        field_model: the scene field (frozen here).
        trajectory: the trajectory with the new control point.
        frame_times: (F,) float64 times of the frames whose rays are given (inside the window).
        frame_rays: F ray batches (any ``frame_ids``; relabelled to slots here).
        local_ba: ``window``, ``n_rays``, ``refine_iters``, learning rates, ``use_dynamics``.
        dynamics: the limits of L_DR.
        loss_settings: rendering and loss settings of ``losses.render_loss``.
        generator: random generator for ray draws, depth-sample jitter and L_DR sample times.

    Returns:
        The refined trajectory (detached) and the optimisation record.
    """
    poses = SplinePoses(trajectory, window_controls(trajectory, local_ba.window), frame_times,
                        trajectory.poses(frame_times), local_ba.lr_rot, local_ba.lr_trans)
    extra = dynamics_term(poses, window_dynamics_range(trajectory, local_ba), dynamics, generator)
    stats = joint_optimization(field_model, None, [(slotted(frame_rays), local_ba.n_rays)], poses, loss_settings,
                               local_ba.refine_iters, generator, extra_loss=extra, optimise_map=False,
                               pose_accum_step=1)
    return poses.trajectory().detach(), stats


def joint_window(field_model: torch.nn.Module, map_optimizer: torch.optim.Optimizer, trajectory: BSplineTrajectory,
                 keyframes: KeyframeDatabase, local_ba: LocalBAConfig, dynamics: DynamicsConfig,
                 loss_settings: RenderLossSettings, generator: Optional[torch.Generator] = None
                 ) -> Tuple[BSplineTrajectory, Optional[BAStats]]:
    """Stage 3: the window's keyframes, jointly with the map (control points in the window move).

    ``local_ba``, ``dynamics``, ``loss_settings`` and ``generator`` as in :func:`refine_window`
    (``joint_iters`` instead of ``refine_iters``).  Returns the trajectory unchanged (and None)
    when ``local_ba.joint_iters`` is 0 or no keyframe lies in the window."""
    if local_ba.joint_iters <= 0:
        return trajectory, None
    time_range = window_time_range(trajectory, local_ba.window)
    kf_times = np.asarray(keyframes.timestamps, dtype=np.float64)
    slots = [s for s, t in enumerate(kf_times) if time_range[0] <= t < time_range[1]]
    if not slots:
        return trajectory, None
    times = kf_times[slots]
    poses = SplinePoses(trajectory, window_controls(trajectory, local_ba.window), times, trajectory.poses(times),
                        local_ba.lr_rot, local_ba.lr_trans)
    extra = dynamics_term(poses, window_dynamics_range(trajectory, local_ba), dynamics, generator)
    stats = joint_optimization(field_model, map_optimizer, [(keyframes.rays(slots), local_ba.n_rays)], poses,
                               loss_settings, local_ba.joint_iters, generator, extra_loss=extra, pose_accum_step=1)
    return poses.trajectory().detach(), stats


def refine_discrete_window(field_model: torch.nn.Module, map_optimizer: torch.optim.Optimizer, poses: torch.Tensor,
                           frame_rays: Sequence[RayBatch], keyframe_mask: Sequence[bool], local_ba: LocalBAConfig,
                           loss_settings: RenderLossSettings, generator: Optional[torch.Generator] = None
                           ) -> torch.Tensor:
    """The "w/o B-S." ablation: stages 2 and 3 on discrete per-frame poses (no spline, no L_DR).

    Args:
        poses: (F, 4, 4) tracked poses of the window's frames.
        frame_rays: their rays.  keyframe_mask: (F,) which of them are keyframes.
        local_ba: ``n_rays``, ``refine_iters``, ``joint_iters`` and the learning rates.
        loss_settings: rendering and loss settings of ``losses.render_loss``.

    Returns:
        (F, 4, 4) refined poses.
    """
    fixed = torch.zeros(len(frame_rays), dtype=torch.bool)
    model = DiscretePoses(poses, fixed, local_ba.lr_rot, local_ba.lr_trans)
    pool = slotted(frame_rays)
    joint_optimization(field_model, None, [(pool, local_ba.n_rays)], model, loss_settings, local_ba.refine_iters,
                       generator, optimise_map=False, pose_accum_step=1)
    keyframe_slots = [slot for slot, is_kf in enumerate(keyframe_mask) if is_kf]
    if keyframe_slots and local_ba.joint_iters > 0:
        kf_pool = RayBatch.cat([pool.subset(torch.nonzero(pool.frame_ids == slot).squeeze(1)) for slot in keyframe_slots])
        joint_optimization(field_model, map_optimizer, [(kf_pool, local_ba.n_rays)], model, loss_settings,
                           local_ba.joint_iters, generator, pose_accum_step=1)
    return model.poses().detach()
