"""Tests for tsslam_ref.dynamics: the L_DR term of Eq. (10) and its continuation past the barrier.

Oracles: the paper's formula evaluated with numpy, analytic derivatives of −ln(1 − x),
finite differences, gradcheck, and exact constant-velocity splines (a = ω̇ = 0).
"""

import math

import numpy as np
import pytest
import torch

from tsslam_ref import dynamics, spline
from tsslam_ref.config import DynamicsConfig
from tsslam_ref.geometry import so3_exp
from tsslam_ref.trajectory import BSplineTrajectory

F64 = torch.float64


def test_eq10_log_barrier_equals_minus_log_inside_the_limit():
    x = torch.linspace(0, 0.95, 40, dtype=F64)
    assert torch.allclose(dynamics.log_barrier(x, 0.95), torch.as_tensor(-np.log(1 - x.numpy())), atol=1e-15)


@pytest.mark.parametrize("limit", [0.5, 0.95])
def test_eq10_continuation_is_c2_at_the_switch(limit):
    """Value, slope and curvature match −ln(1 − x) at L from both sides (analytic: 1/(1−L), 1/(1−L)²)."""
    h = 1e-6
    x = torch.tensor([limit - h, limit, limit + h], dtype=F64, requires_grad=True)
    f = dynamics.log_barrier(x, limit)
    (slope,) = torch.autograd.grad(f.sum(), x, create_graph=True)
    (curvature,) = torch.autograd.grad(slope.sum(), x)
    assert torch.allclose(f.detach(), torch.full((3,), -math.log(1 - limit), dtype=F64), atol=1e-5)
    assert torch.allclose(slope.detach(), torch.full((3,), 1 / (1 - limit), dtype=F64), rtol=1e-4)
    assert torch.allclose(curvature, torch.full((3,), 1 / (1 - limit) ** 2, dtype=F64), rtol=1e-3)


def test_eq10_continuation_finite_positive_increasing_past_one():
    x = torch.tensor([0.96, 0.999, 1.0, 1.5, 10.0, 1e3], dtype=F64, requires_grad=True)
    f = dynamics.log_barrier(x, 0.95)
    (grad,) = torch.autograd.grad(f.sum(), x)
    assert torch.isfinite(f).all() and torch.isfinite(grad).all()
    assert (f > -math.log(0.05)).all() and (grad > 0).all()
    assert (f[1:] > f[:-1]).all() and (grad[1:] > grad[:-1]).all()  # increasing and convex


def test_log_barrier_rejects_bad_limit():
    with pytest.raises(ValueError, match="barrier_limit"):
        dynamics.log_barrier(torch.zeros(2), 1.0)


def test_eq10_regularizer_equals_paper_formula_inside_the_barrier():
    rng = np.random.default_rng(0)
    acc = rng.normal(size=(20, 3))
    acc *= 4.65 / np.linalg.norm(acc, axis=-1, keepdims=True).max()
    ang = rng.normal(size=(20, 3))
    ang *= 2.79 / np.linalg.norm(ang, axis=-1, keepdims=True).max()
    # the largest ratios are 0.93 (4.65 / 5, 2.79 / 3): exact -ln(1 - x) only below the documented
    # default barrier_limit of 0.95, which is not passed
    l1, l2, a_max, w_max = 0.3, 0.7, 5.0, 3.0
    expected = -np.sum(l1 * np.log(1 - np.linalg.norm(acc, axis=-1) / a_max)
                       + l2 * np.log(1 - np.linalg.norm(ang, axis=-1) / w_max))
    value = dynamics.dynamics_regularizer(torch.as_tensor(acc), torch.as_tensor(ang), lambda_acc=l1,
                                          lambda_ang=l2, a_max=a_max, omegadot_max=w_max)
    assert value.shape == () and value > 0
    assert abs(float(value) - expected) < 1e-12


def _constant_velocity_trajectory(requires_grad=True):
    k = torch.arange(7, dtype=F64)[:, None]
    delta = torch.zeros(7, 3, dtype=F64, requires_grad=requires_grad)
    P = (torch.tensor([0.1, 0.2, 0.3], dtype=F64) * k).requires_grad_(requires_grad)
    R = so3_exp(delta) @ so3_exp(k * torch.tensor([0.05, -0.02, 0.1], dtype=F64))
    return delta, P, R


def test_eq10_gradient_finite_at_zero_acceleration():
    delta, P, R = _constant_velocity_trajectory()
    sample = spline.evaluate(R, P, np.linspace(0.4, 1.2, 9), 0.2, 0.0, derivatives=2)
    assert sample.acceleration_world.abs().max() < 1e-12
    value = dynamics.dynamics_regularizer(sample, lambda_acc=0.1, lambda_ang=0.1, a_max=5.0, omegadot_max=5.0)
    grads = torch.autograd.grad(value, (delta, P))
    assert float(value.detach()) < 1e-10
    assert all(torch.isfinite(g).all() for g in grads)


def test_eq10_regularizer_beyond_the_bound_is_finite_and_pushes_back():
    acc = torch.tensor([[6.0, 8.0, 0.0]], dtype=F64, requires_grad=True)  # ‖a‖ = 10 = 2 a_max
    ang = torch.zeros(1, 3, dtype=F64)
    value = dynamics.dynamics_regularizer(acc, ang, lambda_acc=1.0, lambda_ang=1.0, a_max=5.0, omegadot_max=5.0)
    (grad,) = torch.autograd.grad(value, acc)
    assert torch.isfinite(value) and value > 0 and torch.isfinite(grad).all()
    assert float((grad * acc.detach()).sum()) > 0  # descent shrinks ‖a‖


def test_eq10_gradcheck_regularizer_wrt_control_points():
    rng = np.random.default_rng(1)
    base_R = so3_exp(torch.as_tensor(rng.normal(scale=0.3, size=(6, 3))))
    base_P = torch.as_tensor(rng.normal(scale=0.02, size=(6, 3)))
    base_R[3] = base_R[2]  # identical neighbours (d_j = 0) inside the window
    times = np.array([0.42, 0.55, 0.71, 0.93])

    def regulariser(delta, P):
        sample = spline.evaluate(so3_exp(delta) @ base_R, P, times, 0.2, 0.0, derivatives=2)
        return dynamics.dynamics_regularizer(sample, lambda_acc=0.1, lambda_ang=0.2, a_max=5.0, omegadot_max=50.0)

    delta = torch.zeros(6, 3, dtype=F64, requires_grad=True)
    P = base_P.clone().requires_grad_(True)
    sample = spline.evaluate(base_R, base_P, times, 0.2, 0.0, derivatives=2)
    assert sample.acceleration_world.norm(dim=-1).max() < 0.95 * 5.0  # inside the barrier
    assert sample.omegadot_body.norm(dim=-1).max() < 0.95 * 50.0
    assert torch.autograd.gradcheck(regulariser, (delta, P), eps=1e-7, atol=1e-6)


def test_sample_times_stratified_deterministic_float64():
    gen_a, gen_b = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    a = dynamics.sample_times(1.0, 3.0, 8, generator=gen_a)
    b = dynamics.sample_times(1.0, 3.0, 8, generator=gen_b)
    assert a.dtype == F64 and torch.equal(a, b)
    bins = torch.floor((a - 1.0) / 0.25)
    assert bins.tolist() == list(range(8))  # one sample per stratum
    centres = dynamics.sample_times(1.0, 3.0, 4, jitter=False)
    assert torch.allclose(centres, torch.tensor([1.25, 1.75, 2.25, 2.75], dtype=F64))
    with pytest.raises(ValueError, match="t_end"):
        dynamics.sample_times(2.0, 1.0, 4)


def test_trajectory_dynamics_loss_matches_direct_evaluation():
    rng = np.random.default_rng(2)
    R = so3_exp(torch.as_tensor(rng.normal(scale=0.2, size=(8, 3))))
    P = torch.as_tensor(rng.normal(scale=0.01, size=(8, 3)))
    traj = BSplineTrajectory(R, P, 0.25, 0.0)
    start, end = traj.domain()
    cfg = DynamicsConfig(lambda_acc=0.3, lambda_ang=0.4, a_max=5.0, omegadot_max=40.0, n_samples=16)
    value = dynamics.trajectory_dynamics_loss(traj, start, end, cfg, torch.Generator().manual_seed(3))
    times = dynamics.sample_times(start, end, 16, torch.Generator().manual_seed(3))
    sample = traj.evaluate(times, derivatives=2)
    acc = sample.acceleration_world.norm(dim=-1).numpy() / cfg.a_max
    ang = sample.omegadot_body.norm(dim=-1).numpy() / cfg.omegadot_max
    assert acc.max() < 0.95 and ang.max() < 0.95
    expected = -np.sum(cfg.lambda_acc * np.log(1 - acc) + cfg.lambda_ang * np.log(1 - ang))
    assert abs(float(value) - expected) < 1e-12


def test_dynamics_regularizer_rejects_bad_input():
    acc = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="angular_acceleration"):
        dynamics.dynamics_regularizer(acc, lambda_acc=1, lambda_ang=1, a_max=1, omegadot_max=1)
    with pytest.raises(ValueError, match="a_max"):
        dynamics.dynamics_regularizer(acc, acc, lambda_acc=1, lambda_ang=1, a_max=0, omegadot_max=1)
    pose_only = spline.SplineSample(torch.eye(3)[None], torch.zeros(1, 3))
    with pytest.raises(ValueError, match="derivatives=2"):
        dynamics.dynamics_regularizer(pose_only, lambda_acc=1, lambda_ang=1, a_max=1, omegadot_max=1)


def test_trajectory_dynamics_loss_uses_the_configured_barrier_limit():
    """cfg.barrier_limit reaches the barrier.  Oracle, written out here in numpy: with L = 0.3 every
    ratio x above L costs −ln(1 − L) + u + u²/2, u = (x − L)/(1 − L) (the module's continuation),
    which is below the −ln(1 − x) that the default L = 0.95 would give."""
    rng = np.random.default_rng(2)
    traj = BSplineTrajectory(so3_exp(torch.as_tensor(rng.normal(scale=0.2, size=(8, 3)))),
                             torch.as_tensor(rng.normal(scale=0.01, size=(8, 3))), 0.25, 0.0)
    start, end = traj.domain()
    cfg = DynamicsConfig(lambda_acc=0.3, lambda_ang=0.4, a_max=2.0, omegadot_max=25.0, n_samples=16, barrier_limit=0.3)
    value = dynamics.trajectory_dynamics_loss(traj, start, end, cfg, torch.Generator().manual_seed(3))
    sample = traj.evaluate(dynamics.sample_times(start, end, 16, torch.Generator().manual_seed(3)), derivatives=2)
    ratios = [sample.acceleration_world.norm(dim=-1).numpy() / cfg.a_max,
              sample.omegadot_body.norm(dim=-1).numpy() / cfg.omegadot_max]
    assert max(r.max() for r in ratios) < 0.95 and sum((r > 0.3).sum() for r in ratios) >= 4

    def barrier(x):
        u = (x - 0.3) / 0.7
        return np.where(x <= 0.3, -np.log1p(-np.minimum(x, 0.3)), -np.log(0.7) + u + 0.5 * u**2)

    expected = cfg.lambda_acc * barrier(ratios[0]).sum() + cfg.lambda_ang * barrier(ratios[1]).sum()
    assert abs(float(value) - expected) < 1e-12
