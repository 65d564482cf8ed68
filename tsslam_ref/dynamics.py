"""Dynamics regulariser L_DR: log barriers on linear and angular acceleration norms.

TS-SLAM §III-C, the L_DR term of Eq. (10) ``eq:loss_ba``:

    L_DR = −Σ_{k=1..K} ( λ₁ ln(1 − ‖a_k‖/‖a‖_max) + λ₂ ln(1 − ‖ω̇_k‖/‖ω̇‖_max) ),

with a_k from Eq. (8) ``eq_jeck`` and ω̇_k from Eq. (9) ``eq_rot_jeck`` at K times sampled uniformly
in a window (see :mod:`tsslam_ref.spline`).  Norms are Euclidean; ‖ω̇‖ is the same in body and world
frames (ω̇_world = R ω̇_body, since ω × ω = 0).

Layer 1 (math).  Imports ``spline``, ``trajectory`` and ``config`` (the last two for types only).
Taught in notebooks/02_dynamics_regularization.ipynb; docs/spline.md is the user doc.

Beyond the barrier (ours).  The paper leaves x = ‖a‖/a_max ≥ 1 undefined: ln(1 − x) is NaN while
autograd's gradient stays finite, so training would fail silently.  We use

    f(x) = −ln(1 − x)                                       for x ≤ L (= barrier_limit, 0.95)
    f(x) = f(L) + f'(L)(x − L) + ½ f''(L)(x − L)²           for x > L,
    f'(L) = 1/(1 − L), f''(L) = 1/(1 − L)²,

the second-order Taylor continuation at L: finite everywhere, C² at the switch, increasing and
convex for x ≥ 0, so its gradient keeps pushing ‖a‖ back inside the bound.

Glossary

| symbol | variable | shape | frame | unit |
|---|---|---|---|---|
| a_k | ``acceleration`` | (..., 3) | world | m/s² |
| ω̇_k | ``angular_acceleration`` | (..., 3) | body | rad/s² |
| λ₁, λ₂ | ``lambda_acc``, ``lambda_ang`` | float | - | 1 |
| ‖a‖_max, ‖ω̇‖_max | ``a_max``, ``omegadot_max`` | float | - | m/s², rad/s² |
| L | ``barrier_limit`` | float | - | 1 (ratio) |
| K | ``n_samples`` | int | - | - |
"""

import math
from typing import Optional, Union

import torch

from tsslam_ref.config import DynamicsConfig
from tsslam_ref.spline import SplineSample
from tsslam_ref.times import check_float64_seconds
from tsslam_ref.trajectory import BSplineTrajectory


def log_barrier(ratio: torch.Tensor, barrier_limit: float = 0.95) -> torch.Tensor:
    """f(x) = −ln(1 − x) for x ≤ L, its second-order Taylor continuation at L beyond (module doc).

    Args:
        ratio: (...) x = ‖·‖/max ≥ 0, any float dtype.
        barrier_limit: L in (0, 1), where the continuation starts.

    Returns:
        (...) barrier values, ≥ 0 for x ≥ 0, finite with finite gradient everywhere.

    Example:
        >>> float(log_barrier(torch.tensor(0.0)))
        0.0
    """
    if not 0.0 < barrier_limit < 1.0:
        raise ValueError(f"barrier_limit must be in (0, 1), got {barrier_limit}")
    inside = ratio <= barrier_limit
    safe_ratio = torch.where(inside, ratio, torch.zeros_like(ratio))  # no NaN in the unused branch
    log_branch = -torch.log1p(-safe_ratio)
    gap = 1.0 - barrier_limit
    excess = ratio - barrier_limit
    taylor_branch = -math.log1p(-barrier_limit) + excess / gap + 0.5 * (excess / gap) ** 2
    return torch.where(inside, log_branch, taylor_branch)


def dynamics_regularizer(
    sample: Union[SplineSample, torch.Tensor],
    angular_acceleration: Optional[torch.Tensor] = None,
    *,
    lambda_acc: float,
    lambda_ang: float,
    a_max: float,
    omegadot_max: float,
    barrier_limit: float = 0.95,
) -> torch.Tensor:
    """L_DR of Eq. (10): Σ_k λ₁ f(‖a_k‖/a_max) + λ₂ f(‖ω̇_k‖/ω̇_max), f = :func:`log_barrier`.

    Args:
        sample: a :class:`~tsslam_ref.spline.SplineSample` evaluated with ``derivatives=2``, or the
            (..., 3) world accelerations a_k [m/s²] (then pass ``angular_acceleration``).
        angular_acceleration: (..., 3) body angular accelerations ω̇_k [rad/s²] when ``sample`` is
            a tensor.
        lambda_acc, lambda_ang: λ₁, λ₂ ≥ 0.
        a_max, omegadot_max: the bounds (> 0), m/s² and rad/s².
        barrier_limit: ratio where the Taylor continuation starts (module docstring).

    Returns:
        () scalar, summed (not averaged) over all samples as in the paper; ≥ 0.

    Differs from: the paper's −ln(1 − x) is undefined for x ≥ 1; ours continues it (module doc).
    At ‖a‖ = 0 the norm's gradient is the 0 subgradient (torch.linalg.vector_norm), not NaN.
    """
    if isinstance(sample, SplineSample):
        if sample.acceleration_world is None or sample.omegadot_body is None:
            raise ValueError("dynamics_regularizer needs a SplineSample evaluated with derivatives=2")
        acceleration, angular_acceleration = sample.acceleration_world, sample.omegadot_body
    else:
        acceleration = sample
        if angular_acceleration is None:
            raise ValueError("pass angular_acceleration (..., 3) together with the acceleration tensor")
    if acceleration.shape[-1] != 3 or angular_acceleration.shape[-1] != 3:
        raise ValueError(
            f"accelerations must be (..., 3), got {tuple(acceleration.shape)} and {tuple(angular_acceleration.shape)}"
        )
    if not (a_max > 0 and omegadot_max > 0):
        raise ValueError(f"a_max and omegadot_max must be > 0, got {a_max} and {omegadot_max}")
    if lambda_acc < 0 or lambda_ang < 0:
        raise ValueError(f"lambda_acc and lambda_ang must be >= 0, got {lambda_acc} and {lambda_ang}")
    acc_ratio = torch.linalg.vector_norm(acceleration, dim=-1) / a_max  # (...)
    ang_ratio = torch.linalg.vector_norm(angular_acceleration, dim=-1) / omegadot_max  # (...)
    return (lambda_acc * log_barrier(acc_ratio, barrier_limit).sum()
            + lambda_ang * log_barrier(ang_ratio, barrier_limit).sum())


def sample_times(
    t_start: float,
    t_end: float,
    n_samples: int,
    generator: Optional[torch.Generator] = None,
    jitter: bool = True,
) -> torch.Tensor:
    """K times in [t_start, t_end] (s), stratified: one per equal sub-interval.

    With ``jitter`` each time is uniform in its sub-interval (drawn from ``generator``), else the
    sub-interval centres.  Uniform coverage of the window as the paper asks, with less variance
    than K i.i.d. draws.

    Returns:
        (K,) float64 tensor on the CPU, sorted.
    """
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    check_float64_seconds("t_start", t_start)
    check_float64_seconds("t_end", t_end)
    if not t_end > t_start:
        raise ValueError(f"need t_end > t_start, got [{t_start}, {t_end}] s")
    if jitter:
        offsets = torch.rand(n_samples, dtype=torch.float64, generator=generator)
    else:
        offsets = torch.full((n_samples,), 0.5, dtype=torch.float64)
    width = (float(t_end) - float(t_start)) / n_samples
    times = float(t_start) + width * (torch.arange(n_samples, dtype=torch.float64) + offsets)
    return times.clamp(float(t_start), float(t_end))


def trajectory_dynamics_loss(
    trajectory: BSplineTrajectory,
    t_start: float,
    t_end: float,
    cfg: DynamicsConfig,
    generator: Optional[torch.Generator] = None,
) -> torch.Tensor:
    """L_DR of a trajectory over the window [t_start, t_end] with ``cfg.n_samples`` stratified times.

    Returns:
        () scalar, differentiable w.r.t. the trajectory's control tensors.
    """
    times = sample_times(t_start, t_end, cfg.n_samples, generator=generator)
    sample = trajectory.evaluate(times, derivatives=2)
    return dynamics_regularizer(
        sample,
        lambda_acc=cfg.lambda_acc,
        lambda_ang=cfg.lambda_ang,
        a_max=cfg.a_max,
        omegadot_max=cfg.omegadot_max,
        barrier_limit=cfg.barrier_limit,
    )
