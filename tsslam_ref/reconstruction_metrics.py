"""Reconstruction metrics: mesh culling, Accuracy / Completion / Completion Ratio, Depth L1.

TS-SLAM §IV-A "Metrics" (table `tab:syn`): Depth L1, Accuracy, Completion and Completion Ratio
(5 cm) on meshes culled "with the same strategy as Co-SLAM" (Co-SLAM's ``cull_mesh.py`` and
``eval_recon.py``).  A small z-buffer rasteriser stands in for Co-SLAM's pyrender depth.

Side layer (numpy, scipy, trimesh; input conversion from :mod:`tsslam_ref.trajectory_metrics`).
Taught in notebooks/08_evaluation.ipynb; protocol and deviations in docs/evaluation.md;
``python -m tsslam_ref.eval mesh`` is the command line.

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| T_wc | ``poses_c2w[k]`` | (F, 4, 4) | camera-to-world, OpenCV axes | m |
| K = (fx, fy, cx, cy, W, H) | ``intrinsics`` | 6 | OpenCV pixels | px |
| D | ``depths[k]`` / z-buffer | (H, W) | camera z | m |

Conventions: inputs are copied to float64 numpy and never modified; pixel centres sit at integer
coordinates.
"""

import os
from typing import Dict, Optional, Tuple

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from tsslam_ref.trajectory_metrics import _check_poses, _to_float64

OCCLUSION_EPS_M = 0.03
"""A vertex is visible if its depth < z-buffer depth + this (Co-SLAM cull_mesh.py: 3 cm)."""
NEAR_PLANE_M = 0.01
"""Triangles with a vertex closer than this to the camera plane are not rasterised (Co-SLAM near)."""
MAX_MEDIAN_DEPTH_M = 100.0
"""cull_mesh refuses depth maps whose median valid depth exceeds this: RGB-D sensors reach about
10 m, while raw PNG values (x1000, x5000) or millimetres give hundreds or thousands (ours)."""
RASTER_PIXEL_BUDGET = 2_000_000
"""Triangle-pixel candidates processed per chunk in the rasteriser (bounds peak memory, ours)."""


# --------------------------------------------------------------------------------------------
# Culling (Co-SLAM cull_mesh.py), 3-D metrics (eval_recon.py), Depth L1


def _check_intrinsics(intrinsics) -> Tuple[float, float, float, float, int, int]:
    values = list(intrinsics)
    if len(values) != 6:
        raise ValueError(f"intrinsics must be (fx, fy, cx, cy, width, height), got {len(values)} values")
    fx, fy, cx, cy, width, height = values
    if not (fx > 0 and fy > 0 and int(width) == width > 0 and int(height) == height > 0):
        raise ValueError(f"intrinsics need fx, fy > 0 and positive integer width/height, got {values}")
    return float(fx), float(fy), float(cx), float(cy), int(width), int(height)


def _project(vertices_world: np.ndarray, pose_c2w: np.ndarray, fx, fy, cx, cy):
    """World points (V, 3) -> pixel u, v (V,) and depth z (V,) (OpenCV camera, pinhole)."""
    points_cam = (vertices_world - pose_c2w[:3, 3]) @ pose_c2w[:3, :3]  # R^T (x - t)  (V, 3)
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * points_cam[:, 0] / z + cx
        v = fy * points_cam[:, 1] / z + cy
    return u, v, z


def render_depth_zbuffer(vertices_world, faces, pose_c2w, intrinsics, near: float = NEAR_PLANE_M) -> np.ndarray:
    """Depth map (H, W) in m of a triangle mesh seen by one camera (z-buffer, inf = no surface).

    A small vectorised rasteriser: each triangle is tested at the integer pixel centres of its
    screen bounding box with barycentric (edge-function) coordinates; depth is interpolated
    perspective-correctly (1/z is affine in the image) and the nearest depth wins.  No back-face
    culling, so it equals Co-SLAM's double-sided pyrender render (min of both orientations).
    Triangles with any vertex nearer than ``near`` are skipped (no near-plane clipping).

    Args:
        vertices_world: (V, 3) in m.  faces: (F, 3) vertex indices.
        pose_c2w: (4, 4) camera-to-world, OpenCV axes.  intrinsics: (fx, fy, cx, cy, W, H).
    """
    fx, fy, cx, cy, width, height = _check_intrinsics(intrinsics)
    vertices_world = _to_float64(vertices_world)
    faces = np.asarray(faces, np.int64)
    u, v, z = _project(vertices_world, _to_float64(pose_c2w), fx, fy, cx, cy)
    zbuffer = np.full(height * width, np.inf)
    tri_u, tri_v, tri_z = u[faces], v[faces], z[faces]  # (F, 3) each
    in_front = (tri_z > near).all(1)
    x_min = np.clip(np.ceil(tri_u.min(1)), 0, width - 1)
    x_max = np.clip(np.floor(tri_u.max(1)), 0, width - 1)
    y_min = np.clip(np.ceil(tri_v.min(1)), 0, height - 1)
    y_max = np.clip(np.floor(tri_v.max(1)), 0, height - 1)
    on_screen = in_front & (tri_u.max(1) >= 0) & (tri_u.min(1) <= width - 1)
    on_screen &= (tri_v.max(1) >= 0) & (tri_v.min(1) <= height - 1) & (x_max >= x_min) & (y_max >= y_min)
    area = (tri_u[:, 1] - tri_u[:, 0]) * (tri_v[:, 2] - tri_v[:, 0]) - (tri_u[:, 2] - tri_u[:, 0]) * (
        tri_v[:, 1] - tri_v[:, 0]
    )
    drawn = np.flatnonzero(on_screen & (np.abs(area) > 1e-12))
    box_w = (x_max - x_min + 1).astype(np.int64)
    box_h = (y_max - y_min + 1).astype(np.int64)
    n_pixels = box_w[drawn] * box_h[drawn]
    budget_marks = np.arange(0, n_pixels.sum(), RASTER_PIXEL_BUDGET)
    chunk_starts = np.unique(np.searchsorted(np.cumsum(n_pixels), budget_marks, "right"))
    for start, stop in zip(chunk_starts, list(chunk_starts[1:]) + [drawn.size]):
        tri = np.repeat(drawn[start:stop], n_pixels[start:stop])  # (P,) triangle of each candidate
        local = np.arange(tri.size) - np.repeat(np.cumsum(n_pixels[start:stop]) - n_pixels[start:stop], n_pixels[start:stop])
        px = x_min[tri] + local % box_w[tri]  # (P,)
        py = y_min[tri] + local // box_w[tri]
        u0, u1, u2 = tri_u[tri].T
        v0, v1, v2 = tri_v[tri].T
        b0 = ((u1 - px) * (v2 - py) - (u2 - px) * (v1 - py)) / area[tri]
        b1 = ((u2 - px) * (v0 - py) - (u0 - px) * (v2 - py)) / area[tri]
        b2 = 1.0 - b0 - b1
        inside = (b0 >= -1e-9) & (b1 >= -1e-9) & (b2 >= -1e-9)
        inv_z = (b0 / tri_z[tri, 0] + b1 / tri_z[tri, 1] + b2 / tri_z[tri, 2])[inside]
        pixel = (py * width + px)[inside].astype(np.int64)
        np.minimum.at(zbuffer, pixel, 1.0 / inv_z)
    return zbuffer.reshape(height, width)


def _observed_vertices(vertices, faces, poses_c2w, intrinsics, depths, occlusion_eps, occlusion):
    """(V,) bools: in the frustum of some camera, and (if occlusion) not occluded there."""
    fx, fy, cx, cy, width, height = _check_intrinsics(intrinsics)
    in_frustum_any = np.zeros(len(vertices), bool)
    observed_any = np.zeros(len(vertices), bool)
    for k, pose in enumerate(poses_c2w):
        if not np.isfinite(pose).all():
            continue  # invalid (ScanNet) pose: this camera observes nothing
        u, v, z = _project(vertices, pose, fx, fy, cx, cy)
        in_frustum = (z > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
        in_frustum_any |= in_frustum
        if not occlusion:
            continue
        depth_map = render_depth_zbuffer(vertices, faces, pose, intrinsics) if depths is None else depths[k]
        rows = np.round(v[in_frustum]).astype(np.int64)
        cols = np.round(u[in_frustum]).astype(np.int64)
        reference = depth_map[rows, cols]
        # a pixel without depth (sensor hole 0/NaN, or no surface: inf) observes nothing, as in
        # Co-SLAM where pyrender's background depth 0 fails the test
        reference = np.where(np.isfinite(reference) & (reference > 0), reference, -np.inf)
        visible = np.zeros(len(vertices), bool)
        visible[np.flatnonzero(in_frustum)] = z[in_frustum] < reference + occlusion_eps
        observed_any |= visible
    return in_frustum_any, (observed_any if occlusion else in_frustum_any)


def cull_mesh(
    mesh: trimesh.Trimesh, poses_c2w, intrinsics, depths=None, occlusion_eps: float = OCCLUSION_EPS_M,
    frustum_only: bool = False, virtual_poses_c2w=None,
) -> trimesh.Trimesh:
    """Remove the triangles no camera saw (Co-SLAM ``cull_mesh.py``, neural_slam_eval).

    A triangle is kept if one of its vertices is in the frustum of some camera (OpenCV projection,
    0 <= u <= W-1, 0 <= v <= H-1, z > 0) and, unless ``frustum_only``, one vertex is also not
    occluded for some camera: z_vertex < D(u, v) + occlusion_eps at the nearest pixel centre.  D is
    ``depths[k]`` when given (sensor or GT depth), else a z-buffer of this mesh rendered by
    :func:`render_depth_zbuffer`; a pixel with no depth (hole, background) observes nothing.

    Args:
        mesh: triangle mesh (not modified).
        poses_c2w: (F, 4, 4) camera-to-world poses; non-finite poses are skipped.
        intrinsics: (fx, fy, cx, cy, width, height) of the raw images.
        depths: optional (F, H, W) depth maps in m (a median above ``MAX_MEDIAN_DEPTH_M`` is refused).
        occlusion_eps: tolerance in m (Co-SLAM: 0.03).
        frustum_only: skip the occlusion test (iMAP / NICE-SLAM culling).
        virtual_poses_c2w: optional (G, 4, 4) extra cameras that may add observations but never
            frustum membership (Co-SLAM's virtual cameras); rendered with the z-buffer.

    Returns:
        A new mesh with the kept faces and only the vertices they use.

    Differs from: Co-SLAM renders with pyrender/EGL (near 0.01 m, far 10 m, triangles clipped at the
    near plane) and truncates (u, v) to the pixel index; we sample and look up at integer pixel
    centres (OpenCV convention), have no far plane and skip near-crossing triangles, so results can
    differ by a pixel at silhouettes.  Co-SLAM's virtual cameras are hand-picked in Open3D; we
    ship none (pass ``virtual_poses_c2w``).
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"cull_mesh expects a trimesh.Trimesh, got {type(mesh).__name__}")
    poses_c2w = _check_poses(poses_c2w, "poses_c2w")
    _, _, _, _, width, height = _check_intrinsics(intrinsics)
    vertices = np.array(mesh.vertices, np.float64)
    faces = np.array(mesh.faces, np.int64)
    if depths is not None:
        depths = _to_float64(depths)
        if depths.shape != (poses_c2w.shape[0], height, width):
            raise ValueError(f"depths must be (F, H, W) = {(poses_c2w.shape[0], height, width)}, got {depths.shape}")
        measured = depths[np.isfinite(depths) & (depths > 0)]
        if measured.size and np.median(measured) > MAX_MEDIAN_DEPTH_M:  # else nothing is occluded, silently
            raise ValueError(f"depths have a median of {np.median(measured):.4g} m, more than {MAX_MEDIAN_DEPTH_M:g} "
                             f"m: expected metres (raw PNG values or millimetres? divide by the depth scale)")
    in_frustum, observed = _observed_vertices(
        vertices, faces, poses_c2w, intrinsics, depths, occlusion_eps, not frustum_only
    )
    if virtual_poses_c2w is not None and not frustum_only:
        virtual = _check_poses(virtual_poses_c2w, "virtual_poses_c2w")
        observed = observed | _observed_vertices(vertices, faces, virtual, intrinsics, None, occlusion_eps, True)[1]
    keep = in_frustum[faces].any(1) & observed[faces].any(1)
    culled = trimesh.Trimesh(vertices=vertices, faces=faces[keep], process=False)
    culled.remove_unreferenced_vertices()
    return culled


def mesh_metrics(rec_mesh, gt_mesh, n_points: int = 200_000, threshold: float = 0.05, seed: int = 0) -> Dict[str, float]:
    """Accuracy, Completion, Completion Ratio from surface samples (Co-SLAM ``eval_recon.py``).

    X = n_points samples on rec_mesh, Y = n_points samples on gt_mesh (area-uniform, one
    ``numpy.random.default_rng(seed)`` drawing X then Y);
    Accuracy = mean_x min_y |x - y|, Completion = mean_y min_x |y - x|,
    Completion Ratio = share of y with min_x |y - x| < threshold.

    Returns:
        dict(accuracy_m, completion_m, completion_ratio (0..1), threshold_m, n_points).

    Differs from: Co-SLAM first ICP-aligns rec to GT (Open3D, 0.1 m); we do not (SLAM meshes live
    in the GT frame because frame 0 starts at its GT pose).
    """
    for name, mesh in (("rec_mesh", rec_mesh), ("gt_mesh", gt_mesh)):
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or mesh.area <= 0:
            raise ValueError(f"{name} must be a trimesh.Trimesh with at least one non-degenerate face")
    if int(n_points) != n_points or n_points < 1:
        raise ValueError(f"n_points must be a positive integer, got {n_points}")
    rng = np.random.default_rng(seed)
    rec_points = np.asarray(trimesh.sample.sample_surface(rec_mesh, int(n_points), seed=rng)[0])  # (n, 3)
    gt_points = np.asarray(trimesh.sample.sample_surface(gt_mesh, int(n_points), seed=rng)[0])
    rec_to_gt = cKDTree(gt_points).query(rec_points, workers=1)[0]  # (n,)
    gt_to_rec = cKDTree(rec_points).query(gt_points, workers=1)[0]
    return {
        "accuracy_m": float(rec_to_gt.mean()),
        "completion_m": float(gt_to_rec.mean()),
        "completion_ratio": float((gt_to_rec < threshold).mean()),
        "threshold_m": float(threshold),
        "n_points": int(n_points),
    }


RUN_POINTS = 50_000
"""Surface samples per mesh in a run's reconstruction metrics: a quarter of Co-SLAM's 200,000, to
keep the end of a run short (a sampling floor of 0.5 sqrt(area / 50,000), twice Co-SLAM's; ours)."""
CULL_EVERY = 2
"""A run culls with the ground-truth camera of every second frame (Co-SLAM ``cull_mesh.py --skip 2``)."""


def culled_metrics(rec_mesh, gt_mesh, sequence, seed: int = 0, threshold: float = 0.05,
                   n_points: int = RUN_POINTS) -> Dict[str, object]:
    """A run's reconstruction protocol: both meshes culled (frustum and occlusion, :func:`cull_mesh`)
    with the ground-truth cameras of every :data:`CULL_EVERY`-th frame of ``sequence`` in the raw
    images' camera (``sequence.uncropped_intrinsics``: no crop, at the working width; Co-SLAM adds
    hand-picked virtual cameras, which we do not have), then :func:`mesh_metrics`.

    Returns:
        mesh_metrics' dict plus ``sampling_seed`` and ``culling`` (cameras, camera, areas in m²), or
        ``{"reconstruction_note": why}`` when the meshes' sizes differ ten-fold (a mesh in
        millimetres) or nothing is left after culling.
    """
    sizes = mesh_sizes_differ(rec_mesh, gt_mesh)
    if sizes is not None:
        return {"reconstruction_note": f"not scored: the ground-truth mesh spans {sizes[1]:.3g} and the reconstruction "
                                       f"{sizes[0]:.3g} (bounding-box diagonals, the reconstruction in metres): the "
                                       f"ground-truth mesh must be in metres, of the same scene"}
    camera = sequence.uncropped_intrinsics
    intrinsics = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    poses = np.asarray(sequence.gt_poses)[::CULL_EVERY]
    culled, culled_gt = cull_mesh(rec_mesh, poses, intrinsics), cull_mesh(gt_mesh, poses, intrinsics)
    if len(culled.faces) == 0 or len(culled_gt.faces) == 0:
        return {"reconstruction_note": "nothing left after culling"}
    result: Dict[str, object] = dict(mesh_metrics(culled, culled_gt, n_points=n_points, threshold=threshold, seed=seed))
    result["sampling_seed"] = int(seed)
    cameras = int(np.isfinite(poses.reshape(len(poses), -1)).all(axis=1).sum())  # cull_mesh skips unknown poses
    result["culling"] = {"cameras": cameras, "every_nth_frame": CULL_EVERY,
                         "camera": dict(zip(("fx", "fy", "cx", "cy", "width", "height"), intrinsics)),
                         "area_m2": {"reconstruction": float(culled.area), "ground_truth": float(culled_gt.area)}}
    return result


def depth_l1(rendered_depth, reference_depth, valid=None) -> float:
    """Depth L1 in m: mean |rendered - reference| over pixels where reference > 0 and finite.

    Args:
        rendered_depth: (..., H, W) depth in m (numpy or torch); +inf where no surface was hit (as
            :func:`render_depth_zbuffer` marks it) counts as depth 0, so a hole in the reconstruction
            costs the whole reference depth, as with Co-SLAM's renderer, whose background depth is 0.
        reference_depth: same shape, sensor/GT depth in m; 0 or non-finite = missing.
        valid: optional bool mask of the same shape, ANDed with the reference test.

    Raises:
        ValueError: shape mismatch, no valid pixel, or a NaN or -inf rendered depth at a valid pixel.
    """
    rendered = _to_float64(rendered_depth)
    rendered = np.where(np.isposinf(rendered), 0.0, rendered)  # no surface: background depth 0
    reference = _to_float64(reference_depth)
    if rendered.shape != reference.shape:
        raise ValueError(f"rendered_depth {rendered.shape} and reference_depth {reference.shape} must match")
    mask = np.isfinite(reference) & (reference > 0)
    if valid is not None:
        valid = _to_float64(valid).astype(bool)
        if valid.shape != mask.shape:
            raise ValueError(f"valid mask {valid.shape} must match depth shape {mask.shape}")
        mask &= valid
    if not mask.any():
        raise ValueError("depth_l1: no pixel has a valid (finite, > 0) reference depth")
    if not np.isfinite(rendered[mask]).all():
        raise ValueError("depth_l1: rendered depth is NaN or -inf at pixels with a valid reference")
    return float(np.abs(rendered[mask] - reference[mask]).mean())


# --------------------------------------------------------------------------------------------
# Mesh files


def read_mesh(path) -> trimesh.Trimesh:
    """A triangle mesh file as read for the metrics (no processing: faces and vertices as stored);
    ValueError naming the file when it is missing, unreadable, without triangles, with a non-finite
    vertex or only zero-area triangles."""
    path = str(path)
    if not os.path.isfile(path):
        missing = "is a folder; expected a mesh file" if os.path.isdir(path) else "mesh file not found"
        raise ValueError(f"{path}: {missing}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds of errors for bad files
        raise ValueError(f"{path}: cannot read a triangle mesh ({str(error)[:200] or type(error).__name__})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: contains no triangles")
    bad = np.flatnonzero(~np.isfinite(mesh.vertices).all(axis=1))
    if bad.size:
        raise ValueError(f"{path}: vertex {int(bad[0])} is not finite ({mesh.vertices[bad[0]].tolist()}); expected "
                         f"finite coordinates in metres")
    if not (mesh.area_faces > 0).any():
        raise ValueError(f"{path}: every triangle has zero area; expected a surface")
    return mesh


def mesh_sizes_differ(rec_mesh: trimesh.Trimesh, gt_mesh: trimesh.Trimesh,
                      factor: float = 10.0) -> Optional[Tuple[float, float]]:
    """The two meshes' bounding-box diagonals (m) when they differ ``factor``-fold or more
    (millimetres against metres, or a mesh of another scene: the metrics would be meaningless),
    else None."""
    sizes = tuple(float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0])) for mesh in (rec_mesh, gt_mesh))
    return sizes if min(sizes) > 0 and max(sizes) / min(sizes) >= factor else None
