"""The compiled hash-grid kernel where the field's own tests do not reach: the tracking gradient
(points only) with other feature counts than Co-SLAM's two, float64 inputs, and the one dense
vertex whose index equals its level's size.  Oracles: the reference path of the same grid (plain
PyTorch indexing and autograd) and a value worked by hand.  See also tests/test_field.py."""

import pytest
import torch

from tsslam_ref.field import HashGridEncoding

from test_field import _level0_feature_on_every_path, _use_path


def _outputs_and_gradients(grid: HashGridEncoding, path: str, points: torch.Tensor, upstream: torch.Tensor):
    """(features, point gradient) of ``grid`` on ``path`` for sum(features * upstream)."""
    _use_path(grid, path)
    assert grid.uses_compiled_kernel(points) == (path == "compiled")
    x = points.clone().requires_grad_(True)
    out = grid(x)
    (out * upstream).sum().backward()
    return out.detach(), x.grad


@pytest.mark.parametrize("n_features", [1, 4])
def test_the_point_gradient_alone_with_one_and_four_features_per_level(compiled_kernel, n_features):
    """Tracking differentiates the points with the table frozen, which the kernel computes in a pass
    of its own; with F = 1 and 4 features per level (its general loop) it equals the reference's
    point gradient to float32 rounding, points inside and outside the box."""
    torch.manual_seed(5)
    grid = HashGridEncoding(120, n_features=n_features, log2_hashmap_size=12)
    with torch.no_grad():
        grid.table.normal_()
    grid.table.requires_grad_(False)
    points = torch.rand(2000, 3) * 1.4 - 0.2
    upstream = torch.randn(2000, grid.out_dim)
    (v_fast, x_fast), (v_ref, x_ref) = (_outputs_and_gradients(grid, path, points, upstream)
                                        for path in ("compiled", "reference"))
    assert torch.allclose(v_fast, v_ref, atol=1e-5)
    assert torch.allclose(x_fast, x_ref, atol=1e-3, rtol=1e-4)


def test_float64_points_and_table_agree_with_the_reference_to_float64_rounding(compiled_kernel):
    """A float64 grid (16 levels, non-integer level scales) gives the reference's features and point
    gradient to 1e-12: the kernel keeps every level's scale in float64 (a scale rounded to float32
    moves a position by about 1e-6 of a cell)."""
    torch.manual_seed(6)
    grid = HashGridEncoding(120, log2_hashmap_size=12).double()
    assert any(scale != round(scale) for scale in grid.level_scales)
    with torch.no_grad():
        grid.table.normal_()
    grid.table.requires_grad_(False)
    points = torch.rand(2000, 3, dtype=torch.float64) * 1.4 - 0.2
    upstream = torch.randn(2000, grid.out_dim, dtype=torch.float64)
    (v_fast, x_fast), (v_ref, x_ref) = (_outputs_and_gradients(grid, path, points, upstream)
                                        for path in ("compiled", "reference"))
    assert torch.allclose(v_fast, v_ref, rtol=0, atol=1e-12)
    assert torch.allclose(x_fast, x_ref, rtol=1e-10, atol=1e-10)


def test_the_dense_vertex_whose_index_is_the_level_size_wraps_to_row_zero(compiled_kernel):
    """R = 6, size 216: the point (0, 0, 1) on the box's top face sits at position (0.5, 0.5, 5.5),
    corners i, j in {0, 1}, k in {5, 6}, each weighing 1/8.  The corner (0, 0, 6) has index
    0 + 6 * 0 + 36 * 6 = 216, the size itself, which wraps to row 0 like every index past the
    table (216 + 1 -> 1, ...); rows 180, 181, 186, 187, 0, 1, 6, 7, mean 748 / 8 (row 216, the
    next level's first, would give 964 / 8)."""
    grid = HashGridEncoding(12, n_levels=2, base_resolution=6, log2_hashmap_size=8).double()
    assert grid.level_resolutions[0] == 6 and grid.level_sizes[0] == 216 and grid.level_dense == [True, False]
    values = _level0_feature_on_every_path(grid, (0.0, 0.0, 1.0))
    assert "compiled" in values
    for path, value in values.items():
        assert value == pytest.approx(748 / 8, abs=1e-9), path
