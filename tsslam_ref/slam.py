"""The SLAM loop: TS-SLAM as in the paper's Fig. 2, and the Co-SLAM baseline's schedule.

:func:`run_slam` reads like the figure (the baseline follows Co-SLAM's single-process ``coslam.py``):

* **first frame** (:func:`start_map`): its pose is the ground-truth pose when known (Co-SLAM does
  the same, so the map lives in the dataset's world frame and the scene bound applies), else the
  identity; the map is fitted to it for ``mapping.first_iters`` iterations; it becomes keyframe 0.
* **track** every later frame with the map frozen (:func:`track`, ``tracking.py``) from a
  constant-velocity prediction (:func:`motion_prediction`).
* **the method's schedule after tracking** (:func:`after_tracking`):

  - ``method="tsslam"``: the trajectory is a cubic B-spline (``trajectory.py``).  When a frame's
    time passes the end of the newest interval, :func:`map_interval` runs that interval's stages:
    add the control point by curve approximation, local BA in the window, global BA outside it,
    commit with the deviation check (with ``spline.knots="adaptive"`` the end of the next interval
    is decided first, ``knot_schedule.py``).  On every ``mapping.tsslam_map_every``-th frame where no
    interval ends, Co-SLAM's global BA runs on what the spline does not reach yet
    (:func:`tsslam_map_update`, ours; 0 gives the paper's schedule).  Keyframe every
    ``keyframe_every`` frames.
  - ``method="coslam"`` (one pose per frame): global BA every ``map_every`` frames over all
    keyframes + the current frame; keyframe every ``keyframe_every`` frames, added after BA.
    Non-keyframe poses are stored relative to the preceding keyframe (Co-SLAM's ``pose_relative``).

* **finish** (:func:`finish_run`): TS-SLAM maps the last, incomplete interval; the output poses
  are the spline's at the frames' timestamps (``export.py``).

The loop is sequential and, on the CPU, deterministic for a seed; ``parallel.run_slam_in_two_threads`` runs the
same steps in two threads (the caller chooses, as ``run.py`` does).  ``run_slam``'s progress callback lets
the command line show progress, write partial results and checkpoints.

Layer 4 (system): orchestrates; holds only the loop state.  Taught in notebooks/09_full_system.ipynb.
"""

import contextlib
import itertools
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from . import knot_schedule, local_ba
from .bundle import KeyframeDatabase
from .config import Config, validate
from .device import FrameTensors, field_settings_for, frame_to_device, resolve_device, state_on_device
from .export import estimated_trajectory
from .field import SceneField
from .geometry import invert_pose
from .global_ba import CurrentFrame, coslam_global_ba, tsslam_global_ba
from .losses import RenderLossSettings
from .mapping import estimate_bound, fit_map, make_map_optimizer, share_outside_bound
from .render import RayBatch
from .timings import Timings
from .tracking import TrackingResult, check_ray_budget, constant_velocity_init, depth_problem, motion_scale, track_frame
from .trajectory import BSplineTrajectory


class TrackingFailure(RuntimeError):
    """The run cannot go on (non-finite or diverged tracking); the message says where and why."""


@dataclass
class SLAMState:
    """Everything the loop carries from frame to frame (checkpointed by ``run.py``)."""

    cfg: Config
    field: SceneField
    map_optimizer: torch.optim.Optimizer
    keyframes: KeyframeDatabase
    timestamps: np.ndarray  # (N,) float64 seconds of every frame of the sequence
    frame_poses: torch.Tensor  # (N, 4, 4) each frame's current pose: tracked, then updated by BA / the spline
    # the newest two frames' poses exactly as tracking returned them (TS-SLAM's motion_prediction)
    tracking_output: Dict[int, torch.Tensor] = field(default_factory=dict)
    done: int = 0  # frames processed so far
    keyframe_of_frame: Dict[int, int] = field(default_factory=dict)  # frame -> preceding keyframe's frame
    relative_to_keyframe: Dict[int, torch.Tensor] = field(default_factory=dict)  # Co-SLAM pose_relative
    trajectory: Optional[BSplineTrajectory] = None  # TS-SLAM's spline
    intervals_done: int = 0  # TS-SLAM: spline intervals whose mapping step has run
    window_rays: Dict[int, RayBatch] = field(default_factory=dict)  # tracking rays of frames a window may need
    generator: Optional[torch.Generator] = None
    timings: Timings = field(default_factory=Timings)
    log: List[Dict[str, float]] = field(default_factory=list)

    @property
    def loss_settings(self) -> RenderLossSettings:
        """The rendering and loss settings of ``cfg`` that tracking, mapping and BA take."""
        return RenderLossSettings.from_config(self.cfg)


@dataclass
class SLAMResult:
    """What a finished run produced."""

    timestamps: np.ndarray  # (N,) float64 seconds
    poses: np.ndarray  # (N, 4, 4) float64 camera-to-world, OpenCV axes: the method's output
    frame_poses: np.ndarray  # (N, 4, 4) the per-frame poses of the state (tracking, BA, spline)
    state: SLAMState
    frames_per_second: Optional[float]  # over the frames this call processed; None when it processed none
    frames_processed: int  # frames this call processed (fewer than N after a resume)


# ------------------------------------------------------------------------------------------------
# The run


def run_slam(sequence, cfg: Config, device: Optional[torch.device] = None, state: Optional[SLAMState] = None,
             on_frame: Optional[Callable[[SLAMState], None]] = None) -> SLAMResult:
    """Run the whole loop over ``sequence`` (a :class:`tsslam_ref.data.RGBDSequence`), sequentially.

    Args:
        sequence: frames with float64 timestamps; frame 0's ground-truth pose anchors the map.
        cfg: resolved config (``cfg.method`` picks coslam or tsslam).
        device: compute device (default: ``device.resolve_device(cfg.device)``).
        state: a state to resume from (``run.py`` checkpoints); None starts afresh.
        on_frame: called after every frame with the state (progress bars, partial outputs).

    Returns:
        :class:`SLAMResult` with float64 camera-to-world poses for every frame.
    """
    state, device, dtype = prepare_run(sequence, cfg, device, state)
    start, first_new = time.perf_counter(), state.done
    for i in range(state.done, len(sequence)):
        frame = frame_to_device(sequence[i], device, dtype)
        if i == 0:
            start_map(state, frame)
        else:
            track(state, frame)
            after_tracking(state, frame)
        state.done = i + 1
        if on_frame is not None:
            on_frame(state)
    return finish_run(sequence, state, device, dtype, start, first_new)


def prepare_run(sequence, cfg: Config, device: Optional[torch.device], state: Optional[SLAMState]
                ) -> Tuple[SLAMState, torch.device, torch.dtype]:
    """Check the config and the sequence; the state to start from, the device and the dtype."""
    validate(cfg)  # types and ranges, with the key named (config.ranged fields)
    if len(sequence) < 2:
        raise ValueError(f"a SLAM run needs at least 2 frames, the sequence has {len(sequence)}")
    if np.any(np.diff(np.asarray(sequence.timestamps, dtype=np.float64)) <= 0):
        raise ValueError("frame timestamps must be strictly increasing")
    knot_schedule.check_knot_settings(cfg)
    knot_schedule.check_frame_spacing(cfg, sequence.timestamps)
    check_ray_budget(cfg, *sequence[0].depth.shape)
    device = device or resolve_device(cfg.device)
    state = initial_state(sequence, cfg, device) if state is None else state_on_device(state, device)
    return state, device, getattr(torch, cfg.dtype)


def finish_run(sequence, state: SLAMState, device: torch.device, dtype: torch.dtype, started: float,
               first_new: int) -> SLAMResult:
    """TS-SLAM maps its last, incomplete interval; collect the outputs (the frames from
    ``first_new`` on took from ``started``, a ``time.perf_counter()`` value, to now, this step included)."""
    if state.cfg.method == "tsslam" and state.done == len(sequence):
        tsslam_finish(state, sequence, device, dtype)
    elapsed = time.perf_counter() - started
    return SLAMResult(
        timestamps=np.asarray(sequence.timestamps, dtype=np.float64),
        poses=estimated_trajectory(state).detach().cpu().double().numpy(),
        frame_poses=state.frame_poses.detach().cpu().double().numpy(),
        state=state,
        frames_per_second=(len(sequence) - first_new) / max(elapsed, 1e-9) if len(sequence) > first_new else None,
        frames_processed=len(sequence) - first_new,
    )


def initial_state(sequence, cfg: Config, device: torch.device) -> SLAMState:
    """Build the map (bound from the config or from frame 0's depth) and the empty state."""
    dtype = getattr(torch, cfg.dtype)
    torch.manual_seed(cfg.seed)
    generator = torch.Generator(device="cpu").manual_seed(cfg.seed)
    first = sequence[0]
    first_pose = first.pose_c2w if first.pose_c2w is not None and np.all(np.isfinite(first.pose_c2w)) else np.eye(4)
    if cfg.field.bound is not None:
        bound = np.asarray(cfg.field.bound, dtype=np.float64)
        if bound.shape != (3, 2) or np.any(bound[:, 1] <= bound[:, 0]):
            raise ValueError(f"field.bound must be [[xmin,xmax],[ymin,ymax],[zmin,zmax]] with min < max, got {cfg.field.bound}")
    else:
        bound = estimate_bound([first], torch.as_tensor(first_pose[None]), cfg.field.bound_margin,
                               max_depth=min(cfg.data.depth_trunc, cfg.render.far))
    field_model = SceneField(field_settings_for(device, cfg.field), torch.as_tensor(bound, dtype=dtype)).to(device, dtype)
    poses = torch.eye(4, dtype=dtype, device=device).repeat(len(sequence), 1, 1)
    poses[0] = torch.as_tensor(first_pose, dtype=dtype, device=device)
    return SLAMState(
        cfg=cfg,
        field=field_model,
        map_optimizer=make_map_optimizer(field_model, cfg.mapping),
        keyframes=KeyframeDatabase(),
        timestamps=np.asarray(sequence.timestamps, dtype=np.float64),
        frame_poses=poses,
        tracking_output={0: poses[0].clone()},
        generator=generator,
    )


def start_map(state: SLAMState, frame: FrameTensors) -> None:
    """Frame 0: fit the map to it with its pose fixed (Co-SLAM ``first_iters``), keyframe 0, and
    for TS-SLAM the empty spline whose first interval starts at frame 0's time."""
    cfg = state.cfg
    with state.timings.stage("first_frame_mapping", cfg.mapping.first_iters):
        fit_map(state.field, state.map_optimizer, [frame], state.frame_poses[:1], state.loss_settings,
                iters=cfg.mapping.first_iters, n_rays=cfg.mapping.first_n_rays, generator=state.generator)
    add_keyframe(state, frame)
    state.keyframe_of_frame[0] = 0
    state.window_rays[0] = frame.sampled_rays(cfg.tracking.n_rays, state.generator, ignore_edge=cfg.tracking.ignore_edge)
    if cfg.method == "tsslam":
        state.trajectory = BSplineTrajectory.empty(float(state.timestamps[0]), cfg.spline.dt, state.frame_poses)


def after_tracking(state: SLAMState, frame: FrameTensors) -> None:
    """The method's mapping schedule for a tracked frame (:func:`tsslam_after_tracking` or
    :func:`coslam_after_tracking`).  A non-finite loss in a mapping stage ends the run as a
    :class:`TrackingFailure` naming the frame, like every other divergence."""
    try:
        if state.cfg.method == "tsslam":
            tsslam_after_tracking(state, frame)
        else:
            coslam_after_tracking(state, frame)
    except FloatingPointError as error:
        raise TrackingFailure(f"mapping after frame {frame.index} (t = {frame.timestamp:.3f} s) diverged: {error}") from error


def add_keyframe(state: SLAMState, frame: FrameTensors) -> None:
    """Store ``kf_pixel_fraction`` of the frame's pixels, chosen uniformly once (Co-SLAM)."""
    n_pixels = max(1, int(round(state.cfg.mapping.kf_pixel_fraction * frame.height * frame.width)))
    state.keyframes.add(frame.index, frame.timestamp, frame.sampled_rays(n_pixels, state.generator))


# ------------------------------------------------------------------------------------------------
# Tracking


def motion_prediction(state: SLAMState, i: int) -> torch.Tensor:
    """(4, 4) initial pose of frame i: constant velocity, T_i = (T_{i-1} T_{i-2}^-1) T_{i-1}.  Co-SLAM
    measures the motion between the stored poses of frames i-2 and i-1.  TS-SLAM (ours) measures it
    between the two frames' tracking outputs, applies it to frame i-1's stored pose (docs/system.md,
    "The motion prior after an interval") and, across a gap, once per spacing (``tracking.motion_scale``)."""
    previous = state.frame_poses[i - 1].clone()
    if i < 2 or not state.cfg.tracking.const_speed:
        return constant_velocity_init(previous, None)
    before = state.frame_poses[i - 2].clone()
    outputs = state.tracking_output
    if state.cfg.method == "tsslam" and (i - 1) in outputs and (i - 2) in outputs:
        motion = outputs[i - 1] @ invert_pose(outputs[i - 2])  # world frame, T_{i-1} T_{i-2}^-1
        before = invert_pose(motion) @ previous  # so that the prediction is motion @ T_{i-1}
    scale = motion_scale(state.timestamps, i) if state.cfg.method == "tsslam" else 1.0  # the baseline: Co-SLAM's
    return constant_velocity_init(previous, before, scale)


def track(state: SLAMState, frame: FrameTensors, field_model: Optional[SceneField] = None, lock=None) -> None:
    """Track frame ``frame.index`` from :func:`motion_prediction`; store the estimate and its rays.

    ``field_model`` (default ``state.field``) is the map tracked against; ``lock`` (two-thread
    mode, ``parallel.py``) guards the reads and writes of ``state``, not the optimisation."""
    cfg = state.cfg
    i = frame.index
    lock = lock if lock is not None else contextlib.nullcontext()
    with lock:
        init = motion_prediction(state, i)
        reference = [entry["tracking_loss"] for entry in state.log[:5]]
    rays = frame.sampled_rays(cfg.tracking.n_rays, state.generator, ignore_edge=cfg.tracking.ignore_edge)
    started = time.perf_counter()
    result = track_frame(field_model if field_model is not None else state.field, rays, init, cfg.tracking,
                         state.loss_settings, generator=state.generator)
    seconds, best_loss = time.perf_counter() - started, check_tracking(result, reference, cfg, frame)
    with lock:  # the timing and the log entry together: a checkpoint (--parallel) sees both or neither
        state.timings.add("tracking", seconds, len(result.losses))
        state.frame_poses[i] = result.pose
        state.tracking_output[i] = result.pose.clone()
        state.tracking_output.pop(i - 2, None)
        state.window_rays[i] = rays
        state.log.append({"frame": i, "tracking_loss": best_loss, "tracking_seconds": seconds,
                          "tracking_iterations": len(result.losses), "outside_box": share_outside_bound(
                              state.field.bound, rays, result.pose, min(cfg.data.depth_trunc, cfg.render.far))})


def check_tracking(result: TrackingResult, reference: List[float], cfg: Config, frame: FrameTensors) -> float:
    """The kept iteration's loss; :class:`TrackingFailure` when it or the pose is not finite, or when
    it exceeds ``tracking.max_loss_ratio`` x the median of the first five frames' losses."""
    best_loss = result.losses[result.best_iteration] if result.losses else float("nan")
    where = f"frame {frame.index} (t = {frame.timestamp:.3f} s)"
    if not (torch.all(torch.isfinite(result.pose)) and np.isfinite(best_loss)):
        raise TrackingFailure(f"tracking produced a non-finite pose or loss at {where}")
    if len(reference) == 5 and best_loss > cfg.tracking.max_loss_ratio * float(np.median(reference)):
        raise TrackingFailure(
            f"tracking diverged at {where}: loss {best_loss:.4g} is more than {cfg.tracking.max_loss_ratio:g} x "
            f"the median {np.median(reference):.4g} of the first tracked frames{depth_problem(cfg, frame.depth)}"
        )
    return best_loss


def current_frame(state: SLAMState, frame: FrameTensors) -> CurrentFrame:
    """The frame as global BA's current frame: all its rays, its time and its stored pose."""
    return CurrentFrame(rays=frame.all_rays(), timestamp=frame.timestamp, pose=state.frame_poses[frame.index])


# ------------------------------------------------------------------------------------------------
# Co-SLAM's schedule


def coslam_after_tracking(state: SLAMState, frame: FrameTensors) -> None:
    """Global BA every ``map_every`` frames, keyframe every ``keyframe_every``, pose_relative."""
    cfg = state.cfg
    i = frame.index
    if i % cfg.mapping.map_every == 0:
        discrete_global_ba(state, frame)
    if i % cfg.mapping.keyframe_every == 0:
        add_keyframe(state, frame)
    kf_frame = state.keyframes.frame_indices[-1]
    state.keyframe_of_frame[i] = kf_frame
    if kf_frame != i:
        state.relative_to_keyframe[i] = state.frame_poses[i] @ invert_pose(state.frame_poses[kf_frame])
    state.window_rays.pop(i, None)  # the baseline has no local window


def discrete_global_ba(state: SLAMState, frame: FrameTensors, fixed: Optional[np.ndarray] = None,
                       stage: str = "global_ba") -> None:
    """Co-SLAM global BA over all keyframes + the current frame; store the optimised poses.

    ``fixed`` ((K + 1,) bool, keyframes then the current frame) replaces Co-SLAM's choice of fixed
    poses (:func:`global_ba.coslam_global_ba`); ``stage`` names the timer."""
    keyframe_frames = state.keyframes.frame_indices
    with state.timings.stage(stage, state.cfg.mapping.iters):
        keyframe_poses, current_pose, _ = coslam_global_ba(
            state.field, state.map_optimizer, state.keyframes, state.frame_poses[keyframe_frames],
            current_frame(state, frame), state.cfg.mapping, state.loss_settings, state.generator, fixed=fixed)
    state.frame_poses[keyframe_frames] = keyframe_poses
    state.frame_poses[frame.index] = current_pose


# ------------------------------------------------------------------------------------------------
# TS-SLAM's schedule (Fig. 2)


def tsslam_after_tracking(state: SLAMState, frame: FrameTensors) -> None:
    """Map every interval the frame's time completed; else a map update every
    ``mapping.tsslam_map_every`` frames; keyframe every ``keyframe_every`` frames."""
    cfg = state.cfg
    mapped = False
    while frame.timestamp >= state.trajectory.interval(state.intervals_done)[1]:
        map_interval(state, frame)
        mapped = True
    every = cfg.mapping.tsslam_map_every
    if not mapped and every > 0 and frame.index % every == 0:
        tsslam_map_update(state, frame)
    if frame.index % cfg.mapping.keyframe_every == 0:
        add_keyframe(state, frame)


def map_interval(state: SLAMState, frame: FrameTensors) -> None:
    """The mapping step of interval ``state.intervals_done``, triggered by ``frame`` (Fig. 2)."""
    n = state.intervals_done
    if state.cfg.local_ba.use_spline:
        if state.cfg.spline.knots == "adaptive":
            knot_schedule.plan_next_interval(state, frame.index, n)
        trajectory = add_control_point(state, frame, n)
        if state.cfg.local_ba.enabled:
            trajectory = local_ba_in_window(state, frame, trajectory)
        trajectory = global_ba_outside_window(state, frame, trajectory)
        commit_interval(state, frame, trajectory, n)
    else:
        discrete_pose_interval(state, frame, n)
    state.intervals_done = n + 1
    drop_old_rays(state, n)


def add_control_point(state: SLAMState, frame: FrameTensors, n: int) -> BSplineTrajectory:
    """Curve approximation (Eq. 11): the trajectory with the control point of interval ``n`` added,
    fitted to the stored poses of the frames in :func:`local_ba.fit_time_range`."""
    cfg = state.cfg
    times = state.timestamps[: frame.index + 1]
    with state.timings.stage("lba_init") as record:
        fit_start, fit_end = local_ba.fit_time_range(state.trajectory, n, cfg.local_ba)
        fit_frames = np.nonzero((times >= fit_start) & (times < fit_end))[0]
        report = {}
        trajectory = local_ba.curve_approximation(state.trajectory, times[fit_frames], state.frame_poses[fit_frames],
                                                  cfg.local_ba, fit=cfg.local_ba.enabled,
                                                  free_controls=local_ba.fit_size(state.trajectory, n, cfg.local_ba.fit_controls),
                                                  report=report)
        record.iterations = report["iterations"]  # Levenberg-Marquardt stops early: count what ran
    check_finite(trajectory, "the curve approximation", frame)
    return trajectory


def local_ba_in_window(state: SLAMState, frame: FrameTensors, trajectory: BSplineTrajectory) -> BSplineTrajectory:
    """Local BA: the window's control points on the rays of the frames in the window, map frozen,
    then jointly with the map on the window's keyframes (``local_ba.joint_iters``)."""
    cfg = state.cfg
    times = state.timestamps[: frame.index + 1]
    start, end = local_ba.window_time_range(trajectory, cfg.local_ba.window)
    with state.timings.stage("lba_others", cfg.local_ba.refine_iters + cfg.local_ba.joint_iters):
        frames = [j for j in sorted(state.window_rays) if start <= times[j] < end]
        if frames:
            trajectory, _ = local_ba.refine_window(state.field, trajectory, times[frames],
                                                   [state.window_rays[j] for j in frames], cfg.local_ba, cfg.dynamics,
                                                   state.loss_settings, state.generator)
        check_finite(trajectory, "local BA refinement", frame)
        trajectory, _ = local_ba.joint_window(state.field, state.map_optimizer, trajectory, state.keyframes,
                                              cfg.local_ba, cfg.dynamics, state.loss_settings, state.generator)
        check_finite(trajectory, "local BA joint refinement", frame)
    return trajectory


def global_ba_outside_window(state: SLAMState, frame: FrameTensors, trajectory: BSplineTrajectory) -> BSplineTrajectory:
    """Global BA: the map and the control points older than the window (never point 0) on all
    keyframes + the current frame, L_DR over the time before the window."""
    cfg = state.cfg
    window = cfg.local_ba.window
    in_window = set(local_ba.window_controls(trajectory, window)) if cfg.local_ba.enabled else set()
    free = [k for k in range(local_ba.N_ANCHOR_CONTROLS, trajectory.n_ctrl) if k not in in_window]
    before_window = (trajectory.domain()[0], local_ba.window_time_range(trajectory, window)[0])
    keyframe_frames = state.keyframes.frame_indices
    with state.timings.stage("global_ba", cfg.mapping.iters):
        trajectory, _ = tsslam_global_ba(
            state.field, state.map_optimizer, state.keyframes, state.frame_poses[keyframe_frames], trajectory, free,
            current_frame(state, frame), cfg.mapping, cfg.dynamics, state.loss_settings,
            dynamics_range=before_window if cfg.local_ba.use_dynamics else None, generator=state.generator)
    check_finite(trajectory, "global BA", frame)
    return trajectory


def commit_interval(state: SLAMState, frame: FrameTensors, trajectory: BSplineTrajectory, n: int) -> None:
    """Check that the spline follows the tracked poses of interval ``n``, then keep it and store its
    poses for every frame it covers (the next motion prediction starts from them)."""
    times = state.timestamps[: frame.index + 1]
    interval_start, interval_end = trajectory.interval(n)
    in_interval = np.nonzero((times >= interval_start) & (times < interval_end))[0]
    check_spline_follows_tracking(state, trajectory, times[in_interval], in_interval)
    covered = np.nonzero(trajectory.covers(times))[0]
    if len(covered) > 0:
        state.frame_poses[covered] = trajectory.poses(times[covered]).to(state.frame_poses.dtype)
    state.trajectory = trajectory


def discrete_pose_interval(state: SLAMState, frame: FrameTensors, n: int) -> None:
    """The "w/o B-S." ablation's interval: the window stages on the discrete poses of the frames
    of the last ``local_ba.window`` intervals (unless ``local_ba.enabled`` is off), then Co-SLAM's global BA."""
    cfg = state.cfg
    times = state.timestamps[: frame.index + 1]
    interval_end = state.trajectory.interval(n)[1]
    window_start = state.trajectory.knot_time_before(interval_end_knot(state.trajectory, n), cfg.local_ba.window)
    frames = [j for j in sorted(state.window_rays) if window_start <= times[j] < interval_end]
    if frames and cfg.local_ba.enabled:
        with state.timings.stage("lba_others", cfg.local_ba.refine_iters + cfg.local_ba.joint_iters):
            keyframe_set = set(state.keyframes.frame_indices)
            state.frame_poses[frames] = local_ba.refine_discrete_window(
                state.field, state.map_optimizer, state.frame_poses[frames], [state.window_rays[j] for j in frames],
                [j in keyframe_set for j in frames], cfg.local_ba, state.loss_settings, state.generator)
    discrete_global_ba(state, frame)


def interval_end_knot(trajectory: BSplineTrajectory, n: int) -> int:
    """Index k of the knot t_k that ends interval n."""
    return trajectory.interval_start_knot(n) + 1


def drop_old_rays(state: SLAMState, n: int) -> None:
    """Forget the tracking rays of frames older than any window after interval ``n`` can reach
    (:func:`local_ba.window_size` + 2 intervals before its end)."""
    window = local_ba.window_size(state.trajectory, state.cfg.local_ba.window)
    oldest_needed = state.trajectory.knot_time_before(interval_end_knot(state.trajectory, n), window + 2)
    for j in [j for j in state.window_rays if state.timestamps[j] < oldest_needed]:
        del state.window_rays[j]


def check_finite(trajectory: BSplineTrajectory, stage: str, frame: FrameTensors) -> None:
    """:class:`TrackingFailure` naming ``stage`` and the frame when a control point is not finite."""
    if not (torch.isfinite(trajectory.control_rotations).all() and torch.isfinite(trajectory.control_translations).all()):
        raise TrackingFailure(f"the control points became non-finite in {stage} at frame {frame.index} "
                              f"(t = {frame.timestamp:.3f} s)")


def check_spline_follows_tracking(state: SLAMState, trajectory: BSplineTrajectory, times: np.ndarray,
                                  frames: np.ndarray) -> None:
    """Log how far the spline lies from the stored poses of ``frames`` ((F,) indices, times (F,) s) where
    it covers them (``spline_offset_m``, ``spline_offset_deg``); :class:`TrackingFailure` beyond
    ``local_ba.max_deviation`` m.  Without local BA (the 'w/o LBA' ablation) a new control point is only
    an extrapolation and the spline drifts away; the paper reports that the system then fails."""
    inside = trajectory.covers(times)
    if len(frames) == 0 or not inside.any():
        return
    distances, angles = trajectory.offsets(times[inside], state.frame_poses[frames[inside]])
    offsets, first = dict(zip(frames[inside].tolist(), zip(distances.tolist(), angles.tolist()))), frames[inside].min()
    for entry in itertools.takewhile(lambda entry: entry["frame"] >= first, reversed(state.log)):  # frames in order
        if entry["frame"] in offsets:
            entry["spline_offset_m"], entry["spline_offset_deg"] = offsets[entry["frame"]]
    deviation, limit = float(distances.max()), state.cfg.local_ba.max_deviation
    if not np.isfinite(deviation) or deviation > limit:
        raise TrackingFailure(
            f"the spline trajectory is {deviation:.3f} m away from the tracked poses at t = {times[inside][0]:.3f} s "
            f"(limit local_ba.max_deviation = {limit} m); the control points no longer follow the camera"
            + ("; local BA is switched off (local_ba.enabled=false), which the paper reports makes TS-SLAM fail"
               if not state.cfg.local_ba.enabled else "")
        )


def tsslam_map_update(state: SLAMState, frame: FrameTensors) -> None:
    """Co-SLAM's global BA on what the spline does not reach yet (ours, ``mapping.tsslam_map_every``).

    Keyframes the spline covers keep their (spline) poses, as does keyframe 0; the newer ones and
    the current frame (iff ``mapping.optim_cur``) move with the map, and their results replace
    the stored poses that the next curve approximation fits.  The spline is left unchanged.
    Why: docs/system.md, "Walking-speed motion"."""
    slot_times = np.append(state.timestamps[state.keyframes.frame_indices], state.timestamps[frame.index])
    fixed = state.trajectory.covers(slot_times)
    fixed[0] = True
    fixed[-1] = fixed[-1] or not state.cfg.mapping.optim_cur
    discrete_global_ba(state, frame, fixed=fixed, stage="map_update")


def tsslam_finish(state: SLAMState, sequence, device: torch.device, dtype: torch.dtype) -> None:
    """Map the last, incomplete interval so that the spline covers every frame (where it ends:
    ``spline.last_interval``, :func:`knot_schedule.end_last_interval`)."""
    last = state.done - 1
    start, _ = state.trajectory.interval(state.intervals_done)
    if state.timestamps[last] >= start or state.trajectory.n_ctrl < 4:
        knot_schedule.end_last_interval(state, last)
        map_interval(state, frame_to_device(sequence[last], device, dtype))
