"""Local BA (local_ba.py): curve approximation (Eq. 11), the window, the constant-velocity start.

Oracles: the ground-truth path of the synthetic generator and exact constant-velocity motions
(spline.md 3.2: affine control points reproduce them exactly).

Global BA's tests live here too (global_ba.py: which poses and control points are free, the
current frame's slot and ray share), with Co-SLAM's rules worked by hand as the oracle.
"""

import copy

import numpy as np
import pytest
import torch

from tsslam_ref import config, global_ba, knots, local_ba, spline
from tsslam_ref.bundle import BAStats, KeyframeDatabase, SplinePoses
from tsslam_ref.geometry import make_pose, so3_exp
from tsslam_ref.losses import RenderLossSettings
from tsslam_ref.render import RayBatch
from tsslam_ref.synthetic import builtin_trajectory
from tsslam_ref.trajectory import BSplineTrajectory

TIMES = 0.5 + np.arange(90) / 30.0


def grow(poses: torch.Tensor, cfg: config.Config, n_intervals: int = 9):
    """Curve approximation alone, interval after interval; max position error after each."""
    truth = torch.as_tensor(builtin_trajectory(TIMES), dtype=poses.dtype)
    trajectory = BSplineTrajectory.empty(float(TIMES[0]), cfg.spline.dt, poses)
    errors = []
    for n in range(n_intervals):
        start, end = local_ba.fit_time_range(trajectory, n, cfg.local_ba)
        inside = np.nonzero((TIMES >= start) & (TIMES < end))[0]
        trajectory = local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba)
        covered = trajectory.covers(TIMES)
        errors.append(float((trajectory.poses(TIMES[covered])[:, :3, 3] - truth[covered, :3, 3]).norm(dim=-1).max()))
    return trajectory, np.array(errors)


def noisy_truth(sigma: float, seed: int = 0) -> torch.Tensor:
    poses = torch.as_tensor(builtin_trajectory(TIMES))
    noise = torch.randn(len(TIMES), 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    poses[:, :3, 3] += sigma * noise
    return poses


def test_eq11_curve_approximation_stays_at_the_noise_level():
    cfg = config.tiny()
    for sigma in (0.0, 0.001, 0.01):
        trajectory, errors = grow(noisy_truth(sigma), cfg)
        assert trajectory.n_ctrl == 4 + 8
        assert errors.max() < 3.5 * sigma + 0.002, (sigma, errors)  # bounded: no growth with the intervals


def test_eq11_single_point_fit_as_written_in_the_paper_amplifies_errors():
    """Why local_ba fits three points: moving only the new one (weight <= 1/6) diverges."""
    cfg = copy.deepcopy(config.tiny())
    cfg.local_ba.fit_controls = 1
    _, errors = grow(noisy_truth(0.001), cfg, n_intervals=6)
    assert errors[-1] > 10 * errors[1], errors


def mid_interval_errors(poses: torch.Tensor, cfg, n_intervals: int) -> np.ndarray:
    """(n_intervals,) signed x error (m) of the grown curve against the truth in each interval's middle."""
    trajectory, _ = grow(poses, cfg, n_intervals=n_intervals)
    middles = np.array([trajectory.interval(n)[0] + 0.5 * trajectory.dt for n in range(n_intervals)])
    truth = torch.as_tensor(builtin_trajectory(middles), dtype=poses.dtype)
    return (trajectory.poses(middles)[:, 0, 3] - truth[:, 0, 3]).numpy()


def test_holding_a_point_of_the_newest_interval_makes_the_curve_approximation_ring():
    """A 2 cm tracking error in the first interval only (every later pose exact).  Fitting the
    three newest points (the default) holds the fourth newest, which still shapes the newest
    interval: the error returns with alternating sign in every interval and hardly shrinks.
    Fitting four points (the spline's order) forgets it within a few intervals."""
    poses = torch.as_tensor(builtin_trajectory(TIMES))
    in_first_interval = np.nonzero(TIMES < TIMES[0] + config.tiny().spline.dt)[0][1:]
    poses[in_first_interval, 0, 3] += 0.02
    assert config.tiny().local_ba.fit_controls == 3
    ringing = mid_interval_errors(poses, config.tiny(), 9)
    four = copy.deepcopy(config.tiny())
    four.local_ba.fit_controls = 4
    settling = mid_interval_errors(poses, four, 9)
    assert abs(ringing[7]) > 0.4 * abs(ringing[1]), ringing
    assert np.all(np.sign(ringing[2:8]) == -np.sign(ringing[1:7])), ringing  # alternating
    assert abs(settling[7]) < 0.05 * abs(settling[1]), settling


def test_first_interval_constant_velocity_fit_is_exact_for_constant_velocity_motion():
    dt, first = 0.25, 10.0
    times = first + np.arange(8) / 30.0
    velocity = torch.tensor([0.3, -0.1, 0.05], dtype=torch.float64)
    rate = torch.tensor([0.2, 0.4, -0.3], dtype=torch.float64)
    start = make_pose(so3_exp(torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)), torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    elapsed = torch.as_tensor(times - first)
    poses = make_pose(start[:3, :3] @ so3_exp(elapsed[:, None] * rate), start[:3, 3] + elapsed[:, None] * velocity)
    trajectory = BSplineTrajectory.empty(first, dt, poses)
    rotations, translations = local_ba.constant_velocity_control_points(trajectory, times, poses)
    sample = spline.evaluate(rotations, translations, times, dt, trajectory.t0, derivatives=2)
    assert torch.allclose(make_pose(sample.rotation, sample.translation), poses, atol=1e-10)
    assert torch.allclose(sample.velocity_world, velocity.expand(8, 3), atol=1e-10)
    assert torch.allclose(sample.omega_body, rate.expand(8, 3), atol=1e-10)
    assert float(sample.acceleration_world.abs().max()) < 1e-10


def test_extrapolated_control_point_continues_the_polygon():
    rotations = so3_exp(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1], [0.0, 0.0, 0.2]], dtype=torch.float64))
    translations = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.5, 0.0]], dtype=torch.float64)
    trajectory = BSplineTrajectory(rotations, translations, 0.2, 0.0)
    rotation, translation = local_ba.extrapolate_control_point(trajectory)
    assert torch.allclose(rotation, so3_exp(torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)), atol=1e-12)
    assert torch.allclose(translation, torch.tensor([3.0, 1.0, 0.0], dtype=torch.float64))


def test_extrapolated_control_points_stay_rotations_over_many_intervals():
    """Oracle: SO(3) itself (RᵀR = I) and the constant-rate continuation R_k = Exp(k w).  Each new
    float32 point is made from the last two; without projecting it back onto SO(3) the drift of
    float32 products grows about 2.4 times per point and passes 1e-5 within 20 points."""
    rate = torch.tensor([0.02, -0.05, 0.04], dtype=torch.float64)  # rad per control point
    k = torch.arange(4, dtype=torch.float64)[:, None]
    trajectory = BSplineTrajectory(so3_exp(k * rate).float(), (k * 0.1).expand(4, 3).float(), 0.1, 0.0)
    for _ in range(40):
        rotation, translation = local_ba.extrapolate_control_point(trajectory)
        trajectory = BSplineTrajectory(torch.cat([trajectory.control_rotations, rotation[None]]),
                                       torch.cat([trajectory.control_translations, translation[None]]), 0.1, 0.0)
    rotations = trajectory.control_rotations.double()
    drift = (rotations.transpose(-1, -2) @ rotations - torch.eye(3, dtype=torch.float64)).abs().amax()
    assert float(drift) < 1e-5, float(drift)
    expected = so3_exp(43 * rate)
    assert float((rotations[-1] - expected).abs().max()) < 1e-4


def test_window_time_range_is_where_the_window_acts():
    """Control points outside the window shape no time after the window range starts... and the
    window's points shape no time before it (local support)."""
    generator = torch.Generator().manual_seed(0)
    n_ctrl, dt = 12, 0.3
    trajectory = BSplineTrajectory(so3_exp(0.2 * torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64)),
                                   torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64), dt, 0.0)
    window = local_ba.window_controls(trajectory, 5)
    start, end = local_ba.window_time_range(trajectory, 5)
    assert window == list(range(7, 12)) and np.isclose(start, 6 * dt) and np.isclose(end, trajectory.domain()[1])
    before = spline.active_control_indices(np.array([start - 1e-3]), n_ctrl, dt, 0.0).reshape(-1).tolist()
    after = spline.active_control_indices(np.array([start + 1e-3]), n_ctrl, dt, 0.0).reshape(-1).tolist()
    assert set(before).isdisjoint(window) and set(after) & set(window)


def test_the_spline_starts_at_frame_0_and_keeps_starting_there():
    """The gauge: frame 0's spline pose is its own (noisy) pose after the first fit; later fits
    move control points 1 and 2 but control point 0 follows them so that frame 0 keeps its pose,
    and the window never holds control point 0."""
    cfg = config.tiny()
    poses = noisy_truth(0.01, seed=3)
    first, _ = grow(poses, cfg, n_intervals=1)
    assert torch.allclose(first.poses(TIMES[:1])[0], poses[0], atol=1e-9)
    assert torch.equal(first.start_pose, poses[0])
    for n_ctrl in (4, 5, 8):
        shaped = first.with_controls(first.control_rotations[:1].expand(n_ctrl, 3, 3),
                                     first.control_translations[:1].expand(n_ctrl, 3))
        window = local_ba.window_controls(shaped, 6)
        assert min(window) >= local_ba.N_ANCHOR_CONTROLS == 1 and window[-1] == n_ctrl - 1
    grown, _ = grow(poses, cfg, n_intervals=6)
    moved = float((grown.control_translations[2] - first.control_translations[2]).norm())
    assert moved > 1e-4  # the fits moved point 2 ...
    assert torch.allclose(grown.poses(TIMES[:1])[0], poses[0], atol=1e-9)  # ... and frame 0 did not move


def test_first_interval_fit_is_exact_for_constant_velocity_motion_on_uneven_knots():
    """With the next interval planned shorter, the line's control points sit at the knots' Greville
    abscissae; the non-uniform spline (knots.evaluate) then reproduces the motion exactly."""
    first = 10.0
    times = first + np.arange(8) / 30.0
    velocity = torch.tensor([0.3, -0.1, 0.05], dtype=torch.float64)
    rate = torch.tensor([0.2, 0.4, -0.3], dtype=torch.float64)
    elapsed = torch.as_tensor(times - first)
    poses = make_pose(so3_exp(elapsed[:, None] * rate), 1.0 + elapsed[:, None] * velocity)
    trajectory = BSplineTrajectory.empty(first, 0.25, poses)
    trajectory.plan_interval_end(1, trajectory.interval(0)[1] + 0.12)
    rotations, translations = local_ba.constant_velocity_control_points(trajectory, times, poses)
    sample = knots.evaluate(rotations, translations, times, trajectory.knot_vector(4), derivatives=2)
    assert torch.allclose(make_pose(sample.rotation, sample.translation), poses, atol=1e-10)
    assert torch.allclose(sample.velocity_world, velocity.expand(8, 3), atol=1e-10)
    assert float(sample.acceleration_world.abs().max()) < 1e-10


def test_curve_approximation_on_uneven_knots_keeps_them_and_stays_at_the_noise_level():
    """Intervals alternating 0.15 s and 0.3 s: the fit follows the ground truth as on uniform knots."""
    cfg = config.tiny()
    poses = noisy_truth(0.002)
    truth = torch.as_tensor(builtin_trajectory(TIMES), dtype=poses.dtype)
    trajectory = BSplineTrajectory.empty(float(TIMES[0]), cfg.spline.dt, poses)
    for n in range(9):
        trajectory.plan_interval_end(n + 1, trajectory.interval(n)[1] + (0.15 if n % 2 else 0.3))
        start, end = local_ba.fit_time_range(trajectory, n, cfg.local_ba)
        inside = np.nonzero((TIMES >= start) & (TIMES < end))[0]
        trajectory = local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba)
    lengths = np.diff(trajectory.knot_times()[2:])
    assert np.allclose(lengths[1:], [0.3 if n % 2 else 0.15 for n in range(1, len(lengths))], atol=1e-9)
    covered = trajectory.covers(TIMES)
    error = (trajectory.poses(TIMES[covered])[:, :3, 3] - truth[covered, :3, 3]).norm(dim=-1)
    assert float(error.max()) < 0.01, float(error.max())


def test_window_is_held_in_time_with_uneven_knots():
    """With non-uniform knots the window takes the fewest newest points (at least M) whose range
    spans M dt seconds; oracle: the span of every candidate range computed from the knot times."""
    generator = torch.Generator().manual_seed(1)
    n_ctrl, dt, window = 16, 0.3, 4
    uneven = np.cumsum(np.r_[0.0, 0.3, 0.3, 0.1, 0.12, 0.1, 0.4, 0.11, 0.1, 0.1, 0.3, 0.1, 0.1, 0.1, 0.1, 0.1,
                             0.1, 0.1, 0.1])
    rotations = so3_exp(0.2 * torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64))
    translations = torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64)
    uniform = BSplineTrajectory(rotations, translations, dt, 0.0)
    assert local_ba.window_size(uniform, window) == window  # the paper's M control points, as before
    for n in range(6, n_ctrl + 1):
        trajectory = BSplineTrajectory(rotations[:n], translations[:n], dt, 0.0, knots=uneven)
        times = trajectory.knot_times()
        spans = {m: times[n - 1] - trajectory.knot_time(n - m - 1) for m in range(window, n)}
        long_enough = [m for m in spans if spans[m] >= window * dt - 1e-9]
        expected = min(long_enough) if long_enough else n - local_ba.N_ANCHOR_CONTROLS
        assert local_ba.window_size(trajectory, window) == expected, n
        controls = local_ba.window_controls(trajectory, window)
        assert controls == list(range(n - expected, n))
        start, end = local_ba.window_time_range(trajectory, window)
        assert np.isclose(start, max(trajectory.domain()[0], trajectory.knot_time(n - expected - 1)))
        if long_enough:
            assert end - start >= window * dt - 1e-9 or start == trajectory.domain()[0]
    assert local_ba.window_size(trajectory, window) > window  # the short intervals at the end add points


def test_curve_approximation_fits_a_stretch_held_in_time_with_uneven_knots():
    """fit_size: the fewest newest intervals (at least fit_controls) spanning fit_controls dt
    seconds, oracle: sums of the interval lengths; fit_time_range starts at the first of them;
    curve_approximation frees exactly that many newest points."""
    dt, fit_controls = 0.3, 3
    lengths = [0.3, 0.3, 0.1, 0.12, 0.1, 0.4, 0.11, 0.1, 0.1, 0.3, 0.1, 0.1, 0.1, 0.1]
    boundaries = np.cumsum(np.r_[0.0, lengths])
    truth = torch.as_tensor(builtin_trajectory(np.array([0.0])))[0]
    cfg = config.tiny()
    cfg.local_ba.fit_controls = fit_controls
    for n in range(2, len(lengths) - 3):
        n_ctrl = n + 3  # points before interval n's is added (paper convention)
        trajectory = BSplineTrajectory(truth[:3, :3].expand(n_ctrl, 3, 3).clone(), truth[:3, 3].expand(n_ctrl, 3).clone(),
                                       dt, 0.0, knots=boundaries)
        end = 3 + n  # interval n = [t_{n+2}, t_{n+3}) (paper convention)
        assert np.isclose(trajectory.interval(n)[1], boundaries[end])
        spans = {m: boundaries[end] - boundaries[end - m] for m in range(fit_controls, end + 1)}
        long_enough = [m for m in spans if spans[m] >= fit_controls * dt - 1e-9]
        size = local_ba.fit_size(trajectory, n, fit_controls)
        if long_enough:
            assert size == min(long_enough), n
            assert np.isclose(local_ba.fit_time_range(trajectory, n, cfg.local_ba)[0],
                              max(boundaries[end - size], trajectory.interval(0)[0]))
        assert fit_controls <= size <= n_ctrl
        assert local_ba.fit_size(BSplineTrajectory(trajectory.control_rotations, trajectory.control_translations, dt, 0.0),
                                 n, fit_controls) == fit_controls  # uniform knots: as before
    times = np.linspace(boundaries[end - size], boundaries[end] - 1e-3, 25)
    poses = torch.as_tensor(builtin_trajectory(times))
    fitted = local_ba.curve_approximation(trajectory, times, poses, cfg.local_ba, free_controls=size)
    moved = (fitted.control_translations[:n_ctrl] - trajectory.control_translations).norm(dim=-1) > 0
    assert moved.nonzero().reshape(-1).tolist() == list(range(n_ctrl + 1 - size, n_ctrl)), size


def test_curve_approximation_reports_the_levenberg_marquardt_iterations_it_ran(monkeypatch):
    """The runtime table divides the curve approximation's time by the iterations that ran, and
    Levenberg-Marquardt stops early.  Oracle: the Jacobians evaluated (one per iteration), counted
    by wrapping ``torch.func.jacrev``."""
    cfg = config.tiny()
    poses = noisy_truth(0.001)
    trajectory, _ = grow(poses, cfg, n_intervals=4)
    jacobians = []
    jacrev = torch.func.jacrev

    def counting_jacrev(*args, **kwargs):
        jacobians.append(1)
        return jacrev(*args, **kwargs)

    monkeypatch.setattr(torch.func, "jacrev", counting_jacrev)
    start, end = local_ba.fit_time_range(trajectory, 4, cfg.local_ba)
    inside = np.nonzero((TIMES >= start) & (TIMES < end))[0]
    report = {}
    local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba, report=report)
    assert 0 < report["iterations"] == len(jacobians) < cfg.local_ba.fit_iters
    local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba, fit=False, report=report)
    assert report["iterations"] == 0


def test_curve_approximation_with_no_free_point_only_extrapolates_and_refuses_float32_times():
    """``free_controls=0`` freed every point (``fixed[-0:]`` is the whole tensor), moving the old
    ones.  Oracle: with no point free the result is the extrapolated polygon, ``fit=False``'s.
    Float32 stamps (62 s off at TUM's 1.3e9 s) were cast and then reported as outside the domain."""
    cfg = config.tiny()
    poses = noisy_truth(0.001)
    trajectory, _ = grow(poses, cfg, n_intervals=4)
    start, end = local_ba.fit_time_range(trajectory, 4, cfg.local_ba)
    inside = np.nonzero((TIMES >= start) & (TIMES < end))[0]
    none_free = local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba, free_controls=0)
    extrapolated = local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba, fit=False)
    assert torch.equal(none_free.control_translations, extrapolated.control_translations)
    assert torch.equal(none_free.control_rotations, extrapolated.control_rotations)
    with pytest.raises(ValueError, match="free_controls must be >= 0, got -1"):
        local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba, free_controls=-1)
    with pytest.raises(TypeError, match="^times must be float64 seconds"):
        local_ba.curve_approximation(trajectory, TIMES[inside].astype(np.float32), poses[inside], cfg.local_ba)


def test_keyframes_and_spline_pose_slots_refuse_float32_times():
    """``SplinePoses`` cast float32 slot times and ``KeyframeDatabase.add`` a float32 stamp to
    float64 silently: at 1.3e9 s every slot then fell outside the spline and kept its constant pose."""
    rays = RayBatch(torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2), torch.zeros(2, dtype=torch.long))
    with pytest.raises(TypeError, match="^timestamp must be float64 seconds"):
        KeyframeDatabase().add(0, np.float32(1305031102.5), rays)
    trajectory = BSplineTrajectory(so3_exp(torch.zeros(6, 3, dtype=torch.float64)), torch.zeros(6, 3, dtype=torch.float64),
                                   0.3, 1305031102.0)
    fallback = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    stamps = trajectory.domain()[0] + np.array([0.1, 0.2])
    with pytest.raises(TypeError, match="^slot_times must be float64 seconds"):
        SplinePoses(trajectory, [3], stamps.astype(np.float32), fallback, 1e-3, 1e-3)
    assert SplinePoses(trajectory, [3], stamps, fallback, 1e-3, 1e-3).slot_valid.all()


def captured_optimiser(monkeypatch, module):
    """Replace ``module``'s optimiser (``joint_optimization``) by a recorder: the stage's choices
    (which poses move, which rays feed which slot, its options) are then read off the
    (ray_sources, poses, keyword options) it was handed, without running a field."""
    calls = []

    def record(field_model, map_optimizer, ray_sources, poses, *args, **kwargs):
        calls.append((ray_sources, poses, kwargs))
        return BAStats()

    monkeypatch.setattr(module, "joint_optimization", record)
    return calls


def keyframe_rays(n_keyframes: int, n_rays: int, n_current: int):
    """A database of ``n_keyframes`` keyframes at 0.1 s, 0.2 s, ... with ``n_rays`` rays each, and
    the current frame's ``n_current`` rays (frame ids 77: relabelled by global BA)."""
    generator = torch.Generator().manual_seed(n_keyframes)

    def rays(count):
        return RayBatch(torch.randn(count, 3, generator=generator), torch.rand(count, 3, generator=generator),
                        torch.rand(count, generator=generator), torch.full((count,), 77))

    database = KeyframeDatabase()
    for slot in range(n_keyframes):
        database.add(5 * slot, 0.1 * (slot + 1), rays(n_rays))
    return database, rays(n_current)


def test_keyframe_database_slots_are_insertion_positions_and_rays_are_relabelled_by_position():
    """By hand: three keyframes added get slots 0, 1, 2 (the slot add() returns indexes frame_indices
    and timestamps); rays([2, 0]) holds keyframe 2's rays as slot 0, then keyframe 0's as slot 1."""
    database, _ = keyframe_rays(0, 0, 0)
    stored = [keyframe_rays(1, n, 0)[0].rays() for n in (3, 4, 5)]
    slots = [database.add(frame, 0.5 * frame, rays) for frame, rays in zip((10, 20, 30), stored)]
    assert slots == [0, 1, 2] and len(database) == 3
    assert [database.frame_indices[slot] for slot in slots] == [10, 20, 30]
    assert [database.timestamps[slot] for slot in slots] == [5.0, 10.0, 15.0]
    picked = database.rays([2, 0])
    assert picked.frame_ids.tolist() == [0] * 5 + [1] * 3
    assert torch.equal(picked.depth, torch.cat([stored[2].depth, stored[0].depth]))


def test_keyframe_database_holds_every_keyframes_rays_as_their_join_while_it_grows():
    """Keyframes of 1-40 rays added one by one (the pool grows several times): after each add, all
    rays equal the join of every batch given, batch k relabelled k (built here with ``torch.cat``),
    each slot's rays are its batch, a batch changed by its caller afterwards changes nothing stored,
    and a view handed out earlier still holds what it held.  No keyframe: ValueError."""
    with pytest.raises(ValueError):
        KeyframeDatabase().rays()
    database, given, earlier = KeyframeDatabase(), [], []
    generator = torch.Generator().manual_seed(3)
    for slot, count in enumerate((1, 2, 7, 40, 3, 16, 33, 5)):
        rays = keyframe_rays(1, count, 0)[0].rays()
        rays = RayBatch(rays.directions_cam, torch.rand(count, 3, generator=generator), rays.depth, rays.frame_ids)
        given.append(RayBatch(*(values.clone() for values in (rays.directions_cam, rays.rgb, rays.depth,
                                                                  rays.frame_ids))))
        assert database.add(slot, 0.1 * slot, rays) == slot
        rays.depth.fill_(-1.0)  # the caller's batch, changed after add
        everything = database.rays()
        for name in ("directions_cam", "rgb", "depth"):
            assert torch.equal(getattr(everything, name), torch.cat([getattr(batch, name) for batch in given]))
        assert everything.frame_ids.tolist() == [k for k, batch in enumerate(given) for _ in range(len(batch))]
        for k, batch in enumerate(given):
            stored = database.slot_rays(k)
            assert torch.equal(stored.rgb, batch.rgb) and set(stored.frame_ids.tolist()) == {k}
        earlier.append((everything, torch.cat([batch.depth for batch in given])))
    assert all(torch.equal(view.depth, expected) for view, expected in earlier)


def test_global_ba_frees_every_keyframe_but_the_first_and_gives_the_current_frame_its_share(monkeypatch):
    """(Global BA, kept in this file.)  Oracle: Co-SLAM's rules worked by hand for n_rays = 100,
    min_pixels_cur = 10: keyframe 0 fixed, the others free, the current frame (slot K) free iff
    optim_cur; its rays drawn as slot K, max(100 // K, 10) of them, at most those it has."""
    calls = captured_optimiser(monkeypatch, global_ba)
    mapping = copy.deepcopy(config.tiny().mapping)
    mapping.n_rays, mapping.min_pixels_cur = 100, 10
    settings = RenderLossSettings.from_config(config.tiny())
    for n_keyframes, optim_cur, n_current, share, fixed in (
            (3, False, 500, 33, [True, False, False, True]),
            (3, True, 500, 33, [True, False, False, False]),
            (20, False, 500, 10, [True] + [False] * 19 + [True]),
            (4, True, 12, 12, [True, False, False, False, False]),
            (1, True, 500, 100, [True, True])):  # one keyframe: only the map moves
        mapping.optim_cur = optim_cur
        database, current_rays = keyframe_rays(n_keyframes, 6, n_current)
        generator = torch.Generator().manual_seed(n_keyframes)
        poses = make_pose(so3_exp(0.1 * torch.randn(n_keyframes + 1, 3, generator=generator)),
                          torch.randn(n_keyframes + 1, 3, generator=generator))
        current = global_ba.CurrentFrame(current_rays, 0.1 * (n_keyframes + 1), poses[-1])
        global_ba.coslam_global_ba(None, None, database, poses[:-1], current, mapping, settings)
        sources, pose_model, _ = calls.pop()
        assert pose_model.fixed.tolist() == fixed, (n_keyframes, optim_cur)
        assert torch.allclose(pose_model.poses(), poses, atol=1e-6)  # the given poses, slot by slot
        (keyframe_pool, keyframe_draw), (current_pool, current_draw) = sources
        assert keyframe_draw == 100 and current_draw == share, (n_keyframes, current_draw)
        assert keyframe_pool.frame_ids.tolist() == [slot for slot in range(n_keyframes) for _ in range(6)]
        assert current_pool.frame_ids.tolist() == [n_keyframes] * n_current
        assert torch.equal(current_pool.directions_cam, current_rays.directions_cam)


def test_tsslam_global_ba_moves_only_the_given_control_points_and_renders_the_current_frame_on_the_spline(monkeypatch):
    """(Global BA, kept in this file.)  Oracle: the trajectory's own pose at each slot's time (the
    spline itself is checked in tests/test_spline.py), with the slot times, the domain [0.2, 0.7)
    and the free points worked by hand; slots outside the domain keep the given pose; the current
    frame is slot K at its own time."""
    calls = captured_optimiser(monkeypatch, global_ba)
    generator = torch.Generator().manual_seed(4)
    n_ctrl, dt = 8, 0.1
    rotations = so3_exp(0.3 * torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64))
    translations = torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64)
    trajectory = BSplineTrajectory(rotations, translations, dt, 0.0)  # domain [0.2, 0.7)
    database, current_rays = keyframe_rays(7, 4, 50)  # keyframes at 0.1 .. 0.7 s
    given = make_pose(so3_exp(0.1 * torch.randn(8, 3, generator=generator, dtype=torch.float64)),
                      torch.randn(8, 3, generator=generator, dtype=torch.float64))
    current = global_ba.CurrentFrame(current_rays, 0.45, given[-1])
    cfg = config.tiny()
    global_ba.tsslam_global_ba(None, None, database, given[:-1], trajectory, [2, 3], current, cfg.mapping,
                               cfg.dynamics, RenderLossSettings.from_config(cfg))
    sources, pose_model, _ = calls.pop()
    assert pose_model.free_mask.tolist() == [k in (2, 3) for k in range(n_ctrl)]
    slot_times = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.45])
    assert np.allclose(pose_model.slot_times, slot_times)
    rendered = pose_model.poses()
    inside = (slot_times >= 0.2 - 1e-12) & (slot_times < 0.7 - 1e-12)
    for slot, time in enumerate(slot_times):
        expected = trajectory.poses(np.array([time]))[0] if inside[slot] else given[slot]
        assert torch.allclose(rendered[slot], expected, atol=1e-12), slot
    assert sources[1][0].frame_ids.tolist() == [7] * 50


def test_extrapolated_control_point_keeps_the_body_rate_of_a_turned_polygon():
    """Oracle: points R_k = R_base Exp(k w) with R_base and w about different axes (rotations
    that do not commute) continue at R_3 = R_base Exp(3 w); a product taken in the wrong order
    agrees only when every rotation shares one axis."""
    base = so3_exp(torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64))
    rate = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    k = torch.arange(3, dtype=torch.float64)[:, None]
    translations = torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.1, 0.2], [0.7, 0.1, 0.5]], dtype=torch.float64)
    trajectory = BSplineTrajectory(base @ so3_exp(k * rate), translations, 0.2, 0.0)
    rotation, translation = local_ba.extrapolate_control_point(trajectory)
    assert torch.allclose(rotation, base @ so3_exp(3 * rate), atol=1e-12)
    assert torch.allclose(translation, torch.tensor([1.0, 0.3, 0.8], dtype=torch.float64), atol=1e-12)


def test_curve_approximation_on_uneven_knots_keeps_the_curve_starting_at_frame_0():
    """The gauge with a short second interval: every later fit re-pins control point 0, and with
    uneven knots it must use their start weights.  Oracle: frame 0's own (noisy) pose, which the
    curve evaluates to at the domain start after every interval."""
    cfg = config.tiny()
    poses = noisy_truth(0.01, seed=5)
    trajectory = BSplineTrajectory.empty(float(TIMES[0]), cfg.spline.dt, poses)
    for n, length in enumerate((0.12, 0.3, 0.15)):
        trajectory.plan_interval_end(n + 1, trajectory.interval(n)[1] + length)
        start, end = local_ba.fit_time_range(trajectory, n, cfg.local_ba)
        inside = np.nonzero((TIMES >= start) & (TIMES < end))[0]
        trajectory = local_ba.curve_approximation(trajectory, TIMES[inside], poses[inside], cfg.local_ba)
        assert not trajectory.uniform
        assert torch.allclose(trajectory.poses(TIMES[:1])[0], poses[0], atol=1e-9), n


def captured_local_ba(monkeypatch):
    """:func:`captured_optimiser` of local BA, with L_DR replaced by a recorder of where it is sampled."""

    def record_dynamics(poses, time_range, dynamics, generator):
        return None if time_range is None else ("L_DR over", time_range)  # None: no regulariser

    monkeypatch.setattr(local_ba, "dynamics_term", record_dynamics)
    return captured_optimiser(monkeypatch, local_ba)


def ten_point_window():
    """A random 10-point uniform trajectory (dt = 0.1 s, t0 = 0) and tiny settings with M = 4."""
    generator = torch.Generator().manual_seed(2)
    trajectory = BSplineTrajectory(so3_exp(0.2 * torch.randn(10, 3, generator=generator, dtype=torch.float64)),
                                   torch.randn(10, 3, generator=generator, dtype=torch.float64), 0.1, 0.0)
    cfg = copy.deepcopy(config.tiny())
    cfg.local_ba.window, cfg.local_ba.joint_iters = 4, 3
    return trajectory, cfg, RenderLossSettings.from_config(cfg)


def test_local_ba_refines_the_window_points_with_dynamics_over_the_window(monkeypatch):
    """Oracle by hand: 10 points, dt = 0.1 s, t0 = 0, M = 4: points 6..9 free, the map frozen,
    L_DR over the window's times [t_5, t_9) = [0.5, 0.9) s, none with use_dynamics off."""
    calls = captured_local_ba(monkeypatch)
    trajectory, cfg, settings = ten_point_window()
    _, frame_rays = keyframe_rays(1, 4, 5)
    for use_dynamics, dynamics in ((True, ("L_DR over", pytest.approx((0.5, 0.9)))), (False, None)):
        cfg.local_ba.use_dynamics = use_dynamics
        local_ba.refine_window(None, trajectory, np.array([0.6, 0.8]), [frame_rays, frame_rays], cfg.local_ba,
                               cfg.dynamics, settings)
        _, poses, options = calls.pop()
        assert poses.free_mask.tolist() == [False] * 6 + [True] * 4
        assert options["extra_loss"] == dynamics, use_dynamics
        assert options["optimise_map"] is False


def test_local_ba_joint_stage_takes_the_keyframes_inside_the_window_range(monkeypatch):
    """Oracle by hand (the layout above): the window's range is [0.5, 0.9) s, so stage 3 takes the
    keyframes at 0.5 s (the start, included) and 0.7 s, not 0.4 s nor 0.9 s (the end)."""
    calls = captured_local_ba(monkeypatch)
    trajectory, cfg, settings = ten_point_window()
    keyframes = KeyframeDatabase()
    for index, time in enumerate((0.4, 0.5, 0.7, 0.9)):
        keyframes.add(index, time, RayBatch(torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2), torch.zeros(2)))
    cfg.local_ba.use_dynamics = True
    local_ba.joint_window(None, None, trajectory, keyframes, cfg.local_ba, cfg.dynamics, settings)
    sources, poses, options = calls.pop()
    assert np.allclose(poses.slot_times, [0.5, 0.7]) and len(sources[0][0]) == 4
    assert poses.free_mask.tolist() == [False] * 6 + [True] * 4
    assert options["extra_loss"] == ("L_DR over", pytest.approx((0.5, 0.9)))
