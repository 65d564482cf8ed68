"""Joint SE(3) cumulative cubic B-spline (PyPose ``pp.bspline``, Sophus, kontiki's SE3 spline), for the kit.

Not what TS-SLAM uses (the paper's Eq. (5)-(6) are split SO(3) x R³, :mod:`tsslam_ref.spline`); here
so that users of joint SE(3) libraries can check their code with the conformance kit
(``"representation": "se3"``).  Same basis C, same index conventions and the same time rule as
:mod:`tsslam_ref.spline` (its ``locate_segments``).  Formulas (tangent ξ = (ρ, φ), translation first, as
PyPose):

    T(t) = T_k Π_{j=1..3} Exp(B_j(u) ξ_j),   ξ_j = Log(T_{k+j−1}⁻¹ T_{k+j}) ∈ se(3),
    Exp(ρ, φ) = [Exp_SO3(φ), V(φ) ρ; 0, 1],  V(φ) = I + (1 − cos θ)/θ² [φ]× + (θ − sin θ)/θ³ [φ]×²,
    θ = |φ|, Log its inverse (ρ = V(φ)⁻¹ t, φ = Log_SO3(R)).

The rotation of T(t) equals the split spline's (the SE(3) Exp/Log rotation block is the SO(3)
one); the translation differs unless the window's control rotations are equal.  Derivatives:
v = dp/dt, a = d²p/dt² (world), ω_body = vee(RᵀṘ), ω̇_body = vee(RᵀR̈) (skew part), by
forward-mode automatic differentiation in u (du/dt = 1/Δt): exact up to float64 rounding, no
truncation error.

Layer 1 (math).  Imports ``spline`` and ``geometry``.
"""

from typing import Tuple

import torch

from tsslam_ref import spline
from tsslam_ref.geometry import skew, so3_exp, so3_log, vee


def _v_matrix(phi: torch.Tensor) -> torch.Tensor:
    """V(φ) of SE(3) Exp, (..., 3) -> (..., 3, 3); Taylor series below θ² = 1e-8 (smooth in φ)."""
    theta2 = (phi * phi).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    b = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - torch.sin(theta)) / (safe2 * theta))
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def se3_exp(xi: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Exp of (..., 6) tangents (ρ, φ) -> rotations (..., 3, 3), translations (..., 3)."""
    rho, phi = xi[..., :3], xi[..., 3:]
    return so3_exp(phi), (_v_matrix(phi) @ rho.unsqueeze(-1)).squeeze(-1)


def se3_log(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Log of poses (..., 3, 3), (..., 3) -> (..., 6) tangents (ρ, φ) (principal branch)."""
    phi = so3_log(rotation)
    rho = torch.linalg.solve(_v_matrix(phi), translation.unsqueeze(-1)).squeeze(-1)
    return torch.cat([rho, phi], dim=-1)


def knot_twists(control_rotations: torch.Tensor, control_translations: torch.Tensor) -> torch.Tensor:
    """ξ_j = Log(T_{j−1}⁻¹ T_j) for consecutive control poses: (N, 3, 3), (N, 3) -> (N−1, 6)."""
    R_prev_T = control_rotations[:-1].transpose(-1, -2)
    relative_R = R_prev_T @ control_rotations[1:]
    relative_p = (R_prev_T @ (control_translations[1:] - control_translations[:-1]).unsqueeze(-1)).squeeze(-1)
    return se3_log(relative_R, relative_p)


def pose_at_segment(u: torch.Tensor, first_R: torch.Tensor, first_p: torch.Tensor, xi: torch.Tensor):
    """T(u) = T_k Π Exp(B_j(u) ξ_j): u (M,), first pose (M, 3, 3), (M, 3), ξ (M, 3, 6) -> R, p."""
    B = spline.basis(u, 0)[:, 1:]  # (M, 3)
    R, p = first_R, first_p
    for j in range(3):
        step_R, step_p = se3_exp(B[:, j, None] * xi[:, j])
        p = p + (R @ step_p.unsqueeze(-1)).squeeze(-1)
        R = R @ step_R
    return R, p


def evaluate(control_rotations: torch.Tensor, control_translations: torch.Tensor, times, dt: float, t0: float,
             convention: str = "paper", derivatives: int = 0) -> spline.SplineSample:
    """Joint SE(3) spline at query times (unbatched control points), as :func:`tsslam_ref.spline.evaluate`.

    Args:
        control_rotations: (N, 3, 3); control_translations: (N, 3) (T_k = [R_k, t_k], camera-to-world):
            tensors of one dtype, unbatched (checked as :func:`tsslam_ref.spline.evaluate` checks them).
        times: any shape, seconds (float64), flattened to (M,): a scalar gives M = 1, a (2, 3) array
            M = 6 (unlike ``spline.evaluate``, which keeps the shape); a float64 tensor may require grad
            (every field is differentiable in time); dt, t0, convention: as the split spline.
        derivatives: 0 pose; 1 adds v, ω_body; 2 adds a, ω̇_body (ValueError otherwise).

    Returns:
        :class:`tsslam_ref.spline.SplineSample` with fields (M, ...).
    """
    n_ctrl = spline.check_control_points(control_rotations, control_translations, batched=False)
    if derivatives not in (0, 1, 2):
        raise ValueError(f"derivatives must be 0, 1 or 2, got {derivatives!r}")
    first, u, _ = spline.locate_segments(times, n_ctrl, dt, t0, convention)
    device = control_translations.device
    first = first.to(device)
    twists = knot_twists(control_rotations, control_translations)  # (N−1, 6)
    xi = twists[first[:, None] + torch.arange(3, device=device)]  # (M, 3, 6)
    first_R, first_p = control_rotations[first], control_translations[first]
    u = u.to(device=device, dtype=control_translations.dtype)

    def pose(u_):
        return pose_at_segment(u_, first_R, first_p, xi)

    R, p = pose(u)
    if derivatives == 0:
        return spline.SplineSample(R, p)
    rate = torch.full_like(u, 1.0 / dt)

    def first_order(u_):
        return torch.func.jvp(pose, (u_,), (rate,))

    (R, p), (R_dot, p_dot) = first_order(u)
    omega = vee(R.transpose(-1, -2) @ R_dot)
    if derivatives == 1:
        return spline.SplineSample(R, p, p_dot, None, omega, None)
    _, (_, (R_ddot, p_ddot)) = torch.func.jvp(first_order, (u,), (rate,))
    omega_dot = vee(R.transpose(-1, -2) @ R_ddot)
    return spline.SplineSample(R, p, p_dot, p_ddot, omega, omega_dot)
