"""Analytic Jacobians of the split cubic B-spline's outputs w.r.t. its four active control points.

TS-SLAM §III-B/§III-C, Eq. (5)-(9) differentiated w.r.t. the control points (what basalt-headers'
``so3_spline.h`` / ``rd_spline.h`` offer with their ``JacobianStruct``; Sommer et al. 2020, §4).

Perturbation convention (stated once, used for every block):

* control point k: R_k ← Exp(δ_k) R_k (left, world frame), P_k ← P_k + τ_k;
* output rotation: R(t) ← Exp(ε) R(t) (left, world frame), so J_R = ∂ε/∂δ;
* p, v, a, ω_body, ω̇_body: plain derivatives of the vectors.

In the split representation p, v, a depend on τ only and R, ω, ω̇ on δ only; the cross blocks are 0
and not returned.  Formulas (window-relative indices 0..3, d_j = Log(R_{j−1}ᵀ R_j), A_j = Exp(B_j d_j),
J_r the right Jacobian of SO(3)):

* ∂d_j/∂δ_j = J_r⁻¹(d_j) R_jᵀ, ∂d_j/∂δ_{j−1} = −J_r⁻¹(d_j) R_jᵀ (since Exp(δ)R = R Exp(Rᵀδ));
* ∂ε/∂δ_0 = I (directly), ∂ε/∂d_j = (R_0 A_1 ⋯ A_j) B_j J_r(B_j d_j);
* ∂(A_jᵀ w)/∂d_j = [A_jᵀ w]× B_j J_r(B_j d_j) for a fixed vector w;
* the ω recursion ω^(j+1) = A_jᵀ ω^(j) + Ḃ_j d_j and
  ω̇^(j+1) = Ḃ_j ω^(j+1) × d_j + A_jᵀ ω̇^(j) + B̈_j d_j differentiated step by step (forward mode);
* p = Σ_i w_i P_i with the non-cumulative weights w = (1 − B_1, B_1 − B_2, B_2 − B_3, B_3), so
  ∂p/∂τ_i = w_i I (v, a: the same with Ḃ, B̈).

Layer 1 (math).  Imports ``spline`` and ``geometry``.
"""

from typing import Dict, List, NamedTuple, Optional, Tuple

import torch

from tsslam_ref import spline
from tsslam_ref.geometry import skew, so3_exp, so3_log

JACOBIAN_KEYS = ("J_R", "J_p", "J_v", "J_a", "J_omega_body", "J_omegadot_body")
"""Output keys: each (M, 4, 3, 3), [m, i] = ∂(quantity at time m)/∂(perturbation of control point
first[m] + i); J_R, J_omega_body, J_omegadot_body w.r.t. δ, J_p, J_v, J_a w.r.t. τ."""


def _coefficients(phi: torch.Tensor):
    """θ² and the safe coefficient pairs for J_r and J_r⁻¹ of (..., 3) vectors (Taylor near 0)."""
    theta2 = (phi * phi).sum(-1)[..., None, None]
    small = theta2 < 1e-10
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    b = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - torch.sin(theta)) / (safe2 * theta))
    c = torch.where(small, 1.0 / 12.0 + theta2 / 720.0,
                    1.0 / safe2 - (1.0 + torch.cos(theta)) / (2.0 * theta * torch.sin(theta)))
    return a, b, c


def right_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """J_r(φ) = I − (1 − cos θ)/θ² [φ]× + (θ − sin θ)/θ³ [φ]×², (..., 3) -> (..., 3, 3)."""
    a, b, _ = _coefficients(phi)
    K = skew(phi)
    return torch.eye(3, dtype=phi.dtype, device=phi.device) - a * K + b * (K @ K)


def right_jacobian_inverse(phi: torch.Tensor) -> torch.Tensor:
    """J_r⁻¹(φ) = I + ½[φ]× + (1/θ² − (1 + cos θ)/(2θ sin θ)) [φ]×², (..., 3) -> (..., 3, 3) (θ < π)."""
    _, _, c = _coefficients(phi)
    K = skew(phi)
    return torch.eye(3, dtype=phi.dtype, device=phi.device) + 0.5 * K + c * (K @ K)


def _translation_block(weights: torch.Tensor, eye: torch.Tensor) -> torch.Tensor:
    """∂(p, v or a)/∂τ_i = w_i I, w the non-cumulative weights of the cumulative ``weights``
    (B, Ḃ or B̈), (M, 4) -> (M, 4, 3, 3)."""
    w = torch.stack([weights[:, 0] - weights[:, 1], weights[:, 1] - weights[:, 2],
                     weights[:, 2] - weights[:, 3], weights[:, 3]], dim=1)  # (M, 4)
    return w[..., None, None] * eye  # (M, 4, 3, 3)


class _Factor(NamedTuple):
    """The factor A_j = Exp(B_j d_j) of the cumulative product and what its derivatives need."""

    index: int
    """Which relative rotation it holds: 0..2 for d_1..d_3."""
    d: torch.Tensor
    """(M, 3) d_j = Log(R_{j−1}ᵀ R_j)."""
    A_T: torch.Tensor
    """(M, 3, 3) A_jᵀ."""
    Jr_scaled: torch.Tensor
    """(M, 3, 3) B_j J_r(B_j d_j): the tangent of A_j differentiated by d_j."""
    b_dot: torch.Tensor
    """(M, 1) Ḃ_j."""
    b_ddot: torch.Tensor
    """(M, 1) B̈_j."""


def _omega_step(f: _Factor, omega: torch.Tensor, J_omega: List[torch.Tensor],
                eye: torch.Tensor) -> Tuple[torch.Tensor, List[torch.Tensor]]:
    """ω^(j+1) = A_jᵀ ω^(j) + Ḃ_j d_j, (M, 3), and its Jacobians w.r.t. d_1..d_3 (3 x (M, 3, 3))."""
    rotated_omega = (f.A_T @ omega.unsqueeze(-1)).squeeze(-1)
    new_omega = rotated_omega + f.b_dot * f.d
    new_J_omega = [f.A_T @ J for J in J_omega]
    new_J_omega[f.index] = new_J_omega[f.index] + skew(rotated_omega) @ f.Jr_scaled + f.b_dot[..., None] * eye
    return new_omega, new_J_omega


def _omegadot_step(f: _Factor, new_omega: torch.Tensor, new_J_omega: List[torch.Tensor], omega_dot: torch.Tensor,
                   J_omegadot: List[torch.Tensor], eye: torch.Tensor) -> Tuple[torch.Tensor, List[torch.Tensor]]:
    """ω̇^(j+1) = Ḃ_j ω^(j+1) × d_j + A_jᵀ ω̇^(j) + B̈_j d_j, (M, 3), and its Jacobians w.r.t.
    d_1..d_3 (3 x (M, 3, 3)), given ω^(j+1) and its Jacobians from :func:`_omega_step`."""
    rotated_omegadot = (f.A_T @ omega_dot.unsqueeze(-1)).squeeze(-1)
    new_omega_dot = f.b_dot * torch.linalg.cross(new_omega, f.d) + rotated_omegadot + f.b_ddot * f.d
    new_J_omegadot = []
    for k in range(3):
        block = -f.b_dot[..., None] * (skew(f.d) @ new_J_omega[k]) + f.A_T @ J_omegadot[k]
        if k == f.index:
            block = (block + f.b_dot[..., None] * skew(new_omega)
                     + skew(rotated_omegadot) @ f.Jr_scaled + f.b_ddot[..., None] * eye)
        new_J_omegadot.append(block)
    return new_omega_dot, new_J_omegadot


def _rotation_jacobians_wrt_d(R_win: torch.Tensor, d: torch.Tensor, B: torch.Tensor, B_dot: torch.Tensor,
                              B_ddot: torch.Tensor):
    """∂ε, ∂ω_body and ∂ω̇_body w.r.t. d_1..d_3: three lists of 3 blocks (M, 3, 3), by the forward
    recursion over the factors A_1..A_3 (R_win (M, 4, 3, 3), d (M, 3, 3), B.. (M, 4))."""
    M, dtype, device = d.shape[0], d.dtype, d.device
    eye = torch.eye(3, dtype=dtype, device=device)
    J_eps_d = []
    omega = torch.zeros(M, 3, dtype=dtype, device=device)
    omega_dot = torch.zeros_like(omega)
    J_omega = [torch.zeros(M, 3, 3, dtype=dtype, device=device) for _ in range(3)]
    J_omegadot = [torch.zeros(M, 3, 3, dtype=dtype, device=device) for _ in range(3)]
    prefix = R_win[:, 0]  # R_0 A_1 ⋯ A_j
    for j in range(3):
        scaled = B[:, j + 1, None] * d[:, j]  # (M, 3)
        A = so3_exp(scaled)
        factor = _Factor(j, d[:, j], A.transpose(-1, -2), B[:, j + 1, None, None] * right_jacobian(scaled),
                         B_dot[:, j + 1, None], B_ddot[:, j + 1, None])
        prefix = prefix @ A
        J_eps_d.append(prefix @ factor.Jr_scaled)
        omega, new_J_omega = _omega_step(factor, omega, J_omega, eye)
        omega_dot, J_omegadot = _omegadot_step(factor, omega, new_J_omega, omega_dot, J_omegadot, eye)
        J_omega = new_J_omega
    return J_eps_d, J_omega, J_omegadot


def _chain_to_control_points(blocks: List[torch.Tensor], dd_ddelta: torch.Tensor,
                             direct: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Blocks w.r.t. d_1..d_3 (3 x (M, 3, 3)) -> w.r.t. δ_0..δ_3 (M, 4, 3, 3), by ∂d_j/∂δ_j =
    ``dd_ddelta[:, j-1]`` and ∂d_j/∂δ_{j−1} = −(the same); ``direct`` (M, 3, 3) adds a direct ∂/∂δ_0."""
    M = dd_ddelta.shape[0]
    result = torch.zeros(M, 4, 3, 3, dtype=dd_ddelta.dtype, device=dd_ddelta.device)
    if direct is not None:
        result[:, 0] = direct
    for j in range(3):  # d_{j+1} joins control points j and j + 1
        contribution = blocks[j] @ dd_ddelta[:, j]
        result[:, j + 1] = result[:, j + 1] + contribution
        result[:, j] = result[:, j] - contribution
    return result


def jacobians(control_rotations: torch.Tensor, control_translations: torch.Tensor, times, dt: float, t0: float,
              convention: str = "paper") -> Dict[str, torch.Tensor]:
    """Jacobians of R, p, v, a, ω_body, ω̇_body w.r.t. the 4 active control points (module docstring).

    Args:
        control_rotations: (N, 3, 3); control_translations: (N, 3): tensors of one dtype, unbatched
            (checked as :func:`tsslam_ref.spline.evaluate` checks them, ValueError / TypeError).
        times: any shape, seconds (float64; the domain rule of :mod:`tsslam_ref.spline`), flattened
            to (M,): a scalar gives M = 1, a (2, 3) array M = 6 (unlike ``spline.evaluate``, which
            keeps the shape).

    Returns:
        dict with ``first`` (M,) int64 (first active control index) and :data:`JACOBIAN_KEYS`,
        each (M, 4, 3, 3) in the control points' dtype.
    """
    n_ctrl = spline.check_control_points(control_rotations, control_translations, batched=False)
    first, u, _ = spline.locate_segments(times, n_ctrl, dt, t0, convention)
    dtype, device = control_translations.dtype, control_translations.device
    u = u.detach().to(device=device, dtype=dtype)
    first = first.to(device)
    eye = torch.eye(3, dtype=dtype, device=device)
    window = first[:, None] + torch.arange(4, device=device)  # (M, 4)
    R_win = control_rotations[window]  # (M, 4, 3, 3)
    d = so3_log(R_win[:, :-1].transpose(-1, -2) @ R_win[:, 1:])  # (M, 3, 3): d_1..d_3
    B = spline.basis(u, 0)  # (M, 4)
    B_dot = spline.basis(u, 1) / dt
    B_ddot = spline.basis(u, 2) / dt**2
    out = {"first": first, "J_p": _translation_block(B, eye), "J_v": _translation_block(B_dot, eye),
           "J_a": _translation_block(B_ddot, eye)}
    J_eps_d, J_omega, J_omegadot = _rotation_jacobians_wrt_d(R_win, d, B, B_dot, B_ddot)
    # ∂d_j/∂δ: +J_r⁻¹(d_j) R_jᵀ for point j, −(same) for point j − 1.
    dd_ddelta = right_jacobian_inverse(d) @ R_win[:, 1:].transpose(-1, -2)  # (M, 3, 3, 3)
    out["J_R"] = _chain_to_control_points(J_eps_d, dd_ddelta, direct=eye.expand(d.shape[0], 3, 3))
    out["J_omega_body"] = _chain_to_control_points(J_omega, dd_ddelta)
    out["J_omegadot_body"] = _chain_to_control_points(J_omegadot, dd_ddelta)
    return out
