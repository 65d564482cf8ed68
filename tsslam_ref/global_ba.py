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
  Co-SLAM baseline and the "w/o B-S." ablation; ``fixed`` chooses other fixed poses (TS-SLAM's
  map update between spline intervals, ours).
* :func:`tsslam_global_ba` - the keyframes' poses are spline evaluations; only the control points
  older than the sliding window move (control point 0 follows control points 1 and 2 so that frame 0
  keeps its pose, the gauge Co-SLAM fixes by holding keyframe 0); L_DR is sampled over the time
  outside the window.

Layer 3 (optimiser): uses bundle, trajectory, losses (its settings type); never tracking or local_ba.
Taught in notebooks/07_global_ba.ipynb.
"""

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import torch

from .bundle import BAStats, DiscretePoses, KeyframeDatabase, SplinePoses, dynamics_term, joint_optimization, with_slot
from .config import DynamicsConfig, MappingConfig
from .losses import RenderLossSettings
from .render import RayBatch
from .times import float64_seconds
from .trajectory import BSplineTrajectory


@dataclass
class CurrentFrame:
    """The frame whose arrival triggered global BA: all its rays, its time and its pose."""

    rays: RayBatch
    """(H*W,) camera-frame rays of every pixel (any ``frame_ids``)."""
    timestamp: float
    """Seconds (float64)."""
    pose: torch.Tensor
    """(4, 4) camera-to-world pose (tracked, or as the last BA left it)."""


def current_frame_share(mapping: MappingConfig, n_keyframes: int, n_available: int) -> int:
    """Current-frame rays per iteration: max(n_rays // n_kf, min_pixels_cur) (Co-SLAM 5.4), at
    most ``n_available``."""
    return min(n_available, max(mapping.n_rays // max(n_keyframes, 1), mapping.min_pixels_cur))


def ray_sources(keyframes: KeyframeDatabase, current: CurrentFrame, mapping: MappingConfig):
    """Per-iteration ray draws: ``mapping.n_rays`` from all keyframes (slots 0..K-1) and the
    current frame's share (slot K)."""
    n_kf = len(keyframes)
    return [(keyframes.rays(), mapping.n_rays),
            (with_slot(current.rays, n_kf), current_frame_share(mapping, n_kf, len(current.rays)))]


def coslam_global_ba(
    field_model: torch.nn.Module,
    map_optimizer: torch.optim.Optimizer,
    keyframes: KeyframeDatabase,
    keyframe_poses: torch.Tensor,
    current: CurrentFrame,
    mapping: MappingConfig,
    loss_settings: RenderLossSettings,
    generator: Optional[torch.Generator] = None,
    fixed: Optional[np.ndarray] = None,
) -> Tuple[torch.Tensor, torch.Tensor, BAStats]:
    """Co-SLAM global BA.

    Args:
        keyframe_poses: (K, 4, 4) camera-to-world poses of the keyframe slots.
        current: the current frame (its pose is slot K).
        mapping: ``iters``, ``n_rays``, ``min_pixels_cur``, learning rates, ``pose_accum_step``,
            ``optim_cur``.
        loss_settings: rendering and loss settings of ``losses.render_loss``.
        generator: random generator for ray draws and depth-sample jitter.
        fixed: (K + 1,) bool, the slots (keyframes, then the current frame) whose poses stay as
            given, replacing Co-SLAM's rule (keyframe 0, and the current frame unless
            ``optim_cur``); TS-SLAM's map update between two spline intervals fixes the keyframes
            the spline reaches.

    Returns:
        ((K, 4, 4) keyframe poses, (4, 4) current pose, stats), poses detached.
    """
    n_kf = len(keyframes)
    initial = torch.cat([keyframe_poses, current.pose.unsqueeze(0)], dim=0)
    fixed_slots = torch.ones(n_kf + 1, dtype=torch.bool)
    if fixed is not None:
        fixed_slots = torch.as_tensor(fixed, dtype=torch.bool).reshape(-1).clone()
        if fixed_slots.shape[0] != n_kf + 1:
            raise ValueError(f"fixed must have one entry per keyframe plus the current frame ({n_kf + 1}), "
                             f"got {fixed_slots.shape[0]}")
    elif n_kf >= 2:
        fixed_slots[1:n_kf] = False
        fixed_slots[n_kf] = not mapping.optim_cur
    poses = DiscretePoses(initial, fixed_slots, mapping.lr_rot, mapping.lr_trans)
    stats = joint_optimization(field_model, map_optimizer, ray_sources(keyframes, current, mapping), poses,
                               loss_settings, mapping.iters, generator, pose_accum_step=mapping.pose_accum_step)
    result = poses.poses().detach()
    return result[:n_kf], result[n_kf], stats


def tsslam_global_ba(
    field_model: torch.nn.Module,
    map_optimizer: torch.optim.Optimizer,
    keyframes: KeyframeDatabase,
    keyframe_poses: torch.Tensor,
    trajectory: BSplineTrajectory,
    free_controls: Sequence[int],
    current: CurrentFrame,
    mapping: MappingConfig,
    dynamics: DynamicsConfig,
    loss_settings: RenderLossSettings,
    dynamics_range: Optional[Tuple[float, float]] = None,
    generator: Optional[torch.Generator] = None,
) -> Tuple[BSplineTrajectory, BAStats]:
    """TS-SLAM global BA over the map and the control points ``free_controls``.

    Args:
        keyframe_poses: (K, 4, 4) poses used for keyframes the trajectory does not reach yet.
        trajectory: the current trajectory (its start pose, if any, keeps frame 0's pose:
            control point 0 then follows points 1 and 2, :class:`bundle.SplinePoses`).
        free_controls: indices of the control points to optimise (outside the window).
        current: the current frame (its pose is the spline's if its time is inside the domain,
            else the given one; it is never a free pose).
        mapping: as in :func:`coslam_global_ba` (``optim_cur`` is not used).
        dynamics: the limits of L_DR.
        loss_settings: rendering and loss settings of ``losses.render_loss``.
        dynamics_range: (t_start, t_end) seconds where L_DR is sampled (outside the window), or
            None for no regulariser.
        generator: random generator for ray draws, depth-sample jitter and L_DR sample times.

    Returns:
        (the optimised trajectory, detached; stats).
    """
    slot_times = np.append(keyframes.timestamps, float64_seconds(current.timestamp, "current.timestamp"))
    fallback = torch.cat([keyframe_poses, current.pose.unsqueeze(0)], dim=0)
    poses = SplinePoses(trajectory, free_controls, slot_times, fallback, mapping.lr_rot, mapping.lr_trans)
    stats = joint_optimization(field_model, map_optimizer, ray_sources(keyframes, current, mapping), poses,
                               loss_settings, mapping.iters, generator,
                               extra_loss=dynamics_term(poses, dynamics_range, dynamics, generator),
                               pose_accum_step=mapping.pose_accum_step)
    return poses.trajectory().detach(), stats
