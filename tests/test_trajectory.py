"""The trajectory type (trajectory.py): timing, the covered domain, growing and shrinking, pose models.

Oracles: the functional spline (:func:`spline.evaluate`, itself checked against independent
formulas in test_spline.py), the knot arithmetic t_k = t0 + k dt written out by hand, and local
support (a control point moves only the four segments it shapes).
"""

import numpy as np
import pytest
import torch

from tsslam_ref import knots, spline, spline_fit
from tsslam_ref.bundle import SplinePoses, dynamics_term
from tsslam_ref.config import DynamicsConfig
from tsslam_ref.geometry import make_pose, so3_exp, so3_log
from tsslam_ref.trajectory import BSplineTrajectory

F64 = torch.float64


def random_controls(seed: int, n_ctrl: int):
    """(N, 3, 3) rotations a random walk of <= 0.3 rad steps, (N, 3) translations a random walk."""
    generator = torch.Generator().manual_seed(seed)
    steps = 0.3 * torch.rand(n_ctrl, 1, generator=generator, dtype=F64) * torch.nn.functional.normalize(
        torch.randn(n_ctrl, 3, generator=generator, dtype=F64), dim=-1)
    rotations = [so3_exp(steps[0])]
    for k in range(1, n_ctrl):
        rotations.append(rotations[-1] @ so3_exp(steps[k]))
    translations = torch.cumsum(torch.randn(n_ctrl, 3, generator=generator, dtype=F64), dim=0)
    return torch.stack(rotations), translations


def test_accessors_and_poses_match_the_functional_spline():
    R, P = random_controls(26, 7)
    traj = BSplineTrajectory.from_rotvecs(so3_log(R), P, 0.2, 1.0)
    assert len(traj) == traj.n_ctrl == 7
    assert np.allclose(traj.knot_times(), 1.0 + 0.2 * np.arange(7), atol=1e-15)
    assert traj.knot_time(3) == 1.0 + 3 * 0.2
    assert traj.domain() == spline.valid_time_range(7, 0.2, 1.0)  # [t0 + 2 dt, t0 + 6 dt]
    times = np.array([1.45, 1.9])
    sample = spline.evaluate(R, P, times, 0.2, 1.0)
    assert torch.allclose(traj.poses(times), make_pose(sample.rotation, sample.translation), atol=1e-14)
    assert traj.to(torch.float32).control_translations.dtype == torch.float32
    assert "n_ctrl=7" in repr(traj)
    with pytest.raises(ValueError, match="dt must be > 0"):
        BSplineTrajectory(R, P, 0.0, 1.0)
    with pytest.raises(ValueError, match=r"\(N, 3\) translations"):
        BSplineTrajectory(R, P[:5], 0.2, 1.0)


def test_intervals_start_at_the_first_frame_and_the_domain_is_half_open():
    first, dt = 10.0, 0.25
    traj = BSplineTrajectory.empty(first, dt, torch.zeros(1, dtype=F64))
    assert traj.n_ctrl == 0 and traj.t0 == first - 2 * dt
    assert traj.interval(0) == (first, first + dt) and traj.interval(3) == (first + 3 * dt, first + 4 * dt)
    assert traj.domain() == (first, first) and not traj.covers([first, first + 0.1]).any()
    R, P = random_controls(3, 5)
    grown = traj.with_controls(R, P)  # 5 points: intervals 0 and 1
    start, end = grown.domain()
    assert (start, end) == (first, traj.knot_time(4))
    times = np.array([start - 1e-9, start, 0.5 * (start + end), np.nextafter(end, 0.0), end, end + 1e-9])
    assert grown.covers(times).tolist() == [False, True, True, True, False, False]
    assert grown.covers(times.reshape(2, 3)).shape == (2, 3)
    basalt = BSplineTrajectory.empty(first, dt, torch.zeros(1, dtype=F64), convention="basalt")
    assert basalt.t0 == first and basalt.interval(0) == (first, first + dt)


def test_push_back_pop_front_and_window_keep_the_curve():
    R, P = random_controls(27, 9)
    traj = BSplineTrajectory(R, P, 0.3, 0.0)
    start, end = traj.domain()
    times = np.linspace(start + 0.3, end, 11)
    reference = traj.evaluate(times, derivatives=2)
    window = traj.window(1, 9)
    popped = traj.clone()
    popped.pop_front()
    for other in (window, popped):
        assert other.t0 == pytest.approx(0.3)
        for a, b in zip(other.evaluate(times, derivatives=2), reference):
            assert torch.allclose(a, b, atol=1e-14)
    short = BSplineTrajectory(R[:8], P[:8], 0.3, 0.0)
    short.push_back(R[8], P[8])
    assert short.domain() == pytest.approx(traj.domain())
    assert torch.allclose(short.poses(times), traj.poses(times), atol=1e-14)
    with pytest.raises(ValueError):
        traj.window(5, 8)
    tiny = BSplineTrajectory(R[:4], P[:4], 0.3, 0.0)
    with pytest.raises(ValueError, match="needs 4"):
        tiny.pop_front()
    with pytest.warns(UserWarning, match="pi/2"):
        tiny.push_back(R[3] @ so3_exp(torch.tensor([2.0, 0.0, 0.0], dtype=F64)), P[3])


def test_a_popped_trajectory_keeps_no_start_pose_so_ba_on_it_keeps_the_curve():
    """pop_front kept the dropped start's pose: SplinePoses (as BA builds it) pins control point 0 so
    that the curve starts at start_pose, and moved the popped curve's new start there (1.2 m)."""
    R, P = random_controls(31, 9)
    traj = BSplineTrajectory(R, P, 0.3, 0.0)
    traj.start_pose = traj.poses(np.array(traj.domain()[0]))
    traj.pop_front()
    assert traj.start_pose is None
    times = np.linspace(*traj.domain(), 7)
    unmoved = SplinePoses(traj, [1, 2, 3], times, traj.poses(times), 1e-3, 1e-3)
    torch.testing.assert_close(unmoved.poses(), traj.poses(times), atol=1e-12, rtol=0)


def test_planned_knots_and_dynamics_windows_refuse_float32_seconds():
    R, P = random_controls(32, 6)
    traj = BSplineTrajectory(R, P, 0.3, 1305000064.0)
    end = traj.knot_time(traj.n_ctrl + 1)
    with pytest.raises(TypeError, match="end_time must be float64 seconds"):  # was 58 s off at t + 70 s
        traj.plan_interval_end(traj.n_ctrl - 3, np.float32(end + 70.0))
    with pytest.raises(TypeError, match="assumed_spacing must be float64"):
        traj.plan_interval_end(traj.n_ctrl - 3, end + 0.1, assumed_spacing=np.float32(0.3))
    from tsslam_ref.dynamics import sample_times

    with pytest.raises(TypeError, match="t_start must be float64"):  # was "need t_end > t_start"
        sample_times(np.float32(1.3e9), 1.3e9 + 0.3, 4)


def test_pop_front_at_epoch_stamps_does_not_drift_in_time():
    R, P = random_controls(28, 1005)
    traj = BSplineTrajectory(R, P, 0.03, 1.3e9)
    knot_1000 = 1.3e9 + 1000 * 0.03  # t0 += dt rounds to the stamp's ulp at every pop
    for _ in range(1000):
        traj.pop_front()
    assert traj.t0 == knot_1000
    traj.t0 = 5.0  # a t0 set by hand starts a new count
    traj.pop_front()
    assert traj.t0 == 5.03


def test_non_finite_knots_are_named():
    R, P = random_controls(29, 5)
    traj = BSplineTrajectory(R, P, 0.1, 0.0)
    with pytest.raises(ValueError, match=r"finite, got inf s at stored index \d"):
        traj.push_back(R[0], P[0], knot_time=float("inf"))


def test_with_controls_keeps_timing_and_start_pose_and_detaches():
    R, P = random_controls(5, 6)
    start_pose = make_pose(R[1], P[1])
    traj = BSplineTrajectory(R, P, 0.2, 1.0, start_pose=start_pose)
    moved = P.clone().requires_grad_(True)
    other = traj.with_controls(R, moved + 1.0)
    assert (other.dt, other.t0, other.convention) == (traj.dt, traj.t0, traj.convention)
    assert other.start_pose is start_pose and not other.control_translations.requires_grad
    assert torch.equal(other.control_translations, P + 1.0)


def test_spline_poses_build_from_the_trajectory_and_return_one():
    """The pose model holds the trajectory's control points; its trajectory() is differentiable in
    the free points only and, untouched, equals the trajectory it was built from."""
    R, P = random_controls(8, 7)
    traj = BSplineTrajectory(R, P, 0.25, 0.0)
    times = np.array([0.55, 1.3])
    model = SplinePoses(traj, free=[4, 5], slot_times=times, fallback_poses=traj.poses(times),
                        lr_rot=1e-3, lr_trans=1e-3)
    current = model.trajectory()
    assert torch.allclose(current.control_translations, P, atol=0) and torch.allclose(current.poses(times), traj.poses(times))
    grad = torch.autograd.grad(current.control_translations.sum(), [model.translation_delta])[0]
    assert grad[[4, 5]].abs().min() == 1.0 and grad[[0, 1, 2, 3, 6]].abs().max() == 0.0


def test_dynamics_term_is_off_for_an_empty_range_or_no_free_point():
    """One L_DR closure for local and global BA: None where nothing can be regularised, else the
    regulariser of the model's current trajectory over the range."""
    from tsslam_ref.dynamics import trajectory_dynamics_loss

    R, P = random_controls(9, 8)
    traj = BSplineTrajectory(R, 0.01 * P, 0.25, 0.0)
    cfg = DynamicsConfig(n_samples=8)
    free = SplinePoses(traj, free=[5, 6], slot_times=np.array([1.0]), fallback_poses=torch.eye(4, dtype=F64)[None],
                       lr_rot=1e-3, lr_trans=1e-3)
    none_free = SplinePoses(traj, free=[], slot_times=np.array([1.0]), fallback_poses=torch.eye(4, dtype=F64)[None],
                            lr_rot=1e-3, lr_trans=1e-3)
    assert dynamics_term(free, None, cfg, None) is None
    assert dynamics_term(free, (1.0, 1.0), cfg, None) is None
    assert dynamics_term(none_free, (0.5, 1.5), cfg, None) is None
    term = dynamics_term(free, (0.5, 1.5), cfg, torch.Generator().manual_seed(2))
    expected = trajectory_dynamics_loss(traj, 0.5, 1.5, cfg, torch.Generator().manual_seed(2))
    assert torch.allclose(term(), expected, atol=1e-12)


def test_pose_models_use_the_same_domain_rule_as_the_trajectory():
    """A slot at the domain's end is not covered (it belongs to the next, unfitted interval) and
    keeps its fallback pose, as does one before the start; covered slots get the spline's pose."""
    R, P = random_controls(11, 6)
    traj = BSplineTrajectory(R, P, 0.25, 0.0)
    start, end = traj.domain()
    times = np.array([start - 0.01, start, 0.5 * (start + end), end])
    fallback = torch.eye(4, dtype=F64).repeat(4, 1, 1) * 3.0
    model = SplinePoses(traj, free=[3], slot_times=times, fallback_poses=fallback, lr_rot=1e-3, lr_trans=1e-3)
    poses = model.poses()
    assert traj.covers(times).tolist() == [False, True, True, False]
    assert torch.equal(poses[0], fallback[0]) and torch.equal(poses[3], fallback[3])
    assert torch.allclose(poses[1:3], traj.poses(times[1:3]), atol=1e-14)


# --- variable intervals (non-uniform knots)


def uneven_trajectory(seed: int = 31, n_ctrl: int = 10, convention: str = "paper") -> BSplineTrajectory:
    """A trajectory grown by push_back with uneven knot times (0.08 .. 0.45 s)."""
    R, P = random_controls(seed, n_ctrl)
    spacing = np.random.default_rng(seed).uniform(0.08, 0.45, n_ctrl)
    traj = BSplineTrajectory.empty(5.0, 0.3, torch.zeros(1, dtype=F64), convention=convention)
    time = traj.t0
    for k in range(n_ctrl):
        time = time + (0.0 if k == 0 else spacing[k])
        traj.push_back(R[k], P[k], knot_time=time)
    return traj


def test_push_back_with_knot_times_sets_the_intervals_and_the_non_uniform_curve():
    traj = uneven_trajectory()
    assert not traj.uniform
    knots_of_points = traj.knot_times()
    assert np.all(np.diff(knots_of_points) > 0)
    assert traj.interval(3) == (knots_of_points[5], knots_of_points[6])  # paper: [t_{n+2}, t_{n+3})
    assert traj.domain() == (knots_of_points[2], knots_of_points[-1])
    assert traj.knot_time(10) == knots_of_points[-1] + traj.dt and traj.knot_time(11) == knots_of_points[-1] + 2 * traj.dt
    times = np.linspace(*traj.domain(), 41)
    oracle = knots.evaluate(traj.control_rotations, traj.control_translations, times,
                            np.r_[knots_of_points, knots_of_points[-1] + traj.dt * np.arange(1, 3)], 2)
    for a, b in zip(traj.evaluate(times, derivatives=2), oracle):
        assert torch.equal(a, b)
    start, end = traj.domain()
    assert traj.covers([start, end - 1e-9, end]).tolist() == [True, True, False]
    with pytest.raises(ValueError, match=r"knot_time = 1.0 s must come after the previous knot"):
        traj.push_back(traj.control_rotations[-1], traj.control_translations[-1], knot_time=1.0)


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_variable_interval_window_pop_front_clone_keep_the_curve(convention):
    traj = uneven_trajectory(32, 11, convention)
    window = traj.window(2, 9)
    popped = traj.clone()
    popped.pop_front()
    popped.pop_front()
    start, end = window.domain()
    times = np.linspace(start, end, 23)
    reference = traj.evaluate(times, derivatives=2)
    for other in (window, popped, traj.clone(), traj.detach(), traj.to(F64)):
        for a, b in zip(other.evaluate(times, derivatives=2), reference):
            assert torch.allclose(a, b, atol=1e-13, rtol=0)
    assert popped.t0 == traj.knot_time(2) and window.t0 == traj.knot_time(2)
    assert np.array_equal(popped.knot_times(), traj.knot_times()[2:])


def test_pushing_the_uniform_time_keeps_the_trajectory_uniform_and_bitwise_equal():
    R, P = random_controls(33, 7)
    plain = BSplineTrajectory.empty(2.0, 0.25, torch.zeros(1, dtype=F64))
    timed = BSplineTrajectory.empty(2.0, 0.25, torch.zeros(1, dtype=F64))
    for k in range(7):
        plain.push_back(R[k], P[k])
        timed.push_back(R[k], P[k], knot_time=timed.knot_time(k))
    assert timed.uniform and plain.uniform
    times = np.linspace(*plain.domain(), 9)
    for a, b in zip(plain.evaluate(times, 2), timed.evaluate(times, 2)):
        assert torch.equal(a, b)
    nonuniform = BSplineTrajectory(R, P, 0.25, plain.t0, knots=plain.knot_times())  # same times, stored
    for a, b in zip(plain.evaluate(times, 2), nonuniform.evaluate(times, 2)):
        assert torch.allclose(a, b, atol=1e-12, rtol=0)


def test_bad_knot_times_are_named():
    R, P = random_controls(34, 5)
    with pytest.raises(ValueError, match="strictly increasing, got 0.5 s then 0.5 s"):
        BSplineTrajectory(R, P, 0.25, 0.0, knots=[0.0, 0.5, 0.5, 0.7, 0.9])
    with pytest.raises(ValueError, match="t0 = 0.1 s must equal knot 0"):
        BSplineTrajectory(R, P, 0.25, 0.1, knots=[0.0, 0.5, 0.6, 0.7, 0.9])
    with pytest.raises(ValueError, match="must hold knot 0"):
        BSplineTrajectory(R, P, 0.25, 0.0, knots=[0.0, 0.5], knot_offset=1)


def test_planning_an_interval_end_sets_that_knot_and_only_uncovered_intervals_can_be_planned():
    R, P = random_controls(35, 6)
    traj = BSplineTrajectory.empty(1.0, 0.25, torch.zeros(1, dtype=F64))
    traj.plan_interval_end(1, traj.interval(0)[1] + 0.1)  # before any control point, as the loop does
    assert traj.interval(1) == (1.25, 1.35) and not traj.uniform
    for k in range(5):
        traj.push_back(R[k], P[k])
    assert traj.knot_times()[4] == 1.35 and traj.domain() == (1.0, 1.35)  # intervals 0, 1 covered
    with pytest.raises(ValueError, match="interval 1 is already covered by the 5 control points"):
        traj.plan_interval_end(1, 1.4)
    traj.plan_interval_end(2, 1.5)
    traj.push_back(R[5], P[5])
    assert traj.interval(2) == (1.35, 1.5)
    # the curve is the non-uniform spline on exactly these knots (knots.evaluate, checked against scipy)
    knot_vector = np.r_[1.0 - 2 * 0.25 + 0.25 * np.arange(4), 1.35, 1.5, 1.75, 2.0]
    times = np.linspace(*traj.domain(), 13)
    for a, b in zip(traj.evaluate(times, 2), knots.evaluate(R, P, times, knot_vector, 2)):
        assert torch.equal(a, b)


def test_knot_time_before_is_the_uniform_arithmetic_or_the_stored_knot():
    uniform = BSplineTrajectory.empty(1e9 + 0.1, 0.3, torch.zeros(1, dtype=F64))
    assert uniform.knot_time_before(7, 3) == uniform.knot_time(7) - 3 * 0.3  # bit for bit, not t0 + 4 dt
    uneven = uneven_trajectory()
    assert uneven.knot_time_before(7, 3) == uneven.knot_time(4)


def test_spline_poses_keep_the_knot_times():
    traj = uneven_trajectory(36, 8)
    times = np.linspace(*traj.domain(), 11)
    model = SplinePoses(traj, [3, 4], times, traj.poses(times), 1e-3, 1e-3)
    rebuilt = model.trajectory()
    assert np.array_equal(rebuilt.knot_vector(), traj.knot_vector())
    assert torch.allclose(model.poses(), traj.poses(times), atol=1e-12)


def test_planned_interval_assumes_its_own_length_for_the_knots_after_it():
    """The knots after a planned interval end continue at the planned spacing (three stored), not at dt;
    planning the next interval replaces them."""
    trajectory = BSplineTrajectory.empty(1.0, 0.3, torch.zeros(1, dtype=torch.float64))
    trajectory.plan_interval_end(1, 1.4, assumed_spacing=0.1)  # interval 1: [1.3, 1.4)
    assert [round(trajectory.interval(n)[1], 12) for n in range(5)] == [1.3, 1.4, 1.5, 1.6, 1.7]
    assert round(trajectory.interval(5)[1], 12) == 2.0  # beyond the three assumed knots: dt again
    trajectory.plan_interval_end(2, 1.55, assumed_spacing=0.15)
    assert [round(trajectory.interval(n)[1], 12) for n in range(6)] == [1.3, 1.4, 1.55, 1.7, 1.85, 2.0]
    with pytest.raises(ValueError, match="assumed_spacing"):
        trajectory.plan_interval_end(3, 1.8, assumed_spacing=0.0)


def test_knots_before_and_after_the_stored_run_continue_with_spacing_dt():
    """Oracle, the class docstring's rule by hand: stored knots 0..4 at 1.0, 1.15, 1.2, 1.4, 1.45 s
    with dt = 0.1 s continue as t_-2 = 0.8, t_-1 = 0.9 and t_5 = 1.55, t_6 = 1.65; the basalt
    convention's curve (o = 0) reads knots t_-2..t_N-1, so its first interval depends on t_-2, t_-1."""
    R, P = random_controls(37, 5)
    stored = [1.0, 1.15, 1.2, 1.4, 1.45]
    traj = BSplineTrajectory(R, P, 0.1, 1.0, convention="basalt", knots=stored)
    assert [traj.knot_time(k) for k in (-2, -1, 5, 6)] == pytest.approx([0.8, 0.9, 1.55, 1.65], abs=1e-12)
    knot_vector = np.array([0.8, 0.9] + stored)
    assert np.allclose(traj.knot_vector(), knot_vector, atol=1e-12, rtol=0)
    times = np.linspace(*traj.domain(), 7)
    for a, b in zip(traj.evaluate(times, 2), knots.evaluate(R, P, times, knot_vector, 2)):
        assert torch.allclose(a, b, atol=1e-12, rtol=0)


def test_clone_keeps_the_start_pose_as_a_copy():
    """The oracle is the original: a clone has the same start pose (the BA gauge), in a tensor of its own."""
    R, P = random_controls(39, 5)
    start_pose = make_pose(R[2], P[2])
    traj = BSplineTrajectory(R, P, 0.25, 0.0, start_pose=start_pose)
    copied = traj.clone()
    assert torch.equal(copied.start_pose, start_pose) and copied.start_pose.data_ptr() != start_pose.data_ptr()
    assert torch.equal(traj.to(torch.float32).start_pose, start_pose.float())


def test_start_weights_below_four_control_points_follow_the_knots():
    """Oracle, the Cox-de Boor values of knots.start_weights' docstring by hand: interval 0 planned to
    end at 1.1 s on dt = 0.25 s gives κ_0..κ_5 = 0.5, 0.75, 1.0, 1.1, 1.35, 1.6, so
    N_0 = 0.1² / (0.35 · 0.6), N_2 = 0.25² / (0.6 · 0.35) and (B̃_1, B̃_2) = (1 − N_0, N_2),
    with 3 control points as with 4 (the loop asks before the fourth arrives)."""
    R, P = random_controls(38, 3)
    traj = BSplineTrajectory.empty(1.0, 0.25, torch.zeros(1, dtype=F64))
    traj.plan_interval_end(0, 1.1)
    expected = (1 - 0.01 / (0.35 * 0.6), 0.0625 / (0.6 * 0.35))
    for k in range(3):
        traj.push_back(R[k], P[k])
    assert traj.start_weights() == pytest.approx(expected, abs=1e-12)
    traj.push_back(R[2], P[2])
    assert traj.start_weights() == pytest.approx(expected, abs=1e-12)


def test_a_window_keeps_the_stored_knots_it_may_plan_with():
    """Oracle, the original trajectory: window(first, stop) has t0 at knot ``first`` and the same
    knots from first − 2 to stop + 2 (the knots a push or a plan after its last point reads)."""
    traj = uneven_trajectory(40, 11)
    window = traj.window(2, 7)
    assert [window.knot_time(k) for k in range(-2, 8)] == [traj.knot_time(2 + k) for k in range(-2, 8)]


STAMP = 1305031102.175304  # a TUM stamp: float32's spacing there is 128 s
_IDENTITY_ROTATIONS = torch.eye(3, dtype=torch.float64).repeat(6, 1, 1)
_ZERO_TRANSLATIONS = torch.zeros(6, 3, dtype=torch.float64)


@pytest.mark.parametrize("name, call", [
    ("times", lambda: spline.time_in_domain(np.float32([STAMP + 0.2]), 6, 0.1, STAMP)),
    ("times", lambda: spline.time_in_domain(torch.tensor([STAMP + 0.2]), 6, 0.1, STAMP)),  # torch's default float32
    ("boundaries", lambda: knots.knots_from_boundaries(np.float32([STAMP, STAMP + 300.0]), 0.1)),
    ("knot_vector", lambda: knots.start_weights(np.float32(STAMP + 0.1 * np.arange(6)))),
    ("knots", lambda: knots.greville_times(np.float32([0, 1, 2, 3, 4, 5, 6]))),
    ("t0", lambda: BSplineTrajectory(_IDENTITY_ROTATIONS, _ZERO_TRANSLATIONS, 0.1, t0=torch.tensor(STAMP))),
    ("dt", lambda: BSplineTrajectory(_IDENTITY_ROTATIONS, _ZERO_TRANSLATIONS, np.float32(0.1), 0.0)),
    ("knots", lambda: BSplineTrajectory(_IDENTITY_ROTATIONS, _ZERO_TRANSLATIONS, 0.1, 0.0,
                                        knots=np.float32(0.1 * np.arange(8)))),
    ("first_time", lambda: BSplineTrajectory.empty(np.float32(STAMP), 0.1, _IDENTITY_ROTATIONS)),
    ("knot_time", lambda: BSplineTrajectory(_IDENTITY_ROTATIONS, _ZERO_TRANSLATIONS, 0.1, 0.0).push_back(
        torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), knot_time=np.float32(0.7))),
])
def test_float32_times_are_refused_naming_the_argument(name, call):
    """Each took a float32 stamp and rounded it by up to a minute (the spline placed 62 s early,
    time_in_domain answering False for numpy and True for torch): now a TypeError naming it."""
    with pytest.raises(TypeError, match=f"^{name} must be float64 seconds"):
        call()


@pytest.mark.parametrize("name, call", [
    ("t0", lambda: spline_fit.control_point_times(6, 0.1, np.float32(STAMP))),
    ("times", lambda: spline_fit.fit_trajectory(np.float32(STAMP + np.arange(30) / 30.0),
                                                torch.eye(4, dtype=torch.float64).repeat(30, 1, 1), 0.1)),
    ("times", lambda: spline_fit.fit_control_points(np.float32(np.arange(4) / 30.0),
                                                    torch.eye(4, dtype=torch.float64).repeat(4, 1, 1), 0.1, -0.2, 6)),
])
def test_the_curve_fit_refuses_float32_times_naming_them(name, call):
    """fit_trajectory on float32 TUM stamps said "not increasing" (the stamps had merged)."""
    with pytest.raises(TypeError, match=f"^{name} must be float64 seconds"):
        call()


@pytest.mark.parametrize("last", [0.3, 0.3 + 3e-13, 0.30000000001, 0.35])
def test_fit_trajectory_reaches_a_last_time_just_past_a_whole_number_of_intervals(last):
    """Oracle: the spline's own domain rule (time_in_domain) and the poses themselves (identity
    poses fit to identity).  A last time 3e-13 s past 3 dt got 3 intervals and then failed on its own
    evaluation ("outside the spline domain"); it gets a fourth, and 0.3 exactly keeps three."""
    times = np.array([0.0, 0.1, 0.2, last])
    fitted = spline_fit.fit_trajectory(times, torch.eye(4, dtype=torch.float64).repeat(4, 1, 1), 0.1)
    assert fitted.n_ctrl == (6 if last == 0.3 else 7)
    assert spline.time_in_domain(times, fitted.n_ctrl, fitted.dt, fitted.t0).all()
    assert torch.allclose(fitted.poses(times), torch.eye(4, dtype=torch.float64).expand(4, 4, 4), atol=1e-9)
