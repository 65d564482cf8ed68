"""Tests for the conformance kit (tsslam_ref.conformance) and the shipped spline vectors.

The shipped vectors are validated against oracles that do not use our closed-form derivatives:
PyPose rotations (pp.bspline with interval=u), scipy B-splines for translation, autograd in time
for v, a, ω, ω̇, central differences, and the basalt golden table (tsslam_ref/assets/spline_kit.md).
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pypose as pp
import pytest
import scipy.interpolate
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import conformance, knots, spline, spline_kit
from tsslam_ref.geometry import so3_exp, so3_log, vee

F64 = torch.float64
VECTOR_DIR = Path(spline.__file__).resolve().parent / "assets" / "spline_vectors"
ALL_VECTOR_PATHS = sorted(VECTOR_DIR.glob("*.json"))
KNOT_VECTOR_PATHS = [p for p in ALL_VECTOR_PATHS if "knots" in json.loads(p.read_text())]
"""The non-uniform vectors (key "knots"), tested at the end of this file."""
UNIFORM_VECTOR_PATHS = [p for p in ALL_VECTOR_PATHS if p not in KNOT_VECTOR_PATHS]
VECTOR_PATHS = [p for p in UNIFORM_VECTOR_PATHS if json.loads(p.read_text()).get("representation", "split") == "split"]
"""The uniform split vectors (the joint SE(3) ones are tested in tests/test_se3_spline.py)."""
OFFSET = {"paper": 2, "basalt": 0}


def load_vector(path):
    data = json.loads(Path(path).read_text())
    arrays = {key: np.asarray(data[key], dtype=np.float64) for key in ("rotvecs", "translations", "times", *conformance.OUTPUT_KEYS)}
    return data, arrays


def scale_err(value, reference):
    return np.abs(np.asarray(value) - reference).max() / np.abs(reference).max()


def test_shipped_vectors_exist_and_are_small():
    assert len(VECTOR_PATHS) >= 5
    assert sum(path.stat().st_size for path in ALL_VECTOR_PATHS) < 1_500_000
    conventions = {json.loads(path.read_text())["convention"] for path in UNIFORM_VECTOR_PATHS}
    assert conventions == {"paper", "basalt"} and len(KNOT_VECTOR_PATHS) >= 1
    for path in UNIFORM_VECTOR_PATHS:
        data, arrays = load_vector(path)
        t_min, t_max = spline.valid_time_range(len(data["rotvecs"]), data["dt"], data["t0"], data["convention"])
        assert arrays["times"].min() == t_min and arrays["times"].max() == t_max  # both domain ends
        assert len(data["times"]) >= (30 if "J_R" in data else 200)


def test_every_shipped_vector_holds_each_time_once():
    """The domain ends are knots too; a vector must not list them (or any time) twice."""
    for path in ALL_VECTOR_PATHS:
        times = json.loads(path.read_text())["times"]
        assert len(set(times)) == len(times), (path.stem, len(times) - len(set(times)))
        assert times == sorted(times), path.stem


@pytest.mark.parametrize("path", VECTOR_PATHS, ids=lambda p: p.stem)
def test_shipped_vector_rotations_match_pypose_and_translations_match_scipy(path):
    data, arrays = load_vector(path)
    dt, t0, convention = data["dt"], data["t0"], data["convention"]
    n = arrays["rotvecs"].shape[0]
    s = (arrays["times"] - t0) / dt - OFFSET[convention]
    first = np.clip(np.floor(s + 1e-6).astype(int), 0, n - 4)
    u = s - first
    quaternions = Rotation.from_rotvec(arrays["rotvecs"]).as_quat()
    se3 = pp.SE3(torch.as_tensor(np.concatenate([arrays["translations"], quaternions], -1)))
    for m in np.linspace(0, len(u) - 1, 25).astype(int):  # a spread subset (PyPose is slow per call)
        if 1e-6 < u[m] < 1 - 1e-6:
            expected = pp.bspline(se3[first[m]:first[m] + 4], interval=float(u[m])).matrix()[1, :3, :3]
            assert np.abs(arrays["R"][m] - expected.numpy()).max() < 1e-10
    knots = dt * (np.arange(n + 4) - 3 + OFFSET[convention])  # relative to t0 (scipy is not stamp-safe)
    oracle = scipy.interpolate.BSpline(knots, arrays["translations"], 3, extrapolate=True)
    times = arrays["times"] - t0
    assert scale_err(arrays["p"], oracle(times)) < 1e-9
    assert scale_err(arrays["v"], oracle(times, 1)) < 1e-9
    # scipy gets times - t0 (rounded for stamps), which moves a time near a knot by up to an ulp of
    # the stamp: compare a tightly away from knots (exactness at knots: test_spline_reference.py).
    s_rel = times / dt
    away = np.abs(s_rel - np.round(s_rel)) > 1e-4
    assert scale_err(arrays["a"][away], oracle(times[away], 2)) < 1e-9


@pytest.mark.parametrize("path", VECTOR_PATHS, ids=lambda p: p.stem)
def test_shipped_vector_derivatives_match_autograd_in_time(path):
    """v, a, ω_body, ω̇_body of the vector vs forward-mode autograd of the pose path."""
    data, arrays = load_vector(path)
    R = so3_exp(torch.as_tensor(arrays["rotvecs"]))
    P = torch.as_tensor(arrays["translations"])
    times = torch.as_tensor(arrays["times"])
    ones = torch.ones_like(times)

    def pose(t):
        sample = spline.evaluate(R, P, t, data["dt"], data["t0"], data["convention"])
        return sample.rotation, sample.translation

    def first(t):
        return torch.func.jvp(pose, (t,), (ones,))

    (R_t, _), (R_dot, p_dot) = first(times)
    _, (_, (R_ddot, p_ddot)) = torch.func.jvp(first, (times,), (ones,))
    Rt = R_t.transpose(-1, -2)
    assert scale_err(arrays["v"], p_dot.numpy()) < 1e-9
    assert scale_err(arrays["a"], p_ddot.numpy()) < 1e-9
    assert scale_err(arrays["omega_body"], vee(Rt @ R_dot).numpy()) < 1e-9
    assert scale_err(arrays["omegadot_body"], vee(Rt @ R_ddot).numpy()) < 1e-9


def test_shipped_vector_derivatives_match_central_differences():
    data, arrays = load_vector(VECTOR_DIR / "paper_dt0.25_large_rot.json")
    dt = data["dt"]
    R = so3_exp(torch.as_tensor(arrays["rotvecs"]))
    P = torch.as_tensor(arrays["translations"])
    s = (arrays["times"] - data["t0"]) / dt
    inside = np.abs(s - np.round(s)) > 1e-2  # away from knots (jerk jumps there)
    times = arrays["times"][inside]
    h = 1e-5 * dt
    plus = spline.evaluate(R, P, times + h, dt, data["t0"], derivatives=1)
    minus = spline.evaluate(R, P, times - h, dt, data["t0"], derivatives=1)
    assert scale_err(arrays["v"][inside], ((plus.translation - minus.translation) / (2 * h)).numpy()) < 1e-7
    assert scale_err(arrays["a"][inside], ((plus.velocity_world - minus.velocity_world) / (2 * h)).numpy()) < 1e-7
    omega_fd = so3_log(minus.rotation.transpose(-1, -2) @ plus.rotation) / (2 * h)
    assert scale_err(arrays["omega_body"][inside], omega_fd.numpy()) < 1e-7
    assert scale_err(arrays["omegadot_body"][inside], ((plus.omega_body - minus.omega_body) / (2 * h)).numpy()) < 1e-7


def test_basalt_golden_vector_matches_spec_table():
    data, arrays = load_vector(VECTOR_DIR / "basalt_golden_dt0.5.json")
    golden = {  # basalt golden table (tsslam_ref/assets/spline_kit.md), t -> (rotvec, omegadot_body)
        0.00: ((0.134116980, -0.151459662, 0.282680481), (0.896277239, 1.063012442, -0.512550323)),
        0.35: ((0.289163844, -0.111468504, 0.450617209), (-0.532954773, 1.330922034, 0.317237811)),
        0.80: ((0.325661486, 0.139534886, 0.740555699), (-1.292066019, 0.771943126, -0.060129717)),
        1.20: ((0.093519323, 0.413904218, 1.016607449), (-0.781496148, -0.677918007, -1.109365084)),
    }
    positions = {0.00: (0.916666667, 0.166666667, 0.416666667), 0.35: (1.290583333, 0.7045, 0.469166667),
                 0.80: (1.171333333, 1.582, 0.194666667), 1.20: (0.582, 2.171333333, -0.2)}
    for t, (rotvec, omega_dot) in golden.items():
        m = int(np.flatnonzero(arrays["times"] == t)[0])
        assert np.abs(Rotation.from_matrix(arrays["R"][m]).as_rotvec() - rotvec).max() < 1e-8
        assert np.abs(arrays["omegadot_body"][m] - omega_dot).max() < 1e-8
        assert np.abs(arrays["p"][m] - positions[t]).max() < 1e-8


# ------------------------------------------------------------------------------------------
# Command line


def _input_only(path, tmp_path):
    data = json.loads(Path(path).read_text())
    subset = {key: data[key] for key in conformance.INPUT_KEYS}
    target = tmp_path / "input.json"
    target.write_text(json.dumps(subset))
    return target


@pytest.mark.parametrize("path", VECTOR_PATHS, ids=lambda p: p.stem)
def test_cli_evaluate_reproduces_the_shipped_vector_and_check_passes(path, tmp_path, capsys):
    source = _input_only(path, tmp_path)
    output = tmp_path / "out.json"
    assert spline_kit.main(["evaluate", str(source), "-o", str(output)]) == 0
    assert spline_kit.main(["check", str(path), str(output)]) == 0
    assert "PASS" in capsys.readouterr().out
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp_")] == []  # atomic write


def test_cli_check_fails_on_one_perturbed_value(tmp_path, capsys):
    path = VECTOR_PATHS[0]
    data = json.loads(path.read_text())
    data["omegadot_body"][17][1] += 1e-4
    candidate = tmp_path / "cand.json"
    candidate.write_text(json.dumps(data))
    assert spline_kit.main(["check", str(path), str(candidate)]) == 1
    table = capsys.readouterr().out
    assert "omegadot_body" in table and "FAIL" in table
    assert f"index 17, t = {data['times'][17]!r}" in table  # the worst time is named
    assert spline_kit.main(["check", str(path), str(candidate), "--atol", "1e-3"]) == 0


def test_cli_refuses_to_overwrite_without_force(tmp_path, capsys):
    source = _input_only(VECTOR_PATHS[0], tmp_path)
    output = tmp_path / "out.json"
    output.write_text("user data")
    assert spline_kit.main(["evaluate", str(source), "-o", str(output)]) == 2
    assert output.read_text() == "user data" and "--force" in capsys.readouterr().err  # not the kit's file
    assert spline_kit.main(["evaluate", str(source), "-o", str(output), "--force"]) == 0
    assert "R" in json.loads(output.read_text())


def test_cli_out_of_domain_time_exits_2_naming_the_time(tmp_path, capsys):
    data = {"convention": "paper", "dt": 0.5, "t0": 0.0, "rotvecs": [[0, 0, 0]] * 5,
            "translations": [[0, 0, 0]] * 5, "times": [1.0, 2.25]}
    source = tmp_path / "in.json"
    source.write_text(json.dumps(data))
    assert spline_kit.main(["evaluate", str(source), "-o", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert "2.25" in err and "domain" in err
    assert not (tmp_path / "o.json").exists()


@pytest.mark.parametrize("broken,key", [
    ({"dt": None}, "dt"), ({"convention": "kontiki"}, "convention"), ({"rotvecs": [[0, 0]] * 5}, "rotvecs"),
    ({"times": "soon"}, "times"), ({"translations": [[0, 0, 0]] * 4}, "rotvecs"),
])
def test_cli_malformed_input_exits_2_naming_the_key(tmp_path, capsys, broken, key):
    data = {"convention": "paper", "dt": 0.5, "t0": 0.0, "rotvecs": [[0, 0, 0]] * 5,
            "translations": [[0, 0, 0]] * 5, "times": [1.0]}
    data.update(broken)
    source = tmp_path / "in.json"
    source.write_text(json.dumps(data))
    assert spline_kit.main(["evaluate", str(source), "-o", str(tmp_path / "o.json")]) == 2
    assert repr(key) in capsys.readouterr().err


def test_cli_check_malformed_files_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert spline_kit.main(["check", str(VECTOR_PATHS[0]), str(bad)]) == 2
    assert "bad.json" in capsys.readouterr().err
    missing = tmp_path / "missing.json"
    missing.write_text(json.dumps({"times": json.loads(VECTOR_PATHS[0].read_text())["times"]}))
    assert spline_kit.main(["check", str(VECTOR_PATHS[0]), str(missing)]) == 2
    assert "'R'" in capsys.readouterr().err


def test_kit_runs_as_python_dash_m(tmp_path):
    source = _input_only(VECTOR_DIR / "basalt_golden_dt0.5.json", tmp_path)
    output = tmp_path / "out.json"
    command = [sys.executable, "-m", "tsslam_ref.spline_kit", "evaluate", str(source), "-o", str(output)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert spline_kit.main(["check", str(VECTOR_DIR / "basalt_golden_dt0.5.json"), str(output)]) == 0


# ------------------------------------------------------------------------------------------
# Non-uniform knots (key "knots")


@pytest.mark.parametrize("path", KNOT_VECTOR_PATHS, ids=lambda p: p.stem)
def test_knot_vector_translation_matches_scipy_and_rates_match_autograd(path):
    data, arrays = load_vector(path)
    knot_vector = np.asarray(data["knots"])
    assert arrays["times"].min() == knot_vector[2] and arrays["times"].max() == knot_vector[-3]  # domain ends
    origin = knot_vector[0]  # scipy gets times relative to the first knot (stamps)
    relative = np.r_[-1.0, knot_vector - origin, knot_vector[-1] - origin + 1.0]
    oracle = scipy.interpolate.BSpline(relative, arrays["translations"], 3)
    times = arrays["times"] - origin
    gap = np.abs(times[:, None] - (knot_vector - origin)[None, :]).min(1)
    away = gap > 1e-6  # scipy's relative times move a knot-adjacent stamp to the other side
    assert scale_err(arrays["p"], oracle(times)) < 1e-9
    assert scale_err(arrays["v"][away], oracle(times[away], 1)) < 1e-9
    assert scale_err(arrays["a"][away], oracle(times[away], 2)) < 1e-9
    R = so3_exp(torch.as_tensor(arrays["rotvecs"]))
    P = torch.as_tensor(arrays["translations"])
    t = torch.as_tensor(arrays["times"][away])
    ones = torch.ones_like(t)

    def rotation(at):
        return knots.evaluate(R, P, at, knot_vector).rotation

    def first(at):
        return torch.func.jvp(rotation, (at,), (ones,))

    R_t, R_dot = first(t)
    _, (_, R_ddot) = torch.func.jvp(first, (t,), (ones,))
    Rt = R_t.transpose(-1, -2)
    assert scale_err(arrays["omega_body"][away], vee(Rt @ R_dot).numpy()) < 1e-9
    assert scale_err(arrays["omegadot_body"][away], vee(Rt @ R_ddot).numpy()) < 1e-9


@pytest.mark.parametrize("path", KNOT_VECTOR_PATHS, ids=lambda p: p.stem)
def test_cli_evaluates_and_checks_a_knot_vector(path, tmp_path, capsys):
    data = json.loads(path.read_text())
    source = tmp_path / "input.json"
    source.write_text(json.dumps({key: data[key] for key in ("knots", "rotvecs", "translations", "times")}))
    output = tmp_path / "out.json"
    assert spline_kit.main(["evaluate", str(source), "-o", str(output)]) == 0
    assert spline_kit.main(["check", str(path), str(output)]) == 0
    assert "PASS" in capsys.readouterr().out
    perturbed = json.loads(output.read_text())
    perturbed["omegadot_body"][5][0] += 1e-3
    output.write_text(json.dumps(perturbed))
    assert spline_kit.main(["check", str(path), str(output)]) == 1


@pytest.mark.parametrize("change, words", [
    ({"knots": [0.0, 0.5, 0.4, 1.5, 2.0, 2.5, 3.0]}, ["'knots'", "strictly increasing", "knots[1] = 0.5"]),
    ({"knots": [0.0, 0.5, 1.0]}, ["'knots'", "n_ctrl + 2 = 7"]),
    ({"dt": 0.5}, ["'knots' replaces", "'dt'"]),
    ({"representation": "se3"}, ["'knots'", "split"]),
])
def test_cli_bad_knot_input_exits_2_naming_the_key(tmp_path, capsys, change, words):
    data = {"knots": [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0], "rotvecs": [[0, 0, 0]] * 5,
            "translations": [[0, 0, 0]] * 5, "times": [1.2]}
    data.update(change)
    source = tmp_path / "in.json"
    source.write_text(json.dumps(data))
    assert spline_kit.main(["evaluate", str(source), "-o", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert all(word in err for word in words), err


# ------------------------------------------------------------------------------------------
# What an outside implementation meets in `check` and `evaluate`


def _evaluated(path, tmp_path, *flags):
    """The kit's own output for the input of a shipped vector (dict), evaluated with ``flags``."""
    source = _input_only(path, tmp_path)
    output = tmp_path / f"evaluated_{path.stem}.json"
    assert spline_kit.main(["evaluate", str(source), "-o", str(output), "--force", *flags]) == 0
    return json.loads(output.read_text())


def _check_data(reference_path, candidate, tmp_path, capsys):
    """(exit code, stdout + stderr) of `check` against a candidate dict."""
    target = tmp_path / "candidate.json"
    target.write_text(json.dumps(candidate))
    code = spline_kit.main(["check", str(reference_path), str(target)])
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def test_check_of_a_candidate_with_jacobians_against_a_vector_without_them_passes_with_a_note(tmp_path, capsys):
    path = VECTOR_DIR / "paper_dt0.25_large_rot.json"
    code, text = _check_data(path, _evaluated(path, tmp_path, "--jacobians"), tmp_path, capsys)
    assert code == 0 and "PASS" in text, text
    assert "holds no Jacobians; the candidate's were not checked" in text
    jacobian_vector = VECTOR_DIR / "jacobians_paper_dt0.25.json"  # and the reverse: a candidate without them
    candidate = {key: value for key, value in json.loads(jacobian_vector.read_text()).items()
                 if not key.startswith("J_")}
    code, text = _check_data(jacobian_vector, candidate, tmp_path, capsys)
    assert code == 0 and "holds no Jacobians (J_first" in text, text


@pytest.mark.parametrize("change,named", [
    ("no_J_first", "missing J_first"),
    ("misspelt", "missing J_omegadot_body; unknown key(s) J_omegadot"),
])
def test_a_partial_or_misspelt_set_of_jacobian_keys_fails_naming_the_keys(tmp_path, capsys, change, named):
    """Blocks that are all garbage must not pass because the set of keys is incomplete."""
    path = VECTOR_DIR / "jacobians_paper_dt0.25.json"
    candidate = json.loads(path.read_text())
    for key in conformance.JACOBIAN_KEYS:
        candidate[key] = np.full_like(np.asarray(candidate[key]), 5.0).tolist()
    if change == "no_J_first":
        del candidate["J_first"]
    else:
        candidate["J_omegadot"] = candidate.pop("J_omegadot_body")
    code, text = _check_data(path, candidate, tmp_path, capsys)
    assert code == 1 and text.rstrip().endswith("FAIL"), text
    assert "Jacobians      FAIL: " in text and named in text and "holds no Jacobians" not in text, text


@pytest.mark.parametrize("key", ["dt", "t0", "times", "knots"])
def test_kit_python_api_refuses_float32_times_naming_the_key(key):
    """JSON numbers are float64; a Python caller can hand the kit float32 ones, whose digits are gone."""
    name = "knots_uneven_tum_stamps" if key == "knots" else "paper_dt0.03_tum_stamps"
    data = {k: v for k, v in json.loads((VECTOR_DIR / f"{name}.json").read_text()).items()
            if k in conformance.INPUT_KEYS + conformance.OPTIONAL_INPUT_KEYS}
    data[key] = np.float32(data[key]) if key in ("dt", "t0") else np.asarray(data[key], dtype=np.float32)
    with pytest.raises(conformance.ConformanceError, match=f"input: key '{key}' must be float64 seconds"):
        conformance.evaluate_input(data)


def test_a_fractional_j_first_is_refused_naming_its_row(tmp_path, capsys):
    """J_first 0.4 was truncated to 0 and reported as 'candidate 0, reference 0'."""
    path = VECTOR_DIR / "jacobians_paper_dt0.25.json"
    candidate = json.loads(path.read_text())
    candidate["J_first"][3] += 0.4
    code, text = _check_data(path, candidate, tmp_path, capsys)
    assert code == 2 and f"key 'J_first' row 3 is {candidate['J_first'][3]!r}; expected an integer" in text, text


def test_check_fails_another_active_window_as_a_check_failure_not_bad_input(tmp_path, capsys):
    path = VECTOR_DIR / "jacobians_paper_dt0.25.json"
    candidate = json.loads(path.read_text())
    candidate["J_first"][7] += 1  # an index convention one off at one time
    code, text = _check_data(path, candidate, tmp_path, capsys)
    assert code == 1, text
    expected = f"J_first        FAIL: 1 time(s) with another active window; first at index 7, t = {candidate['times'][7]!r}"
    assert expected in text, text


def test_check_names_both_row_counts_when_a_key_is_short(tmp_path, capsys):
    path = VECTOR_PATHS[0]
    candidate = json.loads(path.read_text())
    n_times = len(candidate["times"])
    candidate["a"] = candidate["a"][:-1]
    code, text = _check_data(path, candidate, tmp_path, capsys)
    assert code == 2
    assert f"key 'a' has {n_times - 1} rows but 'times' has {n_times}" in text, text


def test_evaluate_names_the_file_key_and_index_of_a_time_outside_the_domain(tmp_path, capsys):
    data = {"convention": "paper", "dt": 0.5, "t0": 0.0, "rotvecs": [[0, 0, 0]] * 5,
            "translations": [[0, 0, 0]] * 5, "times": [1.0, 1.2, 5.0]}
    source = tmp_path / "mine.json"
    source.write_text(json.dumps(data))
    assert spline_kit.main(["evaluate", str(source), "-o", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert f"{source}: key 'times' index 2: time 5.0 s is outside" in err, err


def test_failure_on_non_uniform_knots_is_placed_between_its_two_knots(tmp_path, capsys):
    path = VECTOR_DIR / "knots_uneven_tum_stamps.json"
    candidate = json.loads(path.read_text())
    knot_vector = candidate["knots"]
    m = candidate["times"].index(knot_vector[9])  # a time on a knot: its segment starts there
    candidate["p"][m][0] += 1e-3
    code, text = _check_data(path, candidate, tmp_path, capsys)
    assert code == 1
    assert f"segment 7 = [knots[9], knots[10]) = [{knot_vector[9]!r}, {knot_vector[10]!r}) s, u = 0.0" in text, text
    assert "t0 + k dt" not in text


def test_a_candidate_time_a_few_ulps_past_the_end_is_checked_at_the_matched_reference_time(tmp_path, capsys):
    data = {"convention": "basalt", "dt": 0.02, "t0": 0.0,
            "rotvecs": [[0, 0, 0], [0.1, 0, 0], [0.2, 0.1, 0], [0.3, 0, 0.1], [0.2, 0.2, 0.2]],
            "translations": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 1, 0], [2, 2, 1]],
            "times": [0.0, 0.01, 0.02, 0.03, 0.04]}  # 0.04 = t_max
    reference = conformance.evaluate_input(data, "reference")
    candidate = dict(reference, times=[0.0, 0.01, 0.02, 0.03, 0.04 + 3.0 * np.finfo(float).eps * 0.04 * 4])
    reference_path = tmp_path / "reference.json"
    reference_path.write_text(json.dumps(reference))
    code, text = _check_data(reference_path, candidate, tmp_path, capsys)
    assert code == 0 and "PASS" in text, text


def test_hints_do_not_blame_the_representation_for_a_time_scaling_or_a_single_bad_sample(tmp_path, capsys):
    path = VECTOR_DIR / "paper_dt0.25_large_rot.json"
    dt = json.loads(path.read_text())["dt"]
    scaled = json.loads(path.read_text())
    scaled["v"] = (np.asarray(scaled["v"]) * dt).tolist()  # v x dt: the chain rule's 1/dt missing
    code, text = _check_data(path, scaled, tmp_path, capsys)
    assert code == 1 and "dt^1" in text and "JOINT" not in text, text
    one_bad = json.loads(path.read_text())
    one_bad["p"][3][2] += 1e-3
    code, text = _check_data(path, one_bad, tmp_path, capsys)
    assert code == 1 and "JOINT" not in text, text
    joint = VECTOR_DIR / "se3_paper_dt0.05_large_rot.json"  # a joint SE(3) candidate for a split vector still is named
    split_twin = {key: value for key, value in json.loads(joint.read_text()).items() if key != "representation"}
    split_path = tmp_path / "split_twin.json"
    split_path.write_text(json.dumps(conformance.evaluate_input(split_twin, "split twin")))
    code, text = _check_data(split_path, json.loads(joint.read_text()), tmp_path, capsys)
    assert code == 1 and "JOINT SE(3) spline of the same control points" in text, text


@pytest.mark.parametrize("dt", [1e300, 0.0, -0.1])
def test_cli_refuses_a_knot_spacing_outside_its_range_in_one_line(tmp_path, capsys, dt):
    """dt = 1e300 overflowed in 1 / dt**2 and ended in a traceback; it is refused naming the key."""
    data = {"convention": "paper", "dt": dt, "t0": 0.0, "rotvecs": [[0, 0, 0]] * 5,
            "translations": [[0, 0, 0]] * 5, "times": [0.1]}
    source = tmp_path / "in.json"
    source.write_text(json.dumps(data))
    assert spline_kit.main(["evaluate", str(source), "-o", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "key 'dt' must be in (0, 1e+06] seconds" in err and len(err.splitlines()) == 1, err
