"""Non-uniform cumulative cubic B-spline (tsslam_ref.knots) against independent oracles.

Translation, v, a: scipy.interpolate.BSpline with the same knots (non-cumulative = cumulative
for R^3).  Rotation: omega_body from central finite differences of R(t) (Log(R(t-h)^T R(t+h))/2h),
omegadot_body from autograd of omega_body in time.  Equally spaced knots: the uniform spline.
"""

import numpy as np
import pytest
import torch
from scipy.interpolate import BSpline

from tsslam_ref import knots, spline, spline_fit
from tsslam_ref.geometry import make_pose, so3_exp, so3_log

F64 = torch.float64


def random_spline(seed: int, n_ctrl: int = 8, step: float = 0.6):
    g = torch.Generator().manual_seed(seed)
    rotations = so3_exp(torch.randn(n_ctrl, 3, generator=g, dtype=F64) * step)
    translations = torch.randn(n_ctrl, 3, generator=g, dtype=F64)
    spacing = np.random.default_rng(seed).uniform(0.03, 0.6, n_ctrl + 1)  # very uneven intervals
    knot_vector = 1.3e3 + np.cumsum(np.r_[0.0, spacing])
    return rotations, translations, knot_vector


def interior_times(knot_vector, count=97):
    """Times in the domain, away from the knots by >= 1e-3 of the shortest interval."""
    t = np.linspace(knot_vector[2], knot_vector[-3], count)
    gap = np.abs(t[:, None] - knot_vector[None, :]).min(1)
    return t[gap > 1e-3 * np.diff(knot_vector).min()]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_translation_and_derivatives_match_scipy_bspline(seed):
    R, P, kv = random_spline(seed)
    t = np.linspace(kv[2], kv[-3], 203)  # includes both ends and knots
    sample = knots.evaluate(R, P, t, kv, derivatives=2)
    oracle = BSpline(np.r_[kv[0] - 1.0, kv, kv[-1] + 1.0], P.numpy(), 3)  # tau_0, tau_{N+3} do not matter
    scale = [np.abs(oracle.derivative(k)(t)).max() for k in range(3)]
    assert np.abs(sample.translation.numpy() - oracle(t)).max() <= 1e-12 * scale[0]
    assert np.abs(sample.velocity_world.numpy() - oracle.derivative(1)(t)).max() <= 1e-11 * scale[1]
    assert np.abs(sample.acceleration_world.numpy() - oracle.derivative(2)(t)).max() <= 1e-10 * scale[2]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_omega_body_matches_central_differences_of_rotation(seed):
    R, P, kv = random_spline(seed)
    t = interior_times(kv)
    h = 1e-4 * np.diff(kv).min()  # truncation ~h², rounding of t ± h at 1.3e3 s ~2e-13/h
    before = knots.evaluate(R, P, t - h, kv).rotation
    after = knots.evaluate(R, P, t + h, kv).rotation
    fd = so3_log(before.transpose(-1, -2) @ after) / (2 * h)  # body-frame rate over [t-h, t+h]
    omega = knots.evaluate(R, P, t, kv, derivatives=1).omega_body
    assert float((omega - fd).abs().max()) <= 1e-6 * float(omega.abs().max())


@pytest.mark.parametrize("seed", [0, 1])
def test_omegadot_body_matches_autograd_of_omega(seed):
    R, P, kv = random_spline(seed)
    t = torch.tensor(interior_times(kv, 31), dtype=F64, requires_grad=True)
    sample = knots.evaluate(R, P, t, kv, derivatives=2)
    rows = [torch.autograd.grad(sample.omega_body[:, c].sum(), t, retain_graph=True)[0] for c in range(3)]
    autograd_omegadot = torch.stack(rows, dim=-1)  # each omega depends on its own time only
    expected = sample.omegadot_body.detach()
    assert float((autograd_omegadot - expected).abs().max()) <= 1e-9 * float(expected.abs().max())


@pytest.mark.parametrize("convention", ["paper", "basalt"])
@pytest.mark.parametrize("t0", [0.01, 1.3e3 + 0.01])
def test_equally_spaced_knots_give_the_uniform_spline(convention, t0):
    R, P, _ = random_spline(3, n_ctrl=9)
    dt = 0.137
    # Knots are absolute times: their float64 rounding (eps |t0|) moves u and h by eps |t0| / dt.
    rel = 1e-12 + 8 * np.finfo(np.float64).eps * abs(t0) / dt
    kv = knots.uniform_knots(9, dt, t0, convention)
    lo, hi = spline.valid_time_range(9, dt, t0, convention)
    assert knots.valid_time_range(kv) == pytest.approx((lo, hi), abs=1e-12)
    t = np.linspace(lo, hi, 301)
    ours = knots.evaluate(R, P, t, kv, derivatives=2)
    uniform = spline.evaluate(R, P, t, dt, t0, convention, derivatives=2)
    for name, a, b in zip(spline.SplineSample._fields, ours, uniform):
        scale = max(1.0, float(b.abs().max()))
        assert float((a - b).abs().max()) <= rel * scale, name


def test_a_time_on_an_interior_knot_starts_the_next_segment():
    """The index rule worked by hand for 8 control points (knots t_0..t_9, domain [t_2, t_7], segments
    0..4): a time exactly on knot t_(3+s) is segment s + 1 at u = 0, the domain's end is the last
    segment at u = 1, and a time just before a knot stays in the previous segment with u near 1."""
    knot_vector = random_spline(0)[2]
    segment, u, _ = knots.locate(knot_vector[2:8], knot_vector)
    assert segment.tolist() == [0, 1, 2, 3, 4, 4]
    assert u.tolist() == [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    before = knot_vector[3:7] - 1e-9
    segment, u, _ = knots.locate(before, knot_vector)
    assert segment.tolist() == [0, 1, 2, 3]
    assert bool(((u > 1.0 - 1e-7) & (u < 1.0)).all())


def test_basis_matrix_of_equal_spacing_is_the_paper_matrix():
    local = torch.tensor([[-2.0, -1.0, 0.0, 1.0, 2.0, 3.0]], dtype=F64)
    C = torch.tensor(spline.CUMULATIVE_BASIS, dtype=F64) / 6.0
    assert torch.allclose(knots.cumulative_basis_matrix(local)[0], C, atol=1e-15, rtol=0)


def test_weights_are_a_partition_of_unity_and_monotone():
    kv = torch.tensor(np.cumsum([0.0, 0.1, 0.7, 0.05, 0.3, 0.02, 0.9]), dtype=F64)
    u = torch.linspace(0, 1, 11, dtype=F64)
    seg = torch.zeros(11, dtype=torch.int64)
    B = knots.cumulative_weights(kv, seg, u).value[..., 0]  # (M, 3): B_1 >= B_2 >= B_3 in [0, 1]
    assert bool(((B[:, :-1] - B[:, 1:]) >= -1e-15).all()) and bool((B >= -1e-15).all() and (B <= 1 + 1e-15).all())


def test_curve_is_c2_across_uneven_knots():
    R, P, kv = random_spline(4)
    for knot in kv[3:-3]:
        eps = 1e-9
        left = knots.evaluate(R, P, np.array([knot - eps]), kv, 2)
        right = knots.evaluate(R, P, np.array([knot]), kv, 2)
        for a, b in zip(left, right):
            assert float((a - b).abs().max()) <= 1e-6 * max(1.0, float(b.abs().max()))


@pytest.mark.parametrize("bad, message", [
    ([0.0, 0.1, 0.2, 0.2, 0.4, 0.5], r"strictly increasing, got knots\[2\] = 0.2 s and knots\[3\] = 0.2"),
    ([0.0, 0.1, 0.3, 0.2, 0.4, 0.5], r"strictly increasing, got knots\[2\] = 0.3"),
    ([0.0, 0.1, 0.2, 0.3, 0.4], r"n_ctrl \+ 2 = 6 times"),
    ([0.0, 0.1, np.nan, 0.3, 0.4, 0.5], r"finite, got nan at index 2"),
])
def test_bad_knot_vectors_are_named(bad, message):
    R, P, _ = random_spline(0, n_ctrl=4)
    with pytest.raises(ValueError, match=message):
        knots.evaluate(R, P, 0.25, bad)


def test_too_few_control_points_and_off_domain_times_are_named():
    R, P, kv = random_spline(0, n_ctrl=4)
    with pytest.raises(ValueError, match="at least 4 control points, got n_ctrl=3"):
        knots.evaluate(R[:3], P[:3], kv[2], kv[:5])
    with pytest.raises(ValueError, match=r"time .* outside the spline domain"):
        knots.evaluate(R, P, kv[-3] + 1e-3, kv)
    end = knots.evaluate(R, P, np.array([kv[2], kv[-3]]), kv).translation  # closed domain
    assert torch.isfinite(end).all()


def test_curve_approximation_on_a_knot_vector_recovers_the_curve():
    """Eq. (11) on a non-uniform layout: from poses of a known non-uniform spline and a start at the
    Greville abscissae, the fitted curve is that spline (oracle: knots.evaluate, checked against scipy)."""
    rotations, translations, knot_vector = random_spline(5, n_ctrl=8, step=0.3)
    times = interior_times(knot_vector, 60)
    sample = knots.evaluate(rotations, translations, times, knot_vector)
    target = make_pose(sample.rotation, sample.translation)
    fit_R, fit_P = spline_fit.fit_control_points(times, target, 1.0, 0.0, 8, iters=50, knots=knot_vector)
    refit = knots.evaluate(fit_R, fit_P, times, knot_vector)
    assert torch.allclose(refit.translation, sample.translation, atol=1e-9)
    assert float(so3_log(refit.rotation.transpose(-1, -2) @ sample.rotation).norm(dim=-1).max()) < 1e-8
    # equally spaced knots: the same fit as the uniform layout
    even = knots.uniform_knots(8, 0.25, 3.0)
    times = interior_times(even, 40)
    sample = knots.evaluate(rotations, translations, times, even)
    target = make_pose(sample.rotation, sample.translation)
    by_knots = spline_fit.fit_control_points(times, target, 1.0, 0.0, 8, iters=30, knots=even)
    by_spacing = spline_fit.fit_control_points(times, target, 0.25, 3.0, 8, iters=30)
    for a, b in zip(by_knots, by_spacing):
        assert torch.allclose(a, b, atol=1e-9)


def test_greville_times_are_where_a_line_puts_its_control_points():
    _, _, knot_vector = random_spline(6, n_ctrl=9)
    greville = knots.greville_times(knot_vector)
    line = np.stack([2.0 + 0.5 * greville, -1.0 * greville, 0.3 + 0 * greville], axis=-1)
    times = interior_times(knot_vector, 31)
    oracle = BSpline(np.r_[knot_vector[0] - 1.0, knot_vector, knot_vector[-1] + 1.0], line, 3)(times)
    assert np.allclose(oracle, np.stack([2.0 + 0.5 * times, -times, 0.3 + 0 * times], -1), atol=1e-9, rtol=0)


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_fit_trajectory_on_boundaries(convention):
    """fit_trajectory(boundaries=): equal boundaries give the uniform fit; uneven ones recover a known
    non-uniform curve whose intervals they are (oracle: knots.evaluate on the same knot vector)."""
    rotations, translations, _ = random_spline(7, n_ctrl=8, step=0.3)
    boundaries = 50.0 + np.cumsum(np.r_[0.0, np.random.default_rng(7).uniform(0.05, 0.5, 5)])  # 5 uneven intervals
    knot_vector = knots.knots_from_boundaries(boundaries, 0.3)
    assert np.allclose(knot_vector, np.r_[boundaries[0] - 0.6, boundaries[0] - 0.3, boundaries,
                                          boundaries[-1] + 0.3, boundaries[-1] + 0.6], atol=0, rtol=0)
    times = np.linspace(boundaries[0], boundaries[-1], 90, endpoint=False)
    sample = knots.evaluate(rotations, translations, times, knot_vector)
    fitted = spline_fit.fit_trajectory(times, make_pose(sample.rotation, sample.translation), 0.3, convention,
                                       iters=50, boundaries=boundaries)
    assert fitted.n_ctrl == len(boundaries) + 2 and not fitted.uniform
    refit = fitted.poses(times)
    assert torch.allclose(refit[:, :3, 3], sample.translation, atol=1e-9)
    assert float(so3_log(refit[:, :3, :3].transpose(-1, -2) @ sample.rotation).norm(dim=-1).max()) < 1e-8
    # equally spaced boundaries from the first time: the uniform fit of fit_trajectory
    even_times = 10.0 + np.arange(40) / 30.0
    even_poses = make_pose(so3_exp(torch.as_tensor(np.stack([np.sin(even_times), 0.3 * even_times, 0 * even_times], -1))),
                           torch.as_tensor(np.stack([even_times ** 2, np.cos(even_times), even_times], -1)))
    uniform = spline_fit.fit_trajectory(even_times, even_poses, 0.25, convention)
    by_boundaries = spline_fit.fit_trajectory(even_times, even_poses, 0.25, convention,
                                              boundaries=even_times[0] + 0.25 * np.arange(uniform.n_ctrl - 2))
    assert torch.allclose(uniform.poses(even_times), by_boundaries.poses(even_times), atol=1e-9)
    with pytest.raises(ValueError, match="the boundaries span"):
        spline_fit.fit_trajectory(even_times, even_poses, 0.25, convention, boundaries=np.array([10.0, 10.5]))


def test_start_pose_gauge_on_uneven_knots():
    """Oracle: a random non-uniform spline's own control point 0, recovered from its start pose
    (knots.evaluate at κ_2) and points 1, 2 with the knots' start weights; equal spacing gives (5/6, 1/6)."""
    rotations, translations, knot_vector = random_spline(11, n_ctrl=7, step=0.5)
    start = knots.evaluate(rotations, translations, np.array([knot_vector[2]]), knot_vector)
    weights = knots.start_weights(knot_vector)
    garbled_R, garbled_P = rotations.clone(), translations.clone()
    garbled_R[0], garbled_P[0] = rotations[4], translations[4] + 3.0
    rotation_0, translation_0 = spline_fit.first_control_point(garbled_R, garbled_P, start.rotation[0],
                                                               start.translation[0], weights)
    assert torch.allclose(rotation_0, rotations[0], atol=1e-9) and torch.allclose(translation_0, translations[0], atol=1e-9)
    # the uniform formula is wrong on these knots: the curve would not start at the start pose
    uniform_R, uniform_P = spline_fit.first_control_point(garbled_R, garbled_P, start.rotation[0], start.translation[0])
    assert float((uniform_P - translations[0]).norm()) > 1e-3
    assert np.allclose(knots.start_weights(knots.uniform_knots(6, 0.3, 2.0)), (5 / 6, 1 / 6), atol=1e-12, rtol=0)
    # the trajectory type hands its weights to the gauge; uniform trajectories hand None
    from tsslam_ref.trajectory import BSplineTrajectory

    uneven = BSplineTrajectory(rotations, translations, 0.3, float(knot_vector[0]), knots=knot_vector)
    assert np.allclose(uneven.start_weights(), weights, atol=1e-12, rtol=0)
    assert BSplineTrajectory(rotations, translations, 0.3, 0.0).start_weights() is None


@pytest.mark.parametrize("layout", ["paper", "basalt", "knots"])
def test_fit_starts_each_control_point_at_the_pose_of_the_time_it_dominates(layout):
    """Eq. (11)'s starting guess, on shuffled frames of a line (constant velocity and body rate).
    Oracle, by hand: the time control point k dominates is t0 + (k + 1) dt (paper), t0 + (k - 1) dt
    (basalt), (κ_k + κ_{k+1} + κ_{k+2}) / 3 (a knot vector); the line's pose there is the start,
    and that start already reproduces the line's positions (the uniform spline, or scipy's BSpline on the knots)."""
    dt, t0, n_ctrl = 0.25, 2.0, 7
    knot_vector = 1.5 + np.cumsum(np.r_[0.0, 0.3, 0.1, 0.25, 0.2, 0.15, 0.35, 0.3, 0.2]) if layout == "knots" else None
    if layout == "knots":
        dominant = (knot_vector[:-2] + knot_vector[1:-1] + knot_vector[2:]) / 3.0
    else:
        dominant = t0 + dt * (np.arange(n_ctrl) + (1.0 if layout == "paper" else -1.0))
    times = np.unique(np.r_[dominant, np.linspace(dominant[0], dominant[-1], 41)])
    times = times[np.random.default_rng(3).permutation(len(times))]  # the guess must not assume sorted frames
    base = so3_exp(torch.tensor([0.4, -0.9, 1.7], dtype=F64))
    rate, velocity = torch.tensor([0.3, -0.5, 0.2], dtype=F64), torch.tensor([1.0, -0.4, 0.25], dtype=F64)

    def line(t):
        elapsed = torch.as_tensor(t - 2.0)[:, None]
        return base @ so3_exp(elapsed * rate), 0.5 + elapsed * velocity

    poses = make_pose(*line(times))
    convention = "paper" if layout == "knots" else layout
    rotations, translations = spline_fit.initial_control_points_from_poses(times, poses, dt, t0, n_ctrl, convention,
                                                                           knot_vector)
    expected_R, expected_P = line(dominant)
    assert torch.allclose(translations, expected_P, atol=1e-12)
    assert torch.allclose(rotations, expected_R, atol=1e-12)
    if layout == "knots":
        inside = interior_times(knot_vector, 30)
        padded = np.r_[knot_vector[0] - 1.0, knot_vector, knot_vector[-1] + 1.0]
        curve = BSpline(padded, translations.numpy(), 3)(inside)
        assert np.allclose(curve, line(inside)[1].numpy(), atol=1e-12, rtol=0)
    else:
        t_min, t_max = spline.valid_time_range(n_ctrl, dt, t0, convention)
        inside = np.linspace(t_min, t_max, 30)
        curve = spline.evaluate(rotations, translations, inside, dt, t0, convention).translation
        assert torch.allclose(curve, line(inside)[1], atol=1e-12)


@pytest.mark.parametrize("make", [lambda k: k.astype(np.float32), lambda k: torch.as_tensor(k, dtype=torch.float32),
                                  lambda k: [np.float32(x) for x in k]], ids=["array", "tensor", "list"])
def test_float32_knots_are_refused_like_float32_times(make):
    """Knots are times: float32 ones (1e-5 relative error near 100 s) are refused naming them."""
    R, P, _ = random_spline(40)
    knot_vector = 100.0 + np.cumsum(np.full(10, 0.05))
    with pytest.raises(TypeError, match="^knots must be float64 seconds"):
        knots.check_knots(make(knot_vector), 8)
    with pytest.raises(TypeError, match="^knots must be float64 seconds"):
        knots.evaluate(R, P, [float(knot_vector[4])], make(knot_vector))


@pytest.mark.parametrize("n_ctrl,dt,t0,words", [
    (8, 0.0, 1.0, "dt must be > 0 s, got 0.0"), (8, -0.1, 1.0, "dt must be > 0 s, got -0.1"),
    (8, float("nan"), 1.0, "dt must be a finite number of seconds, got nan"),
    (8, float("inf"), 1.0, "dt must be a finite number of seconds, got inf"),
    (8, 0.1, float("nan"), "t0 must be a finite number of seconds, got nan"),
    (3, 0.1, 1.0, "at least 4 control points, got n_ctrl=3"), (2, 0.1, 1.0, "got n_ctrl=2")])
def test_uniform_knots_refuses_a_bad_spacing_or_too_few_points_naming_the_value(n_ctrl, dt, t0, words):
    with pytest.raises(ValueError, match=words.replace("(", r"\(")):
        knots.uniform_knots(n_ctrl, dt, t0)
