"""Tests for tsslam_ref.geometry: SO(3) Exp/Log wrappers, quaternions, pose helpers.

Oracles: scipy.spatial.transform.Rotation, analytic values (identity, axis flips), gradcheck, and
the stability cases of SO(3) Exp/Log (0, tiny angles, near π, exactly π).
"""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import geometry

F64 = torch.float64


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_so3_exp_log_batching_matches_scipy(batch, dtype):
    rng = np.random.default_rng(0)
    rotvec = rng.normal(size=batch + (3,))
    rotvec *= 3.0 / np.maximum(np.linalg.norm(rotvec, axis=-1, keepdims=True), 1.0)  # |φ| < π
    R = geometry.so3_exp(torch.as_tensor(rotvec, dtype=dtype))
    assert R.shape == batch + (3, 3) and R.dtype == dtype
    expected = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(batch + (3, 3))
    tol = 1e-12 if dtype == F64 else 2e-6
    assert np.abs(R.numpy() - expected).max() < tol
    assert np.abs(geometry.so3_log(R).numpy() - rotvec).max() < (1e-12 if dtype == F64 else 1e-5)


def test_so3_exp_log_empty_batch_and_shape_errors():
    assert geometry.so3_exp(torch.zeros(0, 3)).shape == (0, 3, 3)
    assert geometry.so3_log(torch.zeros(0, 3, 3)).shape == (0, 3)
    with pytest.raises(ValueError, match="rotation vectors"):
        geometry.so3_exp(torch.zeros(4))
    with pytest.raises(ValueError, match="matrices"):
        geometry.so3_log(torch.zeros(3, 4))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-4, 1.0, math.pi - 1e-2, math.pi - 1e-6])
def test_so3_log_round_trip_at_zero_small_and_near_pi(dtype, angle):
    axis = torch.tensor([0.36, -0.48, 0.8], dtype=F64)
    rotvec = (angle * axis).to(dtype)
    back = geometry.so3_log(geometry.so3_exp(rotvec))
    tol = 1e-12 if dtype == F64 else 1e-6
    assert torch.allclose(back.double(), rotvec.double(), atol=tol, rtol=0)


def test_so3_log_at_exactly_pi_gives_the_same_rotation():
    for axis in ([1.0, 0, 0], [0, 0.6, 0.8]):
        rotvec = math.pi * torch.tensor(axis, dtype=F64)
        R = geometry.so3_exp(rotvec)
        back = geometry.so3_log(R)
        assert abs(float(back.norm()) - math.pi) < 1e-12  # sign of the axis is ambiguous at π
        assert torch.allclose(geometry.so3_exp(back), R, atol=1e-12)


def test_so3_exp_identity_and_finite_gradient_at_zero():
    v = torch.zeros(2, 3, dtype=F64, requires_grad=True)
    R = geometry.so3_exp(v)
    assert torch.equal(R.detach(), torch.eye(3, dtype=F64).expand(2, 3, 3))
    (grad,) = torch.autograd.grad(geometry.so3_log(R).sum(), v)
    assert torch.allclose(grad, torch.ones_like(grad))  # d Log(Exp(v)) / dv = I at 0


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1.0, math.pi - 1e-3])
def test_gradcheck_so3_exp_and_log(angle):
    axis = torch.tensor([0.36, -0.48, 0.8], dtype=F64)
    v = (angle * axis + torch.tensor([0.0, 0.0, 0.0], dtype=F64)).requires_grad_(True)
    assert torch.autograd.gradcheck(geometry.so3_exp, (v,), eps=1e-7, atol=1e-6)
    assert torch.autograd.gradcheck(lambda x: geometry.so3_log(geometry.so3_exp(x)), (v,), eps=1e-7, atol=1e-6)


def test_skew_vee_and_cross_product():
    rng = np.random.default_rng(1)
    w, x = (torch.as_tensor(rng.normal(size=(4, 3))) for _ in range(2))
    assert torch.allclose((geometry.skew(w) @ x[..., None])[..., 0], torch.linalg.cross(w, x), atol=1e-15)
    assert torch.allclose(geometry.vee(geometry.skew(w)), w, atol=1e-15)


def test_quaternion_conversions_match_scipy_and_round_trip():
    rng = np.random.default_rng(2)
    quats = rng.normal(size=(50, 4))
    quats[0] = [0, 0, 0, 1]
    quats[1] = [1, 0, 0, 0]  # angle π
    quats[2] = [0, 0, 0.7071067811865476, -0.7071067811865476]  # qw < 0
    R = geometry.quaternion_xyzw_to_matrix(quats)
    assert np.abs(R - Rotation.from_quat(quats).as_matrix()).max() < 1e-12
    q = geometry.matrix_to_quaternion_xyzw(R)
    expected = Rotation.from_matrix(R).as_quat()
    expected[expected[:, 3] < 0] *= -1
    assert (q[:, 3] >= 0).all()
    sign = np.sign(np.sum(q * expected, axis=-1, keepdims=True))  # q and −q at qw = 0
    assert np.abs(q - sign * expected).max() < 1e-12
    assert np.abs(geometry.quaternion_xyzw_to_matrix(q) - R).max() < 1e-12
    with pytest.raises(ValueError, match="zero norm"):
        geometry.quaternion_xyzw_to_matrix(np.zeros(4))


def test_tum_rows_round_trip_and_pose_helpers():
    rng = np.random.default_rng(3)
    rows = np.concatenate([rng.normal(size=(6, 3)), Rotation.random(6, random_state=4).as_quat()], -1)
    rows[rows[:, 6] < 0, 3:] *= -1
    poses = geometry.tum_to_pose(rows)
    assert np.abs(geometry.pose_to_tum(poses) - rows).max() < 1e-12
    T = torch.as_tensor(poses)
    assert torch.allclose(geometry.invert_pose(T) @ T, torch.eye(4, dtype=F64).expand(6, 4, 4), atol=1e-12)
    rotvec = torch.as_tensor(Rotation.from_matrix(poses[:, :3, :3]).as_rotvec())
    assert torch.allclose(geometry.make_pose(geometry.so3_exp(rotvec), T[:, :3, 3]), T, atol=1e-12)
    np.testing.assert_allclose(geometry.rotation_angle_deg(poses[:, :3, :3]), np.degrees(rotvec.norm(dim=-1).numpy()), atol=1e-10)


def test_rotation_angle_is_accurate_near_zero_and_pi():
    angles = np.array([1e-9, 1e-5, 0.3, np.pi - 1e-7, np.pi])
    axes = np.random.default_rng(7).normal(size=(5, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    matrices = Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    np.testing.assert_allclose(geometry.rotation_angle_deg(matrices), np.degrees(angles), rtol=1e-6, atol=1e-12)


def test_opengl_opencv_flip_is_an_involution_that_flips_y_and_z():
    pose = geometry.tum_to_pose(np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.9]))
    cv = geometry.opengl_to_opencv_pose(pose)
    assert np.allclose(cv[:3, 0], pose[:3, 0]) and np.allclose(cv[:3, 1:3], -pose[:3, 1:3])
    assert np.allclose(cv[:3, 3], pose[:3, 3])
    assert np.allclose(geometry.opencv_to_opengl_pose(cv), pose)


def test_orthonormalize_projects_onto_so3_and_keeps_rotations():
    from tsslam_ref.geometry import orthonormalize, so3_exp

    generator = torch.Generator().manual_seed(0)
    rotations = so3_exp(torch.randn(5, 3, generator=generator, dtype=torch.float64))
    assert torch.allclose(orthonormalize(rotations), rotations, atol=1e-12)
    noisy = rotations + 0.05 * torch.randn(5, 3, 3, generator=generator, dtype=torch.float64)
    projected = orthonormalize(noisy)
    assert torch.allclose(projected.transpose(-1, -2) @ projected, torch.eye(3, dtype=torch.float64).expand(5, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(projected), torch.ones(5, dtype=torch.float64))
    # nearest in Frobenius norm: no other rotation close by is nearer
    for candidate in (so3_exp(0.01 * torch.randn(5, 3, generator=generator, dtype=torch.float64)) @ projected,):
        assert torch.all((candidate - noisy).norm(dim=(1, 2)) >= (projected - noisy).norm(dim=(1, 2)) - 1e-12)


def test_pixel_to_ray_is_the_inverse_intrinsic_matrix_for_numpy_and_torch():
    """Oracle: np.linalg.inv(K) @ [u, v, 1] with K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
    fx, fy, cx, cy = 517.3, 516.5, 318.6, 255.3
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(11)
    u, v = rng.uniform(0, 640, 50), rng.uniform(0, 480, 50)
    expected = (np.linalg.inv(K) @ np.stack([u, v, np.ones_like(u)])).T  # (50, 3)
    np.testing.assert_allclose(geometry.pixel_to_ray(u, v, fx, fy, cx, cy), expected, rtol=1e-12, atol=1e-15)
    rays = geometry.pixel_to_ray(torch.as_tensor(u), torch.as_tensor(v), fx, fy, cx, cy)
    assert isinstance(rays, torch.Tensor) and rays.shape == (50, 3)
    np.testing.assert_allclose(rays.numpy(), expected, rtol=1e-12, atol=1e-15)


def test_orthonormalize_of_a_reflected_matrix_is_the_rotation_not_the_reflection():
    """M = R diag(1, 1, -0.5) has det < 0: its SVD's U V^T is the reflection R diag(1, 1, -1); the
    nearest rotation (flip the smallest singular direction back) is R itself, derived by hand."""
    rotations = torch.as_tensor(Rotation.random(4, random_state=5).as_matrix())
    reflected = rotations @ torch.diag(torch.tensor([1.0, 1.0, -0.5], dtype=F64))
    projected = geometry.orthonormalize(reflected)
    assert torch.allclose(projected, rotations, atol=1e-12)
    assert torch.allclose(torch.linalg.det(projected), torch.ones(4, dtype=F64), atol=1e-12)


def test_continuous_quaternions_follow_the_previous_row_through_several_sign_flips():
    """Rows q0, -q1, q2, -q3 of a smooth motion (written by hand): the result is q0, q1, q2, q3,
    each row's sign set by the row before it, not only by its own dot product."""
    angles = np.array([0.1, 0.2, 0.3, 0.4])
    smooth = np.stack([[np.sin(a / 2), 0.0, 0.0, np.cos(a / 2)] for a in angles])
    written = smooth * np.array([1.0, -1.0, 1.0, -1.0])[:, None]
    np.testing.assert_allclose(geometry.continuous_quaternions(written), smooth, atol=1e-15)
    np.testing.assert_allclose(geometry.continuous_quaternions(-written), -smooth, atol=1e-15)  # the first keeps its sign


def test_trajectory_rows_stay_continuous_through_half_turns():
    """A camera turning about z by θ = 0.5 .. 7 rad while moving: the rows are (t, 0, 0, sin(θ/2),
    cos(θ/2)) by hand, continuous in θ, although each pose alone would be written with qw >= 0
    (a jump from q to -q at θ = π and back at 3π)."""
    angles = np.arange(0.5, 7.0, 0.5)
    translations = np.stack([angles, -2.0 * angles, np.full_like(angles, 0.5)], axis=1)
    poses = np.zeros((len(angles), 4, 4))
    poses[:, :3, :3] = Rotation.from_rotvec(angles[:, None] * np.array([0.0, 0.0, 1.0])).as_matrix()
    poses[:, :3, 3], poses[:, 3, 3] = translations, 1.0
    expected = np.concatenate([translations, np.zeros((len(angles), 2)), np.sin(angles / 2)[:, None],
                               np.cos(angles / 2)[:, None]], axis=1)
    np.testing.assert_allclose(geometry.trajectory_to_tum(poses), expected, atol=1e-12)
