"""Map optimisation with fixed, known camera poses (Co-SLAM's first-frame mapping).

TS-SLAM §III-A (``sec:rep_secene``): "once f_theta converges, the construction of the map is
complete"; the map parameters theta minimise Eq. (4) (``eq:lossfuc``) over rays of posed frames.
Co-SLAM does this for frame 0 (``coslam.py``, first-frame mapping: ``first_iters`` iterations of
``mapping.first_n_rays`` rays drawn from the whole frame, pose fixed, no smoothness term) with one
Adam for the whole run.  The same function maps a sequence with ground-truth
poses, which separates map quality from tracking quality.

Layer 2 (objective): imports config, geometry, render and losses; not tracking or BA.
Taught in notebooks/04_rendering_and_losses.ipynb.

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| T_wc of frame f | ``poses[f]`` | (F, 4, 4) | camera -> world (OpenCV) | m |
| scene box | ``bound`` | (3, 2) | world | m |
"""

from typing import List, Optional, Sequence

import numpy as np
import torch

from .config import MappingConfig
from .geometry import pixel_to_ray
from .losses import RenderLossSettings, render_loss
from .render import RayBatch, _as_tensor, _intrinsic_values, rays_to_world

# Adam betas of Co-SLAM's map optimiser (``coslam.py``).
MAP_ADAM_BETAS = (0.9, 0.99)


def make_map_optimizer(field, mapping_cfg: MappingConfig) -> torch.optim.Adam:
    """Adam over the field: decoder lr_decoder + weight decay 1e-6, grid lr_embed + eps 1e-15.

    ``fused=True`` where the parameters' device and dtype allow it (much faster on CPU); otherwise
    the default implementation.
    """
    groups = field.parameter_groups(mapping_cfg)
    try:
        return torch.optim.Adam(groups, betas=MAP_ADAM_BETAS, fused=True)
    except (RuntimeError, ValueError):
        return torch.optim.Adam(groups, betas=MAP_ADAM_BETAS)


class FramePixels:
    """All pixels of a list of frames stacked once, for fast uniform ray sampling.

    Args:
        frames: objects with ``rgb`` (H, W, 3), ``depth`` (H, W) and ``intrinsics``; all frames
            must share one image size.
        device, dtype: where and in which precision the rays are produced.
    """

    def __init__(self, frames: Sequence, device=None, dtype=torch.float32):
        if len(frames) == 0:
            raise ValueError("no frames given")
        shapes = {tuple(np.shape(frame.depth)) for frame in frames}
        if len(shapes) != 1:
            raise ValueError(f"all frames must share one image size, got {sorted(shapes)}")
        self.height, self.width = shapes.pop()
        self.rgb = torch.stack([_as_tensor(f.rgb, device, dtype) for f in frames])  # (F, H, W, 3)
        self.depth = torch.stack([_as_tensor(f.depth, device, dtype) for f in frames])  # (F, H, W)
        self.intrinsics = torch.tensor(
            [_intrinsic_values(f.intrinsics) for f in frames], device=device, dtype=dtype
        )  # (F, 4): fx, fy, cx, cy
        self.n_frames = len(frames)

    def sample(self, n_rays: int, generator=None, ignore_edge: int = 0) -> RayBatch:
        """n_rays pixels uniformly without replacement over all frames' (inner) pixels."""
        inner_h, inner_w = self.height - 2 * ignore_edge, self.width - 2 * ignore_edge
        total = self.n_frames * inner_h * inner_w
        if inner_h <= 0 or inner_w <= 0 or n_rays > total:
            raise ValueError(f"cannot sample {n_rays} rays from {self.n_frames} frames of {self.height}x{self.width} with edge {ignore_edge}")
        rand_device = generator.device if generator is not None else None
        flat = torch.randperm(total, generator=generator, device=rand_device)[:n_rays].to(self.rgb.device)
        frame_ids = flat // (inner_h * inner_w)
        pixel = flat % (inner_h * inner_w)
        rows = pixel // inner_w + ignore_edge
        cols = pixel % inner_w + ignore_edge
        fx, fy, cx, cy = self.intrinsics[frame_ids].unbind(-1)
        directions = pixel_to_ray(cols.to(fx.dtype), rows.to(fx.dtype), fx, fy, cx, cy)  # (R, 3)
        return RayBatch(
            directions_cam=directions,
            rgb=self.rgb[frame_ids, rows, cols],
            depth=self.depth[frame_ids, rows, cols],
            frame_ids=frame_ids,
        )


def fit_map(
    field,
    optimizer: torch.optim.Optimizer,
    frames: Sequence,
    poses: torch.Tensor,
    loss_settings: RenderLossSettings,
    iters: int,
    n_rays: int,
    generator: Optional[torch.Generator] = None,
    smoothness: bool = False,
    progress: bool = False,
) -> List[float]:
    """Optimise the map on posed frames: ``iters`` Adam steps of :func:`render_loss`.

    Args:
        field: the SceneField being trained (its device and dtype are used).
        optimizer: e.g. :func:`make_map_optimizer` (kept across calls, as in Co-SLAM).
        frames: frames with rgb, depth, intrinsics; poses: (F, 4, 4) camera-to-world, fixed.
        loss_settings: rendering and loss settings of :func:`render_loss`.
        iters: Adam steps.
        n_rays: rays per iteration, drawn uniformly from all frames (no edge ignored, Co-SLAM).
        generator: random generator for the ray draws and the depth-sample jitter.
        smoothness: add the feature smoothness term (Co-SLAM uses it in BA only).
        progress: show a tqdm bar.

    Returns:
        the total loss of every iteration (floats).
    """
    device, dtype = field.bound.device, field.bound.dtype
    poses = torch.as_tensor(poses).to(device=device, dtype=dtype)
    if poses.shape != (len(frames), 4, 4):
        raise ValueError(f"poses must be ({len(frames)}, 4, 4) for {len(frames)} frames, got {tuple(poses.shape)}")
    pixels = FramePixels(frames, device, dtype)
    losses: List[float] = []
    steps = range(iters)
    if progress:
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc="fit_map")
    for _ in steps:
        rays = pixels.sample(n_rays, generator)
        optimizer.zero_grad(set_to_none=True)
        loss, _ = render_loss(field, rays, poses[rays.frame_ids], loss_settings, generator, smoothness=smoothness)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    return losses


def backproject_depth(frame, pose, stride: int = 1, max_depth: Optional[float] = None) -> np.ndarray:
    """World points (M, 3) of the valid depth pixels (0 < D < max_depth) of one frame."""
    depth = np.asarray(frame.depth, dtype=np.float64)[::stride, ::stride]
    fx, fy, cx, cy = _intrinsic_values(frame.intrinsics)
    valid = depth > 0 if max_depth is None else (depth > 0) & (depth < max_depth)
    rows, cols = np.nonzero(valid)
    z = depth[rows, cols]
    points_cam = pixel_to_ray(cols * stride, rows * stride, fx, fy, cx, cy) * z[:, None]  # (M, 3)
    pose = np.asarray(pose, dtype=np.float64)
    return points_cam @ pose[:3, :3].T + pose[:3, 3]


def estimate_bound(
    frames: Sequence, poses, margin: float, percentile: float = 0.5, stride: int = 2,
    max_depth: Optional[float] = None,
) -> np.ndarray:
    """Scene box (3, 2) from back-projected valid depth: robust percentiles, then +- margin.

    Args:
        frames: frames with depth (H, W) and intrinsics; poses: (F, 4, 4) camera-to-world.
        margin: metres added on every side.
        percentile: the lower/upper percentiles used per axis (``percentile``, 100 - ``percentile``)
            so that a few flying pixels do not inflate the box.
        stride: pixel subsampling.
        max_depth: ignore depth at or beyond this (e.g. ``cfg.data.depth_trunc``); None keeps all.

    Returns:
        float64 array [[xmin, xmax], [ymin, ymax], [zmin, zmax]] in metres.  Camera centres are
        included so that every camera lies inside the box.
    """
    poses = np.asarray(poses.detach().cpu() if isinstance(poses, torch.Tensor) else poses, dtype=np.float64)
    frames = list(frames)
    if poses.shape != (len(frames), 4, 4):
        raise ValueError(f"estimate_bound needs one (4, 4) camera-to-world pose per frame: {len(frames)} frame(s), "
                         f"poses of shape {poses.shape}, expected ({len(frames)}, 4, 4)")
    clouds = [backproject_depth(frame, pose, stride, max_depth) for frame, pose in zip(frames, poses)]
    points = np.concatenate(clouds)
    if points.shape[0] == 0:
        raise ValueError("estimate_bound: no valid depth pixel in the given frames")
    low = np.percentile(points, percentile, axis=0)
    high = np.percentile(points, 100.0 - percentile, axis=0)
    low = np.minimum(low, poses[:, :3, 3].min(axis=0))
    high = np.maximum(high, poses[:, :3, 3].max(axis=0))
    return np.stack([low - margin, high + margin], axis=-1)


def share_outside_bound(bound: torch.Tensor, rays: RayBatch, pose: torch.Tensor, max_depth: float) -> float:
    """Share of the rays' measured surface points (0 < depth < ``max_depth``) outside ``bound``.

    The map's box is set once, from frame 0's view (:func:`estimate_bound`); a camera that later
    looks at a part of the scene beyond it sees surface the map cannot hold (on the coarse levels
    such points wrap around the grid, as tiny-cuda-nn's do).  The loop records this share per
    tracked frame and the run warns when it is large.

    Args:
        bound: (3, 2) [[xmin, xmax], ...] metres.  rays: (R,) camera-frame rays with measured depth.
        pose: (4, 4) camera-to-world.  max_depth: depth at and beyond which a ray is not counted.

    Returns:
        The share in [0, 1]; 0 when no ray has a measured depth below ``max_depth``.
    """
    measured = (rays.depth > 0) & (rays.depth < max_depth)
    origins, directions = rays_to_world(rays.directions_cam[measured], pose)
    points = origins + directions * rays.depth[measured].unsqueeze(-1).to(directions.dtype)  # (M, 3) world
    box = bound.to(points)
    outside = ((points < box[:, 0]) | (points > box[:, 1])).any(dim=-1)
    return float(outside.float().mean()) if len(outside) else 0.0
