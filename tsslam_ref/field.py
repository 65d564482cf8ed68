"""The scene field f_theta(x) -> (c, s): Co-SLAM's joint coordinate + parametric encoding.

TS-SLAM §III-A (``sec:rep_secene``), Eq. (1)-(2) (``eq:cal_ray``): the map is Co-SLAM's field, a
OneBlob coordinate encoding gamma(x) and a multi-resolution hash grid V(x) feeding two tiny MLPs:

    x_n        = (x - bound_min) / (bound_max - bound_min)           per axis, in [0, 1]
    s, h       = f_tau( V(x_n), gamma(x_n) )                         geometry MLP, 80 -> 32 -> 16
    c          = sigmoid( f_phi( gamma(x_n), h ) )                   colour MLP, 63 -> 32 -> 3

``s`` is Co-SLAM's *normalised* SDF: metric SDF = s * tr (shared/spec/coslam.md section 1.4).

Layer 1 (math and map): imports torch and config only; knows nothing about rays or cameras.
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
storage, hash primes) and ``oneblob.h`` (quartic kernel) as described in shared/spec/coslam.md
sections 1.1-1.4.  Deviations are listed in docs/map.md.
"""

import itertools
import math
from typing import List, Optional

import torch
from torch import nn

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
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(points.shape)}")


# --------------------------------------------------------------------------------------------
# OneBlob


class OneBlobEncoding(nn.Module):
    """OneBlob coordinate encoding with tcnn's quartic kernel, periodic with period 1.

    For one coordinate x in [0, 1] and bin k = 0..n_bins-1 (spec section 1.2), with v = n_bins * u:

        F(u)     = clamp( (15/16) v (1 - (2/3) v^2 + (1/5) v^4) + 1/2, 0, 1 )   (kernel CDF)
        G(b)     = F(b - x) + F(b - x - 1) + F(b - x + 1)                         (wrap-around)
        out_k    = G((k + 1) / n_bins) - G(k / n_bins)

    Coordinates are first wrapped to [0, 1) (x - floor(x)), so the code has period 1 for every x,
    also outside the box.  The outputs of one coordinate sum to 1.  No parameters.
    Output layout is dim-major: (x bins, y bins, z bins).
    """

    def __init__(self, n_bins: int = 16):
        super().__init__()
        if n_bins < 2:
            raise ValueError(f"OneBlobEncoding needs n_bins >= 2, got {n_bins}")
        self.n_bins = n_bins

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
        edges = torch.arange(self.n_bins + 1, device=points_unit.device, dtype=points_unit.dtype)
        edges = edges / self.n_bins  # (n_bins + 1,)
        wrapped = points_unit - torch.floor(points_unit).detach()  # in [0, 1): exact period 1
        offset = edges - wrapped.unsqueeze(-1)  # (N, 3, n_bins + 1)
        cdf = self.kernel_cdf(offset) + self.kernel_cdf(offset - 1.0) + self.kernel_cdf(offset + 1.0)
        codes = cdf[..., 1:] - cdf[..., :-1]  # (N, 3, n_bins)
        return codes.reshape(points_unit.shape[0], self.out_dim)


# --------------------------------------------------------------------------------------------
# Hash grid


class _TableGather(torch.autograd.Function):
    """rows = table[index] whose backward is one ``scatter_add_`` into a zero table.

    The default backward of ``F.embedding`` / advanced indexing is the slowest op of the whole
    field on CPU (shared/spec/cpu-budget.md); this one writes all gradient rows in one pass.
    Written in the ``setup_context`` style so that it also works under ``torch.func``.
    """

    @staticmethod
    def forward(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        return table.index_select(0, index)

    @staticmethod
    def setup_context(ctx, inputs, output):
        table, index = inputs
        ctx.save_for_backward(index)
        ctx.table_shape = table.shape

    @staticmethod
    def backward(ctx, grad_rows: torch.Tensor):
        (index,) = ctx.saved_tensors
        grad_table = grad_rows.new_zeros(ctx.table_shape)
        grad_table.scatter_add_(0, index.unsqueeze(-1).expand_as(grad_rows), grad_rows)
        return grad_table, None


def gather_rows(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Fast differentiable ``table[index]`` for a (T, F) table and (M,) long index -> (M, F)."""
    return _TableGather.apply(table, index)


class HashGridEncoding(nn.Module):
    """Multi-resolution hash grid with tiny-cuda-nn's level geometry (spec section 1.3).

    Level l = 0..n_levels-1, with b = (res_max / base)^(1 / (n_levels - 1)):

        scale_l = b^l * base - 1,      R_l = ceil(scale_l) + 1 vertices per axis
        p       = x_n * scale_l + 0.5, corner = floor(p), fraction = p - floor(p)
        size_l  = min(next_multiple_of_8(R_l^3), 2^log2_hashmap_size)
        index   = i + j R_l + k R_l^2 (mod size_l)                    if R_l^3 <= size_l (dense)
                  (i * 1 xor j * 2654435761 xor k * 805459861) mod 2^T  otherwise (hashed)

    and trilinear interpolation of the 8 corners.  All levels live in one ``table`` parameter
    (sum_l size_l, n_features) with ``level_offsets``.

    Two paths give the same numbers: the fast one (all levels at once, corner-major, custom
    gather with a ``scatter_add_`` backward) and a plain reference one (a loop over levels and
    corners with ordinary indexing).  ``fast_gather`` picks one.
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
    ):
        super().__init__()
        if res_max < 1:
            raise ValueError(f"res_max must be >= 1, got {res_max} (box too small for voxel_sdf?)")
        if n_levels < 2:
            raise ValueError(f"HashGridEncoding needs n_levels >= 2, got {n_levels}")
        self.res_max = int(res_max)
        self.n_levels = n_levels
        self.n_features = n_features
        self.base_resolution = base_resolution
        self.log2_hashmap_size = log2_hashmap_size
        self.fast_gather = fast_gather
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
        self.register_buffer("dense", torch.tensor(dense), persistent=False)
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
        if self.fast_gather:
            return self._encode_fast(points_unit)
        return self._encode_reference(points_unit)

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
            inside = bool(base.min() >= 0) and bool((base + 1 + resolution + resolution**2 < size).all())
            for c, (dx, dy, dz) in enumerate(CORNER_OFFSETS):
                corner_index = base + (dx + (dy + dz * resolution) * resolution)
                if not inside:  # points outside the box: emulate tcnn's uint32 wrap
                    corner_index = (corner_index & UINT32_MASK) % size
                index[c, :n_dense] = corner_index + self.offsets[:n_dense].view(-1, 1)
        # Hashed levels: (i * 1 xor j * 2654435761 xor k * 805459861) mod 2^T.
        if n_dense < self.n_levels:
            hash_mask = 2**self.log2_hashmap_size - 1
            terms = []
            for coordinate, prime in zip((i0[n_dense:], j0[n_dense:], k0[n_dense:]), HASH_PRIMES):
                scaled = coordinate * prime if prime != 1 else coordinate
                terms.append((scaled, scaled + prime))
            hashed_offsets = self.offsets[n_dense:].view(-1, 1)
            for c, (dx, dy, dz) in enumerate(CORNER_OFFSETS):
                hashed = (terms[0][dx] ^ terms[1][dy] ^ terms[2][dz]) & hash_mask
                index[c, n_dense:] = hashed + hashed_offsets

        rows = gather_rows(self.table, index.view(-1)).to(points_unit.dtype)  # (8 * L * N, F)
        # unbind, not rows[c]: the backward of 8 selects would zero-fill 8 full-size buffers.
        corner_rows = rows.view(8, self.n_levels, n_points, self.n_features).unbind(0)  # 8 x (L, N, F)

        fx, fy, fz = fraction.unsqueeze(-1).unbind(-2)  # (L, N, 1) each
        wx, wy, wz = (1.0 - fx, fx), (1.0 - fy, fy), (1.0 - fz, fz)
        features = None
        for c, (dx, dy, dz) in enumerate(CORNER_OFFSETS):
            term = (wx[dx] * wy[dy] * wz[dz]) * corner_rows[c]  # (L, N, F)
            features = term if features is None else features + term
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
        cfg: FieldConfig (levels, features, table size, voxel_sdf, MLP widths, fast_gather).
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
        self.oneblob = OneBlobEncoding(cfg.oneblob_bins)
        self.grid = HashGridEncoding(
            finest_resolution(bound, cfg.voxel_sdf),
            n_levels=cfg.n_levels,
            n_features=cfg.n_features_per_level,
            base_resolution=cfg.base_resolution,
            log2_hashmap_size=cfg.log2_hashmap_size,
            fast_gather=cfg.fast_gather,
            generator=generator,
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
        geometry = self.geometry_mlp(torch.cat([grid_features, oneblob], dim=-1))  # (N, 16)
        return geometry[:, 0], geometry[:, 1:], oneblob

    def forward(self, points: torch.Tensor):
        """World points (N, 3) -> (rgb (N, 3) in [0, 1], normalised sdf (N,))."""
        sdf, geo_feat, oneblob = self._geometry(points)
        rgb = torch.sigmoid(self.color_mlp(torch.cat([oneblob, geo_feat], dim=-1)))  # (N, 3)
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
