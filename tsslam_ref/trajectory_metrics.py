"""Trajectory metrics: timestamp association, Horn alignment, ATE and RPE.

TS-SLAM §IV-A "Metrics" (tables `tab:scannet_track`, `tab:tum_track`, `tab:syn`, `tab:ablation`):
ATE RMSE after Horn alignment and RPE RMSE over a fixed interval of 1 frame.  Formulas follow the
TUM RGB-D paper (Sturm et al., IROS 2012) in its notation.

Side layer (numpy; torch only to read tensors; :mod:`tsslam_ref.geometry` for pose inversion and
rotation angles).  Taught in notebooks/08_evaluation.ipynb; protocol and deviations in
docs/evaluation.md; ``python -m tsslam_ref.eval trajectory`` is the command line.

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| Q_i | ``gt_poses[i]`` | (N, 4, 4) | camera-to-world (GT world) | m |
| P_i | ``est_poses[i]`` | (N, 4, 4) | camera-to-world (estimate's world) | m |
| S = (s, R, t) | ``alignment`` | (4, 4) | estimate's world -> GT world | m |
| F_i = Q_i^-1 S P_i | ATE residual, only its translation is used | (N,) | - | m |
| E_i = (Q_i^-1 Q_i+d)^-1 (P_i^-1 P_i+d) | RPE residual | (N-d,) | - | m, deg |

Conventions: inputs may be numpy arrays or torch tensors on any device; they are copied to float64
numpy (evaluation is bookkeeping, not part of any autograd graph) and never modified.  Timestamps
are float64 seconds.  Every returned key carries its unit (``_m``, ``_deg``, ``_s``) or is a count
or a ratio in [0, 1].
"""

from typing import Dict, Tuple

import numpy as np
import torch

from tsslam_ref.geometry import invert_pose, rotation_angle_deg
from tsslam_ref.times import float64_seconds

DEFAULT_MAX_DIFF_S = 0.01
"""Association tolerance in seconds (evo's default; TUM's associate.py uses 0.02)."""
_SVD_RANK_EPS = 1e-12
"""Singular values below this (relative) make the alignment ambiguous (collinear points)."""
_COINCIDENT_EPS = 1e-12
"""Points whose RMS spread about their mean is below this times their largest coordinate are one
point (a camera standing still): float64 rounding alone leaves a spread near 1e-16 of it."""


def _coincident(points: np.ndarray) -> bool:
    """(N, 3) points all at one place, up to rounding (:data:`_COINCIDENT_EPS`)."""
    spread = float(np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean()))
    return spread <= _COINCIDENT_EPS * max(float(np.abs(points).max(initial=0.0)), 1e-300)


# --------------------------------------------------------------------------------------------
# Input handling


def _to_float64(array) -> np.ndarray:
    """numpy copy in float64 of a numpy array / torch tensor / sequence (inputs are never mutated)."""
    if isinstance(array, torch.Tensor):
        return array.detach().numpy(force=True).astype(np.float64, copy=True)
    return np.array(array, dtype=np.float64, copy=True)


def _check_poses(poses, name: str) -> np.ndarray:
    poses = _to_float64(poses)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (N, 4, 4), got {poses.shape}")
    return poses


def _check_times(times, name: str) -> np.ndarray:
    times = float64_seconds(times, name)
    if times.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {times.shape}")
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] = {times[bad[0]]} is not a finite timestamp in seconds")
    return times


# --------------------------------------------------------------------------------------------
# Association and alignment


def associate(times_a, times_b, max_diff: float = 0.02,
              names: Tuple[str, str] = ("times_a", "times_b")) -> Tuple[np.ndarray, np.ndarray]:
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
            f"no timestamps within max_diff={max_diff} s: {names[0]} spans "
            f"[{times_a.min() if times_a.size else np.nan:.6f}, {times_a.max() if times_a.size else np.nan:.6f}] s, "
            f"{names[1]} spans [{times_b.min() if times_b.size else np.nan:.6f}, "
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
        ValueError: shape mismatch, fewer than 3 points, or non-finite values.

    Points that do not span a plane (collinear, e.g. a camera on a rail, or coincident, a static
    camera) leave the rotation about their line free; this returns one minimiser, and the
    residuals' lengths (hence ATE) and s are the same for all of them (:func:`alignment_is_unique`).
    A model that does not move at all leaves s free too (any s gives the same ATE): s = 1 then.

    Differs from: Horn's quaternion paper gives a symmetric scale; like evo and TUM we use
    Umeyama's (model -> data) least-squares scale.
    """
    model = _to_float64(model)
    data = _to_float64(data)
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
    S = np.diag([1.0, 1.0, 1.0 if np.linalg.det(U) * np.linalg.det(Vt) > 0 else -1.0])
    R = U @ S @ Vt
    var_model = (model_c**2).sum(1).mean()
    s = float(np.trace(np.diag(D) @ S) / var_model) if with_scale and not _coincident(model) else 1.0
    t = mean_data - s * R @ mean_model
    return R, t, s


def alignment_is_unique(model, data) -> bool:
    """True when the rotation of :func:`horn_alignment` is unique: the cross-covariance of the
    centred points has rank >= 2 (neither point set collinear or coincident)."""
    model, data = _to_float64(model), _to_float64(data)
    if _coincident(model) or _coincident(data):  # D is rounding noise then
        return False
    model_c, data_c = model - model.mean(0), data - data.mean(0)
    D = np.linalg.svd(data_c.T @ model_c / model_c.shape[0], compute_uv=False)
    return bool(D[1] > _SVD_RANK_EPS * max(D[0], 1e-300))


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
        GT world), ``scale``, ``est_positions_aligned_m`` (N, 3), ``alignment_unique`` (False
        for collinear or coincident positions: ATE is still exact, the alignment one of many).
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
    result.update(errors_m=errors, alignment=alignment, scale=s, est_positions_aligned_m=aligned,
                  alignment_unique=alignment_is_unique(est_poses[:, :3, 3], gt_poses[:, :3, 3]))
    return result


def _invert(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) float64 rigid transforms -> their inverses (:func:`geometry.invert_pose`)."""
    return invert_pose(torch.from_numpy(poses)).numpy()


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
    if not (np.isfinite(gt_poses).all() and np.isfinite(est_poses).all()):
        raise ValueError("RPE inputs contain NaN or inf (drop the frames without a pose first)")
    if gt_poses.shape[0] <= delta:
        raise ValueError(f"RPE with delta={delta} frames needs more than {delta} poses, got {gt_poses.shape[0]}")
    est_poses[:, :3, 3] *= est_scale  # est_poses is our own copy
    Q_rel = _invert(gt_poses[:-delta]) @ gt_poses[delta:]  # (N-d, 4, 4)
    P_rel = _invert(est_poses[:-delta]) @ est_poses[delta:]
    E = _invert(Q_rel) @ P_rel
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
    idx_est, idx_gt_finite = associate(est_times, gt_times[finite_gt], max_diff, ("the estimate", "the ground truth"))
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
