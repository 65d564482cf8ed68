"""The conformance kit as a user meets it: exact at knots, a `check` that names the mistake, stand-alone.

Oracles: a second float64 implementation written from the formulas in this test folder
(spline_formulas.py, no import of tsslam_ref.spline) and exact rational arithmetic
(fractions.Fraction) of the translation part and its derivatives.
"""

import json
import math
import os
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

import spline_formulas
from tsslam_ref import conformance, spline_kit

VECTOR_PATHS = [p for p in spline_kit.shipped_vectors() if "knots" not in json.loads(p.read_text())]
"""The uniform vectors (spline_formulas is uniform only; the "knots" ones: test_conformance.py)."""
SPLIT_PATHS = [p for p in VECTOR_PATHS if json.loads(p.read_text()).get("representation", "split") == "split"]
CHECKOUT = Path(__file__).resolve().parents[1]


def load(path):
    return json.loads(Path(path).read_text())


def as_candidate(data, outputs, keep=None):
    keep = np.arange(len(data["times"])) if keep is None else keep
    candidate = {"times": np.asarray(data["times"])[keep].tolist()}
    candidate.update({key: np.asarray(value)[keep].tolist() for key, value in outputs.items()})
    return candidate


def test_a_float64_implementation_from_the_formulas_passes_every_vector_at_default_tolerances():
    for path in VECTOR_PATHS:  # split and joint SE(3)
        data = load(path)
        report = conformance.compare(data, as_candidate(data, spline_formulas.evaluate(data)))
        assert report["ok"], (path.stem, spline_kit.format_report(report))
        assert max(row["scaled"] for row in report["rows"]) < 1e-12


def exact_translation(data, t):
    """p, v, a at time t in exact rationals from the float64 inputs (Eq. (5), (8))."""
    dt, t0 = Fraction(data["dt"]), Fraction(data["t0"])
    n = len(data["translations"])
    s = (Fraction(t) - t0) / dt - spline_formulas.OFFSET[data["convention"]]
    i = min(max(math.floor(s), 0), n - 4)
    u = s - i
    C = [[Fraction(c) for c in row] for row in ([6, 0, 0, 0], [5, 3, -3, 1], [1, 3, 3, -2], [0, 0, 0, 1])]
    def weights(powers):
        return [sum(C[j][k] * powers[k] for k in range(4)) / 6 for j in range(4)]
    B, Bd, Bdd = weights([1, u, u**2, u**3]), weights([0, 1, 2 * u, 3 * u**2]), weights([0, 0, 2, 6 * u])
    P = [[Fraction(x) for x in row] for row in data["translations"]]
    p = list(P[i])
    v, a = [Fraction(0)] * 3, [Fraction(0)] * 3
    for j in range(1, 4):
        for c in range(3):
            delta = P[i + j][c] - P[i + j - 1][c]
            p[c] += B[j] * delta
            v[c] += Bd[j] * delta / dt
            a[c] += Bdd[j] * delta / dt**2
    return [np.array([float(x) for x in value]) for value in (p, v, a)]


@pytest.mark.parametrize("path", SPLIT_PATHS, ids=lambda p: p.stem)
def test_knot_adjacent_times_agree_with_exact_rational_evaluation(path):
    data = load(path)
    times = np.asarray(data["times"])
    s = (times - data["t0"]) / data["dt"]
    near = np.flatnonzero(np.abs(s - np.round(s)) < 1e-4)
    assert near.size >= 5
    for key, k in (("p", 0), ("v", 1), ("a", 2)):
        values = np.asarray(data[key])
        scale = np.abs(values).max()
        for m in near:
            exact = exact_translation(data, times[m])[k]
            assert np.abs(values[m] - exact).max() <= 1e-13 * scale, (key, m, values[m], exact)


def test_the_issue_case_a_time_3e_6_segments_before_a_knot_uses_the_earlier_segment():
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.03_tum_stamps.json")
    knot = data["t0"] + 4 * data["dt"]
    t = knot - 3e-6 * data["dt"]
    query = {key: data[key] for key in conformance.INPUT_KEYS}
    query["times"] = [t]
    ours = conformance.evaluate_input(query)
    _, _, a_exact = exact_translation(data, t)
    assert np.abs(np.asarray(ours["a"][0]) - a_exact).max() < 1e-10 * np.abs(a_exact).max()


# ------------------------------------------------------------------------------------------------
# check names the mistake


def run_check(capsys, reference, candidate, tmp_path, *extra):
    ref_path, cand_path = tmp_path / "ref.json", tmp_path / "cand.json"
    ref_path.write_text(json.dumps(reference))
    cand_path.write_text(json.dumps(candidate))
    code = spline_kit.main(["check", str(ref_path), str(cand_path), *extra])
    captured = capsys.readouterr()
    return code, captured.out + captured.err


@pytest.mark.parametrize("vector,mistake,expected", [
    ("paper_dt0.25_large_rot", "world_frame", "WORLD-frame"),
    ("paper_dt0.25_large_rot", "float32", "float32"),
    ("paper_dt0.25_large_rot", "no_dt", "dt^1"),
    ("basalt_dt1_large_rot", "transposed_basis", "TRANSPOSED basis"),
    ("paper_dt0.03_tum_stamps", "snap_knots", "errors only at times within 1e-4 segments of a knot"),
    ("paper_dt0.25_large_rot", "other_convention", "index convention shifted by 2"),
    ("basalt_dt1_large_rot", "other_convention", "index convention shifted by 2"),
    ("paper_dt0.03_tum_stamps", "other_convention", "index convention shifted by 2"),
    ("paper_dt0.25_large_rot", "transposed_R", "TRANSPOSE, world-to-body"),
    ("paper_dt0.03_tum_stamps", "nanoseconds", "rounded to whole nanoseconds"),
    ("paper_dt0.25_large_rot", "world_increments", "the rotation's composition"),
    ("basalt_dt1_large_rot", "old_omega", "only omegadot fails"),
    ("basalt_dt1_large_rot", "omegadot_sign", "only omegadot fails: check its recursion term by term"),
    ("paper_dt0.03_tum_stamps", "clamp_ends", "errors only at the domain's end times (2 of the 2"),
    ("paper_dt0.25_large_rot", "left_product", "only R fails while omega and omegadot pass"),
    ("paper_dt0.25_large_rot", "non_cumulative", "NON-CUMULATIVE basis"),
    ("basalt_dt1_large_rot", "non_cumulative", "NON-CUMULATIVE basis"),
    ("basalt_dt0.1_floor_knots", "no_t0", "or t0 not subtracted (t0 = 0.1 s is 1 dt)"),
    ("jacobians_paper_dt0.25", "no_t0", "or t0 not subtracted (t0 = 0.5 s is 2 dt)"),
])
def test_each_planted_mistake_triggers_its_hint(capsys, tmp_path, vector, mistake, expected):
    data = load(spline_kit.VECTOR_DIR / f"{vector}.json")
    candidate = as_candidate(data, spline_formulas.evaluate(data, mistake=mistake))
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 1 and "FAIL" in out and expected in out, out
    assert "worst at index" in out and "u = " in out and "ref " in out and "cand " in out


def test_a_bug_at_the_domain_ends_is_not_offered_a_looser_tolerance(capsys, tmp_path):
    """Clamping u at t_min / t_max of the TUM-stamp vector (whose end times lie within rounding
    outside the exact domain) errs by 3e-6 of the scale at two times: the float32 hint took it for
    rounding and advised --rtol 1e-5, under which the bug passes; t_max moved 1 ns inside likewise."""
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.03_tum_stamps.json")
    code, out = run_check(capsys, data, as_candidate(data, spline_formulas.evaluate(data, mistake="clamp_ends")),
                          tmp_path)
    assert code == 1 and "errors only at the domain's end times" in out and "--rtol" not in out, out
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.25_large_rot.json")
    inside = dict(data, times=[t - 1e-9 if t == max(data["times"]) else t for t in data["times"]])
    candidate = dict(as_candidate(inside, spline_formulas.evaluate(inside)), times=data["times"])
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 1 and "errors only at the domain's end times (1 of the" in out and "--rtol" not in out, out


def test_a_time_written_with_too_few_digits_is_named_as_such():
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.03_tum_stamps.json")
    for form in ("{:.15g}", "{:.12g}", "{:.4f}"):
        written = np.array([float(form.format(t)) for t in data["times"]])
        with pytest.raises(conformance.ConformanceError, match="too few digits: write times with 17 significant"):
            conformance.match_times(np.asarray(data["times"]), written, "candidate")
    with pytest.raises(conformance.ConformanceError) as other:  # another time altogether: no such guess
        conformance.match_times(np.asarray(data["times"]), np.asarray(data["times"]) + 0.001, "candidate")
    assert "digits" not in str(other.value)


UNIFORM_SPLIT = [path.stem for path in spline_kit.shipped_vectors()
                 if "knots" not in load(path) and load(path).get("representation", "split") == "split"]


@pytest.mark.parametrize("vector", UNIFORM_SPLIT)
def test_code_on_whole_nanoseconds_passes_at_the_documented_rtol_and_is_named_where_it_fails(capsys, tmp_path, vector):
    """docs/spline.md: times rounded to whole nanoseconds (basalt-headers' int64 ns) check with
    --rtol 1e-7.  The candidate is spline_formulas' numpy code on integer nanoseconds; where the
    default tolerances fail it (every shipped uniform vector: their 1e-10 is below a nanosecond's
    effect), the hint must say why (not blame float32)."""
    data = load(spline_kit.VECTOR_DIR / f"{vector}.json")
    candidate = as_candidate(data, spline_formulas.evaluate(data, mistake="nanoseconds"))
    code, out = run_check(capsys, data, candidate, tmp_path, "--rtol", "1e-7")
    assert code == 0 and "PASS" in out, out
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 1 and "rounded to whole nanoseconds" in out, out


def test_a_one_segment_shift_is_named_as_an_index_convention(capsys, tmp_path):
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.25_large_rot.json")
    times = np.asarray(data["times"])
    t_max = max(times)
    keep = np.flatnonzero(times + data["dt"] <= t_max)
    shifted = dict(data, times=(times[keep] + data["dt"]).tolist())  # a candidate using points i-1..i+2
    outputs = spline_formulas.evaluate(shifted)
    candidate = {"times": times[keep].tolist(), **{k: v.tolist() for k, v in outputs.items()}}
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 1 and "index convention shifted by 1" in out, out


def test_joint_se3_candidate_is_named(capsys, tmp_path):
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.25_large_rot.json")
    joint = conformance.evaluate_input(dict({k: data[k] for k in conformance.INPUT_KEYS}, representation="se3"))
    candidate = {key: joint[key] for key in ("times",) + conformance.OUTPUT_KEYS}
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 1 and "JOINT SE(3)" in out, out


@pytest.mark.parametrize("vector", ["se3_basalt_dt1_pypose", "se3_paper_dt0.05_large_rot"])
def test_joint_se3_without_v_is_named_by_its_pattern_p_v_a_differ_while_the_rotation_agrees(capsys, tmp_path, vector):
    """The documented pattern 'p, v and a all differ while R, omega, omegadot agree' for a uniform vector."""
    data = load(spline_kit.VECTOR_DIR / f"{vector}.json")
    candidate = as_candidate(data, spline_formulas.evaluate(data, mistake="no_V"))
    report = conformance.compare(data, candidate)
    assert {row["quantity"] for row in report["rows"] if not row["ok"]} == {"p", "v", "a"}
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 1 and "hint: p, v and a differ while R, omega, omegadot agree" in out and "V(phi)" in out, out


def test_half_open_candidate_without_t_max_passes_on_what_it_has(capsys, tmp_path):
    data = load(spline_kit.VECTOR_DIR / "basalt_golden_dt0.5.json")
    times = np.asarray(data["times"])
    keep = np.flatnonzero(times < times.max())
    candidate = as_candidate(data, spline_formulas.evaluate(data), keep)
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 0 and "PASS" in out and "half-open" in out and repr(float(times.max())) in out


def test_candidate_time_not_in_the_reference_exits_2_naming_it(capsys, tmp_path):
    data = load(spline_kit.VECTOR_DIR / "basalt_golden_dt0.5.json")
    candidate = as_candidate(data, spline_formulas.evaluate(data))
    candidate["times"][5] += 1e-6
    code, out = run_check(capsys, data, candidate, tmp_path)
    assert code == 2 and repr(candidate["times"][5]) in out and "index 5" in out


@pytest.mark.parametrize("option,value", [("--atol", "-1"), ("--atol", "nan"), ("--rtol", "inf")])
def test_bad_tolerances_exit_2_with_a_message(capsys, tmp_path, option, value):
    path = str(VECTOR_PATHS[0])
    assert spline_kit.main(["check", path, path, option, value]) == 2
    err = capsys.readouterr().err
    assert option in err and value in err


def test_huge_rotation_vectors_are_refused_not_written_as_nan(capsys, tmp_path):
    data = {"convention": "paper", "dt": 0.5, "t0": 0.0, "rotvecs": [[1e200, 0, 0]] + [[0, 0, 0]] * 4,
            "translations": [[0, 0, 0]] * 5, "times": [1.0]}
    source = tmp_path / "in.json"
    source.write_text(json.dumps(data))
    assert spline_kit.main(["evaluate", str(source), "-o", str(tmp_path / "o.json")]) == 2
    assert "'rotvecs'" in capsys.readouterr().err and not (tmp_path / "o.json").exists()


@pytest.mark.parametrize("angle", [math.pi, math.pi - 1e-9])
def test_rotation_step_of_pi_is_refused_naming_the_pair(capsys, tmp_path, angle):
    data = {"convention": "basalt", "dt": 1.0, "t0": 0.0,
            "rotvecs": [[0, 0, 0], [0, 0, 0.5], [0, 0, 0.5 + angle], [0, 0, 0.6 + angle]],
            "translations": [[0, 0, 0]] * 4, "times": [0.5]}
    source = tmp_path / "in.json"
    source.write_text(json.dumps(data))
    assert spline_kit.main(["evaluate", str(source), "-o", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert "control points 1 and 2" in err and "pi" in err


def test_rotation_step_just_below_the_limit_is_evaluated(tmp_path):
    angle = math.pi - 1e-5
    data = {"convention": "basalt", "dt": 1.0, "t0": 0.0,
            "rotvecs": [[0, 0, 0], [0, 0, 0.5], [0, 0, 0.5 + angle], [0, 0, 0.6 + angle]],
            "translations": [[0, 0, 0]] * 4, "times": [0.5]}
    result = conformance.evaluate_input(data)
    # one axis: ω_z is the derivative of the scalar spline of the angles 0, 0.5, 0.5 + angle, 0.6 + angle
    u = 0.5
    weights = spline_formulas.C @ np.array([0.0, 1.0, 2 * u, 3 * u * u])
    expected = weights[1] * 0.5 + weights[2] * angle + weights[3] * 0.1
    assert np.allclose(result["omega_body"][0], [0.0, 0.0, expected], atol=1e-9)


# ------------------------------------------------------------------------------------------------
# the kit on its own


def test_evaluate_echoes_its_inputs_and_reruns_without_force(tmp_path, capsys):
    data = load(VECTOR_PATHS[0])
    source = tmp_path / "in.json"
    source.write_text(json.dumps({key: data[key] for key in conformance.INPUT_KEYS}))
    output = tmp_path / "out.json"
    assert spline_kit.main(["evaluate", str(source), "-o", str(output)]) == 0
    written = json.loads(output.read_text())
    for key in conformance.INPUT_KEYS:
        assert written[key] == data[key]
    assert spline_kit.main(["evaluate", str(source), "-o", str(output)]) == 0  # our own file: replaced
    user_file = tmp_path / "mine.json"
    user_file.write_text("precious")
    assert spline_kit.main(["evaluate", str(source), "-o", str(user_file)]) == 2
    assert user_file.read_text() == "precious" and "--force" in capsys.readouterr().err


def test_kit_runs_from_a_folder_outside_the_checkout(tmp_path):
    """From tmp_path with the package on PYTHONPATH (the checkout root; /work/venv's editable install
    points at another checkout): list, docs, inputs, a user's implementation, check-all."""
    env = dict(os.environ, PYTHONPATH=str(CHECKOUT))

    def kit(*args):
        return subprocess.run([sys.executable, "-m", "tsslam_ref.spline_kit", *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)

    listing = kit("list")
    assert listing.returncode == 0 and "basalt_golden_dt0.5" in listing.stdout
    docs = kit("docs")
    assert docs.returncode == 0 and "0.134116980" in docs.stdout and "shared/" not in docs.stdout
    assert "spline_vectors" in kit("--help").stdout
    assert kit("inputs", "inputs").returncode == 0
    os.makedirs(tmp_path / "mine")
    for path in VECTOR_PATHS:  # the user's own code
        data = load(tmp_path / "inputs" / path.name)
        (tmp_path / "mine" / path.name).write_text(json.dumps(as_candidate(data, spline_formulas.evaluate(data))))
    result = kit("check-all", "mine", "--allow-missing")  # spline_formulas has no non-uniform knots
    assert result.returncode == 0 and "PASS (partial, --allow-missing)" in result.stdout, result.stdout + result.stderr
    assert result.stdout.count("PASS") >= len(VECTOR_PATHS)


def test_domain_ends_allow_only_their_own_float64_rounding_for_stamps_and_relative_times():
    from tsslam_ref import spline

    n, dt = 9, 0.03
    for t0 in (0.0, 1305031102.175304):
        t_min, t_max = spline.valid_time_range(n, dt, t0)
        tolerance = 4 * np.finfo(np.float64).eps * max(abs(t0), abs(t_max))
        assert spline.time_in_domain(np.array([t_min, t_max]), n, dt, t0).all()
        below, above = np.nextafter(t_min, -np.inf), np.nextafter(t_max, np.inf)  # one ulp outside
        assert spline.time_in_domain(np.array([below, above]), n, dt, t0).all()
        outside = np.array([t_min - 2 * tolerance, t_max + 2 * tolerance])
        assert not spline.time_in_domain(outside, n, dt, t0).any()
        with pytest.raises(ValueError, match="outside the spline domain"):
            spline.active_control_indices(outside[:1], n, dt, t0)
    # the issue's example: 5.7e-8 s before 0.06 s is outside, as it would be 2e-6 s before a stamp's end
    assert spline.valid_time_range(10, 0.03, 0.0)[0] == 0.06
    assert not spline.time_in_domain(0.059999942779541016, 10, 0.03, 0.0)


def test_dependencies_point_one_way_math_never_imports_the_kit():
    code = ("import sys, tsslam_ref.spline, tsslam_ref.spline_jacobians, tsslam_ref.se3_spline; "
            "assert 'tsslam_ref.conformance' not in sys.modules and 'tsslam_ref.spline_kit' not in sys.modules; "
            "import tsslam_ref.conformance; assert 'tsslam_ref.spline_kit' not in sys.modules")
    result = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, PYTHONPATH=str(CHECKOUT)),
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
