"""Tests for tsslam_ref.synthetic: SDF, sphere-traced depth against analytic ray intersections,
two-view consistency, depth noise, trajectory resampling and placement, mesh, synthesize -> load.

Oracles: closed-form ray-sphere and ray-box (slab) intersections, the eikonal property through
autograd, scipy's Slerp, a numpy re-projection written here, the clean render for the round trip.
"""

import json
import os

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from tsslam_ref import data, synthetic
from tsslam_ref.synthetic import ProceduralRoom, render_rgbd

SPHERE_CENTRE = np.array([1.0, 0.2, 1.2])
SPHERE_RADIUS = 0.4


def _camera(position, forward):
    pose = np.eye(4)
    pose[:3, :3] = synthetic.look_rotation(forward)
    pose[:3, 3] = position
    return pose


def _rays_world(pose, k):
    v, u = np.mgrid[: k.height, : k.width].astype(np.float64)
    rays_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], -1)  # (H, W, 3)
    return rays_cam @ pose[:3, :3].T  # unnormalised, camera z = 1


def test_sphere_and_walls_depth_match_analytic_intersections():
    """Every pixel's depth equals the nearer of the analytic ray-sphere and ray-room-box hits."""
    scene = ProceduralRoom(boxes=[], cylinders=[], spheres=[(tuple(SPHERE_CENTRE), SPHERE_RADIUS, (1, 0, 0))])
    k = data.Intrinsics(40.0, 40.0, 23.5, 17.5, 48, 36)
    pose = _camera([-0.5, -0.3, 1.1], SPHERE_CENTRE - np.array([-0.5, -0.3, 1.1]))
    _, depth = render_rgbd(scene, pose, k)
    d = _rays_world(pose, k)  # a point at depth z is o + z d
    o = pose[:3, 3]
    # sphere: |o + z d - c|^2 = r^2
    a = (d * d).sum(-1)
    b = 2 * (d * (o - SPHERE_CENTRE)).sum(-1)
    c = ((o - SPHERE_CENTRE) ** 2).sum() - SPHERE_RADIUS**2
    disc = b * b - 4 * a * c
    z_sphere = np.where(disc > 0, (-b - np.sqrt(np.clip(disc, 0, None))) / (2 * a), np.inf)
    # room walls from inside: exit distance of the slab test
    low, high = np.array(synthetic.ROOM_MIN), np.array(synthetic.ROOM_MAX)
    with np.errstate(divide="ignore"):
        z_exit = np.min(np.maximum((low - o) / d, (high - o) / d), axis=-1)
    expected = np.minimum(z_sphere, z_exit)
    assert (disc > 0).mean() > 0.1  # the sphere fills part of the view
    np.testing.assert_allclose(depth, expected, atol=2e-4)


def test_back_projected_depth_lies_on_the_surface():
    """data.back_project of a clean render gives points on the zero level set of the scene SDF."""
    scene = ProceduralRoom()
    k = data.Intrinsics(50.0, 52.0, 30.2, 21.7, 64, 44)
    pose = synthetic.builtin_trajectory(np.array([1.7]))[0]
    _, depth = render_rgbd(scene, pose, k)
    points = data.back_project(depth, k, pose)[depth > 0]  # (N, 3)
    assert len(points) > 0.99 * depth.size
    assert scene.sdf(torch.from_numpy(points)).abs().max().item() < 1e-4
    np.testing.assert_allclose(data.back_project(depth, k)[..., 2], depth)  # camera frame: z = depth


def test_sdf_is_a_distance_field():
    """|grad sdf| = 1 almost everywhere (eikonal) and sdf > 0 at the room centre, < 0 inside objects."""
    scene = ProceduralRoom()
    generator = torch.Generator().manual_seed(0)
    low, high = torch.tensor(synthetic.ROOM_MIN), torch.tensor(synthetic.ROOM_MAX)
    points = (low + (high - low) * torch.rand(2000, 3, generator=generator, dtype=torch.float64)).requires_grad_()
    (grad,) = torch.autograd.grad(scene.sdf(points).sum(), points)
    norms = grad.norm(dim=-1)
    assert ((norms - 1).abs() < 1e-6).float().mean() > 0.97
    centre = torch.tensor([[0.0, 0.0, 1.25]], dtype=torch.float64)
    # nearest surface: the table's top corner at (0.7, 0.35, 0.75) -> offsets (0.7, 0.35, 0.5)
    assert scene.sdf(centre).item() == pytest.approx(np.sqrt(0.7**2 + 0.35**2 + 0.5**2))
    inside = torch.tensor([list(synthetic.DEFAULT_SPHERES[0][0])], dtype=torch.float64)
    assert scene.sdf(inside).item() == pytest.approx(-synthetic.DEFAULT_SPHERES[0][1])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        scene.sdf(torch.zeros(4, 2))


def test_two_views_agree_after_reprojection():
    """Back-project view A with its pose, project into view B: depth and colour agree where both see it."""
    scene = ProceduralRoom(seed=1)
    k = data.Intrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)
    pose_a = _camera([0.2, 0.1, 1.3], [1.0, 0.1, -0.2])
    pose_b = _camera([0.35, -0.05, 1.25], [1.0, -0.15, -0.1])
    rgb_a, depth_a = render_rgbd(scene, pose_a, k)
    rgb_b, depth_b = render_rgbd(scene, pose_b, k)
    points_world = (_rays_world(pose_a, k) * depth_a[..., None] + pose_a[:3, 3]).reshape(-1, 3)
    points_b = (points_world - pose_b[:3, 3]) @ pose_b[:3, :3]  # R^T (p - t), (N, 3)
    u = np.round(k.fx * points_b[:, 0] / points_b[:, 2] + k.cx).astype(int)
    v = np.round(k.fy * points_b[:, 1] / points_b[:, 2] + k.cy).astype(int)
    inside = (points_b[:, 2] > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    z_seen = depth_b[v[inside], u[inside]]
    same_surface = np.abs(z_seen - points_b[inside, 2]) < 0.02
    assert inside.mean() > 0.5 and same_surface.mean() > 0.8
    colour_a = rgb_a.reshape(-1, 3)[inside][same_surface]
    colour_b = rgb_b[v[inside], u[inside]][same_surface]
    assert np.median(np.abs(colour_a - colour_b)) < 0.02  # nearest-pixel rounding only
    assert np.median(np.abs(colour_a - colour_b[np.random.default_rng(0).permutation(len(colour_b))])) > 0.04


def test_depth_noise_model_and_determinism():
    scene = ProceduralRoom()
    k = data.Intrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)
    pose = synthetic.builtin_trajectory(np.array([0.5]))[0]
    _, clean = render_rgbd(scene, pose, k)
    _, noisy = render_rgbd(scene, pose, k, clean=False, generator=torch.Generator().manual_seed(3))
    _, again = render_rgbd(scene, pose, k, clean=False, generator=torch.Generator().manual_seed(3))
    _, other = render_rgbd(scene, pose, k, clean=False, generator=torch.Generator().manual_seed(4))
    np.testing.assert_array_equal(noisy, again)
    assert not np.array_equal(noisy, other)
    valid = noisy > 0
    assert 0.8 < valid.mean() < 0.999  # some dropouts, most pixels kept
    sigma = 0.0012 + 0.0019 * (clean[valid] - 0.4) ** 2
    ratio = np.std((noisy[valid] - clean[valid]) / sigma)
    assert 0.85 < ratio < 1.15
    with pytest.raises(ValueError, match="Generator"):
        render_rgbd(scene, pose, k, clean=False)


def test_resampling_is_linear_and_slerp(shared_data):
    path = shared_data / "trajectories" / "tum_rgbd_fr2_desk_groundtruth.txt"
    raw = np.loadtxt(path, comments="#")
    start = raw[100, 0]
    times, poses = synthetic.resample_trajectory(path, 20, 30.0, start_time=start)
    np.testing.assert_allclose(times, start + np.arange(20) / 30.0)
    np.testing.assert_allclose(poses[0][:3, 3], raw[100, 1:4], atol=1e-12)  # exactly on a sample
    for i in (5, 19):
        j = np.searchsorted(raw[:, 0], times[i])
        slerp = Slerp(raw[j - 1 : j + 1, 0], Rotation.from_quat(raw[j - 1 : j + 1, 4:8]))
        np.testing.assert_allclose(poses[i][:3, :3], slerp([times[i]]).as_matrix()[0], atol=1e-6)
        w = (times[i] - raw[j - 1, 0]) / (raw[j, 0] - raw[j - 1, 0])
        np.testing.assert_allclose(poses[i][:3, 3], (1 - w) * raw[j - 1, 1:4] + w * raw[j, 1:4], atol=1e-9)
    with pytest.raises(ValueError, match="no pose for frame"):
        synthetic.resample_trajectory(path, 10, 30.0, start_time=raw[-1, 0])


def test_placement_keeps_relative_motion():
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(5, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(5, 3)) + 10.0
    placed, _ = synthetic.place_in_room(poses)
    np.testing.assert_allclose(placed[0][:3, 3], synthetic.START_POSITION, atol=1e-12)
    np.testing.assert_allclose(placed[0][:3, :3], synthetic.START_ROTATION, atol=1e-12)
    for i, j in [(0, 3), (2, 4)]:
        np.testing.assert_allclose(np.linalg.inv(placed[i]) @ placed[j], np.linalg.inv(poses[i]) @ poses[j], atol=1e-9)


def test_mesh_lies_on_the_zero_level_set():
    scene = ProceduralRoom()
    voxel = 0.1
    mesh = scene.mesh(voxel)
    vertices = torch.from_numpy(np.array(mesh.vertices))
    assert scene.sdf(vertices).abs().max().item() < 0.5 * voxel
    outward = vertices + 0.05 * torch.from_numpy(np.array(mesh.vertex_normals))
    assert (scene.sdf(outward) > 0).double().mean().item() > 0.9  # normals point into free space
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)


def test_synthesize_round_trip(tmp_path):
    umask = os.umask(0o022)  # a usual umask: under 0o077 mkdtemp's 0o700 would be what mkdir gives too
    try:
        out = synthetic.synthesize(tmp_path / "syn", n_frames=4, width=32, height=24, fps=15.0, seed=2,
                                   clean_depth=True, mesh_voxel=0.15)
        (tmp_path / "made_by_mkdir").mkdir()
    finally:
        os.umask(umask)
    sequence = data.load_sequence(out)
    scene_info = json.loads((out / "scene.json").read_text())
    k = synthetic.default_intrinsics(32, 24)
    assert sequence.kind == "tum" and len(sequence) == 4
    assert sequence.intrinsics == k and scene_info["intrinsics"] == k.to_dict()  # not the fr3 defaults
    np.testing.assert_allclose(scene_info["bound"], [[-2, 2], [-1.5, 1.5], [0, 2.5]])
    np.testing.assert_allclose(sequence.timestamps, np.arange(4) / 15.0, rtol=0, atol=1e-6)  # %.6f stamps
    truth = synthetic.builtin_trajectory(np.arange(4) / 15.0)
    np.testing.assert_allclose(sequence.gt_poses, truth, atol=1e-8)
    frame = sequence[2]
    rgb, depth = render_rgbd(ProceduralRoom(seed=2), truth[2], k)
    np.testing.assert_allclose(frame.depth, depth, atol=0.5 / 5000 + 1e-6)
    np.testing.assert_allclose(frame.rgb, rgb, atol=0.5 / 255 + 1e-6)
    assert (out / "gt_mesh.ply").stat().st_size > 1000
    # the folder is as readable as one mkdir makes (not mkdtemp's 0o700)
    assert out.stat().st_mode & 0o777 == (tmp_path / "made_by_mkdir").stat().st_mode & 0o777 == 0o755
    with pytest.raises(FileExistsError, match="not empty"):
        synthetic.synthesize(out, n_frames=2, width=32, height=24)
    synthetic.synthesize(out, n_frames=2, width=32, height=24, overwrite=True, mesh_voxel=0.2)
    assert len(data.load_sequence(out)) == 2


def test_synthesize_refuses_the_folder_it_runs_in_and_words_the_cli_refusals(tmp_path, capsys, monkeypatch):
    """--out . --force inside a synthesized folder emptied it and then failed ('.' has no parent
    to build the new folder beside); it is refused with every file kept.  Without --force a
    non-empty folder is refused in command-line words: --force for one of ours, a new folder for
    one of the user's (--force would be refused there too)."""
    out = tmp_path / "room"
    assert data.main(["synthesize", "--out", str(out), "--frames", "2", "--size", "16x12", "--mesh-voxel", "0.5"]) == 0
    before = sorted(path.name for path in out.iterdir())
    monkeypatch.chdir(out)
    assert data.main(["synthesize", "--out", ".", "--frames", "2", "--size", "16x12", "--force"]) == 2
    assert "current folder" in capsys.readouterr().err and sorted(path.name for path in out.iterdir()) == before
    monkeypatch.chdir(tmp_path)
    assert data.main(["synthesize", "--out", "room", "--frames", "2", "--size", "16x12"]) == 2
    assert "not empty; --force replaces it" in capsys.readouterr().err
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("the user's")
    assert data.main(["synthesize", "--out", "mine", "--frames", "2", "--size", "16x12"]) == 2
    assert "not written by this command (no scene.json), so choose a new folder" in capsys.readouterr().err
    (tmp_path / "gt.txt").write_text("a file of the user's")
    assert data.main(["synthesize", "--out", "gt.txt/sub", "--frames", "2", "--size", "16x12"]) == 2
    assert "gt.txt is a file, so no folder can be made inside it" in capsys.readouterr().err


def test_synthesize_along_real_motion_and_cli(tmp_path, shared_data, capsys):
    trajectory = shared_data / "trajectories" / "tum_rgbd_fr2_desk_groundtruth.txt"
    out = tmp_path / "desk"
    status = data.main(["synthesize", "--out", str(out), "--trajectory", str(trajectory), "--frames", "3",
                        "--size", "24x16", "--seed", "1", "--mesh-voxel", "0.2"])
    assert status == 0
    sequence = data.load_sequence(out)
    stamps, poses = synthetic.resample_trajectory(trajectory, 3, 30.0)
    np.testing.assert_allclose(sequence.timestamps, np.round(stamps, 6))
    # same motion up to the rigid placement: relative poses equal the source's
    np.testing.assert_allclose(np.linalg.inv(sequence.gt_poses[0]) @ sequence.gt_poses[2],
                               np.linalg.inv(poses[0]) @ poses[2], atol=1e-6)
    assert data.main(["synthesize", "--out", str(out), "--frames", "2"]) == 2
    assert "not empty" in capsys.readouterr().err


def test_synthesize_cli_start_offset(tmp_path, shared_data, capsys):
    """--start S takes frame 0 at S seconds after the file's first pose (TUM-VI room1 from 20 s)."""
    trajectory = shared_data / "trajectories" / "tum_vi_room1_groundtruth.txt"
    first_row = next(line for line in trajectory.read_text().splitlines() if line.strip() and line[0] != "#")
    first_stamp = float(first_row.split()[0])  # independent of the reader
    out = tmp_path / "room1"
    status = data.main(["synthesize", "--out", str(out), "--trajectory", str(trajectory), "--start", "20",
                        "--frames", "3", "--size", "24x16", "--mesh-voxel", "0.2"])
    assert status == 0
    sequence = data.load_sequence(out)
    np.testing.assert_allclose(sequence.timestamps, np.round(first_stamp + 20.0 + np.arange(3) / 30.0, 6), atol=2e-6)
    stamps, poses = synthetic.resample_trajectory(trajectory, 3, 30.0, start_time=first_stamp + 20.0)
    np.testing.assert_allclose(np.linalg.inv(sequence.gt_poses[0]) @ sequence.gt_poses[2],
                               np.linalg.inv(poses[0]) @ poses[2], atol=1e-6)
    assert data.main(["synthesize", "--out", str(tmp_path / "x"), "--start", "2"]) == 2
    assert "--start needs --trajectory" in capsys.readouterr().err
    assert data.main(["synthesize", "--out", str(tmp_path / "y"), "--trajectory", str(trajectory),
                      "--start", "-1"]) == 2
    assert "--start must be >= 0" in capsys.readouterr().err
    assert data.main(["synthesize", "--out", str(tmp_path / "z"), "--trajectory", "tum_vi_room1", "--start", "2",
                      "--frames", "8"]) == 2  # the shipped stretch holds 15-24 s of the recording
    message = capsys.readouterr().err
    assert "--start 2 s: tum_vi_room1.txt covers 15.000 to 24.000 s" in message and "[15.000, 23.767]" in message, message
    assert not (tmp_path / "z").exists()


def test_seeds_are_limited_to_what_the_generator_keeps():
    """PyTorch's CPU generator keeps 32 bits of a seed, so 3 and 2**32 + 3 gave the same run while
    config.json recorded two seeds.  Oracle: torch's own draws, and the refusals of both commands."""
    from tsslam_ref import config

    same = [torch.rand(4, generator=torch.Generator().manual_seed(s)) for s in (3, 2**32 + 3)]
    assert torch.equal(*same)  # why the range stops at 2**32 - 1
    with pytest.raises(ValueError, match="seed"):
        config.apply_overrides(config.tiny(), [f"seed={2**32}"])
    config.apply_overrides(config.tiny(), [f"seed={2**32 - 1}"])
    assert data.main(["synthesize", "--out", "unused", "--seed", str(2**32)]) == 2


def test_look_rotation_is_the_opencv_camera_worked_out_by_hand():
    """Looking along world +x with z up, an OpenCV camera's right (x_c) is world −y, its down (y_c)
    world −z and its forward (z_c) world +x: columns (0, −1, 0), (0, 0, −1), (1, 0, 0)."""
    expected = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    np.testing.assert_allclose(synthetic.look_rotation((2.0, 0.0, 0.0)), expected, atol=1e-15)
    tilted = synthetic.look_rotation((1.0, 1.0, -0.5))
    np.testing.assert_allclose(tilted.T @ tilted, np.eye(3), atol=1e-12)
    assert np.linalg.det(tilted) == pytest.approx(1.0) and tilted[2, 1] < 0  # image down is world down


def test_albedo_is_the_base_colour_scaled_between_0_55_and_1():
    """Module docstring: albedo = base x (0.55 + 0.45 w), w in [0, 1].  In an empty room (base
    ROOM_COLOUR everywhere) the ratio albedo / base stays in [0.55, 1] and spans most of it."""
    scene = ProceduralRoom(boxes=[], spheres=[], cylinders=[])
    generator = torch.Generator().manual_seed(0)
    low, high = torch.tensor(synthetic.ROOM_MIN), torch.tensor(synthetic.ROOM_MAX)
    points = low + (high - low) * torch.rand(4000, 3, generator=generator, dtype=torch.float64)
    ratio = scene.color(points).numpy() / np.asarray(synthetic.ROOM_COLOUR)
    assert ratio.min() >= 0.55 - 1e-12 and ratio.max() <= 1.0 + 1e-12
    assert ratio.min() < 0.65 and ratio.max() > 0.9


def test_depth_noise_sigma_and_dropouts_on_a_depth_step():
    """Module docstring, by hand, on a 200 x 200 step (1 m left, 3 m right, every surface facing the
    camera): sigma(1 m) = 0.0012 + 0.0019 · 0.6² = 0.001884 m and sigma(3 m) = 0.0012 + 0.0019 · 2.6²
    = 0.014044 m; the two columns at the step (spread 2 m > 5 % of z) lose 80 % of their pixels,
    the rest 0.5 % (binomial: 0.5 % of 39,600 is 198 +- 14)."""
    depth = torch.ones(200, 200, dtype=torch.float64)
    depth[:, 100:] = 3.0
    noisy = synthetic._depth_noise(depth, torch.ones_like(depth), torch.Generator().manual_seed(0)).numpy()
    dropped = noisy == 0
    edge = np.zeros_like(dropped)
    edge[:, 99:101] = True
    assert 0.72 < dropped[edge].mean() < 0.88
    assert 0.0035 < dropped[~edge].mean() < 0.0065
    for columns, z, sigma in ((slice(0, 99), 1.0, 0.001884), (slice(101, 200), 3.0, 0.014044)):
        kept = noisy[:, columns][noisy[:, columns] > 0]
        assert np.std(kept - z) == pytest.approx(sigma, rel=0.04)
    # the thresholds either side: a step of 3 % of z is no edge, one of 7 % is (limit 5 %); surfaces
    # seen at |cos| 0.19 are dropped whole, at 0.21 only the 0.5 % (limit 0.2)
    for far, edge_share in ((1.03, (0.0, 0.02)), (1.07, (0.72, 0.88))):
        step = torch.ones(200, 200, dtype=torch.float64)
        step[:, 100:] = far
        dropped = synthetic._depth_noise(step, torch.ones_like(step), torch.Generator().manual_seed(1)).numpy() == 0
        assert edge_share[0] <= dropped[edge].mean() <= edge_share[1], far
    grazing = torch.full((200, 200), 0.21, dtype=torch.float64)
    grazing[:, :100] = 0.19
    dropped = synthetic._depth_noise(torch.ones(200, 200, dtype=torch.float64), grazing,
                                     torch.Generator().manual_seed(2)).numpy() == 0
    assert dropped[:, :100].all() and dropped[:, 100:].mean() < 0.0065


def test_cylinder_sdf_at_points_worked_out_by_hand():
    """One cylinder of radius 0.3 m on z in [0, 1] m at the origin (room walls >= 1.3 m away):
    0.2 m above its cap, 0.2 m beside its side, sqrt(0.2² + 0.4²) m off its rim, −0.1 m inside below the cap."""
    scene = ProceduralRoom(boxes=[], spheres=[], cylinders=[((0.0, 0.0, 0.0, 1.0), 0.3, (1, 0, 0))])
    points = torch.tensor([[0.0, 0.0, 1.2], [0.5, 0.0, 0.5], [0.0, -0.5, 1.4], [0.0, 0.1, 0.9]], dtype=torch.float64)
    expected = [0.2, 0.2, np.hypot(0.2, 0.4), -0.1]
    np.testing.assert_allclose(scene.sdf(points).numpy(), expected, atol=1e-12)


def test_mesh_faces_wind_towards_free_space():
    """Oracle: each face's normal from its vertex order, (v1 − v0) x (v2 − v0), computed here (what a
    PLY reader sees, not trimesh's cached normals); the SDF grows along it for nearly every face."""
    scene = ProceduralRoom()
    mesh = scene.mesh(0.1)
    corners = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]  # (F, 3, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    areas = np.linalg.norm(normals, axis=-1)
    normals, corners = normals[areas > 1e-12] / areas[areas > 1e-12, None], corners[areas > 1e-12]
    centres = torch.from_numpy(corners.mean(axis=1))
    step = torch.from_numpy(0.02 * normals)
    assert (scene.sdf(centres + step) > scene.sdf(centres - step)).double().mean().item() > 0.9


def test_resampling_keeps_the_first_of_duplicate_stamps_and_puts_body_to_camera_on_the_right(tmp_path):
    """Oracle, by hand: stamps 0, 0, 1 s at x = 0, 5, 1 m (identity rotation, then 90 deg about z at
    1 s); frame 0 keeps the first line (x = 0).  With T_bc a 0.1 m shift along body x, the camera
    is 0.1 m along the *rotated* body x: at 1 s that is world +y, so (1, 0.1, 0)."""
    path = tmp_path / "duplicates.txt"
    s = np.sqrt(0.5)
    path.write_text(f"0.0 0 0 0 0 0 0 1\n0.0 5 0 0 0 0 0 1\n1.0 1 0 0 0 0 {s} {s}\n")
    times, poses = synthetic.resample_trajectory(path, 2, 1.0)
    np.testing.assert_allclose(times, [0.0, 1.0])
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    body_to_camera = np.eye(4)
    body_to_camera[0, 3] = 0.1
    _, shifted = synthetic.resample_trajectory(path, 2, 1.0, body_to_camera=body_to_camera)
    np.testing.assert_allclose(shifted[1][:3, 3], [1.0, 0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(shifted[1][:3, :3], poses[1][:3, :3], atol=1e-12)


def test_default_intrinsics_put_the_principal_point_at_the_image_centre():
    """Pixel centres at integers (module docstring): a 640 x 480 image's centre is (319.5, 239.5);
    the Kinect focal length is 525 px at 640 wide, 262.5 px at 320."""
    k = synthetic.default_intrinsics(640, 480)
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (525.0, 525.0, 319.5, 239.5, 640, 480)
    assert synthetic.default_intrinsics(320, 240).fx == 262.5


def test_synthesize_stopped_by_sigterm_leaves_no_scratch_folder(tmp_path):
    """A batch scheduler's SIGTERM killed `data synthesize` without a word and left its hidden
    scratch folder (``.<name>.<random>``) for good; it now stops as on Ctrl-C: one line, exit 130,
    the scratch folder removed and no dataset folder made."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    command = [sys.executable, "-m", "tsslam_ref.data", "synthesize", "--out", str(tmp_path / "room"),
               "--frames", "400", "--size", "64x48"]
    process = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".room.*")) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)  # until the frames are being written
    assert process.poll() is None, process.communicate()
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130 and "interrupted; nothing was left half-written" in err, (process.returncode, err)
    assert list(tmp_path.iterdir()) == []


def test_synthesize_through_a_link_and_up_writes_where_the_system_finds_the_folder(tmp_path, monkeypatch):
    """'out/../run/room' with 'out' a link: the scratch folder's parent was tidied as text into a
    folder that does not exist ("The directory does not exist")."""
    (tmp_path / "real" / "inner").mkdir(parents=True)
    (tmp_path / "real" / "run").mkdir()
    (tmp_path / "out").symlink_to(tmp_path / "real" / "inner")
    monkeypatch.chdir(tmp_path)
    synthetic.synthesize("out/../run/room", n_frames=3, width=32, height=24, fps=30.0, seed=0)
    assert (tmp_path / "real" / "run" / "room" / "rgb.txt").is_file()
    assert [path.name for path in (tmp_path / "real" / "run").iterdir()] == ["room"]


def test_the_builtin_path_is_the_documented_ellipse_one_turn_per_12_s():
    """synthetic.builtin_trajectory's docstring: an ellipse of 0.4 x 0.3 m at about 1.3 m height, one
    turn per 12 s.  By hand: x = 0.4 at t = 0 and 12 s, y = 0.3 a quarter turn in (3 s), x = -0.4
    half a turn in (6 s); the height stays within 1.3 +- 0.1 m."""
    positions = synthetic.builtin_trajectory(np.array([0.0, 3.0, 6.0, 12.0]))[:, :3, 3]
    np.testing.assert_allclose(positions[0], [0.4, 0.0, 1.3], atol=1e-12)
    np.testing.assert_allclose(positions[1], [0.0, 0.3, 1.3], atol=1e-12)
    np.testing.assert_allclose(positions[2], [-0.4, 0.0, 1.3], atol=1e-12)
    np.testing.assert_allclose(positions[3], positions[0], atol=1e-12)
    heights = synthetic.builtin_trajectory(np.linspace(0.0, 12.0, 97))[:, 2, 3]
    assert np.all(np.abs(heights - 1.3) <= 0.1 + 1e-12)


def test_a_camera_too_close_to_a_surface_is_refused_naming_the_frame(tmp_path, monkeypatch):
    """synthesize refuses a path that puts the camera nearer than MIN_CLEARANCE (0.15 m) to a
    surface: the rendering would sit inside the near plane.  By hand: the last frame 0.12 m from the
    +x wall at x = 2.0 m; 0.2 m from it passes."""
    builtin = synthetic.builtin_trajectory

    def near_the_wall(distance):
        def path(times):
            poses = builtin(times)
            poses[-1, :3, 3] = [2.0 - distance, 0.0, 1.3]
            return poses
        return path

    monkeypatch.setattr(synthetic, "builtin_trajectory", near_the_wall(0.12))
    with pytest.raises(ValueError, match=r"frame 3 puts the camera 0\.12 m from a surface \(need >= 0\.15 m"):
        synthetic.synthesize(tmp_path / "near", n_frames=4, width=16, height=12, mesh_voxel=0.2)
    assert not (tmp_path / "near").exists()
    monkeypatch.setattr(synthetic, "builtin_trajectory", near_the_wall(0.2))
    synthetic.synthesize(tmp_path / "clear", n_frames=4, width=16, height=12, mesh_voxel=0.2)
    assert len((tmp_path / "clear" / "rgb.txt").read_text().split("\n")) > 4
