"""The scene field f_theta(x) -> (c, s): Co-SLAM's joint coordinate + parametric encoding.

TS-SLAM §III-A (``sec:rep_secene``), Eq. (1) (Eq. (2), ``eq:cal_ray``, is ``render.py``'s): Co-SLAM's field, a
OneBlob coordinate encoding gamma(x) and a multi-resolution hash grid V(x) feeding two tiny MLPs:

    x_n        = (x - bound_min) / (bound_max - bound_min)           per axis, in [0, 1]
    s, h       = f_tau( V(x_n), gamma(x_n) )                         geometry MLP, 80 -> 32 -> 16
    c          = sigmoid( f_phi( gamma(x_n), h ) )                   colour MLP, 63 -> 32 -> 3

``s`` is Co-SLAM's *normalised* SDF: metric SDF = s * tr.

Layer 1 (math and map): imports torch, ``config`` and ``hash_kernel`` (the optional compiled hash-grid
kernel); knows nothing about rays or cameras.
Taught in notebooks/03_scene_representation.ipynb.

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| x | ``points`` | (N, 3) | world | m |
| x_n | ``points_unit`` | (N, 3) | box | - (in [0, 1] inside the box) |
| gamma(x_n) | ``oneblob`` | (N, 48) | - | - |
| V(x_n) | ``grid_features`` | (N, n_levels * n_features) | - | - |
| s | ``sdf`` | (N,) | - | truncation units (metric = s * tr) |
| h | ``geo_feat`` | (N, 15) | - | - |
| c | ``rgb`` | (N, 3) | - | [0, 1] |

Sources: Co-SLAM @3bb904e ``model/encodings.py`` (16 levels x 2 features, base 16,
per-level scale (res_max/16)^(1/15)), ``model/decoder.py`` (bias-free MLPs), ``model/scene_rep.py``
(per-axis box normalisation); tiny-cuda-nn ``grid.h`` (level scale, +0.5 offset, dense/hashed
storage, hash primes) and ``oneblob.h`` (quartic kernel).  Deviations are listed in docs/map.md.
"""

import itertools
import math
from typing import List, Optional

import torch
from torch import nn

from . import hash_kernel
from .config import FieldConfig, MappingConfig

# tiny-cuda-nn's spatial hash primes (grid.h); the x prime is 1.
HASH_PRIMES = (1, 2654435761, 805459861)
# Hash-table entries are initialised uniform in [-HASH_INIT_RANGE, HASH_INIT_RANGE] (tcnn).
HASH_INIT_RANGE = 1e-4
# Emulates tcnn's uint32 index arithmetic on int64 tensors.
UINT32_MASK = 0xFFFFFFFF
# Corner offsets (dx, dy, dz) of a grid cell in itertools.product order (dx slowest); both
# encoding paths use this order.
CORNER_OFFSETS = tuple(itertools.product((0, 1), repeat=3))


def _check_points(points: torch.Tensor, name: str = "points") -> None:
    if not isinstance(points, torch.Tensor):
        raise TypeError(f"{name} must be a torch tensor (N, 3) on the field's device, got {type(points).__name__}")
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(points.shape)}")


# --------------------------------------------------------------------------------------------
# OneBlob


class OneBlobEncoding(nn.Module):
    """OneBlob coordinate encoding with tcnn's quartic kernel, periodic with period 1.

    For one coordinate x in [0, 1] and bin k = 0..n_bins-1 (tcnn ``oneblob.h``), with v = n_bins * u:

        F(u)     = clamp( (15/16) v (1 - (2/3) v^2 + (1/5) v^4) + 1/2, 0, 1 )   (kernel CDF)
        G(b)     = F(b - x) + F(b - x - 1) + F(b - x + 1)                         (wrap-around)
        out_k    = G((k + 1) / n_bins) - G(k / n_bins)

    Coordinates are first wrapped to [0, 1) (x - floor(x)), so the code has period 1 for every x,
    also outside the box.  The outputs of one coordinate sum to 1.  No parameters.
    Output layout is dim-major: (x bins, y bins, z bins).

    Evaluated with one CDF instead of three: with d = b - x in (-1, 1], r = round(d) and
    e = d - r in [-1/2, 1/2], the kernel's support (|u| <= 1/n_bins <= 1/2) gives
    G(b) = F(e) + r + 1, and the constant cancels in out_k.
    """

    def __init__(self, n_bins: int = 16, compiled: bool = False):
        super().__init__()
        if n_bins < 2:
            raise ValueError(f"OneBlobEncoding needs n_bins >= 2, got {n_bins}")
        self.n_bins = n_bins
        self.compiled = compiled  # CPU: the compiled kernel (csrc/oneblob.cpp) when it builds

    @property
    def out_dim(self) -> int:
        return 3 * self.n_bins

    def kernel_cdf(self, u: torch.Tensor) -> torch.Tensor:
        """F(u): CDF of the quartic kernel (15/16)(1 - v^2)^2 on |v| <= 1, v = n_bins * u."""
        v = (u * self.n_bins).clamp(-1.0, 1.0)
        v2 = v * v
        return 0.9375 * v * (1.0 - v2 * (2.0 / 3.0) + v2 * v2 * 0.2) + 0.5

    def forward(self, points_unit: torch.Tensor) -> torch.Tensor:
        """(N, 3) coordinates in box units -> (N, 3 * n_bins) codes."""
        _check_points(points_unit, "points_unit")
        if self.uses_compiled_kernel(points_unit):
            return hash_kernel.oneblob_encode(points_unit, self.n_bins)
        edges = torch.arange(self.n_bins + 1, device=points_unit.device, dtype=points_unit.dtype)
        edges = edges / self.n_bins  # (n_bins + 1,)
        wrapped = points_unit - torch.floor(points_unit).detach()  # in [0, 1): exact period 1
        offset = edges - wrapped.unsqueeze(-1)  # (N, 3, n_bins + 1), d = b - x in (-1, 1]
        nearest_period = torch.round(offset).detach()  # r
        cdf = self.kernel_cdf(offset - nearest_period) + nearest_period  # G(b) - 1
        codes = cdf[..., 1:] - cdf[..., :-1]  # (N, 3, n_bins)
        return codes.reshape(points_unit.shape[0], self.out_dim)

    def uses_compiled_kernel(self, points_unit: torch.Tensor) -> bool:
        """Whether :meth:`forward` takes the compiled kernel for these points (asked for, CPU, built)."""
        return self.compiled and points_unit.device.type == "cpu" and hash_kernel.available()


# --------------------------------------------------------------------------------------------
# Hash grid


def corner_weights(fraction: torch.Tensor) -> torch.Tensor:
    """Trilinear weights of the 8 cell corners, (..., 3) fractions -> (8, ...), corner order
    ``CORNER_OFFSETS``: w_c = prod_axis (f if offset = 1 else 1 - f)."""
    fx, fy, fz = fraction.unbind(-1)
    wx, wy, wz = (1.0 - fx, fx), (1.0 - fy, fy), (1.0 - fz, fz)
    return torch.stack([wx[dx] * wy[dy] * wz[dz] for dx, dy, dz in CORNER_OFFSETS])


class _TrilinearLookup(torch.autograd.Function):
    """features = sum_c w_c(fraction) * table[index_c], with a hand-written backward.

    Shapes: table (T, F), index (8, L, N) long (global rows, corner-major), fraction (L, N, 3)
    -> features (L, N, F).

    Why a custom Function: the hash grid is memory-bound, every pass
    over the (8, L, N, F) corner rows costs ~20 ms at 1024 rays on two cores, and autograd's own
    graph of this sum makes ~10 such passes plus the slow default backward of indexing.  Here:

        d table      = scatter_add over index of  w_c * g                  (one flat pass)
        d fraction_x = sum_c (d w_c / d f_x) <table[index_c], g>,  d w_c / d f_x = +-w_c^(y) w_c^(z)

    and the same for y, z.  The table gradient is skipped when the map is frozen (tracking), the
    fraction gradient when the points are constants (mapping with fixed poses).  Tested against the
    plain reference path and finite differences (tests/test_field.py).  Once differentiable.
    """

    @staticmethod
    def forward(table: torch.Tensor, index: torch.Tensor, fraction: torch.Tensor) -> torch.Tensor:
        rows = table.index_select(0, index.view(-1)).view(*index.shape, table.shape[1])  # (8, L, N, F)
        rows = rows.to(fraction.dtype)
        weights = corner_weights(fraction).unsqueeze(-1)  # (8, L, N, 1)
        features = weights[0] * rows[0]
        for c in range(1, 8):
            features.addcmul_(weights[c], rows[c])
        return features, rows

    @staticmethod
    def setup_context(ctx, inputs, output):
        table, index, fraction = inputs
        _, rows = output
        ctx.mark_non_differentiable(rows)
        ctx.set_materialize_grads(False)  # no zero-filled (8, L, N, F) gradient for ``rows``
        ctx.table_shape, ctx.table_dtype = table.shape, table.dtype
        ctx.save_for_backward(index, fraction, rows)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_features: torch.Tensor, _grad_rows):
        index, fraction, rows = ctx.saved_tensors
        grad_table = grad_fraction = None
        if grad_features is None:  # the features were not used
            return grad_table, None, grad_fraction
        weights = corner_weights(fraction)  # (8, L, N)
        if ctx.needs_input_grad[0]:
            # one 1-D scatter per feature column: faster on CPU than a (M, F) scatter whose
            # inner dimension is only F = 2 wide
            flat_index = index.view(-1)
            grad_table = grad_features.new_zeros(ctx.table_shape, dtype=ctx.table_dtype)
            for feature in range(ctx.table_shape[1]):
                grad_rows = (weights * grad_features[..., feature]).to(ctx.table_dtype)  # (8, L, N)
                grad_table[:, feature].scatter_add_(0, flat_index, grad_rows.view(-1))
        if ctx.needs_input_grad[2]:
            grad_weights = sum(rows[..., f] * grad_features[..., f] for f in range(rows.shape[-1]))
            grad_weights = grad_weights.view(2, 2, 2, *fraction.shape[:-1])
            fx, fy, fz = fraction.unbind(-1)
            wx, wy, wz = torch.stack((1.0 - fx, fx)), torch.stack((1.0 - fy, fy)), torch.stack((1.0 - fz, fz))
            # grad_weights[dx, dy, dz]: d loss / d w_c; difference along one axis, weighted by the others
            grad_x = ((grad_weights[1] - grad_weights[0]) * wy[:, None] * wz[None, :]).sum((0, 1))
            grad_y = ((grad_weights[:, 1] - grad_weights[:, 0]) * wx[:, None] * wz[None, :]).sum((0, 1))
            grad_z = ((grad_weights[:, :, 1] - grad_weights[:, :, 0]) * wx[:, None] * wy[None, :]).sum((0, 1))
            grad_fraction = torch.stack((grad_x, grad_y, grad_z), dim=-1)
        return grad_table, None, grad_fraction


def trilinear_lookup(table: torch.Tensor, index: torch.Tensor, fraction: torch.Tensor) -> torch.Tensor:
    """(T, F) table, (8, L, N) corner rows, (L, N, 3) fractions -> (L, N, F) interpolated features."""
    return _TrilinearLookup.apply(table, index, fraction)[0]


class HashGridEncoding(nn.Module):
    """Multi-resolution hash grid with tiny-cuda-nn's level geometry (tcnn ``grid.h``).

    Level l = 0..n_levels-1, with b = (res_max / base)^(1 / (n_levels - 1)):

        scale_l = b^l * base - 1,      R_l = ceil(scale_l) + 1 vertices per axis
        p       = x_n * scale_l + 0.5, corner = floor(p), fraction = p - floor(p)
        size_l  = min(next_multiple_of_8(R_l^3), 2^log2_hashmap_size)
        index   = i + j R_l + k R_l^2 (mod size_l)                    if R_l^3 <= size_l (dense)
                  (i * 1 xor j * 2654435761 xor k * 805459861) mod 2^T  otherwise (hashed)

    and trilinear interpolation of the 8 corners.  All levels live in one ``table`` parameter
    (sum_l size_l, n_features) with ``level_offsets``.

    Three paths give the same numbers to rounding: the compiled CPU kernel
    (``hash_kernel.py``, ``csrc/hash_grid.cpp``: hash, gather and interpolation in one pass per
    point), the PyTorch fast one (all levels at once, corner-major, custom trilinear lookup with a
    hand-written backward, ``_TrilinearLookup``) and a plain reference one (a loop over levels and
    corners with ordinary indexing).  ``fast_gather`` picks between the fast ones and the
    reference; ``compiled`` lets the fast path use the kernel for CPU tensors when it builds.
    """

    def __init__(
        self,
        res_max: int,
        n_levels: int = 16,
        n_features: int = 2,
        base_resolution: int = 16,
        log2_hashmap_size: int = 16,
        fast_gather: bool = True,
        generator: Optional[torch.Generator] = None,
        compiled: bool = True,
    ):
        super().__init__()
        if res_max < 1:
            raise ValueError(f"res_max must be >= 1, got {res_max} (field.voxel_sdf, metres, above the box's side?)")
        if n_levels < 2:
            raise ValueError(f"HashGridEncoding needs n_levels >= 2, got {n_levels}")
        self.res_max = int(res_max)
        self.n_levels = n_levels
        self.n_features = n_features
        self.base_resolution = base_resolution
        self.log2_hashmap_size = log2_hashmap_size
        self.fast_gather = fast_gather
        self.compiled = compiled
        if compiled and fast_gather:
            hash_kernel.available()  # build or load it now, not inside the first timed iteration
        self.per_level_scale = 2.0 ** (math.log2(res_max / base_resolution) / (n_levels - 1))

        scales, resolutions, sizes, dense = [], [], [], []
        max_size = 2**log2_hashmap_size
        for level in range(n_levels):
            scale = 2.0 ** (level * math.log2(self.per_level_scale)) * base_resolution - 1.0
            resolution = int(math.ceil(scale)) + 1
            size = min(((resolution**3 + 7) // 8) * 8, max_size)
            scales.append(scale)
            resolutions.append(resolution)
            sizes.append(size)
            dense.append(resolution**3 <= size)
        self.level_scales: List[float] = scales
        self.level_resolutions: List[int] = resolutions
        self.level_sizes: List[int] = sizes
        self.level_dense: List[bool] = dense
        if any(dense[level] and not dense[level - 1] for level in range(1, n_levels)):
            raise ValueError("dense levels must come before hashed levels")
        self.n_dense_levels = sum(dense)
        offsets = [0] + list(itertools.accumulate(sizes))
        self.level_offset_list: List[int] = offsets[:-1]

        table = torch.empty(offsets[-1], n_features)
        table.uniform_(-HASH_INIT_RANGE, HASH_INIT_RANGE, generator=generator)
        self.table = nn.Parameter(table)
        self.register_buffer("scales", torch.tensor(scales, dtype=torch.float64), persistent=False)
        self.register_buffer("resolutions", torch.tensor(resolutions), persistent=False)
        self.register_buffer("sizes", torch.tensor(sizes), persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets[:-1]), persistent=False)

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    @property
    def n_params(self) -> int:
        return self.table.numel()

    def forward(self, points_unit: torch.Tensor) -> torch.Tensor:
        """(N, 3) coordinates in box units -> (N, n_levels * n_features), level-major."""
        _check_points(points_unit, "points_unit")
        if not self.fast_gather:
            return self._encode_reference(points_unit)
        if self.uses_compiled_kernel(points_unit):
            return self._encode_compiled(points_unit)
        return self._encode_fast(points_unit)

    def uses_compiled_kernel(self, points_unit: torch.Tensor) -> bool:
        """Whether :meth:`forward` takes the compiled kernel for these points (CPU, table's dtype)."""
        return (self.compiled and self.fast_gather and points_unit.device.type == "cpu"
                and points_unit.dtype == self.table.dtype and hash_kernel.available())

    # -- compiled path ------------------------------------------------------------------------

    def _encode_compiled(self, points_unit: torch.Tensor) -> torch.Tensor:
        features = hash_kernel.hash_grid_lookup(points_unit, self.table, self.scales, self.resolutions, self.sizes,
                                                self.offsets, self.n_dense_levels)  # (N, L, F)
        return features.view(points_unit.shape[0], self.out_dim)  # (N, L * F), no copy

    # -- fast path ----------------------------------------------------------------------------

    def _encode_fast(self, points_unit: torch.Tensor) -> torch.Tensor:
        n_points, n_dense = points_unit.shape[0], self.n_dense_levels
        scales = self.scales.to(points_unit.dtype).view(-1, 1, 1)  # (L, 1, 1)
        position = points_unit.unsqueeze(0) * scales + 0.5  # (L, N, 3)
        corner_float = torch.floor(position)
        fraction = position - corner_float  # (L, N, 3), differentiable in the points
        i0, j0, k0 = corner_float.detach().long().unbind(-1)  # (L, N) each

        index = torch.empty(8, self.n_levels, n_points, dtype=torch.long, device=points_unit.device)
        # Dense levels (the coarse ones, first): index = i + j R + k R^2 (uint32) mod size.
        if n_dense > 0:
            resolution = self.resolutions[:n_dense].view(-1, 1)  # (Ld, 1)
            size = self.sizes[:n_dense].view(-1, 1)
            base = i0[:n_dense] + (j0[:n_dense] + k0[:n_dense] * resolution) * resolution  # (Ld, N)
            offsets = self.offsets[:n_dense].view(-1, 1)
            inside = bool((base >= 0).all()) and bool((base + 1 + resolution + resolution**2 < size).all())  # True for N = 0
            if inside:
                base = base + offsets  # fold the level offsets in once
            for c, (dx, dy, dz) in enumerate(CORNER_OFFSETS):
                corner_step = dx + (dy + dz * resolution) * resolution  # (Ld, 1)
                if inside:
                    torch.add(base, corner_step, out=index[c, :n_dense])
                else:  # points outside the box: emulate tcnn's uint32 wrap
                    index[c, :n_dense] = ((base + corner_step) & UINT32_MASK) % size + offsets
        # Hashed levels: (i * 1 xor j * 2654435761 xor k * 805459861) mod 2^T, written in place.
        if n_dense < self.n_levels:
            hash_mask = 2**self.log2_hashmap_size - 1
            terms = []
            for coordinate, prime in zip((i0[n_dense:], j0[n_dense:], k0[n_dense:]), HASH_PRIMES):
                scaled = coordinate * prime if prime != 1 else coordinate
                terms.append((scaled, scaled + prime))
            hashed_offsets = self.offsets[n_dense:].view(-1, 1)
            xy_hashes = {(dx, dy): terms[0][dx] ^ terms[1][dy] for dx in (0, 1) for dy in (0, 1)}
            for c, (dx, dy, dz) in enumerate(CORNER_OFFSETS):
                hashed = index[c, n_dense:]  # (Lh, N), contiguous
                torch.bitwise_xor(xy_hashes[dx, dy], terms[2][dz], out=hashed)
                hashed.bitwise_and_(hash_mask).add_(hashed_offsets)

        features = trilinear_lookup(self.table, index, fraction)  # (L, N, F)
        return features.permute(1, 0, 2).reshape(n_points, self.out_dim)  # (N, L * F)

    # -- reference path -----------------------------------------------------------------------

    def level_index(self, level: int, corner: torch.Tensor) -> torch.Tensor:
        """Table rows (global) of integer grid vertices (..., 3) on one level (plain formula)."""
        resolution = self.level_resolutions[level]
        size = self.level_sizes[level]
        i, j, k = corner.unbind(-1)
        if self.level_dense[level]:
            local = ((i + j * resolution + k * resolution * resolution) & UINT32_MASK) % size
        else:
            local = ((i * HASH_PRIMES[0]) ^ (j * HASH_PRIMES[1]) ^ (k * HASH_PRIMES[2])) % size
        return local + self.level_offset_list[level]

    def _encode_reference(self, points_unit: torch.Tensor) -> torch.Tensor:
        per_level = []
        for level in range(self.n_levels):
            position = points_unit * self.level_scales[level] + 0.5  # (N, 3)
            corner = torch.floor(position)
            fraction = position - corner
            corner = corner.detach().long()
            level_features = 0.0
            for dx, dy, dz in CORNER_OFFSETS:
                delta = torch.tensor([dx, dy, dz], device=corner.device)
                rows = self.table[self.level_index(level, corner + delta)].to(points_unit.dtype)
                choose = delta.to(points_unit.dtype)
                weight = torch.prod(choose * fraction + (1 - choose) * (1 - fraction), dim=-1)
                level_features = level_features + weight.unsqueeze(-1) * rows  # (N, F)
            per_level.append(level_features)
        return torch.cat(per_level, dim=-1)


def finest_resolution(bound: torch.Tensor, voxel_sdf: float) -> int:
    """res_max = int(max box side / voxel_sdf); a voxel_sdf > 10 is taken as the resolution."""
    if voxel_sdf > 10:
        return int(voxel_sdf)
    extent = float((bound[:, 1] - bound[:, 0]).max())
    return int(extent / voxel_sdf)


# --------------------------------------------------------------------------------------------
# The field


class _LinearOnParts(torch.autograd.Function):
    """y (N, H) = cat(parts, dim=1) (N, D) @ W.T for W (H, D): an MLP's first layer on its joined
    inputs, with the input gradient computed only for the parts that need one.

    The forward and both gradients are the products autograd computes for ``nn.Linear`` on the
    joined input (``mm``; weight gradient ``grad.t() @ inputs``, input gradient ``grad @ W``), so
    they are equal bit for bit as long as the BLAS computes each output column on its own (MKL
    does: tests/test_field.py).  What it saves is the product for the parts nobody differentiates:
    when the map alone is optimised the OneBlob codes need no gradient, which is 48 of the
    geometry MLP's 80 inputs and 48 of the colour MLP's 63, and the gradients it returns are
    contiguous, so the kernels' backward passes need no copy of a strided slice.  Differentiable
    once, like the compiled kernels: a second derivative through the field raises an error."""

    @staticmethod
    def forward(ctx, weight, *parts):
        inputs = torch.cat(parts, dim=-1)
        ctx.save_for_backward(weight, inputs if ctx.needs_input_grad[0] else None)  # kept for dW only
        ctx.widths = [part.shape[-1] for part in parts]
        return inputs.mm(weight.t())

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_output):
        weight, inputs = ctx.saved_tensors
        grad_weight = grad_output.t().mm(inputs) if ctx.needs_input_grad[0] else None
        grad_parts, start = [], 0
        for needed, width in zip(ctx.needs_input_grad[1:], ctx.widths):
            grad_parts.append(grad_output.mm(weight[:, start:start + width]) if needed else None)
            start += width
        return (grad_weight, *grad_parts)


def _mlp_on_parts(mlp: nn.Sequential, parts) -> torch.Tensor:
    """``mlp(torch.cat(parts, dim=1))`` for the bias-free Linear -> ReLU -> Linear below, the
    first layer as :class:`_LinearOnParts`.  parts: tensors (N, D_i) -> (N, out_dim)."""
    hidden = _LinearOnParts.apply(mlp[0].weight, *parts)
    return mlp[2](mlp[1](hidden))


def _bias_free_mlp(in_dim: int, hidden_dim: int, out_dim: int, generator) -> nn.Sequential:
    """Linear -> ReLU -> Linear without biases, PyTorch's default init drawn from ``generator``."""
    mlp = nn.Sequential(
        nn.Linear(in_dim, hidden_dim, bias=False), nn.ReLU(), nn.Linear(hidden_dim, out_dim, bias=False)
    )
    for layer in (mlp[0], mlp[2]):
        nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
    return mlp


class SceneField(nn.Module):
    """Co-SLAM's field: OneBlob + hash grid -> geometry MLP (s, h) -> colour MLP (c).

    Args:
        cfg: FieldConfig (levels, features, table size, voxel_sdf, MLP widths, fast_gather,
            compiled_kernel, compiled_oneblob).
        bound: (3, 2) scene box [[xmin, xmax], [ymin, ymax], [zmin, zmax]] in metres (world).
        generator: optional torch.Generator for the table and MLP initialisation.
    """

    def __init__(self, cfg: FieldConfig, bound, generator: Optional[torch.Generator] = None):
        super().__init__()
        bound = torch.as_tensor(bound, dtype=torch.float32).detach().clone().cpu()
        if bound.shape != (3, 2) or not bool(torch.all(bound[:, 1] > bound[:, 0])):
            raise ValueError(f"bound must be (3, 2) with min < max per axis, got {bound.tolist()}")
        self.register_buffer("bound", bound)
        self.cfg = cfg
        self.oneblob = OneBlobEncoding(cfg.oneblob_bins, compiled=cfg.compiled_oneblob)
        self.grid = HashGridEncoding(
            finest_resolution(bound, cfg.voxel_sdf),
            n_levels=cfg.n_levels,
            n_features=cfg.n_features_per_level,
            base_resolution=cfg.base_resolution,
            log2_hashmap_size=cfg.log2_hashmap_size,
            fast_gather=cfg.fast_gather,
            generator=generator,
            compiled=cfg.compiled_kernel,
        )
        self.geometry_mlp = _bias_free_mlp(
            self.grid.out_dim + self.oneblob.out_dim, cfg.hidden_dim, 1 + cfg.geo_feat_dim, generator
        )
        self.color_mlp = _bias_free_mlp(
            self.oneblob.out_dim + cfg.geo_feat_dim, cfg.hidden_dim_color, 3, generator
        )

    def normalize(self, points: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) in metres -> (N, 3) box units, in [0, 1] per axis inside the box.

        Points are cast to the field's dtype (that of ``bound``), so float64 poses can drive a
        float32 map."""
        _check_points(points)
        points = points.to(self.bound.dtype)  # the field's own precision; differentiable
        return (points - self.bound[:, 0]) / (self.bound[:, 1] - self.bound[:, 0])

    def grid_features(self, points: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) -> hash-grid features (N, n_levels * n_features) (smoothness loss)."""
        return self.grid(self.normalize(points))

    def _geometry(self, points: torch.Tensor):
        points_unit = self.normalize(points)
        oneblob = self.oneblob(points_unit)  # (N, 48)
        grid_features = self.grid(points_unit)  # (N, 32)
        geometry = _mlp_on_parts(self.geometry_mlp, [grid_features, oneblob])  # (N, 16)
        sdf, geo_feat = geometry.split([1, geometry.shape[1] - 1], dim=1)  # backward: one cat, no zeros
        return sdf.squeeze(1), geo_feat, oneblob

    def forward(self, points: torch.Tensor):
        """World points (N, 3) -> (rgb (N, 3) in [0, 1], normalised sdf (N,))."""
        sdf, geo_feat, oneblob = self._geometry(points)
        rgb = torch.sigmoid(_mlp_on_parts(self.color_mlp, [oneblob, geo_feat]))  # (N, 3)
        return rgb, sdf

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) -> normalised SDF (N,) (geometry MLP only)."""
        return self._geometry(points)[0]

    def decoder_parameters(self) -> List[nn.Parameter]:
        return list(self.geometry_mlp.parameters()) + list(self.color_mlp.parameters())

    def parameter_groups(self, mapping_cfg: MappingConfig) -> List[dict]:
        """Adam groups (Co-SLAM section 5.6): decoder lr_decoder + weight decay 1e-6; grid
        lr_embed + eps 1e-15."""
        return [
            {"params": self.decoder_parameters(), "lr": mapping_cfg.lr_decoder, "weight_decay": 1e-6},
            {"params": [self.grid.table], "lr": mapping_cfg.lr_embed, "eps": 1e-15},
        ]
