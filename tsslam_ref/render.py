"""Rays, samples along rays and SDF volume rendering (Co-SLAM's ``render_rays``).

TS-SLAM §III-A (``sec:rep_secene``): Eq. (2) (``eq:cal_ray``) places the samples of pixel (u, v)
at x_i = t + d_i R K^-1 [u, v, 1]^T, and Eq. (3) renders colour and depth as weighted means

    c_hat = sum_i w_i c_i / sum_j w_j,     d_hat = sum_i w_i d_i / sum_j w_j,
    w_i   = sigmoid(s_i / tr) * sigmoid(-s_i / tr)

with two Co-SLAM details kept (``render_rays``, ``sdf2weights``): s_i is the *normalised*
SDF (so in metric terms the logistic scale is tr^2, "double scaling"), and every weight beyond
z_min + tr is cut, where z_min is the sample just before the first sign change of s.

Layer 1 (math and map): takes a callable ``field_fn(points) -> (rgb, sdf)``, never the field class.
Taught in notebooks/04_rendering_and_losses.ipynb.

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| K^-1 [u, v, 1] | ``directions_cam`` | (R, 3) | camera (OpenCV, z = 1) | - |
| t, R d | ``origins``, ``directions`` | (R, 3) | world | m, - |
| d_i | ``z_vals`` | (R, S) | camera depth | m |
| s_i | ``sdf`` | (R, S) | - | truncation units |
| w_i | ``weights`` | (R, S) | - | - |
| tr | ``truncation`` | scalar | - | m |

Pixel convention: pixel (row, col) is centred at image coordinates (u, v) = (col, row), OpenCV's
convention for calibrated intrinsics (Co-SLAM also uses the integer indices, without +0.5).
Sources: Co-SLAM @3bb904e ``model/scene_rep.py`` (``render_rays``), ``model/utils.py``
(``sdf2weights``), ``datasets/utils.py`` (ray directions).  Deviations: docs/map.md.
"""

import dataclasses
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
import torch

from .config import RenderConfig
from .geometry import pixel_to_ray

# Guard added to the weight sum before normalising (Co-SLAM sdf2weights); prevents 0/0 on rays
# whose every sample was cut.
WEIGHT_SUM_EPS = 1e-8

FieldFn = Callable[[torch.Tensor], Tuple[torch.Tensor, torch.Tensor]]


@dataclass
class RayBatch:
    """Rays in the camera frame plus their targets.

    Attributes:
        directions_cam: (R, 3) OpenCV camera-frame directions with z = 1 (ray parameter = depth).
        rgb: (R, 3) target colours in [0, 1].
        depth: (R,) target depth in metres, 0 = invalid.
        frame_ids: (R,) long, caller-defined ids (keyframe slot, frame index, ...).
    """

    directions_cam: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor
    frame_ids: torch.Tensor

    def __post_init__(self):
        n_rays = self.directions_cam.shape[0]
        if self.directions_cam.shape != (n_rays, 3):
            raise ValueError(f"RayBatch.directions_cam must be (R, 3), got {tuple(self.directions_cam.shape)}")
        for name, shape in (("rgb", (n_rays, 3)), ("depth", (n_rays,)), ("frame_ids", (n_rays,))):
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"RayBatch.{name} must be {shape}, got {tuple(getattr(self, name).shape)}")

    def __len__(self) -> int:
        return self.directions_cam.shape[0]

    def to(self, device) -> "RayBatch":
        return RayBatch(*(getattr(self, f.name).to(device) for f in dataclasses.fields(self)))

    def subset(self, index) -> "RayBatch":
        """Rays at ``index`` (a slice, boolean mask or long tensor)."""
        return RayBatch(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))

    @staticmethod
    def cat(batches: Sequence["RayBatch"]) -> "RayBatch":
        if len(batches) == 0:
            raise ValueError("RayBatch.cat needs at least one batch")
        return RayBatch(
            *(torch.cat([getattr(b, f.name) for b in batches]) for f in dataclasses.fields(RayBatch))
        )


def _intrinsic_values(intrinsics) -> Tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from an object with those attributes or a 4-sequence."""
    if all(hasattr(intrinsics, name) for name in ("fx", "fy", "cx", "cy")):
        return float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cx), float(intrinsics.cy)
    values = tuple(float(v) for v in intrinsics)
    if len(values) != 4:
        raise ValueError(f"intrinsics must have fx, fy, cx, cy; got {intrinsics!r}")
    return values


def pixel_directions(rows: torch.Tensor, cols: torch.Tensor, intrinsics) -> torch.Tensor:
    """Camera-frame ray directions K^-1 [u, v, 1]^T of pixels, OpenCV axes, z = 1.

        d = ((col - cx) / fx, (row - cy) / fy, 1)

    Args:
        rows, cols: (R,) pixel indices (any numeric dtype); the centre of pixel (row, col) is at
            (u, v) = (col, row) (OpenCV).  Intrinsics are used as given (not floored).
        intrinsics: ``tsslam_ref.data.Intrinsics`` or any object with ``fx fy cx cy``, or a tuple.

    Returns:
        (R, 3) float32 directions (float64 if ``rows`` is float64).

    Differs from: Co-SLAM uses OpenGL axes (y up, z backwards) and floors fx, fy, cx, cy.
    """
    fx, fy, cx, cy = _intrinsic_values(intrinsics)
    dtype = rows.dtype if rows.is_floating_point() else torch.float32
    return pixel_to_ray(cols.to(dtype), rows.to(dtype), fx, fy, cx, cy)  # (R, 3)


def check_image_size(height: int, width: int, intrinsics, what: str) -> None:
    """Refuse an image whose size is not that of ``intrinsics`` (when they carry ``width`` and
    ``height``; a bare (fx, fy, cx, cy) tuple carries no size): rays through the pixels of an image
    of another size point elsewhere, and every depth along them would be silently wrong."""
    expected = (getattr(intrinsics, "width", None), getattr(intrinsics, "height", None))
    if None not in expected and expected != (width, height):
        raise ValueError(f"{what} is {width}x{height} (W x H) but the intrinsics are for {expected[0]}x{expected[1]} "
                         f"images: pass the intrinsics of this size (Intrinsics.resized / .cropped)")


def sample_pixels(
    height: int, width: int, n: int, ignore_edge: int = 0, generator: Optional[torch.Generator] = None
) -> Tuple[torch.Tensor, torch.Tensor]:
    """n pixels drawn uniformly without replacement, ``ignore_edge`` px excluded on every side.

    Returns:
        (rows (n,), cols (n,)) long tensors on the generator's device (CPU without one).
    """
    inner_h, inner_w = height - 2 * ignore_edge, width - 2 * ignore_edge
    if inner_h <= 0 or inner_w <= 0:
        raise ValueError(f"ignore_edge={ignore_edge} leaves no pixels in a {height}x{width} image")
    if n > inner_h * inner_w or n < 0:
        raise ValueError(f"cannot sample {n} pixels from {inner_h * inner_w} available ({height}x{width}, edge {ignore_edge})")
    device = generator.device if generator is not None else None
    flat = torch.randperm(inner_h * inner_w, generator=generator, device=device)[:n]
    return flat // inner_w + ignore_edge, flat % inner_w + ignore_edge


def _as_tensor(array, device=None, dtype=torch.float32) -> torch.Tensor:
    if isinstance(array, np.ndarray):
        array = torch.from_numpy(np.ascontiguousarray(array))
    return array.to(device=device, dtype=dtype)


def frame_rays(rgb, depth, intrinsics, rows, cols, frame_id: int = 0, device=None) -> RayBatch:
    """RayBatch of the pixels (rows, cols) of one RGB-D frame.

    Args:
        rgb: (H, W, 3) float colours in [0, 1] (numpy or torch; integer images are refused).
        depth: (H, W) float depth in metres, 0 = invalid (integer PNG values are refused).
        intrinsics: see :func:`pixel_directions`.
        rows, cols: (R,) long pixel indices.
        frame_id: stored in every ray's ``frame_ids``.
        device: where the batch lives (default: that of ``rgb`` if a tensor, else CPU).
    """
    if device is None:
        device = rgb.device if isinstance(rgb, torch.Tensor) else "cpu"
    for name, image, expected in (("rgb", rgb, "colours in [0, 1]: divide 8-bit values by 255"),
                                  ("depth", depth, "metres: divide the PNG values by the depth scale")):
        if not (image.dtype.is_floating_point if isinstance(image, torch.Tensor) else image.dtype.kind == "f"):
            raise TypeError(f"frame_rays: {name} is {image.dtype}; expected floating-point {expected}")
    rgb_t = _as_tensor(rgb, device)
    depth_t = _as_tensor(depth, device)
    if rgb_t.dim() != 3 or rgb_t.shape[-1] != 3 or depth_t.shape != rgb_t.shape[:2]:
        raise ValueError(f"frame_rays expects rgb (H, W, 3) and depth (H, W), got {tuple(rgb_t.shape)} and {tuple(depth_t.shape)}")
    check_image_size(depth_t.shape[0], depth_t.shape[1], intrinsics, "frame_rays' depth image")
    rows = torch.as_tensor(rows, device=device).long()
    cols = torch.as_tensor(cols, device=device).long()
    return RayBatch(
        directions_cam=pixel_directions(rows, cols, intrinsics),
        rgb=rgb_t[rows, cols],
        depth=depth_t[rows, cols],
        frame_ids=torch.full_like(rows, int(frame_id)),
    )


def rays_to_world(directions_cam: torch.Tensor, c2w: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """World rays o = t_wc, d = R_wc d_cam; differentiable in ``c2w``.

    Args:
        directions_cam: (R, 3) camera-frame directions.
        c2w: (4, 4) one camera-to-world pose, or (R, 4, 4) one per ray.

    Returns:
        origins (R, 3) and directions (R, 3) in the world frame, in the promoted dtype.
    """
    if not isinstance(c2w, torch.Tensor):  # else torch.promote_types names a numpy dtype
        raise TypeError(f"c2w must be a torch tensor, got {type(c2w).__name__}: torch.as_tensor(c2w) converts it")
    dtype = torch.promote_types(directions_cam.dtype, c2w.dtype)
    directions_cam = directions_cam.to(dtype)
    c2w = c2w.to(dtype)
    if c2w.shape == (4, 4):
        directions = directions_cam @ c2w[:3, :3].T  # (R, 3)
        origins = c2w[:3, 3].expand_as(directions)
    elif c2w.dim() == 3 and c2w.shape[1:] == (4, 4) and c2w.shape[0] == directions_cam.shape[0]:
        directions = torch.einsum("rij,rj->ri", c2w[:, :3, :3], directions_cam)  # (R, 3)
        origins = c2w[:, :3, 3]
    else:
        raise ValueError(f"c2w must be (4, 4) or (R, 4, 4) with R = {directions_cam.shape[0]}, got {tuple(c2w.shape)}")
    return origins, directions


def sample_along_rays(
    target_depth: torch.Tensor, cfg: RenderConfig, generator: Optional[torch.Generator] = None
) -> torch.Tensor:
    """Depths of the S = n_range_d + n_samples samples of each ray, sorted (Co-SLAM's ``render_rays``).

    n_range_d samples evenly in [D - range_d, D + range_d] (in [near, far] where D <= 0), plus
    n_samples evenly in [near, far]; sorted; with ``cfg.perturb`` each sample is redrawn
    uniformly between the midpoints to its neighbours (the ends use their own value).

    Args:
        target_depth: (R,) sensor depth in metres (0 = invalid).

    Returns:
        z_vals (R, S) in metres, same dtype and device as ``target_depth``.
    """
    dtype, device = target_depth.dtype, target_depth.device
    n_rays = target_depth.shape[0]
    depth = target_depth.unsqueeze(-1)  # (R, 1)
    band = torch.linspace(-cfg.range_d, cfg.range_d, cfg.n_range_d, dtype=dtype, device=device)
    uniform = torch.linspace(cfg.near, cfg.far, cfg.n_range_d, dtype=dtype, device=device)
    z_guided = torch.where(depth > 0, depth + band, uniform)  # (R, n_range_d)
    t = torch.linspace(0.0, 1.0, cfg.n_samples, dtype=dtype, device=device)
    z_uniform = (cfg.near * (1.0 - t) + cfg.far * t).expand(n_rays, -1)  # (R, n_samples)
    z_vals, _ = torch.sort(torch.cat([z_uniform, z_guided], dim=-1), dim=-1)  # (R, S)
    if cfg.perturb:
        mids = 0.5 * (z_vals[:, 1:] + z_vals[:, :-1])
        upper = torch.cat([mids, z_vals[:, -1:]], dim=-1)
        lower = torch.cat([z_vals[:, :1], mids], dim=-1)
        rand_device = generator.device if generator is not None else device
        jitter = torch.rand(z_vals.shape, generator=generator, device=rand_device, dtype=dtype).to(device)
        z_vals = lower + (upper - lower) * jitter
    return z_vals


def sdf_to_weights(sdf: torch.Tensor, z_vals: torch.Tensor, truncation: float) -> torch.Tensor:
    """Rendering weights of Eq. (3) with Co-SLAM's first-surface cut and normalisation.

        w_i = sigmoid(s_i / tr) sigmoid(-s_i / tr)               (bell, max 1/4 at s = 0)
        z_min = z_k, k = first i with s_i s_{i+1} < 0            (k = 0 if there is none)
        w_i <- w_i [z_i < z_min + tr];   w_i <- w_i / (sum_j w_j + 1e-8)

    Args:
        sdf: (R, S) normalised SDF (metric = s * tr).
        z_vals: (R, S) sorted sample depths in metres.
        truncation: tr in metres.

    Returns:
        (R, S) weights; a row sums to W / (W + 1e-8) for the kept weights' sum W: to 1 only when
        a sample lies within a few truncations of the surface (depth-guided samples do); a row of
        evenly spaced samples farther apart than ``truncation`` can sum to much less (below 0.99
        on most rays of a fitted teddy frame at 32 samples over 5 m), and its depth comes out short.

    Differs from: the paper's formula reads s as metric; with Co-SLAM's normalised s this is a
    double scaling (metric logistic scale tr^2), kept as Co-SLAM's ``sdf2weights`` has it
    (docs/map.md). Also as Co-SLAM: a sample exactly at s = 0 makes both of its products 0, so it is
    no crossing; the bias-free MLP gives s = 0 exactly wherever all its hidden units are off.
    """
    weights = torch.sigmoid(sdf / truncation) * torch.sigmoid(-sdf / truncation)  # (R, S)
    sign_change = (sdf[:, 1:] * sdf[:, :-1] < 0).to(sdf.dtype)  # (R, S - 1)
    first = torch.argmax(sign_change, dim=-1, keepdim=True)  # (R, 1), 0 when no sign change
    z_min = torch.gather(z_vals, 1, first)  # (R, 1)
    weights = weights * (z_vals < z_min + truncation).to(weights.dtype)
    return weights / (weights.sum(dim=-1, keepdim=True) + WEIGHT_SUM_EPS)


def render_rays(
    field_fn: FieldFn,
    origins: torch.Tensor,
    directions: torch.Tensor,
    target_depth: torch.Tensor,
    cfg: RenderConfig,
    generator: Optional[torch.Generator] = None,
) -> Dict[str, torch.Tensor]:
    """Sample, query the field and composite (Eq. 2-3).

    Args:
        field_fn: points (N, 3) world -> (rgb (N, 3) in [0, 1], normalised sdf (N,)).
        origins, directions: (R, 3) world rays; ``directions`` have camera z = 1.
        target_depth: (R,) sensor depth (m) guiding the samples; 0 = invalid.
        cfg: RenderConfig (sample counts, range_d, near, far, truncation, perturb).

    Returns:
        dict rgb (R, 3), depth (R,), sdf (R, S), z_vals (R, S), weights (R, S).
    """
    n_rays = origins.shape[0]
    if origins.dim() != 2 or origins.shape[1] != 3 or directions.shape != origins.shape or \
            target_depth.shape != (n_rays,):
        raise ValueError(f"render_rays expects origins and directions (R, 3) and target_depth (R,), got "
                         f"{tuple(origins.shape)}, {tuple(directions.shape)} and {tuple(target_depth.shape)}")
    z_vals = sample_along_rays(target_depth.to(origins.dtype), cfg, generator)  # (R, S)
    points = origins.unsqueeze(1) + directions.unsqueeze(1) * z_vals.unsqueeze(-1)  # (R, S, 3)
    rgb, sdf = field_fn(points.reshape(-1, 3))
    rgb = rgb.reshape(n_rays, -1, 3)  # (R, S, 3)
    sdf = sdf.reshape(n_rays, -1)  # (R, S)
    z_vals = z_vals.to(sdf.dtype)
    weights = sdf_to_weights(sdf, z_vals, cfg.truncation)
    return {
        "rgb": (weights.unsqueeze(-1) * rgb).sum(dim=1),
        "depth": (weights * z_vals).sum(dim=1),
        "sdf": sdf,
        "z_vals": z_vals,
        "weights": weights,
    }


def _render_size(intrinsics, depth, height: Optional[int], width: Optional[int]) -> Tuple[int, int]:
    """(H, W) of :func:`render_image`: the depth's, else the arguments', else the intrinsics' (the
    first two checked against ``intrinsics`` when they carry a size)."""
    if depth is not None:
        check_image_size(depth.shape[0], depth.shape[1], intrinsics, "render_image's depth")
        return depth.shape[0], depth.shape[1]
    height = height if height is not None else getattr(intrinsics, "height", None)
    width = width if width is not None else getattr(intrinsics, "width", None)
    if height is None or width is None:
        raise ValueError("render_image needs the image size: intrinsics.width/height, height/width or depth")
    check_image_size(height, width, intrinsics, "render_image's height/width")
    return height, width


def render_image(
    field_fn: FieldFn,
    c2w: torch.Tensor,
    intrinsics,
    cfg: RenderConfig,
    depth: Optional[torch.Tensor] = None,
    chunk: Optional[int] = None,
    height: Optional[int] = None,
    width: Optional[int] = None,
) -> Dict[str, torch.Tensor]:
    """Render a full image without gradients, ``chunk`` rays at a time, with no jitter.

    Args:
        c2w: (4, 4) camera-to-world pose (OpenCV axes).
        intrinsics: with ``width``/``height`` attributes, or pass ``height``/``width`` or ``depth``;
            a ``depth`` of another size than ``intrinsics.width`` x ``height`` is refused.
        depth: optional (H, W) sensor depth guiding the samples (as in training); without it
            only the uniform samples in [near, far] are used (plus n_range_d more in [near, far]),
            and they must lie closer than ``cfg.truncation`` to find the surface: with ``tum-cpu``'s
            32 over 5 m (5 cm truncation) a fitted teddy frame rendered 0.68 m short (median), with
            ``n_samples=128`` 1 cm (:func:`sdf_to_weights`).
        chunk: rays per chunk (default ``cfg.chunk``).

    Returns:
        dict rgb (H, W, 3), depth (H, W) on ``c2w``'s device (a NumPy ``c2w``: the field's).
    """
    height, width = _render_size(intrinsics, depth, height, width)
    if not isinstance(c2w, torch.Tensor):  # a NumPy pose: onto the map's device (a module's parameters)
        parameter = next(iter(field_fn.parameters()), None) if isinstance(field_fn, torch.nn.Module) else None
        c2w = torch.as_tensor(c2w, device=None if parameter is None else parameter.device)
    if c2w.shape != (4, 4):
        raise ValueError(f"render_image renders one camera: c2w must be one (4, 4) camera-to-world pose, "
                         f"got {tuple(c2w.shape)}")
    chunk = chunk or cfg.chunk
    still_cfg = dataclasses.replace(cfg, perturb=False)
    device = c2w.device
    rows, cols = torch.meshgrid(
        torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij"
    )
    directions_cam = pixel_directions(rows.reshape(-1), cols.reshape(-1), intrinsics).to(c2w.dtype)
    target = (
        torch.as_tensor(depth, device=device).reshape(-1).to(c2w.dtype)
        if depth is not None
        else torch.zeros(height * width, device=device, dtype=c2w.dtype)
    )
    rgb_parts, depth_parts = [], []
    with torch.no_grad():
        for start in range(0, height * width, chunk):
            stop = start + chunk
            origins, directions = rays_to_world(directions_cam[start:stop], c2w)
            out = render_rays(field_fn, origins, directions, target[start:stop], still_cfg)
            rgb_parts.append(out["rgb"])
            depth_parts.append(out["depth"])
    return {
        "rgb": torch.cat(rgb_parts).reshape(height, width, 3),
        "depth": torch.cat(depth_parts).reshape(height, width),
    }
