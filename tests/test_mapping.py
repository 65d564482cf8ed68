"""Tests for tsslam_ref.mapping: optimiser settings, ray sampling, bounds, mapping with GT poses."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import config
from tsslam_ref.eval import cull_mesh, mesh_metrics
from tsslam_ref.field import SceneField
from tsslam_ref.losses import RenderLossSettings
from tsslam_ref.mapping import FramePixels, backproject_depth, estimate_bound, fit_map, make_map_optimizer
from tsslam_ref.mesh import extract_mesh
from tsslam_ref.render import render_image
from tsslam_ref.synthetic import ProceduralRoom, builtin_trajectory, default_intrinsics, render_rgbd


def _plane_frame(depth_value=2.0, width=40, height=30, fill=None):
    depth = np.full((height, width), depth_value, dtype=np.float32)
    rgb = np.zeros((height, width, 3), dtype=np.float32)
    rgb[..., 0] = np.arange(width)[None, :] / width  # encodes the column
    rgb[..., 1] = np.arange(height)[:, None] / height  # encodes the row
    if fill is not None:
        rgb[..., 2] = fill
    return SimpleNamespace(rgb=rgb, depth=depth, intrinsics=(20.0, 20.0, (width - 1) / 2, (height - 1) / 2))


def test_map_optimizer_uses_coslam_adam_settings():
    cfg = config.tum_cpu()
    field = SceneField(cfg.field, [[0.0, 1.0]] * 3)
    optimizer = make_map_optimizer(field, cfg.mapping)
    assert optimizer.defaults["betas"] == (0.9, 0.99)
    decoder, grid = optimizer.param_groups
    assert decoder["lr"] == cfg.mapping.lr_decoder and decoder["weight_decay"] == 1e-6
    assert grid["lr"] == cfg.mapping.lr_embed and grid["eps"] == 1e-15
    assert optimizer.defaults.get("fused") in (True, None)


def test_frame_pixels_sample_uniform_over_frames_and_consistent_targets():
    frames = [_plane_frame(fill=0.1 * k) for k in range(3)]
    rays = FramePixels(frames, "cpu").sample(1200, torch.Generator().manual_seed(0), ignore_edge=2)
    assert len(rays) == 1200
    # each ray's blue channel identifies its frame, red/green its pixel: check against directions
    assert torch.allclose(rays.rgb[:, 2], 0.1 * rays.frame_ids.float())
    cols = rays.directions_cam[:, 0] * 20.0 + 19.5
    rows = rays.directions_cam[:, 1] * 20.0 + 14.5
    assert torch.allclose(rays.rgb[:, 0] * 40, cols, atol=1e-4) and torch.allclose(rays.rgb[:, 1] * 30, rows, atol=1e-4)
    assert cols.min() >= 2 and cols.max() <= 37 and rows.min() >= 2 and rows.max() <= 27
    counts = torch.bincount(rays.frame_ids, minlength=3).float()
    assert (counts - 400).abs().max() < 80  # 3 sigma of a uniform draw is ~45
    pairs = set(zip(rays.frame_ids.tolist(), rows.round().long().tolist(), cols.round().long().tolist()))
    assert len(pairs) == 1200  # without replacement


def test_estimate_bound_of_a_fronto_parallel_plane():
    frame = _plane_frame(depth_value=2.0)
    bound = estimate_bound([frame], np.eye(4)[None], margin=0.1, percentile=0.0, stride=1)
    # x = (col - cx) / fx * z over cols 0..39: +-19.5 / 20 * 2 = +-1.95; y: +-14.5 / 20 * 2
    expected = np.array([[-1.95, 1.95], [-1.45, 1.45], [0.0, 2.0]]) + np.array([-0.1, 0.1])
    assert np.allclose(bound, expected, atol=1e-6)  # z min is the camera centre (z = 0)
    shifted = np.eye(4)
    shifted[:3, 3] = [1.0, 2.0, 3.0]
    assert np.allclose(estimate_bound([frame], shifted[None], 0.1, 0.0, 1), expected + np.array([[1.0], [2.0], [3.0]]))
    far = _plane_frame(depth_value=2.0)
    far.depth[:, 20:] = 9.0  # right half of the image sees a far wall
    limited = estimate_bound([far], np.eye(4)[None], 0.1, 0.0, 1, max_depth=5.0)
    # only the near (left) half remains; x max is the camera centre (0) + margin
    assert limited[2, 1] == pytest.approx(2.1) and limited[0, 1] == pytest.approx(0.1)


def test_estimate_bound_refuses_a_pose_count_other_than_the_frame_count():
    """zip would drop the second frame; a bare (4, 4) pose would be read row by row."""
    frame = _plane_frame(depth_value=2.0)
    with pytest.raises(ValueError, match=r"2 frame\(s\), poses of shape \(1, 4, 4\), expected \(2, 4, 4\)"):
        estimate_bound([frame, frame], np.eye(4)[None], margin=0.1)
    with pytest.raises(ValueError, match=r"poses of shape \(4, 4\), expected \(1, 4, 4\)"):
        estimate_bound([frame], np.eye(4), margin=0.1)


@pytest.fixture(scope="module")
def synthetic_views():
    """9 clean RGB-D views of the procedural room along the built-in path (sphere traced)."""
    scene = ProceduralRoom()
    intrinsics = default_intrinsics(64, 48)
    times = np.linspace(0.0, 6.0, 9)
    poses = builtin_trajectory(times)
    frames = []
    for index, pose in enumerate(poses):
        rgb, depth = render_rgbd(scene, pose, intrinsics)
        frames.append(SimpleNamespace(index=index, rgb=rgb, depth=depth, intrinsics=intrinsics, pose_c2w=pose))
    return scene, intrinsics, frames


def test_mapping_with_gt_poses_reconstructs_the_synthetic_room(synthetic_views):
    """Map from 6 posed views, evaluate on 3 held-out views and against the analytic mesh."""
    scene, intrinsics, frames = synthetic_views
    train, held_out = [f for f in frames if f.index % 3 != 1], [f for f in frames if f.index % 3 == 1]
    cfg = config.tiny()
    bound = estimate_bound(train, np.stack([f.pose_c2w for f in train]), margin=cfg.field.bound_margin)
    assert np.all(bound[:, 0] < scene.bound[:, 1]) and np.all(bound[:, 1] > scene.bound[:, 0])
    field = SceneField(cfg.field, bound, generator=torch.Generator().manual_seed(0))
    optimizer = make_map_optimizer(field, cfg.mapping)
    poses = torch.from_numpy(np.stack([f.pose_c2w for f in train]))
    losses = fit_map(field, optimizer, train, poses, RenderLossSettings.from_config(cfg), iters=60, n_rays=256,
                     generator=torch.Generator().manual_seed(0))
    assert len(losses) == 60 and np.mean(losses[-10:]) < 0.2 * np.mean(losses[:10])

    errors = []
    for frame in held_out:
        out = render_image(field, torch.from_numpy(frame.pose_c2w), intrinsics, cfg.render, depth=torch.from_numpy(frame.depth))
        valid = frame.depth > 0
        errors.append(np.abs(out["depth"].numpy()[valid] - frame.depth[valid]).mean())
    assert np.mean(errors) < 0.05  # metres, generous for 60 iterations at tiny size

    all_poses = np.stack([f.pose_c2w for f in frames])
    depths = np.stack([f.depth for f in frames])
    camera = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width, intrinsics.height)
    reconstruction = cull_mesh(extract_mesh(field, voxel_size=0.08, color=False), all_poses, camera, depths)
    ground_truth = cull_mesh(scene.mesh(0.04), all_poses, camera, depths)
    metrics = mesh_metrics(reconstruction, ground_truth, n_points=20_000, threshold=0.05, seed=0)
    assert metrics["accuracy_m"] < 0.08 and metrics["completion_m"] < 0.08


def test_frame_pixels_use_each_frames_own_intrinsics():
    """Frames with different intrinsics (a zoomed and a shifted camera): each ray's direction is
    ((col - cx) / fx, (row - cy) / fy, 1) with its own frame's values, the pixel read back from the
    colours (red: column, green: row, blue: frame)."""
    frames = [_plane_frame(fill=0.1 * k) for k in range(3)]
    frames[1].intrinsics = (35.0, 31.0, 17.0, 12.0)
    frames[2].intrinsics = (12.0, 14.0, 22.5, 16.5)
    rays = FramePixels(frames, "cpu", torch.float64).sample(600, torch.Generator().manual_seed(1))
    frame = torch.round(rays.rgb[:, 2] / 0.1).long()
    assert torch.equal(frame, rays.frame_ids) and set(frame.tolist()) == {0, 1, 2}
    cols, rows = torch.round(rays.rgb[:, 0] * 40), torch.round(rays.rgb[:, 1] * 30)  # float32 colours: exact after rounding
    fx, fy, cx, cy = torch.tensor([frames[k].intrinsics for k in frame.tolist()], dtype=torch.float64).unbind(-1)
    expected = torch.stack([(cols - cx) / fx, (rows - cy) / fy, torch.ones_like(cols)], dim=-1)
    assert torch.allclose(rays.directions_cam, expected, atol=1e-12)


def test_backproject_depth_with_stride_and_a_rotated_moving_camera():
    """Depth varying per pixel, every second pixel, a camera turned 0.7 rad about (1, 2, 2)/3 and moved:
    each point is R (z ((c - cx) / fx, (r - cy) / fy, 1)) + t at the full-resolution pixel (r, c),
    r and c even; a pixel with zero depth gives no point."""
    frame = _plane_frame()
    frame.intrinsics = (20.0, 24.0, 19.5, 14.5)
    rows, cols = np.mgrid[0:30, 0:40]
    frame.depth = (1.0 + 0.05 * cols + 0.02 * rows).astype(np.float32)
    frame.depth[4, 6] = 0.0
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(0.7 * np.array([1.0, 2.0, 2.0]) / 3.0).as_matrix()
    pose[:3, 3] = [0.4, -1.3, 2.2]
    points = backproject_depth(frame, pose, stride=2)
    keep = (rows % 2 == 0) & (cols % 2 == 0) & (frame.depth > 0)
    z = frame.depth[keep].astype(np.float64)
    camera = np.stack([(cols[keep] - 19.5) / 20.0 * z, (rows[keep] - 14.5) / 24.0 * z, z], axis=1)
    expected = np.einsum("ij,nj->ni", pose[:3, :3], camera) + pose[:3, 3]
    assert points.shape == (15 * 20 - 1, 3)
    np.testing.assert_allclose(points, expected, atol=1e-6)


def test_estimate_bound_ignores_flying_pixels_and_depth_at_the_limit():
    """Two flying pixels at 50 m (under 0.5 % of 1200) leave the 0.5/99.5 percentile box of the
    2 m plane unchanged: x +-1.95, y +-1.45, z 0..2 (hand-derived, camera centre included); depth
    exactly at max_depth is ignored."""
    frame = _plane_frame(depth_value=2.0)
    frame.depth[20, 25] = frame.depth[3, 5] = 50.0  # x, y = +13.75 and -36.25, -28.75 at 50 m
    bound = estimate_bound([frame], np.eye(4)[None], margin=0.1, stride=1)
    expected = np.array([[-1.95, 1.95], [-1.45, 1.45], [0.0, 2.0]]) + np.array([-0.1, 0.1])
    np.testing.assert_allclose(bound, expected, atol=1e-6)
    frame.depth[:, 20:] = 5.0
    limited = estimate_bound([frame], np.eye(4)[None], 0.1, 0.0, 1, max_depth=5.0)
    assert limited[2, 1] == pytest.approx(2.1) and limited[0, 1] == pytest.approx(0.1)  # the 5 m half is gone


def test_share_outside_bound_counts_measured_surface_points_past_the_box():
    """Oracle by hand: rays straight ahead (+z) at depths 1, 3 and 5 m against the box z in [0, 2]:
    one of three inside, so 2/3 outside; no depth (0) and depth at the cut-off are not counted;
    the same rays from a camera turned half a turn about y land at z < 0, all outside."""
    from tsslam_ref.mapping import share_outside_bound
    from tsslam_ref.render import RayBatch

    n = 5
    rays = RayBatch(directions_cam=torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1), rgb=torch.zeros(n, 3),
                    depth=torch.tensor([1.0, 3.0, 5.0, 0.0, 8.0]), frame_ids=torch.zeros(n, dtype=torch.long))
    bound = torch.tensor([[-1.0, 1.0], [-1.0, 1.0], [0.0, 2.0]])
    assert share_outside_bound(bound, rays, torch.eye(4), max_depth=8.0) == pytest.approx(2 / 3)
    assert share_outside_bound(bound, rays, torch.eye(4), max_depth=2.0) == 0.0  # only the 1 m ray counts
    turned = torch.eye(4, dtype=torch.float64)
    turned[:3, :3] = torch.as_tensor(Rotation.from_euler("y", 180, degrees=True).as_matrix())
    assert share_outside_bound(bound, rays, turned, max_depth=8.0) == 1.0
    assert share_outside_bound(bound, rays, torch.eye(4), max_depth=0.5) == 0.0  # no ray counted: 0, not NaN
