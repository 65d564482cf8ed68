"""Tests for tsslam_ref.eval (TS-SLAM §IV-A metrics).

Oracles: planted truth (known SE(3)/Sim(3), known noise, known jumps), evo (APE/RPE, an independent
implementation), scipy's Rotation.align_vectors, analytic distances between parallel planes and
concentric spheres, a half-covered plane and a far extra plane (with the Poisson nearest-neighbour
correction), analytic depth of planes.
"""

import json
import numpy as np
import pytest
import torch
import trimesh
from scipy import integrate, optimize
from scipy.spatial.transform import Rotation

from tsslam_ref import eval as ev
from tsslam_ref.data import write_tum_trajectory
from tsslam_ref.geometry import pose_to_tum, tum_to_pose

FR2_DESK = "trajectories/tum_rgbd_fr2_desk_groundtruth.txt"


# ------------------------------------------------------------------------------------------
# helpers (test-side, independent of the module under test)


def load_tum(path):
    """Read a TUM file with numpy.loadtxt (independent of the package reader)."""
    table = np.loadtxt(path, comments="#")
    return table[:, 0], tum_to_pose(table[:, 1:])


def random_rigid(rng, translation_scale=2.0):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    pose[:3, 3] = rng.normal(size=3) * translation_scale
    return pose


def perturb(poses, rng, sigma_m, sigma_rad):
    """Add isotropic position noise (m) and random small rotations (rad) to (N, 4, 4) poses."""
    noisy = poses.copy()
    noisy[:, :3, 3] += rng.normal(scale=sigma_m, size=(len(poses), 3))
    delta = Rotation.from_rotvec(rng.normal(scale=sigma_rad, size=(len(poses), 3))).as_matrix()
    noisy[:, :3, :3] = poses[:, :3, :3] @ delta
    return noisy


@pytest.fixture(scope="module")
def fr2_desk(shared_data):
    times, poses = load_tum(shared_data / FR2_DESK)
    return times, poses


# ------------------------------------------------------------------------------------------
# Horn / Umeyama alignment


@pytest.mark.parametrize("with_scale", [False, True])
def test_horn_alignment_recovers_planted_similarity(with_scale):
    rng = np.random.default_rng(1)
    model = rng.normal(size=(50, 3))
    true_R = Rotation.random(random_state=rng).as_matrix()
    true_t = rng.normal(size=3)
    true_s = 1.7 if with_scale else 1.0
    data = true_s * model @ true_R.T + true_t
    R, t, s = ev.horn_alignment(model, data, with_scale=with_scale)
    np.testing.assert_allclose(R, true_R, atol=1e-12)
    np.testing.assert_allclose(t, true_t, atol=1e-12)
    assert s == pytest.approx(true_s, abs=1e-12)


def test_horn_alignment_rotation_matches_scipy_align_vectors():
    rng = np.random.default_rng(2)
    model = rng.normal(size=(200, 3)) * [3.0, 1.0, 0.3]
    data = model @ Rotation.random(random_state=rng).as_matrix().T + rng.normal(scale=0.2, size=(200, 3))
    R, t, _ = ev.horn_alignment(model, data)
    # scipy: rotation C minimising sum |a_i - C b_i|^2 on the centred sets (a = data, b = model)
    scipy_R = Rotation.align_vectors(data - data.mean(0), model - model.mean(0))[0].as_matrix()
    np.testing.assert_allclose(R, scipy_R, atol=1e-10)
    np.testing.assert_allclose(t, data.mean(0) - R @ model.mean(0), atol=1e-12)


def test_horn_alignment_is_a_least_squares_minimum():
    rng = np.random.default_rng(3)
    model = rng.normal(size=(100, 3))
    data = 0.8 * model @ Rotation.random(random_state=rng).as_matrix().T + rng.normal(scale=0.3, size=(100, 3))
    R, t, s = ev.horn_alignment(model, data, with_scale=True)

    def cost(R_, t_, s_):
        return np.sum((s_ * model @ R_.T + t_ - data) ** 2)

    best = cost(R, t, s)
    for _ in range(20):
        dR = Rotation.from_rotvec(rng.normal(scale=1e-3, size=3)).as_matrix()
        assert cost(dR @ R, t, s) > best
        assert cost(R, t + rng.normal(scale=1e-3, size=3), s) > best
        assert cost(R, t, s * (1 + rng.normal(scale=1e-3))) > best


def test_horn_alignment_of_a_mirror_image_is_the_best_proper_rotation_and_its_scale():
    """A mirror image (z -> -z) of the data: the unconstrained SVD solution U V^T is then a
    reflection (det -1), which no trajectory can undergo.  Oracles: scipy's Rotation.align_vectors
    (best proper rotation of the centred sets) for R; for that R the least-squares scale, from
    d/ds sum |s R m'_i - d'_i|^2 = 0, is s = sum d'_i . R m'_i / sum |m'_i|^2."""
    rng = np.random.default_rng(21)
    data = rng.normal(size=(60, 3)) * [2.0, 1.0, 0.5]
    model = 0.6 * data * [1.0, 1.0, -1.0] + rng.normal(scale=0.05, size=(60, 3))
    model_c, data_c = model - model.mean(0), data - data.mean(0)
    scipy_R = Rotation.align_vectors(data_c, model_c)[0].as_matrix()
    for with_scale in (False, True):
        R, t, s = ev.horn_alignment(model, data, with_scale=with_scale)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(R, scipy_R, atol=1e-10)
        expected_s = np.sum(data_c * (model_c @ R.T)) / np.sum(model_c**2) if with_scale else 1.0
        assert s == pytest.approx(expected_s, rel=1e-12)
        np.testing.assert_allclose(t, data.mean(0) - s * R @ model.mean(0), atol=1e-12)


def _poses_at(positions):
    poses = np.tile(np.eye(4), (len(positions), 1, 1))
    poses[:, :3, 3] = positions
    return poses


def test_ate_of_a_camera_on_a_rail_or_standing_still_is_the_least_squares_minimum():
    """Collinear or coincident ground truth (a rail, a static camera): the rotation about the line
    is free but ATE is not.  Oracle: a rigid copy has ATE 0; else a numerical minimisation of the
    same cost over rotation vector and translation from many starts."""
    rng = np.random.default_rng(3)
    line = np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0])
    copy = line @ Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix().T + [0.5, -1.0, 2.0]
    result = ev.ate(_poses_at(line), _poses_at(copy))
    assert result["ate_rmse_m"] < 1e-12 and result["alignment_unique"] is False
    for gt_positions in (line, np.zeros((10, 3)) + [1.0, 2.0, 3.0]):  # a rail; a static camera
        estimate = gt_positions + rng.normal(scale=0.05, size=(10, 3))

        def cost(x):
            moved = estimate @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:]
            return np.sqrt(np.mean(np.sum((moved - gt_positions) ** 2, axis=1)))

        best = min(optimize.minimize(cost, start, method="Powell", options={"xtol": 1e-10, "ftol": 1e-14}).fun
                   for start in np.concatenate([rng.normal(size=(12, 6)), np.zeros((1, 6))]))
        result = ev.ate(_poses_at(gt_positions), _poses_at(estimate))
        assert result["ate_rmse_m"] == pytest.approx(best, rel=1e-6) and not result["alignment_unique"]
    spread = rng.normal(size=(10, 3))
    assert ev.ate(_poses_at(spread), _poses_at(spread + rng.normal(scale=0.05, size=(10, 3))))["alignment_unique"] is True
    with pytest.raises(ValueError, match="at least 3"):
        ev.horn_alignment(np.zeros((2, 3)), np.zeros((2, 3)))
    assert ev.horn_alignment(np.zeros((4, 3)), line[:4], with_scale=True)[2] == 1.0  # no 0 / 0
    # an estimate standing still away from the origin: rounding leaves a spread of 1e-16 of its
    # coordinates, which made a "scale" out of noise; every scale gives the same ATE, s = 1 is reported
    still = np.full((10, 3), [1.0, 2.0, 3.0]) + np.array([1e-16, 0.0, 0.0]) * np.arange(10)[:, None]
    moving = line + [0.5, 0.0, 0.0]
    result = ev.ate(_poses_at(moving), _poses_at(still), with_scale=True)
    assert result["scale"] == 1.0 and not result["alignment_unique"]
    centred = moving - moving.mean(0)
    assert result["ate_rmse_m"] == pytest.approx(np.sqrt((centred ** 2).sum(1).mean()), rel=1e-9)  # best: the mean


def test_alignment_of_a_planar_trajectory_is_unique():
    """A ground robot's positions lie in a plane: two independent directions fix a rotation, so
    the alignment is unique (only a line or a point leaves it free).  Oracle: the planted rotation
    about z and translation of a rigid copy are recovered."""
    rng = np.random.default_rng(22)
    planar = np.column_stack([rng.normal(size=(20, 2)), np.zeros(20)])
    planted = Rotation.from_rotvec([0.0, 0.0, 0.7]).as_matrix()
    estimate = planar @ planted.T + [0.3, -0.2, 0.0]  # what the estimate saw; GT = planted^-1 (est - t)
    result = ev.ate(_poses_at(planar), _poses_at(estimate))
    assert result["alignment_unique"] is True and result["ate_rmse_m"] < 1e-12
    np.testing.assert_allclose(result["alignment"][:3, :3], planted.T, atol=1e-12)


def test_rpe_statistics_by_hand_in_metres_and_degrees():
    """Consecutive-pair errors of 1, 2, 3, 4, 5 cm (a sideways step added to each move) and, on a
    camera turning in place, 1, 2, 3, 4, 5 degrees (added yaw per frame).  By hand for e = 1..5:
    mean 3, median 3, RMSE sqrt(55 / 5) = sqrt(11), std sqrt(2) (population, numpy's and evo's;
    the sample std would be sqrt(2.5)), min 1, max 5."""
    steps = np.arange(1.0, 6.0)
    gt = _poses_at(np.outer(np.arange(6.0), [1.0, 0.0, 0.0]))
    est = _poses_at(np.column_stack([np.arange(6.0), np.concatenate([[0.0], np.cumsum(0.01 * steps)]), np.zeros(6)]))
    turning = np.tile(np.eye(4), (6, 1, 1))
    turning[:, :3, :3] = Rotation.from_euler("z", np.concatenate([[0.0], np.cumsum(steps)])[:, None], degrees=True).as_matrix()
    by_hand = {"rmse": np.sqrt(11.0), "mean": 3.0, "median": 3.0, "std": np.sqrt(2.0), "min": 1.0, "max": 5.0}
    trans = ev.rpe(gt, est)
    rot = ev.rpe(np.tile(np.eye(4), (6, 1, 1)), turning)
    np.testing.assert_allclose(trans["trans_errors_m"], 0.01 * steps, atol=1e-12)
    np.testing.assert_allclose(rot["rot_errors_deg"], steps, atol=1e-9)
    for stat, value in by_hand.items():
        assert trans[f"rpe_trans_{stat}_m"] == pytest.approx(0.01 * value, abs=1e-12), stat
        assert rot[f"rpe_rot_{stat}_deg"] == pytest.approx(value, abs=1e-9), stat
    assert rot["rpe_trans_max_m"] < 1e-12 and trans["rpe_rot_max_deg"] < 1e-9


def test_rpe_refuses_missing_poses_as_ate_does():
    poses = _poses_at(np.random.default_rng(4).normal(size=(5, 3)))
    holed = poses.copy()
    holed[2] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        ev.rpe(holed, poses)


# ------------------------------------------------------------------------------------------
# ATE / RPE planted truth on a real trajectory


def test_ate_planted_se3_and_sim3_align_back_to_zero(fr2_desk):
    _, gt = fr2_desk
    gt = gt[::10]
    rng = np.random.default_rng(4)
    world_change = random_rigid(rng)
    est = world_change @ gt  # same trajectory, expressed in another world frame
    result = ev.ate(gt, est)
    assert result["ate_rmse_m"] < 1e-9 and result["ate_max_m"] < 1e-9
    np.testing.assert_allclose(result["alignment"], np.linalg.inv(world_change), atol=1e-9)

    scaled = est.copy()
    scaled[:, :3, 3] *= 0.37  # Sim(3): the estimate has the wrong scale
    assert ev.ate(gt, scaled)["ate_rmse_m"] > 0.05  # SE(3) alignment cannot absorb it
    result = ev.ate(gt, scaled, with_scale=True)
    assert result["ate_rmse_m"] < 1e-9
    assert result["scale"] == pytest.approx(1 / 0.37, rel=1e-9)


def test_ate_of_isotropic_noise_is_sqrt3_sigma(fr2_desk):
    """E|e|^2 = 3 sigma^2 (1 - 2/N) after fitting 6 dof; RMSE has ~0.6% std for N = 4000."""
    _, gt = fr2_desk
    gt = gt[::5]
    rng = np.random.default_rng(5)
    sigma = 0.02
    est = random_rigid(rng) @ perturb(gt, rng, sigma, 0.0)
    result = ev.ate(gt, est)
    expected = np.sqrt(3 * sigma**2 * (1 - 2 / len(gt)))
    assert result["ate_rmse_m"] == pytest.approx(expected, rel=0.03)
    assert result["ate_mean_m"] < result["ate_rmse_m"] < result["ate_max_m"]
    # the mean of a chi(3) variable: sigma * 2 sqrt(2/pi)
    assert result["ate_mean_m"] == pytest.approx(sigma * 2 * np.sqrt(2 / np.pi), rel=0.03)


def test_rpe_is_invariant_to_a_global_rigid_transform(fr2_desk):
    _, gt = fr2_desk
    gt = gt[:3000:3]
    rng = np.random.default_rng(6)
    est = perturb(gt, rng, 0.01, 0.01)
    base = ev.rpe(gt, est)
    moved = ev.rpe(gt, random_rigid(rng) @ est)
    assert base["rpe_trans_rmse_m"] > 1e-3
    np.testing.assert_allclose(moved["trans_errors_m"], base["trans_errors_m"], atol=1e-10)
    np.testing.assert_allclose(moved["rot_errors_deg"], base["rot_errors_deg"], atol=1e-8)


def test_rpe_sees_a_single_translation_jump_and_a_single_rotation_jump(fr2_desk):
    _, gt = fr2_desk
    gt = gt[:2000:4]
    n, k = len(gt), 200
    jump = np.eye(4)
    jump[:3, 3] = [0.03, -0.04, 0.0]  # 5 cm in the world frame from frame k on
    est = gt.copy()
    est[k:] = jump @ gt[k:]
    result = ev.rpe(gt, est)
    expected = np.zeros(n - 1)
    expected[k - 1] = 0.05
    np.testing.assert_allclose(result["trans_errors_m"], expected, atol=1e-12)
    np.testing.assert_allclose(result["rot_errors_deg"], 0.0, atol=1e-6)
    assert result["rpe_trans_rmse_m"] == pytest.approx(0.05 / np.sqrt(n - 1), rel=1e-9)

    twist = np.eye(4)
    twist[:3, :3] = Rotation.from_rotvec(np.radians(3.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    est = gt.copy()
    est[k:] = twist @ gt[k:]
    result = ev.rpe(gt, est)
    expected_deg = np.zeros(n - 1)
    expected_deg[k - 1] = 3.0
    np.testing.assert_allclose(result["rot_errors_deg"], expected_deg, atol=1e-9)
    assert np.count_nonzero(result["trans_errors_m"] > 1e-9) == 1


# ------------------------------------------------------------------------------------------
# Cross-check against evo


def _evo_numbers(ref_times, ref_poses, est_times, est_poses, with_scale, delta):
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    ref = PoseTrajectory3D(poses_se3=list(ref_poses), timestamps=ref_times)
    est = PoseTrajectory3D(poses_se3=list(est_poses), timestamps=est_times)
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    est.align(ref, correct_scale=with_scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    numbers = {"n_matched": ref.num_poses, "ate_rmse_m": ape.get_statistic(metrics.StatisticsType.rmse)}
    for relation, key in (
        (metrics.PoseRelation.translation_part, "rpe_trans_rmse_m"),
        (metrics.PoseRelation.rotation_angle_deg, "rpe_rot_rmse_deg"),
    ):
        rpe = metrics.RPE(relation, delta=delta, delta_unit=metrics.Unit.frames, all_pairs=True)
        rpe.process_data((ref, est))
        numbers[key] = rpe.get_statistic(metrics.StatisticsType.rmse)
    return numbers


@pytest.mark.parametrize("with_scale,delta", [(False, 1), (True, 1), (False, 3)])
def test_matches_evo_on_a_real_trajectory(fr2_desk, with_scale, delta):
    gt_times, gt_poses = fr2_desk
    gt_times, gt_poses = gt_times[:6000], gt_poses[:6000]  # ~28 s of fr2/desk
    rng = np.random.default_rng(8)
    pick = np.arange(0, len(gt_times), 10)
    est_poses = random_rigid(rng) @ perturb(gt_poses[pick], rng, 0.01, np.radians(0.5))
    if with_scale:
        est_poses[:, :3, 3] *= 1.3
    est_times = gt_times[pick] + rng.uniform(-0.004, 0.004, size=pick.size)
    ours = ev.evaluate_trajectory(gt_times, gt_poses, est_times, est_poses, max_diff=0.01,
                                  with_scale=with_scale, delta=delta)
    theirs = _evo_numbers(gt_times, gt_poses, est_times, est_poses, with_scale, delta)
    assert ours["n_matched"] == theirs["n_matched"] == pick.size
    for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg"):
        assert ours[key] == pytest.approx(theirs[key], abs=1e-6), key
    assert ours["ate_rmse_m"] > 0.005 and ours["rpe_rot_rmse_deg"] > 0.1  # non-trivial numbers


# ------------------------------------------------------------------------------------------
# Association and bookkeeping


def test_associate_is_one_to_one_nearest_first():
    # by hand: candidates (a1,b0)=1ms, (a0,b0)=3ms, (a1,b1)=8ms; (a0,b1)=12ms is too far
    idx_a, idx_b = ev.associate([0.0, 0.004], [0.003, 0.012], max_diff=0.01)
    assert idx_a.tolist() == [1] and idx_b.tolist() == [0]
    # the tolerance is inclusive and strict beyond it: 9 ms pairs, 11 ms does not
    idx_a, idx_b = ev.associate([0.0, 1.0, 2.0], [0.009, 1.011, 1.9905], max_diff=0.01)
    assert idx_a.tolist() == [0, 2] and idx_b.tolist() == [0, 2]


def test_associate_pairs_a_difference_of_exactly_max_diff():
    """Binary-exact stamps: |1.25 - 1.0| = 0.25 equals max_diff and pairs (<=, as evo and the
    docstring say); every other difference is 0.5 and does not."""
    idx_a, idx_b = ev.associate([0.0, 1.0], [0.5, 1.25], max_diff=0.25)
    assert idx_a.tolist() == [1] and idx_b.tolist() == [1]


def test_associate_handles_unsorted_input_like_sorted_input():
    rng = np.random.default_rng(9)
    times_a = np.sort(rng.uniform(0, 10, 300)) + 1.3e9
    times_b = times_a[::2] + rng.uniform(-0.005, 0.005, 150)
    sorted_pairs = set(zip(*ev.associate(times_a, times_b, 0.01)))
    perm_a, perm_b = rng.permutation(300), rng.permutation(150)
    idx_a, idx_b = ev.associate(times_a[perm_a], times_b[perm_b], 0.01)
    assert set(zip(perm_a[idx_a], perm_b[idx_b])) == sorted_pairs
    assert np.all(np.diff(times_a[perm_a][idx_a]) >= 0)  # returned in time order
    assert len(sorted_pairs) == 150


def test_associate_errors_are_actionable():
    with pytest.raises(ValueError, match="no timestamps within max_diff"):
        ev.associate([1.0, 2.0], [1000.0, 2000.0], 0.02)
    with pytest.raises(ValueError, match=r"times_b\[1\]"):
        ev.associate([1.0, 2.0], [1.0, np.nan])


@pytest.mark.parametrize("make", [lambda t: torch.tensor(t.tolist()), lambda t: t.astype(np.float32),
                                  lambda t: list(t.astype(np.float32))], ids=["tensor", "array", "list"])
def test_float32_stamps_are_refused_before_they_pair_every_pose_with_one_stamp(make):
    """TUM stamps in float32 round to one value (spacing 128 s at 1.34e9 s): refused, naming the argument."""
    stamps = 1341841873.0 + np.arange(10) / 30.0
    assert len(np.unique(stamps.astype(np.float32))) == 1  # the loss the check guards against
    poses = np.tile(np.eye(4), (10, 1, 1))
    with pytest.raises(TypeError, match="est_times must be float64 seconds"):
        ev.evaluate_trajectory(stamps, poses, make(stamps), poses)
    with pytest.raises(TypeError, match="times_b must be float64 seconds"):
        ev.associate(stamps, make(stamps))
    with pytest.raises(TypeError, match="timestamps must be float64 seconds"):
        write_tum_trajectory("never_written.txt", make(stamps), poses)


def test_evaluate_trajectory_drops_nonfinite_gt_rows(fr2_desk):
    gt_times, gt_poses = fr2_desk
    gt_times, gt_poses = gt_times[:3000:3].copy(), gt_poses[:3000:3].copy()
    rng = np.random.default_rng(10)
    est = perturb(gt_poses, rng, 0.01, 0.005)
    invalid = np.zeros(len(gt_times), bool)
    invalid[[5, 6, 500, 900]] = True
    gt_with_nan = gt_poses.copy()
    gt_with_nan[invalid] = np.nan
    result = ev.evaluate_trajectory(gt_times, gt_with_nan, gt_times, est, max_diff=1e-6)
    reference = ev.ate(gt_poses[~invalid], est[~invalid])
    assert result["n_gt_nonfinite_dropped"] == 4 and result["n_matched"] == (~invalid).sum()
    assert result["ate_rmse_m"] == pytest.approx(reference["ate_rmse_m"], abs=1e-12)
    with pytest.raises(ValueError, match=r"est_poses\[3\]"):
        est_bad = est.copy()
        est_bad[3, 0, 3] = np.inf
        ev.evaluate_trajectory(gt_times, gt_poses, gt_times, est_bad)


def test_metrics_do_not_mutate_inputs_and_accept_torch(fr2_desk):
    _, gt = fr2_desk
    gt = gt[:1000:5]
    est = perturb(gt, np.random.default_rng(11), 0.01, 0.01)
    gt_copy, est_copy = gt.copy(), est.copy()
    numpy_result = ev.rpe(gt, est, est_scale=2.0)
    ev.ate(gt, est, with_scale=True)
    np.testing.assert_array_equal(gt, gt_copy)
    np.testing.assert_array_equal(est, est_copy)
    torch_result = ev.rpe(torch.from_numpy(gt).float(), torch.from_numpy(est).float(), est_scale=2.0)
    assert torch_result["rpe_trans_rmse_m"] == pytest.approx(numpy_result["rpe_trans_rmse_m"], rel=1e-4)


# ------------------------------------------------------------------------------------------
# Reconstruction metrics


def plane_patch(half_size, z):
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) * [half_size, half_size, 1]
    vertices[:, 2] = z
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)


def expected_nn_distance(offset, density):
    """E sqrt(offset^2 + r^2), r = distance to the nearest point of a 2-D Poisson process."""
    pdf = lambda r: 2 * np.pi * density * r * np.exp(-np.pi * density * r**2)  # noqa: E731
    return integrate.quad(lambda r: np.sqrt(offset**2 + r**2) * pdf(r), 0, np.inf, limit=200)[0]


@pytest.mark.parametrize("offset", [0.0, 0.02])
def test_mesh_metrics_parallel_planes(offset):
    n_points = 100_000
    gt = plane_patch(1.0, 0.0)
    rec = plane_patch(1.0, offset)
    result = ev.mesh_metrics(rec, gt, n_points=n_points, threshold=0.05, seed=0)
    expected = expected_nn_distance(offset, n_points / 4.0)
    assert result["accuracy_m"] == pytest.approx(expected, rel=0.02)
    assert result["completion_m"] == pytest.approx(expected, rel=0.02)
    assert result["completion_ratio"] == 1.0


def test_mesh_metrics_concentric_spheres_and_ratio_threshold():
    gt = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    n_points = 30_000
    for radius, ratio in ((1.02, 1.0), (1.08, 0.0)):
        rec = trimesh.creation.icosphere(subdivisions=4, radius=radius)
        result = ev.mesh_metrics(rec, gt, n_points=n_points)
        # icospheres are scaled copies, so facet flattening changes the gap by < 0.1%
        expected = expected_nn_distance(radius - 1.0, n_points / (4 * np.pi))
        assert result["accuracy_m"] == pytest.approx(expected, rel=0.02)
        assert result["completion_m"] == pytest.approx(expected, rel=0.02)
        assert result["completion_ratio"] == ratio
    assert ev.mesh_metrics(rec, gt, n_points=n_points) == result  # deterministic for a seed
    assert ev.mesh_metrics(rec, gt, n_points=n_points, seed=1) != result


def test_mesh_metrics_half_covered_plane_separates_accuracy_from_completion():
    """Accuracy is rec -> GT, Completion is GT -> rec (docs/evaluation.md); a one-sided scene tells them apart.

    GT = square [-1, 1]^2 at z = 0 (area 4, n samples: density n/4); rec = its half x >= 0 (area 2,
    density n/2).  Every rec sample lies on the GT plane, so Accuracy = Poisson nearest-neighbour
    distance at the GT density, E = expected_nn_distance(0, n/4) (about 3 mm).  Half of the GT
    samples (x >= 0) have a rec sample at the rec density, expected_nn_distance(0, n/2); the other
    half (x uniform on [-1, 0)) are |x| from the rec edge x = 0, mean 1/2, so
    Completion = 1/2 * 1/2 + 1/2 * expected_nn_distance(0, n/2).  Completion Ratio (5 cm): the
    covered half plus the strip -0.05 < x < 0 (share 0.05 / 2) = 0.525.
    """
    n_points = 100_000
    gt = plane_patch(1.0, 0.0)
    rec = trimesh.Trimesh([[0, -1, 0], [1, -1, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    result = ev.mesh_metrics(rec, gt, n_points=n_points, threshold=0.05, seed=0)
    assert result["accuracy_m"] == pytest.approx(expected_nn_distance(0.0, n_points / 4.0), rel=0.03)
    expected_completion = 0.25 + 0.5 * expected_nn_distance(0.0, n_points / 2.0)
    assert result["completion_m"] == pytest.approx(expected_completion, rel=0.02)
    assert result["completion_ratio"] == pytest.approx(0.525, abs=0.01)  # binomial sd 0.0016


def test_mesh_metrics_extra_far_surface_raises_accuracy_only():
    """Reconstructed surface away from the GT costs Accuracy, never Completion.

    GT = square [-1, 1]^2 at z = 0; rec = that square plus a copy at z = 1 (area 8, density n/8 on
    each).  Half the rec samples lie on the GT (Poisson distance at GT density n/4), the other half
    sit 1 m straight above it: sqrt(1 + r^2), i.e. expected_nn_distance(1, n/4).  So
    Accuracy = (expected_nn_distance(0, n/4) + expected_nn_distance(1, n/4)) / 2, about 0.5 m.
    Every GT sample has the z = 0 copy at density n/8: Completion = expected_nn_distance(0, n/8)
    (about 4.5 mm) and Completion Ratio = 1.
    """
    n_points = 100_000
    gt = plane_patch(1.0, 0.0)
    rec = trimesh.util.concatenate([plane_patch(1.0, 0.0), plane_patch(1.0, 1.0)])
    result = ev.mesh_metrics(rec, gt, n_points=n_points, threshold=0.05, seed=0)
    density_gt = n_points / 4.0
    expected_accuracy = 0.5 * (expected_nn_distance(0.0, density_gt) + expected_nn_distance(1.0, density_gt))
    assert result["accuracy_m"] == pytest.approx(expected_accuracy, rel=0.01)  # binomial sd of the split 0.3 %
    assert result["completion_m"] == pytest.approx(expected_nn_distance(0.0, n_points / 8.0), rel=0.02)
    assert result["completion_ratio"] == 1.0


def test_depth_l1():
    rng = np.random.default_rng(12)
    reference = rng.uniform(0.5, 4.0, size=(2, 12, 16))
    reference[:, :3] = 0.0  # missing depth
    rendered = reference + 0.1
    rendered[reference == 0] = np.nan  # ignored where the reference is missing
    assert ev.depth_l1(rendered, reference) == pytest.approx(0.1, abs=1e-12)
    assert ev.depth_l1(torch.from_numpy(rendered), torch.from_numpy(reference)) == pytest.approx(0.1, abs=1e-12)
    valid = np.zeros_like(reference, bool)
    valid[0, 5:] = True
    rendered[0, 5:] += 0.2
    assert ev.depth_l1(rendered, reference, valid=valid) == pytest.approx(0.3, abs=1e-12)
    with pytest.raises(ValueError, match="no pixel"):
        ev.depth_l1(rendered, np.zeros_like(reference))


def test_depth_l1_counts_a_hole_in_the_reconstruction_as_depth_zero():
    """render_depth_zbuffer marks pixels without surface +inf; depth_l1 raised on them, so the documented
    way to Depth L1 failed on any mesh with a hole.  Co-SLAM's renderer gives depth 0 there."""
    plane = trimesh.Trimesh([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2]], [[0, 1, 2], [0, 2, 3]], process=False)
    half = trimesh.Trimesh([[-1, -1, 2], [0.0, -1, 2], [0.0, 1, 2], [-1, 1, 2]], [[0, 1, 2], [0, 2, 3]], process=False)
    camera = (10.0, 10.0, 4.5, 4.5, 10, 10)  # 10 x 10 pixels, the plane fills the view at 2 m
    reference = ev.render_depth_zbuffer(plane.vertices, plane.faces, np.eye(4), camera)
    rendered = ev.render_depth_zbuffer(half.vertices, half.faces, np.eye(4), camera)
    assert np.isfinite(reference).all() and np.isposinf(rendered).any()
    hole = np.isposinf(rendered)  # the right half of the view: |2 m - 0| each
    assert 0.3 < hole.mean() < 0.7
    assert ev.depth_l1(rendered, reference) == pytest.approx(2.0 * hole.mean(), abs=1e-12)
    with pytest.raises(ValueError, match="NaN or -inf"):
        ev.depth_l1(np.full_like(reference, np.nan), reference)


# ------------------------------------------------------------------------------------------
# Rasteriser and culling on an analytic scene


FX, FY, CX, CY, W, H = 40.0, 40.0, 31.5, 23.5, 64, 48
INTRINSICS = (FX, FY, CX, CY, W, H)


def grid_plane(x_range, y_range, z, step):
    xs = np.arange(x_range[0], x_range[1] + 1e-9, step)
    ys = np.arange(y_range[0], y_range[1] + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)
    nx = xs.size
    faces = []
    for j in range(ys.size - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i + 1, (j + 1) * nx + i
            faces += [[a, b, c], [a, c, d]]
    return vertices, np.array(faces)


def test_zbuffer_depth_of_a_tilted_plane_is_perspective_correct():
    # plane z = 2 + 0.5 x; the ray through pixel (u, v) is z (a, b, 1) with a = (u - cx)/fx, so
    # z = 2 / (1 - 0.5 a).  Two big triangles (one quad) cover the whole image.
    corners = np.array([[-3, -3], [3, -3], [3, 3], [-3, 3]], float)  # z in [0.5, 3.5]
    vertices = np.column_stack([corners, 2 + 0.5 * corners[:, 0]])
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    pose = random_rigid(np.random.default_rng(13))
    world_vertices = vertices @ pose[:3, :3].T + pose[:3, 3]  # camera placed anywhere in the world
    depth = ev.render_depth_zbuffer(world_vertices, quad, pose, INTRINSICS)
    a = (np.arange(W) - CX) / FX
    expected = np.broadcast_to(2 / (1 - 0.5 * a), (H, W))
    np.testing.assert_allclose(depth, expected, rtol=1e-10)


def _scene():
    """A small front quad at z = 2 occluding the middle of a large back plane at z = 4 (camera
    at the origin looking along +z), plus one triangle behind the camera and one off to the side."""
    front_v, front_f = grid_plane((-0.3, 0.3), (-0.2, 0.2), 2.0, 0.2)
    back_v, back_f = grid_plane((-4.0, 4.0), (-3.0, 3.0), 4.0, 0.1)
    behind_v = np.array([[-0.5, 0, -1.0], [0.5, 0, -1.0], [0, 0.5, -1.0]])
    side_v = np.array([[10, 0, 2.0], [11, 0, 2.0], [10, 1, 2.0]])
    parts = [(front_v, front_f), (back_v, back_f), (behind_v, np.array([[0, 1, 2]])), (side_v, np.array([[0, 1, 2]]))]
    vertices, faces, labels, offset = [], [], [], 0
    for label, (v, f) in enumerate(parts):
        vertices.append(v)
        faces.append(f + offset)
        labels += [label] * len(f)
        offset += len(v)
    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False), np.array(labels)


def _kept(original, culled):
    """Boolean per original face: is the same triangle (by vertex coordinates) in the culled mesh?"""
    key = lambda m: {tuple(np.round(m.vertices[f], 9).ravel()) for f in m.faces}  # noqa: E731
    kept = key(culled)
    return np.array([tuple(np.round(original.vertices[f], 9).ravel()) in kept for f in original.faces])


def test_cull_mesh_frustum_and_occlusion():
    mesh, labels = _scene()
    before = (mesh.vertices.copy(), mesh.faces.copy())
    poses = np.eye(4)[None]
    face_vertices = mesh.vertices[mesh.faces]  # (F, 3, 3)
    x, y = face_vertices[..., 0], face_vertices[..., 1]
    # analytic frustum at z = 4: 0 <= 10 x + 31.5 <= 63 and 0 <= 10 y + 23.5 <= 47
    in_view = ((np.abs(x) <= 3.15) & (np.abs(y) <= 2.35)).any(1)
    back = labels == 1

    frustum = _kept(mesh, ev.cull_mesh(mesh, poses, INTRINSICS, frustum_only=True))
    assert frustum[labels == 0].all()
    assert not frustum[labels == 2].any() and not frustum[labels == 3].any()
    np.testing.assert_array_equal(frustum[back], in_view[back])

    occluded = _kept(mesh, ev.cull_mesh(mesh, poses, INTRINSICS))
    # back vertices whose ray hits the front quad (|x| < 0.6, |y| < 0.4 at z = 4) are hidden
    hidden = ((np.abs(x) <= 0.5) & (np.abs(y) <= 0.3)).all(1)
    clearly_seen = (((np.abs(x) >= 0.7) | (np.abs(y) >= 0.5)) & (np.abs(x) <= 3.15) & (np.abs(y) <= 2.35)).any(1)
    assert occluded[labels == 0].all()
    assert not occluded[back & hidden].any() and (back & hidden).sum() > 20
    assert occluded[back & clearly_seen].all()
    assert not occluded[labels >= 2].any()

    # the same answer from a depth map given as a sensor would (analytic render of the scene)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    a, b = (u - CX) / FX, (v - CY) / FY
    depth = np.where((np.abs(2 * a) <= 0.3) & (np.abs(2 * b) <= 0.2), 2.0, 4.0)
    with_depth = _kept(mesh, ev.cull_mesh(mesh, poses, INTRINSICS, depths=depth[None]))
    np.testing.assert_array_equal(with_depth[back & (hidden | clearly_seen)], occluded[back & (hidden | clearly_seen)])
    # the same map in raw TUM PNG units (x 5000) kept every back triangle in view, occlusion silently off
    with pytest.raises(ValueError, match=r"depths have a median of 2e\+04 m, more than 100 m: expected metres"):
        ev.cull_mesh(mesh, poses, INTRINSICS, depths=5000 * depth[None])

    # a camera turned around (looking along -z) sees only the triangle behind the first camera
    turned = np.eye(4)
    turned[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    assert len(ev.cull_mesh(mesh, turned[None], INTRINSICS, frustum_only=True).faces) == 1  # the 'behind' one
    np.testing.assert_array_equal(mesh.vertices, before[0])
    np.testing.assert_array_equal(mesh.faces, before[1])


def test_depth_l1_valid_mask_never_counts_a_missing_reference():
    """valid is ANDed with reference > 0: a pixel without reference depth is left out even where
    valid is True.  Oracle by hand: |2.5 - 2|, |1.5 - 1|, |3.5 - 3| -> 0.5; the missing pixel's 5 m is ignored."""
    reference = np.array([[0.0, 2.0], [1.0, 3.0]])
    rendered = np.array([[5.0, 2.5], [1.5, 3.5]])
    assert ev.depth_l1(rendered, reference, valid=np.ones((2, 2), bool)) == pytest.approx(0.5, abs=1e-12)


def test_zbuffer_skips_a_triangle_with_a_vertex_behind_the_camera():
    """A triangle crossing the camera plane (one vertex at z = -1) is not rasterised, as documented
    (no near-plane clipping); projecting its behind vertex would flip it across the image.
    Oracle: every pixel stays inf (no surface)."""
    crossing = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, -1.0]])
    depth = ev.render_depth_zbuffer(crossing, np.array([[0, 1, 2]]), np.eye(4), INTRINSICS)
    assert np.isinf(depth).all()


def test_virtual_cameras_add_observations_but_never_frustum_membership():
    """Co-SLAM's virtual cameras may reveal a triangle a real camera had in view but occluded;
    they never add one no real camera had in its frustum.  Oracle: the analytic scene with a
    virtual camera 3 m to the right: the back plane behind the front quad with 0 <= x <= 0.5 is
    seen from there (its rays pass x >= 1.6 at z = 2), the back plane beyond x = 3.15 is in no real frustum."""
    mesh, labels = _scene()
    x, y = mesh.vertices[mesh.faces][..., 0], mesh.vertices[mesh.faces][..., 1]
    back = labels == 1
    virtual = np.eye(4)
    virtual[0, 3] = 3.0
    kept = _kept(mesh, ev.cull_mesh(mesh, np.eye(4)[None], INTRINSICS, virtual_poses_c2w=virtual[None]))
    revealed = back & ((x >= 0.0) & (x <= 0.5) & (np.abs(y) <= 0.3)).all(1)
    outside = back & ((x > 3.2) | (np.abs(y) > 2.4)).all(1)
    assert revealed.sum() > 5 and kept[revealed].all()
    assert outside.sum() > 20 and not kept[outside].any()


# ------------------------------------------------------------------------------------------
# Command line


def _write_tum(path, times, poses):
    rows = np.column_stack([times, pose_to_tum(poses)])
    np.savetxt(path, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")


def test_cli_trajectory_json_and_bad_file(tmp_path, fr2_desk, capsys):
    gt_times, gt_poses = fr2_desk[0][:2000], fr2_desk[1][:2000]
    est_poses = perturb(gt_poses[::7], np.random.default_rng(14), 0.01, 0.01)
    _write_tum(tmp_path / "gt.txt", gt_times, gt_poses)
    _write_tum(tmp_path / "est.txt", gt_times[::7], est_poses)
    assert ev.main(["trajectory", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)  # exactly one JSON object and nothing else
    direct = ev.evaluate_trajectory(gt_times, gt_poses, gt_times[::7], est_poses)
    for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "n_matched"):
        assert printed[key] == pytest.approx(direct[key], rel=1e-6, abs=1e-9)
    assert (printed["n_est"], printed["n_gt"], printed["delta_frames"]) == (len(est_poses), 2000, 1)  # what was used

    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 1\n")
    assert ev.main(["trajectory", str(tmp_path / "gt.txt"), str(bad)]) == 2
    assert f"{bad}:3" in capsys.readouterr().err
    assert ev.main(["trajectory", str(tmp_path / "missing.txt"), str(bad)]) == 2


def test_cli_interpolate_scores_at_the_estimate_stamps_as_a_run_does(tmp_path, capsys):
    """Oracle: a motion that linear interpolation reproduces exactly (constant velocity, constant
    rotation rate about one axis), sampled at 100 Hz for the ground truth and at frame stamps
    between samples for the estimate: interpolated, ATE and RPE are 0; nearest, they are not."""
    def motion(times):
        poses = np.tile(np.eye(4), (len(times), 1, 1))
        poses[:, :3, :3] = Rotation.from_rotvec(np.outer(times - 10.0, [0.0, 0.0, 0.5])).as_matrix()
        poses[:, :3, 3] = np.outer(times - 10.0, [0.8, -0.3, 0.1])
        return poses

    gt_times = 10.0 + 0.01 * np.arange(300)
    est_times = 10.0 + 0.004 + np.arange(40) / 15.0  # never on a GT stamp
    _write_tum(tmp_path / "gt.txt", gt_times, motion(gt_times))
    _write_tum(tmp_path / "est.txt", est_times, motion(est_times))
    arguments = ["trajectory", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json", "--max-diff", "0.02"]
    assert ev.main(arguments + ["--interpolate"]) == 0
    interpolated = json.loads(capsys.readouterr().out)
    assert interpolated["n_matched"] == 40 and interpolated["ate_rmse_m"] < 1e-7 and interpolated["rpe_rot_rmse_deg"] < 1e-5
    assert interpolated["n_gt"] == 300 and interpolated["n_est"] == 40  # the poses read from each file (n_gt was 40)
    assert ev.main(arguments) == 0
    nearest = json.loads(capsys.readouterr().out)
    assert nearest["ate_rmse_m"] > 1e-3  # 4 ms at 0.86 m/s


def test_cli_interpolate_uses_the_given_max_diff(tmp_path, capsys):
    """Ground truth at 10 Hz, estimate stamps 45 ms after a GT stamp: with --max-diff 0.06 a GT stamp
    is near enough and the bracketing pair (0.1 s apart <= 2 x 0.06) interpolates the motion exactly
    (oracle: the same linear motion written here, ATE 0 on all 12 frames); with --max-diff 0.03 no
    GT stamp is near enough and the command refuses (exit 2)."""
    def motion(times):
        return _poses_at(np.outer(times - 5.0, [0.5, 0.2, -0.1]))

    gt_times = 5.0 + 0.1 * np.arange(30)
    est_times = 5.045 + 0.2 * np.arange(12)
    _write_tum(tmp_path / "gt.txt", gt_times, motion(gt_times))
    _write_tum(tmp_path / "est.txt", est_times, motion(est_times))
    arguments = ["trajectory", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json", "--interpolate"]
    assert ev.main(arguments + ["--max-diff", "0.06"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["n_matched"] == 12 and printed["ate_rmse_m"] < 1e-7
    assert ev.main(arguments + ["--max-diff", "0.03"]) == 2
    message = capsys.readouterr().err  # named as the files and their time spans, not as a ground-truth fault
    assert "no stamp of" in message and "est.txt" in message and "gt.txt" in message
    assert "[5.045000, 7.245000]" in message
    _write_tum(tmp_path / "later.txt", est_times + 1000.0, motion(est_times))  # another clock, without --interpolate
    assert ev.main(["trajectory", str(tmp_path / "gt.txt"), str(tmp_path / "later.txt")]) == 2
    assert "the estimate spans [1005.045000" in capsys.readouterr().err


def test_cli_delta_sets_the_rpe_interval(tmp_path, capsys):
    """Oracle by hand: identity rotations and an estimate that drifts 1 cm per frame along x, so
    every pair (i, i + delta) has a relative translation error of exactly delta cm: RPE RMSE 0.01 m
    with the default --delta 1, 0.03 m with --delta 3, and no rotation error."""
    times = 2.0 + 0.1 * np.arange(20)
    gt_positions = np.outer(np.arange(20), [0.05, 0.02, 0.0])
    _write_tum(tmp_path / "gt.txt", times, _poses_at(gt_positions))
    _write_tum(tmp_path / "est.txt", times, _poses_at(gt_positions + np.outer(np.arange(20), [0.01, 0.0, 0.0])))
    arguments = ["trajectory", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json"]
    for extra, expected in (([], 0.01), (["--delta", "3"], 0.03)):
        assert ev.main(arguments + extra) == 0
        printed = json.loads(capsys.readouterr().out)
        assert printed["rpe_trans_rmse_m"] == pytest.approx(expected, abs=1e-8) and printed["rpe_rot_rmse_deg"] < 1e-6


def test_cli_mesh(tmp_path, capsys):
    trimesh.creation.icosphere(subdivisions=3, radius=1.0).export(tmp_path / "gt.ply")
    trimesh.creation.icosphere(subdivisions=3, radius=1.02).export(tmp_path / "rec.ply")
    assert ev.main(["mesh", str(tmp_path / "rec.ply"), str(tmp_path / "gt.ply"), "--points", "5000", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    direct = ev.mesh_metrics(trimesh.load(tmp_path / "rec.ply"), trimesh.load(tmp_path / "gt.ply"), n_points=5000)
    assert printed == pytest.approx(direct, rel=1e-12)
    assert 0.02 <= printed["accuracy_m"] < 0.05 and printed["n_points"] == 5000
    (tmp_path / "junk.ply").write_text("not a mesh")
    assert ev.main(["mesh", str(tmp_path / "junk.ply"), str(tmp_path / "gt.ply")]) == 2
    assert "junk.ply" in capsys.readouterr().err
    broken = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    broken.vertices[5] = np.nan
    broken.export(tmp_path / "nan.ply")
    assert ev.main(["mesh", str(tmp_path / "nan.ply"), str(tmp_path / "gt.ply")]) == 2
    assert "nan.ply: vertex 5 is not finite" in capsys.readouterr().err
    trimesh.creation.icosphere(subdivisions=3, radius=1000.0).export(tmp_path / "millimetres.ply")
    assert ev.main(["mesh", str(tmp_path / "millimetres.ply"), str(tmp_path / "gt.ply"), "--points", "500"]) == 0
    assert "warning:" in capsys.readouterr().err  # metres against millimetres: printed, and said


def test_documented_defaults_hold_when_no_value_is_passed(tmp_path, capsys):
    """docs/evaluation.md's defaults, used without passing them (the other tests pass every value):
    evaluate_trajectory and `eval trajectory` match within 0.01 s (evo's), associate within 0.02 s
    (TUM's associate.py), `eval mesh` samples 200000 points.  Oracle: stamps 8 and 15 ms off
    alternately, so only the 8 ms half is within 0.01 s; 15 and 25 ms for 0.02 s."""
    times = 1.0 + 0.1 * np.arange(20)
    positions = np.outer(np.arange(20), [0.05, 0.02, 0.01])
    positions[:, 1] += 0.1 * np.sin(np.arange(20))  # not collinear: the alignment is unique
    late = times + np.where(np.arange(20) % 2 == 0, 0.008, 0.015)
    assert ev.evaluate_trajectory(times, _poses_at(positions), late, _poses_at(positions))["n_matched"] == 10
    _write_tum(tmp_path / "gt.txt", times, _poses_at(positions))
    _write_tum(tmp_path / "est.txt", late, _poses_at(positions))
    assert ev.main(["trajectory", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_matched"] == 10
    idx_a, _ = ev.associate(times, times + np.where(np.arange(20) % 2 == 0, 0.015, 0.025))
    assert idx_a.tolist() == list(range(0, 20, 2))
    trimesh.creation.icosphere(subdivisions=2, radius=1.0).export(tmp_path / "gt.ply")
    trimesh.creation.icosphere(subdivisions=2, radius=1.01).export(tmp_path / "rec.ply")
    assert ev.main(["mesh", str(tmp_path / "rec.ply"), str(tmp_path / "gt.ply"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_points"] == 200000


def test_cull_mesh_keeps_the_cap_a_camera_sees_on_a_sphere():
    """From distance 3 on the axis, a unit sphere is visible exactly where z > 1/3 (tangent cone)."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    camera = np.eye(4)
    camera[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looks along world -z
    camera[:3, 3] = [0.0, 0.0, 3.0]
    culled = ev.cull_mesh(sphere, camera[None], (120.0, 120.0, 79.5, 59.5, 160, 120))
    vertex_z = sphere.vertices[sphere.faces][..., 2]  # (F, 3)
    kept = _kept(sphere, culled)
    assert kept[(vertex_z > 0.45).all(1)].all()  # well inside the cap: kept
    assert not kept[(vertex_z < 0.25).all(1)].any()  # beyond the limb or on the back: removed


def test_errors_over_time_stamp_each_rpe_error_at_the_later_frame_of_its_pair():
    """trajectory_errors_over_time's time axes, by construction: the camera moves 1 m/s along x;
    the estimate (stamps 3 ms late, frame 4 missing) jumps 5 cm sideways from frame 7 on.  With
    delta = 1 the matched frames are 0-3, 5-9 and the only RPE error (5 cm) is the pair (6, 7),
    stamped at frame 7's estimate time; with delta = 2 the pairs (5, 7) and (6, 8) carry it.  The
    pair (3, 5) across the gap has none (both move 0.2 m)."""
    gt_times = np.arange(10) * 0.1
    gt_poses = np.tile(np.eye(4), (10, 1, 1))
    gt_poses[:, 0, 3] = gt_times
    kept = np.array([0, 1, 2, 3, 5, 6, 7, 8, 9])
    est_times = gt_times[kept] + 0.003
    est_poses = gt_poses[kept].copy()
    est_poses[kept >= 7, 1, 3] += 0.05
    one = ev.trajectory_errors_over_time(gt_times, gt_poses, est_times, est_poses, max_diff=0.01)
    np.testing.assert_array_equal(one["times_s"], est_times)
    np.testing.assert_array_equal(one["rpe_times_s"], est_times[1:])
    assert one["trans_errors_m"].shape == one["rpe_times_s"].shape
    jumps = one["rpe_times_s"][one["trans_errors_m"] > 1e-9]
    np.testing.assert_allclose(jumps, [0.703], atol=1e-12)
    np.testing.assert_allclose(one["trans_errors_m"].max(), 0.05, atol=1e-12)
    two = ev.trajectory_errors_over_time(gt_times, gt_poses, est_times, est_poses, max_diff=0.01, delta=2)
    np.testing.assert_array_equal(two["rpe_times_s"], est_times[2:])
    np.testing.assert_allclose(two["rpe_times_s"][two["trans_errors_m"] > 1e-9], [0.703, 0.803], atol=1e-12)
