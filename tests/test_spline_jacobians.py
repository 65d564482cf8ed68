"""Analytic Jacobians (tsslam_ref.spline_jacobians) against autograd and central finite differences.

Convention under test: R_k ← Exp(δ_k) R_k, P_k ← P_k + τ_k; output rotation R ← Exp(ε) R.
Oracles: torch.func.jacrev of spline.evaluate with that parametrisation (ε read off as
vee(∂R/∂δ · Rᵀ)), and central differences of spline.evaluate.
"""

import json

import numpy as np
import pytest
import torch

from tsslam_ref import se3_spline, spline, spline_jacobians, spline_kit
from tsslam_ref.geometry import so3_exp, vee

F64 = torch.float64
QUANTITIES = ("J_R", "J_p", "J_v", "J_a", "J_omega_body", "J_omegadot_body")


def random_spline(seed, n_ctrl=8, max_angle=1.5):
    rng = np.random.default_rng(seed)
    rotation = so3_exp(torch.as_tensor(rng.normal(size=3)))
    rotations = [rotation]
    for _ in range(n_ctrl - 1):
        axis = rng.normal(size=3)
        step = axis / np.linalg.norm(axis) * rng.uniform(0, max_angle)
        rotation = rotation @ so3_exp(torch.as_tensor(step))
        rotations.append(rotation)
    return torch.stack(rotations), torch.as_tensor(rng.normal(size=(n_ctrl, 3)))


def outputs(R, P, times, dt, t0, convention, delta, tau):
    """All six outputs with control points perturbed by δ (N, 3) and τ (N, 3)."""
    sample = spline.evaluate(so3_exp(delta) @ R, P + tau, times, dt, t0, convention, derivatives=2)
    return sample.rotation, sample.translation, sample.velocity_world, sample.acceleration_world, \
        sample.omega_body, sample.omegadot_body


def reference_jacobians(R, P, times, dt, t0, convention):
    """Full (M, 3, N, 3) Jacobians by autograd, rotation output as the left tangent ε."""
    n = R.shape[0]
    zero = torch.zeros(n, 3, dtype=F64)
    full_delta = torch.func.jacrev(lambda x: outputs(R, P, times, dt, t0, convention, x, zero))(zero)
    full_tau = torch.func.jacrev(lambda x: outputs(R, P, times, dt, t0, convention, zero, x))(zero)
    R_t = outputs(R, P, times, dt, t0, convention, zero, zero)[0]
    dR = full_delta[0]  # (M, 3, 3, N, 3)
    eps = vee(torch.einsum("mabnc,mdb->mncad", dR, R_t))  # (M, N, 3[c], 3[ad]) -> vee over (a, d)
    J_R = eps.permute(0, 3, 1, 2)  # (M, 3, N, 3)
    return {"J_R": J_R, "J_p": full_tau[1], "J_v": full_tau[2], "J_a": full_tau[3],
            "J_omega_body": full_delta[4], "J_omegadot_body": full_delta[5]}, full_delta, full_tau


def analytic_full(R, P, times, dt, t0, convention):
    """Analytic blocks scattered into (M, 3, N, 3)."""
    blocks = spline_jacobians.jacobians(R, P, times, dt, t0, convention)
    n = R.shape[0]
    full = {}
    for key in QUANTITIES:
        J = torch.zeros(len(times), 3, n, 3, dtype=F64)
        for m in range(len(times)):
            for i in range(4):
                J[m, :, int(blocks["first"][m]) + i, :] = blocks[key][m, i]
        full[key] = J
    return full


@pytest.mark.parametrize("convention,seed", [("paper", 0), ("basalt", 1), ("paper", 2)])
def test_jacobians_match_autograd_to_1e_9_relative(convention, seed):
    R, P = random_spline(seed)
    dt, t0 = 0.2, 1.0
    t_min, t_max = spline.valid_time_range(R.shape[0], dt, t0, convention)
    rng = np.random.default_rng(seed + 10)
    times = np.concatenate([[t_min, t_max, t0 + 4 * dt], rng.uniform(t_min, t_max, 9)])
    expected, _, _ = reference_jacobians(R, P, times, dt, t0, convention)
    ours = analytic_full(R, P, times, dt, t0, convention)
    for key in QUANTITIES:
        scale = expected[key].abs().max()
        assert (ours[key] - expected[key]).abs().max() <= 1e-9 * scale, key


def test_cross_blocks_are_zero_in_the_split_spline():
    R, P = random_spline(3)
    times = np.array([0.7, 1.1])
    _, full_delta, full_tau = reference_jacobians(R, P, times, 0.2, 0.0, "paper")
    for k in (1, 2, 3):  # p, v, a do not depend on δ
        assert full_delta[k].abs().max() == 0
    for k in (0, 4, 5):  # R, ω, ω̇ do not depend on τ
        assert full_tau[k].abs().max() == 0


def test_jacobians_match_central_differences():
    R, P = random_spline(4)
    dt, t0, convention = 0.25, 0.0, "paper"
    times = np.array([0.61, 0.93, 1.27])
    blocks = spline_jacobians.jacobians(R, P, times, dt, t0, convention)
    n, h = R.shape[0], 1e-6
    base = outputs(R, P, times, dt, t0, convention, torch.zeros(n, 3, dtype=F64), torch.zeros(n, 3, dtype=F64))
    for m in range(len(times)):
        first = int(blocks["first"][m])
        for i in range(4):
            for c in range(3):
                delta = torch.zeros(n, 3, dtype=F64)
                delta[first + i, c] = h
                plus = outputs(R, P, times, dt, t0, convention, delta, torch.zeros_like(delta))
                minus = outputs(R, P, times, dt, t0, convention, -delta, torch.zeros_like(delta))
                eps = vee((plus[0][m] - minus[0][m]) @ base[0][m].T) / (2 * h)
                assert torch.allclose(blocks["J_R"][m, i, :, c], eps, atol=1e-7)
                for key, k in (("J_omega_body", 4), ("J_omegadot_body", 5)):
                    fd = (plus[k][m] - minus[k][m]) / (2 * h)
                    assert torch.allclose(blocks[key][m, i, :, c], fd, atol=1e-6 * max(1.0, float(fd.abs().max())))
                plus = outputs(R, P, times, dt, t0, convention, torch.zeros_like(delta), delta)
                minus = outputs(R, P, times, dt, t0, convention, torch.zeros_like(delta), -delta)
                for key, k in (("J_p", 1), ("J_v", 2), ("J_a", 3)):
                    fd = (plus[k][m] - minus[k][m]) / (2 * h)
                    assert torch.allclose(blocks[key][m, i, :, c], fd, atol=1e-6 * max(1.0, float(fd.abs().max())))


def test_jacobians_at_identical_consecutive_rotations_are_finite_and_match_autograd():
    R, P = random_spline(5)
    R[3] = R[2]  # d = 0 for one pair
    times = np.array([0.9, 1.0, 1.05])
    expected, _, _ = reference_jacobians(R, P, times, 0.2, 0.0, "paper")
    ours = analytic_full(R, P, times, 0.2, 0.0, "paper")
    for key in QUANTITIES:
        assert torch.isfinite(ours[key]).all()
        assert (ours[key] - expected[key]).abs().max() <= 1e-9 * expected[key].abs().max(), key


def test_shipped_jacobian_vector_matches_autograd():
    data = json.loads((spline_kit.VECTOR_DIR / "jacobians_paper_dt0.25.json").read_text())
    R = so3_exp(torch.as_tensor(data["rotvecs"], dtype=F64))
    P = torch.as_tensor(data["translations"], dtype=F64)
    times = np.asarray(data["times"])
    expected, _, _ = reference_jacobians(R, P, times, data["dt"], data["t0"], data["convention"])
    first = np.asarray(data["J_first"]).astype(int)
    assert first.tolist() == spline.active_control_indices(times, R.shape[0], data["dt"], data["t0"])[:, 0].tolist()
    for key in QUANTITIES:
        shipped = torch.as_tensor(data[key], dtype=F64)  # (M, 4, 3, 3)
        picked = torch.stack([expected[key][m, :, first[m]:first[m] + 4, :].permute(1, 0, 2)
                              for m in range(len(times))])
        assert (shipped - picked).abs().max() <= 1e-9 * picked.abs().max(), key


def test_cli_evaluate_jacobians_and_check_catches_a_wrong_block(tmp_path, capsys):
    vector = spline_kit.VECTOR_DIR / "jacobians_paper_dt0.25.json"
    data = json.loads(vector.read_text())
    source = tmp_path / "in.json"
    source.write_text(json.dumps({key: data[key] for key in ("convention", "dt", "t0", "rotvecs", "translations", "times")}))
    output = tmp_path / "out.json"
    assert spline_kit.main(["evaluate", str(source), "-o", str(output), "--jacobians"]) == 0
    assert spline_kit.main(["check", str(vector), str(output)]) == 0
    written = json.loads(output.read_text())
    written["J_omega_body"][3][1][0][2] += 1e-3  # one entry of one block
    output.write_text(json.dumps(written))
    assert spline_kit.main(["check", str(vector), str(output)]) == 1
    out = capsys.readouterr().out
    assert "J_omega_body" in out and "worst at index 3" in out


def _se3(R, P, times, dt, t0, derivatives=2):
    return se3_spline.evaluate(R, P, times, dt, t0, derivatives=derivatives)


BAD_CONTROL_POINTS = [
    ("batched", lambda R, P: (R.expand(2, 8, 3, 3), P.expand(2, 8, 3)), ValueError,
     "control_rotations must be (N, 3, 3), got (2, 8, 3, 3) (one spline: no batch dimension)"),
    ("quaternions", lambda R, P: (torch.ones(8, 4, dtype=F64), P), ValueError,
     "control_rotations must be (N, 3, 3), got (8, 4) (rotation matrices: convert quaternions"),
    ("rotation_vectors", lambda R, P: (torch.ones(8, 3, dtype=F64), P), ValueError,
     "control_rotations must be (N, 3, 3), got (8, 3)"),
    ("numpy", lambda R, P: (R.numpy(), P.numpy()), TypeError,
     "control_rotations must be a float32 or float64 torch tensor, got ndarray"),
    ("half", lambda R, P: (R.half(), P.half()), TypeError,  # ran silently, 1e-2 off in R(t) and 0.3 in omega dot
     "control_rotations must be a float32 or float64 torch tensor, got a tensor of torch.float16"),
    ("integers", lambda R, P: (R.long(), P.long()), TypeError,  # failed inside torch.finfo, naming nothing
     "control_rotations must be a float32 or float64 torch tensor, got a tensor of torch.int64"),
    ("R_float32", lambda R, P: (R.float(), P), ValueError,
     "control rotations (torch.float32) and translations (torch.float64) must share a dtype"),
    ("P_float32", lambda R, P: (R, P.float()), ValueError,
     "control rotations (torch.float64) and translations (torch.float32) must share a dtype"),
    ("P_four_columns", lambda R, P: (R, torch.ones(8, 4, dtype=F64)), ValueError,
     "control_translations must be (N, 3) matching control_rotations (8, 3, 3), got (8, 4)"),
    ("P_fewer_rows", lambda R, P: (R, P[:5]), ValueError,
     "control_translations must be (N, 3) matching control_rotations (8, 3, 3), got (5, 3)"),
]


@pytest.mark.parametrize("function", [spline_jacobians.jacobians, _se3], ids=["jacobians", "se3_spline"])
@pytest.mark.parametrize("case,make,error,words", BAD_CONTROL_POINTS, ids=[case[0] for case in BAD_CONTROL_POINTS])
def test_jacobians_and_se3_spline_check_their_control_points_naming_what_was_given(function, case, make, error, words):
    """As spline.evaluate: a batch, quaternions, numpy arrays, mixed dtypes and mismatched rows are named."""
    R, P = random_spline(5)
    R_bad, P_bad = make(R, P)
    with pytest.raises(error) as raised:
        function(R_bad, P_bad, [1.2], 0.25, 0.5)
    assert words in str(raised.value), str(raised.value)


@pytest.mark.parametrize("derivatives", [3, -1, "2", None])
def test_se3_spline_refuses_other_derivative_orders_as_spline_does(derivatives):
    R, P = random_spline(6)
    for function in (spline.evaluate, se3_spline.evaluate):
        with pytest.raises(ValueError, match=r"derivatives must be 0, 1 or 2, got"):
            function(R, P, [1.2], 0.25, 0.5, derivatives=derivatives)


def test_jacobians_and_se3_spline_flatten_times_to_m_as_documented():
    R, P = random_spline(7)
    times = np.full((2, 3), 1.2)
    assert spline_jacobians.jacobians(R, P, times, 0.25, 0.5)["J_R"].shape == (6, 4, 3, 3)
    assert se3_spline.evaluate(R, P, times, 0.25, 0.5).rotation.shape == (6, 3, 3)
    assert se3_spline.evaluate(R, P, 1.2, 0.25, 0.5).translation.shape == (1, 3)
    assert spline.evaluate(R, P, times, 0.25, 0.5).rotation.shape == (2, 3, 3, 3)  # keeps the shape
