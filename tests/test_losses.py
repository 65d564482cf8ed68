"""Tests for tsslam_ref.losses: the five Co-SLAM terms and render_loss."""

import dataclasses

import pytest
import torch

from tsslam_ref import config
from tsslam_ref.config import FieldConfig
from tsslam_ref.field import SceneField
from tsslam_ref.geometry import make_pose, so3_exp
from tsslam_ref.losses import RenderLossSettings, reconstruction_losses, render_loss, smoothness_lattice, smoothness_loss
from tsslam_ref.render import RayBatch, pixel_directions, rays_to_world, render_rays, sample_pixels

TR = 0.1


def _rendered(z_vals, sdf, rgb, depth):
    return {"z_vals": z_vals, "sdf": sdf, "rgb": rgb, "depth": depth}


def test_every_loss_is_zero_at_ground_truth():
    z = torch.linspace(0.0, 3.0, 31, dtype=torch.float64).expand(4, 31)
    target_depth = torch.tensor([1.0, 2.0, 0.0, 6.0], dtype=torch.float64)  # invalid, beyond trunc
    depth_col = target_depth.unsqueeze(-1)
    # ideal normalised SDF: 1 in front of the band, (D - z) / tr inside it, anything behind
    sdf = torch.where(z < depth_col - TR, torch.ones_like(z), (depth_col - z) / TR)
    sdf[2] = 0.37  # a ray without depth: nothing constrains it
    target_rgb = torch.rand(4, 3, dtype=torch.float64)
    losses = reconstruction_losses(
        _rendered(z, sdf, target_rgb.clone(), target_depth.clone()), target_rgb, target_depth,
        config.tum().loss, TR, depth_trunc=5.0,
    )
    for name in ("rgb", "depth", "sdf", "fs"):
        assert losses[name].item() == pytest.approx(0.0, abs=1e-20), name


def test_masks_balancing_factors_and_rgb_missing_match_a_hand_computation():
    """Two rays written out sample by sample; every term recomputed with Python loops."""
    z = torch.tensor([[0.5, 0.85, 0.95, 1.0, 1.05, 1.3], [0.2, 0.4, 0.6, 0.8, 1.0, 1.2]], dtype=torch.float64)
    target_depth = torch.tensor([1.0, 0.0], dtype=torch.float64)
    sdf = torch.tensor([[0.5, 0.2, 0.3, -0.1, 0.4, -2.0], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]], dtype=torch.float64)
    rgb = torch.tensor([[0.2, 0.4, 0.6], [0.9, 0.1, 0.5]], dtype=torch.float64)
    target_rgb = torch.tensor([[0.3, 0.4, 0.5], [0.1, 0.1, 0.1]], dtype=torch.float64)
    depth = torch.tensor([1.2, 0.7], dtype=torch.float64)
    loss_cfg = dataclasses.replace(config.synthetic().loss, rgb_missing=0.05)
    out = reconstruction_losses(_rendered(z, sdf, rgb, depth), target_rgb, target_depth, loss_cfg, TR, 100.0)

    # ray 0 (D = 1): front z < 0.9 -> samples 0, 1; band |z - 1| <= 0.1 -> 2, 3, 4; behind -> 5
    # ray 1 has no depth -> no SDF / free-space samples at all
    n_front, n_band = 2, 3
    fs_factor, sdf_factor = 1 - n_front / 5, 1 - n_band / 5
    fs = sum((sdf[0, i].item() - 1) ** 2 for i in (0, 1)) / 12 * fs_factor
    band = sum((z[0, i].item() + sdf[0, i].item() * TR - 1.0) ** 2 for i in (2, 3, 4)) / 12 * sdf_factor
    rgb_expected = (sum((rgb[0] - target_rgb[0]) ** 2) + 0.05**2 * sum((rgb[1] - target_rgb[1]) ** 2)) / 6
    assert out["fs"].item() == pytest.approx(fs, rel=1e-12)
    assert out["sdf"].item() == pytest.approx(band, rel=1e-12)
    assert out["rgb"].item() == pytest.approx(rgb_expected.item(), rel=1e-12)
    assert out["depth"].item() == pytest.approx((1.2 - 1.0) ** 2, rel=1e-12)  # valid ray only


def test_depth_beyond_trunc_keeps_sdf_losses_but_no_depth_loss():
    z = torch.linspace(0.0, 7.0, 71, dtype=torch.float64).unsqueeze(0)
    target_depth = torch.tensor([6.0], dtype=torch.float64)
    sdf = torch.full_like(z, 0.5)
    out = reconstruction_losses(
        _rendered(z, sdf, torch.zeros(1, 3, dtype=torch.float64), torch.tensor([3.0], dtype=torch.float64)),
        torch.ones(1, 3, dtype=torch.float64), target_depth, config.tum().loss, 0.05, depth_trunc=5.0,
    )
    assert out["depth"].item() == 0.0
    assert out["fs"].item() > 0 and out["sdf"].item() > 0
    assert out["rgb"].item() == pytest.approx(1.0)  # TUM rgb_missing = 1


def _small_field(dtype=torch.float64, seed=0):
    cfg = config.tiny()
    field = SceneField(cfg.field, [[-1.5, 1.5], [-1.5, 1.5], [0.0, 3.0]], generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        field.grid.table.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(seed + 1))
    return field.to(dtype), cfg


def test_render_loss_pose_gradient_matches_central_differences():
    field, cfg = _small_field()
    cfg.render = dataclasses.replace(cfg.render, perturb=False)
    rows, cols = sample_pixels(48, 64, 64, generator=torch.Generator().manual_seed(2))
    intrinsics = (40.0, 40.0, 31.5, 23.5)
    rays = RayBatch(
        directions_cam=pixel_directions(rows, cols, intrinsics).double(),
        rgb=torch.rand(64, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3)),
        depth=1.0 + torch.rand(64, dtype=torch.float64, generator=torch.Generator().manual_seed(4)),
        frame_ids=torch.zeros(64, dtype=torch.long),
    )
    # (a translation like 0.1 would put the z = 0 samples exactly on a grid vertex plane: a kink)
    params = torch.tensor([0.02, -0.03, 0.01, 0.0517, -0.0213, 0.1234], dtype=torch.float64)

    def loss_of(p):
        return render_loss(field, rays, make_pose(so3_exp(p[:3]), p[3:]), RenderLossSettings.from_config(cfg))[0]

    p = params.clone().requires_grad_(True)
    loss_of(p).backward()
    step = 1e-6
    numeric = torch.stack([
        (loss_of(params + step * e) - loss_of(params - step * e)) / (2 * step)
        for e in torch.eye(6, dtype=torch.float64)
    ])
    assert p.grad.abs().max() > 1e-3  # the check is not vacuous
    assert torch.allclose(p.grad, numeric, rtol=1e-4, atol=1e-6)


def test_render_loss_is_the_weighted_sum_of_the_terms():
    """Every returned term is its weight times the unweighted term, and the total their sum.
    Oracle: render_rays, reconstruction_losses and smoothness_loss called here on the same rays and
    the same generator state, weighted with distinct weights set here (a weight read for the wrong
    term, or left out, changes a term by a factor 3 or more)."""
    field, cfg = _small_field(torch.float32)
    weights = {"rgb": 3.0, "depth": 0.3, "sdf": 170.0, "fs": 23.0, "smooth": 0.1}  # pairwise ratios >= 3, none near 1
    cfg.loss = dataclasses.replace(cfg.loss, **{f"{name}_weight": weight for name, weight in weights.items()})
    rows, cols = sample_pixels(48, 64, 32, generator=torch.Generator().manual_seed(0))
    rays = RayBatch(pixel_directions(rows, cols, (40.0, 40.0, 31.5, 23.5)), torch.rand(32, 3), 1 + torch.rand(32),
                    torch.zeros(32, dtype=torch.long))
    pose = torch.eye(4, dtype=torch.float64)
    settings = RenderLossSettings.from_config(cfg)
    for smoothness in (False, True):
        total, terms = render_loss(field, rays, pose, settings, torch.Generator().manual_seed(0), smoothness=smoothness)
        generator = torch.Generator().manual_seed(0)
        with torch.no_grad():
            origins, directions = rays_to_world(rays.directions_cam, pose)
            rendered = render_rays(field, origins, directions, rays.depth, cfg.render, generator)
            unweighted = {name: float(value) for name, value in reconstruction_losses(
                rendered, rays.rgb, rays.depth, cfg.loss, cfg.render.truncation, cfg.data.depth_trunc).items()}
            if smoothness:
                unweighted["smooth"] = float(smoothness_loss(field, cfg.loss, generator))
        assert set(terms) == set(unweighted) == {"rgb", "depth", "sdf", "fs"} | ({"smooth"} if smoothness else set())
        for name, value in unweighted.items():
            assert value > 0, name  # a zero term would hide its weight
            assert terms[name] == pytest.approx(weights[name] * value, rel=1e-5), name
        assert total.item() == pytest.approx(sum(weights[name] * value for name, value in unweighted.items()), rel=1e-5)
    assert terms["smooth"] > 0.1 * total.item()  # the smoothness term shows in the total


def _linear_feature_field():
    """All levels dense, every table row set to A^T x_n of its vertex: features are linear."""
    cfg = FieldConfig(n_levels=3, base_resolution=16, log2_hashmap_size=20, voxel_sdf=0.05)
    field = SceneField(cfg, [[0.0, 2.0], [0.0, 2.5], [0.0, 3.0]]).double()
    grid = field.grid
    coefficients = torch.tensor([[0.3, -1.1], [0.7, 0.2], [-0.4, 0.9]], dtype=torch.float64)
    with torch.no_grad():
        for level in range(grid.n_levels):
            assert grid.level_dense[level]
            axis = torch.arange(grid.level_resolutions[level])
            vertex = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
            grid.table[grid.level_index(level, vertex)] = ((vertex.double() - 0.5) / grid.level_scales[level]) @ coefficients
    return field, coefficients


def test_render_loss_settings_take_the_depth_limit_from_the_data_config():
    """data.depth_trunc reaches render_loss: with every target depth beyond it L_d is 0 and L_rgb
    is scaled by rgb_missing^2 (the mean of the squared colour error, computed here by hand)."""
    field, cfg = _small_field(torch.float64)
    cfg.render = dataclasses.replace(cfg.render, perturb=False)
    rows, cols = sample_pixels(48, 64, 32, generator=torch.Generator().manual_seed(0))
    rays = RayBatch(pixel_directions(rows, cols, (40.0, 40.0, 31.5, 23.5)).double(),
                    torch.rand(32, 3, dtype=torch.float64), 1 + torch.rand(32, dtype=torch.float64),
                    torch.zeros(32, dtype=torch.long))
    pose = torch.eye(4, dtype=torch.float64)
    cfg.data.depth_trunc = 100.0
    _, kept = render_loss(field, rays, pose, RenderLossSettings.from_config(cfg))
    cfg.data.depth_trunc = 0.5  # every target depth (1-2 m) is now invalid
    settings = RenderLossSettings.from_config(cfg)
    assert settings.depth_trunc == 0.5 and settings.render is cfg.render and settings.loss is cfg.loss
    _, cut = render_loss(field, rays, pose, settings)
    assert kept["depth"] > 0 and cut["depth"] == 0.0
    assert cut["rgb"] == pytest.approx(kept["rgb"] * cfg.loss.rgb_missing**2, rel=1e-9)
    assert cut["sdf"] == pytest.approx(kept["sdf"], rel=1e-12)  # the SDF masks only need D > 0


def test_smoothness_of_linear_features_matches_the_analytic_total_variation():
    field, coefficients = _linear_feature_field()
    loss_cfg = dataclasses.replace(config.synthetic().loss, smooth_pts=8, smooth_vox=0.1, smooth_margin=0.05)
    loss = smoothness_loss(field, loss_cfg, torch.Generator().manual_seed(0))
    n, v = 8, 0.1
    extent = torch.tensor([2.0, 2.5, 3.0], dtype=torch.float64)
    pairs_per_axis = (n - 1) ** 2 * (n - 2)
    per_pair = ((v / extent).unsqueeze(-1) * coefficients).square().sum(-1) * field.grid.n_levels  # (3,)
    expected = pairs_per_axis * per_pair.sum() / n**3
    assert loss.item() == pytest.approx(expected.item(), rel=1e-9)


def test_smoothness_lattice_geometry_and_constant_features_give_zero():
    bound = torch.tensor([[0.0, 4.0], [1.0, 3.0], [-1.0, 2.0]], dtype=torch.float64)
    loss_cfg = dataclasses.replace(config.synthetic().loss, smooth_pts=6, smooth_vox=0.1, smooth_margin=0.05)
    points = smoothness_lattice(bound, loss_cfg, torch.Generator().manual_seed(1))
    assert points.shape == (5, 5, 5, 3)
    assert torch.allclose(points[1:] - points[:-1], torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64).expand(4, 5, 5, 3))
    assert bool((points.reshape(-1, 3) >= bound[:, 0] + 0.05).all())
    assert bool((points.reshape(-1, 3) <= bound[:, 1] - 0.05).all())
    field, _ = _small_field()
    with torch.no_grad():
        field.grid.table.fill_(0.3)
    assert smoothness_loss(field, loss_cfg, torch.Generator().manual_seed(0)).item() == pytest.approx(0.0, abs=1e-20)


def test_samples_exactly_on_the_band_edges_and_a_depth_exactly_at_the_limit():
    """Co-SLAM's get_masks: front is z < D - tr, behind is z > D + tr, so both edges z = D -+ tr
    belong to the band; a depth equal to depth_trunc is invalid for L_d and L_rgb.  Oracle: one ray,
    D = 1, tr = 0.25, samples 0.5, 0.75, 1.0, 1.25, 1.5 (all exact in binary): 1 front, 3 band, 1
    behind; the terms written out by hand (SDF 0 everywhere, so the band residual is z - D)."""
    z = torch.tensor([[0.5, 0.75, 1.0, 1.25, 1.5]], dtype=torch.float64)
    target_depth = torch.tensor([1.0], dtype=torch.float64)
    rendered = _rendered(z, torch.zeros_like(z), torch.zeros(1, 3, dtype=torch.float64), torch.tensor([0.5], dtype=torch.float64))
    loss_cfg = dataclasses.replace(config.synthetic().loss, rgb_missing=0.5)
    out = reconstruction_losses(rendered, torch.ones(1, 3, dtype=torch.float64), target_depth, loss_cfg, 0.25, 1.0)
    n_front, n_band = 1, 3
    assert out["fs"].item() == pytest.approx((0 - 1) ** 2 / 5 * (1 - n_front / 4), rel=1e-12)
    assert out["sdf"].item() == pytest.approx((0.25**2 + 0 + 0.25**2) / 5 * (1 - n_band / 4), rel=1e-12)
    assert out["depth"].item() == 0.0  # D = depth_trunc: invalid
    assert out["rgb"].item() == pytest.approx(0.5**2, rel=1e-12)  # rgb_missing applies


def test_a_lattice_that_just_fits_the_bound_stays_inside_its_margins():
    """Co-SLAM's offset o = m + U (E - (n-1) v - 2m): with E = (n-1) v + 2m per axis o = m for
    every draw, so the lattice starts within one voxel of bound_min + m (only delta in [0, 1)
    moves it) and ends inside bound_max - m.  Oracle: this arithmetic, for several seeds."""
    n, v, m = 6, 0.1, 0.05
    extent = (n - 1) * v + 2 * m  # 0.6 m per axis
    bound = torch.tensor([[0.0, extent], [1.0, 1.0 + extent], [-1.0, -1.0 + extent]], dtype=torch.float64)
    loss_cfg = dataclasses.replace(config.synthetic().loss, smooth_pts=n, smooth_vox=v, smooth_margin=m)
    for seed in range(6):
        points = smoothness_lattice(bound, loss_cfg, torch.Generator().manual_seed(seed)).reshape(-1, 3)
        start = points.min(0).values - (bound[:, 0] + m)  # = delta v per axis
        assert bool((start >= -1e-12).all() and (start < v).all()), (seed, start)
        assert bool((points.max(0).values <= bound[:, 1] - m + 1e-12).all()), seed
