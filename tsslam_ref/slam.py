"""The SLAM system loop: track every frame, map on schedule, keep map, poses and keyframes.

TS-SLAM Sec. III-D (Fig. 2) and, for the baseline, Co-SLAM's single-process schedule
(its single-process ``coslam.py``):

* frame 0: its pose is the ground-truth pose when known (Co-SLAM does the same so that the map
  lives in the dataset's world frame and the scene bound applies), else the identity; the map is
  fitted to it for ``mapping.first_iters`` iterations; it becomes keyframe 0.
* every later frame is tracked with the map frozen (``tracking.py``) from a constant-velocity
  prediction (:func:`motion_prediction`; TS-SLAM measures the motion between tracking results).
* ``method="coslam"`` (one pose per frame, the paper's baseline and "w/o B-S." row): global BA
  every ``map_every`` frames over all keyframes + the current frame; keyframe every
  ``keyframe_every`` frames, added after BA.  Non-keyframe poses are stored relative to the
  preceding keyframe and re-anchored after BA (Co-SLAM's ``pose_relative``, the trajectory its
  paper reports).
* ``method="tsslam"``: the trajectory is a cubic B-spline (``spline.py``); every ``dt`` of sequence
  time a new control point is added and the mapping step runs local BA over the sliding window
  then global BA over the keyframes outside it (``local_ba.py``, ``global_ba.py``); on every
  ``mapping.tsslam_map_every``-th frame where no interval ends, Co-SLAM's global BA runs on what
  the spline does not reach yet (ours; 0 gives the paper's schedule).  Output poses are the
  spline's poses at the frames' timestamps.

The loop is sequential and deterministic for a seed.  ``run_slam`` takes a progress callback and a
checkpoint hook so the command line (``run.py``) can show progress, write partial results and
resume.

Layer 4 (system): orchestrates; holds only small state dataclasses.
Taught in notebooks/09_full_system.ipynb.
"""

import contextlib
import ctypes
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import numpy as np
import torch

from . import local_ba
from . import spline as spline_module
from .bundle import KeyframeDatabase
from .config import Config, validate
from .field import SceneField
from .geometry import invert_pose, make_pose, pose_to_tum
from .global_ba import coslam_global_ba, tsslam_global_ba
from .mapping import estimate_bound, fit_map, make_map_optimizer
from .render import RayBatch, frame_rays, sample_pixels
from .tracking import constant_velocity_init, track_frame


class TrackingFailure(RuntimeError):
    """The run cannot go on (non-finite or diverged tracking); the message says where and why."""


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; 'cpu' / 'cuda' / 'cuda:1' as given."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for but torch.cuda.is_available() is False")
    return device


def tune_cpu_allocator() -> bool:
    """Keep freed buffers in the process instead of returning them to the OS (glibc only).

    The map's iterations allocate and free the same ~50 MB buffers again and again; with glibc's
    defaults each is a fresh mmap that page-faults on first touch (measured on two cores, docs/map.md:
    20-40 % of an iteration).  Raising the mmap and trim thresholds (``mallopt``, the same as the
    ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` / ``MALLOC_TOP_PAD_`` environment
    variables) avoids that.  Process-wide, so only the command-line entry points call it.
    Returns False (and changes nothing) where glibc is not available.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3  # glibc malloc.h
    ok = mallopt(m_mmap_threshold, 1 << 30) and mallopt(m_trim_threshold, 1 << 30)
    return bool(ok and mallopt(m_top_pad, 1 << 28))


@dataclass
class FrameTensors:
    """One frame on the compute device."""

    index: int
    timestamp: float
    rgb: torch.Tensor  # (H, W, 3)
    depth: torch.Tensor  # (H, W)
    intrinsics: object

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])

    def rays(self, rows: torch.Tensor, cols: torch.Tensor, frame_id: int = 0) -> RayBatch:
        return frame_rays(self.rgb, self.depth, self.intrinsics, rows, cols, frame_id=frame_id)

    def all_rays(self) -> RayBatch:
        """Every pixel as a camera-frame ray, (H*W,)."""
        rows, cols = torch.meshgrid(
            torch.arange(self.height, device=self.depth.device),
            torch.arange(self.width, device=self.depth.device),
            indexing="ij",
        )
        return self.rays(rows.reshape(-1), cols.reshape(-1))

    def sampled_rays(self, n: int, generator: torch.Generator, ignore_edge: int = 0) -> RayBatch:
        rows, cols = sample_pixels(self.height, self.width, n, ignore_edge=ignore_edge, generator=generator)
        return self.rays(rows.to(self.depth.device), cols.to(self.depth.device))


def frame_to_device(frame, device: torch.device, dtype: torch.dtype) -> FrameTensors:
    """:class:`tsslam_ref.data.Frame` (numpy) -> :class:`FrameTensors` on ``device``."""
    return FrameTensors(
        index=frame.index,
        timestamp=float(frame.timestamp),
        rgb=torch.as_tensor(np.ascontiguousarray(frame.rgb), dtype=dtype, device=device),
        depth=torch.as_tensor(np.ascontiguousarray(frame.depth), dtype=dtype, device=device),
        intrinsics=frame.intrinsics,
    )


@dataclass
class Timings:
    """Wall-clock seconds spent per stage and iteration counts (for the paper's runtime table)."""

    seconds: Dict[str, float] = field(default_factory=dict)
    iterations: Dict[str, int] = field(default_factory=dict)
    calls: Dict[str, int] = field(default_factory=dict)

    def add(self, stage: str, seconds: float, iterations: int) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds
        self.iterations[stage] = self.iterations.get(stage, 0) + iterations
        self.calls[stage] = self.calls.get(stage, 0) + 1

    def table(self) -> Dict[str, Dict[str, float]]:
        """Per stage: ms per iteration, iterations per call, calls, total seconds."""
        rows = {}
        for stage, seconds in self.seconds.items():
            iterations = max(self.iterations[stage], 1)
            rows[stage] = {
                "ms_per_iteration": 1000.0 * seconds / iterations,
                "iterations_per_call": self.iterations[stage] / max(self.calls[stage], 1),
                "calls": self.calls[stage],
                "total_s": seconds,
            }
        return rows


@dataclass
class SLAMState:
    """Everything the loop carries from frame to frame (checkpointed by ``run.py``)."""

    cfg: Config
    field: SceneField
    map_optimizer: torch.optim.Optimizer
    keyframes: KeyframeDatabase
    timestamps: np.ndarray  # (N,) float64 seconds of every frame of the sequence
    tracked_poses: torch.Tensor  # (N, 4, 4) discrete estimates (tracking, then BA updates)
    # the last two frames' poses as tracking returned them (TS-SLAM's motion_prediction)
    tracking_results: Dict[int, torch.Tensor] = field(default_factory=dict)
    done: int = 0  # frames processed so far
    keyframe_of_frame: Dict[int, int] = field(default_factory=dict)  # frame -> preceding kf frame
    relative_to_keyframe: Dict[int, torch.Tensor] = field(default_factory=dict)  # Co-SLAM pose_relative
    spline: Optional[local_ba.SplineTrack] = None  # TS-SLAM's trajectory (interval bookkeeping too)
    frame_rays: Dict[int, RayBatch] = field(default_factory=dict)  # recent frames' rays (local BA window)
    generator: Optional[torch.Generator] = None
    timings: Timings = field(default_factory=Timings)
    log: List[Dict[str, float]] = field(default_factory=list)


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
    field_model = SceneField(cfg.field, torch.as_tensor(bound, dtype=dtype)).to(device=device, dtype=dtype)
    optimizer = make_map_optimizer(field_model, cfg.mapping)
    n_frames = len(sequence)
    poses = torch.eye(4, dtype=dtype, device=device).repeat(n_frames, 1, 1)
    poses[0] = torch.as_tensor(first_pose, dtype=dtype, device=device)
    return SLAMState(
        cfg=cfg,
        field=field_model,
        map_optimizer=optimizer,
        keyframes=KeyframeDatabase(),
        timestamps=np.asarray(sequence.timestamps, dtype=np.float64),
        tracked_poses=poses,
        tracking_results={0: poses[0].clone()},
        generator=generator,
    )


def add_keyframe(state: SLAMState, frame: FrameTensors) -> None:
    """Store ``kf_pixel_fraction`` of the frame's pixels, chosen uniformly once (Co-SLAM 5.3)."""
    n_pixels = max(1, int(round(state.cfg.mapping.kf_pixel_fraction * frame.height * frame.width)))
    state.keyframes.add(frame.index, frame.timestamp, frame.sampled_rays(n_pixels, state.generator))


def first_frame_mapping(state: SLAMState, frame: FrameTensors) -> None:
    """Fit the map to frame 0 with its pose fixed (Co-SLAM ``first_iters``)."""
    cfg = state.cfg
    start = time.perf_counter()
    fit_map(
        state.field, state.map_optimizer, [frame], state.tracked_poses[:1], cfg,
        iters=cfg.mapping.first_iters, n_rays=cfg.mapping.first_n_rays, generator=state.generator,
    )
    state.timings.add("first_frame_mapping", time.perf_counter() - start, cfg.mapping.first_iters)
    add_keyframe(state, frame)
    state.keyframe_of_frame[0] = 0
    state.frame_rays[0] = frame.sampled_rays(cfg.tracking.n_rays, state.generator, ignore_edge=cfg.tracking.ignore_edge)


def motion_prediction(state: SLAMState, i: int) -> torch.Tensor:
    """(4, 4) initial pose of frame i: constant velocity, T_i = (T_{i-1} T_{i-2}^-1) T_{i-1}.

    Co-SLAM measures the motion between the stored poses of frames i-2 and i-1, whatever global BA
    made of them.  TS-SLAM (ours) measures it between the two frames' tracking results and applies
    it to frame i-1's stored pose: right after a spline interval ends, frame i-2 holds its spline
    pose and frame i-1 still its tracked one, and their difference is the curve's distance from
    tracking, not camera motion (docs/system.md, "The motion prior after an interval")."""
    previous = state.tracked_poses[i - 1].clone()
    if i < 2 or not state.cfg.tracking.const_speed:
        return constant_velocity_init(previous, None)
    before = state.tracked_poses[i - 2].clone()
    results = state.tracking_results
    if state.cfg.method == "tsslam" and (i - 1) in results and (i - 2) in results:
        motion = results[i - 1] @ invert_pose(results[i - 2])  # world frame, T_{i-1} T_{i-2}^-1
        before = invert_pose(motion) @ previous  # so that the prediction is motion @ T_{i-1}
    return constant_velocity_init(previous, before)


def track(state: SLAMState, frame: FrameTensors, field_model: Optional[SceneField] = None, lock=None) -> None:
    """Track frame ``frame.index`` from :func:`motion_prediction`; store the estimate.

    ``field_model`` (default ``state.field``) is the map tracked against; ``lock`` (parallel mode,
    parallel.py) guards the reads and writes of ``state``, not the optimisation."""
    cfg = state.cfg
    i = frame.index
    lock = lock if lock is not None else contextlib.nullcontext()
    with lock:
        init = motion_prediction(state, i)
        reference = [entry["tracking_loss"] for entry in state.log[:5]]
    rays = frame.sampled_rays(cfg.tracking.n_rays, state.generator, ignore_edge=cfg.tracking.ignore_edge)
    start = time.perf_counter()
    result = track_frame(field_model if field_model is not None else state.field, rays, init, cfg,
                         generator=state.generator)
    state.timings.add("tracking", time.perf_counter() - start, len(result.losses))
    best_loss = result.losses[result.best_iteration] if result.losses else float("nan")
    if not (torch.all(torch.isfinite(result.pose)) and np.isfinite(best_loss)):
        raise TrackingFailure(f"tracking produced a non-finite pose or loss at frame {i} (t = {frame.timestamp:.3f} s)")
    if len(reference) == 5 and best_loss > cfg.tracking.max_loss_ratio * float(np.median(reference)):
        raise TrackingFailure(
            f"tracking diverged at frame {i} (t = {frame.timestamp:.3f} s): loss {best_loss:.4g} is more than "
            f"{cfg.tracking.max_loss_ratio:g} x the median {np.median(reference):.4g} of the first tracked frames"
        )
    with lock:
        state.tracked_poses[i] = result.pose
        state.tracking_results[i] = result.pose.clone()
        state.tracking_results.pop(i - 2, None)
        state.frame_rays[i] = rays
        state.log.append({"frame": i, "tracking_loss": best_loss})


def coslam_mapping(state: SLAMState, frame: FrameTensors, held: Optional[np.ndarray] = None,
                   stage: str = "global_ba") -> None:
    """Co-SLAM global BA over all keyframes + the current frame; write back the optimised poses.

    ``held`` ((K + 1,) bool, keyframes then the current frame) replaces Co-SLAM's choice of held
    poses (:func:`global_ba.coslam_global_ba`); ``stage`` names the timer."""
    cfg = state.cfg
    keyframe_frames = state.keyframes.frame_indices
    start = time.perf_counter()
    keyframe_poses, current_pose, _ = coslam_global_ba(
        state.field, state.map_optimizer, state.keyframes, state.tracked_poses[keyframe_frames],
        frame.all_rays(), state.tracked_poses[frame.index], cfg, state.generator,
        held=held,
    )
    state.timings.add(stage, time.perf_counter() - start, cfg.mapping.iters)
    state.tracked_poses[keyframe_frames] = keyframe_poses
    state.tracked_poses[frame.index] = current_pose


def coslam_step(state: SLAMState, frame: FrameTensors) -> None:
    """One frame of the Co-SLAM baseline schedule (after frame 0)."""
    track(state, frame)
    coslam_after_tracking(state, frame)


def coslam_after_tracking(state: SLAMState, frame: FrameTensors) -> None:
    """The mapping side of a Co-SLAM frame: global BA every ``map_every``, keyframes, pose_relative."""
    cfg = state.cfg
    i = frame.index
    if i % cfg.mapping.map_every == 0:
        coslam_mapping(state, frame)
    if i % cfg.mapping.keyframe_every == 0:
        add_keyframe(state, frame)
    kf_frame = state.keyframes.frame_indices[-1]
    state.keyframe_of_frame[i] = kf_frame
    if kf_frame != i:
        state.relative_to_keyframe[i] = state.tracked_poses[i] @ invert_pose(state.tracked_poses[kf_frame])
    state.frame_rays.pop(i, None)  # the baseline has no local window


# ------------------------------------------------------------------------------------------------
# TS-SLAM


def tsslam_start(state: SLAMState) -> None:
    """Empty spline whose first interval starts at frame 0's time (paper convention, t0 = t_first - 2 dt)."""
    state.spline = local_ba.SplineTrack.empty(float(state.timestamps[0]), state.cfg.spline.dt, state.tracked_poses)


def _check_finite(track: "local_ba.SplineTrack", stage: str, frame: FrameTensors) -> None:
    if not (torch.isfinite(track.rotations).all() and torch.isfinite(track.translations).all()):
        raise TrackingFailure(f"the control points became non-finite in {stage} at frame {frame.index} (t = {frame.timestamp:.3f} s)")


def tsslam_mapping(state: SLAMState, frame: FrameTensors) -> None:
    """The mapping step of interval ``state.spline.intervals_done``: local BA, then global BA."""
    cfg = state.cfg
    track = state.spline
    n = track.intervals_done
    interval_start, interval_end = track.interval(n)
    times = state.timestamps[: frame.index + 1]
    in_interval = np.nonzero((times >= interval_start) & (times < interval_end))[0]
    window = cfg.local_ba.window
    if cfg.local_ba.use_spline:
        start = time.perf_counter()
        fit_start, fit_end = local_ba.fit_time_range(track, n, cfg)
        fit_frames = np.nonzero((times >= fit_start) & (times < fit_end))[0]
        track = local_ba.curve_approximation(track, times[fit_frames], state.tracked_poses[fit_frames], cfg,
                                             fit=cfg.local_ba.enabled)
        state.timings.add("lba_init", time.perf_counter() - start, cfg.local_ba.fit_iters if cfg.local_ba.enabled else 0)
        _check_finite(track, "the curve approximation", frame)
        window_range = track.window_time_range(window)
        if cfg.local_ba.enabled:
            start = time.perf_counter()
            frames = [j for j in sorted(state.frame_rays) if window_range[0] <= times[j] < window_range[1]]
            if frames:
                track, _ = local_ba.refine_window(state.field, track, times[frames], [state.frame_rays[j] for j in frames],
                                                  cfg, state.generator)
            _check_finite(track, "local BA refinement", frame)
            track, _ = local_ba.joint_window(state.field, state.map_optimizer, track, state.keyframes, cfg, state.generator)
            _check_finite(track, "local BA joint refinement", frame)
            state.timings.add("lba_others", time.perf_counter() - start, cfg.local_ba.refine_iters + cfg.local_ba.joint_iters)
        window_controls = set(track.window_controls(window)) if cfg.local_ba.enabled else set()
        free = [k for k in range(local_ba.N_ANCHOR_CONTROLS, track.n_ctrl) if k not in window_controls]
        domain_start, _ = track.domain()
        start = time.perf_counter()
        kf_frames = state.keyframes.frame_indices
        rotations, translations, _ = tsslam_global_ba(
            state.field, state.map_optimizer, state.keyframes, state.tracked_poses[kf_frames],
            track.rotations, track.translations, free, track.dt, track.t0, track.convention,
            frame.all_rays(), frame.timestamp, state.tracked_poses[frame.index], cfg,
            dynamics_range=(domain_start, window_range[0]) if cfg.local_ba.use_dynamics else None,
            generator=state.generator, start_pose=track.start_pose,
        )
        state.timings.add("global_ba", time.perf_counter() - start, cfg.mapping.iters)
        track = track.with_controls(rotations, translations)
        _check_finite(track, "global BA", frame)
        check_spline_follows_tracking(state, track, times[in_interval], in_interval)
        covered = np.nonzero(track.covers(times))[0]
        if len(covered) > 0:
            state.tracked_poses[covered] = track.poses(times[covered]).to(state.tracked_poses.dtype)
    else:
        start = time.perf_counter()
        window_start = interval_end - window * track.dt
        frames = [j for j in sorted(state.frame_rays) if window_start <= times[j] < interval_end]
        if frames:
            keyframe_set = set(state.keyframes.frame_indices)
            state.tracked_poses[frames] = local_ba.refine_discrete_window(
                state.field, state.map_optimizer, state.tracked_poses[frames], [state.frame_rays[j] for j in frames],
                [j in keyframe_set for j in frames], cfg, state.generator)
        state.timings.add("lba_others", time.perf_counter() - start, cfg.local_ba.refine_iters + cfg.local_ba.joint_iters)
        coslam_mapping(state, frame)
    track.intervals_done = n + 1
    state.spline = track
    oldest_needed = interval_end - (window + 2) * track.dt
    for j in [j for j in state.frame_rays if state.timestamps[j] < oldest_needed]:
        del state.frame_rays[j]


def check_spline_follows_tracking(state: SLAMState, track: "local_ba.SplineTrack", times: np.ndarray,
                                  frames: np.ndarray) -> None:
    """Raise :class:`TrackingFailure` when the spline left the tracked poses of the newest interval.

    Local BA keeps the spline within centimetres of tracking; without it (the 'w/o LBA' ablation)
    a new control point is only an extrapolation and the spline drifts away - the paper reports
    that the system then fails, and this is where ours says so.
    """
    if len(frames) == 0:
        return
    inside = track.covers(times)
    if not inside.any():
        return
    spline_positions = track.poses(times[inside])[:, :3, 3]
    tracked_positions = state.tracked_poses[frames[inside], :3, 3]
    deviation = float(torch.linalg.vector_norm(spline_positions - tracked_positions, dim=-1).max())
    limit = state.cfg.local_ba.max_deviation
    if not np.isfinite(deviation) or deviation > limit:
        raise TrackingFailure(
            f"the spline trajectory is {deviation:.3f} m away from the tracked poses at t = {times[inside][0]:.3f} s "
            f"(limit local_ba.max_deviation = {limit} m); the control points no longer follow the camera"
            + ("; local BA is switched off (local_ba.enabled=false), which the paper reports makes TS-SLAM fail"
               if not state.cfg.local_ba.enabled else "")
        )


def tsslam_step(state: SLAMState, frame: FrameTensors) -> None:
    """One frame of TS-SLAM: track; every completed dt-interval, map; keyframe every 5 frames."""
    track(state, frame)
    tsslam_after_tracking(state, frame)


def tsslam_after_tracking(state: SLAMState, frame: FrameTensors) -> None:
    """The mapping side of a TS-SLAM frame: local + global BA per completed interval, else a
    map update every ``mapping.tsslam_map_every`` frames; keyframes."""
    cfg = state.cfg
    mapped = False
    while frame.timestamp >= state.spline.interval(state.spline.intervals_done)[1]:
        tsslam_mapping(state, frame)
        mapped = True
    every = cfg.mapping.tsslam_map_every
    if not mapped and every > 0 and frame.index % every == 0:
        tsslam_map_update(state, frame)
    if frame.index % cfg.mapping.keyframe_every == 0:
        add_keyframe(state, frame)


def tsslam_map_update(state: SLAMState, frame: FrameTensors) -> None:
    """Co-SLAM's global BA on what the spline does not reach yet (ours, ``mapping.tsslam_map_every``).

    Between two spline intervals the map would otherwise see no new view for dt seconds; on
    walking-speed motion tracking then runs off the mapped part of the scene (docs/system.md).
    Keyframes the spline reaches keep their (spline) poses, as does keyframe 0; the newer ones and
    the current frame (iff ``mapping.optim_cur``) are discrete poses optimised with the map, and
    their results replace the tracked poses that the next curve approximation fits.  The
    spline is left unchanged."""
    slot_times = np.append(state.timestamps[state.keyframes.frame_indices], state.timestamps[frame.index])
    held = state.spline.covers(slot_times)
    held[0] = True
    held[-1] = held[-1] or not state.cfg.mapping.optim_cur
    coslam_mapping(state, frame, held=held, stage="map_update")


def tsslam_finish(state: SLAMState, sequence, device: torch.device, dtype: torch.dtype) -> None:
    """Map the last, incomplete interval so that the spline covers every frame."""
    last = state.done - 1
    start, _ = state.spline.interval(state.spline.intervals_done)
    if state.timestamps[last] >= start or state.spline.n_ctrl < 4:
        tsslam_mapping(state, frame_to_device(sequence[last], device, dtype))


def spline_output_poses(state: SLAMState) -> torch.Tensor:
    """(done, 4, 4): spline poses where the spline reaches, tracked poses elsewhere."""
    poses = state.tracked_poses[: state.done].clone()
    if state.spline is None or not state.cfg.local_ba.use_spline:
        return poses
    times = state.timestamps[: state.done]
    covered = np.nonzero(state.spline.covers(times))[0]
    if len(covered) > 0:
        poses[covered] = state.spline.poses(times[covered]).to(poses.dtype)
    return poses


def export_continuous(state: SLAMState, rate_hz: float, path) -> np.ndarray:
    """Sample the spline at ``rate_hz`` and write one line per time (atomic, refuses nothing: run.py
    owns the folder).  Columns: t tx ty tz qx qy qz qw vx vy vz wx wy wz, with v the world-frame
    linear velocity (m/s) and w the body-frame angular velocity (rad/s).  Returns the rows."""
    import os
    import tempfile

    if rate_hz <= 0:
        raise ValueError(f"--export-rate must be positive, got {rate_hz}")
    start, end = state.spline.domain()
    times = np.arange(start, end, 1.0 / rate_hz, dtype=np.float64)
    sample = spline_module.evaluate(state.spline.rotations, state.spline.translations, times, state.spline.dt,
                                    state.spline.t0, convention=state.spline.convention, derivatives=1)
    poses = make_pose(sample.rotation, sample.translation).detach().cpu().double().numpy()
    rows = np.concatenate([times[:, None], pose_to_tum(poses), sample.velocity_world.detach().cpu().double().numpy(),
                           sample.omega_body.detach().cpu().double().numpy()], axis=1)
    directory = os.path.dirname(os.path.abspath(str(path)))
    handle, temporary = tempfile.mkstemp(dir=directory, suffix=".tmp")
    with os.fdopen(handle, "w") as stream:
        stream.write("# t tx ty tz qx qy qz qw vx vy vz wx wy wz (camera-to-world, OpenCV axes; v world m/s, w body rad/s)\n")
        np.savetxt(stream, rows, fmt="%.9f")
    os.replace(temporary, str(path))
    return rows


def coslam_trajectory(state: SLAMState) -> torch.Tensor:
    """Co-SLAM's reported trajectory: keyframes as optimised, others re-anchored (pose_relative)."""
    poses = state.tracked_poses[: state.done].clone()
    for i, relative in state.relative_to_keyframe.items():
        if i < state.done:
            poses[i] = relative @ state.tracked_poses[state.keyframe_of_frame[i]]
    return poses


@dataclass
class SLAMResult:
    """What a finished (or interrupted) run produced."""

    timestamps: np.ndarray  # (N,) float64 seconds
    poses: np.ndarray  # (N, 4, 4) float64 camera-to-world, OpenCV axes
    tracked_poses: np.ndarray  # (N, 4, 4) the discrete tracking estimates
    state: SLAMState
    frames_per_second: float


def estimated_trajectory(state: SLAMState) -> torch.Tensor:
    """(done, 4, 4) the method's output poses for the frames processed so far."""
    if state.cfg.method == "tsslam":
        return spline_output_poses(state)
    return coslam_trajectory(state)


def run_slam(
    sequence,
    cfg: Config,
    device: Optional[torch.device] = None,
    state: Optional[SLAMState] = None,
    on_frame: Optional[Callable[[SLAMState], None]] = None,
) -> SLAMResult:
    """Run the whole loop over ``sequence`` (a :class:`tsslam_ref.data.RGBDSequence`).

    Args:
        sequence: frames with float64 timestamps; frame 0's ground-truth pose anchors the map.
        cfg: resolved config (``cfg.method`` picks coslam or tsslam).
        device: compute device (default: ``resolve_device(cfg.device)``).
        state: a state to resume from (``run.py`` checkpoints); None starts afresh.
        on_frame: called after every frame with the state (progress bars, partial outputs).

    Returns:
        :class:`SLAMResult` with float64 camera-to-world poses for every frame.
    """
    validate(cfg)  # types and ranges, with the key named (config.RANGES)
    if len(sequence) < 2:
        raise ValueError(f"a SLAM run needs at least 2 frames, the sequence has {len(sequence)}")
    timestamps = np.asarray(sequence.timestamps, dtype=np.float64)
    if np.any(np.diff(timestamps) <= 0):
        raise ValueError("frame timestamps must be strictly increasing")
    device = device or resolve_device(cfg.device)
    dtype = getattr(torch, cfg.dtype)
    if state is None:
        state = initial_state(sequence, cfg, device)
    start = time.perf_counter()
    start_frame = state.done
    for i in range(state.done, len(sequence)):
        if i > 0 and cfg.parallel:
            from .parallel import run_tracking_and_mapping  # the optional two-thread schedule

            run_tracking_and_mapping(sequence, state, device, dtype, on_frame)
            break
        frame = frame_to_device(sequence[i], device, dtype)
        if i == 0:
            first_frame_mapping(state, frame)
            if cfg.method == "tsslam":
                tsslam_start(state)
        elif cfg.method == "coslam":
            coslam_step(state, frame)
        else:
            tsslam_step(state, frame)
        state.done = i + 1
        if on_frame is not None:
            on_frame(state)
    if cfg.method == "tsslam" and state.done == len(sequence):
        tsslam_finish(state, sequence, device, dtype)
    elapsed = time.perf_counter() - start
    poses = estimated_trajectory(state).detach().cpu().double().numpy()
    return SLAMResult(
        timestamps=timestamps,
        poses=poses,
        tracked_poses=state.tracked_poses.detach().cpu().double().numpy(),
        state=state,
        frames_per_second=(len(sequence) - start_frame) / max(elapsed, 1e-9),
    )
