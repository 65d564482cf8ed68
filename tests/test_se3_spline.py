"""Joint SE(3) spline (tsslam_ref.se3_spline) and its shipped vectors against PyPose's pp.bspline.

Oracles: PyPose 0.9.5 ``pp.bspline`` (joint SE(3) cumulative, knot spacing 1; ``interval=u`` puts the
pose at u in output row 1) for R and p; central differences of PyPose poses for v, ω_body;
central differences of our own v, ω for a, ω̇.
"""

import json

import numpy as np
import pypose as pp
import pytest
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import conformance, se3_spline, spline, spline_kit
from tsslam_ref.geometry import so3_exp, so3_log

SE3_PATHS = [p for p in spline_kit.shipped_vectors() if json.loads(p.read_text()).get("representation") == "se3"]
OFFSET = {"paper": 2, "basalt": 0}


def pypose_pose(rotvecs, translations, first, u):
    """PyPose's pose at fraction u of the segment whose window starts at control point ``first``."""
    quaternions = Rotation.from_rotvec(rotvecs[first:first + 4]).as_quat()
    data = pp.SE3(torch.as_tensor(np.concatenate([translations[first:first + 4], quaternions], -1)))
    matrix = pp.bspline(data, interval=float(u)).matrix()[1].numpy()
    return matrix[:3, :3], matrix[:3, 3]


def test_there_are_joint_se3_vectors_in_both_conventions():
    assert {json.loads(p.read_text())["convention"] for p in SE3_PATHS} == {"paper", "basalt"}


@pytest.mark.parametrize("path", SE3_PATHS, ids=lambda p: p.stem)
def test_se3_vectors_match_pypose_bspline_to_1e_10(path):
    data = json.loads(path.read_text())
    rotvecs, translations = np.asarray(data["rotvecs"]), np.asarray(data["translations"])
    times = np.asarray(data["times"])
    s = (times - data["t0"]) / data["dt"] - OFFSET[data["convention"]]
    first = np.clip(np.floor(s), 0, len(rotvecs) - 4).astype(int)
    u = s - first
    checked = 0
    for m in np.linspace(0, len(times) - 1, 40).astype(int):
        if 1e-6 < u[m] < 1 - 1e-6:  # pp.bspline's interval must lie in (0, 1)
            R, p = pypose_pose(rotvecs, translations, first[m], u[m])
            assert np.abs(np.asarray(data["R"][m]) - R).max() < 1e-10
            assert np.abs(np.asarray(data["p"][m]) - p).max() < 1e-10
            checked += 1
    assert checked >= 30


@pytest.mark.parametrize("path", SE3_PATHS, ids=lambda p: p.stem)
def test_se3_vector_velocities_match_central_differences_of_pypose(path):
    data = json.loads(path.read_text())
    rotvecs, translations = np.asarray(data["rotvecs"]), np.asarray(data["translations"])
    dt = data["dt"]
    times = np.asarray(data["times"])
    s = (times - data["t0"]) / dt - OFFSET[data["convention"]]
    first = np.clip(np.floor(s), 0, len(rotvecs) - 4).astype(int)
    u = s - first
    h = 1e-5
    for m in np.linspace(0, len(times) - 1, 15).astype(int):
        if 1e-3 < u[m] < 1 - 1e-3:
            R_minus, p_minus = pypose_pose(rotvecs, translations, first[m], u[m] - h)
            R_plus, p_plus = pypose_pose(rotvecs, translations, first[m], u[m] + h)
            v = (p_plus - p_minus) / (2 * h * dt)
            omega = so3_log(torch.as_tensor(R_minus.T @ R_plus)).numpy() / (2 * h * dt)
            assert np.abs(np.asarray(data["v"][m]) - v).max() < 1e-7 * np.abs(data["v"]).max()
            assert np.abs(np.asarray(data["omega_body"][m]) - omega).max() < 1e-7 * np.abs(data["omega_body"]).max()


def test_se3_second_derivatives_match_central_differences_of_first():
    path = SE3_PATHS[0]
    data = json.loads(path.read_text())
    R = so3_exp(torch.as_tensor(data["rotvecs"], dtype=torch.float64))
    P = torch.as_tensor(data["translations"], dtype=torch.float64)
    dt, t0, convention = data["dt"], data["t0"], data["convention"]
    times = np.asarray(data["times"])
    s = (times - t0) / dt
    inside = np.abs(s - np.round(s)) > 1e-2
    t = times[inside]
    h = 1e-5 * dt
    plus = se3_spline.evaluate(R, P, t + h, dt, t0, convention, derivatives=1)
    minus = se3_spline.evaluate(R, P, t - h, dt, t0, convention, derivatives=1)
    a = (plus.velocity_world - minus.velocity_world).numpy() / (2 * h)
    omega_dot = (plus.omega_body - minus.omega_body).numpy() / (2 * h)
    assert np.abs(np.asarray(data["a"])[inside] - a).max() < 1e-6 * np.abs(data["a"]).max()
    assert np.abs(np.asarray(data["omegadot_body"])[inside] - omega_dot).max() < 1e-6 * np.abs(data["omegadot_body"]).max()


def test_se3_rotation_equals_the_split_rotation_and_translation_does_not():
    data = json.loads(SE3_PATHS[0].read_text())
    split = conformance.evaluate_input({key: data[key] for key in conformance.INPUT_KEYS})
    assert np.abs(np.asarray(split["R"]) - np.asarray(data["R"])).max() < 1e-14
    assert np.abs(np.asarray(split["omega_body"]) - np.asarray(data["omega_body"])).max() < 1e-12
    assert np.abs(np.asarray(split["p"]) - np.asarray(data["p"])).max() > 1e-2


def test_se3_with_equal_rotations_is_the_split_spline():
    n = 6
    R = so3_exp(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)).expand(n, 3, 3).clone()
    P = torch.as_tensor(np.random.default_rng(3).normal(size=(n, 3)))
    times = np.linspace(0.0, 3.0, 31)
    joint = se3_spline.evaluate(R, P, times, 1.0, 0.0, "basalt", derivatives=2)
    data = {"convention": "basalt", "dt": 1.0, "t0": 0.0, "rotvecs": so3_log(R).tolist(),
            "translations": P.tolist(), "times": times.tolist()}
    split = conformance.evaluate_input(data)
    for key, value in zip(conformance.OUTPUT_KEYS, joint):
        assert np.abs(value.numpy() - np.asarray(split[key])).max() < 1e-12


def test_check_names_a_split_candidate_against_a_joint_se3_vector(tmp_path, capsys):
    path = SE3_PATHS[0]
    data = json.loads(path.read_text())
    split = conformance.evaluate_input({key: data[key] for key in conformance.INPUT_KEYS})
    candidate = tmp_path / "split.json"
    candidate.write_text(json.dumps({key: split[key] for key in ("times",) + conformance.OUTPUT_KEYS}))
    assert spline_kit.main(["check", str(path), str(candidate)]) == 1
    out = capsys.readouterr().out
    assert "p equals the SPLIT" in out and "worst at index" in out


def _short_spacing_spline(seed: int):
    """7 random control points with large rotations at dt = 0.05 s from t0 = 10 s, and 12 query
    times off the knots: (R (7, 3, 3), P (7, 3), t (12,), dt, t0)."""
    g = torch.Generator().manual_seed(seed)
    n, dt, t0 = 7, 0.05, 10.0
    R = so3_exp(torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.7)
    P = torch.randn(n, 3, generator=g, dtype=torch.float64)
    t = t0 + dt * (2 + np.add.outer(np.arange(n - 3), [0.13, 0.5, 0.87]).reshape(-1))
    return R, P, t, dt, t0


def test_se3_a_and_omegadot_are_time_derivatives_at_a_short_knot_spacing():
    """derivatives=2 at Δt = 0.05 s, where d/du and d/dt differ by 20x (a: 400x), with large rotations.
    Oracles: ω̇_body equals the split spline's Eq. (9) recursion (the same rotation curve, another
    formulation) to 1e-11; a equals central differences (h = 1e-5 Δt) of v to 1e-7, both float64."""
    R, P, t, dt, t0 = _short_spacing_spline(seed=5)
    joint = se3_spline.evaluate(R, P, t, dt, t0, derivatives=2)
    split = spline.evaluate(R, P, t, dt, t0, derivatives=2)
    scale = float(split.omegadot_body.abs().max())
    assert float((joint.omegadot_body - split.omegadot_body).abs().max()) <= 1e-11 * scale
    h = 1e-5 * dt
    plus = se3_spline.evaluate(R, P, t + h, dt, t0, derivatives=1).velocity_world
    minus = se3_spline.evaluate(R, P, t - h, dt, t0, derivatives=1).velocity_world
    fd = (plus - minus) / (2 * h)
    assert float((joint.acceleration_world - fd).abs().max()) <= 1e-7 * float(fd.abs().max())


def test_se3_v_and_omega_are_time_derivatives_at_a_short_knot_spacing():
    """derivatives=1 at Δt = 0.05 s (d/dt = 20 d/du), large rotations.  Oracle: central differences
    (h = 1e-5 Δt) of the pose, v = (p(t+h) − p(t−h))/2h and ω_body = Log(R(t−h)ᵀ R(t+h))/2h, to 1e-7."""
    R, P, t, dt, t0 = _short_spacing_spline(seed=6)
    sample = se3_spline.evaluate(R, P, t, dt, t0, derivatives=1)
    h = 1e-5 * dt
    plus, minus = se3_spline.evaluate(R, P, t + h, dt, t0), se3_spline.evaluate(R, P, t - h, dt, t0)
    v = (plus.translation - minus.translation) / (2 * h)
    omega = so3_log(minus.rotation.transpose(-1, -2) @ plus.rotation) / (2 * h)
    assert float((sample.velocity_world - v).abs().max()) <= 1e-7 * float(v.abs().max())
    assert float((sample.omega_body - omega).abs().max()) <= 1e-7 * float(omega.abs().max())


def test_se3_evaluate_is_differentiable_with_respect_to_time():
    """Times given as a float64 tensor that requires grad get a gradient, as in the split spline
    (time offsets are estimated this way).  Oracle: central differences (h = 1e-5 Δt) of the
    translation and of the velocity, to 1e-7."""
    R, P, t, dt, t0 = _short_spacing_spline(seed=7)
    times = torch.tensor(t, dtype=torch.float64, requires_grad=True)
    sample = se3_spline.evaluate(R, P, times, dt, t0, derivatives=1)
    h = 1e-5 * dt
    plus = se3_spline.evaluate(R, P, t + h, dt, t0, derivatives=1)
    minus = se3_spline.evaluate(R, P, t - h, dt, t0, derivatives=1)
    for got, up, down in ((sample.translation, plus.translation, minus.translation),
                          (sample.velocity_world, plus.velocity_world, minus.velocity_world)):
        fd = ((up - down) / (2 * h))[:, 2]
        grad, = torch.autograd.grad(got[:, 2].sum(), times, retain_graph=True)
        assert float((grad - fd).abs().max()) <= 1e-7 * float(fd.abs().max())
