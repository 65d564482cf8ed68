"""benchmarks/gpu_check.py, the script kept for the day a GPU is lent: its pieces on the CPU.

Without a GPU the script's CUDA path cannot run here, but everything around it can: the kernel
comparison (the map's two paths on the CPU agree to rounding, one path with itself exactly), the pose distances it reports (oracle: a known
offset and turn), its pass rule for the runs (hand-made ATEs whose verdict is known) and its
refusals of bad input before any work.  A full dry run is `python benchmarks/gpu_check.py --device
cpu` (about a minute at `--frames 0:3 --seeds 0`).
"""

import dataclasses
import importlib
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tsslam_ref import config
from tsslam_ref.geometry import so3_exp

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def gpu_check(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # the script imports bench_field beside it
    return importlib.import_module("gpu_check")


def test_the_kernel_comparison_on_the_cpu_compares_the_two_map_paths_and_the_point_gradient(gpu_check):
    """The dry run compared the compiled kernel with itself (0.0), which could not catch a fault of
    the PyTorch path a GPU takes, and left out the points' gradient that tracking and BA use."""
    report = {}
    assert gpu_check.check_kernels(config.load("tum-cpu"), torch.device("cpu"), report)
    kernels = report["kernels"]
    field = kernels["field_relative_difference"]
    assert kernels["passed"] and {"rgb", "sdf", "grad points", "grad grid.table"} <= set(field), field
    assert 0.0 < max(field.values()) <= gpu_check.FLOAT32_TOLERANCE  # two paths, rounding apart
    assert max(kernels["spline_relative_difference"].values()) == 0.0
    same_path = dataclasses.replace(config.load("tum-cpu").field, compiled_kernel=False, compiled_oneblob=False)
    cfg = config.load("tum-cpu")
    cfg.field = same_path
    assert max(gpu_check.field_agreement(cfg, torch.device("cpu")).values()) == 0.0  # one path: equal


def test_pose_agreement_reports_a_known_offset_and_turn(gpu_check):
    poses = np.tile(np.eye(4), (5, 1, 1))
    moved = poses.copy()
    moved[2, :3, 3] = [0.03, 0.0, 0.04]  # 5 cm at one frame
    moved[4, :3, :3] = so3_exp(torch.tensor([0.0, 0.0, np.deg2rad(2.0)], dtype=torch.float64)).numpy()
    match = gpu_check.agreement(poses, moved)
    assert match["max_position_cm"] == pytest.approx(5.0)
    assert match["rms_position_cm"] == pytest.approx(np.sqrt(25.0 / 5))
    assert match["max_rotation_deg"] == pytest.approx(2.0, abs=1e-9)


@pytest.mark.parametrize("device_ates, passes", [((1.4, 1.9), True), ((1.6, 2.1), False)])
def test_the_run_check_allows_the_cpu_seed_range_plus_the_tolerance(gpu_check, monkeypatch, device_ates, passes):
    """CPU ATEs 1.0 and 1.2 cm (range 0.2) with 0.5 cm tolerance allow a mean difference of 0.7 cm:
    device means 1.65 (difference 0.55) pass, 1.85 (0.75) do not."""
    cpu_ates = {0: 1.0, 1: 1.2}
    device_by_seed = dict(zip((0, 1), device_ates))
    calls = itertools.count()  # check_runs runs each seed on the CPU first, then on the device

    def fake_run(sequence, cfg, device):
        ate = device_by_seed[cfg.seed] if next(calls) % 2 else cpu_ates[cfg.seed]
        return {"poses": np.tile(np.eye(4), (3, 1, 1)), "ate_cm": ate, "rpe_cm": 0.1,
                "frames_per_second": 1.0, "runtime": {}}

    monkeypatch.setattr(gpu_check, "run_method", fake_run)
    report = {"methods": {}}
    assert gpu_check.check_runs(None, config.load("tum-cpu"), torch.device("cpu"), [0, 1], 0.5, report) is passes
    for method in ("tsslam", "coslam"):
        entry = report["methods"][method]
        assert entry["cpu_mean_ate_cm"] == pytest.approx(1.1)
        assert entry["allowed_difference_cm"] == pytest.approx(0.7)
        assert entry["passed"] is passes


def test_bad_input_is_refused_before_any_work(gpu_check, tmp_path, capsys):
    existing = tmp_path / "gpu_check.json"
    existing.write_text(json.dumps({"kept": True}))
    assert gpu_check.main(["--json", str(existing)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert json.loads(existing.read_text()) == {"kept": True}
    fresh = tmp_path / "fresh.json"
    assert gpu_check.main(["--json", str(fresh), "--device", "cpu", "--frames", "5:2"]) == 2
    assert "frames" in capsys.readouterr().err.lower()
    if not torch.cuda.is_available():
        assert gpu_check.main(["--json", str(fresh)]) == 2  # the default device, cuda, is not there
        assert "torch.cuda.is_available() is False" in capsys.readouterr().err
    assert not fresh.exists()
