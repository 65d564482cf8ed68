"""view3d: the figures hold what they are given, and the display bundle holds both pictures.

Oracles: frustum corners from the pinhole formula written out with fx, fy, cx, cy and scipy's
rotations (not K^-1), checked again by projecting them back to the image corners; the inputs
themselves for trajectories, clouds and meshes; plotly's own JSON reader and Pillow's PNG decoder
for the bundle; pixel colours of the PNG for what it draws.
"""

import base64
import io
import json

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

import plotly.io

from tsslam_ref import view3d

FX, FY, CX, CY, W, H = 120.0, 110.0, 81.0, 58.5, 160, 120
K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])


def random_poses(count: int, seed: int = 0) -> np.ndarray:
    """(count, 4, 4) camera-to-world poses with scipy's random rotations."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.uniform(-2, 2, size=(count, 3))
    return poses


def trace_points(trace) -> np.ndarray:
    """(N, 3) coordinates of a trace, gaps (None) dropped."""
    xyz = [np.array([np.nan if v is None else v for v in trace[a]], dtype=float) for a in "xyz"]
    points = np.stack(xyz, axis=1)
    return points[~np.isnan(points).any(axis=1)]


def test_frustum_corners_are_the_back_projected_image_corners():
    poses, depth = random_poses(4), 0.3
    corners = view3d.frustum_corners(poses, K, (W, H), depth=depth)
    pixels = [(-0.5, -0.5), (W - 0.5, -0.5), (W - 0.5, H - 0.5), (-0.5, H - 0.5)]
    for pose, camera_corners in zip(poses, corners):
        for (u, v), corner in zip(pixels, camera_corners):
            in_camera = depth * np.array([(u - CX) / FX, (v - CY) / FY, 1.0])
            np.testing.assert_allclose(corner, pose[:3, :3] @ in_camera + pose[:3, 3], atol=1e-12)
            back = pose[:3, :3].T @ (corner - pose[:3, 3])  # world -> camera, then project
            np.testing.assert_allclose([FX * back[0] / back[2] + CX, FY * back[1] / back[2] + CY, back[2]],
                                       [u, v, depth], atol=1e-9)


def test_frustum_corners_take_one_intrinsics_per_camera_and_torch():
    poses = random_poses(3, seed=1)
    per_camera = np.stack([K, 2 * K - np.diag([0, 0, 1.0]), K])
    corners = view3d.frustum_corners(torch.tensor(poses), torch.tensor(per_camera), (W, H), 0.5)
    np.testing.assert_allclose(corners[0], view3d.frustum_corners(poses[:1], K, (W, H), 0.5)[0])
    assert not np.allclose(corners[1], view3d.frustum_corners(poses[1:2], K, (W, H), 0.5)[0])


def test_camera_frusta_trace_draws_apex_corners_and_every_nth_camera():
    poses = random_poses(6, seed=2)
    trace = view3d.camera_frusta(poses, K, (W, H), depth=0.2, every=2)
    drawn = trace_points(trace)
    expected = np.concatenate([poses[::2, :3, 3], view3d.frustum_corners(poses[::2], K, (W, H), 0.2).reshape(-1, 3)])
    for point in expected:
        assert np.abs(drawn - point).max(axis=1).min() < 1e-4
    for pose in poses[1::2]:
        assert np.abs(drawn - pose[:3, 3]).max(axis=1).min() > 1e-3
    assert trace.mode == "lines" and sum(v is None for v in trace.x) == 3  # one piece per camera


def test_frustum_roof_sits_above_the_image_top_edge():
    """Oracle by hand: identity pose, K = diag(100, 100, 1) with (cx, cy) = (49.5, 39.5), a
    100 x 80 image, depth 1: the top corners are at y = (-0.5 - 39.5) / 100 = -0.4, their midpoint
    at (0, -0.4, 1), and the roof 0.25 m further towards -y (up in OpenCV axes): (0, -0.65, 1)."""
    intrinsics = np.array([[100.0, 0.0, 49.5], [0.0, 100.0, 39.5], [0.0, 0.0, 1.0]])
    trace = view3d.camera_frusta(np.eye(4)[None], intrinsics, (100, 80), depth=1.0)
    roof = [trace[a][9] for a in "xyz"]  # apex, c0, c1, apex, c2, c3, apex, c3, c0, roof, ...
    np.testing.assert_allclose(roof, [0.0, -0.65, 1.0], atol=1e-9)


def test_trajectory_holds_the_positions_from_positions_or_poses():
    poses = random_poses(10, seed=3)
    from_poses = view3d.trajectory(poses, name="estimate", color="red")
    from_positions = view3d.trajectory(torch.tensor(poses[:, :3, 3]), name="ground truth")
    np.testing.assert_allclose(trace_points(from_poses), poses[:, :3, 3], atol=5e-5)
    np.testing.assert_allclose(trace_points(from_positions), poses[:, :3, 3], atol=5e-5)
    assert (from_poses.name, from_positions.name) == ("estimate", "ground truth")


def test_point_cloud_keeps_a_seeded_subset_with_its_own_values():
    rng = np.random.default_rng(4)
    points, values = rng.uniform(-1, 1, size=(5000, 3)), rng.uniform(0, 3, size=5000)
    trace = view3d.point_cloud(points, values, max_points=700, seed=7, color_title="depth (m)")
    drawn = trace_points(trace)
    assert drawn.shape == (700, 3)
    nearest = np.abs(points[None] - drawn[:, None]).max(axis=2).argmin(axis=1)  # (700,) source rows
    np.testing.assert_allclose(points[nearest], drawn, atol=5e-5)
    np.testing.assert_allclose(values[nearest], trace.marker.color, atol=5e-5)
    assert len(set(nearest.tolist())) == 700
    again = view3d.point_cloud(points, values, max_points=700, seed=7)
    assert again.x == trace.x and view3d.point_cloud(points, max_points=700, seed=8).x != trace.x
    small = view3d.point_cloud(points[:10], max_points=700)
    np.testing.assert_allclose(trace_points(small), points[:10], atol=5e-5)


def test_mesh_faces_and_colours_are_the_inputs():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    faces = np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3]])
    colours = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    trace = view3d.mesh(vertices, torch.tensor(faces), colours)
    np.testing.assert_array_equal(np.stack([trace.i, trace.j, trace.k], axis=1), faces)
    np.testing.assert_allclose(trace_points(trace), vertices)
    assert list(trace.vertexcolor) == ["rgb(255,0,0)", "rgb(0,255,0)", "rgb(0,0,255)", "rgb(255,255,255)"]


def test_mesh_takes_a_read_ply_s_rgba_integer_colours_as_0_to_255():
    """A mesh.ply read by trimesh gives (V, 4) uint8 RGBA; a dark one (every value <= 1) is still 0-255."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    rgba = np.array([[1, 0, 0, 255], [0, 1, 0, 255], [200, 100, 50, 255]], dtype=np.uint8)
    trace = view3d.mesh(vertices, [[0, 1, 2]], rgba)
    assert list(trace.vertexcolor) == ["rgb(1,0,0)", "rgb(0,1,0)", "rgb(200,100,50)"]
    dark = view3d.mesh(vertices, [[0, 1, 2]], rgba[:2].repeat([1, 2], axis=0)[:, :3])
    assert list(dark.vertexcolor) == ["rgb(1,0,0)", "rgb(0,1,0)", "rgb(0,1,0)"]


def test_trajectory_marks_its_first_position():
    """Oracle: the start marker (size 6) is on the first of the given positions, the others size 0."""
    trace = view3d.trajectory(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]))
    assert list(trace.marker.size) == [6, 0, 0] and trace.mode == "lines+markers"


@pytest.mark.parametrize("view,eye", [((90.0, 0.0), (0.0, 0.0, 2.0)), ((0.0, 90.0), (0.0, 2.0, 0.0)),
                                      ((30.0, 0.0), (3**0.5, 0.0, 1.0))])
def test_scene_view_puts_the_eye_at_elevation_and_azimuth(view, eye):
    """Oracle by hand: the eye sits 2 units from the centre at the given (elevation, azimuth), z up:
    straight above for elevation 90, on +y for azimuth 90, (2 cos 30, 0, 2 sin 30) for (30, 0)."""
    camera = view3d.scene(view3d.trajectory(random_poses(3)), view=view).layout.scene.camera
    np.testing.assert_allclose([camera.eye.x, camera.eye.y, camera.eye.z], eye, atol=1e-4)


def test_scene_has_equal_axes_in_metres():
    figure = view3d.scene(view3d.trajectory(random_poses(3)), title="path")
    assert figure.layout.scene.aspectmode == "data"
    assert [figure.layout.scene[f"{a}axis"].title.text for a in "xyz"] == ["x (m)", "y (m)", "z (m)"]


def test_bundle_holds_plotly_json_and_a_png_of_the_scene():
    poses = random_poses(5, seed=5)
    cloud = np.random.default_rng(5).uniform(-2, 2, size=(300, 3))
    figure = view3d.scene(view3d.point_cloud(cloud, cloud[:, 2]), view3d.camera_frusta(poses, K, (W, H)),
                          view3d.trajectory(poses, name="gt", color="red", width=8))
    bundle = view3d.mimebundle(figure)
    assert set(bundle) == {view3d.MIMETYPE, "image/png", "text/plain"}
    text = json.dumps(bundle[view3d.MIMETYPE])  # plain JSON, as a notebook stores it
    assert "bdata" not in text
    reread = plotly.io.from_json(text)
    np.testing.assert_allclose(trace_points(reread.data[2]), poses[:, :3, 3], atol=5e-5)
    image = np.asarray(Image.open(io.BytesIO(base64.b64decode(bundle["image/png"]))).convert("RGB"))
    assert image.shape[0] > 300 and image.shape[1] > 400
    red = (image[..., 0] > 200) & (image[..., 1] < 60) & (image[..., 2] < 60)
    assert red.sum() > 50  # the red trajectory is drawn
    no_path = view3d.scene(view3d.point_cloud(cloud, cloud[:, 2]))
    image = np.asarray(Image.open(io.BytesIO(view3d.png_bytes(no_path))).convert("RGB"))
    assert ((image[..., 0] > 200) & (image[..., 1] < 60) & (image[..., 2] < 60)).sum() < 5


def test_bundle_draws_a_mesh_and_rgb_points():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    figure = view3d.scene(view3d.mesh(vertices, [[0, 1, 2]], color="blue"),
                          view3d.point_cloud(vertices, np.tile([0.0, 1.0, 0.0], (4, 1)), size=6))
    image = np.asarray(Image.open(io.BytesIO(view3d.png_bytes(figure))).convert("RGB")).astype(int)
    assert ((image[..., 2] > 150) & (image[..., 0] < 80) & (image[..., 1] < 80)).sum() > 100  # blue face
    assert ((image[..., 1] > 150) & (image[..., 0] < 80) & (image[..., 2] < 80)).sum() > 5  # green points


@pytest.mark.parametrize("call, message", [
    (lambda: view3d.point_cloud(np.zeros((5, 2))), r"points has shape \(5, 2\), expected \(N, 3\)"),
    (lambda: view3d.point_cloud(np.zeros((5, 3)), np.zeros(4)), r"color has shape \(4,\), expected \(5,\)"),
    (lambda: view3d.point_cloud(np.full((2, 3), np.nan)), "non-finite"),
    (lambda: view3d.point_cloud(np.zeros((2, 3)), 2 * np.ones((2, 3))), r"RGB color must lie in \[0, 1\]"),
    (lambda: view3d.point_cloud(np.zeros((2, 3)), np.zeros(2), colorscale="Jet"), "colorscale = 'Jet'"),
    (lambda: view3d.point_cloud(np.zeros((2, 3)), max_points=0), "max_points = 0"),
    (lambda: view3d.frustum_corners(np.eye(4), K, (W, H)), r"poses has shape \(4, 4\), expected \(N, 4, 4\)"),
    (lambda: view3d.frustum_corners(np.eye(4)[None], K[:2], (W, H)), r"intrinsics has shape \(2, 3\)"),
    (lambda: view3d.frustum_corners(np.eye(4)[None], K, (W, H), depth=0), "depth = 0"),
    (lambda: view3d.camera_frusta(np.eye(4)[None], K, (W, H), every=0), "every = 0"),
    (lambda: view3d.trajectory(np.zeros((3, 2))), r"positions has shape \(3, 2\)"),
    (lambda: view3d.mesh(np.zeros((3, 3)), [[0, 1, 3]]), r"faces must be integer indices in \[0, 3\)"),
    (lambda: view3d.mesh(np.zeros((3, 3)), [[0, 1.5, 2]]), "faces must be integer"),
])
def test_bad_input_names_the_value_and_what_was_expected(call, message):
    with pytest.raises(ValueError, match=message):
        call()
