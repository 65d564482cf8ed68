"""The conformance kit's verdicts: default tolerances that separate float64 from float32, and a
check-all that passes only when every shipped vector was checked.

Candidates: the shipped values rounded to float32 (the best a float32 implementation can do), our
spline evaluated with float32 control points, and correct float64 formulations that do not use our
code's closed forms: spline_formulas.py (numpy, from the formulas), scipy's B-spline basis functions
summed into the cumulative weights (non-uniform knots) and autograd Jacobians of the pose.
"""

import json
import shutil

import numpy as np
import pytest
import scipy.interpolate
import torch

import spline_formulas
from tsslam_ref import conformance, conformance_hints, knots, se3_spline, spline, spline_jacobians, spline_kit
from tsslam_ref.geometry import so3_exp, so3_log

VECTOR_PATHS = spline_kit.shipped_vectors()
FLOAT32_RTOL = 1e-5
"""The looser rtol docs/spline.md gives float32 implementations."""


def load(path):
    return json.loads(path.read_text())


def as_candidate(data, outputs):
    return {"times": data["times"], **{key: np.asarray(value).tolist() for key, value in outputs.items()}}


def rounded_to_float32(data):
    """The reference values stored as float32: every output key and Jacobian block."""
    keys = [key for key in conformance.OUTPUT_KEYS + conformance.JACOBIAN_KEYS if key in data]
    outputs = {key: np.asarray(data[key], dtype=np.float32) for key in keys}
    if "J_first" in data:
        outputs["J_first"] = np.asarray(data["J_first"])
    return outputs


def ours_in_float32(data):
    """Our spline with float32 control points (times stay float64), Jacobians too where the vector has them."""
    parsed = conformance.parse_input(data)
    rotations = so3_exp(torch.as_tensor(parsed["rotvecs"], dtype=torch.float32))
    points = torch.as_tensor(parsed["translations"], dtype=torch.float32)
    times = parsed["times"]
    if parsed["knots"] is not None:
        sample = knots.evaluate(rotations, points, times, parsed["knots"], derivatives=2)
    elif parsed["representation"] == "se3":
        sample = se3_spline.evaluate(rotations, points, times, parsed["dt"], parsed["t0"], parsed["convention"], 2)
    else:
        sample = spline.evaluate(rotations, points, times, parsed["dt"], parsed["t0"], parsed["convention"], 2)
    values = (sample.rotation, sample.translation, sample.velocity_world, sample.acceleration_world,
              sample.omega_body, sample.omegadot_body)
    outputs = {key: value.numpy() for key, value in zip(conformance.OUTPUT_KEYS, values)}
    if "J_R" in data:
        blocks = spline_jacobians.jacobians(rotations, points, times, parsed["dt"], parsed["t0"], parsed["convention"])
        outputs.update({key: blocks[key].numpy() for key in conformance.JACOBIAN_KEYS}, J_first=blocks["first"].numpy())
    return outputs


@pytest.mark.parametrize("make", [rounded_to_float32, ours_in_float32], ids=["float32_outputs", "float32_arithmetic"])
@pytest.mark.parametrize("path", VECTOR_PATHS, ids=lambda p: p.stem)
def test_a_float32_candidate_fails_every_quantity_at_the_defaults_and_passes_at_the_documented_rtol(path, make):
    data = load(path)
    candidate = as_candidate(data, make(data))
    report = conformance_hints.check(data, candidate)
    assert not any(row["ok"] for row in report["rows"]), spline_kit.format_report(report)
    assert min(row["error"] / row["bound"] for row in report["rows"]) > 20  # far from the bound, not by luck
    assert any("errors at the float32 level" in hint for hint in report["hints"]), report["hints"]
    loose = conformance_hints.check(data, candidate, conformance.DEFAULT_ATOL, FLOAT32_RTOL)
    assert loose["ok"], spline_kit.format_report(loose)


def test_check_tells_a_float32_user_the_cause_and_the_option(tmp_path, capsys):
    path = spline_kit.VECTOR_DIR / "paper_dt0.25_large_rot.json"
    candidate = tmp_path / "mine.json"
    candidate.write_text(json.dumps(as_candidate(load(path), rounded_to_float32(load(path)))))
    assert spline_kit.main(["check", path.stem, str(candidate)]) == 1
    out = capsys.readouterr().out
    assert "(atol 1e-10, rtol 1e-10)" in out and "errors at the float32 level" in out and "--rtol 1e-5" in out, out
    assert spline_kit.main(["check", path.stem, str(candidate), "--rtol", str(FLOAT32_RTOL)]) == 0


def cumulative_from_scipy_basis(data, mistake=None):
    """Non-uniform split spline from scipy's basis functions N_l (and derivatives) summed into the
    cumulative weights, then the ω, ω̇ recursion; translation from scipy's BSpline directly.

    mistake: None, "uniform_basis" (the uniform matrix C on each segment, u = (t - κ_{s+2}) / h_s,
    derivatives over h_s), "shift+1" / "shift-1" (segment s's weights on control points s ± 1..,
    clamped to the valid ones), "cumulative" (no mistake); with any of them the translation is the
    cumulative sum of the weights, as the rotation's, instead of scipy's BSpline."""
    knot_vector = np.asarray(data["knots"])
    origin, n = knot_vector[0], len(data["rotvecs"])
    relative = np.r_[-1.0, knot_vector - origin, knot_vector[-1] - origin + 1.0]  # N + 4 knots, times - origin
    basis = scipy.interpolate.BSpline(relative, np.eye(n), 3)
    translation = scipy.interpolate.BSpline(relative, np.asarray(data["translations"]), 3)
    points = np.asarray(data["translations"])
    rotations = [spline_formulas.exp_so3(v) for v in np.asarray(data["rotvecs"])]
    outputs = {key: [] for key in conformance.OUTPUT_KEYS}
    for t in data["times"]:
        segment = min(max(int(np.searchsorted(knot_vector, t, side="right")) - 3, 0), n - 4)
        local = t - origin
        B, B_dot, B_ddot = (np.cumsum(basis(local, nu)[segment:segment + 4][::-1])[::-1] for nu in (0, 1, 2))
        if mistake == "uniform_basis":
            h = knot_vector[segment + 3] - knot_vector[segment + 2]
            u = (t - knot_vector[segment + 2]) / h
            B, B_dot, B_ddot = (spline_formulas.C @ np.array(row) / h**order for order, row in
                                enumerate([[1, u, u * u, u**3], [0, 1, 2 * u, 3 * u * u], [0, 0, 2, 6 * u]]))
        first = min(max(segment + {"shift+1": 1, "shift-1": -1}.get(mistake, 0), 0), n - 4)
        R, omega, omega_dot = rotations[first].copy(), np.zeros(3), np.zeros(3)
        p, v, a = points[first].copy(), np.zeros(3), np.zeros(3)
        for j in range(1, 4):
            d = spline_formulas.log_so3(rotations[first + j - 1].T @ rotations[first + j])
            A = spline_formulas.exp_so3(B[j] * d)
            R = R @ A
            omega = A.T @ omega + B_dot[j] * d
            omega_dot = B_dot[j] * np.cross(omega, d) + A.T @ omega_dot + B_ddot[j] * d
            step = points[first + j] - points[first + j - 1]
            p, v, a = p + B[j] * step, v + B_dot[j] * step, a + B_ddot[j] * step
        if mistake is None:
            p, v, a = translation(local), translation(local, 1), translation(local, 2)
        values = (R, p, v, a, omega, omega_dot)
        for key, value in zip(conformance.OUTPUT_KEYS, values):
            outputs[key].append(value)
    return {key: np.stack(value) for key, value in outputs.items()}


def autograd_jacobians(data, right_input=False, right_output=False):
    """J_first and the six (M, 4, 3, 3) blocks by autograd of our pose w.r.t. δ (R_k <- Exp(δ_k) R_k), τ;
    ``right_input`` perturbs R_k <- R_k Exp(δ_k), ``right_output`` reads R(t) <- R(t) Exp(ε) instead (the
    mistakes a user makes)."""
    parsed = conformance.parse_input(data)
    rotations, points, times = so3_exp(torch.as_tensor(parsed["rotvecs"])), torch.as_tensor(parsed["translations"]), \
        parsed["times"]
    timing = (parsed["dt"], parsed["t0"], parsed["convention"])
    base = spline.evaluate(rotations, points, times, *timing).rotation

    def outputs(delta, tau):
        perturbed = rotations @ so3_exp(delta) if right_input else so3_exp(delta) @ rotations
        sample = spline.evaluate(perturbed, points + tau, times, *timing, derivatives=2)
        epsilon = so3_log(base.transpose(-1, -2) @ sample.rotation if right_output else
                          sample.rotation @ base.transpose(-1, -2))
        return (epsilon, sample.translation, sample.velocity_world, sample.acceleration_world, sample.omega_body,
                sample.omegadot_body)

    full = torch.autograd.functional.jacobian(outputs, (torch.zeros_like(points), torch.zeros_like(points)))
    first = spline.active_control_indices(times, len(points), *timing)[..., 0].numpy()
    window = first[:, None] + np.arange(4)  # (M, 4)
    rows = np.arange(len(times))[:, None]
    blocks = {"J_first": first}
    for q, key in enumerate(conformance.JACOBIAN_KEYS):
        J = full[q][1 if key in ("J_p", "J_v", "J_a") else 0].numpy()  # (M, 3, N, 3)
        blocks[key] = J.transpose(0, 2, 1, 3)[rows, window]  # (M, 4, 3, 3)
    return blocks


def independent_float64(data):
    outputs = cumulative_from_scipy_basis(data) if "knots" in data else spline_formulas.evaluate(data)
    return {**outputs, **autograd_jacobians(data)} if "J_R" in data else outputs


def test_the_report_table_keeps_its_columns_for_the_longest_quantity_name():
    """J_omegadot_body (15 characters) pushed its row one column right of the header's."""
    data = load(next(path for path in VECTOR_PATHS if path.stem == "jacobians_paper_dt0.25"))
    table = spline_kit.format_report(conformance_hints.check(data, data)).splitlines()[1:]
    rows = [line for line in table if line.split()[0] in conformance.OUTPUT_KEYS + conformance.JACOBIAN_KEYS]
    assert len(rows) == 12 and {line.index(" ok") for line in rows} == {table[0].index(" result")}


@pytest.mark.parametrize("path", VECTOR_PATHS, ids=lambda p: p.stem)
def test_a_correct_independent_float64_candidate_passes_every_vector_with_a_wide_margin(path):
    data = load(path)
    report = conformance.compare(data, as_candidate(data, independent_float64(data)))
    assert report["ok"] and not report["notes"], spline_kit.format_report(report)  # Jacobians compared too
    assert max(row["scaled"] for row in report["rows"]) < conformance.DEFAULT_RTOL / 1000, spline_kit.format_report(report)


JACOBIAN_VECTOR = spline_kit.VECTOR_DIR / "jacobians_paper_dt0.25.json"


def _planted_jacobians(data, mistake):
    """Values from the formulas (spline_formulas) and Jacobians by autograd, with one planted mistake."""
    dt = data["dt"]
    blocks = autograd_jacobians(data, right_input=mistake in ("right_input", "right_both"),
                                right_output=mistake in ("right_output", "right_both"))
    if mistake == "transposed":  # a column-major dump of every block
        blocks.update({key: np.swapaxes(blocks[key], -1, -2) for key in conformance.JACOBIAN_KEYS})
    elif mistake == "reversed":
        blocks.update({key: blocks[key][:, ::-1] for key in conformance.JACOBIAN_KEYS})
    elif mistake == "J_v_no_dt":
        blocks["J_v"] = blocks["J_v"] * dt
    elif mistake == "J_a_no_dt2":
        blocks["J_a"] = blocks["J_a"] * dt**2
    elif mistake == "J_R_sign":
        blocks["J_R"] = -blocks["J_R"]
    return {**spline_formulas.evaluate(data), **blocks}


@pytest.mark.parametrize("mistake,expected", [
    ("transposed", "J_R, J_omega_body, J_omegadot_body: each 3x3 block is the TRANSPOSE"),
    ("reversed", "J_R, J_p, J_v, J_a, J_omega_body, J_omegadot_body: the 4 blocks are in REVERSE order"),
    ("J_v_no_dt", "J_v: the reference times dt^1 (dt = 0.25)"),
    ("J_a_no_dt2", "J_a: the reference times dt^2 (dt = 0.25)"),
    ("J_R_sign", "J_R: the NEGATIVE of the reference"),
    ("right_input", "J_R, J_omega_body, J_omegadot_body: RIGHT perturbation of the control rotations"),
    ("right_output", "J_R: RIGHT perturbation of the output rotation"),
    ("right_both", "J_R: RIGHT perturbation of both the control rotations and the output rotation"),
])
def test_each_planted_jacobian_mistake_triggers_its_hint(mistake, expected):
    data = load(JACOBIAN_VECTOR)
    report = conformance_hints.check(data, as_candidate(data, _planted_jacobians(data, mistake)))
    assert not report["ok"] and any(hint.startswith(expected) for hint in report["hints"]), report["hints"]
    assert len(report["hints"]) == 1 + (mistake == "right_both"), report["hints"]  # right_both: J_omega.. too
    assert all(row["ok"] for row in report["rows"] if not row["quantity"].startswith("J_")), report["hints"]


def test_a_value_hint_survives_jacobians_that_fail_along_with_the_values():
    """The documented 'only omegadot fails' hint, for a candidate that also holds (failing) Jacobians."""
    data = load(JACOBIAN_VECTOR)
    outputs = {**spline_formulas.evaluate(data, mistake="old_omega"), **autograd_jacobians(data)}
    outputs["J_omegadot_body"] = outputs["J_omegadot_body"] * 1.01
    report = conformance_hints.check(data, as_candidate(data, outputs))
    failing = {row["quantity"] for row in report["rows"] if not row["ok"]}
    assert failing == {"omegadot_body", "J_omegadot_body"}, failing
    assert any(hint.startswith("only omegadot fails") for hint in report["hints"]), report["hints"]


def test_the_worst_jacobian_entry_is_named_by_block_control_point_row_and_column(tmp_path, capsys):
    data = load(JACOBIAN_VECTOR)
    data["J_omega_body"][3][1][0][2] += 1e-3  # time 3, block 1, output component 0, perturbation component 2
    candidate = tmp_path / "mine.json"
    candidate.write_text(json.dumps(data))
    assert spline_kit.main(["check", JACOBIAN_VECTOR.stem, str(candidate)]) == 1
    out = capsys.readouterr().out
    point = int(data["J_first"][3]) + 1
    assert "J_omega_body worst at index 3" in out, out
    assert f"block i = 1 (control point J_first + 1 = {point}), entry (row 0, col 2) = (output component 0, " \
           f"perturbation component 2)" in out, out
    ref_line = next(line for line in out.splitlines() if line.startswith("    ref "))
    assert ref_line.count(",") == 8, ref_line  # the one 3 x 3 block, not 36 numbers


# ------------------------------------------------------------------------------------------------
# check-all


def test_compare_verdict_maths_by_hand():
    """The module docstring's definition on a three-time file whose numbers are exact in binary:
    error = max over times and components of |cand - ref|, scale = max |ref| (the reference's, not
    the candidate's), pass when error <= atol + rtol * scale (the bound itself passes), scaled =
    error / scale.  By hand: p_ref = (1, 0, 0), (2, 0, 0), (4, 0, 0), so scale 4; with
    atol = 2^-10 and rtol = 2^-12 the bound is 2^-10 + 2^-10 = 2^-9."""
    zeros, identity = np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1))
    reference = {"times": [0.0, 1.0, 2.0], "R": identity, "p": np.outer([1.0, 2.0, 4.0], [1.0, 0.0, 0.0]),
                 "v": zeros, "a": zeros, "omega_body": zeros, "omegadot_body": zeros}
    atol, rtol = 2.0**-10, 2.0**-12
    for offset, ok in ((2.0**-9, True), (2.0**-9 + 2.0**-10, False)):
        candidate = dict(reference, p=reference["p"] + [[0.0, 0.0, 0.0], [0.0, offset, 0.0], [0.0, 0.0, 0.0]])
        candidate["p"][2, 0] = 8.0 - offset  # a candidate far off in scale: the scale must stay the reference's
        report = conformance.compare(reference, candidate, atol=atol, rtol=rtol)
        row = {row["quantity"]: row for row in report["rows"]}["p"]
        assert (row["error"], row["scale"], row["bound"], row["scaled"]) == (4.0 - offset, 4.0, 2.0**-9, (4.0 - offset) / 4)
        candidate["p"][2, 0] = 4.0
        report = conformance.compare(reference, candidate, atol=atol, rtol=rtol)
        row = {row["quantity"]: row for row in report["rows"]}["p"]
        assert (row["error"], row["index"], row["bound"], row["ok"], report["ok"]) == (offset, 1, 2.0**-9, ok, ok)
        assert row["per_time"].tolist() == [0.0, offset, 0.0]
    assert conformance.compare(reference, dict(reference), atol=0.0, rtol=0.0)["ok"]  # identical passes at zero tolerance


def test_compare_matches_large_times_by_relative_gap_lists_left_out_times_and_places_the_worst_error():
    """By hand.  Times near 1e9 s one ulp (1.2e-7 s) apart from the reference's match, since the
    match is relative (4 eps max(1, |t|)); a candidate without the reference's last time gets that
    time in ``missing``; paper convention, t0 = 0, dt = 0.25: t = 0.8 s lies in segment
    [t_3, t_4) = [0.75, 1.0) at u = (0.8 - 0.75) / 0.25 = 0.2."""
    zeros = np.zeros((3, 3))
    big = {"times": 1e9 + np.array([0.0, 0.5, 1.0]), "R": np.tile(np.eye(3), (3, 1, 1)), "p": zeros, "v": zeros,
           "a": zeros, "omega_body": zeros, "omegadot_body": zeros}
    nudged = {key: value[:2] for key, value in big.items()}
    nudged["times"] = np.nextafter(big["times"][:2], np.inf)
    report = conformance.compare(big, nudged)
    assert report["ok"] and report["matched"].tolist() == [0, 1] and report["missing"].tolist() == [1e9 + 1.0]
    data = {"convention": "paper", "dt": 0.25, "t0": 0.0, "rotvecs": 0.1 * np.arange(18.0).reshape(6, 3) % 0.7,
            "translations": np.arange(18.0).reshape(6, 3) ** 0.5, "times": [0.6, 0.8, 1.1]}
    reference = conformance.evaluate_input(data)
    candidate = dict(reference, p=np.array(reference["p"]) + [[0.0] * 3, [1e-3, 0.0, 0.0], [0.0] * 3])
    row = {row["quantity"]: row for row in conformance.compare(reference, candidate)["rows"]}["p"]
    assert (row["index"], row["segment"]) == (1, 3) and row["u"] == pytest.approx(0.2, abs=1e-12)


def test_a_candidate_may_leave_out_t_max_alone_and_fails_when_it_leaves_out_any_other_time():
    """A half-open domain drops t_max: that candidate passes with a note naming it.  Leaving out
    more fails, even when the times it gives are right, with a line naming the left-out times (all
    3 of 3 with no '...'; the first 3 of 4 and '...'), because wrong values could hide there.  A
    candidate giving one time in 256, with wrong values at all the others, fails the same way.
    Oracle: the reference's own distinct times, taken with np.unique."""
    reference = load(VECTOR_PATHS[1])
    distinct = np.unique(reference["times"])
    keys = ("times",) + conformance.OUTPUT_KEYS
    no_t_max = np.asarray(reference["times"]) < distinct[-1]
    report = conformance_hints.check(reference, {key: np.asarray(reference[key])[no_t_max] for key in keys})
    text = spline_kit.format_report(report)
    assert report["ok"] and f"leaves out t_max = {float(distinct[-1])!r} s" in text, text
    for left_out, ellipsis in ((4, False), (5, True)):  # t_max and 3 or 4 times before it
        keep = np.asarray(reference["times"]) < distinct[-left_out]
        report = conformance_hints.check(reference, {key: np.asarray(reference[key])[keep] for key in keys})
        line = next(line for line in spline_kit.format_report(report).splitlines() if "before t_max" in line)
        shown = ", ".join(repr(float(t)) for t in distinct[-left_out:-1][:3])
        assert not report["ok"] and f"leaves out {left_out - 1} reference time(s) before t_max (missing: {shown}" in line
        assert (" ...)" in line) == ellipsis, line
    one = {key: np.asarray(reference[key])[:1] for key in keys}
    report = conformance_hints.check(reference, one)
    assert not report["ok"] and all(row["ok"] for row in report["rows"])  # its one time is right


def _user_folder(tmp_path, leave_out=(), break_one=None):
    """FOLDER/<name>.json for every shipped vector (the vector itself as a correct candidate)."""
    folder = tmp_path / "mine"
    folder.mkdir(parents=True)
    for path in VECTOR_PATHS:
        if path.stem not in leave_out:
            shutil.copyfile(path, folder / path.name)
    if break_one:
        data = load(folder / f"{break_one}.json")
        data["p"][3][0] += 1e-3
        (folder / f"{break_one}.json").write_text(json.dumps(data))
    return folder


def _check_all(capsys, folder, *extra):
    code = spline_kit.main(["check-all", str(folder), *extra])
    captured = capsys.readouterr()
    return code, captured.out.strip().splitlines(), captured.err


JACOBIANS_CHECKED = "; Jacobians checked in 1 of the 1 passing vector(s) that hold them, 0 unchecked"
"""The last line's tail when jacobians_paper_dt0.25 passed with its Jacobians compared."""


def test_check_all_passes_only_with_every_vector_and_says_so_on_its_last_line(tmp_path, capsys):
    code, lines, _ = _check_all(capsys, _user_folder(tmp_path))
    total = len(VECTOR_PATHS)
    assert code == 0 and lines[-1] == (f"PASS: {total} of {total} shipped vectors passed, 0 failed, 0 malformed, "
                                       f"0 missing{JACOBIANS_CHECKED}"), lines[-1]


def test_check_all_says_when_a_passing_vector_had_its_jacobians_unchecked(tmp_path, capsys):
    """A candidate without Jacobian keys passes on its values (Jacobians are optional), but the
    summary and the last line say that the reference's Jacobians went unchecked."""
    folder = _user_folder(tmp_path)
    target = folder / "jacobians_paper_dt0.25.json"
    target.write_text(json.dumps({key: value for key, value in load(target).items() if not key.startswith("J_")}))
    code, lines, _ = _check_all(capsys, folder)
    total = len(VECTOR_PATHS)
    assert code == 0, lines
    assert f"  {'jacobians_paper_dt0.25':<28} PASS (Jacobians not checked: the candidate holds none)" in lines, lines
    assert lines[-1] == (f"PASS: {total} of {total} shipped vectors passed, 0 failed, 0 malformed, 0 missing; "
                         f"Jacobians checked in 0 of the 1 passing vector(s) that hold them, 1 unchecked"), lines[-1]


def test_check_all_with_a_missing_vector_exits_1_and_lists_it(tmp_path, capsys):
    folder = _user_folder(tmp_path, leave_out={"basalt_dt1_large_rot"})
    code, lines, _ = _check_all(capsys, folder)
    total = len(VECTOR_PATHS)
    assert code == 1, lines
    assert f"  {'basalt_dt1_large_rot':<28} missing (no {folder / 'basalt_dt1_large_rot.json'})" in lines
    assert lines[-1].startswith(f"FAIL: {total - 1} of {total} shipped vectors passed, 0 failed, 0 malformed, "
                                f"1 missing") and "--allow-missing" in lines[-1], lines[-1]


def test_check_all_allow_missing_is_a_partial_check_that_still_counts_them(tmp_path, capsys):
    folder = _user_folder(tmp_path, leave_out={"knots_uneven_tum_stamps", "basalt_dt1_large_rot"})
    (folder / "basalt_dt1_large.json").write_text("{}")  # a misspelt name: named, not checked
    code, lines, _ = _check_all(capsys, folder, "--allow-missing")
    total = len(VECTOR_PATHS)
    assert code == 0 and lines[-1] == (f"PASS (partial, --allow-missing): {total - 2} of {total} shipped vectors "
                                       f"passed, 0 failed, 0 malformed, 2 missing{JACOBIANS_CHECKED}"), lines
    assert any(line.startswith("note: 1 file(s)") and line.endswith("basalt_dt1_large.json") for line in lines), lines
    code, lines, _ = _check_all(capsys, _user_folder(tmp_path / "b", {"knots_uneven_tum_stamps"}, "basalt_golden_dt0.5"),
                                "--allow-missing")
    assert code == 1 and lines[-1].startswith(f"FAIL: {total - 2} of {total} shipped vectors passed, 1 failed"), lines


def test_check_all_counts_a_malformed_candidate_as_a_failure(tmp_path, capsys):
    """The documented exit codes: a candidate that is no JSON object fails check-all (exit 1) with
    every other vector passing, with or without --allow-missing, and the last line counts it."""
    folder = _user_folder(tmp_path)
    (folder / "basalt_dt1_large_rot.json").write_text("[1, 2]")
    total = len(VECTOR_PATHS)
    for extra in ((), ("--allow-missing",)):
        code, lines, _ = _check_all(capsys, folder, *extra)
        assert code == 1 and lines[-1] == (f"FAIL: {total - 1} of {total} shipped vectors passed, 0 failed, "
                                           f"1 malformed, 0 missing{JACOBIANS_CHECKED}"), lines


def test_check_all_refuses_a_negative_tolerance_before_checking_anything(tmp_path, capsys):
    """The documented exit code 2 for bad input: --atol -1 is refused up front, in one line naming
    the option and its value, with no vector checked (no '== <name>' block printed)."""
    code, lines, err = _check_all(capsys, _user_folder(tmp_path), "--atol", "-1")
    assert code == 2 and lines == [] and "--atol" in err and "-1" in err, (lines, err)


def test_check_all_of_a_folder_without_any_vector_is_bad_input(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, _, err = _check_all(capsys, tmp_path / "empty", "--allow-missing")
    assert code == 2 and "holds none of the shipped names" in err



def test_inputs_refuses_before_writing_any_file_when_one_is_the_users(tmp_path, capsys):
    """Exit 2 means nothing written (docs/cli.md): the refusal came mid-loop, after other files."""
    folder = tmp_path / "inputs"
    folder.mkdir()
    mine = folder / VECTOR_PATHS[len(VECTOR_PATHS) // 2].name  # one in the middle of the list
    mine.write_text('{"mine": 1}')
    assert spline_kit.main(["inputs", str(folder)]) == 2
    assert [path.name for path in folder.iterdir()] == [mine.name] and mine.read_text() == '{"mine": 1}'
    assert "nothing was written" in capsys.readouterr().err
    assert spline_kit.main(["inputs", str(folder), "--force"]) == 0 and len(list(folder.iterdir())) == len(VECTOR_PATHS)
    for path in folder.iterdir():
        path.unlink()
    (folder / mine.name).mkdir()  # a folder of a vector's name: not even --force writes the others first
    assert spline_kit.main(["inputs", str(folder), "--force"]) == 2
    assert [path.name for path in folder.iterdir()] == [mine.name] and "is a folder" in capsys.readouterr().err
    reference = VECTOR_PATHS[0]
    data = json.loads(reference.read_text())
    (tmp_path / "mine.json").write_text(json.dumps(data))
    assert spline_kit.main(["check", str(reference), str(tmp_path / "mine.json")]) == 0
    first = capsys.readouterr().out.splitlines()[0]  # the report names what it compares
    assert first.startswith(f"{tmp_path / 'mine.json'} against {reference}: error = max"), first
    assert spline_kit.main(["check", reference.stem, str(tmp_path / "mine.json")]) == 0  # a shipped name, as typed
    assert capsys.readouterr().out.startswith(f"{tmp_path / 'mine.json'} against {reference.stem}: ")


def test_check_all_counts_a_file_still_holding_the_input_as_missing(tmp_path, capsys):
    """The documented workflow writes the inputs into FOLDER and the user's outputs over them; a
    file nobody evaluated is missing (named as the input), so --allow-missing still makes a partial
    check pass, and without it the check fails."""
    folder = _user_folder(tmp_path, leave_out={"knots_uneven_tum_stamps"})
    inputs = tmp_path / "inputs"
    assert spline_kit.main(["inputs", str(inputs)]) == 0
    shutil.copyfile(inputs / "knots_uneven_tum_stamps.json", folder / "knots_uneven_tum_stamps.json")
    capsys.readouterr()
    total = len(VECTOR_PATHS)
    code, lines, _ = _check_all(capsys, folder, "--allow-missing")
    assert code == 0 and lines[-1] == (f"PASS (partial, --allow-missing): {total - 1} of {total} shipped vectors "
                                       f"passed, 0 failed, 0 malformed, 1 missing{JACOBIANS_CHECKED}"), lines
    assert any("knots_uneven_tum_stamps" in line and "is still the input" in line for line in lines), lines
    code, lines, _ = _check_all(capsys, folder)
    assert code == 1 and "1 missing" in lines[-1], lines


def test_check_all_of_a_folder_that_does_not_exist_says_so(tmp_path, capsys):
    code, _, err = _check_all(capsys, tmp_path / "nowhere")
    assert code == 2 and "no such folder" in err and "nowhere" in err, err


def test_a_non_finite_candidate_value_is_refused_naming_its_row_and_time():
    reference = load(VECTOR_PATHS[1])
    candidate = {key: reference[key] for key in ("times",) + conformance.OUTPUT_KEYS}
    candidate["omega_body"] = [list(row) for row in candidate["omega_body"]]
    candidate["omega_body"][17][1] = float("nan")
    with pytest.raises(conformance.ConformanceError, match=rf"'omega_body' contains non-finite values \(first at "
                                                           rf"row 17, t = {reference['times'][17]!r} s\)"):
        conformance.compare(reference, candidate)


KNOT_VECTOR = spline_kit.VECTOR_DIR / "knots_uneven_tum_stamps.json"


@pytest.mark.parametrize("mistake,expected", [
    ("uniform_basis", "R and p equal the UNIFORM cumulative basis on each segment"),
    ("shift+1", "the candidate equals the reference with the control points shifted by +1 against the knots"),
    ("shift-1", "the candidate equals the reference with the control points shifted by -1 against the knots"),
])
def test_each_planted_knot_vector_mistake_triggers_its_hint(mistake, expected):
    """An implementer's usual non-uniform mistakes, built on scipy's basis, not on the kit's code."""
    data = load(KNOT_VECTOR)
    report = conformance_hints.check(data, as_candidate(data, cumulative_from_scipy_basis(data, mistake)))
    assert not report["ok"] and any(hint.startswith(expected) for hint in report["hints"]), report["hints"]
    assert len(report["hints"]) == 1, report["hints"]


def test_the_planted_knot_mistakes_translation_path_alone_passes():
    """With a mistake the candidate's translation is a cumulative sum, not scipy's BSpline: without
    one, that sum passes, so each planted candidate holds only its planted mistake."""
    data = load(KNOT_VECTOR)
    report = conformance_hints.check(data, as_candidate(data, cumulative_from_scipy_basis(data, "cumulative")))
    assert report["ok"] and not report["hints"], spline_kit.format_report(report)


@pytest.mark.parametrize("vector", ["se3_basalt_dt1_pypose", "se3_paper_dt0.05_large_rot"])
def test_joint_se3_with_world_side_increments_is_named(vector):
    data = load(spline_kit.VECTOR_DIR / f"{vector}.json")
    report = conformance_hints.check(data, as_candidate(data, spline_formulas.evaluate(data, mistake="world_twists")))
    assert not report["ok"] and any("WORLD-side increments" in hint for hint in report["hints"]), report["hints"]
    correct = conformance_hints.check(data, as_candidate(data, spline_formulas.evaluate(data)))
    assert correct["ok"] and not correct["hints"]


@pytest.mark.parametrize("keys", [("R",), ("omegadot_body",)])
def test_a_rotation_stored_in_float32_alone_is_blamed_on_the_storage_not_on_the_formula(keys):
    """Only R (or only omegadot) rounded to float32: the structural hints ("R's own product", "the
    cross term's sign") told a correct float64 implementation to fix its formulas."""
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.25_large_rot.json")
    outputs = {key: np.asarray(data[key], dtype=np.float32 if key in keys else np.float64)
               for key in conformance.OUTPUT_KEYS}
    report = conformance_hints.check(data, as_candidate(data, outputs))
    assert [row["quantity"] for row in report["rows"] if not row["ok"]] == list(keys)
    assert report["hints"] and report["hints"][0].startswith(f"only {keys[0]} fail, by rounding-sized errors")
    assert not any("product" in hint or "term by term" in hint for hint in report["hints"]), report["hints"]


def test_float32_jacobians_are_not_called_transposed_where_the_transpose_is_the_same_block():
    """J_v's blocks are multiples of the identity: "the TRANSPOSE of the reference's" matched float32
    rounding of them (found under --rtol 2e-7)."""
    data = load(spline_kit.VECTOR_DIR / "jacobians_paper_dt0.25.json")
    report = conformance_hints.check(data, as_candidate(data, ours_in_float32(data)), conformance.DEFAULT_ATOL, 2e-7)
    assert not report["ok"] and not any("TRANSPOSE" in hint for hint in report["hints"]), report["hints"]


def test_float32_failing_at_a_few_times_under_a_looser_rtol_is_still_named_without_more_tolerance():
    data = load(spline_kit.VECTOR_DIR / "paper_dt0.25_large_rot.json")  # R and a fail, at 3.5 % of the times
    report = conformance_hints.check(data, as_candidate(data, ours_in_float32(data)), conformance.DEFAULT_ATOL, 3e-7)
    assert not report["ok"]
    hint = next(hint for hint in report["hints"] if hint.startswith("errors at the float32 level"))
    assert "% of the times: look at those before any looser tolerance" in hint and "--rtol" not in hint
