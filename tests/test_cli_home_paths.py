"""A leading ``~`` in a path argument is the home folder on every command line: a shell leaves
``--out=~/x`` and a quoted ``"~/x"`` as they are, and a literal ``./~`` folder is a trap."""

import json
import shutil
from pathlib import Path

from tsslam_ref import data, eval as evaluation, run, spline_kit

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "tsslam_ref" / "assets" / "tum_fr3_teddy_160x120"


def test_tilde_paths_name_the_home_folder_on_every_command_line(tmp_path, monkeypatch, capsys):
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    assert data.main(["synthesize", "--out=~/room", "--frames", "2", "--size", "16x12", "--mesh-voxel", "0.5"]) == 0
    assert (home / "room" / "scene.json").is_file() and not (work / "~").exists()
    capsys.readouterr()
    assert data.main(["info", "~/room", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 2
    shutil.copy(BUNDLED / "groundtruth.txt", home / "gt.txt")
    assert evaluation.main(["trajectory", "~/gt.txt", "~/gt.txt", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ate_rmse_m"] < 1e-12
    assert spline_kit.main(["inputs", "~/vectors"]) == 0
    assert (home / "vectors").is_dir() and not (work / "~").exists()
    args = run.build_parser().parse_args(["--out=~/runs/a", "--data", "~/room", "--config", "~/config.json"])
    assert (args.out, args.data, args.config) == (str(home / "runs/a"), str(home / "room"), str(home / "config.json"))
    assert run.main(["--out", "~/missing", "--resume", "--config", "tiny"]) == 2
    assert f"the output folder {home / 'missing'} does not exist" in capsys.readouterr().err


def test_data_info_without_a_path_describes_the_bundled_slice_a_run_reads(capsys):
    assert data.main(["info", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["name"] == "tum_fr3_teddy_160x120" and summary["path"] == str(data.default_sequence_path())
    assert summary["frames_with_gt"] == len(data.load_sequence(data.default_sequence_path()))  # what a run uses
