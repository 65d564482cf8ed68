"""The reconstruction loss L_NeRF: Co-SLAM's five terms, and the one ``render_loss`` everyone uses.

TS-SLAM §III-A, Eq. (4) (``eq:lossfuc``): L_NeRF = L_rgb + L_d + L_sdf + L_fs + L_smooth, each
term weighted as in Co-SLAM @3bb904e:

    L_rgb    = mean_{r, ch} (a_r C_hat_r - a_r C_r)^2,  a_r = 1 (valid depth) or rgb_missing
               (Co-SLAM's boolean weight tensor stores any non-zero rgb_missing as 1: docs/deviations.md)
    L_d      = mean_{valid r} (D_hat_r - D_r)^2
    L_sdf    = (1 - n_sdf / n) mean_{r, i} m_sdf (z_i + s_i tr - D_r)^2     band |z - D| <= tr, D > 0
    L_fs     = (1 - n_fs / n)  mean_{r, i} m_fs (s_i - 1)^2                 front z < D - tr
    L_smooth = sum over lattice neighbours of |V(p) - V(p')|^2 / n_pts^3    hash features only

"valid" means 0 < D < depth_trunc; the SDF/free-space masks only need D > 0; samples behind the
band get no loss; n_fs, n_sdf count masked samples over the whole batch and n = n_fs + n_sdf.

Layer 2 (objective): imports config and render; the smoothness term uses the field it is given.
Tracking, local BA, global BA and first-frame mapping all call :func:`render_loss` with one
:class:`RenderLossSettings` (the rendering, the loss weights and the valid-depth limit).
Taught in notebooks/04_rendering_and_losses.ipynb.
Sources: Co-SLAM @3bb904e ``model/scene_rep.py`` (``forward``, losses), ``model/utils.py``
(``get_masks``, ``get_sdf_loss``), ``model/scene_rep.py`` ``smoothness``.
"""

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import torch

from .config import Config, LossConfig, RenderConfig
from .render import RayBatch, rays_to_world, render_rays


@dataclass(frozen=True)
class RenderLossSettings:
    """What :func:`render_loss` reads from the config; tracking, BA and mapping pass it through."""

    render: RenderConfig
    """Ray sampling and volume rendering (sample counts, near / far, truncation tr, jitter)."""
    loss: LossConfig
    """Weights of the terms of Eq. (4), the colour factor of rays without depth, the smoothness lattice."""
    depth_trunc: float
    """Depths (m) at or beyond this are invalid for L_rgb / L_d (``data.depth_trunc``)."""

    @classmethod
    def from_config(cls, cfg: Config) -> "RenderLossSettings":
        """The settings of a run's config: ``cfg.render``, ``cfg.loss``, ``cfg.data.depth_trunc``."""
        return cls(render=cfg.render, loss=cfg.loss, depth_trunc=cfg.data.depth_trunc)


def _masked_mean_square(residual: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """mean over the masked entries of residual^2; 0 (with a gradient path) if the mask is empty."""
    count = mask.sum()
    return (residual.square() * mask).sum() / count.clamp(min=1)


def sdf_masks(z_vals: torch.Tensor, target_depth: torch.Tensor, truncation: float):
    """Front (free-space) and band (SDF) sample masks of Co-SLAM's ``get_masks``.

    Args:
        z_vals: (R, S) sample depths (m); target_depth: (R,) sensor depth (m), 0 = invalid.

    Returns:
        front (R, S) bool: z < D - tr and D > 0;  band (R, S) bool: |z - D| <= tr and D > 0.
    """
    depth = target_depth.unsqueeze(-1).to(z_vals.dtype)  # (R, 1)
    has_depth = depth > 0
    front = (z_vals < depth - truncation) & has_depth
    back = z_vals > depth + truncation
    band = ~front & ~back & has_depth
    return front, band


def reconstruction_losses(
    rendered: Dict[str, torch.Tensor],
    target_rgb: torch.Tensor,
    target_depth: torch.Tensor,
    loss_cfg: LossConfig,
    truncation: float,
    depth_trunc: float,
) -> Dict[str, torch.Tensor]:
    """The four per-ray terms of Eq. (4), unweighted.

    Args:
        rendered: output of :func:`tsslam_ref.render.render_rays` (rgb, depth, sdf, z_vals).
        target_rgb: (R, 3) in [0, 1]; target_depth: (R,) metres, 0 = invalid.
        loss_cfg: uses ``rgb_missing``.
        truncation: tr (m); depth_trunc: depths at or beyond this are invalid for L_rgb / L_d.

    Returns:
        dict rgb, depth, sdf, fs of scalar tensors.
    """
    dtype = rendered["rgb"].dtype
    target_rgb = target_rgb.to(dtype)
    target_depth = target_depth.to(dtype)
    valid = (target_depth > 0) & (target_depth < depth_trunc)  # (R,)
    ones = torch.ones_like(target_depth)
    rgb_factor = torch.where(valid, ones, ones * loss_cfg.rgb_missing).unsqueeze(-1)  # (R, 1)
    rgb_loss = ((rendered["rgb"] * rgb_factor - target_rgb * rgb_factor) ** 2).mean()
    depth_loss = _masked_mean_square(rendered["depth"] - target_depth, valid.to(dtype))

    sdf, z_vals = rendered["sdf"], rendered["z_vals"]
    front, band = sdf_masks(z_vals, target_depth, truncation)
    n_front = front.sum().to(dtype)
    n_band = band.sum().to(dtype)
    n_total = (n_front + n_band).clamp(min=1)
    fs_factor = 1.0 - n_front / n_total
    sdf_factor = 1.0 - n_band / n_total
    front_f, band_f = front.to(dtype), band.to(dtype)
    fs_loss = ((sdf * front_f - front_f) ** 2).mean() * fs_factor
    depth_col = target_depth.unsqueeze(-1)  # (R, 1)
    sdf_loss = (((z_vals + sdf * truncation) * band_f - depth_col * band_f) ** 2).mean() * sdf_factor
    return {"rgb": rgb_loss, "depth": depth_loss, "sdf": sdf_loss, "fs": fs_loss}


def smoothness_lattice(bound: torch.Tensor, loss_cfg: LossConfig, generator=None) -> torch.Tensor:
    """World points (n-1, n-1, n-1, 3) of Co-SLAM's random smoothness lattice.

        o = m + U(0,1) (E - (n-1) v - 2m)  per axis;   delta ~ U(0,1)^3 shared
        p_ijk = bound_min + o + ((i, j, k) + delta) v,  i, j, k = 0..n-2
    """
    n, v, m = loss_cfg.smooth_pts, loss_cfg.smooth_vox, loss_cfg.smooth_margin
    extent = bound[:, 1] - bound[:, 0]  # (3,)
    rand_device = generator.device if generator is not None else bound.device
    draws = torch.rand(2, 3, generator=generator, device=rand_device, dtype=bound.dtype).to(bound.device)
    offset = m + draws[0] * (extent - (n - 1) * v - 2 * m)  # (3,)
    index = torch.arange(n - 1, device=bound.device, dtype=bound.dtype)
    grid = torch.stack(torch.meshgrid(index, index, index, indexing="ij"), dim=-1)  # (n-1, n-1, n-1, 3)
    return bound[:, 0] + offset + (grid + draws[1]) * v


def smoothness_loss(field, loss_cfg: LossConfig, generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """L_smooth: total variation of the hash-grid features on a random lattice, / n^3 (unweighted).

    Args:
        field: a :class:`tsslam_ref.field.SceneField` (uses ``bound`` and ``grid_features``).
    """
    points = smoothness_lattice(field.bound, loss_cfg, generator)
    side = points.shape[0]
    features = field.grid_features(points.reshape(-1, 3)).reshape(side, side, side, -1)
    tv_x = (features[1:] - features[:-1]).square().sum()
    tv_y = (features[:, 1:] - features[:, :-1]).square().sum()
    tv_z = (features[:, :, 1:] - features[:, :, :-1]).square().sum()
    return (tv_x + tv_y + tv_z) / loss_cfg.smooth_pts**3


def render_loss(
    field,
    rays: RayBatch,
    c2w: torch.Tensor,
    loss_settings: RenderLossSettings,
    generator: Optional[torch.Generator] = None,
    smoothness: bool = False,
) -> Tuple[torch.Tensor, Dict[str, float]]:
    """The one loss of tracking, BA and mapping: rays_to_world -> render_rays -> weighted Eq. (4).

    Args:
        field: callable points -> (rgb, sdf); needs ``bound``/``grid_features`` if ``smoothness``.
        rays: camera-frame rays and targets.
        c2w: (4, 4) or (R, 4, 4) camera-to-world poses (any float dtype; gradients flow).
        loss_settings: the rendering, the loss weights and the valid-depth limit.
        generator: random generator for the depth-sample jitter and the smoothness lattice.
        smoothness: add smooth_weight * L_smooth (Co-SLAM: global BA only).

    Returns:
        total (scalar tensor) and a dict of the weighted terms as floats.
    """
    render_cfg, loss_cfg = loss_settings.render, loss_settings.loss
    origins, directions = rays_to_world(rays.directions_cam, c2w)
    rendered = render_rays(field, origins, directions, rays.depth, render_cfg, generator)
    terms = reconstruction_losses(
        rendered, rays.rgb, rays.depth, loss_cfg, render_cfg.truncation, loss_settings.depth_trunc
    )
    weights = {
        "rgb": loss_cfg.rgb_weight,
        "depth": loss_cfg.depth_weight,
        "sdf": loss_cfg.sdf_weight,
        "fs": loss_cfg.fs_weight,
    }
    weighted = {name: weights[name] * terms[name] for name in weights}
    if smoothness:
        weighted["smooth"] = loss_cfg.smooth_weight * smoothness_loss(field, loss_cfg, generator)
    total = sum(weighted.values())
    return total, {name: float(value.detach()) for name, value in weighted.items()}
