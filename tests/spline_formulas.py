"""A second, independent float64 implementation of the cumulative cubic B-spline (split, and joint
SE(3) with the Lie-group form of the ω recursion), for tests.

Written from the formulas of docs/spline.md / tsslam_ref/assets/spline_kit.md only (numpy; it does
not import tsslam_ref.spline): B(u) = C [1, u, u², u³]ᵀ, Eq. (5) p, Eq. (6) R, Eq. (8) v, a,
Eq. (9) ω, ω̇ (body frame), segment = floor of the exact (t − t0)/Δt (fractions.Fraction).
``mistake`` plants the usual errors a user makes, so tests can check that ``check`` names them.
"""

import math
from fractions import Fraction

import numpy as np

C = np.array([[6, 0, 0, 0], [5, 3, -3, 1], [1, 3, 3, -2], [0, 0, 0, 1]], dtype=np.float64) / 6.0
OFFSET = {"paper": 2, "basalt": 0}
NON_CUMULATIVE = np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], dtype=np.float64) / 6.0
"""The textbook non-cumulative matrix, p(u) = [1, u, u², u³] M [P_k..P_{k+3}]ᵀ (for the mistake only)."""


def hat(v):
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_so3(v):
    theta = math.sqrt(float(v @ v))
    K = hat(v)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + math.sin(theta) / theta * K + (1 - math.cos(theta)) / theta**2 * K @ K


def log_so3(R):
    """Principal Log for angles < π − 1e-3 (enough for the shipped vectors' steps ≤ 2 rad)."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    s, c = np.linalg.norm(w), (np.trace(R) - 1.0) / 2.0
    theta = math.atan2(s, c)
    return w * (theta / s if s > 1e-12 else 1.0 + theta**2 / 6.0)


def v_matrix(phi):
    theta = math.sqrt(float(phi @ phi))
    K = hat(phi)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return np.eye(3) + (1 - math.cos(theta)) / theta**2 * K + (theta - math.sin(theta)) / theta**3 * K @ K


def exp_se3(xi, with_v=True):
    """4 x 4 pose of a tangent ξ = (ρ, φ); ``with_v=False`` leaves V(φ) out (a common mistake)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = exp_so3(xi[3:]), (v_matrix(xi[3:]) if with_v else np.eye(3)) @ xi[:3]
    return T


def log_se3(T, with_v=True):
    phi = log_so3(T[:3, :3])
    return np.concatenate([np.linalg.solve(v_matrix(phi) if with_v else np.eye(3), T[:3, 3]), phi])


def hat_se3(xi):
    H = np.zeros((4, 4))
    H[:3, :3], H[:3, 3] = hat(xi[3:]), xi[:3]
    return H


def evaluate_se3(data, with_v=True, world_twists=False):
    """Joint SE(3): T = T_k Π Exp(B_j ξ_j); body twist H = T⁻¹Ṫ by the Lie-group recursion
    H' = A⁻¹ H A + Ḃ ξ̂, Ḣ' = Ḃ [H', ξ̂] + A⁻¹ Ḣ A + B̈ ξ̂; v = R ρ, a = R(ω × ρ + ρ̇).
    ``with_v=False``: Exp(ρ, φ) = [Exp(φ), ρ] and its inverse as Log (V(φ) left out).
    ``world_twists``: ξ_j = Log(T_{k+j} T_{k+j-1}⁻¹), the world-side increment, composed on the right."""
    dt, t0, convention = data["dt"], data["t0"], data["convention"]
    poses = []
    for v, p in zip(np.asarray(data["rotvecs"], dtype=np.float64), np.asarray(data["translations"], dtype=np.float64)):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = exp_so3(v), p
        poses.append(T)
    n = len(poses)
    out = {key: [] for key in ("R", "p", "v", "a", "omega_body", "omegadot_body")}
    for t in data["times"]:
        i = exact_segment(t, t0, dt, OFFSET[convention], n)
        u = (t - t0) / dt - OFFSET[convention] - i
        B = C @ np.array([1, u, u * u, u**3])
        Bd = C @ np.array([0, 1, 2 * u, 3 * u * u]) / dt
        Bdd = C @ np.array([0, 0, 2, 6 * u]) / dt**2
        T, H, H_dot = poses[i].copy(), np.zeros((4, 4)), np.zeros((4, 4))
        for j in range(1, 4):
            xi = log_se3(poses[i + j] @ np.linalg.inv(poses[i + j - 1]) if world_twists else
                         np.linalg.inv(poses[i + j - 1]) @ poses[i + j], with_v)
            A = exp_se3(B[j] * xi, with_v)
            A_inv = np.linalg.inv(A)
            T = T @ A
            H = A_inv @ H @ A + Bd[j] * hat_se3(xi)
            H_dot = Bd[j] * (H @ hat_se3(xi) - hat_se3(xi) @ H) + A_inv @ H_dot @ A + Bdd[j] * hat_se3(xi)
        R = T[:3, :3]
        omega = np.array([H[2, 1], H[0, 2], H[1, 0]])
        omega_dot = np.array([H_dot[2, 1], H_dot[0, 2], H_dot[1, 0]])
        rho, rho_dot = H[:3, 3], H_dot[:3, 3]
        values = (R, T[:3, 3], R @ rho, R @ (np.cross(omega, rho) + rho_dot), omega, omega_dot)
        for key, value in zip(out, values):
            out[key].append(value)
    return {key: np.stack(value) for key, value in out.items()}


def exact_segment(t, t0, dt, offset, n_ctrl):
    """floor((t − t0)/Δt) − offset in exact rationals, clamped to the segments."""
    s = (Fraction(float(t)) - Fraction(float(t0))) / Fraction(float(dt))
    return min(max(math.floor(s) - offset, 0), n_ctrl - 4)


def evaluate(data, dtype=np.float64, mistake=None):
    """Outputs dict (R, p, v, a, omega_body, omegadot_body) of a vector's input, float64 arrays.

    mistake: None, "float32" (all arithmetic in float32), "world_frame" (ω, ω̇ world),
    "no_dt" (v, a not divided by Δt, Δt²), "transposed_basis" (Cᵀ for the translation),
    "snap_knots" (segment = floor(s + 1e-4): a time up to 1e-4 segments before a knot is put
    in the next one), "other_convention" (the other convention's control points, the segment
    clamped to the valid ones as code that never checks its domain does), "transposed_R" (R stored
    world-to-body), "nanoseconds" (correct code on int64 nanoseconds, as basalt-headers: t, t0 and
    Δt each rounded to whole ns, u from the integers), "world_increments" (d_j = Log(R_{k+j} R_{k+j-1}ᵀ),
    the increment in the world frame, composed on the right as if it were the body one), "old_omega"
    (ω̇'s cross product with ω^(j), before its update and rotation by A_jᵀ), "no_V" (joint SE(3) vectors:
    Exp(ρ, φ) = [Exp(φ), ρ] and Log likewise, V(φ) left out), "world_twists" (joint SE(3) vectors:
    ξ_j = Log(T_{k+j} T_{k+j-1}⁻¹) composed on the right), "clamp_ends" (u clamped to [0, 1], so a
    time within rounding outside the domain is evaluated at its end), "left_product" (R = A_3 A_2 A_1 R_k,
    the increments on the left in R alone), "non_cumulative" (the non-cumulative matrix's weights in the
    cumulative sum), "omegadot_sign" (ω̇'s cross term subtracted), "no_t0" (u from t / Δt: t0 forgotten).
    """
    if data.get("representation", "split") == "se3":
        return evaluate_se3(data, with_v=mistake != "no_V", world_twists=mistake == "world_twists")
    if mistake == "float32":
        dtype = np.float32
    dt, t0, convention = data["dt"], data["t0"], data["convention"]
    rotvecs = np.asarray(data["rotvecs"], dtype=np.float64)
    points = np.asarray(data["translations"], dtype=np.float64).astype(dtype)
    rotations = [exp_so3(v).astype(dtype) for v in rotvecs]
    n = len(rotations)
    out = {key: [] for key in ("R", "p", "v", "a", "omega_body", "omegadot_body")}
    basis_p = C.T if mistake == "transposed_basis" else C
    if mistake == "non_cumulative":
        C_used = NON_CUMULATIVE.T
        basis_p = C_used
    else:
        C_used = C
    if mistake == "no_t0":
        t0 = 0.0
    offset = OFFSET[convention]
    if mistake == "other_convention":
        offset = OFFSET["basalt" if convention == "paper" else "paper"]
    if mistake == "nanoseconds":
        t0_ns, dt_ns = round(Fraction(float(t0)) * 10**9), round(Fraction(float(dt)) * 10**9)
        dt = dt_ns * 1e-9
    for t in data["times"]:
        s_float = (t - t0) / dt - offset
        if mistake == "snap_knots":
            i = min(max(math.floor(s_float + 1e-4), 0), n - 4)
        elif mistake == "nanoseconds":
            relative_ns = round(Fraction(float(t)) * 10**9) - t0_ns - offset * dt_ns
            i = min(max(relative_ns // dt_ns, 0), n - 4)
            s_float = i + (relative_ns - i * dt_ns) / dt_ns
        else:
            i = exact_segment(t, t0, dt, offset, n)
        u = dtype(min(max(s_float - i, 0.0), 1.0) if mistake == "clamp_ends" else s_float - i)
        B = (C_used @ np.array([1, u, u * u, u * u * u], dtype=np.float64)).astype(dtype)
        Bd = (C_used @ np.array([0, 1, 2 * u, 3 * u * u], dtype=np.float64)).astype(dtype)
        Bdd = (C_used @ np.array([0, 0, 2, 6 * u], dtype=np.float64)).astype(dtype)
        Bp = (basis_p @ np.array([1, u, u * u, u * u * u], dtype=np.float64)).astype(dtype)
        Bpd = (basis_p @ np.array([0, 1, 2 * u, 3 * u * u], dtype=np.float64)).astype(dtype)
        Bpdd = (basis_p @ np.array([0, 0, 2, 6 * u], dtype=np.float64)).astype(dtype)
        scale_v, scale_a = (1.0, 1.0) if mistake == "no_dt" else (dtype(dt), dtype(dt) ** 2)
        p, v, a = points[i].copy(), np.zeros(3, dtype), np.zeros(3, dtype)
        R = rotations[i].copy()
        omega, omega_dot = np.zeros(3, dtype), np.zeros(3, dtype)
        for j in range(1, 4):
            delta = points[i + j] - points[i + j - 1]
            p = p + Bp[j] * delta
            v = v + Bpd[j] * delta / scale_v
            a = a + Bpdd[j] * delta / scale_a
            increment = rotations[i + j] @ rotations[i + j - 1].T if mistake == "world_increments" else (
                rotations[i + j - 1].T @ rotations[i + j])
            d = log_so3(increment.astype(np.float64)).astype(dtype)
            A = exp_so3(B[j] * d.astype(np.float64)).astype(dtype)
            R = A @ R if mistake == "left_product" else R @ A
            previous = omega
            omega = A.T @ omega + Bd[j] / scale_v * d
            crossed = previous if mistake == "old_omega" else omega  # (A_jᵀ ω^(j)) × d_j would equal ω^(j+1) × d_j
            sign = -1.0 if mistake == "omegadot_sign" else 1.0
            omega_dot = sign * Bd[j] / scale_v * np.cross(crossed, d) + A.T @ omega_dot + Bdd[j] / scale_a * d
        if mistake == "world_frame":
            omega, omega_dot = R @ omega, R @ omega_dot
        if mistake == "transposed_R":
            R = R.T
        for key, value in zip(out, (R, p, v, a, omega, omega_dot)):
            out[key].append(np.asarray(value, dtype=np.float64))
    return {key: np.stack(value) for key, value in out.items()}
