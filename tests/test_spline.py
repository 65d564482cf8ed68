"""Tests for tsslam_ref.spline: every oracle of the spline's contract (docs/spline.md).

Oracles are independent of the closed forms under test: exact fractions and analytic motions,
scipy B-splines (translation, scalar angle), PyPose (rotations), basalt golden values, central
finite differences and autograd in time (torch.func.jvp), gradcheck for control-point gradients.
"""

import math

from fractions import Fraction

import numpy as np
import pypose as pp
import pytest
import scipy.interpolate
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import knots, spline, spline_fit
from tsslam_ref.geometry import make_pose, so3_exp, so3_log, vee

F64 = torch.float64
OFFSET = {"paper": 2, "basalt": 0}


def random_spline(seed, n_ctrl=8, max_angle=1.0, scale=1.0, dtype=F64):
    """Random-walk control points: R_k = R_{k-1} Exp(step), |step| <= max_angle (rad)."""
    rng = np.random.default_rng(seed)
    rotation = so3_exp(torch.as_tensor(rng.normal(size=3)))
    rotations = [rotation]
    for _ in range(n_ctrl - 1):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        rotation = rotation @ so3_exp(torch.as_tensor(axis * rng.uniform(0.3 * max_angle, max_angle)))
        rotations.append(rotation)
    translations = torch.as_tensor(np.cumsum(rng.normal(scale=scale, size=(n_ctrl, 3)), axis=0))
    return torch.stack(rotations).to(dtype), translations.to(dtype)


def interior_times(n_ctrl, dt, t0, convention, n_per_segment=7, margin=1e-2, seed=0):
    """Random times inside segments, at least margin*dt away from knots (float64 numpy)."""
    rng = np.random.default_rng(seed)
    t_min, _ = spline.valid_time_range(n_ctrl, dt, t0, convention)
    segments = np.repeat(np.arange(n_ctrl - 3), n_per_segment)
    u = rng.uniform(margin, 1 - margin, size=segments.shape)
    return t_min + (segments + u) * dt


def scipy_bspline(values, dt, t0, convention):
    """Independent oracle: scipy's degree-3 B-spline with uniform knots matching our convention.

    Control point k is active on [t_{k-3+offset}, t_{k+1+offset}), so knot j is t0 + (j-3+offset)dt.
    """
    n = values.shape[0]
    knots = t0 + dt * (np.arange(n + 4, dtype=np.float64) - 3 + OFFSET[convention])
    return scipy.interpolate.BSpline(knots, np.asarray(values, dtype=np.float64), 3, extrapolate=False)


def autograd_in_time(rotations, translations, times, dt, t0, convention):
    """Oracle: Ṙ, R̈, ṗ, p̈ by forward-mode autograd in t; ω = vee(RᵀṘ), ω̇ = vee(RᵀR̈)."""
    times = torch.as_tensor(times, dtype=F64)
    ones = torch.ones_like(times)

    def pose(t):
        sample = spline.evaluate(rotations, translations, t, dt, t0, convention)
        return sample.rotation, sample.translation

    def first(t):
        return torch.func.jvp(pose, (t,), (ones,))

    (R, p), (R_dot, p_dot) = first(times)
    _, (_, (R_ddot, p_ddot)) = torch.func.jvp(first, (times,), (ones,))
    Rt = R.transpose(-1, -2)
    return p_dot, p_ddot, vee(Rt @ R_dot), vee(Rt @ R_ddot)


def rel_err(value, reference):
    value, reference = torch.as_tensor(value, dtype=F64), torch.as_tensor(reference, dtype=F64)
    return float((value - reference).abs().max() / reference.abs().max().clamp_min(1e-300))


# ------------------------------------------------------------------------------------------
# Basis


def test_basis_B0_identically_one_and_noncumulative_weights_partition_unity():
    u = torch.linspace(0, 1, 101, dtype=F64)
    B = spline.basis(u)
    assert torch.equal(B[:, 0], torch.ones_like(u))
    weights = torch.stack([B[:, 0] - B[:, 1], B[:, 1] - B[:, 2], B[:, 2] - B[:, 3], B[:, 3]], -1)
    # B_0 - B_1 at u = 1 is 0 exactly; computed, it is a difference of values near 1, so allow a
    # few ulps of 1.0 (2.2e-16 each; a BLAS with another summation order gave -2.2e-16).
    assert (weights >= -4 * torch.finfo(F64).eps).all()
    assert torch.allclose(weights.sum(-1), torch.ones_like(u), atol=1e-15, rtol=0)


def test_basis_exact_fractions_at_segment_ends():
    u = torch.tensor([0.0, 1.0], dtype=F64)
    expected = {
        0: [[6, 5, 1, 0], [6, 6, 5, 1]],  # ×1/6
        1: [[0, 3, 3, 0], [0, 0, 3, 3]],  # Ḃ·Δt = (0,1,1,0)/2, (0,0,1,1)/2, ×1/6
        2: [[0, -6, 6, 0], [0, 0, -6, 6]],  # B̈·Δt² = (0,-1,1,0), (0,0,-1,1), ×1/6
    }
    for order, values in expected.items():
        assert torch.allclose(spline.basis(u, order), torch.tensor(values, dtype=F64) / 6, atol=1e-15, rtol=0)


def test_basis_derivatives_match_fd_in_u():
    u = torch.linspace(0.05, 0.95, 19, dtype=F64)
    h = 1e-5
    for order in (1, 2, 3):
        fd = (spline.basis(u + h, order - 1) - spline.basis(u - h, order - 1)) / (2 * h)
        assert rel_err(spline.basis(u, order), fd) < 1e-7


def test_basis_rejects_bad_order():
    with pytest.raises(ValueError, match="order"):
        spline.basis(torch.zeros(1), 4)


# ------------------------------------------------------------------------------------------
# Knot closed forms


def test_eq5_eq6_eq9_closed_forms_at_knots():
    dt, t0 = 0.4, 0.7
    R, P = random_spline(1, n_ctrl=7, max_angle=1.5)
    for i in range(2, 6):  # paper indexing: knot t_i starts the segment using i-2..i+1
        s = spline.evaluate(R, P, np.array([t0 + i * dt]), dt, t0, derivatives=2)
        assert torch.allclose(s.translation[0], (P[i - 2] + 4 * P[i - 1] + P[i]) / 6, atol=1e-12)
        assert torch.allclose(s.velocity_world[0], (P[i] - P[i - 2]) / (2 * dt), atol=1e-12)
        assert torch.allclose(s.acceleration_world[0], (P[i - 2] - 2 * P[i - 1] + P[i]) / dt**2, atol=1e-12)
        d1 = so3_log(R[i - 2].T @ R[i - 1])
        d2 = so3_log(R[i - 1].T @ R[i])
        assert torch.allclose(s.rotation[0], R[i - 2] @ so3_exp(5 * d1 / 6) @ so3_exp(d2 / 6), atol=1e-12)
        rotated_d1 = so3_exp(-d2 / 6) @ d1
        assert torch.allclose(s.omega_body[0], (rotated_d1 + d2) / (2 * dt), atol=1e-12)
        omega_dot = (torch.linalg.cross(rotated_d1, d2) / 4 + d2 - rotated_d1) / dt**2
        assert torch.allclose(s.omegadot_body[0], omega_dot, atol=1e-12)


# ------------------------------------------------------------------------------------------
# C² continuity


def test_c2_continuity_at_interior_knots_and_jerk_jumps():
    dt = 0.3
    R, P = random_spline(2, n_ctrl=9, max_angle=1.5)
    n_seg = R.shape[0] - 3
    left_first = torch.arange(n_seg - 1)
    ones = torch.ones(n_seg - 1, dtype=F64)
    left = spline.evaluate_segments(R, P, left_first, ones, dt, 2)
    right = spline.evaluate_segments(R, P, left_first + 1, 0 * ones, dt, 2)
    for a, b in zip(left, right):
        assert torch.allclose(a, b, atol=1e-12, rtol=0)
    # Jerk (third derivative) jumps: a is linear in u per segment, so its slope is exact.
    seg_start = spline.evaluate_segments(R, P, torch.arange(n_seg), torch.zeros(n_seg, dtype=F64), dt, 2)
    seg_end = spline.evaluate_segments(R, P, torch.arange(n_seg), torch.ones(n_seg, dtype=F64), dt, 2)
    jerk = (seg_end.acceleration_world - seg_start.acceleration_world) / dt  # (n_seg, 3)
    assert (torch.linalg.vector_norm(jerk[1:] - jerk[:-1], dim=-1) > 1e-2).all()
    h = 1e-4
    near_end = spline.evaluate_segments(R, P, left_first, ones - h, dt, 2).omegadot_body
    after_start = spline.evaluate_segments(R, P, left_first + 1, ones * h, dt, 2).omegadot_body
    rot_jerk_left = (left.omegadot_body - near_end) / (h * dt)
    rot_jerk_right = (after_start - right.omegadot_body) / (h * dt)
    assert (torch.linalg.vector_norm(rot_jerk_left - rot_jerk_right, dim=-1) > 1e-2).all()


# ------------------------------------------------------------------------------------------
# Exact motions


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_constant_velocity_control_points_give_exact_motion(convention):
    dt, t0, n = 0.2, -0.3, 8
    a0 = torch.tensor([0.3, -1.0, 2.0], dtype=F64)
    b0 = torch.tensor([0.5, 0.2, -0.4], dtype=F64)
    R0 = so3_exp(torch.tensor([0.4, 0.1, -0.9], dtype=F64))
    w0 = torch.tensor([0.3, -0.5, 0.2], dtype=F64)
    k = torch.arange(n, dtype=F64)[:, None]
    P = a0 + b0 * k
    R = R0 @ so3_exp(k * w0)
    t_min, t_max = spline.valid_time_range(n, dt, t0, convention)
    times = np.linspace(t_min, t_max, 41)
    s = spline.evaluate(R, P, times, dt, t0, convention, derivatives=2)
    index = torch.as_tensor((times - t0) / dt - OFFSET[convention] + 1)[:, None]  # s − i + (i − offset + 1)
    assert torch.allclose(s.translation, a0 + b0 * index, atol=1e-12)
    assert torch.allclose(s.rotation, R0 @ so3_exp(index * w0), atol=1e-12)
    assert torch.allclose(s.velocity_world, (b0 / dt).expand(41, 3), atol=1e-12)
    assert torch.allclose(s.omega_body, (w0 / dt).expand(41, 3), atol=1e-12)
    assert s.acceleration_world.abs().max() < 1e-12
    assert s.omegadot_body.abs().max() < 1e-12


def test_identical_control_points_give_constant_pose_and_zero_derivatives():
    R = so3_exp(torch.tensor([0.2, -1.1, 0.5], dtype=F64)).expand(6, 3, 3)
    P = torch.tensor([1.0, 2.0, -3.0], dtype=F64).expand(6, 3)
    s = spline.evaluate(R, P, np.linspace(0.2, 0.5, 13), 0.1, 0.0, derivatives=2)
    assert torch.allclose(s.rotation, R[0].expand(13, 3, 3), atol=1e-15)
    assert torch.allclose(s.translation, P[0].expand(13, 3), atol=1e-15)
    for value in s[2:]:
        assert value.abs().max() == 0


def test_single_axis_rotation_equals_scalar_spline_scipy():
    dt, t0 = 0.25, 1.0
    rng = np.random.default_rng(3)
    theta = np.cumsum(rng.uniform(-2.5, 2.5, size=8))  # |Δθ| < π, not wrapped
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    R = so3_exp(torch.as_tensor(theta[:, None] * axis))
    P = torch.zeros(8, 3, dtype=F64)
    times = interior_times(8, dt, t0, "paper")
    s = spline.evaluate(R, P, times, dt, t0, derivatives=2)
    scalar = scipy_bspline(theta, dt, t0, "paper")
    expected_R = so3_exp(torch.as_tensor(scalar(times)[:, None] * axis))
    assert torch.allclose(s.rotation, expected_R, atol=1e-12)
    assert torch.allclose(s.omega_body, torch.as_tensor(scalar(times, 1)[:, None] * axis), atol=1e-11)
    assert torch.allclose(s.omegadot_body, torch.as_tensor(scalar(times, 2)[:, None] * axis), atol=1e-10)


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_eq5_eq8_translation_velocity_acceleration_match_scipy_bspline(convention):
    dt, t0 = 0.1, 0.1
    R, P = random_spline(4, n_ctrl=10)
    times = interior_times(10, dt, t0, convention)
    s = spline.evaluate(R, P, times, dt, t0, convention, derivatives=2)
    oracle = scipy_bspline(P.numpy(), dt, t0, convention)
    assert rel_err(s.translation, oracle(times)) < 1e-12
    assert rel_err(s.velocity_world, oracle(times, 1)) < 1e-12
    assert rel_err(s.acceleration_world, oracle(times, 2)) < 1e-11


# ------------------------------------------------------------------------------------------
# Invariances


def _all_outputs(R, P, times, dt, t0=0.0):
    return spline.evaluate(R, P, times, dt, t0, derivatives=2)


def test_left_invariance_of_poses_and_body_rates():
    R, P = random_spline(5, max_angle=1.5)
    G = so3_exp(torch.tensor([0.7, -0.4, 1.9], dtype=F64))
    g = torch.tensor([3.0, -1.0, 0.5], dtype=F64)
    times = interior_times(8, 0.5, 0.0, "paper")
    base = _all_outputs(R, P, times, 0.5)
    moved = _all_outputs(G @ R, P @ G.T + g, times, 0.5)
    assert torch.allclose(moved.rotation, G @ base.rotation, atol=1e-12)
    assert torch.allclose(moved.translation, base.translation @ G.T + g, atol=1e-12)
    assert torch.allclose(moved.velocity_world, base.velocity_world @ G.T, atol=1e-12)
    assert torch.allclose(moved.acceleration_world, base.acceleration_world @ G.T, atol=1e-12)
    assert torch.allclose(moved.omega_body, base.omega_body, atol=1e-12)
    assert torch.allclose(moved.omegadot_body, base.omegadot_body, atol=1e-12)


def test_right_invariance_rotates_body_rates():
    R, P = random_spline(6, max_angle=1.5)
    H = so3_exp(torch.tensor([-1.2, 0.3, 0.8], dtype=F64))
    times = interior_times(8, 0.5, 0.0, "paper")
    base = _all_outputs(R, P, times, 0.5)
    moved = _all_outputs(R @ H, P, times, 0.5)
    assert torch.allclose(moved.rotation, base.rotation @ H, atol=1e-12)
    assert torch.allclose(moved.omega_body, base.omega_body @ H, atol=1e-12)  # Hᵀ ω as row vectors
    assert torch.allclose(moved.omegadot_body, base.omegadot_body @ H, atol=1e-12)


def test_time_scaling_of_derivatives():
    R, P = random_spline(7, max_angle=1.5)
    c, dt = 3.7, 0.2
    times = interior_times(8, dt, 0.0, "paper")
    base = _all_outputs(R, P, times, dt)
    slow = _all_outputs(R, P, times * c, dt * c)
    assert torch.allclose(slow.rotation, base.rotation, atol=1e-12)
    assert torch.allclose(slow.translation, base.translation, atol=1e-12)
    assert rel_err(slow.velocity_world * c, base.velocity_world) < 1e-12
    assert rel_err(slow.acceleration_world * c**2, base.acceleration_world) < 1e-12
    assert rel_err(slow.omega_body * c, base.omega_body) < 1e-12
    assert rel_err(slow.omegadot_body * c**2, base.omegadot_body) < 1e-12


# ------------------------------------------------------------------------------------------
# Finite differences with large rotations


@pytest.mark.parametrize("seed,dt,max_angle", [(10, 1.0, 0.8), (11, 0.1, 2.0), (12, 0.05, 0.3)])
def test_eq8_eq9_derivatives_match_central_differences(seed, dt, max_angle):
    R, P = random_spline(seed, n_ctrl=8, max_angle=max_angle)
    times = interior_times(8, dt, 0.0, "paper", margin=1e-2, seed=seed)
    s = _all_outputs(R, P, times, dt)

    def at(shift):
        return _all_outputs(R, P, times + shift, dt)

    h = 1e-5 * dt
    plus, minus = at(h), at(-h)
    assert rel_err(s.velocity_world, (plus.translation - minus.translation) / (2 * h)) < 1e-7
    assert rel_err(s.acceleration_world, (plus.velocity_world - minus.velocity_world) / (2 * h)) < 1e-7
    omega_fd = so3_log(minus.rotation.transpose(-1, -2) @ plus.rotation) / (2 * h)  # body frame
    assert rel_err(s.omega_body, omega_fd) < 1e-7
    assert rel_err(s.omegadot_body, (plus.omega_body - minus.omega_body) / (2 * h)) < 1e-7
    # Second differences, independent of the recursion.
    h = 1e-4 * dt
    plus, minus = at(h), at(-h)
    a_fd = (plus.translation - 2 * s.translation + minus.translation) / h**2
    assert rel_err(s.acceleration_world, a_fd) < 1e-5
    Rt = s.rotation.transpose(-1, -2)
    omega_dot_fd = (so3_log(Rt @ plus.rotation) + so3_log(Rt @ minus.rotation)) / h**2
    assert rel_err(s.omegadot_body, omega_dot_fd) < 1e-5


# ------------------------------------------------------------------------------------------
# Autograd in time


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_eq8_eq9_match_autograd_in_time(convention):
    dt, t0 = 0.3, 2.0
    R, P = random_spline(13, n_ctrl=7, max_angle=2.0)
    t_min, t_max = spline.valid_time_range(7, dt, t0, convention)
    times = np.concatenate([np.linspace(t_min, t_max, 9), interior_times(7, dt, t0, convention)])
    s = spline.evaluate(R, P, times, dt, t0, convention, derivatives=2)
    v, a, omega, omega_dot = autograd_in_time(R, P, times, dt, t0, convention)
    assert rel_err(s.velocity_world, v) < 1e-10
    assert rel_err(s.acceleration_world, a) < 1e-10
    assert rel_err(s.omega_body, omega) < 1e-10
    assert rel_err(s.omegadot_body, omega_dot) < 1e-10


# ------------------------------------------------------------------------------------------
# External oracles


def _pypose_poses(R, P):
    """(N, 7) SE3 LieTensor (tx, ty, tz, qx, qy, qz, qw) from our control points."""
    quaternions = torch.as_tensor(Rotation.from_matrix(R.numpy()).as_quat())
    return pp.SE3(torch.cat([P, quaternions], dim=-1))


@pytest.mark.parametrize("u", [0.0, 0.123, 0.5, 0.77, 0.999])
def test_eq6_rotation_matches_pypose_at_arbitrary_u(u):
    dt, t0 = 0.5, 0.0
    R, P = random_spline(14, n_ctrl=7, max_angle=2.0)
    data = _pypose_poses(R, P)
    for first in range(4):  # basalt convention: window first..first+3 at u ↔ t0 + (first + u)dt
        if u == 0.0:
            expected = pp.bspline(data[first:first + 4], interval=0.5).matrix()[0]
        else:
            expected = pp.bspline(data[first:first + 4], interval=u).matrix()[1]
        ours = spline.evaluate(R, P, np.array([t0 + (first + u) * dt]), dt, t0, "basalt")
        assert torch.allclose(ours.rotation[0], expected[:3, :3].to(F64), atol=1e-12)


def test_eq5_translation_matches_pypose_when_rotations_equal():
    R, P = random_spline(15, n_ctrl=6)
    R = R[2].expand(6, 3, 3).clone()
    data = _pypose_poses(R, P)
    for u in (0.2, 0.6):
        for first in range(3):
            expected = pp.bspline(data[first:first + 4], interval=u).matrix()[1]
            ours = spline.evaluate(R, P, np.array([(first + u) * 0.5 + 1.0]), 0.5, 0.0, "paper")
            assert torch.allclose(ours.translation[0], expected[:3, 3].to(F64), atol=1e-12)


BASALT_ROTVECS = [[0, 0, 0], [0.1, -0.2, 0.3], [0.4, -0.1, 0.5], [0.3, 0.3, 0.9], [-0.2, 0.6, 1.2], [-0.5, 0.4, 1.0]]
BASALT_POSITIONS = [[0, 0, 0], [1, 0, 0.5], [1.5, 1, 0.5], [1, 2, 0], [0, 2.5, -0.5], [-1, 2, -1]]
BASALT_TABLE = {  # basalt reference values: t -> rotvec, p, v, a, omega_body, omegadot_body
    0.00: [(0.134116980, -0.151459662, 0.282680481), (0.916666667, 0.166666667, 0.416666667), (1.5, 1.0, 0.5),
           (-2, 4, -2), (0.419692610, -0.127856638, 0.478245352), (0.896277239, 1.063012442, -0.512550323)],
    0.35: [(0.289163844, -0.111468504, 0.450617209), (1.290583333, 0.7045, 0.469166667), (0.555, 1.91, -0.2),
           (-3.4, 1.2, -2.0), (0.486098815, 0.289351146, 0.436568364), (-0.532954773, 1.330922034, 0.317237811)],
    0.80: [(0.325661486, 0.139534886, 0.740555699), (1.171333333, 1.582, 0.194666667), (-1.02, 1.82, -0.92),
           (-2.8, -1.2, -0.8), (-0.011635585, 0.865875154, 0.595161303), (-1.292066019, 0.771943126, -0.060129717)],
    1.20: [(0.093519323, 0.413904218, 1.016607449), (0.582, 2.171333333, -0.2), (-1.82, 1.02, -1.0),
           (-1.2, -2.8, 0.0), (-0.506706704, 0.905555220, 0.391334791), (-0.781496148, -0.677918007, -1.109365084)],
}


@pytest.mark.parametrize("convention,shift", [("basalt", 0.0), ("paper", 1.0)])
def test_basalt_golden_values(convention, shift):
    R = so3_exp(torch.tensor(BASALT_ROTVECS, dtype=F64))
    P = torch.tensor(BASALT_POSITIONS, dtype=F64)
    times = np.array(sorted(BASALT_TABLE)) + shift
    s = spline.evaluate(R, P, times, 0.5, 0.0, convention, derivatives=2)
    ours = [so3_log(s.rotation), s.translation, s.velocity_world, s.acceleration_world, s.omega_body, s.omegadot_body]
    for column, value in enumerate(ours):
        golden = torch.tensor([BASALT_TABLE[t][column] for t in sorted(BASALT_TABLE)], dtype=F64)
        assert torch.allclose(value, golden, atol=1e-8, rtol=0), column


# ------------------------------------------------------------------------------------------
# Domain


def test_valid_time_range_both_conventions():
    assert spline.valid_time_range(6, 0.5, 1.0, "paper") == (2.0, 3.5)
    assert spline.valid_time_range(6, 0.5, 1.0, "basalt") == (1.0, 2.5)
    with pytest.raises(ValueError, match="at least 4"):
        spline.valid_time_range(3, 0.5, 0.0)
    with pytest.raises(ValueError, match="convention"):
        spline.valid_time_range(6, 0.5, 0.0, "kontiki")
    with pytest.raises(ValueError, match="dt"):
        spline.valid_time_range(6, 0.0, 0.0)


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_domain_is_closed_tmax_maps_to_last_segment_at_u_equal_one(convention):
    dt, t0, n = 0.25, 3.0, 7
    R, P = random_spline(16, n_ctrl=n)
    t_min, t_max = spline.valid_time_range(n, dt, t0, convention)
    s = spline.evaluate(R, P, np.array([t_min, t_max]), dt, t0, convention, derivatives=2)
    start = spline.evaluate_segments(R, P, torch.tensor([0]), torch.tensor([0.0], dtype=F64), dt, 2)
    end = spline.evaluate_segments(R, P, torch.tensor([n - 4]), torch.tensor([1.0], dtype=F64), dt, 2)
    for value, a, b in zip(s, start, end):
        assert torch.allclose(value[0], a[0], atol=1e-14) and torch.allclose(value[1], b[0], atol=1e-14)
    indices = spline.active_control_indices(np.array([t_min, t_max]), n, dt, t0, convention)
    assert indices.tolist() == [[0, 1, 2, 3], [n - 4, n - 3, n - 2, n - 1]]


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_out_of_domain_raises_value_error_naming_time_and_domain(convention):
    dt, t0, n = 0.25, 3.0, 7
    R, P = random_spline(16, n_ctrl=n)
    t_min, t_max = spline.valid_time_range(n, dt, t0, convention)
    for bad in (t_min - 1e-6, t_max + 1e-6, float("nan")):
        with pytest.raises(ValueError, match="outside the spline domain") as info:
            spline.evaluate(R, P, np.array([t_min, bad]), dt, t0, convention)
        assert repr(bad) in str(info.value) and repr(t_max) in str(info.value)


def test_knot_times_use_the_exact_floor_of_their_float64_value():
    """The float64 number is the time: a knot t0 + kΔt that float64 puts before the knot is in the
    previous segment (at u = 1), as exact rational arithmetic on the same numbers says."""
    dt = t0 = 0.1
    n = 53
    knots = t0 + dt * np.arange(n, dtype=np.float64)
    exact = np.array([math.floor((Fraction(k) - Fraction(t0)) / Fraction(dt)) for k in knots])
    assert (exact != np.arange(n)).any() and (exact == np.arange(n)).any()  # both cases occur here
    indices = spline.active_control_indices(knots[:n - 2], n, dt, t0, "basalt")
    assert indices[:, 0].tolist() == np.clip(exact[:n - 2], 0, n - 4).tolist()
    indices = spline.active_control_indices(knots[2:n - 1], n, dt, t0, "paper")
    assert indices[:, 0].tolist() == np.clip(exact[2:n - 1] - 2, 0, n - 4).tolist()
    R, P = random_spline(18, n_ctrl=n)
    at_knots = spline.evaluate(R, P, knots[:n - 2], dt, t0, "basalt", derivatives=1)
    segment_start = spline.evaluate_segments(R, P, torch.arange(n - 3), torch.zeros(n - 3, dtype=F64), dt, 1)
    for value, start in zip(at_knots[:3] + at_knots[4:5], segment_start[:3] + segment_start[4:5]):
        assert torch.allclose(value[:n - 3], start, atol=1e-12)  # C1 quantities: the choice is invisible


def test_the_exact_floor_holds_where_the_float64_quotient_rounds_across_a_whole_number():
    """Random t0 and dt, times at a knot t0 + k dt as float64 computes it and at its neighbours: the
    segment is floor of the exact rational (t - t0) / dt (docs/spline.md, "Exactness rule"), also
    where the float64 quotient lands a few ulps on the other side of a whole number (with t0 = dt =
    0.1 it never does).  Oracle: Fraction arithmetic on the same float64 numbers."""
    rng = np.random.default_rng(11)
    n_ctrl, rounded_across = 40, 0
    for _ in range(1500):
        t0, dt, k = rng.uniform(-5.0, 5.0), rng.uniform(0.05, 1.0), int(rng.integers(1, 30))
        knot = t0 + k * dt
        times = np.array([np.nextafter(knot, -np.inf), knot, np.nextafter(knot, np.inf)])
        exact = [math.floor((Fraction(t) - Fraction(t0)) / Fraction(dt)) for t in times]
        rounded_across += sum(math.floor((t - t0) / dt) != e for t, e in zip(times, exact))
        first = spline.active_control_indices(times, n_ctrl, dt, t0, "basalt")[:, 0]
        assert first.tolist() == exact, (t0, dt, k)
    assert rounded_across > 0  # the cases the rule is there for occurred


def test_large_absolute_timestamps_handled_in_float64():
    dt, stamp = 0.03, 1305031102.175304  # TUM stamp: float32 spacing 128 s
    R, P = random_spline(17, n_ctrl=8, scale=0.05)
    ends = spline.evaluate(R, P, np.array([stamp + 2 * dt, stamp + 7 * dt]), dt, stamp)  # accepted
    assert torch.allclose(ends.translation[0], (P[0] + 4 * P[1] + P[2]) / 6, atol=1e-6)
    relative = np.linspace(2 * dt + 1e-4, 7 * dt - 1e-4, 21)
    absolute = stamp + relative
    ours = spline.evaluate(R, P, absolute, dt, stamp, derivatives=2)
    reference = spline.evaluate(R, P, absolute - stamp, dt, 0.0, derivatives=2)
    for a, b in zip(ours, reference):
        assert torch.allclose(a, b, atol=1e-5)


def test_times_shape_is_preserved_and_batched_control_points_match_loop():
    dt = 0.2
    rotations, translations = zip(*(random_spline(seed, n_ctrl=6) for seed in (20, 21)))
    R, P = torch.stack(rotations), torch.stack(translations)  # (2, 6, 3, 3), (2, 6, 3)
    times = np.array([[0.45, 0.5], [0.61, 0.99]])
    batched = spline.evaluate(R, P, times, dt, 0.0, derivatives=2)
    assert batched.rotation.shape == (2, 2, 2, 3, 3) and batched.omegadot_body.shape == (2, 2, 2, 3)
    for b in range(2):
        single = spline.evaluate(R[b], P[b], times, dt, 0.0, derivatives=2)
        for x, y in zip(batched, single):
            assert torch.allclose(x[b], y, atol=1e-15)
    scalar = spline.evaluate(R[0], P[0], 0.5, dt, 0.0, derivatives=1)
    assert scalar.rotation.shape == (3, 3) and scalar.acceleration_world is None


def test_evaluate_rejects_malformed_control_points():
    R, P = random_spline(22, n_ctrl=6)
    with pytest.raises(ValueError, match="control_translations"):
        spline.evaluate(R, P[:5], 0.5, 0.2, 0.0)
    with pytest.raises(ValueError, match="dtype"):
        spline.evaluate(R, P.float(), 0.5, 0.2, 0.0)
    with pytest.raises(ValueError, match="derivatives"):
        spline.evaluate(R, P, 0.5, 0.2, 0.0, derivatives=3)


# ------------------------------------------------------------------------------------------
# Gradients w.r.t. control points


@pytest.mark.parametrize("gap", [0.0, 1e-9, 1e-5, 0.7])
def test_gradcheck_poses_and_derivatives_wrt_control_points(gap):
    base_R, base_P = random_spline(23, n_ctrl=5, max_angle=1.0)
    axis = torch.tensor([0.6, -0.8, 0.0], dtype=F64)
    base_R[2] = base_R[1] @ so3_exp(gap * axis)  # neighbours exactly equal / 1e-9 / 1e-5 apart
    times = np.array([0.43, 0.61])  # paper, dt 0.2: domain [0.4, 0.8]

    def outputs(delta, P):
        R = so3_exp(delta) @ base_R  # left tangent increments
        s = spline.evaluate(R, P, times, 0.2, 0.0, derivatives=2)
        return torch.cat([s.rotation.reshape(-1), *(value.reshape(-1) for value in s[1:])])

    delta = torch.zeros(5, 3, dtype=F64, requires_grad=True)
    P = base_P.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(outputs, (delta, P), eps=1e-7, atol=1e-6)
    loss = outputs(delta, P).square().sum()
    grads = torch.autograd.grad(loss, (delta, P))
    assert all(torch.isfinite(g).all() for g in grads)


def test_local_support_zero_gradient_outside_the_four_active_points():
    R0, P0 = random_spline(24, n_ctrl=9)
    delta = torch.zeros(9, 3, dtype=F64, requires_grad=True)
    P = P0.clone().requires_grad_(True)
    time = np.array([0.2 * 4.5])  # paper, dt 0.2: segment i = 4 uses control points 2..5
    active = spline.active_control_indices(time, 9, 0.2, 0.0)[0].tolist()
    assert active == [2, 3, 4, 5]
    s = spline.evaluate(so3_exp(delta) @ R0, P, time, 0.2, 0.0, derivatives=2)
    loss = sum(value.sum() for value in s)
    grad_delta, grad_P = torch.autograd.grad(loss, (delta, P))
    outside = [k for k in range(9) if k not in active]
    assert grad_delta[outside].abs().max() == 0 and grad_P[outside].abs().max() == 0
    assert (grad_delta[active].abs().sum(-1) > 0).all() and (grad_P[active].abs().sum(-1) > 0).all()


# ------------------------------------------------------------------------------------------
# Precision


def test_float32_matches_float64():
    R, P = random_spline(25, n_ctrl=8, max_angle=1.5)
    times = interior_times(8, 0.1, 100.0, "paper")
    s64 = spline.evaluate(R, P, times, 0.1, 100.0, derivatives=2)
    s32 = spline.evaluate(R.float(), P.float(), times, 0.1, 100.0, derivatives=2)
    for a, b in zip(s32, s64):
        assert a.dtype == torch.float32
        assert rel_err(a, b) < 1e-5


@pytest.mark.parametrize("times", [torch.tensor([1.5e9 + 0.05, 1.5e9 + 0.2], dtype=torch.float32),
                                   np.array([1.5e9 + 0.05, 1.5e9 + 0.2], dtype=np.float32),
                                   np.float32(1.5e9 + 0.05), [np.float32(1.5e9 + 0.05), np.float32(1.5e9 + 0.2)]],
                         ids=["tensor", "array", "numpy_scalar", "list_of_numpy_scalars"])
def test_float32_times_are_refused_not_rounded_to_one_instant(times):
    R, P = random_spline(26, n_ctrl=8)
    with pytest.raises(TypeError, match="float64"):  # float32 puts both stamps at 1.5e9 s
        spline.evaluate(R, P, times, 0.1, 1.5e9 - 0.3)
    with pytest.raises(TypeError, match="float64"):
        knots.locate(times, knots.uniform_knots(8, 0.1, 1.5e9 - 0.3))


@pytest.mark.parametrize("name,value", [("t0", np.float32(12.3)), ("dt", np.float32(0.033)),
                                        ("t0", torch.tensor(12.3)), ("dt", np.array(0.033, dtype=np.float16))])
def test_float32_t0_and_dt_are_refused_like_float32_times(name, value):
    """t0 and dt are times too: float32 ones lose their digits before any cast (12.3 s in float32 is
    12.300000190734863 s), so every entry point refuses them naming the argument."""
    R, P = random_spline(28, n_ctrl=8)
    timing = {"t0": 12.3, "dt": 0.033, name: value}
    t_mid = 12.3 + 4.5 * 0.033
    for call in (lambda: spline.valid_time_range(8, timing["dt"], timing["t0"]),
                 lambda: spline.evaluate(R, P, [t_mid], timing["dt"], timing["t0"]),
                 lambda: spline.active_control_indices([t_mid], 8, timing["dt"], timing["t0"]),
                 lambda: spline.time_in_domain([t_mid], 8, timing["dt"], timing["t0"]),
                 lambda: knots.uniform_knots(8, timing["dt"], timing["t0"])):
        with pytest.raises(TypeError, match=f"^{name} must be float64 seconds .*digits are gone"):
            call()


@pytest.mark.parametrize("name", ["t0", "dt"])
def test_a_non_finite_t0_or_dt_is_named_by_the_spline_itself(name):
    """A NaN t0 was reported as an interval 'too short for times near nan s'; an infinite dt gave an
    infinite domain.  The check lives in valid_time_range, which knots.uniform_knots calls too."""
    R, P = random_spline(30, n_ctrl=8)
    timing = {"t0": 0.5, "dt": 0.25, name: float("nan") if name == "t0" else float("inf")}
    with pytest.raises(ValueError, match=f"{name} must be a finite number of seconds"):
        spline.evaluate(R, P, [1.2], timing["dt"], timing["t0"])


def test_the_domain_message_prints_plain_floats_for_numpy_float64_timing():
    R, P = random_spline(29, n_ctrl=8)
    with pytest.raises(ValueError) as raised:
        spline.evaluate(R, P, [5.0], np.float64(0.25), np.float64(0.5))
    assert "outside the spline domain [1.0, 2.25] s" in str(raised.value) and "np." not in str(raised.value)
    assert spline.valid_time_range(8, np.float64(0.25), np.float64(0.5)) == (1.0, 2.25)
    assert all(type(end) is float for end in spline.valid_time_range(8, np.float64(0.25), np.float64(0.5)))


def test_an_interval_too_short_for_float64_stamps_is_refused():
    R, P = random_spline(27, n_ctrl=8)
    t_min, _ = spline.valid_time_range(8, 1e-3, 1.5e9)  # 1 ms at 1.5e9 s: ~4000 ulps, fine
    spline.evaluate(R, P, [t_min], 1e-3, 1.5e9)
    for dt in (1e-6, 1e-9):  # the end tolerance (1.3e-6 s) would be a segment or more
        with pytest.raises(ValueError, match="too short for times near 1500000000.0 s"):
            spline.valid_time_range(8, dt, 1.5e9)
    spline.valid_time_range(8, 1e-9, 0.0)  # relative times resolve it
    with pytest.raises(ValueError, match="too short"):
        knots.check_knots(1.5e9 + np.array([0, 1, 2, 2 + 1e-6, 3, 4, 5, 6, 7, 8.0]), 8)


# ------------------------------------------------------------------------------------------
# Curve approximation, Eq. (11)


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_eq11_fit_recovers_control_points_of_a_sampled_spline(convention):
    dt, t0, n = 0.25, 10.0, 8
    R, P = random_spline(28, n_ctrl=n, max_angle=0.6)
    t_min, t_max = spline.valid_time_range(n, dt, t0, convention)
    times = np.linspace(t_min, t_max, 60)
    s = spline.evaluate(R, P, times, dt, t0, convention)
    fit_R, fit_P = spline_fit.fit_control_points(times, make_pose(s.rotation, s.translation), dt, t0, n,
                                                 convention=convention)
    assert torch.allclose(fit_R, R, atol=1e-8)
    assert torch.allclose(fit_P, P, atol=1e-8)


def test_eq11_fit_new_control_point_with_the_others_fixed():
    dt, t0, n = 0.2, 0.0, 7
    R, P = random_spline(29, n_ctrl=n, max_angle=0.5)
    times = np.linspace(t0 + 5 * dt, t0 + 6 * dt, 7)  # last interval only, as in local BA
    s = spline.evaluate(R, P, times, dt, t0)
    init_R, init_P = R.clone(), P.clone()
    init_R[-1], init_P[-1] = R[-2], P[-2]  # new point starts at its neighbour
    fixed = torch.tensor([True] * (n - 1) + [False])
    fit_R, fit_P = spline_fit.fit_control_points(times, make_pose(s.rotation, s.translation), dt, t0, n,
                                                 init_rotations=init_R, init_translations=init_P, fixed=fixed)
    assert torch.equal(fit_R[:-1], R[:-1]) and torch.equal(fit_P[:-1], P[:-1])
    assert torch.allclose(fit_R[-1], R[-1], atol=1e-8) and torch.allclose(fit_P[-1], P[-1], atol=1e-8)
    with pytest.raises(ValueError, match="fixed"):
        spline_fit.fit_control_points(times, make_pose(s.rotation, s.translation), dt, t0, n, fixed=fixed)


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_fit_trajectory_finds_the_layout_and_control_points_of_a_sampled_spline(convention):
    """Oracle: a random spline laid out as the system lays its own (domain from the first time)."""
    dt, first_time, n = 0.3, 5.0, 9
    R, P = random_spline(41, n_ctrl=n, max_angle=0.4)
    t0 = first_time - OFFSET[convention] * dt
    _, t_max = spline.valid_time_range(n, dt, t0, convention)
    times = np.linspace(first_time, t_max, 61)  # 30 Hz-like, both ends of the domain
    s = spline.evaluate(R, P, times, dt, t0, convention)
    fitted = spline_fit.fit_trajectory(times, make_pose(s.rotation, s.translation), dt, convention=convention)
    assert fitted.n_ctrl == n and fitted.t0 == pytest.approx(t0, abs=1e-12) and fitted.convention == convention
    assert torch.allclose(fitted.control_rotations, R, atol=1e-8)
    assert torch.allclose(fitted.control_translations, P, atol=1e-8)


def test_fit_trajectory_removes_noise_from_real_hand_held_motion(shared_data):
    """Oracle: TUM fr2/desk motion capture.  Two seconds at 30 Hz with 1 cm and 1 deg (per axis) of
    noise on every pose; the dt = 0.3 s spline fitted to the noisy poses is within half the noise
    of the real motion, in position and in rotation (a smooth curve does not follow the hand's
    tremor exactly: fitted to the clean poses it is 0.16 cm / 0.38 deg off)."""
    from tsslam_ref.datasets.tum_format import read_tum_trajectory
    from tsslam_ref.synthetic import resample_trajectory

    path = shared_data / "trajectories" / "tum_rgbd_fr2_desk_groundtruth.txt"
    times, truth = resample_trajectory(path, 60, 30.0, float(read_tum_trajectory(path)[0].min()) + 20.0)
    rng = np.random.default_rng(0)
    noisy = truth.copy()
    noisy[:, :3, 3] += rng.normal(scale=0.01, size=(60, 3))
    noisy[:, :3, :3] = Rotation.from_rotvec(np.radians(1.0) * rng.normal(size=(60, 3))).as_matrix() @ truth[:, :3, :3]
    fitted = spline_fit.fit_trajectory(times, torch.as_tensor(noisy), 0.3).poses(times).numpy()

    def errors(poses):
        """RMS position (cm) and rotation (deg) error against the motion capture."""
        position = np.sqrt(np.mean(np.sum((poses[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1)))
        angle = Rotation.from_matrix(np.swapaxes(truth[:, :3, :3], 1, 2) @ poses[:, :3, :3]).magnitude()
        return 100 * position, np.degrees(np.sqrt(np.mean(angle ** 2)))

    (noise_cm, noise_deg), (fit_cm, fit_deg) = errors(noisy), errors(fitted)
    assert fit_cm < 0.5 * noise_cm, (fit_cm, noise_cm)
    assert fit_deg < 0.5 * noise_deg, (fit_deg, noise_deg)


def test_fit_trajectory_rejects_times_that_do_not_increase():
    poses = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    with pytest.raises(ValueError, match="strictly increasing"):
        spline_fit.fit_trajectory(np.array([0.0, 0.1, 0.1]), poses, 0.3)
    with pytest.raises(ValueError, match="dt must be > 0"):
        spline_fit.fit_trajectory(np.array([0.0, 0.1, 0.2]), poses, 0.0)


@pytest.mark.parametrize("convention", ["paper", "basalt"])
def test_first_control_point_recovers_control_point_0_from_the_start_pose(convention):
    """Oracle: a random spline's own control point 0, recovered from its start pose and points 1, 2."""
    dt, t0, n = 0.25, 3.0, 6
    R, P = random_spline(31, n_ctrl=n, max_angle=0.8)
    t_min, _ = spline.valid_time_range(n, dt, t0, convention)
    start = spline.evaluate(R, P, np.array([t_min]), dt, t0, convention=convention)
    garbled_R, garbled_P = R.clone(), P.clone()
    garbled_R[0], garbled_P[0] = R[3], P[3] + 5.0
    rotation_0, translation_0 = spline_fit.first_control_point(garbled_R, garbled_P, start.rotation[0], start.translation[0])
    assert torch.allclose(rotation_0, R[0], atol=1e-10) and torch.allclose(translation_0, P[0], atol=1e-10)
    pinned_R, pinned_P = spline_fit.pin_first_control_point(garbled_R, garbled_P, make_pose(start.rotation[0], start.translation[0]))
    assert torch.allclose(pinned_R, R, atol=1e-10) and torch.allclose(pinned_P, P, atol=1e-10)
    assert spline_fit.pin_first_control_point(garbled_R, garbled_P, None)[1] is garbled_P
    with pytest.raises(ValueError, match="control points 1 and 2"):
        spline_fit.first_control_point(R[:2], P[:2], start.rotation[0], start.translation[0])

