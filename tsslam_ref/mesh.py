"""Marching-cubes meshes of the field's zero level set, with vertex colours.

Co-SLAM's ``utils.extract_mesh`` (from NeuralRGBD): the normalised SDF is queried on a regular grid over
the box (N_axis = round(extent / voxel + 0.0005) cells per axis, chunks of 65,536 points), and
marching cubes extracts the iso-0 surface; cells where a corner has |s| >= 3 (3 tr) are skipped,
which removes spurious surfaces far from anything observed.  Vertex colours come from the
colour head at the vertices.  Not an equation of TS-SLAM; it produces the meshes of §IV (Table III).

Layer 2: imports only :mod:`tsslam_ref.files` (atomic writes of the .ply file); needs only
``field.sdf`` (and ``field(points)`` for colours) and ``field.bound`` of the field it is given.
Taught in notebooks/04_rendering_and_losses.ipynb.

Differs from: Co-SLAM uses NeuralRGBD's C++ ``NumpyMarchingCubes``; we use scikit-image's
Lewiner marching cubes with its ``mask`` argument set to the cells whose 8 corners all have
|s| < sdf_cutoff (same cells kept), and report vertices as float metres.
"""

import os

import numpy as np
import torch
import trimesh
from skimage.measure import marching_cubes

from .files import atomic_write_bytes


MAX_GRID_POINTS = 400_000_000
"""Largest marching-cubes grid (about 1.6 GB of float32 SDF values, 6 GB with the masks and the
float64 copy scikit-image takes); tum-cpu's final mesh of the bundled slice has 2.2 million points."""


def _grid_axes(bound: np.ndarray, voxel_size: float):
    """Per-axis sample coordinates: N = round(extent / voxel + 0.0005) cells, N + 1 points."""
    axes = []
    for low, high in bound:
        n_cells = int(round((high - low) / voxel_size + 0.0005))
        if n_cells < 1:
            raise ValueError(f"bound side {high - low:.4f} m is smaller than voxel_size {voxel_size} m")
        axes.append(np.linspace(low, high, n_cells + 1))
    n_points = int(np.prod([len(axis) for axis in axes], dtype=np.float64))
    if n_points > MAX_GRID_POINTS:
        sides = " x ".join(f"{high - low:.1f}" for low, high in bound)
        raise ValueError(f"a mesh of the {sides} m bound at voxel_size {voxel_size} m needs {n_points:.3g} grid points "
                         f"(more than {MAX_GRID_POINTS:.0e}); raise the voxel size (mesh.voxel_final) or check the depth scale")
    return axes


def _field_device_dtype(field):
    bound = getattr(field, "bound", None)
    if isinstance(bound, torch.Tensor):
        return bound.device, bound.dtype
    return torch.device("cpu"), torch.float32


def _query(fn, points: np.ndarray, device, dtype) -> np.ndarray:
    """``fn`` on (M, 3) float64 numpy points moved to ``device`` / ``dtype`` -> float32 numpy output."""
    return fn(torch.from_numpy(points).to(device=device, dtype=dtype)).float().cpu().numpy()


@torch.no_grad()
def query_in_chunks(fn, points: np.ndarray, chunk: int, device, dtype) -> np.ndarray:
    """Apply ``fn`` to (M, 3) numpy points ``chunk`` at a time -> concatenated numpy output."""
    return np.concatenate([_query(fn, points[start : start + chunk], device, dtype)
                           for start in range(0, points.shape[0], chunk)])


@torch.no_grad()
def query_grid(fn, axes, chunk: int, device, dtype) -> np.ndarray:
    """Apply ``fn`` to every point of the grid spanned by ``axes``, ``chunk`` points at a time.

    The points are those of ``np.meshgrid(*axes, indexing="ij")`` in C order, built one chunk at a
    time from their flat indices, so the (N, 3) float64 grid is never held in memory (the bundled
    teddy box at ``tum-cpu``'s 0.04 m has 2.2 million points: 50 MiB, and as much again for
    meshgrid's temporaries; an 8 x 8 x 3 m room at 0.03 m has 7.3 million).

    Args:
        fn: callable (M, 3) tensor -> (M,) tensor.
        axes: three 1-D numpy arrays, the sample coordinates per axis (lengths Nx, Ny, Nz).

    Returns:
        (Nx, Ny, Nz) float32 values.
    """
    shape = tuple(len(axis) for axis in axes)
    values = np.empty(int(np.prod(shape)), dtype=np.float32)
    for start in range(0, values.size, chunk):
        flat = np.arange(start, min(start + chunk, values.size))
        points = np.stack([axis[index] for axis, index in zip(axes, np.unravel_index(flat, shape))], axis=-1)
        values[start : start + len(flat)] = _query(fn, points, device, dtype)
    return values.reshape(shape)


def extract_mesh(
    field,
    bound=None,
    voxel_size: float = 0.05,
    sdf_cutoff: float = 3.0,
    chunk: int = 65536,
    color: bool = True,
) -> trimesh.Trimesh:
    """Iso-0 mesh of ``field.sdf`` over ``bound`` (metres), skipping far-from-surface cells.

    Args:
        field: object with ``sdf(points (N, 3)) -> (N,)`` (normalised SDF), callable as
            ``field(points) -> (rgb, sdf)`` when ``color``; ``bound`` attribute used if ``bound`` is None.
        bound: (3, 2) box in metres, or None for ``field.bound``.
        voxel_size: grid spacing in metres.
        sdf_cutoff: cells with any corner |s| >= sdf_cutoff are skipped (Co-SLAM: 3.0).
        chunk: points per query.
        color: add vertex colours (uint8 RGBA) from the colour head.

    Returns:
        trimesh.Trimesh with float64 vertices in metres (world), faces wound so that normals
        point towards positive SDF (outside).  Raises ValueError if no surface is found.
    """
    if bound is None:
        bound = field.bound
    bound = np.asarray(bound.detach().cpu() if isinstance(bound, torch.Tensor) else bound, dtype=np.float64)
    if bound.shape != (3, 2):
        raise ValueError(f"bound must be (3, 2), got {bound.shape}")
    device, dtype = _field_device_dtype(field)
    axes = _grid_axes(bound, voxel_size)
    sdf = query_grid(field.sdf, axes, chunk, device, dtype)  # (Nx+1, Ny+1, Nz+1)

    near = np.abs(sdf) < sdf_cutoff  # (Nx+1, Ny+1, Nz+1) per vertex
    cell_keep = np.ones(tuple(n - 1 for n in near.shape), dtype=bool)  # (Nx, Ny, Nz) per cell
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                cell_keep &= near[dx : dx + near.shape[0] - 1, dy : dy + near.shape[1] - 1, dz : dz + near.shape[2] - 1]
    mask = np.zeros(near.shape, dtype=bool)
    mask[1:, 1:, 1:] = cell_keep  # scikit-image reads a cell's mask at its highest corner (tested)
    if not (sdf.min() < 0 < sdf.max()) or not cell_keep.any():
        raise ValueError("extract_mesh: the SDF has no zero crossing inside the bound")
    spacing = tuple(float(axis[1] - axis[0]) for axis in axes)
    try:
        vertices, faces, _, _ = marching_cubes(sdf, level=0.0, spacing=spacing, mask=mask)
    except RuntimeError:  # scikit-image: "No surface found" in the kept cells
        raise ValueError(f"extract_mesh: the SDF has no zero crossing in the cells near a surface "
                         f"(all 8 corners with |s| < sdf_cutoff = {sdf_cutoff})") from None
    vertices = vertices + bound[:, 0]
    # scikit-image's default ("descent") winding already points face normals to positive SDF.
    vertex_colors = None
    if color:
        rgb = query_in_chunks(lambda p: field(p)[0], vertices, chunk, device, dtype)
        alpha = np.ones((rgb.shape[0], 1))
        vertex_colors = (np.clip(np.concatenate([rgb, alpha], axis=-1), 0, 1) * 255).astype(np.uint8)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=vertex_colors, process=False)


def save_mesh(mesh: trimesh.Trimesh, path, overwrite: bool = False) -> None:
    """Write ``mesh`` as .ply atomically (``files.atomic_write_bytes``: a new file, then rename).

    Raises FileExistsError if ``path`` exists and ``overwrite`` is False, ValueError for a
    suffix other than .ply.
    """
    path = os.fspath(path)
    if not path.lower().endswith(".ply"):
        raise ValueError(f"save_mesh writes .ply files, got '{path}'")
    if os.path.exists(path) and not overwrite:
        raise FileExistsError(f"'{path}' exists; pass overwrite=True to replace it")
    atomic_write_bytes(path, trimesh.exchange.ply.export_ply(mesh))
