"""Tests for tsslam_ref.mesh: marching cubes of analytic SDFs, the |s| cutoff, colours, saving."""

import numpy as np
import pytest
import torch
import trimesh

from tsslam_ref.mesh import extract_mesh, query_grid, save_mesh

CENTRE = torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64)
RADIUS = 0.45
TRUNCATION = 0.1


RAMP_OFFSET = torch.tensor([0.3, 0.6, 0.2], dtype=torch.float64)
"""Colour ramp rgb = clip(world xyz + RAMP_OFFSET, 0, 1): 0.05..0.95 per channel on the sphere below."""


def colour_ramp(points):
    """(N, 3) world points in metres -> (N, 3) rgb in 0..1, a different linear ramp per channel."""
    return torch.clamp(points + RAMP_OFFSET.to(points), 0.0, 1.0)


class AnalyticField:
    """A lambda wrapped as a field: normalised SDF of a sphere (metric / tr) and a colour ramp of
    world position; the bound's minimum (-0.5, -0.8, -0.4) is not the origin, so colours looked up
    at grid-local instead of world coordinates come out 0.4..0.8 off."""

    def __init__(self, sdf_metric):
        self.sdf_metric = sdf_metric
        self.bound = torch.tensor([[-0.5, 0.9], [-0.8, 0.6], [-0.4, 1.0]], dtype=torch.float64)

    def sdf(self, points):
        return self.sdf_metric(points) / TRUNCATION

    def __call__(self, points):
        return colour_ramp(points), self.sdf(points)


def sphere(points):
    return torch.linalg.vector_norm(points - CENTRE, dim=-1) - RADIUS


def test_sphere_mesh_has_the_right_radius_and_outward_normals():
    mesh = extract_mesh(AnalyticField(sphere), voxel_size=0.04)
    radii = np.linalg.norm(mesh.vertices - CENTRE.numpy(), axis=1)
    assert np.abs(radii - RADIUS).max() < 0.01
    assert mesh.is_watertight
    # volume of the polyhedron vs the sphere (marching cubes cuts corners: slightly smaller)
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * RADIUS**3, rel=0.03)
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - CENTRE.numpy())
    assert (outward > 0).all()
    # each vertex carries the ramp at its own world position, stored as uint8 (0..255 levels):
    # within one level of 255 * ramp (truncation or rounding), alpha opaque
    colours = np.asarray(mesh.visual.vertex_colors)
    assert colours.shape == (len(mesh.vertices), 4) and colours.dtype == np.uint8
    expected_levels = 255 * np.clip(mesh.vertices + RAMP_OFFSET.numpy(), 0, 1)  # (V, 3), by hand
    assert np.abs(colours[:, :3] - expected_levels).max() <= 1 + 1e-3
    assert (colours[:, 3] == 255).all()
    assert np.ptp(colours[:, :3], axis=0).min() > 200  # a real ramp: every channel spans most levels


def test_cells_far_from_any_surface_are_skipped():
    """A field that crosses zero far from the true surface (|s| > cutoff on both sides) gives no faces there."""

    def sphere_with_far_jump(points):
        metric = sphere(points)
        far_side = points[:, 0] > 0.75  # a sign flip in empty space, |s| = 5 on both sides
        return torch.where(far_side, torch.full_like(metric, -0.5), torch.where(points[:, 0] > 0.7, torch.full_like(metric, 0.5), metric))

    field = AnalyticField(sphere_with_far_jump)
    kept = extract_mesh(field, voxel_size=0.04, sdf_cutoff=3.0, color=False)
    assert kept.vertices[:, 0].max() < 0.7  # only the sphere
    everything = extract_mesh(field, voxel_size=0.04, sdf_cutoff=1e9, color=False)
    assert everything.vertices[:, 0].max() > 0.7  # without the cutoff the jump becomes a wall


def test_save_mesh_is_atomic_and_refuses_to_overwrite(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    target = tmp_path / "m.ply"
    save_mesh(mesh, target)
    loaded = trimesh.load(target)
    assert np.allclose(loaded.vertices, mesh.vertices)
    with pytest.raises(FileExistsError):
        save_mesh(mesh, target)
    save_mesh(mesh, target, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["m.ply"]
    with pytest.raises(ValueError, match=".ply"):
        save_mesh(mesh, tmp_path / "m.obj")


def test_grid_query_in_chunks_equals_the_whole_meshgrid_at_once():
    """The grid built chunk by chunk from flat indices holds the meshgrid's points, in its order."""
    axes = [np.linspace(-0.5, 0.9, 8), np.linspace(-0.8, 0.6, 5), np.linspace(-0.4, 1.0, 11)]
    weights = torch.tensor([1.0, 10.0, 100.0], dtype=torch.float64)

    def position_code(points):  # distinct for every grid point, and not linear in the coordinates
        return (points * weights).sum(dim=-1) + torch.sin(7 * points[:, 0])

    whole = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    expected = position_code(torch.from_numpy(whole)).float().numpy().reshape(8, 5, 11)
    for chunk in (1, 7, 64, 440, 10_000):  # 440 points: chunks that do and do not divide it
        values = query_grid(position_code, axes, chunk, torch.device("cpu"), torch.float64)
        assert values.dtype == np.float32 and values.shape == (8, 5, 11)
        np.testing.assert_array_equal(values, expected)


def test_no_surface_raises():
    field = AnalyticField(lambda p: torch.ones(p.shape[0], dtype=p.dtype))
    with pytest.raises(ValueError, match="zero crossing"):
        extract_mesh(field, voxel_size=0.1)


class UnitBoxField:
    """A normalised SDF given directly (no truncation scaling) on the unit box."""

    def __init__(self, sdf):
        self.sdf = sdf
        self.bound = torch.tensor([[0.0, 1.0]] * 3, dtype=torch.float64)


def test_the_cutoff_keeps_exactly_the_cells_whose_corners_are_near_the_surface():
    """Co-SLAM's rule per cell: mesh it iff all 8 corners have |s| < cutoff.  Oracle: fields whose
    one crossing cell is (or is not) such a cell, anywhere in the box, the last layer included."""
    def steps(values, edges):  # s as a step function of x: values[i] between edges[i-1] and edges[i]
        return lambda p: torch.as_tensor(np.asarray(values)[np.searchsorted(edges, p[:, 0].numpy(), side="right")],
                                         dtype=p.dtype)

    far_corner = UnitBoxField(steps([-10.0, 1.0], [0.45]))  # crossing cell 0.4-0.5 has a corner at -10
    with pytest.raises(ValueError, match="zero crossing"):
        extract_mesh(far_corner, voxel_size=0.1, sdf_cutoff=3.0, color=False)
    near_corners = UnitBoxField(steps([-1.0, 1.0, 10.0], [0.45, 0.55]))  # corners -1 / +1: kept
    wall = extract_mesh(near_corners, voxel_size=0.1, sdf_cutoff=3.0, color=False)
    assert np.allclose(wall.vertices[:, 0], 0.45) and np.ptp(wall.vertices[:, 1]) == pytest.approx(1.0)
    top_layer = UnitBoxField(lambda p: (p[:, 0] - 0.95) / 0.1)  # the crossing in the box's last cell
    plane = extract_mesh(top_layer, voxel_size=0.1, sdf_cutoff=3.0, color=False)
    assert np.allclose(plane.vertices[:, 0], 0.95) and np.ptp(plane.vertices[:, 2]) == pytest.approx(1.0)


def test_a_grid_too_large_is_refused_before_any_memory_is_taken():
    field = UnitBoxField(lambda p: p[:, 0] - 0.5)
    field.bound = torch.tensor([[0.0, 82.0], [0.0, 62.0], [0.0, 67.0]], dtype=torch.float64)  # a depth scale 10x off
    with pytest.raises(ValueError, match=r"82.0 x 62.0 x 67.0 m bound at voxel_size 0.03 m needs 1.26e\+10 grid points"):
        extract_mesh(field, voxel_size=0.03, color=False)


def test_a_corner_at_exactly_the_cutoff_or_far_on_the_upper_side_skips_the_cell():
    """The cutoff is strict (|s| < cutoff keeps a corner, |s| = cutoff does not), and all 8
    corners count, the upper ones on every axis too.  Oracle: step fields whose only crossing
    cell (0.4-0.5 along one axis) has corners -1 below and +3 (or -10 with +1 below) above."""
    def steps(values, axis):  # s = values[0] for coordinate < 0.45 along axis, values[1] beyond
        return lambda p: torch.where(p[:, axis] < 0.45, torch.tensor(values[0], dtype=p.dtype),
                                     torch.tensor(values[1], dtype=p.dtype))

    for axis in range(3):
        for values in ([-1.0, 3.0], [1.0, -10.0]):
            with pytest.raises(ValueError, match="zero crossing"):
                extract_mesh(UnitBoxField(steps(values, axis)), voxel_size=0.1, sdf_cutoff=3.0, color=False)
        kept = extract_mesh(UnitBoxField(steps([-1.0, 2.99], axis)), voxel_size=0.1, sdf_cutoff=3.0, color=False)
        assert np.allclose(kept.vertices[:, axis], 0.4 + 0.1 / 3.99)  # linear interpolation -1 -> 2.99


def test_the_grid_has_round_extent_over_voxel_cells_spanning_the_bound_exactly():
    """N = round(extent / voxel + 0.0005) cells per axis, stretched to the bound.  Oracle by hand:
    a 0.7 m side at 0.1 m is 7 cells (0.7 / 0.1 = 6.9999... in floating point), a 1 m side at
    0.37 m is round(2.70) = 3 cells of 1/3 m; a plane x = 0.5 then has vertices at x = 0.5 on
    the (N + 1) x (N + 1) lattice of the other two axes."""
    field = UnitBoxField(lambda p: (p[:, 0] - 0.5) / 0.1)
    for side, voxel, n_cells in ((0.7, 0.1, 7), (1.0, 0.37, 3)):
        field.bound = torch.tensor([[0.0, 1.0], [0.0, side], [0.0, side]], dtype=torch.float64)
        plane = extract_mesh(field, voxel_size=voxel, color=False)
        assert np.allclose(plane.vertices[:, 0], 0.5)
        for axis in (1, 2):
            np.testing.assert_allclose(np.unique(plane.vertices[:, axis].round(9)), np.linspace(0, side, n_cells + 1))


def test_a_run_culls_with_the_raw_camera_whatever_the_crop(tmp_path):
    """Co-SLAM culls with the raw images' camera (its YAML values), not the cropped one the run tracks
    with; a run with crop_edge used to cull with the cropped frustum (completion measured
    3.4x better).  Oracle: the same meshes culled with the folder's own calibration, which no crop changes."""
    from tsslam_ref import data, synthetic
    from tsslam_ref.reconstruction_metrics import cull_mesh, mesh_metrics
    from tsslam_ref.run_outputs import reconstruction_metrics

    folder = synthetic.synthesize(tmp_path / "room", n_frames=6, width=64, height=48, clean_depth=True, mesh_voxel=0.1)
    gt_mesh = trimesh.load(folder / "gt_mesh.ply", process=False)
    reconstruction = gt_mesh.copy()
    reconstruction.apply_translation([0.02, 0.0, 0.0])
    cropped = data.load_sequence(folder, crop_edge=8)
    native = cropped.native_intrinsics
    assert (cropped.intrinsics.width, cropped.intrinsics.height) == (48, 32)
    raw = (native.fx, native.fy, native.cx, native.cy, native.width, native.height)
    poses = cropped.gt_poses[::2]
    expected = mesh_metrics(cull_mesh(reconstruction, poses, raw), cull_mesh(gt_mesh, poses, raw), n_points=50_000,
                            threshold=0.05, seed=0)
    for sequence in (cropped, data.load_sequence(folder)):
        result = reconstruction_metrics(reconstruction, gt_mesh, sequence, seed=0)
        assert {key: result[key] for key in expected} == expected
        assert result["culling"]["camera"] == dict(zip(("fx", "fy", "cx", "cy", "width", "height"), raw))
        assert result["culling"]["cameras"] == 3 and result["sampling_seed"] == 0


def test_a_ground_truth_mesh_in_millimetres_is_not_scored_but_named(tmp_path, capsys):
    """A run scored a GT mesh in millimetres silently (accuracy 4.53 m, completion 1462 m in metrics.json)."""
    from tsslam_ref import data, synthetic
    from tsslam_ref.run_outputs import reconstruction_metrics

    folder = synthetic.synthesize(tmp_path / "room", n_frames=4, width=32, height=24, clean_depth=True, mesh_voxel=0.2)
    gt_mesh = trimesh.load(folder / "gt_mesh.ply", process=False)
    in_millimetres = gt_mesh.copy()
    in_millimetres.apply_scale(1000.0)
    result = reconstruction_metrics(gt_mesh, in_millimetres, data.load_sequence(folder), seed=0)
    assert list(result) == ["reconstruction_note"] and "must be in metres" in result["reconstruction_note"], result
    assert "warning: reconstruction metrics: not scored: the ground-truth mesh spans" in capsys.readouterr().err
    assert "accuracy_m" in reconstruction_metrics(gt_mesh, gt_mesh, data.load_sequence(folder), seed=0)
