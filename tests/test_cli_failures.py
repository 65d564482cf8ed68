"""Bad input, misuse and faults on every command line: exit status, one line naming the culprit,
no traceback, and nothing the user made changed (docs/cli.md has the table).

Each class of failure runs at least once as a real subprocess (``python -m tsslam_ref.<module>``);
the longer lists of bad values of one class call the same ``main`` in-process, which is what the
subprocess runs.  Folders are compared before and after by a snapshot of every entry (kind, link
target, SHA-256), files outside the run folder included.  Three short real runs (the Co-SLAM
loop with very few iterations on a 64x48 synthetic sequence) cover --overwrite, Ctrl-C, resume
and its refusals.
"""

import argparse
import csv
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image
from scipy.spatial.transform import Rotation

from tsslam_ref import checkpoint, cli_args, data, files, run, run_outputs, spline_kit
from tsslam_ref import config as config_module
from tsslam_ref import eval as evaluation

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "tsslam_ref" / "assets" / "tum_fr3_teddy_160x120"


def cli(module: str, *arguments, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    return subprocess.run([sys.executable, "-m", f"tsslam_ref.{module}", *map(str, arguments)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def snapshot(root: Path) -> dict:
    """Every entry under ``root`` (links not followed): kind plus link target or content hash."""
    entries = {}
    for folder, names, file_names in os.walk(root):
        for name in names + file_names:
            path = Path(folder) / name
            key = str(path.relative_to(root))
            if path.is_symlink():
                entries[key] = ("link", os.readlink(path))
            elif path.is_dir():
                entries[key] = ("dir",)
            else:
                entries[key] = ("file", hashlib.sha256(path.read_bytes()).hexdigest(), os.stat(path).st_mode)
    return entries


def refused(result: subprocess.CompletedProcess, *needles: str) -> None:
    """Exit 2, one line on stderr holding every needle, no traceback."""
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def refused_in_process(capsys, main, arguments, *needles: str) -> None:
    try:
        code = main([str(a) for a in arguments])
    except SystemExit as stop:  # argparse's usage errors
        code = stop.code
    captured = capsys.readouterr()
    refused(subprocess.CompletedProcess(arguments, code, captured.out, captured.err), *needles)


@pytest.fixture
def dataset(tmp_path) -> Path:
    """A copy of the bundled TUM slice (rgb.txt, depth.txt, groundtruth.txt, intrinsics.json)."""
    return Path(shutil.copytree(BUNDLED, tmp_path / "teddy"))


def _first_listed(folder: Path, listing: str) -> str:
    return next(line.split()[1] for line in (folder / listing).read_text().splitlines() if line and line[0] != "#")


# ------------------------------------------------------------------------------------------------
# run: arguments, config, device, output folder - refused before anything is written


def test_late_errors_are_now_refused_before_the_output_folder_is_made(tmp_path):
    """One subprocess per kind of error that used to fail after config.json was written."""
    (tmp_path / "list.json").write_text("[1, 2]")
    cases = [(["--set", "device=banana"], ["device = 'banana'", "auto, cpu, cuda"]),
             (["--export-rate", "nan"], ["--export-rate nan", "(0, 1000]"]),
             (["--config", "list.json"], ["list.json", "expected an object"]),
             (["--frames", "-3:8"], ["--frames -3:8", ">= 0"])]
    if not torch.cuda.is_available():
        cases.append((["--device", "cuda"], ["cuda"]))
    before = snapshot(tmp_path)
    for arguments, needles in cases:
        refused(cli("run", *arguments, "--out", "out", cwd=tmp_path), *needles)
        assert snapshot(tmp_path) == before, arguments  # no out folder, nothing else touched


@pytest.mark.parametrize("arguments, needles", [
    (["--export-rate", "-5"], ["--export-rate -5"]),
    (["--export-rate", "0"], ["--export-rate 0", "leave the option out"]),
    (["--export-rate", "1e9"], ["--export-rate 1e9"]),
    (["--set", "field.bound=[[0,1],[0,1]]"], ["field.bound", "[[xmin, xmax]"]),
    (["--set", "field.bound=[[0,1],[0,1],[1,0]]"], ["field.bound", "min < max"]),
    (["--checkpoint-every", "-1"], ["--checkpoint-every -1", "0 for no checkpoint"]),
    (["--seed", "1e23"], ["--seed", "'1e23'"]),
    (["--seed", str(2**32)], ["--seed", "2**32 - 1"]),  # PyTorch's generator would run it as seed 0
    (["--set", "seed=-1"], ["seed = -1"]),
    (["--frames", "0:1"], ["--frames 0:1 selects 1 frame", "at least 2"]),
    (["--set", "data.frame_stop=1"], ["data.frame_start:frame_stop:frame_step = 0:1:1 selects 1 frame"]),  # not "has"
    (["--frames", "0:10", "--set", "data.frame_step=20"],  # the --set wins: not "--frames 0:10 selects 1 frame"
     ["data.frame_start:frame_stop:frame_step = 0:10:20 selects 1 frame"]),
    (["--set", "tracking.iter=3"], ["unknown key 'tracking.iter' (did you mean 'tracking.iters'?)"]),
    (["--set", "trackin.iters=3"], ["unknown section 'trackin' (did you mean 'tracking'?)"]),
    (["--set", "name=my run 3"], ["name = 'my run 3' must be one of default, tum, "]),  # its config.json would not load
    (["--set", "data.dataset=tumm"], ["data.dataset = 'tumm' must be one of auto, tum, scannet"]),
    (["--set", "mesh.voxel_eval=0.5"], ["unknown key 'mesh.voxel_eval'"]),  # nothing read it
    (["--set", "tracking.iters=2.5"], ["tracking.iters = 2.5 must be an integer"]),
    (["--frames=-3:8"], ["--frames -3:8"]),
    (["--frames", "5:2"], ["--frames '5:2' selects no frames"]),
    (["--frames", "0:5000"], ["stop=5000 is beyond the 100 usable frames", "none (START:)"]),  # ran 100, said 5000
    (["--config", "replica"], ["data.dataset = 'replica' (preset replica)", "no --data names one"]),  # named the
    (["--config", "scannet"], ["data.dataset = 'scannet' (preset scannet)", "bundled TUM slice"]),  # bundled folder
    (["--set", "spline.dt=1e6"], ["spline.dt = 1000000.0", "(0, 10]"]),
    (["--method", "coslam", "--export-rate", "5"], ["--export-rate needs --method tsslam"]),
    (["--set", "method=coslam", "--export-rate", "5"], ["--export-rate needs --method tsslam", "coslam"]),
    (["--set", "local_ba.use_spline=false", "--export-rate", "30"],
     ["--export-rate needs the spline", "local_ba.use_spline = false"]),
    (["--set", "spline.knots=adaptive", "--set", "spline.dt_min=0.5", "--set", "spline.dt_max=0.2"],
     ["spline.dt_min = 0.5 s", "spline.dt_max = 0.2 s"]),
    (["--set", "spline.knots=adaptive", "--set", "local_ba.use_spline=false"], ["local_ba.use_spline must be true"]),
    (["--resume", "--overwrite"], ["--resume and --overwrite"]),
    (["--resume"], ["--resume given but the output folder"]),
    (["--set", "tracking.nope=1"], ["unknown key 'tracking.nope'"]),
    (["--set", "tracking.iters.real=3"], ["unknown key 'tracking.iters.real'"]),  # Python attributes are no keys
    (["--set", "tracking.__doc__=x"], ["unknown key 'tracking.__doc__'"]),
    (["--set", "__doc__=x"], ["unknown key '__doc__'"]),
    (["--frames", "0:100:10"], ["0.336 s apart", "spline.dt = 0.25 s", "--set spline.dt=0.35"]),  # every 10th frame
    (["--set", "tracking.ignore_edge=60"], ["tracking.ignore_edge = 60 px", "160x120", "expected < 60"]),  # was mid-run
    (["--set", "tracking.n_rays=30000"], ["tracking.n_rays = 30000", "16500 pixels"]),
    (["--set", "mapping.first_n_rays=30000"], ["mapping.first_n_rays = 30000", "19200 pixels"]),
])
def test_every_bad_value_is_refused_naming_it(tmp_path, capsys, arguments, needles):
    before = snapshot(tmp_path)
    refused_in_process(capsys, run.main, arguments + ["--out", tmp_path / "out"], *needles)
    assert snapshot(tmp_path) == before


def test_config_files_and_output_paths_are_named(tmp_path, capsys):
    (tmp_path / "binary.json").write_bytes(np.random.default_rng(0).bytes(300))
    (tmp_path / "broken.json").write_text('{"seed": ')
    (tmp_path / "a_file").write_text("mine")
    (tmp_path / "dangling").symlink_to(tmp_path / "missing")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    refused(cli("run", "--config", "binary.json", "--out", "out", cwd=tmp_path), "binary.json", "not a text file")
    refused_in_process(capsys, run.main, ["--config", tmp_path / "broken.json", "--out", tmp_path / "out"],
                       "broken.json", "not valid JSON")
    refused(cli("run", "--out", "dangling", cwd=tmp_path), "dangling", "symbolic link to a missing target")
    refused_in_process(capsys, run.main, ["--out", tmp_path / "a_file"], "a_file", "is not a folder")
    refused_in_process(capsys, run.main, ["--out", tmp_path / "taken"], "taken", "not empty", "--overwrite",
                       "none of its 1 entries is a file a run writes")
    (tmp_path / "taken" / "config.json").write_text("{}")  # the user's own config.json, say
    refused_in_process(capsys, run.main, ["--out", tmp_path / "taken"], "not empty",
                       "it would replace config.json and keep 1 other entry")
    (tmp_path / "taken" / ".checkpoint.pt.abcd1234.tmp").write_text("left by a killed run")  # --overwrite removes it
    refused_in_process(capsys, run.main, ["--out", tmp_path / "taken"], "not empty", "it would replace config.json, "
                       "1 file(s) a killed run left and keep 1 other entry")
    (tmp_path / "taken" / ".checkpoint.pt.abcd1234.tmp").unlink()
    (tmp_path / "taken" / "notes.txt").unlink()  # a run stopped before its first checkpoint: --resume has nothing
    with pytest.raises(ValueError, match=r"would replace config\.json\)$"):
        run_outputs.check_output_folder(tmp_path / "taken", overwrite=False, resume=False, data_folder=str(tmp_path))
    (tmp_path / "taken" / "checkpoint.pt").write_text("a checkpoint")
    with pytest.raises(ValueError, match=r"would replace checkpoint\.pt, config\.json\) or --resume to continue it$"):
        run_outputs.check_output_folder(tmp_path / "taken", overwrite=False, resume=False, data_folder=str(tmp_path))
    (tmp_path / "taken" / "checkpoint.pt").unlink()
    (tmp_path / "taken" / "config.json").unlink()
    (tmp_path / "taken" / "notes.txt").write_text("mine")
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------------
# Checkpoints cannot run code


def _system_pickle(command: str) -> bytes:
    """A protocol-2 pickle whose loading calls os.system(command)."""
    return (b"\x80\x02cposix\nsystem\nq\x00X" + len(command).to_bytes(4, "little") + command.encode()
            + b"q\x01\x85q\x02Rq\x03.")


def test_a_planted_pickle_checkpoint_never_runs(tmp_path):
    import pickle

    live = tmp_path / "live"
    pickle.loads(_system_pickle(f"touch '{live}'"))  # the payload is live under plain unpickling
    assert live.exists()
    live.unlink()
    marker = tmp_path / "marker"
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(_system_pickle(f"touch '{marker}'"))
    before = snapshot(tmp_path)
    refused(cli("run", "--resume", "--out", "out", cwd=tmp_path), "checkpoint.pt", "not a readable tsslam_ref checkpoint")
    assert not marker.exists()
    assert snapshot(tmp_path) == before
    (out / "checkpoint.pt").write_bytes(b"")
    refused(cli("run", "--resume", "--out", "out", cwd=tmp_path), "checkpoint.pt", "empty")


# ------------------------------------------------------------------------------------------------
# Dataset lists and images


def test_list_paths_leaving_the_dataset_are_refused_naming_file_and_line(dataset, tmp_path, capsys):
    outside = tmp_path / "secret.png"
    shutil.copy(dataset / _first_listed(dataset, "rgb.txt"), outside)
    lines = (dataset / "rgb.txt").read_text().splitlines()
    number = next(i for i, line in enumerate(lines) if line and line[0] != "#")  # first data line (0-based)
    stamp = lines[number].split()[0]
    (dataset / "rgb" / "escape.png").symlink_to(outside)
    (dataset / "rgb" / "alias.png").symlink_to(dataset / lines[number].split()[1])
    cases = [(f"{stamp} ../secret.png", "leads outside the dataset folder"),
             (f"{stamp} rgb/../../secret.png", "leads outside the dataset folder"),
             (f"{stamp} {outside}", "is an absolute path"),
             (f"{stamp} rgb/escape.png", "leads outside the dataset folder")]
    original = list(lines)
    for index, (line, message) in enumerate(cases):
        lines[number] = line
        (dataset / "rgb.txt").write_text("\n".join(lines) + "\n")
        before = snapshot(tmp_path)
        if index == 0:
            refused(cli("data", "info", dataset, cwd=tmp_path), f"rgb.txt:{number + 1}:", message)
        else:
            refused_in_process(capsys, data.main, ["info", dataset], f"rgb.txt:{number + 1}:", message)
        assert snapshot(tmp_path) == before
    lines[number] = f"{stamp} rgb/alias.png"  # a link that stays inside the folder is allowed
    (dataset / "rgb.txt").write_text("\n".join(lines) + "\n")
    assert data.main(["info", str(dataset), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["files_checked"] == 2 * len(data.load_sequence(dataset, require_gt=False))
    lines = list(original)
    lines.insert(number + 1, lines[number])  # the same stamp twice
    (dataset / "rgb.txt").write_text("\n".join(lines) + "\n")
    refused_in_process(capsys, data.main, ["info", dataset], f"rgb.txt:{number + 2}:", "repeats line")
    refused_in_process(capsys, run.main, ["--data", dataset, "--out", tmp_path / "out"], f"rgb.txt:{number + 2}:")
    assert not (tmp_path / "out").exists()


def _depth_cases(shape):
    height, width = shape
    return {
        "truncated": ("truncated", "not a readable depth image"),
        "random bytes": (np.random.default_rng(1).bytes(2000), "not a readable depth image"),
        "wrong size": (Image.fromarray(np.ones((height // 2, width // 2), np.uint16)), f"expected {width}x{height}"),
        "8-bit": (Image.fromarray(np.ones(shape, np.uint8)), "mode L; expected a single-channel 16-bit PNG"),
        "3-channel": (Image.fromarray(np.ones(shape + (3,), np.uint8)), "mode RGB; expected a single-channel 16-bit PNG"),
    }


def test_broken_images_are_refused_naming_the_file(dataset, tmp_path, capsys):
    sequence = data.load_sequence(dataset, require_gt=False)
    victim = sequence.depth_paths[7]  # data info checks every frame, not a sample
    original = victim.read_bytes()
    shape = (sequence.native_intrinsics.height, sequence.native_intrinsics.width)
    for index, (name, (content, message)) in enumerate(_depth_cases(shape).items()):
        if isinstance(content, str):
            victim.write_bytes(original[: len(original) // 2])
        elif isinstance(content, bytes):
            victim.write_bytes(content)
        else:
            content.save(victim, format="PNG")
        before = snapshot(tmp_path)
        if index == 0:
            refused(cli("data", "info", dataset, cwd=tmp_path), victim.name, message)
            refused(cli("run", "--data", dataset, "--out", "out", "--frames", "0:9", cwd=tmp_path), victim.name, message)
        else:
            refused_in_process(capsys, data.main, ["info", dataset], victim.name, message)
        assert snapshot(tmp_path) == before, name
    victim.write_bytes(original)
    first = data.load_sequence(dataset).depth_paths[0]  # frame 0 of a run (the first frame with ground truth)
    Image.fromarray(np.zeros(shape, np.uint16)).save(first, format="PNG")
    refused_in_process(capsys, run.main, ["--data", dataset, "--out", tmp_path / "out", "--frames", "0:3"], first.name,
                       "depth is 0 (no measurement) at every pixel")
    assert not (tmp_path / "out").exists()


def test_a_folder_of_random_files_is_named(tmp_path, capsys):
    folder = tmp_path / "junk"
    folder.mkdir()
    rng = np.random.default_rng(2)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        (folder / name).write_bytes(rng.bytes(500))
    refused_in_process(capsys, data.main, ["info", folder], "rgb.txt:1:", "not text")
    refused(cli("run", "--data", folder, "--out", "out", cwd=tmp_path), "rgb.txt:1:", "not text")
    assert not (tmp_path / "out").exists()


def test_broken_calibration_and_ground_truth_mesh_are_named_before_the_run(dataset, tmp_path, capsys):
    (dataset / "gt_mesh.ply").write_bytes(np.random.default_rng(4).bytes(700))
    refused_in_process(capsys, run.main, ["--data", dataset, "--out", tmp_path / "out", "--frames", "0:3"], "gt_mesh.ply")
    assert not (tmp_path / "out").exists()
    # a vertex at NaN: the run once dropped its faces (trimesh's processing) and scored the rest; eval mesh refused
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 0]], dtype=float)
    trimesh.Trimesh(vertices, [[0, 1, 2], [1, 2, 3]], process=False).export(dataset / "gt_mesh.ply")
    refused_in_process(capsys, run.main, ["--data", dataset, "--out", tmp_path / "out", "--frames", "0:3"],
                       "ground-truth mesh", "gt_mesh.ply: vertex 3 is not finite", "remove it to skip")
    assert not (tmp_path / "out").exists()
    (dataset / "intrinsics.json").write_bytes(np.random.default_rng(5).bytes(300))
    refused_in_process(capsys, data.main, ["info", dataset], "intrinsics.json", "not a text file")
    refused_in_process(capsys, data.main, ["info", dataset / "rgb.txt"], "rgb.txt", "is a file; expected a dataset folder")


# ------------------------------------------------------------------------------------------------
# eval and the spline kit


def test_eval_refuses_repeated_stamps_binary_input_and_bad_thresholds(tmp_path, capsys):
    gt = BUNDLED / "groundtruth.txt"
    lines = [line for line in gt.read_text().splitlines() if line and line[0] != "#"][:8]
    (tmp_path / "est.txt").write_text("\n".join(lines[:5] + [lines[4]] + lines[5:]) + "\n")
    (tmp_path / "binary.txt").write_bytes(np.random.default_rng(3).bytes(400))
    before = snapshot(tmp_path)
    refused(cli("eval", "trajectory", gt, "est.txt", cwd=tmp_path), "est.txt:6:", "repeats line 5")
    refused_in_process(capsys, evaluation.main, ["trajectory", gt, tmp_path / "binary.txt"], "binary.txt:1:", "not text")
    refused(cli("eval", "mesh", "a.ply", "b.ply", "--threshold", "-1", cwd=tmp_path), "--threshold -1", "(0, 100]")
    for arguments, needle in ((["mesh", "a.ply", "b.ply", "--threshold", "nan"], "--threshold nan"),
                              (["trajectory", gt, gt, "--max-diff", "0"], "--max-diff 0"),
                              (["trajectory", gt, gt, "--delta", "0"], "--delta 0"),
                              (["mesh", "a.ply", "b.ply", "--points", "0"], "--points 0"),
                              (["trajectory", tmp_path, gt], "is a folder; expected a text file"),
                              (["mesh", tmp_path, tmp_path], "is a folder; expected a mesh file")):
        refused_in_process(capsys, evaluation.main, arguments, needle)
    assert snapshot(tmp_path) == before


def test_spline_kit_output_that_cannot_be_written_is_one_line(tmp_path, capsys):
    vector = spline_kit.shipped_vectors()[0]
    (tmp_path / "a_folder").mkdir()
    before = snapshot(tmp_path)
    refused_in_process(capsys, spline_kit.main, ["evaluate", vector, "-o", tmp_path / "missing" / "out.json"],
                       "out.json", "missing does not exist")
    refused_in_process(capsys, spline_kit.main, ["evaluate", vector, "-o", tmp_path / "a_folder", "--force"],
                       "a_folder", "is a folder")
    assert snapshot(tmp_path) == before


def test_spline_kit_refuses_negative_and_nan_tolerances(tmp_path, capsys):
    reference = spline_kit.shipped_vectors()[0]
    for arguments in (["--atol", "-1"], ["--atol", "nan"], ["--rtol=-1e-9"], ["--rtol", "abc"]):
        refused_in_process(capsys, spline_kit.main, ["check", reference, reference] + arguments, arguments[0][:6])


def test_benchmark_refuses_too_few_ground_truth_frames_before_running(tmp_path):
    """ATE and RPE need 3 frames with a ground-truth pose; two frames are refused up front, naming
    the sequence, the range and the count (not a KeyError after the runs)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_system.py"), "--frames", "0:2",
                             "--json", str(tmp_path / "rows.json")], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=300)
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode == 2, (result.returncode, result.stderr)
    message = result.stderr.strip().splitlines()[-1]
    for needle in ("tum_fr3_teddy_160x120", "0:2", "2 of 2 frames", "at least 3"):
        assert needle in message, message
    assert not (tmp_path / "rows.json").exists()


# ------------------------------------------------------------------------------------------------
# Real runs: --overwrite in a planted folder, Ctrl-C, resume and its refusals

CHEAP = ["--config", "tiny", "--method", "coslam", "--frames", "0:10", "--quiet", "--no-mesh", "--checkpoint-every", "1",
         "--set", "tracking.ignore_edge=2", "--set", "tracking.iters=2", "--set", "tracking.n_rays=32",
         "--set", "mapping.first_iters=3", "--set", "mapping.iters=1", "--set", "mapping.n_rays=64",
         "--set", "mapping.first_n_rays=64", "--set", "render.n_samples=8", "--set", "render.n_range_d=2"]


INTERRUPT_AFTER_FRAME_4 = """
import os, runpy, signal, sys
from tsslam_ref import slam
# a shell without job control starts background commands with SIGINT ignored, and Python then
# installs no KeyboardInterrupt handler; a user's terminal has one, so give it back
signal.signal(signal.SIGINT, signal.default_int_handler)
run_slam = slam.run_slam
def interrupted_run_slam(*args, on_frame, **kwargs):
    def on_frame_then_ctrl_c(state):
        on_frame(state)
        if state.done == 4:
            os.kill(os.getpid(), signal.SIGINT)
    return run_slam(*args, on_frame=on_frame_then_ctrl_c, **kwargs)
slam.run_slam = interrupted_run_slam
sys.argv[0] = "tsslam_ref.run"
runpy.run_module("tsslam_ref.run", run_name="__main__")
"""


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A synthetic sequence, a finished run made with --overwrite in a planted folder, and an
    interrupted run of the same command."""
    root = tmp_path_factory.mktemp("runs")
    assert cli("data", "synthesize", "--out", "room", "--size", "64x48", "--frames", "12", "--clean-depth",
               "--mesh-voxel", "0.2", cwd=root).returncode == 0
    outside = root / "outside"
    outside.mkdir()
    (outside / "precious.png").write_bytes(b"user's picture")
    (outside / "metrics.json").write_text("user's numbers")
    planted = root / "planted"
    planted.mkdir()
    (planted / "trajectory.png").symlink_to(outside / "precious.png")
    (planted / "metrics.json").symlink_to(outside / "metrics.json")
    (planted / "checkpoint.pt").write_bytes(b"an earlier run's checkpoint")
    (planted / "trajectory_50hz.txt").write_text("an earlier run's export")
    (planted / ".trajectory.txt.abcd1234.tmp").write_text("left by a killed run")
    (planted / "notes.txt").write_text("the user's notes")
    (planted / "tmp_backup1.tmp").write_text("the user's backup")  # a user's name, not one of our temporaries
    outside_before = snapshot(outside)
    finished = cli("run", "--data", "room", "--out", "planted", "--overwrite", *CHEAP, cwd=root)
    assert finished.returncode == 0 and "Traceback" not in finished.stderr, finished.stderr

    # Ctrl-C after the fourth frame, delivered as a real SIGINT by the process to itself from the
    # per-frame callback: a signal sent from here at a moment read off the output races the run, which
    # on an idle machine finishes its ten tiny frames before the signal lands.
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    process = subprocess.Popen([sys.executable, "-c", INTERRUPT_AFTER_FRAME_4, "--data", "room", "--out", "stopped",
                                *CHEAP], cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, stopped_err = process.communicate(timeout=120)
    return {"root": root, "outside": outside, "outside_before": outside_before, "planted": planted,
            "stopped": root / "stopped", "stopped_code": process.returncode, "stopped_err": stopped_err}


def test_overwrite_replaces_only_our_files_never_through_a_link(runs):
    planted = runs["planted"]
    assert snapshot(runs["outside"]) == runs["outside_before"]  # the link targets are byte-identical
    assert (planted / "notes.txt").read_text() == "the user's notes"
    assert (planted / "tmp_backup1.tmp").read_text() == "the user's backup"
    assert not (planted / "trajectory_50hz.txt").exists()  # the earlier run's export is gone
    assert not (planted / ".trajectory.txt.abcd1234.tmp").exists()
    for name in ("trajectory.png", "metrics.json"):
        assert not (planted / name).is_symlink() and (planted / name).is_file()
    metrics = json.loads((planted / "metrics.json").read_text())
    assert metrics["frames"] == 10
    calibration = json.loads((runs["root"] / "room" / "intrinsics.json").read_text())  # 64x48, no crop or resize
    assert metrics["camera"] == {key: calibration[key] for key in ("fx", "fy", "cx", "cy", "width", "height",
                                                                   "depth_scale")}
    assert 50 < metrics["peak_rss_mib"] < 64 * 1024  # importing torch alone takes more than 50 MiB
    assert run.load_checkpoint(planted / "checkpoint.pt").done == 10  # a new checkpoint, not the planted bytes
    mode = files.normal_mode()
    for name in ("trajectory.txt", "frames.csv", "config.json", "metrics.json", "trajectory.png", "errors.png",
                 "checkpoint.pt"):
        assert os.stat(planted / name).st_mode & 0o777 == mode, name


def test_ctrl_c_resume_refusals_and_resume(runs):
    root, stopped = runs["root"], runs["stopped"]
    assert runs["stopped_code"] == 130, runs["stopped_err"]
    assert "Traceback" not in runs["stopped_err"]
    message = runs["stopped_err"].strip().splitlines()[-1]
    assert message.startswith("interrupted with 4 of 10 frames done") and "--resume" in message, message
    assert run.load_checkpoint(stopped / "checkpoint.pt").done == 4  # stopped mid-way, checkpoint readable
    before = snapshot(stopped)
    config_json = (stopped / "config.json").read_bytes()
    for change, key in ((["--seed", "1"], "seed was 0 in the checkpoint, this command gives 1"),
                        (["--set", "tracking.iters=3"], "tracking.iters was 2"),
                        (["--frames", "0:9"], "data.frame_stop was 10"),
                        (["--method", "tsslam"], "method was \"coslam\"")):
        refused(cli("run", "--data", "room", "--out", "stopped", *CHEAP, *change, "--resume", cwd=root), key)
        assert snapshot(stopped) == before and (stopped / "config.json").read_bytes() == config_json
    resumed = cli("run", "--data", "room", "--out", "stopped", *CHEAP, "--checkpoint-every", "3", "--resume", cwd=root)
    assert resumed.returncode == 0 and "Traceback" not in resumed.stderr, resumed.stderr
    assert (stopped / "trajectory.txt").read_bytes() == (runs["planted"] / "trajectory.txt").read_bytes()
    finished = snapshot(stopped)
    again = cli("run", "--data", "room", "--out", "stopped", *CHEAP, "--resume", cwd=root)
    assert again.returncode == 0 and "finished run" in again.stdout, again.stdout + again.stderr
    assert snapshot(stopped) == finished


def test_resume_of_a_finished_run_without_a_checkpoint_says_it_is_finished(runs):
    """A run made with --checkpoint-every 0 deletes its checkpoint when it finishes; --resume then
    has nothing to continue and says so (exit 0), as for a finished run that kept one."""
    root = runs["root"]
    finished = root / "finished_without_checkpoint"
    shutil.copytree(runs["planted"], finished, symlinks=True)
    (finished / "checkpoint.pt").unlink()
    before = snapshot(finished)
    again = cli("run", "--data", "room", "--out", finished.name, *CHEAP, "--resume", cwd=root)
    assert again.returncode == 0 and "finished run" in again.stdout, again.stdout + again.stderr
    assert snapshot(finished) == before
    # other settings are refused as with a checkpoint, against the run's config.json
    other = cli("run", "--data", "room", "--out", finished.name, *CHEAP, "--seed", "1", "--resume", cwd=root)
    refused(other, "--resume refused", "config.json", "seed was 0 in config.json, this command gives 1")
    assert snapshot(finished) == before
    # a run of an earlier version, whose config.json holds mesh.voxel_eval (read by nothing, since removed)
    saved = json.loads((finished / "config.json").read_text())
    saved["mesh"]["voxel_eval"] = 0.05
    (finished / "config.json").write_text(json.dumps(saved))
    older = cli("run", "--data", "room", "--out", finished.name, *CHEAP, "--resume", cwd=root)
    assert older.returncode == 0 and "finished run" in older.stdout, older.stdout + older.stderr
    assert checkpoint.config_differences(saved, config_module.load(str(finished / "config.json"))) == []
    # ... and without the keys added since (each counts at the default it gets when the file is loaded): these
    # were refused as settings the user had changed, from "<absent>" to their defaults
    del saved["data"]["require_gt"], saved["spline"]["last_interval"]
    (finished / "config.json").write_text(json.dumps(saved))
    older = cli("run", "--data", "room", "--out", finished.name, *CHEAP, "--resume", cwd=root)
    assert older.returncode == 0 and "finished run" in older.stdout, older.stdout + older.stderr
    changed = cli("run", "--data", "room", "--out", finished.name, *CHEAP, "--resume", "--set", "data.require_gt=false",
                  cwd=root)
    refused(changed, "data.require_gt was true by default (", "of an earlier version, lacks it), this command gives false")


def test_export_rate_on_a_finished_run_writes_the_export_from_its_checkpoint(runs):
    """A finished TS-SLAM run that kept its checkpoint: --resume --export-rate writes the continuous
    trajectory byte for byte as a run made with that rate from the start wrote it (the oracle), and
    touches no other file; without the checkpoint it says what is missing."""
    root = runs["root"]
    tsslam = [argument for argument in CHEAP if argument != "coslam"]
    tsslam[tsslam.index("--method") + 1:tsslam.index("--method") + 1] = ["tsslam"]
    first = cli("run", "--data", "room", "--out", "later_export", *tsslam, cwd=root)
    assert first.returncode == 0, first.stderr
    before = snapshot(root / "later_export")
    again = cli("run", "--data", "room", "--out", "later_export", *tsslam, "--export-rate", "50", "--resume", cwd=root)
    assert again.returncode == 0 and "wrote trajectory_50hz.txt from its checkpoint" in again.stdout, again.stderr
    after = snapshot(root / "later_export")
    assert {name: entry for name, entry in after.items() if name != "trajectory_50hz.txt"} == before
    direct = cli("run", "--data", "room", "--out", "export_from_start", *tsslam, "--export-rate", "50", cwd=root)
    assert direct.returncode == 0, direct.stderr
    exported = (root / "later_export" / "trajectory_50hz.txt").read_bytes()
    assert exported == (root / "export_from_start" / "trajectory_50hz.txt").read_bytes() and exported.count(b"\n") > 5
    (root / "later_export" / "checkpoint.pt").unlink()
    again = cli("run", "--data", "room", "--out", "later_export", *tsslam, "--export-rate", "20", "--resume", cwd=root)
    assert again.returncode == 0 and "needs the run's checkpoint" in again.stdout, again.stdout
    assert not (root / "later_export" / "trajectory_20hz.txt").exists()


def test_the_dataset_folder_itself_is_refused_as_output_folder(runs):
    """The folder layout reads trajectory.txt as ground truth and a run writes trajectory.txt:
    --out on the data folder is refused before anything is written, --overwrite or not."""
    root = runs["root"]
    data = root / "room_as_out"
    shutil.copytree(root / "room", data)
    before = snapshot(data)
    for extra in ([], ["--overwrite"]):
        refused(cli("run", "--data", data.name, "--out", data.name, *CHEAP, *extra, cwd=root),
                "is the dataset folder itself")
        assert snapshot(data) == before


def test_ctrl_c_in_a_resumed_run_without_checkpoints_points_to_the_checkpoint_it_resumed_from(runs):
    root = runs["root"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = ["--data", "room", "--out", "twice", *CHEAP]
    first = subprocess.run([sys.executable, "-c", INTERRUPT_AFTER_FRAME_4, *command], cwd=root, env=env,
                           capture_output=True, text=True, timeout=120)
    assert first.returncode == 130, first.stderr
    interrupt_after_frame_7 = INTERRUPT_AFTER_FRAME_4.replace("state.done == 4", "state.done == 7")
    second = subprocess.run([sys.executable, "-c", interrupt_after_frame_7, *command, "--checkpoint-every", "0",
                             "--resume"], cwd=root, env=env, capture_output=True, text=True, timeout=120)
    assert second.returncode == 130, second.stderr
    message = second.stderr.strip().splitlines()[-1]
    assert "interrupted with 7 of 10 frames done" in message and "holds 4 frames" in message and "--resume" in message, message
    assert run.load_checkpoint(root / "twice" / "checkpoint.pt").done == 4


def _shifted_ground_truth(folder: Path, shift: float, drop_first: int = 0) -> None:
    """Rewrite folder/groundtruth.txt with every time moved by ``shift`` s and its first rows dropped."""
    lines = (folder / "groundtruth.txt").read_text().splitlines()
    rows = [line.split() for line in lines if line.strip() and not line.startswith("#")][drop_first:]
    shifted = (f"{float(row[0]) + shift:.6f} {' '.join(row[1:])}\n" for row in rows)
    (folder / "groundtruth.txt").write_text("".join(shifted))


def test_ground_truth_on_another_clock_is_named_and_can_be_set_aside(runs):
    """Ground truth 1000 s off every frame: refused naming both time spans and the setting that runs
    without it; with --set data.require_gt=false the run completes without ATE.  Ground truth that
    misses the first frames: the run leaves them out and says how many."""
    root = runs["root"]
    other_clock = root / "room_other_clock"
    shutil.copytree(root / "room", other_clock)
    _shifted_ground_truth(other_clock, 1000.0)
    refused(cli("run", "--data", other_clock.name, "--out", "clock_out", *CHEAP, cwd=root),
            "no frame has a ground-truth pose", "the frames span", "the ground truth 10", "data.require_gt=false")
    assert not (root / "clock_out").exists()
    result = cli("run", "--data", other_clock.name, "--out", "clock_out", *CHEAP, "--set", "data.require_gt=false",
                 cwd=root)
    assert result.returncode == 0, result.stderr
    assert "ate_rmse_m" not in json.loads((root / "clock_out" / "metrics.json").read_text())
    late = root / "room_late_gt"
    shutil.copytree(root / "room", late)
    _shifted_ground_truth(late, 0.0, drop_first=3)
    refused(cli("run", "--data", late.name, "--out", "late_out", *CHEAP, cwd=root),  # 0:10 of the 9 left: named
            "stop=10 is beyond the 9 usable frames", "3 frame(s) without a ground-truth pose are left out")
    result = cli("run", "--data", late.name, "--out", "late_out", *CHEAP, "--frames", "0:9", cwd=root)
    assert result.returncode == 0 and "note: 3 frame(s)" in result.stdout and "require_gt=false" in result.stdout, (
        result.stdout + result.stderr)


def test_user_data_without_ground_truth_or_with_a_bad_frame_mid_run(runs):
    """A ground-truth mesh beside data without ground-truth poses cannot be culled: the run skips
    the reconstruction metrics (it crashed after the run). A frame that turns out unreadable mid-run
    exits 2 and says how to go on: --overwrite, or --resume from the checkpoint."""
    root = runs["root"]
    with_mesh = [argument for argument in CHEAP if argument != "--no-mesh"]
    no_gt = root / "room_no_gt"
    shutil.copytree(root / "room", no_gt)
    (no_gt / "groundtruth.txt").unlink()
    assert (no_gt / "gt_mesh.ply").is_file()
    result = cli("run", "--data", no_gt.name, "--out", "no_gt_out", *with_mesh, cwd=root)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    metrics = json.loads((root / "no_gt_out" / "metrics.json").read_text())
    assert "ate_rmse_m" not in metrics and (root / "no_gt_out" / "mesh.ply").is_file()
    assert "gt_mesh.ply is not scored: culling needs ground-truth camera poses" in result.stdout, result.stdout
    assert "frames/s; no ground-truth poses, so no ATE / RPE; peak RSS" in result.stdout, result.stdout

    bad_frame = root / "room_bad_frame"
    shutil.copytree(root / "room", bad_frame)
    listed = [line.split() for line in (bad_frame / "depth.txt").read_text().splitlines() if not line.startswith("#")]
    depth_path = bad_frame / listed[6][1]
    Image.fromarray(np.zeros_like(np.asarray(Image.open(depth_path)))).save(depth_path)  # frame 6: no depth at all
    result = cli("run", "--data", bad_frame.name, "--out", "bad_frame_out", *CHEAP, cwd=root)
    refused(result, "after replacing the file, run the same command with --resume to continue from its checkpoint "
                    "(6 frames done); after removing the frame from the lists instead, with --overwrite")


def test_a_users_own_folder_gets_its_own_layout_and_depth_scale_not_the_presets(tmp_path):
    """The default preset is TUM's (layout tum, depth 5000 per metre); with --data the folder's
    layout is detected and its depth scale comes from its calibration file or layout standard
    (a ScanNet folder read at 5000 would put every depth 5x too near), also when --dataset names
    the layout.  --set and a config file of the user's still decide."""
    def resolved(*arguments):
        return run.resolve_config(run.build_parser().parse_args(list(arguments))).data

    assert (resolved().dataset, resolved().depth_scale) == ("tum", 5000.0)  # the bundled slice: the preset's
    for preset in ([], ["--config", "tum-cpu"], ["--config", "scannet"]):
        mine = resolved("--data", str(tmp_path), *preset)
        assert (mine.dataset, mine.depth_scale) == ("auto", None), preset
    assert resolved("--data", str(tmp_path), "--set", "data.depth_scale=4000").depth_scale == 4000.0
    for layout in ("scannet", "folder", "tum"):  # naming the layout gives its standard scale, not the preset's 5000
        mine = resolved("--data", str(tmp_path), "--dataset", layout)
        assert (mine.dataset, mine.depth_scale) == (layout, None), layout
    config_file = tmp_path / "mine.json"
    config_file.write_text(json.dumps({"data": {"dataset": "tum", "depth_scale": 5000.0}}))
    mine = resolved("--data", str(tmp_path), "--config", str(config_file))
    assert (mine.dataset, mine.depth_scale) == ("tum", 5000.0)


def test_output_piped_into_a_reader_that_stops_early_ends_quietly():
    """`spline_kit docs | head -1`: the reader closes the pipe; no BrokenPipeError traceback."""
    process = subprocess.Popen([sys.executable, "-m", "tsslam_ref.spline_kit", "docs"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, env=dict(os.environ, PYTHONUNBUFFERED="0"))
    first_line = process.stdout.readline()
    process.stdout.close()  # as `head -1` does after one line
    _, stderr = process.communicate(timeout=120)
    assert first_line and process.returncode == 0, (process.returncode, stderr.decode())
    assert b"Traceback" not in stderr and b"BrokenPipe" not in stderr, stderr.decode()


def test_synthesize_force_never_deletes_what_the_user_added(tmp_path, capsys):
    arguments = ["synthesize", "--out", str(tmp_path / "room"), "--frames", "2", "--size", "16x16", "--mesh-voxel", "0.5"]
    assert data.main(arguments) == 0
    (tmp_path / "room" / "notes.txt").write_text("mine")
    (tmp_path / "room" / "run1").mkdir()  # e.g. a run's outputs kept beside the data
    before = snapshot(tmp_path / "room")
    assert data.main(arguments + ["--force"]) == 2
    assert "notes.txt, run1" in capsys.readouterr().err
    assert snapshot(tmp_path / "room") == before
    (tmp_path / "room" / "notes.txt").unlink()
    (tmp_path / "room" / "run1").rmdir()
    assert data.main(arguments + ["--force"]) == 0  # its own folder alone is replaced


def test_an_output_folder_that_cannot_be_written_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    """No write permission is refused before the run (the check, as root cannot lose permission,
    is driven through os.access); a disk that fills up while the outputs are written ends in one
    line naming the folder, exit 2, not a traceback."""
    assert data.main(["synthesize", "--out", str(tmp_path / "room"), "--frames", "4", "--size", "32x24",
                      "--mesh-voxel", "0.5"]) == 0
    capsys.readouterr()
    (tmp_path / "empty").mkdir()
    before = snapshot(tmp_path)
    with monkeypatch.context() as patch:
        patch.setattr(run_outputs.os, "access", lambda path, mode: False)
        refused_in_process(capsys, run.main, ["--out", tmp_path / "new" / "run"], "cannot create the output folder",
                           "no permission to write in")
        refused_in_process(capsys, run.main, ["--out", tmp_path / "empty"], "empty", "no permission to write in it")
    assert snapshot(tmp_path) == before

    def disk_full(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(run, "write_outputs", disk_full)
    arguments = [a for a in CHEAP if a not in ("0:10",)]
    arguments[arguments.index("--frames") + 1:arguments.index("--frames") + 1] = ["0:3"]
    refused_in_process(capsys, run.main, arguments + ["--data", tmp_path / "room", "--out", tmp_path / "out"],
                       "cannot write the outputs in", "No space left on device")


def test_the_closing_line_says_why_there_is_no_ate():
    two_known = np.full((5, 4, 4), np.nan)
    two_known[[0, 3]] = np.eye(4)
    assert run_outputs._why_no_metrics(SimpleNamespace(gt_poses=None)) == "no ground-truth poses, so no ATE / RPE"
    assert run_outputs._why_no_metrics(SimpleNamespace(gt_poses=np.full((5, 4, 4), np.nan))).startswith("no ground-truth")
    assert run_outputs._why_no_metrics(SimpleNamespace(gt_poses=two_known)) == (
        "only 2 frames with a ground-truth pose, so no ATE / RPE (they need 3)")


@pytest.mark.parametrize("motion", ["standing still", "turning in place"])
def test_a_camera_standing_still_or_turning_in_place_gets_its_ate(tmp_path, capsys, motion):
    """Collinear or coincident ground-truth positions made the run crash after its last frame (the
    alignment refused them), with no metrics.json; now both methods finish with a finite ATE."""
    times = np.arange(0.0, 2.0, 0.01)
    yaw = np.radians(10.0) * times if motion == "turning in place" else np.zeros_like(times)
    half = yaw / 2.0  # quaternion of a rotation about the camera's y axis (x, y, z, w)
    rows = np.column_stack([times, np.zeros((len(times), 3)), np.zeros_like(half), np.sin(half), np.zeros_like(half), np.cos(half)])
    np.savetxt(tmp_path / "motion.txt", rows, fmt="%.9f")
    assert data.main(["synthesize", "--out", str(tmp_path / "room"), "--trajectory", str(tmp_path / "motion.txt"),
                      "--frames", "8", "--size", "48x36", "--fps", "10", "--mesh-voxel", "0.5"]) == 0
    for method in ("coslam", "tsslam"):
        arguments = [a for a in CHEAP if a != "coslam"]
        arguments[arguments.index("--method") + 1:arguments.index("--method") + 1] = [method]
        out = tmp_path / f"out_{method}"
        assert run.main(arguments + ["--data", str(tmp_path / "room"), "--out", str(out), "--frames", "0:8"]) == 0, (
            capsys.readouterr().err)
        metrics = json.loads((out / "metrics.json").read_text())
        assert np.isfinite(metrics["ate_rmse_m"]) and metrics["ate_rmse_m"] < 0.5, metrics
        assert ("spline" in metrics) == ("spline_offsets" in metrics) == (method == "tsslam")
        assert ("spline from the tracked poses: RMS" in capsys.readouterr().out) == (method == "tsslam")
        with open(out / "frames.csv", newline="") as table:  # one row per frame; tracking's values from frame 1
            rows = list(csv.DictReader(table))
        assert [int(row["frame"]) for row in rows] == list(range(8))
        assert [row["tracking_loss"] != "" for row in rows] == [False] + [True] * 7
        offsets = np.array([float(row["spline_offset_deg"]) for row in rows[1:] if row["spline_offset_deg"]])
        assert len(offsets) == (7 if method == "tsslam" else 0)
    assert np.sqrt(np.mean(offsets ** 2)) == pytest.approx(metrics["spline_offsets"]["rotation_rms_deg"], rel=1e-6)
    assert metrics["spline_offsets"]["frames"] == 7  # every tracked frame (1-7) once, the last interval's too
    stamps = np.loadtxt(out / "trajectory.txt")[:, 0]  # the TS-SLAM run's frames: its intervals cover them
    bounds = np.array(metrics["spline"]["interval_boundaries_s"])
    assert metrics["spline"]["knots"] == "uniform" and metrics["spline"]["intervals"] == len(bounds) - 1
    assert abs(bounds[0] - stamps[0]) < 1e-6 and bounds[-2] <= stamps[-1] < bounds[-1]
    np.testing.assert_allclose(np.diff(bounds[:-1]), config_module.tiny().spline.dt, rtol=1e-9)
    assert bounds[-1] == pytest.approx(stamps[-1] + 0.25 * 0.1, abs=2e-6)  # a quarter spacing past the last


def test_a_map_without_a_surface_still_ends_with_metrics(runs, tmp_path, monkeypatch, capsys):
    """Meshing after the last frame can find no surface; the trajectory and its metrics are written
    anyway, with a note, exit 0 (it was a traceback with no metrics.json)."""
    from tsslam_ref import mesh

    def no_surface(*_, **__):
        raise ValueError("extract_mesh: the SDF has no zero crossing inside the bound")

    monkeypatch.setattr(mesh, "extract_mesh", no_surface)
    with_mesh = [argument for argument in CHEAP if argument != "--no-mesh"]
    assert run.main(with_mesh + ["--data", str(runs["root"] / "room"), "--out", str(tmp_path / "out")]) == 0
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert "ate_rmse_m" in metrics and metrics["mesh_note"].startswith("no mesh.ply: extract_mesh: the SDF has no zero")
    assert not (tmp_path / "out" / "mesh.ply").exists()
    assert "warning: no mesh.ply" in capsys.readouterr().err


def test_depth_mostly_beyond_the_map_range_is_warned_about_before_the_run(tmp_path, capsys):
    """A depth scale 5x off put 99 % of the depth beyond render.far: the map was built from a few
    pixels and the reconstruction was empty, with no word; the check reads frame 0 in prepare."""
    assert data.main(["synthesize", "--out", str(tmp_path / "room"), "--frames", "3", "--size", "32x24",
                      "--mesh-voxel", "0.5"]) == 0
    calibration = json.loads((tmp_path / "room" / "intrinsics.json").read_text())
    calibration.pop("depth_scale")  # PNGs at 5000 per metre, read at 1000: five times too far
    (tmp_path / "room" / "intrinsics.json").write_text(json.dumps(calibration))
    capsys.readouterr()
    common = ["--data", str(tmp_path / "room"), "--config", "tiny", "--out", str(tmp_path / "out")]
    run.prepare(run.build_parser().parse_args(common + ["--set", "data.depth_scale=1000"]))
    warning = capsys.readouterr().err
    assert "warning: 99 % of frame 0's measured depth lies beyond 4 m" in warning and "data.depth_scale = 1000" in warning
    run.prepare(run.build_parser().parse_args(common + ["--set", "data.depth_scale=5000"]))
    assert "warning" not in capsys.readouterr().err
    run.prepare(run.build_parser().parse_args(common + ["--set", "data.depth_scale=50000"]))  # ten times too near
    warning = capsys.readouterr().err  # the room's median is 1.60 m (data info), read as 0.16 m
    assert "warning: frame 0's median measured depth is 0.16 m" in warning and "data.depth_scale = 50000" in warning
    assert not (tmp_path / "out").exists()


def _interrupted_beside_its_data(runs, tmp_path) -> None:
    """tmp_path/room (a copy of the synthetic sequence) and tmp_path/stopped, a run of it stopped by
    Ctrl-C after frame 4 (exit 130), made from tmp_path with the relative --data room."""
    shutil.copytree(runs["root"] / "room", tmp_path / "room")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    stopped = subprocess.run([sys.executable, "-c", INTERRUPT_AFTER_FRAME_4, "--data", "room", "--out", "stopped",
                              *CHEAP], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert stopped.returncode == 130, stopped.stderr


def test_resume_with_a_frame_removed_names_where_the_frames_differ(runs, tmp_path):
    """The same folder (its frame list edited in place: a copy of the folder would be another
    folder, refused as such) with the third frame gone."""
    _interrupted_beside_its_data(runs, tmp_path)
    lines = (tmp_path / "room" / "rgb.txt").read_text().splitlines()
    data_lines = [i for i, line in enumerate(lines) if line and not line.startswith("#")]
    del lines[data_lines[2]]  # the third frame
    (tmp_path / "room" / "rgb.txt").write_text("\n".join(lines) + "\n")
    before = snapshot(tmp_path / "stopped")
    refused(cli("run", *CHEAP, "--data", "room", "--out", "stopped", "--resume", cwd=tmp_path),
            "--resume refused", "differ from those in", "the first difference at frame 2")
    assert snapshot(tmp_path / "stopped") == before


def test_resume_compares_the_data_folder_itself_not_the_path_as_typed(runs, tmp_path, monkeypatch):
    """A relative --data was stored as typed and resolved against the resuming command's folder:
    the same data given from elsewhere was refused, and another folder with the same time stamps
    (a copy, re-rendered, ...) was accepted and mixed into the trajectory.  prepare() checks and
    writes nothing, so the refusals and acceptances are seen without running."""
    root = runs["root"]
    shutil.copytree(runs["stopped"], tmp_path / "stopped")
    resume = [*CHEAP, "--out", str(tmp_path / "stopped"), "--resume"]
    monkeypatch.chdir(root.parent)
    plan = run.prepare(run.build_parser().parse_args(resume + ["--data", f"{root.name}/room"]))  # the same folder
    assert plan.finished or plan.state.done == 4  # accepted (another test may have finished the stopped run)
    shutil.copytree(root / "room", tmp_path / "room")  # the same frames and stamps, another folder
    monkeypatch.chdir(tmp_path)
    with pytest.raises(run.BadInput, match="--resume refused.*data.path was"):
        run.prepare(run.build_parser().parse_args(resume + ["--data", "room"]))


def test_ctrl_c_while_the_outputs_are_written_gives_advice_that_works(runs, tmp_path, monkeypatch, capsys):
    """metrics.json marks a finished run, so it is written last; and --resume is advised only when a
    checkpoint is there to resume from (it was advised always, and then refused)."""
    def interrupted(*_):
        raise KeyboardInterrupt

    monkeypatch.setattr(run, "write_outputs", interrupted)
    data_folder = str(runs["root"] / "room")
    cheap = [a for a in CHEAP if a != "0:10"]
    cheap[cheap.index("--frames") + 1:cheap.index("--frames") + 1] = ["0:3"]
    assert run.main(cheap + ["--data", data_folder, "--out", str(tmp_path / "a")]) == 130  # a checkpoint every frame
    assert "run the same command with --resume to finish them from its checkpoint" in capsys.readouterr().err
    no_checkpoint = cheap[:cheap.index("--checkpoint-every") + 1] + ["0"] + cheap[cheap.index("--checkpoint-every") + 2:]
    assert run.main(no_checkpoint + ["--data", data_folder, "--out", str(tmp_path / "b")]) == 130
    assert "run the same command with --overwrite to run it again" in capsys.readouterr().err


def test_starting_a_run_does_not_import_trimesh():
    """trimesh wraps its networkx import in `except BaseException`, which swallowed a Ctrl-C in a
    run's first seconds (the run went on to exit 0); it is now imported only to read or score a mesh."""
    check = "import sys, tsslam_ref.run; print('trimesh' in sys.modules, 'networkx' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", check], env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout.split() == ["False", "False"], (result.stdout, result.stderr)


def test_resume_in_another_environment_warns_and_metrics_record_both(runs, tmp_path, monkeypatch, capsys):
    """The checkpoint records the environment the run started in (PyTorch, device, CPU kernels,
    threads, map kernels); a resume elsewhere used to go on without a word, and metrics.json then
    described only the finishing process.  Another PyTorch is stood in for by patching what
    device.compute_environment reports."""
    from tsslam_ref import device as device_module

    _interrupted_beside_its_data(runs, tmp_path)
    started_in = checkpoint.read(tmp_path / "stopped" / "checkpoint.pt")["environment"]
    assert started_in["torch"] == torch.__version__ and started_in["map_kernels"]["hash_grid"] in ("compiled", "pytorch")
    assert started_in["tsslam_ref"] == device_module.source_version()
    real = device_module.compute_environment
    monkeypatch.setattr(device_module, "compute_environment", lambda where: {**real(where), "torch": "0.0-other"})
    monkeypatch.setattr(device_module, "source_version", lambda: "0.1.0, source edited")  # the package was edited
    monkeypatch.chdir(tmp_path)
    assert run.main([*CHEAP, "--data", "room", "--out", "stopped", "--resume"]) == 0
    warning = capsys.readouterr().err
    assert f"torch was '{torch.__version__}' when the run started, now '0.0-other'" in warning
    assert f"tsslam_ref was '{started_in['tsslam_ref']}' when the run started, now '0.1.0, source edited'" in warning
    assert "frames from 4 on will not match" in warning
    metrics = json.loads((tmp_path / "stopped" / "metrics.json").read_text())
    assert metrics["environment"]["torch"] == "0.0-other" and metrics["environment_at_start"] == started_in


def test_resuming_an_earlier_versions_checkpoint_says_the_frames_may_differ_not_that_they_will(monkeypatch, capsys):
    """A checkpoint of an earlier version records no code digest: that the code differs is not known,
    so the warning says the frames may not match; a recorded difference says they will not."""
    from tsslam_ref import device as device_module

    now = {"tsslam_ref": "0.1.0, source 0123456789ab", "torch": "2.13.0+cpu", "threads": 2}
    monkeypatch.setattr(device_module, "run_environment", lambda *args: now)
    plan = SimpleNamespace(device=torch.device("cpu"), state=SimpleNamespace(field=None, done=7), finished=False)
    earlier = {"torch": "2.13.0+cpu", "threads": 2}
    assert run._resume_environment(earlier, plan) is earlier
    warning = capsys.readouterr().err
    assert ("the checkpoint, of an earlier version, does not record tsslam_ref (now '0.1.0, source 0123456789ab')"
            in warning)
    assert "the frames from 7 on may not match an uninterrupted run" in warning
    run._resume_environment(dict(earlier, threads=1), plan)
    assert "threads was 1 when the run started, now 2" in (warning := capsys.readouterr().err)
    assert "the frames from 7 on will not match" in warning
    run._resume_environment(dict(now), plan)
    assert capsys.readouterr().err == ""


def test_three_frames_with_a_ground_truth_pose_get_an_ate():
    """docs and the closing line say ATE / RPE need 3 frames with a ground-truth pose: with exactly
    3 (frames 0, 2, 4 of 5) metrics.json gets them. Oracle: the estimate is the ground truth moved
    by one rigid motion, so its ATE after alignment is 0, over the 3 known frames."""
    times = np.arange(5) * 0.1
    gt = np.full((5, 4, 4), np.nan)
    for i, position in zip((0, 2, 4), ([0.0, 0.0, 0.0], [0.3, 0.1, 0.0], [0.2, 0.5, 0.4])):
        gt[i] = np.eye(4)
        gt[i, :3, :3] = Rotation.from_rotvec([0.1 * i, 0.0, 0.05]).as_matrix()
        gt[i, :3, 3] = position
    moved = np.eye(4)
    moved[:3, :3], moved[:3, 3] = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), [1.0, 2.0, 3.0]
    estimate = np.array([moved @ pose if np.isfinite(pose).all() else np.eye(4) for pose in gt])
    metrics = run_outputs.trajectory_metrics(SimpleNamespace(gt_poses=gt), times, estimate)
    assert metrics["n_matched"] == 3 and metrics["ate_rmse_m"] < 1e-9
    gt[2] = np.nan  # two frames left: too few to align, so no ATE / RPE (not a failed alignment)
    assert run_outputs.trajectory_metrics(SimpleNamespace(gt_poses=gt), times, estimate) == {}


def test_number_options_accept_both_closed_ends_of_their_range():
    """The ends written in docs/cli.md: --seed 0 and 2**32 - 1, --checkpoint-every 0,
    --export-rate 1000 are accepted; --export-rate 0 (an open end) is refused."""
    assert run._seed("0") == 0 and run._seed(str(2**32 - 1)) == 2**32 - 1
    assert run._checkpoint_every("0") == 0 and run._export_rate(str(run.MAX_EXPORT_RATE)) == run.MAX_EXPORT_RATE
    with pytest.raises(argparse.ArgumentTypeError, match=r"--export-rate 0: must be a finite number in \(0, "):
        run._export_rate("0")
    assert cli_args.number_in("--fps", 0, 1000, low_open=True)("1000") == 1000.0


def test_frames_edges_parse_as_documented():
    """docs/cli.md: 0 <= START < STOP, STEP >= 1; worked by hand: ':5' is frames 0..4 (an empty START
    is 0), '3:3' selects nothing, and a negative STOP gets the negative-position message."""
    assert run.parse_frames(":5") == (0, 5, 1) and run.parse_frames("2:") == (2, None, 1)
    assert run.parse_frames("1:9:2") == (1, 9, 2)
    with pytest.raises(run.BadInput, match="'3:3' selects no frames"):
        run.parse_frames("3:3")
    with pytest.raises(run.BadInput, match="must be >= 0"):
        run.parse_frames("0:-3")


def test_command_line_options_reach_the_config_even_at_their_zero_value(tmp_path):
    """A config file with seed 7: --seed 0 must still give seed 0 (0 is a valid seed, not 'unset');
    --dataset synthetic names a folder written by `data synthesize`, in the TUM layout (the
    option's help), so the layout is 'tum'."""
    config_file = tmp_path / "mine.json"
    config_file.write_text(json.dumps({"seed": 7}))
    parse = run.build_parser().parse_args
    assert run.resolve_config(parse(["--config", str(config_file), "--seed", "0"])).seed == 0
    assert run.resolve_config(parse(["--config", str(config_file)])).seed == 7
    assert run.resolve_config(parse(["--dataset", "synthetic", "--data", str(tmp_path)])).data.dataset == "tum"


def test_overwrite_removes_exports_by_their_exact_name_and_dangling_links(tmp_path):
    """Worked by hand from OUTPUT_NAMES: 'trajectory_5hz.txt' is ours (also as a link to nothing),
    'trajectory_5hz.txt.bak' and 'my_trajectory_5hz.txt' are the user's and stay."""
    (tmp_path / "trajectory_5hz.txt.bak").write_text("mine")
    (tmp_path / "my_trajectory_5hz.txt").write_text("mine")
    (tmp_path / "trajectory_5hz.txt").symlink_to(tmp_path / "gone")
    assert not run.is_output_name("trajectory_5hz.txt.bak") and run.is_output_name("trajectory_5hz.txt")
    assert run.remove_previous_outputs(tmp_path) == [tmp_path / "trajectory_5hz.txt"]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["my_trajectory_5hz.txt", "trajectory_5hz.txt.bak"]


def test_the_default_output_folder_names_the_sequence_and_the_configs_method(tmp_path, monkeypatch):
    """docs: --out defaults to runs/<sequence>-<method>; with no --method the method is the
    config's (tum-cpu: tsslam), never the absent option's None."""
    monkeypatch.chdir(tmp_path)
    parse = run.build_parser().parse_args
    assert run.prepare(parse([])).out == Path("runs") / f"{BUNDLED.name}-tsslam"
    assert run.prepare(parse(["--set", "method=coslam"])).out == Path("runs") / f"{BUNDLED.name}-coslam"


def test_resume_refusal_counts_the_other_differences(tmp_path, monkeypatch, capsys):
    """A checkpoint whose config differs in seed and tracking.iters (two keys, set by hand here):
    the message names the first (sorted: seed) and adds '(and 1 more)'."""
    saved = config_module.load("tum-cpu")
    saved.seed, saved.tracking.iters = 5, saved.tracking.iters + 1
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"read through the stand-in below")
    values = {"config": json.dumps(config_module.to_dict(saved))}
    monkeypatch.setattr(checkpoint, "read", lambda path: values)
    refused_in_process(capsys, run.main, ["--out", out, "--resume"], "seed was 5", "(and 1 more)")


def test_resume_names_the_first_frame_past_a_shorter_selection(tmp_path, monkeypatch, capsys):
    """The checkpoint holds frames 0..10 of the bundled slice, this command selects 0..9: the frames
    agree as far as both go, so by hand the first difference is frame 10 (11 saved, 10 now)."""
    cfg = run.resolve_config(run.build_parser().parse_args(["--frames", "0:10"]))
    saved = data.load_from_config(run.resolve_config(run.build_parser().parse_args(["--frames", "0:11"])).data)
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"read through the stand-in below")
    values = {"config": json.dumps(config_module.to_dict(cfg)), "timestamps": torch.from_numpy(saved.timestamps)}
    monkeypatch.setattr(checkpoint, "read", lambda path: values)
    refused_in_process(capsys, run.main, ["--frames", "0:10", "--out", out, "--resume"],
                       "11 frames saved, 10 now; the first difference at frame 10")


def test_settings_the_method_never_reads_are_noted_and_change_nothing(runs):
    """The baseline has no spline: ``--set spline.knots=adaptive`` with ``--method coslam`` once ran
    silently, as if adaptive knots were in use.  Noted now; the trajectory is the one without it."""
    unread = ["--set", "spline.knots=adaptive", "--set", "local_ba.window=3", "--set", "dynamics.a_max=1"]
    result = cli("run", "--data", "room", "--out", "unread", *CHEAP, *unread, cwd=runs["root"])
    assert result.returncode == 0, result.stderr
    notes = [line for line in result.stdout.splitlines() if "has no effect with --method coslam" in line]
    assert [line.split("--set ")[1].split(" ")[0] for line in notes] == [unread[1], unread[3], unread[5]], notes
    assert (runs["root"] / "unread" / "trajectory.txt").read_bytes() == (runs["planted"] / "trajectory.txt").read_bytes()



def test_keys_an_ablation_switch_leaves_unread_are_noted_and_change_nothing(runs):
    """'w/o B-S.' (``local_ba.use_spline=false``) runs no curve fit, deviation check or L_DR, and a
    run renders no whole image: their keys were taken without a word.  The oracle is the run
    without them: the same trajectory, byte for byte."""
    ablation = [*CHEAP, "--method", "tsslam", "--set", "local_ba.use_spline=false"]
    unread = ["dynamics.a_max=0.01", "local_ba.fit_iters=0", "local_ba.max_deviation=1e-6",
              "spline.last_interval=last_frame", "render.chunk=1"]
    plain = cli("run", "--data", "room", "--out", "no_spline", *ablation, cwd=runs["root"])
    noted = cli("run", "--data", "room", "--out", "no_spline_unread", *ablation,
                *[word for key in unread for word in ("--set", key)], cwd=runs["root"])
    assert plain.returncode == 0 and noted.returncode == 0, (plain.stderr, noted.stderr)
    notes = [line.split("--set ")[1].split(" ")[0] for line in noted.stdout.splitlines() if "has no effect" in line]
    assert notes == unread, noted.stdout
    assert "has no effect" not in plain.stdout
    assert ((runs["root"] / "no_spline_unread" / "trajectory.txt").read_bytes()
            == (runs["root"] / "no_spline" / "trajectory.txt").read_bytes())


def test_local_ba_switched_off_notes_its_own_settings_and_the_baseline_takes_any_window():
    unread = config_module.overrides_without_effect
    without_lba = config_module.apply_overrides(config_module.load("tum-cpu"), ["local_ba.enabled=false"])
    keys = ["local_ba.refine_iters=3", "local_ba.lr_rot=1e-3", "local_ba.window=3", "dynamics.a_max=1"]
    assert [text.split(" has no effect with ")[1] for text in unread("tsslam", keys, without_lba)] == [
        "local_ba.enabled=false (no curve fit and no window stages)"] * 2  # the window sets L_DR's range
    without_dr = config_module.apply_overrides(config_module.load("tum-cpu"), ["local_ba.use_dynamics=false"])
    assert [text.split(" ")[0] for text in unread("tsslam", keys, without_dr)] == ["dynamics.a_max=1"]
    # the baseline reads no local_ba key, so local BA's rule fit_controls <= window is not its to enforce
    baseline = config_module.apply_overrides(config_module.load("tum-cpu"), ["method=coslam", "local_ba.window=2"])
    assert baseline.local_ba.window == 2
    with pytest.raises(ValueError, match="local_ba.fit_controls = 3 must be <= local_ba.window = 2"):
        config_module.apply_overrides(baseline, ["method=tsslam"])
    for ablation in ("local_ba.use_spline=false", "local_ba.enabled=false"):  # no curve fit either
        assert config_module.apply_overrides(baseline, ["method=tsslam", ablation]).local_ba.window == 2


def test_keys_of_the_other_method_are_matched_by_name_and_section():
    unread = config_module.overrides_without_effect
    assert unread("tsslam", ["mapping.map_every=3", "mapping.map_every_x=1", "spline.dt=0.1"]) == [
        "mapping.map_every=3 has no effect with --method tsslam (TS-SLAM maps once per spline interval and every "
        "mapping.tsslam_map_every frames)"]
    assert [text.split(" ")[0] for text in unread("coslam", ["mapping.tsslam_map_every=0", "mapping.map_every=3",
                                                            "splines.dt=1", "local_ba.enabled=false"])] == [
        "mapping.tsslam_map_every=0", "local_ba.enabled=false"]
    uniform, adaptive = config_module.load("tum-cpu"), config_module.apply_overrides(
        config_module.load("tum-cpu"), ["spline.knots=adaptive"])
    policy = ["spline.dt_min=0.2", "spline.dt_max=0.5", "spline.rotation_tolerance=1", "spline.position_tolerance=1"]
    assert unread("tsslam", policy + ["spline.dt=0.2"], uniform) == [
        f"{text} has no effect with uniform knots (read only with spline.knots=adaptive)" for text in policy]
    assert unread("tsslam", policy, adaptive) == [] and unread("tsslam", policy) == []



def test_a_full_disk_at_a_checkpoint_gives_one_line_naming_the_file(runs):
    """torch.save reports a failed write as a RuntimeError: a checkpoint that met a full disk (here a
    file-size limit, with SIGXFSZ ignored so that writes fail with EFBIG) ended in a traceback and
    exit 1, and a failed write inside the loop was worded as a frame that could not be read."""
    import resource
    import signal

    def file_size_limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))  # the checkpoint is megabytes

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    result = subprocess.run([sys.executable, "-m", "tsslam_ref.run", "--data", "room", "--out", "full", *CHEAP],
                            cwd=runs["root"], env=env, preexec_fn=file_size_limit, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("error: cannot write the outputs in full: ") and "checkpoint.pt failed" in last, last
    assert "replacing the file" not in last and not list((runs["root"] / "full").glob(".*.tmp"))
    assert last.endswith("run with --overwrite"), last  # no checkpoint was written: --resume would be refused
    # a stop whose message names no file of the data is not blamed on the data either
    other = cli("run", "--data", "room", "--out", "coarse", *CHEAP, "--set", "field.voxel_sdf=9", cwd=runs["root"])
    last = other.stderr.strip().splitlines()[-1]
    assert other.returncode == 2 and "res_max" in last and last.endswith(
        "after fixing the cause, run the same command with --overwrite"), other.stderr



@pytest.mark.parametrize("module", ["run", "data", "eval", "spline_kit"])
def test_every_command_line_helps_under_python_OO(module, tmp_path):
    """``python -OO`` strips docstrings: a parser built from ``__doc__`` failed with an AttributeError."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    result = subprocess.run([sys.executable, "-OO", "-m", f"tsslam_ref.{module}", "--help"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout.startswith("usage: python -m tsslam_ref."), result.stderr



def test_output_in_an_encoding_without_the_folder_names_characters_is_escaped_not_a_traceback(tmp_path):
    """Windows encodes redirected output in its ANSI code page (cp1252 here, through
    PYTHONIOENCODING): a folder named 'Łódź' printed to a log file ended the command with a
    UnicodeEncodeError traceback (`run` after writing its config.json)."""
    from tsslam_ref import data as data_module

    folder = tmp_path / "Łódź"
    shutil.copytree(data_module.default_sequence_path(), folder)
    env = dict(os.environ, PYTHONIOENCODING="cp1252",
               PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    info = subprocess.run([sys.executable, "-m", "tsslam_ref.data", "info", str(folder)], cwd=tmp_path, env=env,
                          capture_output=True, timeout=300)
    assert info.returncode == 0 and b"\\u0141\xf3d\\u017a" in info.stdout, info.stderr.decode("cp1252", "replace")
    kit = subprocess.run([sys.executable, "-m", "tsslam_ref.spline_kit", "docs"], cwd=tmp_path, env=env,
                         capture_output=True, timeout=300)
    assert kit.returncode == 0 and b"Traceback" not in kit.stderr, kit.stderr.decode("cp1252", "replace")


def test_a_parallel_run_stopped_with_ctrl_c_resumes(runs):
    """The mapping thread writes the checkpoint while tracking may be a mapping period ahead; the
    resumed run finishes (its trajectory is not the uninterrupted one's: --parallel is not deterministic)."""
    root = runs["root"]
    slow_mapping = ("from tsslam_ref import parallel\nimport time\nafter_tracking = slam.after_tracking\n"
                    "slam.after_tracking = lambda *a: time.sleep(0.5) or after_tracking(*a)  # tracking gets ahead\n"
                    "run_slam = parallel.run_slam_in_two_threads")
    script = INTERRUPT_AFTER_FRAME_4.replace("run_slam = slam.run_slam", slow_mapping).replace(
        "slam.run_slam = interrupted_run_slam", "parallel.run_slam_in_two_threads = interrupted_run_slam")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = ["--data", "room", "--out", "parallel", "--parallel", *CHEAP, "--method", "tsslam"]  # lag: one interval
    stopped = subprocess.run([sys.executable, "-c", script, *command], cwd=root, env=env, capture_output=True, text=True,
                             timeout=120)
    assert stopped.returncode == 130 and "--resume" in stopped.stderr, stopped.stderr
    assert 4 <= run.load_checkpoint(root / "parallel" / "checkpoint.pt").done < 10
    resumed = cli("run", *command, "--resume", cwd=root)
    assert resumed.returncode == 0 and "Traceback" not in resumed.stderr, resumed.stderr
    rows = [line for line in (root / "parallel" / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(rows) == 10


def test_an_export_from_a_finished_run_refits_only_the_last_interval_and_ctrl_c_there_changes_nothing(
        runs, tmp_path, monkeypatch, capsys):
    """A checkpoint every 3 of 10 frames left the finished run's last one at frame 9, so --export-rate
    tracked frame 10 again, silently different in another environment; and Ctrl-C during the export
    advised --overwrite, which deletes the finished run."""
    from tsslam_ref import device as device_module
    from tsslam_ref import export as export_module

    tsslam = [argument for argument in CHEAP if argument != "coslam"]
    tsslam[tsslam.index("--method") + 1:tsslam.index("--method") + 1] = ["tsslam"]
    command = [*tsslam, "--checkpoint-every", "3", "--data", str(runs["root"] / "room"), "--out", str(tmp_path / "done")]
    assert run.main(command) == 0
    assert run.load_checkpoint(tmp_path / "done" / "checkpoint.pt").done == 10
    capsys.readouterr()
    before = snapshot(tmp_path / "done")

    def interrupted(*_):
        raise KeyboardInterrupt

    with monkeypatch.context() as patched:
        patched.setattr(export_module, "export_continuous", interrupted)
        assert run.main(command + ["--resume", "--export-rate", "50"]) == 130
    assert "run the same command again: the finished run's files are unchanged" in capsys.readouterr().err
    assert snapshot(tmp_path / "done") == before
    real = device_module.compute_environment
    monkeypatch.setattr(device_module, "compute_environment", lambda where: {**real(where), "torch": "0.0-other"})
    assert run.main(command + ["--resume", "--export-rate", "50"]) == 0
    assert "the export will not match one the run itself had written bit for bit" in capsys.readouterr().err


def test_sigterm_stops_a_run_as_ctrl_c_does_and_it_resumes(runs):
    """Batch schedulers end jobs with SIGTERM; the run died without a word (its checkpoint survived)."""
    root = runs["root"]
    script = INTERRUPT_AFTER_FRAME_4.replace("signal.SIGINT)\n    return", "signal.SIGTERM)\n    return")
    assert "signal.SIGTERM" in script
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    stopped = subprocess.run([sys.executable, "-c", script, "--data", "room", "--out", "terminated", *CHEAP], cwd=root,
                             env=env, capture_output=True, text=True, timeout=120)
    assert stopped.returncode == 130 and "interrupted with 4 of 10 frames done" in stopped.stderr, stopped.stderr
    assert run.load_checkpoint(root / "terminated" / "checkpoint.pt").done == 4
    resumed = cli("run", "--data", "room", "--out", "terminated", *CHEAP, "--resume", cwd=root)
    assert resumed.returncode == 0, resumed.stderr
    assert (root / "terminated" / "trajectory.txt").read_bytes() == (runs["planted"] / "trajectory.txt").read_bytes()


def test_eval_mesh_cull_like_a_run_gives_the_runs_reconstruction_numbers(runs):
    """metrics.json's reconstruction numbers could be reproduced only from Python (eval mesh does not
    cull); --cull-like OUT reads the run's config.json and culls and samples as the run did.  mesh.ply
    holds float32 vertices (about 1e-7 m at a few metres), the run scored its float64 mesh: equal to
    a micrometre, and the ratio to a few of the 50,000 samples."""
    root = runs["root"]
    with_mesh = [argument for argument in CHEAP if argument != "--no-mesh"]
    assert cli("run", "--data", "room", "--out", "meshed", *with_mesh, "--seed", "3", cwd=root).returncode == 0
    metrics = json.loads((root / "meshed" / "metrics.json").read_text())
    assert metrics["sampling_seed"] == 3 and metrics["culling"]["cameras"] == 5
    result = cli("eval", "mesh", "meshed/mesh.ply", "room/gt_mesh.ply", "--cull-like", "meshed", "--json", cwd=root)
    assert result.returncode == 0, result.stderr
    scored = json.loads(result.stdout)
    for key, tolerance in (("accuracy_m", 1e-6), ("completion_m", 1e-6), ("completion_ratio", 3 / 50_000)):
        assert scored[key] == pytest.approx(metrics[key], abs=tolerance), key
    assert scored["n_points"] == metrics["n_points"] == 50_000 and scored["sampling_seed"] == 3
    zero = cli("eval", "mesh", "meshed/mesh.ply", "room/gt_mesh.ply", "--cull-like", "meshed", "--seed", "0", "--json",
               cwd=root)
    assert zero.returncode == 0 and json.loads(zero.stdout)["sampling_seed"] == 0  # an explicit 0 is not "unset"
    plain = json.loads(cli("eval", "mesh", "meshed/mesh.ply", "room/gt_mesh.ply", "--json", cwd=root).stdout)
    assert plain["accuracy_m"] > 2 * metrics["accuracy_m"]  # unculled: the whole box's surface against the seen part
    refused(cli("eval", "mesh", "meshed/mesh.ply", "room/gt_mesh.ply", "--cull-like", "room", cwd=root),
            "--cull-like room: no config.json there")
    # the data moved since the run (its config.json records the old place): named, and --data reads it
    shutil.copytree(root / "meshed", root / "moved")
    saved = json.loads((root / "moved" / "config.json").read_text())
    saved["data"]["path"] = str(root / "room_before_moving")
    (root / "moved" / "config.json").write_text(json.dumps(saved))
    refused(cli("eval", "mesh", "moved/mesh.ply", "room/gt_mesh.ply", "--cull-like", "moved", cwd=root),
            f"the data folder its config.json records ({root / 'room_before_moving'}) cannot be read", "--data")
    again = cli("eval", "mesh", "moved/mesh.ply", "room/gt_mesh.ply", "--cull-like", "moved", "--data", "room",
                "--json", cwd=root)
    assert again.returncode == 0 and json.loads(again.stdout) == scored, again.stderr
    refused(cli("eval", "mesh", "moved/mesh.ply", "room/gt_mesh.ply", "--data", "room", cwd=root),
            "--data names the data of the run given by --cull-like")
    # earlier versions recorded --data as typed: relative to where that run started, so the same command
    # scored against whatever folder of that name the current directory held
    saved["data"]["path"] = "room"
    (root / "moved" / "config.json").write_text(json.dumps(saved))
    refused(cli("eval", "mesh", "moved/mesh.ply", "room/gt_mesh.ply", "--cull-like", "moved", cwd=root),
            "records the data folder as 'room', relative to wherever that run started", "pass --data")


def test_resume_naming_the_device_the_run_used_is_not_refused(runs, tmp_path, monkeypatch, capsys):
    """A run started with the default --device auto (the CPU here) was refused on --resume --device cpu
    ("device was auto"): the device actually used is compared, as part of the environment."""
    _interrupted_beside_its_data(runs, tmp_path)
    monkeypatch.chdir(tmp_path)
    assert run.main([*CHEAP, "--data", "room", "--out", "stopped", "--resume", "--device", "cpu"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert (tmp_path / "stopped" / "trajectory.txt").read_bytes() == (runs["planted"] / "trajectory.txt").read_bytes()


def test_a_view_past_the_maps_box_is_warned_about_once_and_recorded(capsys):
    """A tracked frame whose measured surface lies mostly outside the map's box: one warning naming
    the frame, its share and the box, however many frames follow; metrics.json's summary (hand-made
    log: the largest share, its frame, the frames over the warning share)."""
    from types import SimpleNamespace

    from tsslam_ref.run_outputs import advance
    from tsslam_ref.run_summaries import outside_box_summary

    state = SimpleNamespace(log=[], field=SimpleNamespace(bound=torch.tensor([[-0.6, 3.0], [-1.0, 1.0], [0.0, 2.5]])),
                            cfg=config_module.load("tum-cpu"), done=1)
    reached = {}
    for frame, share in enumerate([0.02, 0.1, 0.48, 1.0, 0.3]):
        state.log.append({"frame": frame + 1, "tracking_loss": 1.0, "outside_box": share})
        state.done += 1
        advance(None, state, reached)
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning")]
    assert len(warnings) == 1, warnings
    assert warnings[0].startswith("warning: frame 3: 48 % of its measured surface lies outside the map's box")
    assert "[-0.60, 3.00], [-1.00, 1.00], [0.00, 2.50] m, set from frame 0's view" in warnings[0]
    assert "--set 'field.bound=" in warnings[0]
    assert outside_box_summary(state.log) == {"outside_box": {"max_share": 1.0, "frame": 4, "frames_over_warning": 3,
                                                              "warning_share": 0.25}}  # README: over 25 %
    straddling = [{"frame": 1, "tracking_loss": 1.0, "outside_box": 0.22},
                  {"frame": 2, "tracking_loss": 1.0, "outside_box": 0.27}]
    assert outside_box_summary(straddling)["outside_box"]["frames_over_warning"] == 1
    assert outside_box_summary([{"frame": 1, "tracking_loss": 1.0}]) == {}  # a log from before the record


def test_with_tracking_ahead_of_mapping_each_frame_done_is_checked_for_the_box(capsys):
    """With --parallel the loop reports a frame done while tracking has logged frames past it; the
    check read the newest entry, so a frame over the share was never looked at when a later one was
    under it.  Oracle: the hand-made log, frame 2 over the share, frames up to 6 tracked."""
    from types import SimpleNamespace

    from tsslam_ref.run_outputs import advance

    shares = {1: 0.0, 2: 0.6, 3: 0.0, 4: 0.0, 5: 0.0, 6: 0.0}
    state = SimpleNamespace(log=[{"frame": frame, "tracking_loss": 1.0, "outside_box": share}
                                 for frame, share in shares.items()],
                            field=SimpleNamespace(bound=torch.tensor([[-1.0, 1.0]] * 3)), cfg=config_module.load("tum-cpu"))
    reached = {}
    for done in (2, 3, 4):  # frames 1, 2 and 3 mapped, one at a time
        state.done = done
        advance(None, state, reached)
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning")]
    assert len(warnings) == 1 and warnings[0].startswith("warning: frame 2: 60 %"), warnings


def test_a_finished_run_records_its_largest_share_outside_the_box(runs):
    """metrics.json's outside_box is the largest of the per-frame shares the loop logged (read back
    from the run's last checkpoint, which holds every frame's log entry)."""
    metrics = json.loads((runs["planted"] / "metrics.json").read_text())
    state = run.load_checkpoint(runs["planted"] / "checkpoint.pt")
    logged = [(entry["outside_box"], entry["frame"]) for entry in state.log]
    assert len(logged) == metrics["frames"] - 1  # every frame but frame 0, which is not tracked
    assert all(0.0 <= share <= 1.0 for share, _ in logged)
    assert (metrics["outside_box"]["max_share"], metrics["outside_box"]["frame"]) == max(logged)
