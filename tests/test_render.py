"""Tests for tsslam_ref.render: rays (Eq. 2), samples (Co-SLAM's render_rays), weights and compositing (Eq. 3)."""

import dataclasses

import numpy as np
import pytest
import scipy.stats
import torch

from tsslam_ref import config
from tsslam_ref.field import SceneField
from tsslam_ref.geometry import make_pose, so3_exp
from tsslam_ref.render import (
    RayBatch,
    frame_rays,
    pixel_directions,
    rays_to_world,
    render_image,
    render_rays,
    sample_along_rays,
    sample_pixels,
    sdf_to_weights,
)

INTRINSICS = (50.0, 55.0, 31.5, 23.5)  # fx, fy, cx, cy of a 64 x 48 image


def test_pixel_directions_equal_inverse_intrinsics():
    rows = torch.tensor([0, 23, 47, 10])
    cols = torch.tensor([0, 31, 63, 50])
    fx, fy, cx, cy = INTRINSICS
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    expected = np.linalg.solve(K, np.stack([cols.numpy(), rows.numpy(), np.ones(4)]).astype(float)).T
    directions = pixel_directions(rows, cols, INTRINSICS)
    assert directions.dtype == torch.float32
    assert np.allclose(directions.numpy(), expected, atol=1e-6)
    assert torch.all(directions[:, 2] == 1)


def test_pixel_directions_of_float64_subpixel_positions_stay_float64():
    """Sub-pixel float64 positions give float64 directions equal to K^-1 [u, v, 1] (numpy's solve)
    to 1e-12, which float32 (relative 6e-8) cannot meet."""
    rows = torch.tensor([23.5, 0.25, 47.125], dtype=torch.float64)
    cols = torch.tensor([31.5, 63.75, 0.0625], dtype=torch.float64)
    fx, fy, cx, cy = INTRINSICS
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    expected = np.linalg.solve(K, np.stack([cols.numpy(), rows.numpy(), np.ones(3)])).T
    directions = pixel_directions(rows, cols, INTRINSICS)
    assert directions.dtype == torch.float64
    assert np.allclose(directions.numpy(), expected, rtol=0, atol=1e-12)

def test_sample_pixels_unique_inside_edge_and_seeded():
    rows, cols = sample_pixels(48, 64, 500, ignore_edge=5, generator=torch.Generator().manual_seed(1))
    assert rows.dtype == torch.long and len(rows) == 500
    assert rows.min() >= 5 and rows.max() < 43 and cols.min() >= 5 and cols.max() < 59
    assert len(set(zip(rows.tolist(), cols.tolist()))) == 500
    rows2, cols2 = sample_pixels(48, 64, 500, ignore_edge=5, generator=torch.Generator().manual_seed(1))
    assert torch.equal(rows, rows2) and torch.equal(cols, cols2)
    with pytest.raises(ValueError, match="cannot sample"):
        sample_pixels(10, 10, 101)


def test_frame_rays_and_raybatch_helpers():
    rgb = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    depth = np.random.default_rng(1).random((48, 64)).astype(np.float32)
    rows, cols = torch.tensor([1, 2, 3]), torch.tensor([4, 5, 6])
    batch = frame_rays(rgb, depth, INTRINSICS, rows, cols, frame_id=7)
    assert len(batch) == 3 and torch.all(batch.frame_ids == 7)
    assert np.allclose(batch.rgb.numpy(), rgb[[1, 2, 3], [4, 5, 6]])
    assert np.allclose(batch.depth.numpy(), depth[[1, 2, 3], [4, 5, 6]])
    both = RayBatch.cat([batch, batch.subset(slice(0, 2))])
    assert len(both) == 5 and torch.equal(both.rgb[3:], batch.rgb[:2])
    assert len(both.to("cpu")) == 5
    with pytest.raises(ValueError, match="depth"):
        RayBatch(batch.directions_cam, batch.rgb, batch.depth[:2], batch.frame_ids)


def test_an_image_of_another_size_than_the_intrinsics_is_refused():
    """An 80x60 depth with the intrinsics of 160x120 images: every ray would point elsewhere."""
    from tsslam_ref.data import Intrinsics

    full = Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)
    half = np.ones((60, 80), dtype=np.float32)
    rows, cols = torch.tensor([0]), torch.tensor([0])
    with pytest.raises(ValueError, match=r"frame_rays' depth image is 80x60 .* intrinsics are for 160x120"):
        frame_rays(np.zeros((60, 80, 3), np.float32), half, full, rows, cols)
    with pytest.raises(ValueError, match=r"render_image's depth is 80x60 .* for 160x120"):
        render_image(lambda x: None, torch.eye(4), full, config.tiny().render, depth=torch.from_numpy(half))
    with pytest.raises(ValueError, match=r"render_image's height/width is 80x60 .* for 160x120"):
        render_image(lambda x: None, torch.eye(4), full, config.tiny().render, height=60, width=80)
    resized = full.resized(80, 60)
    assert len(frame_rays(np.zeros((60, 80, 3), np.float32), half, resized, rows, cols)) == 1  # the right size


def test_images_and_rays_of_the_wrong_kind_are_refused_naming_what_was_expected():
    """8-bit colours (a loss 600000 times too large) and raw PNG depth would pass every shape check."""
    rows, cols = torch.tensor([0]), torch.tensor([0])
    rgb, depth = np.zeros((48, 64, 3), np.float32), np.ones((48, 64), np.float32)
    with pytest.raises(TypeError, match="rgb is uint8; expected floating-point colours in .* divide 8-bit"):
        frame_rays((rgb * 255).astype(np.uint8), depth, INTRINSICS, rows, cols)
    with pytest.raises(TypeError, match="depth is torch.int32; expected floating-point metres"):
        frame_rays(torch.from_numpy(rgb), torch.ones(48, 64, dtype=torch.int32), INTRINSICS, rows, cols)
    cfg = config.tiny().render
    origins = torch.zeros(5, 3)
    with pytest.raises(ValueError, match=r"target_depth \(R,\), got \(5, 3\), \(5, 3\) and \(5, 1\)"):
        render_rays(lambda x: None, origins, origins, torch.ones(5, 1), cfg)
    with pytest.raises(ValueError, match=r"one \(4, 4\) camera-to-world pose, got \(2, 4, 4\)"):
        render_image(lambda x: None, torch.eye(4).repeat(2, 1, 1), INTRINSICS, cfg, height=4, width=4)


def test_rays_to_world_single_and_per_ray_poses_and_pose_gradient():
    generator = torch.Generator().manual_seed(0)
    directions = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    rotvec = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    trans = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    poses = make_pose(so3_exp(rotvec), trans)
    origins, world = rays_to_world(directions, poses)
    for r in range(6):
        assert torch.allclose(world[r], poses[r, :3, :3] @ directions[r])
        assert torch.allclose(origins[r], trans[r])
    origins1, world1 = rays_to_world(directions, poses[2])
    assert torch.allclose(world1[2], world[2]) and torch.allclose(origins1, trans[2].expand(6, 3))
    pose = poses[0].clone().requires_grad_(True)
    rays_to_world(directions, pose)[1].sum().backward()
    assert pose.grad is not None and pose.grad[:3, :3].abs().sum() > 0
    with pytest.raises(ValueError, match="c2w"):
        rays_to_world(directions, poses[:2])


def test_samples_follow_coslam_layout():
    cfg = dataclasses.replace(config.tum().render, perturb=False)  # 64 uniform + 21 guided
    depth = torch.tensor([1.5, 0.0])
    z = sample_along_rays(depth, cfg)
    assert z.shape == (2, 85)
    assert torch.all(z[:, 1:] >= z[:, :-1])
    band = torch.linspace(1.25, 1.75, 21)
    assert all(torch.isclose(z[0], value).any() for value in band)
    # invalid depth: the 21 guided samples are spread over [near, far] as well
    assert z[1].min() == 0 and z[1].max() == 5.0
    assert (z[1] == 0).sum() == 2 and (z[1] == 5.0).sum() == 2
    assert all(torch.isclose(z[1], torch.tensor(value)).any() for value in (0.25, 1.25, 3.75))


def test_samples_with_a_near_plane_span_near_to_far():
    """near = 0.5, far = 4: the 8 uniform samples are 0.5 + 3.5 i / 7 = 0.5, 1.0, ..., 4.0 (worked
    by hand), the 3 guided ones 1.9, 2.0, 2.1 around a depth of 2 m or, without a depth, 0.5, 2.25,
    4.0 (evenly in [near, far])."""
    cfg = dataclasses.replace(config.tum().render, perturb=False, near=0.5, far=4.0, n_samples=8, n_range_d=3,
                              range_d=0.1)
    z = sample_along_rays(torch.tensor([2.0, 0.0], dtype=torch.float64), cfg)
    expected = torch.tensor([[0.5, 1.0, 1.5, 1.9, 2.0, 2.0, 2.1, 2.5, 3.0, 3.5, 4.0],
                             [0.5, 0.5, 1.0, 1.5, 2.0, 2.25, 2.5, 3.0, 3.5, 4.0, 4.0]], dtype=torch.float64)
    assert torch.allclose(z, expected, atol=1e-12)

def test_perturbed_samples_stay_sorted_within_midpoints_and_are_seeded():
    cfg = config.tiny().render
    depth = torch.rand(100) * 3
    fixed = sample_along_rays(depth, dataclasses.replace(cfg, perturb=False))
    z = sample_along_rays(depth, cfg, torch.Generator().manual_seed(4))
    mids = 0.5 * (fixed[:, 1:] + fixed[:, :-1])
    assert torch.all(z[:, 1:] >= z[:, :-1] - 1e-6)
    assert torch.all(z[:, 1:-1] >= mids[:, :-1] - 1e-6) and torch.all(z[:, 1:-1] <= mids[:, 1:] + 1e-6)
    assert torch.equal(z, sample_along_rays(depth, cfg, torch.Generator().manual_seed(4)))
    # each sample uniform over its cell, between the midpoints to its neighbours (the ends at their own
    # value), and another seed draws other depths: fixed samples pass every check above
    lower = torch.cat([fixed[:, :1], mids], dim=-1)
    upper = torch.cat([mids, fixed[:, -1:]], dim=-1)
    width = upper - lower
    fractions = ((z - lower) / width)[width > 1e-6].double().numpy()
    assert fractions.size > 1000 and scipy.stats.kstest(fractions, "uniform").pvalue > 1e-3
    assert not torch.allclose(z, sample_along_rays(depth, cfg, torch.Generator().manual_seed(5)))


def _bell(s):
    """Logistic density written independently: e^-s / (1 + e^-s)^2."""
    return torch.exp(-s) / (1 + torch.exp(-s)) ** 2


def test_weights_are_the_normalised_bell_when_nothing_is_cut():
    sdf = torch.tensor([[0.3, 0.1, 0.0, -0.2, -0.5]], dtype=torch.float64)
    z = torch.linspace(0.0, 0.4, 5, dtype=torch.float64).unsqueeze(0)
    truncation = 10.0  # z_min + tr covers the whole ray
    weights = sdf_to_weights(sdf, z, truncation)
    bell = _bell(sdf / truncation)
    assert torch.allclose(weights, bell / bell.sum(), atol=1e-9)
    assert _bell(torch.tensor(0.0)) == 0.25 and bool((_bell(sdf) <= 0.25).all())
    assert weights.argmax() == 2  # peak at s = 0


def test_first_surface_cut_keeps_samples_before_the_first_crossing_plus_tr():
    z = torch.linspace(0.0, 2.0, 21).unsqueeze(0)  # spacing 0.1
    # two surfaces: crossing between z = 0.5 and 0.6, another between 1.5 and 1.6
    metric = torch.where(z < 1.05, 0.55 - z, z - 1.55)
    truncation = 0.25
    weights = sdf_to_weights(metric / truncation, z, truncation)
    kept = weights[0] > 0
    assert torch.equal(kept, z[0] < 0.5 + truncation)  # z_min = 0.5 (sample before crossing)
    assert torch.allclose(weights.sum(), torch.tensor(1.0))


def test_a_sample_exactly_at_zero_is_no_crossing_as_in_coslam():
    """Co-SLAM's crossing test is s_i s_(i+1) < 0: around an exact zero both products are 0, so a ray
    that only passes through zero (no strict sign change) is cut at its first sample, worked by hand:
    z = 0.5, 0.6, ..., kept where z < 0.5 + tr."""
    z = (torch.arange(8, dtype=torch.float64) * 0.1 + 0.5).unsqueeze(0)
    sdf = torch.tensor([[0.9, 0.6, 0.3, 0.0, -0.3, -0.6, -0.9, -1.0]], dtype=torch.float64)
    weights = sdf_to_weights(sdf, z, 0.25)
    assert torch.equal(weights[0] > 0, z[0] < 0.5 + 0.25)
    nudged = sdf_to_weights(sdf - 1e-9 * (sdf == 0), z, 0.25)  # a strict change between 0.7 and 0.8 m
    assert torch.equal(nudged[0] > 0, z[0] < 0.7 + 0.25)


def test_no_sign_change_keeps_only_samples_within_tr_of_the_first():
    z = torch.linspace(0.5, 3.0, 26).unsqueeze(0)
    sdf = torch.full_like(z, 0.8)
    weights = sdf_to_weights(sdf, z, 0.3)
    assert torch.equal(weights[0] > 0, z[0] < 0.5 + 0.3)
    assert torch.allclose(weights.sum(), torch.tensor(1.0))


@pytest.mark.parametrize("truncation", [0.05, 0.1])
def test_planar_sdf_renders_the_plane_depth_within_one_sample_spacing(truncation):
    """World plane n . x = c seen by a tilted camera: rendered depth = analytic ray-plane depth."""
    cfg = dataclasses.replace(config.tiny().render, truncation=truncation)
    normal = torch.tensor([0.1, -0.2, -1.0], dtype=torch.float64)
    normal = normal / normal.norm()
    offset = -2.0  # plane n . x = offset

    def planar_field(points):
        metric = offset - points @ normal  # positive on the camera side
        return torch.full_like(points, 0.5), metric / truncation

    pose = make_pose(so3_exp(torch.tensor([0.05, -0.1, 0.02], dtype=torch.float64)), torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64))
    rows, cols = sample_pixels(48, 64, 200, generator=torch.Generator().manual_seed(0))
    origins, directions = rays_to_world(pixel_directions(rows, cols, INTRINSICS).double(), pose)
    true_depth = (offset - origins @ normal) / (directions @ normal)
    assert bool((true_depth > 0.5).all() and (true_depth < cfg.far - 0.5).all())
    out = render_rays(planar_field, origins, directions, true_depth, cfg, torch.Generator().manual_seed(1))
    spacing = 2 * cfg.range_d / (cfg.n_range_d - 1)
    assert (out["depth"] - true_depth).abs().max() < spacing
    # weights sum to 1 up to the 1e-8 guard (visible when every sample is far from s = 0)
    assert torch.allclose(out["weights"].sum(-1), torch.ones(200, dtype=torch.float64), atol=1e-2)
    assert torch.allclose(out["rgb"], 0.5 * out["weights"].sum(-1, keepdim=True).expand(200, 3))


def test_image_render_puts_each_pixels_depth_at_its_row_and_column():
    """A tilted plane seen by a 12 x 16 camera: every pixel's rendered depth against the ray-plane depth
    worked out in numpy for that pixel's (row, col), so a transposed or scrambled pixel order fails."""
    cfg = config.tiny().render
    normal = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    offset = -2.0  # plane n . x = offset, the camera at the origin looking along +z

    def planar_field(points):
        return torch.full_like(points, 0.5), (offset - points @ torch.from_numpy(normal)) / cfg.truncation

    fx, fy, cx, cy = small = (12.0, 13.0, 7.5, 5.5)
    rows, cols = np.mgrid[0:12, 0:16]
    rays = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones((12, 16))], axis=-1)  # (12, 16, 3)
    true_depth = offset / (rays @ normal)  # camera z = depth along a z = 1 ray
    out = render_image(planar_field, torch.eye(4, dtype=torch.float64), small, cfg, depth=torch.from_numpy(true_depth))
    spacing = 2 * cfg.range_d / (cfg.n_range_d - 1)
    assert out["depth"].shape == (12, 16)
    assert float(np.ptp(true_depth)) > 10 * spacing  # the plane's tilt is resolved
    assert np.abs(out["depth"].numpy() - true_depth).max() < spacing


def test_chunked_image_render_equals_unchunked():
    cfg = config.tiny()
    field = SceneField(cfg.field, [[-1.0, 1.0], [-1.0, 1.0], [0.0, 3.0]], generator=torch.Generator().manual_seed(0))
    pose = make_pose(so3_exp(torch.tensor([0.0, 0.1, 0.0])), torch.tensor([0.0, 0.0, -0.5]))
    depth = torch.rand(12, 16) * 2 + 0.5
    small = (12.0, 12.0, 7.5, 5.5)
    one = render_image(field, pose, small, cfg.render, depth=depth, chunk=10_000)
    many = render_image(field, pose, small, cfg.render, depth=depth, chunk=7)
    assert one["rgb"].shape == (12, 16, 3) and one["depth"].shape == (12, 16)
    assert torch.allclose(one["rgb"], many["rgb"], atol=1e-6)
    assert torch.allclose(one["depth"], many["depth"], atol=1e-6)
    with pytest.raises(ValueError, match="image size"):
        render_image(field, pose, small, cfg.render)
