"""timings.py and device.peak_memory: the runtime table and the peak memory that metrics.json reports.

Oracle: counts written out by hand, and the table's definition (ms per iteration = 1000 s / iterations).
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tsslam_ref.timings import Timings


def test_stage_counts_calls_iterations_and_time_and_skips_a_failed_body():
    timings = Timings()
    with timings.stage("global_ba", 20):
        time.sleep(0.01)
    with timings.stage("global_ba", 20):
        pass
    with timings.stage("tracking") as record:
        record.iterations = 7  # known only at the end of the body
    with pytest.raises(RuntimeError):
        with timings.stage("tracking", 3):
            raise RuntimeError("diverged")
    assert timings.calls == {"global_ba": 2, "tracking": 1}
    assert timings.iterations == {"global_ba": 40, "tracking": 7}
    assert timings.seconds["global_ba"] >= 0.01
    row = timings.table()["global_ba"]
    assert row["calls"] == 2 and row["iterations_per_call"] == 20
    assert row["ms_per_iteration"] == pytest.approx(1000.0 * timings.seconds["global_ba"] / 40)
    assert timings.table()["tracking"]["total_s"] == timings.seconds["tracking"]


def test_a_stage_without_iterations_reports_its_time_per_call_not_its_total():
    timings = Timings()
    for _ in range(3):
        with timings.stage("lba_init", 0):
            time.sleep(0.01)
    row = timings.table()["lba_init"]
    assert row["iterations_per_call"] == 0 and row["calls"] == 3
    assert row["ms_per_iteration"] == pytest.approx(1000.0 * timings.seconds["lba_init"] / 3)


PEAK_PROBE = """
import json, sys
import numpy as np
import torch
from tsslam_ref.device import peak_memory
from test_timings import _high_water_mib

before = (peak_memory(torch.device("cpu"))["peak_rss_mib"], _high_water_mib())
block = np.ones(256 * 2**17)  # 256 MiB of float64, every page touched
after = (peak_memory(torch.device("cpu"))["peak_rss_mib"], _high_water_mib())
print(json.dumps({"before": before, "after": after, "keys": sorted(peak_memory(torch.device("cpu")))}))
"""


def _high_water_mib() -> float:
    """This process's VmHWM from /proc/self/status, in MiB."""
    line = next(line for line in Path("/proc/self/status").read_text().splitlines() if line.startswith("VmHWM:"))
    return int(line.split()[1]) / 1024  # kB


def test_peak_memory_matches_the_kernels_high_water_mark_and_sees_a_new_peak():
    """device.peak_memory (getrusage) against an independent reader, Linux's /proc/self/status
    VmHWM, in a fresh process before and after it touches 256 MiB more.

    On Linux getrusage's peak also covers the image before exec: a process forked from this one
    starts with this process's high-water mark. So the oracle is max(VmHWM of the probe, VmHWM of
    this process), the latter read after the probe ended (it only grows)."""
    if not Path("/proc/self/status").exists():
        pytest.skip("needs Linux's /proc/self/status as the oracle")
    root = Path(__file__).resolve().parents[1]
    search_path = os.pathsep.join([str(root), str(root / "tests")])  # the package and this file's reader
    result = subprocess.run([sys.executable, "-c", PEAK_PROBE], env=dict(os.environ, PYTHONPATH=search_path),
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    parent = _high_water_mib()
    probe = json.loads(result.stdout.strip().splitlines()[-1])
    (before, before_own), (after, after_own) = probe["before"], probe["after"]
    assert after_own >= before_own + 250  # the oracle sees the new peak
    for reported, own in ((before, before_own), (after, after_own)):
        assert 0.98 * own <= reported <= 1.02 * max(own, parent), (reported, own, parent)
    assert after >= before
    if parent < before_own:  # a small parent (a shell, a small test process): the probe's own peak
        assert after == pytest.approx(after_own, rel=0.02)
    assert probe["keys"] == ["peak_rss_mib"]  # no GPU figure for a CPU device


PLOTS_PROBE = """
import json
from pathlib import Path
from types import SimpleNamespace
import numpy as np
import torch
from tsslam_ref import run_outputs
from test_timings import _high_water_mib

seen = {}

def plots_that_take_memory(out, *rest):
    block = np.ones(256 * 2**17)  # 256 MiB of float64, every page touched
    seen["during_plots"] = _high_water_mib()

run_outputs.save_plots = plots_that_take_memory
run_outputs.trajectory_metrics = lambda *args: {}
run_outputs.run_environment = lambda *args: {}
seen["before_plots"] = _high_water_mib()
camera = SimpleNamespace(fx=1.0, fy=1.0, cx=0.5, cy=0.5, width=2, height=2)
two_frames = type("Frames", (list,), {"name": "probe", "gt_poses": None, "intrinsics": camera,
                                      "depth_scale": 1000.0})([None, None])
plan = SimpleNamespace(args=SimpleNamespace(no_mesh=True, export_rate=None, checkpoint_every=0),
                       cfg=SimpleNamespace(method="tsslam", local_ba=SimpleNamespace(use_spline=False)),
                       sequence=two_frames, out=Path("."),
                       environment=None, device=torch.device("cpu"))
result = SimpleNamespace(timestamps=np.array([0.0, 0.1]), poses=np.repeat(np.eye(4)[None], 2, axis=0),
                         frames_per_second=1.0, frames_processed=2,
                         state=SimpleNamespace(timings=SimpleNamespace(table=lambda: {}), field=None, log=[]))
run_outputs.write_outputs(plan, result)
seen["reported"] = json.load(open("metrics.json"))["peak_rss_mib"]
print(json.dumps(seen))
"""


def test_the_reported_peak_memory_includes_the_plots(tmp_path):
    """metrics.json's ``peak_rss_mib`` is taken after everything a finished run does before writing
    it, the plots included: a stand-in for the plots touches 256 MiB more in a fresh process, and the
    reported peak must reach the high-water mark Linux's /proc/self/status showed inside them."""
    if not Path("/proc/self/status").exists():
        pytest.skip("needs Linux's /proc/self/status as the oracle")
    root = Path(__file__).resolve().parents[1]
    search_path = os.pathsep.join([str(root), str(root / "tests")])
    # Started by a shell that forks it (not by this process's vfork and exec), so the probe's peak
    # starts from the shell's few MiB, not from this test process's high-water mark.
    result = subprocess.run(["sh", "-c", '"$0" -c "$1"', sys.executable, PLOTS_PROBE],
                            env=dict(os.environ, PYTHONPATH=search_path), cwd=tmp_path, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    seen = json.loads(result.stdout.strip().splitlines()[-1])
    assert seen["during_plots"] >= seen["before_plots"] + 250  # the oracle sees the plots' peak
    assert seen["reported"] >= 0.98 * seen["during_plots"], seen
