"""Evaluation: trajectory metrics (ATE, RPE) and reconstruction metrics (culling, Acc/Comp, Depth L1).

TS-SLAM §IV-A "Metrics" (no numbered equations; tables `tab:scannet_track`, `tab:tum_track`,
`tab:syn`, `tab:ablation` report these numbers): ATE RMSE after Horn alignment, RPE RMSE over a
fixed interval of 1 frame, Depth L1, Accuracy, Completion and Completion Ratio (5 cm) on meshes
culled "with the same strategy as Co-SLAM".  Formulas follow the TUM RGB-D paper (Sturm et al.,
IROS 2012) in its notation; the mesh protocol follows shared/spec/coslam.md §6.2-6.4.

Layer: side (numpy, scipy, trimesh, torch; tsslam_ref.data only for the TUM file reader).  Taught in
notebooks/08_evaluation.ipynb; protocol and deviations in docs/evaluation.md.

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| Q_i | ``gt_poses[i]`` | (N, 4, 4) | camera-to-world (GT world) | m |
| P_i | ``est_poses[i]`` | (N, 4, 4) | camera-to-world (estimate's world) | m |
| S = (s, R, t) | ``alignment`` | (4, 4) | estimate's world -> GT world | m |
| F_i = Q_i^-1 S P_i | ATE residual, only its translation is used | (N,) | - | m |
| E_i = (Q_i^-1 Q_i+d)^-1 (P_i^-1 P_i+d) | RPE residual | (N-d,) | - | m, deg |
| K = (fx, fy, cx, cy, W, H) | ``intrinsics`` | 6 | OpenCV pixels | px |

Conventions: inputs may be numpy arrays or torch tensors on any device; they are copied to float64
numpy (evaluation is bookkeeping, not part of any autograd graph) and never modified.  Timestamps
are float64 seconds.  Every returned key carries its unit (``_m``, ``_deg``, ``_s``) or is a count
or a ratio in [0, 1].
"""

import json
import os
import sys
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from tsslam_ref.data import read_tum_trajectory

DEFAULT_MAX_DIFF_S = 0.01
"""Association tolerance in seconds (evo's default; TUM's associate.py uses 0.02)."""
OCCLUSION_EPS_M = 0.03
"""A vertex is visible if its depth < z-buffer depth + this (Co-SLAM cull_mesh.py: 3 cm)."""
NEAR_PLANE_M = 0.01
"""Triangles with a vertex closer than this to the camera plane are not rasterised (Co-SLAM near)."""
RASTER_PIXEL_BUDGET = 2_000_000
"""Triangle-pixel candidates processed per chunk in the rasteriser (bounds peak memory, ours)."""
_SVD_RANK_EPS = 1e-12
"""Singular values below this (relative) make the alignment ambiguous (collinear points)."""


# --------------------------------------------------------------------------------------------
# Input handling


def _to_float64(array, name: str) -> np.ndarray:
    """numpy copy in float64 of a numpy array / torch tensor / sequence (inputs are never mutated)."""
    if isinstance(array, torch.Tensor):
        return array.detach().numpy(force=True).astype(np.float64, copy=True)
    return np.array(array, dtype=np.float64, copy=True)


def _check_poses(poses, name: str) -> np.ndarray:
    poses = _to_float64(poses, name)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (N, 4, 4), got {poses.shape}")
    return poses


def _check_times(times, name: str) -> np.ndarray:
    times = _to_float64(times, name)
    if times.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {times.shape}")
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] = {times[bad[0]]} is not a finite timestamp in seconds")
    return times


# --------------------------------------------------------------------------------------------
# Association and alignment


def associate(times_a, times_b, max_diff: float = 0.02) -> Tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-first association of two timestamp lists (TUM ``associate.py``).

    All pairs with |a_i - b_j| <= max_diff are candidates; they are accepted greedily from the
    smallest difference up (ties broken by index), each index used at most once.

    Args:
        times_a: (N,) float64 seconds, in any order.
        times_b: (M,) float64 seconds, in any order.
        max_diff: largest accepted |a - b| in seconds.

    Returns:
        ``(idx_a, idx_b)``: (K,) int64 indices, pairs sorted by ``times_a[idx_a]``.

    Raises:
        ValueError: non-finite or wrongly shaped times, negative max_diff, or no pair within
            max_diff (the message gives both time ranges and what to try).

    Differs from: evo's ``matching_time_indices`` matches each stamp of the shorter list to its
    nearest stamp of the longer one and may reuse a stamp; both agree whenever every nearest
    neighbour is unique (e.g. one list sparser than the other by more than 2 x max_diff).
    Unsorted input is handled (not an error), unlike TUM's script it uses ``<=`` as evo does.
    """
    times_a = _check_times(times_a, "times_a")
    times_b = _check_times(times_b, "times_b")
    if not max_diff >= 0:
        raise ValueError(f"max_diff must be >= 0 seconds, got {max_diff}")
    order_b = np.argsort(times_b, kind="stable")
    sorted_b = times_b[order_b]
    lo = np.searchsorted(sorted_b, times_a - max_diff, side="left")
    hi = np.searchsorted(sorted_b, times_a + max_diff, side="right")
    counts = hi - lo  # candidates per a  (N,)
    cand_a = np.repeat(np.arange(times_a.size), counts)  # (C,)
    offsets = np.arange(cand_a.size) - np.repeat(np.cumsum(counts) - counts, counts)
    cand_b = order_b[np.repeat(lo, counts) + offsets]  # (C,)
    diffs = np.abs(times_a[cand_a] - times_b[cand_b])
    keep = diffs <= max_diff
    cand_a, cand_b, diffs = cand_a[keep], cand_b[keep], diffs[keep]
    if cand_a.size == 0:
        raise ValueError(
            f"no timestamps within max_diff={max_diff} s: times_a spans "
            f"[{times_a.min() if times_a.size else np.nan:.6f}, {times_a.max() if times_a.size else np.nan:.6f}] s, "
            f"times_b spans [{times_b.min() if times_b.size else np.nan:.6f}, "
            f"{times_b.max() if times_b.size else np.nan:.6f}] s; check that both use the same clock "
            f"(seconds, not nanoseconds or frame indices) or raise max_diff"
        )
    order = np.lexsort((cand_b, cand_a, diffs))  # smallest difference first
    used_a = np.zeros(times_a.size, bool)
    used_b = np.zeros(times_b.size, bool)
    idx_a, idx_b = [], []
    for a, b in zip(cand_a[order], cand_b[order]):
        if not used_a[a] and not used_b[b]:
            used_a[a] = used_b[b] = True
            idx_a.append(a)
            idx_b.append(b)
    idx_a, idx_b = np.asarray(idx_a, np.int64), np.asarray(idx_b, np.int64)
    by_time = np.lexsort((idx_a, times_a[idx_a]))
    return idx_a[by_time], idx_b[by_time]


def horn_alignment(model, data, with_scale: bool = False) -> Tuple[np.ndarray, np.ndarray, float]:
    """Closed-form similarity (s, R, t) minimising sum_i ||s R model_i + t - data_i||^2.

    Aligns ``model`` ONTO ``data`` (for ATE: model = estimated positions, data = ground truth).
    SVD form of Horn (1987) / Umeyama (1991): with centred points m'_i, d'_i,
    Sigma = (1/N) sum d'_i m'_i^T = U D V^T,  S = diag(1, 1, sign(det U det V)),
    R = U S V^T,  s = tr(D S) / ((1/N) sum |m'_i|^2) (1 if not with_scale),  t = mean(d) - s R mean(m).

    Args:
        model: (N, 3) points to be moved, e.g. estimated positions in m.
        data: (N, 3) target points, e.g. ground-truth positions in m.
        with_scale: also estimate s (Sim(3)), for monocular-style evaluation.

    Returns:
        ``(R (3, 3), t (3,), s)``.

    Raises:
        ValueError: shape mismatch, fewer than 3 points, non-finite values, or points that do not
            span a plane (collinear/coincident), where the rotation is not unique.

    Differs from: Horn's quaternion paper gives a symmetric scale; like evo and TUM we use
    Umeyama's (model -> data) least-squares scale.
    """
    model = _to_float64(model, "model")
    data = _to_float64(data, "data")
    if model.shape != data.shape or model.ndim != 2 or model.shape[1] != 3:
        raise ValueError(f"model and data must both be (N, 3), got {model.shape} and {data.shape}")
    if model.shape[0] < 3:
        raise ValueError(f"alignment needs at least 3 matched positions, got {model.shape[0]}")
    if not (np.isfinite(model).all() and np.isfinite(data).all()):
        raise ValueError("alignment inputs contain NaN or inf")
    mean_model, mean_data = model.mean(0), data.mean(0)
    model_c, data_c = model - mean_model, data - mean_data  # (N, 3)
    Sigma = data_c.T @ model_c / model.shape[0]  # (3, 3)
    U, D, Vt = np.linalg.svd(Sigma)
    if D[1] <= _SVD_RANK_EPS * max(D[0], 1e-300):
        raise ValueError(
            f"alignment is ambiguous: the {model.shape[0]} positions are collinear or coincident "
            f"(singular values {D}); use a longer trajectory"
        )
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ S @ Vt
    var_model = (model_c**2).sum(1).mean()
    s = float(np.trace(np.diag(D) @ S) / var_model) if with_scale else 1.0
    t = mean_data - s * R @ mean_model
    return R, t, s


# --------------------------------------------------------------------------------------------
# Trajectory metrics


def _stats(errors: np.ndarray, prefix: str, unit: str) -> Dict[str, float]:
    return {
        f"{prefix}_rmse_{unit}": float(np.sqrt(np.mean(errors**2))),
        f"{prefix}_mean_{unit}": float(np.mean(errors)),
        f"{prefix}_median_{unit}": float(np.median(errors)),
        f"{prefix}_std_{unit}": float(np.std(errors)),
        f"{prefix}_min_{unit}": float(np.min(errors)),
        f"{prefix}_max_{unit}": float(np.max(errors)),
    }


def ate(gt_poses, est_poses, with_scale: bool = False) -> Dict[str, object]:
    """Absolute trajectory error (TUM): translation of F_i = Q_i^-1 S P_i after Horn alignment.

    |trans(F_i)| = |s R p_i + t - q_i| with p_i, q_i the optical centres and S = (s, R, t) from
    :func:`horn_alignment` (estimate aligned onto ground truth).  Rotations do not enter ATE.

    Args:
        gt_poses: (N, 4, 4) ground-truth camera-to-world poses Q_i, matched to est_poses row by row.
        est_poses: (N, 4, 4) estimated camera-to-world poses P_i.
        with_scale: Sim(3) alignment instead of SE(3).

    Returns:
        dict with ``ate_rmse_m``, ``ate_mean_m``, ``ate_median_m``, ``ate_std_m``, ``ate_min_m``,
        ``ate_max_m``, ``errors_m`` (N,), ``alignment`` (4, 4) = [[sR, t], [0, 1]] (estimate world ->
        GT world), ``scale``, ``est_positions_aligned_m`` (N, 3).
    """
    gt_poses = _check_poses(gt_poses, "gt_poses")
    est_poses = _check_poses(est_poses, "est_poses")
    if gt_poses.shape != est_poses.shape:
        raise ValueError(f"gt_poses {gt_poses.shape} and est_poses {est_poses.shape} must match")
    R, t, s = horn_alignment(est_poses[:, :3, 3], gt_poses[:, :3, 3], with_scale)
    aligned = s * est_poses[:, :3, 3] @ R.T + t  # (N, 3)
    errors = np.linalg.norm(aligned - gt_poses[:, :3, 3], axis=1)
    alignment = np.eye(4)
    alignment[:3, :3], alignment[:3, 3] = s * R, t
    result: Dict[str, object] = _stats(errors, "ate", "m")
    result.update(errors_m=errors, alignment=alignment, scale=s, est_positions_aligned_m=aligned)
    return result


def _invert_rigid(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) rigid transforms -> inverses via R^T, -R^T t."""
    inverse = np.zeros_like(poses)
    rotation_t = np.swapaxes(poses[:, :3, :3], 1, 2)
    inverse[:, :3, :3] = rotation_t
    inverse[:, :3, 3] = -np.einsum("nij,nj->ni", rotation_t, poses[:, :3, 3])
    inverse[:, 3, 3] = 1.0
    return inverse


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """Angle |Log(R)| in degrees of (..., 3, 3) rotations, atan2 form (accurate near 0 and pi).

    angle = atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2).
    """
    rotations = np.asarray(rotations, np.float64)
    skew_part = np.stack(
        [
            rotations[..., 2, 1] - rotations[..., 1, 2],
            rotations[..., 0, 2] - rotations[..., 2, 0],
            rotations[..., 1, 0] - rotations[..., 0, 1],
        ],
        -1,
    )
    sin_angle = 0.5 * np.linalg.norm(skew_part, axis=-1)
    cos_angle = 0.5 * (np.trace(rotations, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sin_angle, cos_angle))


def rpe(gt_poses, est_poses, delta: int = 1, est_scale: float = 1.0) -> Dict[str, object]:
    """Relative pose error over a fixed frame interval (TUM RGB-D paper, "RPE").

    E_i = (Q_i^-1 Q_i+d)^-1 (P_i^-1 P_i+d) for every i = 0 .. N-1-d (all overlapping pairs, as
    TUM's evaluate_rpe.py); translational error |trans(E_i)|, rotational error angle(rot(E_i)).
    Invariant to any rigid transform applied to the whole estimate (so no alignment is needed).

    Args:
        gt_poses: (N, 4, 4) ground-truth camera-to-world poses Q_i, time ordered.
        est_poses: (N, 4, 4) estimated camera-to-world poses P_i, matched row by row.
        delta: interval d in frames (paper: 1).
        est_scale: multiplies estimated translations first (the Sim(3) scale from :func:`ate`).

    Returns:
        dict with ``rpe_trans_{rmse,mean,median,std,min,max}_m``,
        ``rpe_rot_{rmse,mean,median,std,min,max}_deg``, ``trans_errors_m`` (N-d,),
        ``rot_errors_deg`` (N-d,), ``delta_frames``.

    Differs from: evo's RPE uses non-overlapping pairs (0, d), (d, 2d), ... unless
    ``all_pairs=True``; for d = 1 both are the same.
    """
    gt_poses = _check_poses(gt_poses, "gt_poses")
    est_poses = _check_poses(est_poses, "est_poses")
    if gt_poses.shape != est_poses.shape:
        raise ValueError(f"gt_poses {gt_poses.shape} and est_poses {est_poses.shape} must match")
    if int(delta) != delta or delta < 1:
        raise ValueError(f"delta must be a positive integer number of frames, got {delta}")
    delta = int(delta)
    if gt_poses.shape[0] <= delta:
        raise ValueError(f"RPE with delta={delta} frames needs more than {delta} poses, got {gt_poses.shape[0]}")
    est_poses[:, :3, 3] *= est_scale  # est_poses is our own copy
    Q_rel = _invert_rigid(gt_poses[:-delta]) @ gt_poses[delta:]  # (N-d, 4, 4)
    P_rel = _invert_rigid(est_poses[:-delta]) @ est_poses[delta:]
    E = _invert_rigid(Q_rel) @ P_rel
    trans_errors = np.linalg.norm(E[:, :3, 3], axis=1)
    rot_errors = rotation_angle_deg(E[:, :3, :3])
    result: Dict[str, object] = _stats(trans_errors, "rpe_trans", "m")
    result.update(_stats(rot_errors, "rpe_rot", "deg"))
    result.update(trans_errors_m=trans_errors, rot_errors_deg=rot_errors, delta_frames=delta)
    return result


def trajectory_errors_over_time(
    gt_times, gt_poses, est_times, est_poses, max_diff: float = DEFAULT_MAX_DIFF_S,
    with_scale: bool = False, delta: int = 1,
) -> Dict[str, object]:
    """Associate by timestamp, then per-frame ATE and RPE errors (for plots) and all statistics.

    GT rows with NaN/inf (ScanNet's invalid poses) are dropped before association; a non-finite
    estimated pose is an error.  Matched pairs are in time order; RPE uses consecutive matched
    pairs (delta counts matched frames).

    Args:
        gt_times: (N,) float64 s.  gt_poses: (N, 4, 4) camera-to-world.
        est_times: (M,) float64 s.  est_poses: (M, 4, 4) camera-to-world.
        max_diff: association tolerance in s.  with_scale: Sim(3) alignment.  delta: RPE frames.

    Returns:
        :func:`ate` and :func:`rpe` entries plus ``times_s`` (K,) (estimate stamps),
        ``gt_index``/``est_index`` (K,), ``rpe_times_s`` (K-d,), ``n_matched``, ``n_gt``,
        ``n_est``, ``n_gt_nonfinite_dropped``, ``max_diff_s``.
    """
    gt_times, est_times = _check_times(gt_times, "gt_times"), _check_times(est_times, "est_times")
    gt_poses, est_poses = _check_poses(gt_poses, "gt_poses"), _check_poses(est_poses, "est_poses")
    for name, times, poses in (("gt", gt_times, gt_poses), ("est", est_times, est_poses)):
        if times.shape[0] != poses.shape[0]:
            raise ValueError(f"{name}_times has {times.shape[0]} rows but {name}_poses has {poses.shape[0]}")
    bad_est = np.flatnonzero(~np.isfinite(est_poses).all(axis=(1, 2)))
    if bad_est.size:
        raise ValueError(f"est_poses[{bad_est[0]}] (t = {est_times[bad_est[0]]:.6f} s) is not finite")
    finite_gt = np.flatnonzero(np.isfinite(gt_poses).all(axis=(1, 2)))
    if finite_gt.size == 0:
        raise ValueError("every ground-truth pose is NaN/inf; nothing to evaluate")
    idx_est, idx_gt_finite = associate(est_times, gt_times[finite_gt], max_diff)
    idx_gt = finite_gt[idx_gt_finite]
    result = ate(gt_poses[idx_gt], est_poses[idx_est], with_scale)
    result.update(rpe(gt_poses[idx_gt], est_poses[idx_est], delta, est_scale=result["scale"]))
    result.update(
        times_s=est_times[idx_est], gt_index=idx_gt, est_index=idx_est,
        rpe_times_s=est_times[idx_est][delta:], n_matched=int(idx_est.size),
        n_gt=int(gt_times.size), n_est=int(est_times.size),
        n_gt_nonfinite_dropped=int(gt_times.size - finite_gt.size), max_diff_s=float(max_diff),
    )
    return result


def evaluate_trajectory(
    gt_times, gt_poses, est_times, est_poses, max_diff: float = DEFAULT_MAX_DIFF_S,
    with_scale: bool = False, delta: int = 1,
) -> Dict[str, object]:
    """ATE and RPE of an estimated trajectory against ground truth, associated by timestamp.

    Same arguments as :func:`trajectory_errors_over_time`; returns only its scalar entries
    (``ate_rmse_m``, ``rpe_trans_rmse_m``, ``rpe_rot_rmse_deg``, ``n_matched``, ``scale`` ...)
    plus ``alignment`` (4, 4).
    """
    full = trajectory_errors_over_time(gt_times, gt_poses, est_times, est_poses, max_diff, with_scale, delta)
    return {k: v for k, v in full.items() if k == "alignment" or not isinstance(v, np.ndarray)}


# --------------------------------------------------------------------------------------------
# Reconstruction: culling (Co-SLAM cull_mesh.py), 3-D metrics (eval_recon.py), Depth L1


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
    vertices_world = _to_float64(vertices_world, "vertices")
    faces = np.asarray(faces, np.int64)
    u, v, z = _project(vertices_world, _to_float64(pose_c2w, "pose_c2w"), fx, fy, cx, cy)
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
    """Remove the triangles no camera saw (Co-SLAM ``cull_mesh.py``, shared/spec/coslam.md §6.2).

    A triangle is kept if one of its vertices is in the frustum of some camera (OpenCV projection,
    0 <= u <= W-1, 0 <= v <= H-1, z > 0) and, unless ``frustum_only``, one vertex is also not
    occluded for some camera: z_vertex < D(u, v) + occlusion_eps at the nearest pixel centre.  D is
    ``depths[k]`` when given (sensor or GT depth), else a z-buffer of this mesh rendered by
    :func:`render_depth_zbuffer`; a pixel with no depth (hole, background) observes nothing.

    Args:
        mesh: triangle mesh (not modified).
        poses_c2w: (F, 4, 4) camera-to-world poses; non-finite poses are skipped.
        intrinsics: (fx, fy, cx, cy, width, height) of the raw images.
        depths: optional (F, H, W) depth maps in m.
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
        depths = _to_float64(depths, "depths")
        if depths.shape != (poses_c2w.shape[0], height, width):
            raise ValueError(f"depths must be (F, H, W) = {(poses_c2w.shape[0], height, width)}, got {depths.shape}")
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


def depth_l1(rendered_depth, reference_depth, valid=None) -> float:
    """Depth L1 in m: mean |rendered - reference| over pixels where reference > 0 and finite.

    Args:
        rendered_depth: (..., H, W) depth in m (numpy or torch).
        reference_depth: same shape, sensor/GT depth in m; 0 or non-finite = missing.
        valid: optional bool mask of the same shape, ANDed with the reference test.

    Raises:
        ValueError: shape mismatch, no valid pixel, or a non-finite rendered depth at a valid pixel.
    """
    rendered = _to_float64(rendered_depth, "rendered_depth")
    reference = _to_float64(reference_depth, "reference_depth")
    if rendered.shape != reference.shape:
        raise ValueError(f"rendered_depth {rendered.shape} and reference_depth {reference.shape} must match")
    mask = np.isfinite(reference) & (reference > 0)
    if valid is not None:
        valid = _to_float64(valid, "valid").astype(bool)
        if valid.shape != mask.shape:
            raise ValueError(f"valid mask {valid.shape} must match depth shape {mask.shape}")
        mask &= valid
    if not mask.any():
        raise ValueError("depth_l1: no pixel has a valid (finite, > 0) reference depth")
    if not np.isfinite(rendered[mask]).all():
        raise ValueError("depth_l1: rendered depth is NaN/inf at pixels with a valid reference")
    return float(np.abs(rendered[mask] - reference[mask]).mean())


# --------------------------------------------------------------------------------------------
# Files and command line


def _load_mesh(path: str) -> trimesh.Trimesh:
    if not os.path.isfile(path):
        raise ValueError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds of errors for bad files
        raise ValueError(f"{path}: cannot read a triangle mesh ({error})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: contains no triangles")
    return mesh


def _print_result(result: Dict[str, object], keys: Sequence[str], as_json: bool) -> None:
    chosen = {key: result[key] for key in keys}
    if as_json:
        print(json.dumps(chosen))
    else:
        for key, value in chosen.items():
            print(f"{key}: {value:.6f}" if isinstance(value, float) else f"{key}: {value}")


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m tsslam_ref.eval trajectory GT EST`` or ``... mesh REC GT``; bad input -> exit 2."""
    from tsslam_ref.cli_args import OneLineParser, number_in

    parser = OneLineParser(prog="python -m tsslam_ref.eval", description=__doc__.split("\n")[0],
                           epilog="Exit status: 0 done, 2 bad input (one line naming the file and what was expected).")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    trajectory = commands.add_parser("trajectory", help="ATE/RPE of EST against GT (TUM format files)")
    trajectory.add_argument("gt", help="ground truth, 'timestamp tx ty tz qx qy qz qw' per line")
    trajectory.add_argument("est", help="estimate, same format, camera-to-world; one line per time stamp")
    trajectory.add_argument("--max-diff", type=number_in("--max-diff", 0, 10, low_open=True), default=DEFAULT_MAX_DIFF_S,
                            help="association tolerance (s), in (0, 10]")
    trajectory.add_argument("--scale", action="store_true", help="Sim(3) alignment (estimate scale)")
    trajectory.add_argument("--delta", type=number_in("--delta", 1, 10**9, integer=True), default=1,
                            help="RPE interval in frames, >= 1")
    trajectory.add_argument("--json", action="store_true", help="print one JSON object")
    mesh = commands.add_parser("mesh", help="accuracy/completion of REC against GT meshes")
    mesh.add_argument("rec")
    mesh.add_argument("gt")
    mesh.add_argument("--threshold", type=number_in("--threshold", 0, 100, low_open=True), default=0.05,
                      help="completion-ratio threshold (m), in (0, 100]")
    mesh.add_argument("--points", type=number_in("--points", 1, 10**8, integer=True), default=200_000,
                      help="surface samples per mesh, 1 to 1e8")
    mesh.add_argument("--seed", type=number_in("--seed", 0, 2**63 - 1, integer=True), default=0)
    mesh.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    try:
        if args.command == "trajectory":
            gt_times, gt_poses = read_tum_trajectory(args.gt)
            est_times, est_poses = read_tum_trajectory(args.est, unique_stamps=True)  # one pose per frame
            result = evaluate_trajectory(
                gt_times, gt_poses, est_times, est_poses, args.max_diff, args.scale, args.delta
            )
            keys = ["ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "n_matched", "scale"]
        else:
            result = mesh_metrics(_load_mesh(args.rec), _load_mesh(args.gt), args.points, args.threshold, args.seed)
            keys = ["accuracy_m", "completion_m", "completion_ratio", "threshold_m", "n_points"]
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    _print_result(result, keys, args.json)
    return 0


if __name__ == "__main__":
    from tsslam_ref.cli_args import interruptible

    sys.exit(interruptible(main, "python -m tsslam_ref.eval"))
