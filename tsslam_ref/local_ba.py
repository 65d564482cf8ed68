"""Local bundle adjustment over a sliding window of B-spline control points.

TS-SLAM Sec. III-D "Local Bundle Adjustment" and Fig. 5.  Every ``dt`` of sequence time (one
control-point interval) the mapping step runs, coarse to fine:

1. **Curve approximation** (Eq. 11).  The new control point Phi_{i+1} is initialised from the
   tracked poses {T_i^k} of the frames in the newest interval [t_i, t_{i+1}) by least squares on
   ||Log(R_i^k^T R(t_i^k))|| and ||t_i^k - t(t_i^k)||, the older control points held fixed; in the
   first interval all four control points are fitted.  Before the fit the new point is placed by
   extrapolating the control polygon at constant velocity (ours: the fit alone is poorly
   conditioned because the new point's weight in that interval is B_3(u) <= 1/6), and the three
   newest points are fitted, not the new one alone (ours, :func:`curve_approximation`).
2. **Refinement with the map frozen.**  The ``M`` newest control points are optimised on the
   reconstruction loss of rays of every frame inside the window plus the dynamics regulariser
   L_DR sampled uniformly inside the window (Eq. 10).
3. **Joint refinement.**  The keyframes (every fifth frame) inside the window are optimised jointly
   with the map: the window's control points and the map move together.  Off by default
   (``local_ba.joint_iters = 0``, ours): it raised ATE on our synthetic sequences (docs/system.md,
   "TS-SLAM's ATE on clean synthetic data"); ``local_ba.joint_iters=10`` runs it.

Index convention: the paper's.  Control point k sits at t0 + k*dt; frame 0's time is the start of
the first interval, t_first = t0 + 2*dt, so interval n is [t_first + n*dt, t_first + (n+1)*dt) and
needs control points n..n+3.  Control point k shapes times [t_{k-1}, t_{k+3}); the window of the
``M`` newest points 0 <= N-M..N-1 therefore acts on [t_{N-M-1}, t_{N-1}) (Fig. 5: the RGB-D
observations in [t_{i+1-M}, t_{i+1})).

Ablations of paper Table V: ``local_ba.use_spline=False`` ("w/o B-S.") runs the same window stages
on discrete per-frame poses; ``local_ba.enabled=False`` ("w/o LBA") skips all three stages, so a new
control point is only the extrapolated control polygon and only global BA can correct it;
``local_ba.use_dynamics=False`` ("w/o DR") drops L_DR.

Layer 3 (optimiser): uses spline, dynamics, bundle; never tracking or global_ba.
Taught in notebooks/06_local_ba.ipynb.
"""

import dataclasses
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch

from . import spline as spline_module
from .bundle import BAStats, DiscretePoses, KeyframeDatabase, SplinePoses, joint_optimization, slotted
from .config import Config
from .dynamics import trajectory_dynamics_loss
from .geometry import make_pose, so3_exp, so3_log
from .render import RayBatch


N_ANCHOR_CONTROLS = 1
"""Control point 0 is never a free parameter: it follows control points 1 and 2 so that the curve
keeps starting at frame 0's pose (:attr:`SplineTrack.start_pose`, :func:`spline.first_control_point`),
the gauge Co-SLAM fixes by holding keyframe 0.  Every other control point moves in local and global
BA.  (An earlier version froze the three oldest points instead, which froze the whole first
interval at its constant-velocity fit; docs/system.md, "TS-SLAM's ATE on clean synthetic data".)"""


@dataclass
class SplineTrack:
    """The TS-SLAM trajectory being built: control points plus the interval bookkeeping.

    Attributes:
        dt: knot spacing (s).  t0: time of control point 0 (s), = first frame time - 2 dt.
        rotations: (N, 3, 3) control rotations; translations: (N, 3) control translations (world).
        intervals_done: number of intervals whose mapping step has run.
        start_pose: (4, 4) camera-to-world pose of frame 0 that the curve starts at (the gauge),
            set by the first interval's fit; None before.
    """

    dt: float
    t0: float
    rotations: torch.Tensor
    translations: torch.Tensor
    intervals_done: int = 0
    convention: str = "paper"
    start_pose: Optional[torch.Tensor] = None

    def with_controls(self, rotations: torch.Tensor, translations: torch.Tensor) -> "SplineTrack":
        """The same track with new (detached) control points."""
        return dataclasses.replace(self, rotations=rotations.detach(), translations=translations.detach())

    @classmethod
    def empty(cls, first_time: float, dt: float, like: torch.Tensor) -> "SplineTrack":
        """No control points yet; the first interval starts at ``first_time``."""
        return cls(dt=float(dt), t0=float(first_time) - 2.0 * float(dt),
                   rotations=like.new_zeros(0, 3, 3), translations=like.new_zeros(0, 3))

    @property
    def n_ctrl(self) -> int:
        return int(self.rotations.shape[0])

    def knot_time(self, k: int) -> float:
        """t_k = t0 + k dt (s)."""
        return self.t0 + k * self.dt

    def interval(self, n: int) -> Tuple[float, float]:
        """[start, end) of interval n (s): [t_{n+2}, t_{n+3})."""
        return self.knot_time(n + 2), self.knot_time(n + 3)

    def domain(self) -> Tuple[float, float]:
        """Valid time range of the current control points (empty if fewer than 4)."""
        if self.n_ctrl < 4:
            return (self.knot_time(2), self.knot_time(2))
        return spline_module.valid_time_range(self.n_ctrl, self.dt, self.t0, self.convention)

    def covers(self, times: np.ndarray) -> np.ndarray:
        """(M,) bool: which times the spline can evaluate."""
        start, end = self.domain()
        times = np.asarray(times, dtype=np.float64)
        return (times >= start) & (times < end) if self.n_ctrl >= 4 else np.zeros(times.shape, dtype=bool)

    def window_controls(self, window: int) -> List[int]:
        """Indices of the ``window`` newest control points, never the ``N_ANCHOR_CONTROLS`` oldest."""
        return list(range(max(N_ANCHOR_CONTROLS, self.n_ctrl - window), self.n_ctrl))

    def window_time_range(self, window: int) -> Tuple[float, float]:
        """Times shaped by the window's control points, clipped to the domain: [t_{N-M-1}, t_{N-1})."""
        start, end = self.domain()
        first = max(N_ANCHOR_CONTROLS, self.n_ctrl - window)
        return max(start, self.knot_time(first - 1)), end

    def poses(self, times: np.ndarray) -> torch.Tensor:
        """(M, 4, 4) camera-to-world spline poses at ``times`` (inside the domain)."""
        sample = spline_module.evaluate(self.rotations, self.translations, np.asarray(times, dtype=np.float64),
                                        self.dt, self.t0, convention=self.convention, derivatives=0)
        return make_pose(sample.rotation, sample.translation)

    def trajectory(self) -> "spline_module.BSplineTrajectory":
        return spline_module.BSplineTrajectory(self.rotations, self.translations, self.dt, self.t0, self.convention)


def extrapolate_control_point(track: SplineTrack) -> Tuple[torch.Tensor, torch.Tensor]:
    """Constant-velocity continuation of the control polygon: R_N = R_{N-1} R_{N-2}^T R_{N-1}, t_N = 2 t_{N-1} - t_{N-2}."""
    if track.n_ctrl < 2:
        return track.rotations[-1].clone(), track.translations[-1].clone()
    r_prev, r_last = track.rotations[-2], track.rotations[-1]
    t_prev, t_last = track.translations[-2], track.translations[-1]
    return r_last @ r_prev.transpose(-1, -2) @ r_last, 2.0 * t_last - t_prev


def constant_velocity_control_points(track: SplineTrack, times: np.ndarray, poses: torch.Tensor
                                     ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Four control points whose spline is the least-squares constant-velocity fit of the poses.

    With P_k = c + v dt (k - 1) and R_k = R_first Exp((k - 1) w dt) the paper-convention spline
    is exactly p(t) = c + v (t - t_first), R(t) = R_first Exp(w (t - t_first)) (spline.md 3.2), so
    fitting the velocity v and the body rate w to the first interval's poses is a linear,
    well-conditioned problem, whereas four free points fitted to one segment's noisy poses swing
    far off (a cubic extrapolated from a fraction of a second of data).  The line starts at the
    first pose (c = p_first, R_first its rotation): the spline then passes exactly through frame
    0's pose, which anchors the map as in Co-SLAM; :attr:`SplineTrack.start_pose` keeps it there.

    Args:
        times: (K,) float64 s, the first interval's frames (the first is frame 0).
        poses: (K, 4, 4) their camera-to-world poses.
    """
    first_time = track.knot_time(2)
    elapsed = torch.as_tensor(np.asarray(times, dtype=np.float64) - first_time)  # (K,)
    positions = poses[:, :3, 3].double()  # (K, 3)
    offset = positions[0]  # c: the line starts at the first pose
    first_rotation = poses[0, :3, :3].double()
    rotvecs = so3_log(first_rotation.transpose(-1, -2).unsqueeze(0) @ poses[:, :3, :3].double())  # (K, 3) body
    weight = elapsed.square().sum()  # least squares through the origin: x = sum(e y) / sum(e^2)
    if float(weight) > 0:
        velocity = (elapsed[:, None] * (positions - offset)).sum(0) / weight
        rate = (elapsed[:, None] * rotvecs).sum(0) / weight
    else:
        velocity = rate = torch.zeros(3, dtype=torch.float64)
    k = torch.arange(4, dtype=torch.float64)[:, None] - 1.0  # (4, 1)
    translations = offset + velocity * track.dt * k  # (4, 3)
    rotations = first_rotation @ so3_exp(rate * track.dt * k)  # (4, 3, 3)
    return rotations.to(poses.dtype), translations.to(poses.dtype)


def curve_approximation(track: SplineTrack, times: np.ndarray, poses: torch.Tensor, cfg: Config,
                        fit: bool = True) -> SplineTrack:
    """Add the control point of the next interval, Eq. (11).

    Args:
        track: the trajectory so far (``intervals_done`` intervals mapped).
        times: (K,) float64 timestamps of the frames to fit: those of the new interval and of the
            ``local_ba.fit_controls - 1`` intervals before it (:func:`fit_time_range`).
        poses: (K, 4, 4) their camera-to-world poses (tracked, or spline-refined for older frames).
        cfg: run config (``local_ba.fit_iters``, ``local_ba.fit_controls``).
        fit: False only extrapolates (the "w/o LBA" ablation).

    Returns:
        The track with 4 control points (first interval) or one more.

    Differs from the paper: Eq. (11) moves only the new control point Phi_{i+1}.  Its weight in
    the newest interval is B_3(u) = u^3/6 <= 1/6, so every misfit of that interval is pushed, six
    times larger, into Phi_{i+1}, which then dominates the next interval: the error grows about
    7x per interval (found while writing notebooks/06).  We place Phi_{i+1} by extrapolating the
    control polygon and then fit the ``fit_controls`` newest points (default 3) to the poses of the
    last ``fit_controls`` intervals, the older points fixed.  The newest interval depends on the
    four newest points, so with 3 the held point Phi_{N-4} still weighs up to 1/6 in it: its error
    is pushed, sign flipped, into the free points, and the approximation alone rings - an error
    of the first interval returns with alternating sign in every later interval, shrinking only
    ~12 % per interval.  Fitting 4 (the spline's order) stops that, but in the full system it
    raised ATE on TUM teddy (likely because it lets the newest tracked poses move a point that
    local and global BA have already refined), so the default stays 3 (``tests/test_local_ba.py``;
    docs/system.md, "The curve approximation rings").  The first interval is a constant-velocity fit
    (:func:`constant_velocity_control_points`).
    """
    poses = poses.detach()
    start_pose = track.start_pose
    if track.n_ctrl == 0:
        if len(times) == 0:
            raise ValueError("the first spline interval holds no frame")
        rotations, translations = constant_velocity_control_points(track, times, poses)
        start_pose = poses[0].clone()
    else:
        new_rotation, new_translation = extrapolate_control_point(track)
        rotations = torch.cat([track.rotations, new_rotation.unsqueeze(0)], dim=0)
        translations = torch.cat([track.translations, new_translation.unsqueeze(0)], dim=0)
        if fit and len(times) > 0:
            fixed = torch.ones(rotations.shape[0], dtype=torch.bool)
            fixed[-cfg.local_ba.fit_controls:] = False
            fixed[:N_ANCHOR_CONTROLS] = True
            rotations, translations = spline_module.fit_control_points(
                np.asarray(times, dtype=np.float64), poses, track.dt, track.t0, rotations.shape[0],
                init_rotations=rotations, init_translations=translations, fixed=fixed,
                iters=cfg.local_ba.fit_iters, convention=track.convention)
            rotations, translations = spline_module.pin_first_control_point(rotations, translations, start_pose)
    return dataclasses.replace(track, rotations=rotations.detach().to(poses.dtype),
                               translations=translations.detach().to(poses.dtype), start_pose=start_pose)


def fit_time_range(track: SplineTrack, n: int, cfg: Config) -> Tuple[float, float]:
    """[start, end) of the frames :func:`curve_approximation` fits when mapping interval ``n``."""
    start, end = track.interval(n)
    return max(track.interval(0)[0], start - (cfg.local_ba.fit_controls - 1) * track.dt), end


def window_dynamics(poses: SplinePoses, time_range: Tuple[float, float], cfg: Config,
                    generator: Optional[torch.Generator]):
    """L_DR over ``time_range`` for the control points held by ``poses`` (None when switched off)."""
    if not cfg.local_ba.use_dynamics or time_range[1] <= time_range[0]:
        return None
    return lambda: trajectory_dynamics_loss(poses.trajectory(), time_range[0], time_range[1], cfg.dynamics, generator)


def refine_window(field_model: torch.nn.Module, track: SplineTrack, frame_times: np.ndarray, frame_rays: Sequence[RayBatch],
                  cfg: Config, generator: Optional[torch.Generator] = None) -> Tuple[SplineTrack, BAStats]:
    """Stage 2: the window's control points on the window frames' rays, map frozen, L_DR in the window.

    Args:
        frame_times: (F,) float64 times of the frames whose rays are given (inside the window).
        frame_rays: F ray batches (any ``frame_ids``; relabelled to slots here).
    """
    window = track.window_controls(cfg.local_ba.window)
    time_range = track.window_time_range(cfg.local_ba.window)
    fallback = track.poses(frame_times)
    poses = SplinePoses(track.rotations, track.translations, window, track.dt, track.t0, track.convention,
                        frame_times, fallback, cfg.local_ba.lr_rot, cfg.local_ba.lr_trans, track.start_pose)
    pool = slotted(frame_rays)
    stats = joint_optimization(field_model, None, [(pool, cfg.local_ba.n_rays)], poses, cfg, cfg.local_ba.refine_iters,
                               generator, extra_loss=window_dynamics(poses, time_range, cfg, generator),
                               optimise_map=False, pose_accum_step=1)
    return track.with_controls(*poses.control_points()), stats


def joint_window(field_model: torch.nn.Module, map_optimizer: torch.optim.Optimizer, track: SplineTrack,
                 keyframes: KeyframeDatabase, cfg: Config,
                 generator: Optional[torch.Generator] = None) -> Tuple[SplineTrack, Optional[BAStats]]:
    """Stage 3: the window's keyframes, jointly with the map (control points in the window move)."""
    if cfg.local_ba.joint_iters <= 0:
        return track, None
    window = track.window_controls(cfg.local_ba.window)
    time_range = track.window_time_range(cfg.local_ba.window)
    kf_times = np.asarray(keyframes.timestamps, dtype=np.float64)
    slots = [s for s, t in enumerate(kf_times) if time_range[0] <= t < time_range[1]]
    if not slots:
        return track, None
    times = kf_times[slots]
    poses = SplinePoses(track.rotations, track.translations, window, track.dt, track.t0, track.convention,
                        times, track.poses(times), cfg.local_ba.lr_rot, cfg.local_ba.lr_trans, track.start_pose)
    stats = joint_optimization(field_model, map_optimizer, [(keyframes.rays(slots), cfg.local_ba.n_rays)], poses, cfg,
                               cfg.local_ba.joint_iters, generator,
                               extra_loss=window_dynamics(poses, time_range, cfg, generator), pose_accum_step=1)
    return track.with_controls(*poses.control_points()), stats


def refine_discrete_window(field_model: torch.nn.Module, map_optimizer: torch.optim.Optimizer, poses: torch.Tensor,
                           frame_rays: Sequence[RayBatch], keyframe_mask: Sequence[bool], cfg: Config,
                           generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """The "w/o B-S." ablation: stages 2 and 3 on discrete per-frame poses (no spline, no L_DR).

    Args:
        poses: (F, 4, 4) tracked poses of the window's frames.
        frame_rays: their rays.  keyframe_mask: (F,) which of them are keyframes.

    Returns:
        (F, 4, 4) refined poses.
    """
    fixed = torch.zeros(len(frame_rays), dtype=torch.bool)
    model = DiscretePoses(poses, fixed, cfg.local_ba.lr_rot, cfg.local_ba.lr_trans)
    pool = slotted(frame_rays)
    joint_optimization(field_model, None, [(pool, cfg.local_ba.n_rays)], model, cfg, cfg.local_ba.refine_iters,
                       generator, optimise_map=False, pose_accum_step=1)
    keyframe_slots = [slot for slot, is_kf in enumerate(keyframe_mask) if is_kf]
    if keyframe_slots and cfg.local_ba.joint_iters > 0:
        kf_pool = RayBatch.cat([pool.subset(torch.nonzero(pool.frame_ids == slot).squeeze(1)) for slot in keyframe_slots])
        joint_optimization(field_model, map_optimizer, [(kf_pool, cfg.local_ba.n_rays)], model, cfg,
                           cfg.local_ba.joint_iters, generator, pose_accum_step=1)
    return model.poses().detach()
