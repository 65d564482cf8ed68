"""Tests for tsslam_ref.field: OneBlob, hash-grid geometry (tiny-cuda-nn grid.h), the field."""

import dataclasses
import math
import os
from pathlib import Path

import pytest
import torch

from tsslam_ref import config, hash_kernel
from tsslam_ref.field import HashGridEncoding, OneBlobEncoding, SceneField, finest_resolution, trilinear_lookup


# ---------------------------------------------------------------- OneBlob


def _oneblob_direct(x: float, n_bins: int = 16):
    """Independent oracle: integrate the periodic quartic kernel over each bin numerically."""
    values = []
    for k in range(n_bins):
        lo, hi = k / n_bins, (k + 1) / n_bins
        t = torch.linspace(lo, hi, 4001, dtype=torch.float64)
        total = torch.zeros_like(t)
        for shift in (-1.0, 0.0, 1.0):
            v = (t - x + shift) * n_bins
            total += torch.where(v.abs() <= 1, (15 / 16) * (1 - v**2) ** 2, torch.zeros_like(v)) * n_bins
        values.append(torch.trapezoid(total, t))
    return torch.stack(values)


def _oneblob(compiled: bool, request) -> OneBlobEncoding:
    """The PyTorch OneBlob, or the compiled one (which needs the kernel's fixture)."""
    if compiled:
        request.getfixturevalue("compiled_kernel")
    return OneBlobEncoding(16, compiled=compiled)


@pytest.mark.parametrize("compiled", [False, True], ids=["torch", "compiled"])
def test_oneblob_matches_numerical_integral_of_quartic_kernel(compiled, request):
    encoding = _oneblob(compiled, request)
    xs = [0.0, 0.013, 0.03125, 0.06, 0.3, 0.5, 0.77, 0.95, 0.97, 0.99, 1 - 1e-9]
    points = torch.tensor([[x, x, x] for x in xs], dtype=torch.float64)
    assert encoding.uses_compiled_kernel(points) == compiled
    codes = encoding(points)
    for row, x in zip(codes, xs):
        assert torch.allclose(row[:16], _oneblob_direct(x), atol=1e-6)


@pytest.mark.parametrize("compiled", [False, True], ids=["torch", "compiled"])
def test_oneblob_partition_of_unity_and_periodicity(compiled, request):
    encoding = _oneblob(compiled, request)
    points = torch.rand(500, 3, dtype=torch.float64) * 3 - 1
    codes = encoding(points).view(-1, 3, 16)
    assert torch.allclose(codes.sum(-1), torch.ones(500, 3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(encoding(points + 1.0), encoding(points), atol=1e-12)
    edge = encoding(torch.zeros(1, 3, dtype=torch.float64)).view(3, 16)
    assert torch.allclose(edge[:, 0], torch.full((3,), 0.5, dtype=torch.float64))
    assert torch.allclose(edge[:, 15], torch.full((3,), 0.5, dtype=torch.float64))
    assert encoding.out_dim == 48


@pytest.mark.parametrize("compiled", [False, True], ids=["torch", "compiled"])
def test_oneblob_gradient_matches_finite_differences(compiled, request):
    encoding = _oneblob(compiled, request)
    points = torch.rand(8, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(encoding, (points,))
    outside = (torch.rand(8, 3, dtype=torch.float64) * 3 - 1).requires_grad_(True)
    assert torch.autograd.gradcheck(encoding, (outside,))


@pytest.mark.parametrize("dtype, n_bins", [(torch.float32, 16), (torch.float32, 7), (torch.float64, 16),
                                           (torch.float64, 2)])
def test_compiled_oneblob_equals_the_pytorch_path_bit_for_bit(compiled_kernel, dtype, n_bins):
    """The codes and the point gradient equal the PyTorch path's and its autograd gradient's bit
    for bit (same operations, same order, the same accumulation order as autograd's engine), so the
    switch changes no result; points inside and outside the box, exactly on bin edges, far outside
    (the floor past 2^62), and signed zeros in the incoming gradient.  Both copies of the kernel's
    loops: the portable one and, for 16 bins on a processor with AVX2, the 8-wide one."""
    generator = torch.Generator().manual_seed(11)
    edges = torch.arange(-2 * n_bins, 4 * n_bins + 1, dtype=torch.float64).div(2 * n_bins)
    far = torch.tensor([[1e9, -1e9, 3e20], [-0.0, 0.0, -1e-30], [-2.0**62, 2.0**63, -5e18], [3e18, -3e18, -8388607.5]],
                       dtype=torch.float64)
    points = torch.cat([torch.rand(20000, 3, generator=generator, dtype=torch.float64) * 1.4 - 0.2,
                        edges.repeat(3, 1).T, far]).to(dtype)
    upstream = torch.randn(points.shape[0], 3 * n_bins, generator=generator, dtype=torch.float64).to(dtype)
    upstream[::5, 0] = -0.0  # the padded ends g_{-1} = 0 and -g_n = 0 meet signed zeros
    upstream[::7, -1] = -0.0
    encodings = {"pytorch": OneBlobEncoding(n_bins, compiled=False),
                 "portable": lambda x: hash_kernel.oneblob_encode(x, n_bins, allow_avx2=False),
                 "default": OneBlobEncoding(n_bins, compiled=True)}
    results = {}
    for name, encoding in encodings.items():
        x = points.clone().requires_grad_(True)
        codes = encoding(x)
        (codes * upstream).sum().backward()
        results[name] = (codes.detach(), x.grad)
    codes_torch, grad_torch = results["pytorch"]
    for name in ("portable", "default"):  # equal values (a zero gradient's sign may differ with 2 bins)
        codes_compiled, grad_compiled = results[name]
        assert torch.equal(codes_compiled, codes_torch), name
        assert torch.equal(grad_compiled, grad_torch), name
    assert grad_torch.abs().max() > 0  # the comparison is not between two zero tensors


# ---------------------------------------------------------------- hash-grid geometry


@pytest.mark.parametrize(
    "extent, voxel, log2_size, res_max, scale, params_millions",
    [
        (6.5, 0.02, 16, 325, 1.2223, 1.641),  # TUM fr1_desk / Replica office0
        (8.0, 0.02, 16, 400, 1.2394, 1.667),  # Replica room0
        (9.0, 0.04, 16, 225, 1.1927, 1.594),  # ScanNet scene0000
        (9.3, 0.04, 12, 232, 1.1952, 0.131),  # ScanNet scene0059
        (12.0, 0.02, 16, 600, 1.2733, 1.713),  # TUM fr3_office
    ],
)
def test_level_geometry_matches_spec_table(extent, voxel, log2_size, res_max, scale, params_millions):
    bound = torch.tensor([[0.0, extent], [0.0, 1.0], [0.0, 2.0]])
    assert finest_resolution(bound, voxel) == res_max
    grid = HashGridEncoding(res_max, log2_hashmap_size=log2_size)
    assert grid.per_level_scale == pytest.approx(scale, abs=1e-4)
    assert grid.n_params / 1e6 == pytest.approx(params_millions, abs=0.0015)


def test_levels_dense_then_hashed_with_tcnn_sizes():
    grid = HashGridEncoding(325, log2_hashmap_size=16)
    # level 0: scale 15, 16 vertices per axis, 4096 entries dense.
    assert grid.level_scales[0] == pytest.approx(15.0)
    assert grid.level_resolutions[0] == 16 and grid.level_sizes[0] == 4096 and grid.level_dense[0]
    for level, (resolution, size, dense) in enumerate(
        zip(grid.level_resolutions, grid.level_sizes, grid.level_dense)
    ):
        expected_scale = 16 * grid.per_level_scale**level - 1
        assert grid.level_scales[level] == pytest.approx(expected_scale)
        assert resolution == math.ceil(expected_scale) + 1
        assert size == min(-(-resolution**3 // 8) * 8, 2**16)
        assert dense == (resolution**3 <= size)
    assert grid.level_dense == sorted(grid.level_dense, reverse=True)
    assert grid.level_scales[-1] == pytest.approx(324.0)


def test_trilinear_interpolation_reproduces_a_linear_function():
    """Set every table row to a linear function of its vertex; the encoding returns it exactly."""
    grid = HashGridEncoding(40, n_levels=3, base_resolution=16, log2_hashmap_size=20).double()
    coefficients = torch.tensor([[0.3, -1.1], [0.7, 0.2], [-0.4, 0.9]], dtype=torch.float64)
    with torch.no_grad():
        for level in range(grid.n_levels):
            resolution = grid.level_resolutions[level]
            assert grid.level_dense[level]
            axis = torch.arange(resolution)
            vertex = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
            rows = grid.level_index(level, vertex)
            # vertex v sits at x_n = (v - 0.5) / scale
            grid.table[rows] = ((vertex.double() - 0.5) / grid.level_scales[level]) @ coefficients
    points = torch.rand(300, 3, dtype=torch.float64) * 0.9 + 0.05
    for path in ("compiled", "torch", "reference"):
        if path == "compiled" and not hash_kernel.available():
            continue  # covered by the compiled-kernel tests, which say why they skip
        _use_path(grid, path)
        features = grid(points).view(300, 3, 2)
        for level in range(3):
            assert torch.allclose(features[:, level], points @ coefficients, atol=1e-10)


def _use_path(grid: HashGridEncoding, path: str) -> None:
    """Point ``grid`` at one of its three encoding paths."""
    grid.fast_gather = path != "reference"
    grid.compiled = path == "compiled"


@pytest.mark.parametrize("path, n_features", [("compiled", 2), ("torch", 2), ("compiled", 1), ("compiled", 4)])
def test_fast_paths_agree_with_the_reference_in_values_and_gradients(path, n_features, request):
    """Values, table and point gradients of each fast path against the reference; the kernel also
    with F = 1 and 4 features per level (its general feature loop; F = 2 has its own unrolled one)."""
    if path == "compiled":
        request.getfixturevalue("compiled_kernel")
    torch.manual_seed(3)
    grid = HashGridEncoding(120, n_features=n_features, log2_hashmap_size=12)
    with torch.no_grad():
        grid.table.normal_()
    points = torch.rand(2000, 3) * 1.4 - 0.2  # includes points outside the box
    upstream = torch.randn(2000, grid.out_dim)
    results = []
    for which in (path, "reference"):
        _use_path(grid, which)
        assert grid.uses_compiled_kernel(points) == (which == "compiled")
        grid.table.grad = None
        x = points.clone().requires_grad_(True)
        out = grid(x)
        (out * upstream).sum().backward()
        results.append((out.detach(), grid.table.grad.clone(), x.grad.clone()))
    (v_fast, g_fast, x_fast), (v_ref, g_ref, x_ref) = results
    assert torch.allclose(v_fast, v_ref, atol=1e-5)
    assert torch.allclose(g_fast, g_ref, atol=1e-4)
    assert torch.allclose(x_fast, x_ref, atol=1e-3, rtol=1e-4)


def test_compiled_kernel_floors_cell_positions_as_torch_floor_does(compiled_kernel):
    """The kernel's integer floor against the reference path's torch.floor: points whose position on
    a level lands exactly on a vertex (where a floor one too low moves the point gradient to the
    other cell's one-sided derivative) and points far outside the box (negative positions, a dense
    index past its table), on a dense and a hashed level."""
    torch.manual_seed(5)
    grid = HashGridEncoding(60, n_levels=2, base_resolution=8, log2_hashmap_size=9)
    assert grid.level_dense == [True, False]
    with torch.no_grad():
        grid.table.normal_()
    candidates = []
    for scale in grid.level_scales:
        vertex = torch.randint(-200, 200, (4000, 3)).float()
        points = (vertex - 0.5) / scale
        on_vertex = ((points * scale + 0.5) == vertex).all(dim=1)  # exact in float32
        candidates.append(points[on_vertex][:500])
    points = torch.cat(candidates + [torch.rand(500, 3) * 40.0 - 30.0])
    assert points.shape[0] > 1000 and bool((points < 0).any())
    upstream = torch.randn(points.shape[0], grid.out_dim)
    results = []
    for which in ("compiled", "reference"):
        _use_path(grid, which)
        x = points.clone().requires_grad_(True)
        out = grid(x)
        (out * upstream).sum().backward()
        results.append((out.detach(), x.grad))
    (v_kernel, x_kernel), (v_ref, x_ref) = results
    assert torch.allclose(v_kernel, v_ref, atol=1e-5)
    assert torch.allclose(x_kernel, x_ref, atol=1e-3, rtol=1e-4)


def test_compiled_kernel_gradcheck_and_skipped_gradients(compiled_kernel):
    """The kernel's hand-written backward vs finite differences (float64), table and points, on a
    grid with a dense and a hashed level; each gradient alone when the other input is constant
    (the point gradient with the table frozen, as tracking freezes the map)."""
    grid = HashGridEncoding(6, n_levels=2, base_resolution=4, log2_hashmap_size=7).double()
    assert grid.level_dense == [True, False]
    points = torch.rand(5, 3, dtype=torch.float64) * 1.2 - 0.1
    table = grid.table.detach().clone().normal_().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda t: torch.func.functional_call(grid, {"table": t}, (points,)), (table,)
    )
    x = points.clone().requires_grad_(True)
    grid.requires_grad_(False)
    assert torch.autograd.gradcheck(grid._encode_compiled, (x,))
    grid.requires_grad_(True)
    both = points.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p, t: torch.func.functional_call(grid, {"table": t}, (p,)), (both, table)
    )


def test_compiled_kernel_one_pass_gradients_equal_the_two_single_gradients_bit_for_bit(compiled_kernel):
    """With the table and the points both needing a gradient (BA) one kernel pass computes both;
    it must give exactly the numbers of the point-gradient and table-gradient ops run apart (the
    same sums in the same order), here on a dense and a hashed level with points outside the box."""
    torch.manual_seed(7)
    grid = HashGridEncoding(60, n_levels=4, base_resolution=4, log2_hashmap_size=9)
    assert grid.level_dense == [True, False, False, False]
    with torch.no_grad():
        grid.table.normal_()
    points = torch.rand(5000, 3) * 1.2 - 0.1
    upstream = torch.randn(5000, grid.out_dim)
    grid.table.grad = None
    x = points.clone().requires_grad_(True)
    (grid._encode_compiled(x) * upstream).sum().backward()
    levels = (grid.scales, grid.resolutions, grid.sizes, grid.offsets, grid.n_dense_levels)
    grad_features = upstream.view(5000, grid.n_levels, -1)  # (N, L, F)
    table = grid.table.detach()
    apart_points = torch.ops.tsslam_hash_grid.backward_points(grad_features, points, table, *levels)
    apart_table = torch.ops.tsslam_hash_grid.backward_table(grad_features, points, table, *levels)
    assert torch.equal(x.grad, apart_points)
    assert torch.equal(grid.table.grad, apart_table)


def test_compiled_kernel_is_deterministic_across_thread_counts(compiled_kernel):
    """Each level's table gradient is summed by one thread in point order, each point's gradient by
    one thread: bit-identical results with 1 and 2 threads (the seed alone fixes a run), although
    the points are split into blocks of other sizes."""
    torch.manual_seed(5)
    grid = HashGridEncoding(200, log2_hashmap_size=10)  # small table: many points share rows
    points = torch.rand(30000, 3)
    upstream = torch.randn(30000, grid.out_dim)
    threads = torch.get_num_threads()
    results = []
    try:
        for n_threads in (1, 2):
            torch.set_num_threads(n_threads)
            grid.table.grad = None
            x = points.clone().requires_grad_(True)
            features = grid._encode_compiled(x)
            (features * upstream).sum().backward()
            results.append((grid.table.grad.clone(), x.grad.clone(), features.detach()))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(results[0][0], results[1][0])
    assert torch.equal(results[0][1], results[1][1])
    assert torch.equal(results[0][2], results[1][2])  # the point blocks differ (15 vs 16): same bits


def test_trilinear_lookup_gradcheck_float64():
    """The hand-written backward of the fused lookup vs finite differences, table and fractions."""
    generator = torch.Generator().manual_seed(0)
    table = torch.randn(7, 2, dtype=torch.float64, generator=generator, requires_grad=True)
    index = torch.randint(0, 7, (8, 2, 5), generator=generator)  # repeated rows on purpose
    fraction = torch.rand(2, 5, 3, dtype=torch.float64, generator=generator, requires_grad=True)
    assert torch.autograd.gradcheck(trilinear_lookup, (table, index, fraction))
    # each input alone (the other a constant): the backward skips the unused branch
    assert torch.autograd.gradcheck(lambda t: trilinear_lookup(t, index, fraction.detach()), (table,))
    assert torch.autograd.gradcheck(lambda f: trilinear_lookup(table.detach(), index, f), (fraction,))


def test_fast_encoding_gradcheck_on_tiny_grid():
    """Gradients of the fast path w.r.t. the table and the points vs finite differences (float64)."""
    grid = HashGridEncoding(6, n_levels=2, base_resolution=4, log2_hashmap_size=7, compiled=False).double()
    assert grid.level_dense == [True, False]
    points = torch.rand(5, 3, dtype=torch.float64) * 0.8 + 0.1
    table = grid.table.detach().clone().normal_().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda t: torch.func.functional_call(grid, {"table": t}, (points,)), (table,)
    )
    x = points.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(grid._encode_fast, (x,))


def _level0_feature_on_every_path(grid: HashGridEncoding, point, column: int = 0) -> dict:
    """Level 0, feature 0 (or the output ``column``) of one point on each encoding path, with table
    row r holding the value r."""
    with torch.no_grad():
        grid.table[:] = torch.arange(grid.table.shape[0], dtype=grid.table.dtype).unsqueeze(1)
    values = {}
    for path in ("compiled", "torch", "reference"):
        if path == "compiled" and not hash_kernel.available():
            continue  # covered by the compiled-kernel tests, which say why they skip
        _use_path(grid, path)
        values[path] = float(grid(torch.tensor([point], dtype=torch.float64))[0, column].detach())
    return values


def test_hashed_index_is_tcnns_spatial_hash_worked_by_hand():
    """A hashed level (R = 8, 512 vertices, 64 rows): tcnn's hash (i * 1) xor (j * 2654435761) xor
    (k * 805459861) mod 64 for the vertex (3, 5, 2) is 28 (the primes written here, not read from
    field.py), so the level's row is its offset 64 + 28.  A point exactly on that vertex takes the
    row's value alone (weight 1); output column 2 is level 1's first feature.  With the y and z
    primes swapped the row would be 64 + 8."""
    grid = HashGridEncoding(8, n_levels=2, base_resolution=4, log2_hashmap_size=6).double()
    assert grid.level_dense == [True, False] and grid.level_sizes[1] == 64 and grid.level_scales[1] == 7.0
    local = (3 * 1 ^ 5 * 2654435761 ^ 2 * 805459861) % 64
    assert local == 28
    point = tuple((vertex - 0.5) / 7.0 for vertex in (3, 5, 2))  # position = point * scale + 0.5
    for path, value in _level0_feature_on_every_path(grid, point, column=2).items():
        assert value == pytest.approx(64 + local, abs=1e-6), path


def test_dense_index_one_past_the_level_wraps_to_its_first_row():
    """A dense level with R^3 = size (R = 4, 64 rows): the point (-1/3, -1/3, 1) sits at position
    (-0.5, -0.5, 3.5), the middle of the cell with corners i, j in {-1, 0}, k in {3, 4}, so each
    corner weighs 1/8.  Hand-worked rows i + 4j + 16k mod 64: 43, 44, 47, 48, 59, 60, 63 and
    64 mod 64 = 0 (not row 64, the hashed level's first row); mean 364 / 8 = 45.5.  The point is
    the batch's only one, so the fast path takes its no-wrap branch, whose test must send an
    index equal to the level's size to the wrap."""
    grid = HashGridEncoding(8, n_levels=2, base_resolution=4, log2_hashmap_size=6).double()
    assert grid.level_resolutions[0] == 4 and grid.level_sizes[0] == 64 and grid.level_dense == [True, False]
    for path, value in _level0_feature_on_every_path(grid, (-1 / 3, -1 / 3, 1.0)).items():
        assert value == pytest.approx(45.5, abs=1e-9), path


def test_dense_index_outside_the_box_wraps_as_tcnn_uint32():
    """tcnn computes a dense index in uint32: a negative i + R j + R^2 k becomes 2^32 + n before
    mod size.  R = 6, size 216 (which does not divide 2^32, so this differs from n mod 216):
    the point (-0.2, -0.2, -0.2) sits at position -0.5 on every axis, corners i, j, k in
    {-1, 0}, each weighing 1/8; rows (n mod 2^32) mod 216 for n in {0, -1, -6, -7, -36, -37,
    -42, -43} are 0, 183, 178, 177, 148, 147, 142, 141 (2^32 mod 216 = 184); mean 1116 / 8."""
    grid = HashGridEncoding(12, n_levels=2, base_resolution=6, log2_hashmap_size=8).double()
    assert grid.level_resolutions[0] == 6 and grid.level_sizes[0] == 216 and grid.level_dense == [True, False]
    rows = [(i + 6 * j + 36 * k) % 2**32 % 216 for i in (-1, 0) for j in (-1, 0) for k in (-1, 0)]
    assert sorted(rows) == [0, 141, 142, 147, 148, 177, 178, 183]
    for path, value in _level0_feature_on_every_path(grid, (-0.2, -0.2, -0.2)).items():
        assert value == pytest.approx(1116 / 8, abs=1e-9), path


# ---------------------------------------------------------------- the field


def test_scene_field_shapes_ranges_and_normalisation():
    cfg = config.tiny()
    bound = [[-1.0, 2.0], [0.0, 1.0], [-0.5, 0.5]]
    field = SceneField(cfg.field, bound, generator=torch.Generator().manual_seed(0))
    assert field.bound.dtype == torch.float32 and field.bound.shape == (3, 2)
    corners = torch.tensor([[-1.0, 0.0, -0.5], [2.0, 1.0, 0.5], [0.5, 0.5, 0.0]])
    assert torch.allclose(field.normalize(corners), torch.tensor([[0.0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5]]))
    rgb, sdf = field(torch.rand(50, 3))
    assert rgb.shape == (50, 3) and sdf.shape == (50,)
    assert bool((rgb > 0).all() and (rgb < 1).all())
    assert torch.allclose(field.sdf(corners), field(corners)[1])
    assert field.grid_features(corners).shape == (3, cfg.field.n_levels * cfg.field.n_features_per_level)
    mlp_params = sum(p.numel() for p in field.decoder_parameters())
    assert mlp_params == 5184  # spec 1.4: 3,072 + 2,112, bias-free


def test_field_gradients_do_not_depend_on_the_compiled_oneblob(compiled_kernel):
    """A whole field's outputs and every gradient (table, MLP weights, points) equal bit for bit
    with ``compiled_oneblob`` on and off, points inside and outside the box: the switch cannot
    change a run."""
    cfg = config.tiny()
    bound = [[-1.0, 2.0], [0.0, 1.0], [-0.5, 0.5]]
    points = torch.rand(3000, 3, generator=torch.Generator().manual_seed(3)) * 4.0 - 1.5
    results = []
    for compiled in (False, True):
        field_cfg = dataclasses.replace(cfg.field, compiled_oneblob=compiled)
        field = SceneField(field_cfg, bound, generator=torch.Generator().manual_seed(0))
        assert field.oneblob.uses_compiled_kernel(points) == compiled
        x = points.clone().requires_grad_(True)
        rgb, sdf = field(x)
        (rgb.square().sum() + sdf.sin().sum()).backward()
        results.append([rgb, sdf, x.grad] + [p.grad for p in field.parameters()])
    for torch_path, compiled_path in zip(*results):
        assert torch.equal(torch_path, compiled_path)
    assert results[0][2].abs().max() > 0


def _plain_field_forward(field, points):
    """The field as ``nn.Linear`` on the joined inputs, autograd's own gradients (the oracle)."""
    points_unit = field.normalize(points)
    oneblob, grid_features = field.oneblob(points_unit), field.grid(points_unit)
    geometry = field.geometry_mlp(torch.cat([grid_features, oneblob], dim=-1))
    rgb = torch.sigmoid(field.color_mlp(torch.cat([oneblob, geometry[:, 1:]], dim=-1)))
    return rgb, geometry[:, 0]


@pytest.mark.parametrize("n_points", [22016, 37])
@pytest.mark.parametrize("optimised", ["map", "points", "both"])
def test_first_layers_skip_only_unneeded_gradients(n_points, optimised):
    """The MLPs' first layers compute the input gradient only for the parts that need one; outputs
    and every gradient (table, weights, points) equal autograd's on ``nn.Linear`` of the joined
    inputs, for the map alone (mapping), the points alone (tracking) and both (BA).  Bit for bit
    under MKL (each output column of a product is its own sum there); to rounding otherwise."""
    cfg = config.load("tum-cpu")
    bound = [[-3.5, 3.0], [-3.0, 3.0], [-3.0, 3.0]]
    results = []
    for forward in (_plain_field_forward, lambda field, x: field(x)):
        field = SceneField(cfg.field, bound, generator=torch.Generator().manual_seed(0))
        if optimised == "points":
            field.requires_grad_(False)
        points = torch.rand(n_points, 3, generator=torch.Generator().manual_seed(1)) * 6.0 - 3.0
        points.requires_grad_(optimised != "map")
        rgb, sdf = forward(field, points)
        (rgb.square().mean() + (0.3 * sdf).sin().mean()).backward()
        gradients = [points.grad] + [parameter.grad for parameter in field.parameters()]
        assert [g is None for g in gradients] == [optimised == "map"] + [optimised == "points"] * 5  # table, 4 weights
        results.append([rgb, sdf] + [g for g in gradients if g is not None])
    for oracle, ours in zip(*results):
        assert oracle.abs().max() > 0
        if torch.backends.mkl.is_available():
            assert torch.equal(oracle, ours)
        else:
            assert torch.allclose(oracle, ours, rtol=1e-5, atol=1e-12)


def test_integer_bound_is_stored_as_float_and_bad_bound_rejected():
    cfg = config.tiny()
    field = SceneField(cfg.field, [[0, 2], [0, 2], [0, 2]])
    assert field.bound.dtype == torch.float32
    with pytest.raises(ValueError, match="bound"):
        SceneField(cfg.field, [[1.0, 0.0], [0, 1], [0, 1]])


def test_same_generator_seed_gives_same_field():
    cfg = config.tiny()
    bound = [[0.0, 1.0]] * 3
    a = SceneField(cfg.field, bound, generator=torch.Generator().manual_seed(5))
    b = SceneField(cfg.field, bound, generator=torch.Generator().manual_seed(5))
    c = SceneField(cfg.field, bound, generator=torch.Generator().manual_seed(6))
    points = torch.rand(10, 3)
    assert torch.equal(a(points)[1], b(points)[1])
    assert not torch.equal(a(points)[1], c(points)[1])


def test_parameter_groups_follow_coslam_adam_settings():
    cfg = config.synthetic()
    field = SceneField(cfg.field, [[0.0, 2.0]] * 3)
    decoder, grid = field.parameter_groups(cfg.mapping)
    assert decoder["lr"] == 0.01 and decoder["weight_decay"] == 1e-6
    assert grid["lr"] == 0.001 and grid["eps"] == 1e-15
    assert grid["params"][0] is field.grid.table


def test_kernel_build_failure_falls_back_to_the_pytorch_path_with_one_warning(monkeypatch):
    """A machine without a working compiler: one RuntimeWarning that says why, then the PyTorch
    fast path gives the field's values (the reference path is the oracle)."""
    from torch.utils import cpp_extension

    def broken_build(*args, **kwargs):
        raise OSError("no C++ compiler found (simulated)")

    monkeypatch.setattr(cpp_extension, "load", broken_build)
    monkeypatch.setattr(hash_kernel, "_STATE", {"loaded": None, "error": None})
    monkeypatch.delenv("TSSLAM_NO_COMPILED_KERNEL", raising=False)
    with pytest.warns(RuntimeWarning, match="simulated"):
        assert not hash_kernel.available()
    assert "simulated" in hash_kernel.load_error()
    grid = HashGridEncoding(60, log2_hashmap_size=10)
    points = torch.rand(500, 3)
    assert not grid.uses_compiled_kernel(points)
    fallback = grid(points)
    _use_path(grid, "reference")
    assert torch.allclose(fallback, grid(points), atol=1e-6)


TORCH_BUILD_FAILURE = (  # the shape of torch's message: the whole command line first, the cause at the end
    "Error building extension 'tsslam_hash_grid_0123': [1/3] c++ -MMD -MF hash_grid.o.d -DTORCH_EXTENSION_NAME="
    + "-I/some/include/path " * 40 + "-c /site/tsslam_ref/csrc/hash_grid.cpp -o hash_grid.o\n"
    "FAILED: hash_grid.o\n/bin/sh: 1: c++: not found\nninja: build stopped: subcommand failed.\n")


def test_a_failed_build_is_reported_by_its_cause_not_by_the_command_line(monkeypatch):
    from torch.utils import cpp_extension

    def failing_build(*args, **kwargs):
        raise RuntimeError(TORCH_BUILD_FAILURE)

    monkeypatch.setattr(cpp_extension, "load", failing_build)
    monkeypatch.setattr(hash_kernel, "_STATE", {"loaded": None, "error": None})
    monkeypatch.delenv("TSSLAM_NO_COMPILED_KERNEL", raising=False)
    monkeypatch.delenv("CXX", raising=False)
    with pytest.warns(RuntimeWarning, match="c\\+\\+: not found") as caught:
        assert not hash_kernel.available()
    assert len(str(caught[0].message)) < 800 and "-I/some/include/path" not in str(caught[0].message)
    assert hash_kernel.load_error() == "RuntimeError: " + TORCH_BUILD_FAILURE  # the whole text stays recorded
    assert hash_kernel.failure_summary("line one\nline two") == "line one | line two"  # nothing telling: the end


def test_a_missing_compiler_is_named_before_torch_tries_to_build(monkeypatch):
    from torch.utils import cpp_extension

    calls = []
    monkeypatch.setattr(cpp_extension, "load", lambda *args, **kwargs: calls.append(1))
    monkeypatch.setattr(hash_kernel, "_STATE", {"loaded": None, "error": None})
    monkeypatch.delenv("TSSLAM_NO_COMPILED_KERNEL", raising=False)
    monkeypatch.setenv("CXX", "/nonexistent/c++")
    with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler: '/nonexistent/c\\+\\+' \\(\\$CXX\\)"):
        assert not hash_kernel.available()
    assert calls == []  # torch's own banner about the compiler's version never comes



@pytest.mark.parametrize("setting", ["no standard output", "a cache it cannot write"])
def test_a_built_kernel_loads_without_stdout_and_from_a_cache_it_cannot_write(setting, tmp_path):
    """Two ways a finished build was not used and the run silently took the PyTorch path (slower,
    other last bits): ``>&-`` (torch flushes sys.stdout, None then, while it loads) and a cache the
    user may read but not write (torch wants its lock file; simulated, as root may write anywhere).
    In a child process: loading the real library twice in one process aborts it."""
    import subprocess
    import sys

    assert hash_kernel.available(), hash_kernel.load_error()  # the build the child finds in the cache
    script = {"no standard output": "import sys; sys.stdout = None\n",
              "a cache it cannot write": "from torch.utils import cpp_extension\n"
                                         "def locked(*args, **kwargs):\n"
                                         "    raise PermissionError(13, 'Permission denied', 'lock')\n"
                                         "cpp_extension.load = locked\n"}[setting]
    script += ("import sys\nfrom tsslam_ref import hash_kernel\n"
               "print(hash_kernel.available(), hash_kernel.load_error(), file=sys.stderr)\n")
    result = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                            env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])))
    assert result.stderr.strip().splitlines()[-1] == "True None", result.stderr


def test_environment_switch_turns_the_kernel_off(monkeypatch):
    monkeypatch.setattr(hash_kernel, "_STATE", {"loaded": None, "error": None})
    monkeypatch.setenv("TSSLAM_NO_COMPILED_KERNEL", "1")
    assert not hash_kernel.available()
    assert "TSSLAM_NO_COMPILED_KERNEL" in hash_kernel.load_error()


def test_environment_switch_set_to_zero_keeps_the_kernel(monkeypatch):
    """Only a value other than "" and "0" turns the kernel off: TSSLAM_NO_COMPILED_KERNEL=0 reads
    as "no" (a shell flag), so the loader goes on to build or load the kernel (a stand-in here,
    which records the call: loading the real library twice in one process aborts it)."""
    builds = []
    monkeypatch.setattr(hash_kernel, "_build", lambda: builds.append(1) or True)
    monkeypatch.setattr(hash_kernel, "_STATE", {"loaded": None, "error": None})
    monkeypatch.setenv("TSSLAM_NO_COMPILED_KERNEL", "0")
    assert hash_kernel.available() and builds == [1]
    assert hash_kernel.load_error() is None


def test_stale_kernel_build_lock_is_named(tmp_path):
    """A build lock left by a killed build makes torch wait forever; the kernel loader names it
    (with its path) once it is older than a plausible build, and stays quiet otherwise."""
    import os
    from tsslam_ref import hash_kernel

    assert hash_kernel.stale_lock_message(tmp_path) is None  # no lock
    lock = tmp_path / "lock"
    lock.write_text("")
    now = lock.stat().st_mtime
    assert hash_kernel.stale_lock_message(tmp_path, now=now + 60) is None  # a build in progress
    message = hash_kernel.stale_lock_message(tmp_path, now=now + hash_kernel.STALE_LOCK_SECONDS + 120)
    assert message is not None and str(lock) in message and "delete" in message
    os.utime(lock, (now - 3600, now - 3600))
    assert "60 min" in hash_kernel.stale_lock_message(tmp_path, now=now)


def test_kernel_build_name_separates_checkouts_and_source_versions(tmp_path, monkeypatch):
    """Each checkout and each version of the kernel sources gets its own cached build folder, and
    the same sources at the same place always the same one (no rebuild when nothing changed)."""
    import shutil
    from tsslam_ref import hash_kernel

    name = hash_kernel.build_name()
    assert name == hash_kernel.build_name() and name.startswith("tsslam_hash_grid_")
    copy = tmp_path / "csrc"
    copy.mkdir()
    for source in (hash_kernel.SOURCE, hash_kernel.ONEBLOB_SOURCE):
        shutil.copy(source, copy / source.name)
    monkeypatch.setattr(hash_kernel, "SOURCE", copy / hash_kernel.SOURCE.name)
    monkeypatch.setattr(hash_kernel, "ONEBLOB_SOURCE", copy / hash_kernel.ONEBLOB_SOURCE.name)
    other_checkout = hash_kernel.build_name()
    assert other_checkout != name  # same bytes, another checkout: its own folder
    with open(copy / hash_kernel.ONEBLOB_SOURCE.name, "a") as source:
        source.write("\n")
    assert hash_kernel.build_name() not in (name, other_checkout)  # edited source: a new build


@pytest.mark.parametrize("compiled", [False, True], ids=["torch", "compiled"])
def test_an_empty_batch_gives_empty_outputs_on_every_path(compiled, request):
    """The PyTorch fast path (the one CUDA runs) took the min of an empty tensor."""
    if compiled:
        request.getfixturevalue("compiled_kernel")
    cfg = config.tiny().field
    cfg.compiled_kernel = compiled
    field = SceneField(cfg, torch.tensor([[0.0, 1.0]] * 3), generator=torch.Generator().manual_seed(0))
    rgb, sdf = field(torch.zeros(0, 3))
    assert rgb.shape == (0, 3) and sdf.shape == (0,)


def test_ninja_of_the_virtual_environment_is_found_without_activating_it(tmp_path):
    """environment.txt installs ninja into the venv's scripts folder, which is not on PATH when
    .venv/bin/python runs unactivated; torch looks for ninja on PATH only.  Oracle: shutil.which
    on the returned PATH, with a stand-in ninja executable."""
    import shutil

    scripts, system = tmp_path / "venv_bin", tmp_path / "usr_bin"
    scripts.mkdir()
    system.mkdir()
    assert shutil.which("ninja", path=hash_kernel.ninja_search_path(str(system), str(scripts))) is None  # none anywhere
    (scripts / "ninja").write_text("#!/bin/sh\n")
    (scripts / "ninja").chmod(0o755)
    found = shutil.which("ninja", path=hash_kernel.ninja_search_path(str(system), str(scripts)))
    assert found == str(scripts / "ninja")
    (system / "ninja").write_text("#!/bin/sh\n")
    (system / "ninja").chmod(0o755)
    assert hash_kernel.ninja_search_path(str(system), str(scripts)) == str(system)  # the system's wins, PATH unchanged


def test_points_that_are_not_an_n_by_3_tensor_are_refused_naming_what_was_expected():
    field = SceneField(config.tiny().field, [[-1.0, 1.0], [-1.0, 1.0], [0.0, 3.0]],
                       generator=torch.Generator().manual_seed(0))
    with pytest.raises(TypeError, match=r"points must be a torch tensor \(N, 3\) .*, got ndarray"):
        field(torch.zeros(5, 3).numpy())
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\), got \(3,\)"):
        field.sdf(torch.zeros(3))


def test_on_windows_the_kernel_is_not_built_and_the_reason_is_not_a_missing_gcc(monkeypatch):
    """PyTorch compiles with MSVC on Windows, which ignores the kernel's GCC/Clang flags: the advice
    was to install g++ or set CXX, after which cl built an unoptimised single-thread kernel."""
    from torch.utils import cpp_extension

    calls = []
    monkeypatch.setattr(cpp_extension, "load", lambda *args, **kwargs: calls.append(1))
    monkeypatch.setattr(hash_kernel, "_STATE", {"loaded": None, "error": None})
    monkeypatch.delenv("TSSLAM_NO_COMPILED_KERNEL", raising=False)
    import warnings

    monkeypatch.setattr(hash_kernel.os, "name", "nt")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            built, reason = hash_kernel.available(), hash_kernel.load_error()
    finally:
        monkeypatch.undo()  # os.name back before pytest (pathlib) reads it
    assert not built and calls == [] and "MSVC ignores" in reason, (built, calls, reason)
    assert [str(warning.message).count("MSVC ignores") for warning in caught] == [1]
