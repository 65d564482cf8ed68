"""Rigid-body geometry shared by every layer: SO(3) Exp/Log, poses, camera conventions.

Layer 0 (base). Imports torch, numpy and kornia only.

Conventions used everywhere in tsslam_ref
-----------------------------------------
* **Poses are camera-to-world**, ``T_wc`` (4, 4): a point in camera coordinates ``x_c`` maps to
  world coordinates as ``x_w = R_wc @ x_c + t_wc``.  ``t_wc`` is the optical centre in the world.
* **Camera axes are OpenCV's**: x right, y down, z forward (the camera looks along +z).
  Co-SLAM works internally in OpenGL axes (y up, looking along -z); we convert once, in the data
  loaders, with :func:`opengl_to_opencv_pose`.  Depth is the z coordinate in the camera frame.
* **Rotation vectors** (axis * angle, radians) are the tangent coordinates of SO(3):
  ``R = Exp(phi)``, ``phi = Log(R)``, with the principal branch ``|phi| <= pi``.
* **Quaternions** in files (TUM format) are ``(qx, qy, qz, qw)``, scalar last.

SO(3) Exp/Log go through kornia's ``axis_angle_to_rotation_matrix`` and
``rotation_matrix_to_axis_angle`` (quaternion based): stable at 0 and near pi in float32 and
float64, with finite gradients at exactly 0 (tests/test_geometry.py checks both and a gradcheck).  The wrappers here add batching over any leading shape.

Glossary

| symbol | variable | shape | unit |
|---|---|---|---|
| phi, Log(R) | ``rotvec`` | (..., 3) | rad |
| R | ``rotation`` | (..., 3, 3) | - |
| T_wc | ``pose`` / ``c2w`` | (..., 4, 4) | m |
| [w]x | ``skew(w)`` | (..., 3, 3) | - |
"""

import numpy as np
import torch
from kornia.geometry.conversions import (
    axis_angle_to_rotation_matrix,
    rotation_matrix_to_axis_angle,
)

# OpenCV <-> OpenGL camera axes: flip y and z of the camera frame (a right-multiplication).
_GL_CV_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def so3_exp(rotvec: torch.Tensor) -> torch.Tensor:
    """Exp: so(3) -> SO(3) (Rodrigues), batched.

    Args:
        rotvec: (..., 3) rotation vectors in radians.

    Returns:
        (..., 3, 3) rotation matrices.  Exact and differentiable at ``rotvec = 0``.
    """
    if rotvec.shape[-1] != 3:
        raise ValueError(f"so3_exp expects (..., 3) rotation vectors, got shape {tuple(rotvec.shape)}")
    batch = rotvec.shape[:-1]
    flat = rotvec.reshape(-1, 3)
    if flat.shape[0] == 0:
        return rotvec.new_zeros(*batch, 3, 3)
    return axis_angle_to_rotation_matrix(flat).reshape(*batch, 3, 3)


def so3_log(rotation: torch.Tensor) -> torch.Tensor:
    """Log: SO(3) -> so(3), principal branch (angle in [0, pi]), batched.

    Args:
        rotation: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors.  Stable near identity and near pi (quaternion based).  The
        sign of the axis is ambiguous at exactly pi, and Log is discontinuous there.
    """
    if rotation.shape[-2:] != (3, 3):
        raise ValueError(f"so3_log expects (..., 3, 3) matrices, got shape {tuple(rotation.shape)}")
    batch = rotation.shape[:-2]
    flat = rotation.reshape(-1, 3, 3)
    if flat.shape[0] == 0:
        return rotation.new_zeros(*batch, 3)
    return rotation_matrix_to_axis_angle(flat).reshape(*batch, 3)


def orthonormalize(rotation: torch.Tensor) -> torch.Tensor:
    """Nearest rotation matrix (Frobenius norm) to each (..., 3, 3) matrix: U diag(1, 1, det) V^T.

    Products of float32 rotations drift off SO(3) (about 1e-7 per product); a recursion such as
    the constant-velocity prediction T_{t-1} T_{t-2}^-1 T_{t-1} multiplies that drift by about
    1 + √2 ≈ 2.4 every frame unless the result is projected back.
    """
    U, _, Vh = torch.linalg.svd(rotation)
    sign = torch.sign(torch.linalg.det(U @ Vh))
    correction = torch.ones_like(rotation[..., 0])
    correction = torch.cat([correction[..., :2], sign.unsqueeze(-1)], dim=-1)  # (..., 3)
    return U @ (correction.unsqueeze(-1) * Vh)


def skew(vector: torch.Tensor) -> torch.Tensor:
    """Hat operator [w]x with [w]x v = w x v.  (..., 3) -> (..., 3, 3)."""
    x, y, z = vector.unbind(-1)
    zero = torch.zeros_like(x)
    rows = [
        torch.stack([zero, -z, y], dim=-1),
        torch.stack([z, zero, -x], dim=-1),
        torch.stack([-y, x, zero], dim=-1),
    ]
    return torch.stack(rows, dim=-2)


def vee(matrix: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`skew` applied to the skew-symmetric part.  (..., 3, 3) -> (..., 3)."""
    return 0.5 * torch.stack(
        [
            matrix[..., 2, 1] - matrix[..., 1, 2],
            matrix[..., 0, 2] - matrix[..., 2, 0],
            matrix[..., 1, 0] - matrix[..., 0, 1],
        ],
        dim=-1,
    )


def make_pose(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Stack (..., 3, 3) rotations and (..., 3) translations into (..., 4, 4) poses."""
    batch = rotation.shape[:-2]
    top = torch.cat([rotation, translation.unsqueeze(-1)], dim=-1)  # (..., 3, 4)
    bottom = rotation.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*batch, 1, 4)
    return torch.cat([top, bottom], dim=-2)


def invert_pose(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (..., 4, 4) using R^T and -R^T t (no general inverse)."""
    rotation_t = pose[..., :3, :3].transpose(-1, -2)
    translation = -(rotation_t @ pose[..., :3, 3:4]).squeeze(-1)
    return make_pose(rotation_t, translation)


def pixel_to_ray(u, v, fx, fy, cx, cy):
    """Camera-frame ray K^-1 [u, v, 1]^T = ((u - cx) / fx, (v - cy) / fy, 1) through pixel (u, v).

    OpenCV axes (z forward), so a point at depth z on pixel (u, v) is z times the ray.  u is the
    column, v the row; pixel centres sit at integer coordinates.  Works on numpy arrays or torch
    tensors (``u`` decides which) of any matching shape; fx, fy, cx, cy are numbers or arrays of
    that shape.  -> (..., 3).
    """
    if isinstance(u, torch.Tensor):
        return torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)


def quaternion_xyzw_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) in (qx, qy, qz, qw) order -> rotation matrices (..., 3, 3).

    The quaternion is normalised first; ``q`` and ``-q`` give the same matrix.
    Raises ValueError for a zero-norm quaternion.
    """
    q = np.asarray(quaternion, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise ValueError("quaternion with zero norm cannot be converted to a rotation")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quaternion_xyzw(rotation: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) as (qx, qy, qz, qw), qw >= 0.

    Uses the numerically stable branch on the largest diagonal term (Shepperd's method).
    """
    R = np.asarray(rotation, dtype=np.float64)
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    q = np.empty((R.shape[0], 4))
    trace = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    for n in range(R.shape[0]):
        m = R[n]
        candidates = [trace[n], m[0, 0], m[1, 1], m[2, 2]]
        k = int(np.argmax(candidates))
        if k == 0:
            s = 2.0 * np.sqrt(max(1.0 + trace[n], 0.0))
            q[n] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
        elif k == 1:
            s = 2.0 * np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
            q[n] = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif k == 2:
            s = 2.0 * np.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0))
            q[n] = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0))
            q[n] = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(*batch, 4)


def tum_to_pose(row: np.ndarray) -> np.ndarray:
    """TUM trajectory values (..., 7) = (tx, ty, tz, qx, qy, qz, qw) -> (..., 4, 4) float64 poses."""
    row = np.asarray(row, dtype=np.float64)
    pose = np.zeros(row.shape[:-1] + (4, 4))
    pose[..., :3, :3] = quaternion_xyzw_to_matrix(row[..., 3:7])
    pose[..., :3, 3] = row[..., :3]
    pose[..., 3, 3] = 1.0
    return pose


def pose_to_tum(pose: np.ndarray) -> np.ndarray:
    """(..., 4, 4) poses -> (..., 7) TUM values (tx, ty, tz, qx, qy, qz, qw)."""
    pose = np.asarray(pose, dtype=np.float64)
    return np.concatenate([pose[..., :3, 3], matrix_to_quaternion_xyzw(pose[..., :3, :3])], axis=-1)


def continuous_quaternions(quaternions: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions in time order -> the same rotations, each row's sign chosen so that it
    lies in the hemisphere of the row before (q and -q are one rotation).  Written this way, rows
    of a smooth motion never jump from q to about -q, and linear interpolation or differences of
    neighbouring rows stay meaningful.  The first row keeps its sign."""
    quaternions = np.asarray(quaternions, dtype=np.float64)
    if len(quaternions) < 2:
        return quaternions.copy()
    agree = np.where(np.sum(quaternions[1:] * quaternions[:-1], axis=-1) < 0, -1.0, 1.0)  # (N - 1,)
    signs = np.concatenate([[1.0], np.cumprod(agree)])
    return quaternions * signs[:, None]


def trajectory_to_tum(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses in time order -> (N, 7) TUM rows (tx, ty, tz, qx, qy, qz, qw) whose
    quaternions are :func:`continuous_quaternions` (the first with qw >= 0): what a trajectory file
    writes."""
    values = pose_to_tum(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4))
    values[:, 3:] = continuous_quaternions(values[:, 3:])
    return values


def opengl_to_opencv_pose(pose_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world pose with OpenGL camera axes -> the same camera with OpenCV axes.

    Negates the 2nd and 3rd columns of the rotation (the camera's y and z axes); the optical
    centre is unchanged.  The map is its own inverse.  (..., 4, 4) -> (..., 4, 4).
    """
    return np.asarray(pose_gl, dtype=np.float64) @ _GL_CV_FLIP


opencv_to_opengl_pose = opengl_to_opencv_pose


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """Angle |Log(R)| in degrees of (..., 3, 3) rotations, atan2 form (accurate near 0 and pi).

    angle = atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2).
    """
    rotations = np.asarray(rotations, np.float64)
    skew_part = np.stack(
        [
            rotations[..., 2, 1] - rotations[..., 1, 2],
            rotations[..., 0, 2] - rotations[..., 2, 0],
            rotations[..., 1, 0] - rotations[..., 0, 1],
        ],
        -1,
    )
    sin_angle = 0.5 * np.linalg.norm(skew_part, axis=-1)
    cos_angle = 0.5 * (np.trace(rotations, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sin_angle, cos_angle))


def pose_offsets(poses_a: np.ndarray, poses_b: np.ndarray):
    """How far two pose sequences are apart, pose by pose: (N,) distances between the camera centres
    (m) and (N,) angles |Log(R_a^T R_b)| (deg) of (N, 4, 4) camera-to-world poses, float64."""
    poses_a, poses_b = np.asarray(poses_a, np.float64), np.asarray(poses_b, np.float64)
    distances = np.linalg.norm(poses_a[:, :3, 3] - poses_b[:, :3, 3], axis=-1)
    return distances, rotation_angle_deg(np.swapaxes(poses_a[:, :3, :3], -1, -2) @ poses_b[:, :3, :3])
