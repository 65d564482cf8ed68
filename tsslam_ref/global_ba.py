"""Global bundle adjustment: the map and the keyframe poses (or control points), jointly.

TS-SLAM Sec. III-D "Global Bundle Adjustment": the map and "the control points corresponding to all
keyframes outside the sliding window" are optimised with the loss of local BA (Eq. 10), the dynamics
regulariser being applied outside the window.  It keeps Co-SLAM's global BA
(its ``coslam.py``, commit 3bb904e): per iteration ``mapping.n_rays`` rays drawn uniformly from
the union of the keyframe rays plus ``max(n_rays // n_kf, min_pixels_cur)`` rays of the current
frame, the feature-smoothness term, one map step per iteration, pose steps every
``pose_accum_step`` iterations.

* :func:`coslam_global_ba` - one free pose per keyframe, keyframe 0 fixed, the current frame's pose
  optimised iff ``optim_cur`` (with fewer than two keyframes only the map moves).  This is the
  Co-SLAM baseline and the "w/o B-S." ablation; ``held`` chooses other held poses (TS-SLAM's
  map update between spline intervals, ours).
* :func:`tsslam_global_ba` - the keyframes' poses are spline evaluations; only the control points
  older than the sliding window move (control point 0 follows control points 1 and 2 so that frame 0
  keeps its pose, the gauge Co-SLAM fixes by holding keyframe 0); L_DR is sampled over the time
  outside the window.

Layer 3 (optimiser): uses bundle, dynamics; never tracking or local_ba.
Taught in notebooks/07_global_ba.ipynb.
"""

from typing import Optional, Sequence, Tuple

import numpy as np
import torch

from .bundle import BAStats, DiscretePoses, KeyframeDatabase, SplinePoses, joint_optimization, with_slot
from .config import Config
from .dynamics import trajectory_dynamics_loss
from .render import RayBatch


def current_frame_share(cfg: Config, n_keyframes: int, n_available: int) -> int:
    """Current-frame rays per iteration: max(n_rays // n_kf, min_pixels_cur) (Co-SLAM 5.4)."""
    return min(n_available, max(cfg.mapping.n_rays // max(n_keyframes, 1), cfg.mapping.min_pixels_cur))


def coslam_global_ba(
    field_model: torch.nn.Module,
    map_optimizer: torch.optim.Optimizer,
    keyframes: KeyframeDatabase,
    keyframe_poses: torch.Tensor,
    current_rays: RayBatch,
    current_pose: torch.Tensor,
    cfg: Config,
    generator: Optional[torch.Generator] = None,
    held: Optional[np.ndarray] = None,
) -> Tuple[torch.Tensor, torch.Tensor, BAStats]:
    """Co-SLAM global BA.

    Args:
        keyframe_poses: (K, 4, 4) camera-to-world poses of the keyframe slots.
        current_rays: rays of the whole current frame (any ``frame_ids``).
        current_pose: (4, 4) its camera-to-world pose.
        held: (K + 1,) bool, the slots (keyframes, then the current frame) whose poses stay as
            given, replacing Co-SLAM's rule above (TS-SLAM's map update between two spline
            intervals, ``mapping.tsslam_map_every``, holds the keyframes the spline reaches).

    Returns:
        ((K, 4, 4) keyframe poses, (4, 4) current pose, stats), poses detached.
    """
    n_kf = len(keyframes)
    initial = torch.cat([keyframe_poses, current_pose.unsqueeze(0)], dim=0)
    fixed = torch.ones(n_kf + 1, dtype=torch.bool)
    if held is not None:
        fixed = torch.as_tensor(held, dtype=torch.bool).reshape(-1).clone()
        if fixed.shape[0] != n_kf + 1:
            raise ValueError(f"held must have one entry per keyframe plus the current frame ({n_kf + 1}), got {fixed.shape[0]}")
    elif n_kf >= 2:
        fixed[1:n_kf] = False
        fixed[n_kf] = not cfg.mapping.optim_cur
    poses = DiscretePoses(initial, fixed, cfg.mapping.lr_rot, cfg.mapping.lr_trans)
    sources = [(keyframes.rays(), cfg.mapping.n_rays),
               (with_slot(current_rays, n_kf), current_frame_share(cfg, n_kf, len(current_rays)))]
    stats = joint_optimization(field_model, map_optimizer, sources, poses, cfg, cfg.mapping.iters, generator,
                               pose_accum_step=cfg.mapping.pose_accum_step)
    result = poses.poses().detach()
    return result[:n_kf], result[n_kf], stats


def tsslam_global_ba(
    field_model: torch.nn.Module,
    map_optimizer: torch.optim.Optimizer,
    keyframes: KeyframeDatabase,
    keyframe_fallback_poses: torch.Tensor,
    control_rotations: torch.Tensor,
    control_translations: torch.Tensor,
    free_controls: Sequence[int],
    dt: float,
    t0: float,
    convention: str,
    current_rays: RayBatch,
    current_time: float,
    current_pose: torch.Tensor,
    cfg: Config,
    dynamics_range: Optional[Tuple[float, float]] = None,
    generator: Optional[torch.Generator] = None,
    start_pose: Optional[torch.Tensor] = None,
) -> Tuple[torch.Tensor, torch.Tensor, BAStats]:
    """TS-SLAM global BA over the map and the control points ``free_controls``.

    Args:
        keyframe_fallback_poses: (K, 4, 4) poses for keyframes the spline does not reach yet.
        control_rotations, control_translations: (N, 3, 3), (N, 3) current control points.
        free_controls: indices of the control points to optimise (outside the window).
        dt, t0, convention: the spline's timing.
        current_rays, current_time, current_pose: the current frame (its pose is the spline's if
            its time is inside the domain, else the given tracked pose; it is never a free pose).
        dynamics_range: (t_start, t_end) seconds where L_DR is sampled (outside the window), or
            None for no regulariser.
        start_pose: (4, 4) frame 0's pose the curve must keep starting at (control point 0 then
            follows points 1 and 2, :class:`bundle.SplinePoses`); None leaves point 0 as it is.

    Returns:
        ((N, 3, 3) rotations, (N, 3) translations, stats), detached.
    """
    n_kf = len(keyframes)
    slot_times = np.asarray(list(keyframes.timestamps) + [current_time], dtype=np.float64)
    fallback = torch.cat([keyframe_fallback_poses, current_pose.unsqueeze(0)], dim=0)
    poses = SplinePoses(control_rotations, control_translations, free_controls, dt, t0, convention,
                        slot_times, fallback, cfg.mapping.lr_rot, cfg.mapping.lr_trans, start_pose)
    extra = None
    if dynamics_range is not None and dynamics_range[1] > dynamics_range[0] and len(free_controls) > 0:
        extra = lambda: trajectory_dynamics_loss(poses.trajectory(), dynamics_range[0], dynamics_range[1], cfg.dynamics, generator)
    sources = [(keyframes.rays(), cfg.mapping.n_rays),
               (with_slot(current_rays, n_kf), current_frame_share(cfg, n_kf, len(current_rays)))]
    stats = joint_optimization(field_model, map_optimizer, sources, poses, cfg, cfg.mapping.iters, generator,
                               extra_loss=extra, pose_accum_step=cfg.mapping.pose_accum_step)
    rotations, translations = poses.control_points()
    return rotations.detach(), translations.detach(), stats
