"""The conformance kit's check-all: it passes only when every shipped vector was checked, and its
last line counts the vectors that passed, failed, were malformed or missing.
"""

import json
import shutil

from tsslam_ref import spline_kit

VECTOR_PATHS = spline_kit.shipped_vectors()


def load(path):
    return json.loads(path.read_text())


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


def test_check_all_passes_only_with_every_vector_and_says_so_on_its_last_line(tmp_path, capsys):
    code, lines, _ = _check_all(capsys, _user_folder(tmp_path))
    total = len(VECTOR_PATHS)
    assert code == 0 and lines[-1] == f"PASS: {total} of {total} shipped vectors passed, 0 failed, 0 malformed, 0 missing"


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
                                       f"passed, 0 failed, 0 malformed, 2 missing"), lines
    assert any(line.startswith("note: 1 file(s)") and line.endswith("basalt_dt1_large.json") for line in lines), lines
    code, lines, _ = _check_all(capsys, _user_folder(tmp_path / "b", {"knots_uneven_tum_stamps"}, "basalt_golden_dt0.5"),
                                "--allow-missing")
    assert code == 1 and lines[-1].startswith(f"FAIL: {total - 2} of {total} shipped vectors passed, 1 failed"), lines


def test_check_all_of_a_folder_without_any_vector_is_bad_input(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, _, err = _check_all(capsys, tmp_path / "empty", "--allow-missing")
    assert code == 2 and "holds none of the shipped names" in err
