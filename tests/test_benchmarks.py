"""benchmarks/bench_system.py --against: a run compared with a stored table of the same runs; and
benchmarks/bench_mesh.py's check that the chunked grid query gives the whole grid's mesh.

The oracles are hand-made rows whose verdicts are known (equal numbers, a mean inside, below or
above the stored seeds' range), a real command line that must be refused before any run, and the
mesh of the grid held whole (the PLY bytes of both ways must be equal).
"""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[1]
STORED_TEDDY = ROOT / "tsslam_ref" / "assets" / "results" / "teddy_tum-cpu_3seeds.json"
STORED_FR2 = ROOT / "tsslam_ref" / "assets" / "results" / "fr2_desk_synthetic-cpu_3seeds.json"
STORED_FR2_ABLATIONS = ROOT / "tsslam_ref" / "assets" / "results" / "fr2_desk_synthetic-cpu_ablations_3seeds.json"


def _bench_system():
    spec = importlib.util.spec_from_file_location("bench_system", ROOT / "benchmarks" / "bench_system.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(ate, rpe, fps=1.0, tracking_ms=25.0):
    return {"ate_cm": ate, "rpe_cm": rpe, "rpe_deg": 0.5, "wall_fps": fps,
            "runtime": {"tracking": {"ms_per_iteration": tracking_ms, "iterations_per_call": 20}}}


def test_spread_verdicts_against_the_stored_seeds():
    bench = _bench_system()
    stored = [_row(5.0, 0.40), _row(6.6, 0.46), _row(5.6, 0.86)]
    assert bench.spread_verdict([_row(5.0, 0.40), _row(6.6, 0.46), _row(5.6, 0.86)], stored, "ate_cm") == "identical"
    # the same mean from other per-seed numbers is not "identical"
    assert bench.spread_verdict([_row(5.6, 0.4), _row(6.0, 0.4), _row(5.6, 0.4)], stored, "ate_cm") == "inside"
    assert bench.spread_verdict([_row(4.0, 0.4)] * 3, stored, "ate_cm") == "below"
    assert bench.spread_verdict([_row(7.0, 0.4)] * 3, stored, "ate_cm") == "above"
    assert bench.spread_verdict([_row(5.0, 0.87)] * 3, stored, "rpe_cm") == "above"
    assert bench.spread_verdict([_row(5.0, 0.40)] * 3, stored, "rpe_cm") == "inside"  # the range's ends count


def test_adaptive_speed_line_divides_the_two_rows_of_one_run():
    bench = _bench_system()
    results = {"TS-SLAM": {"mean": {"wall_fps": 0.80}}, bench.ADAPTIVE: {"mean": {"wall_fps": 0.60}}}
    line = bench.adaptive_speed_line(results)
    assert line.startswith(f"{bench.ADAPTIVE} / TS-SLAM: frames/s x0.75 ") and "0.60 against 0.80" in line
    assert bench.adaptive_speed_line({"TS-SLAM": results["TS-SLAM"]}) == ""  # no adaptive row
    assert bench.adaptive_speed_line(dict(results, **{"TS-SLAM": {"mean": {"failed": "x"}}})) == ""


def test_comparison_table_rows_rss_and_environment():
    bench = _bench_system()
    environment = {"torch": "2.13.0+cpu", "device": "cpu", "cpu_capability": "AVX2", "threads": 2}
    stored = {"settings": {"environment": environment},
              "results": {"TS-SLAM": {"rows": [_row(5.0, 0.4, 0.70, 26.0), _row(6.0, 0.5, 0.72, 24.0)]},
                          "Co-SLAM (baseline)": {"rows": [_row(4.7, 1.0)]}},
              "peak_rss_mib": 900.0}
    results = {"TS-SLAM": {"rows": [_row(5.0, 0.4, 0.90, 20.0), _row(6.0, 0.5, 0.94, 22.0)]},
               "TS-SLAM dt=0.15 s": {"rows": [_row(5.0, 0.4)]}}  # not stored: named, no row
    lines = bench.comparison_lines(results, stored, environment, 812.4)
    table = [line for line in lines if line.startswith("| TS-SLAM")]
    assert len(table) == 1, lines
    cells = [cell.strip() for cell in table[0].strip("|").split("|")]
    assert cells[1] == "5.500 / 5.000 / 6.000" and cells[2] == "0.450 / 0.400 / 0.500", cells
    assert cells[3] == "identical, identical"
    assert cells[4] == "0.92 / 0.71"  # mean frames/s now / stored
    assert cells[5] == "21 / 25"  # tracking ms per iteration, means
    assert cells[6] == "-" and cells[7] == "-"  # stages neither side ran
    assert "not in the stored file: TS-SLAM dt=0.15 s" in lines
    assert any("812 MiB now, 900 MiB stored" in line for line in lines)
    other = dict(environment, cpu_capability="AVX512")
    assert any(line.startswith("environment differs") for line in bench.comparison_lines(results, stored, other, 1.0))
    # which code wrote the stored file: named when it is not this code, nothing when it is
    now = f"now {bench.source_version()}"
    assert ("code: the stored file does not record which code wrote it (an earlier version); now tsslam_ref "
            f"{bench.source_version()}") in lines
    stored["settings"]["tsslam_ref"] = "0.1.0, source 0123456789ab"
    assert f"code: stored by tsslam_ref 0.1.0, source 0123456789ab, {now}" in bench.comparison_lines(
        results, stored, environment, 1.0)
    stored["settings"]["tsslam_ref"] = bench.source_version()
    assert not any(line.startswith("code:") for line in bench.comparison_lines(results, stored, environment, 1.0))


def test_the_runtime_table_averages_every_column_over_the_seeds():
    """Three seeds' tracking at 102, 66 and 62 ms: the row shows their mean (it showed seed 0's
    beside the seeds' mean frames/s), and a stage one seed lacks is averaged over those that ran it."""
    bench = _bench_system()
    rows = [_row(5.0, 0.4, tracking_ms=ms) for ms in (102.0, 66.0, 62.0)]
    rows[0]["runtime"]["lba_init"] = {"ms_per_iteration": 18.0, "iterations_per_call": 9.0}
    runtime = bench.mean_runtime(rows)
    assert runtime["tracking"] == {"ms_per_iteration": (102.0 + 66.0 + 62.0) / 3, "iterations_per_call": 20.0}
    assert runtime["lba_init"] == {"ms_per_iteration": 18.0, "iterations_per_call": 9.0}
    assert bench.runtime_line("TS-SLAM", runtime).startswith("| TS-SLAM | 77 x 20 | 18 x 9 | - |")


def test_environment_lines_name_what_differs_and_a_map_path_a_stored_file_did_not_record():
    bench = _bench_system()
    stored = {"torch": "2.13.0+cpu", "device": "cpu", "cpu_capability": "AVX2", "threads": 2}
    compiled = dict(stored, map_kernels={"hash_grid": "compiled", "oneblob": "compiled"})
    assert bench.environment_lines(stored, compiled) == []  # a file from before the record: nothing to say
    assert bench.environment_lines(compiled, compiled) == []
    pytorch = dict(stored, map_kernels={"hash_grid": "pytorch", "oneblob": "pytorch"})
    for lines in (bench.environment_lines(stored, pytorch), bench.environment_lines(compiled, pytorch)):
        assert len(lines) == 1 and lines[0].startswith("environment differs (map_kernels: stored ") and "pytorch" in lines[0]
    (line,) = bench.environment_lines(stored, dict(compiled, threads=1))
    assert "threads: stored 2, now 1" in line and "map_kernels" not in line


def test_against_compares_the_data_fingerprint_where_the_stored_file_has_one(tmp_path):
    """Two folders of one name at another image size are told apart by the fingerprint; a stored
    file without one (written before it was recorded) is compared and the closing lines say how."""
    from tsslam_ref import data

    bench = _bench_system()
    sequence = data.load_sequence(data.default_sequence_path(), frame_stop=4)
    smaller = data.load_sequence(data.default_sequence_path(), frame_stop=4, resize_width=80)
    settings = {"preset": "tum-cpu", "sequence": sequence.name, "frames": 4, "frame_range": "0:4", "seeds": [0],
                "ablation_seeds": [0], "data_fingerprint": bench.data_fingerprint(sequence)}
    assert bench.data_fingerprint(smaller) != settings["data_fingerprint"]
    assert bench.data_fingerprint(data.load_sequence(data.default_sequence_path(), frame_stop=4)) == \
        settings["data_fingerprint"]  # the same folder read again
    stored = {"settings": dict(settings), "results": {}}
    path = tmp_path / "stored.json"
    path.write_text(json.dumps(stored))
    with pytest.raises(ValueError, match="data_fingerprint"):
        bench.load_stored(str(path), dict(settings, data_fingerprint=bench.data_fingerprint(smaller)))
    del stored["settings"]["data_fingerprint"]
    path.write_text(json.dumps(stored))
    assert bench.load_stored(str(path), settings) == stored
    assert any("does not record the data's fingerprint" in line for line in bench.comparison_lines({}, stored, {}, 1.0))


def test_against_a_file_of_other_frames_is_refused_before_any_run(tmp_path):
    """The shipped teddy table has 100 frames; a 10-frame run is not the same runs: refused up
    front, naming the file, the setting and both values, and no --json file is written."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = [sys.executable, str(ROOT / "benchmarks" / "bench_system.py"), "--frames", "0:10",
               "--json", str(tmp_path / "rows.json")]
    for against, needles in ((STORED_TEDDY, ("--against", str(STORED_TEDDY), "frames is 100", "is 10")),
                             (tmp_path / "missing.json", ("--against", "missing.json", "cannot read"))):
        result = subprocess.run(command + ["--against", str(against)], cwd=tmp_path, env=env,
                                capture_output=True, text=True, timeout=300)
        assert "Traceback" not in result.stderr, result.stderr
        assert result.returncode == 2, (result.returncode, result.stderr)
        message = result.stderr.strip().splitlines()[-1]
        for needle in needles:
            assert needle in message, message
        assert not (tmp_path / "rows.json").exists()


def test_the_shipped_tables_have_what_the_comparison_reads():
    """The shipped tables load as --against files for their own settings, with three seeds of
    every row (the ablation table: the README's ten rows), and carry no path of the machine that
    wrote them."""
    bench = _bench_system()
    ablation_rows = ("w/o B-S.", "w/o DR", "w/o LBA", "+ LBA joint stage", "paper schedule",
                     "TS-SLAM dt=0.15 s", "TS-SLAM dt=0.45 s")
    for path, preset, extra in ((STORED_TEDDY, "tum-cpu", ()), (STORED_FR2, "synthetic-cpu", ()),
                                (STORED_FR2_ABLATIONS, "synthetic-cpu", ablation_rows)):
        stored = json.loads(path.read_text())
        assert stored["settings"]["preset"] == preset and stored["settings"]["seeds"] == [0, 1, 2]
        assert bench.load_stored(str(path), dict(stored["settings"])) == stored
        assert not Path(stored["settings"]["data"]).is_absolute()
        for name in ("TS-SLAM", "Co-SLAM (baseline)") + extra:
            rows = stored["results"][name]["rows"]
            assert len(rows) == 3 and all({"ate_cm", "rpe_cm", "wall_fps", "runtime"} <= set(row) for row in rows)
        if extra:  # the offline control is no SLAM run: accuracy only
            rows = stored["results"]["Co-SLAM + spline fit (offline control)"]["rows"]
            assert len(rows) == 3 and all({"ate_cm", "rpe_cm", "rpe_deg"} <= set(row) for row in rows)


def _curve_floor():
    spec = importlib.util.spec_from_file_location("curve_floor", ROOT / "benchmarks" / "curve_floor.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_curve_floor_scores_an_exactly_representable_motion_as_exact():
    """benchmarks/curve_floor.py on a screw motion (constant angular and linear velocity, written
    with scipy's rotations): every cumulative spline of uniform steps holds it exactly, so each
    layout's RPE is ~0, and the frame-to-frame rotation is the rate over the frame rate."""
    import numpy as np
    import torch
    from scipy.spatial.transform import Rotation

    from tsslam_ref.config import SplineConfig

    curve_floor = _curve_floor()
    fps, rate_deg, speed = 30.0, 45.0, 0.4
    times = np.arange(60) / fps
    truth = np.tile(np.eye(4), (60, 1, 1))
    truth[:, :3, :3] = Rotation.from_rotvec(np.outer(np.radians(rate_deg) * times, [0.3, -0.5, 0.8])
                                            / np.linalg.norm([0.3, -0.5, 0.8])).as_matrix()
    truth[:, :3, 3] = np.outer(speed * times, [1.0, 0.5, -0.2])
    assert abs(curve_floor.median_frame_rotation_deg(truth) - rate_deg / fps) < 1e-9
    truth = torch.as_tensor(truth)
    rows = curve_floor.curve_rows(times, truth, truth.clone(), [0.30, 0.10], SplineConfig())
    assert [name for name, _, _ in rows] == ["uniform 0.30 s", "uniform 0.10 s", "adaptive"]
    for _, _, rpe in rows:
        assert rpe["rpe_rot_rmse_deg"] < 1e-4 and rpe["rpe_trans_rmse_m"] < 1e-6
    # A 7 Hz tremor of amplitude A (deg) about one axis on top of it: far above what 0.30 s knots
    # can follow, so the fit keeps the smooth motion and its rotational RPE is the tremor's own
    # frame-to-frame change, RMS = A * 2 sin(pi f / fps) / sqrt(2) (0.95 A at 7 Hz, 30 Hz).
    amplitude, frequency = 0.2, 7.0
    tremor = Rotation.from_rotvec(np.outer(np.radians(amplitude) * np.sin(2 * np.pi * frequency * times), [1, 0, 0]))
    trembling = truth.clone()
    trembling[:, :3, :3] = torch.as_tensor((Rotation.from_matrix(truth[:, :3, :3].numpy()) * tremor).as_matrix())
    expected = amplitude * 2 * np.sin(np.pi * frequency / fps) / np.sqrt(2)
    (_, _, rpe), = curve_floor.curve_rows(times, trembling, trembling.clone(), [0.30], SplineConfig())[:1]
    assert abs(rpe["rpe_rot_rmse_deg"] - expected) < 0.1 * expected, (rpe["rpe_rot_rmse_deg"], expected)


def test_bench_mesh_chunked_and_whole_grid_give_the_same_mesh():
    """Both ways of querying the grid, each in its own process, must write the same PLY bytes
    (the script exits 1 and says DIFFER otherwise).  At 0.1 m the grid has 144,522 points, three
    65,536-point chunks, so the chunk boundaries are crossed."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_mesh.py"), "--voxel", "0.1",
                             "--fit-iters", "2", "--repeats", "1"], env=env, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "PLY bytes: identical in every run" in result.stdout
    assert "chunked / whole (medians)" in result.stdout


@pytest.mark.parametrize("script, arguments, needle", [
    ("bench_mesh.py", ["--voxel", "9", "--fit-iters", "1", "--repeats", "1"], "smaller than voxel_size 9.0 m"),  # hung
    ("bench_mesh.py", ["--voxel", "0"], "--voxel 0"),
    ("bench_spline.py", ["--n", "0"], "--n 0"),
    ("bench_spline.py", ["--n-ctrl", "2"], "--n-ctrl 2"),
    ("bench_field.py", ["--repeats", "0"], "--repeats 0"),
    ("bench_field.py", ["--presets", "nosuch"], "nosuch"),
    ("profile_step.py", ["--threads", "0"], "--threads 0"),
    ("profile_step.py", ["--preset", "replica"], "invalid choice: 'replica'"),  # offered, then a traceback
    ("profile_step.py", ["--top", "-2"], "--top -2"),
    ("profile_step.py", ["--fit-iters", "-5"], "--fit-iters -5"),
    ("bench_spline.py", ["--n", "1", "--n-ctrl", "100"], "--n 1 must be at least --n-ctrl - 2 = 98"),
    ("curve_floor.py", ["--dts", "nan"], "--dts nan"),
    ("curve_floor.py", ["--dts", "inf"], "--dts inf"),
    ("curve_floor.py", ["--noise", "-1"], "--noise -1"),
    ("curve_floor.py", ["--seed", "-1"], "--seed -1"),  # was numpy's traceback
    ("tracking_floor.py", ["--preset", "bogus"], "config 'bogus'"),  # were tracebacks
    ("tracking_floor.py", ["--try", "tracking.iters=0"], "tracking.iters = 0"),
    ("tracking_floor.py", ["--try", "mapping.iters=5"], "mapping.iters is not a setting of tracking, render, loss"),
    ("gpu_check.py", ["--device", "cpu", "--frames", "0:2", "--json", "check.json"], "selects 2 frame(s)"),
    ("gpu_check.py", ["--device", "cpu", "--frames", "0:1000"], "stop=1000 is beyond the 100 usable frames"),
    ("gpu_check.py", ["--device", "cpu", "--seeds", "-1"], "--seeds -1"),  # were tracebacks after the first runs
    ("gpu_check.py", ["--device", "cpu", "--json", "taken.txt/check.json"], "is a file, not a folder"),
    ("bench_system.py", ["--frames", "6:2"], "--frames '6:2'"),
    ("bench_system.py", ["--skip", "baseline", "tsslam"], "leaves nothing to run"),
    ("bench_system.py", ["--seeds", "0", "-1"], "--seeds -1"),  # were tracebacks after the first runs
    ("bench_system.py", ["--ablations", "--dts", "0"], "--dts 0"),
    ("bench_system.py", ["--ablation-seeds", "-2"], "--ablation-seeds -2"),
    ("bench_system.py", ["--json", "no_such_folder/rows.json"], "the folder no_such_folder does not exist"),
])
def test_benchmarks_refuse_bad_arguments_in_one_line(tmp_path, script, arguments, needle):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    (tmp_path / "taken.txt").write_text("a user's file")  # the --json under a file
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *arguments], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert needle in result.stderr.strip().splitlines()[-1], result.stderr


def test_tracking_floor_scores_a_shortened_path_by_its_scale_and_lag():
    """benchmarks/tracking_floor.py's row figures on a path whose error is known by construction:
    the ground truth itself scores 0 cm and scale 1; the same path shrunk about frame 0 by 1/1.25
    (a tracker that stops short) scores a Sim(3) scale of 1.25 and a negative along-path error of
    the mean shortfall, (1 - 1/1.25) x the mean distance travelled."""
    import numpy as np

    spec = importlib.util.spec_from_file_location("tracking_floor", ROOT / "benchmarks" / "tracking_floor.py")
    tracking_floor = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tracking_floor)
    times = np.arange(30) / 30.0
    truth = np.tile(np.eye(4), (30, 1, 1))
    truth[:, :3, 3] = np.outer(times, [0.6, -0.2, 0.1]) + np.outer(np.sin(4 * times), [0.0, 0.1, 0.05])
    sequence = SimpleNamespace(timestamps=times)

    exact = tracking_floor.scores(sequence, truth, truth)
    assert max(exact["ate_cm"], exact["rpe_cm"], exact["rpe_deg"], abs(exact["along_cm"])) < 1e-9
    assert abs(exact["scale"] - 1.0) < 1e-9
    short = truth.copy()
    short[:, :3, 3] = truth[0, :3, 3] + (truth[:, :3, 3] - truth[0, :3, 3]) / 1.25
    shortened = tracking_floor.scores(sequence, truth, short)
    travelled = np.linalg.norm(truth[1:, :3, 3] - truth[0, :3, 3], axis=1)
    assert abs(shortened["scale"] - 1.25) < 1e-6 and shortened["ate_cm"] > 0.5
    assert abs(shortened["along_cm"] - 100 * -(1 - 1 / 1.25) * travelled.mean()) < 1e-9
    assert tracking_floor.table_cells(shortened).count("|") == 4  # five cells of the printed row


def test_tracking_floor_tracks_every_setting_on_the_same_rays_with_its_own_loss_settings(monkeypatch):
    """--try rows drew their rays from the generator that also drew the depth samples (a setting with
    fewer samples got other rays from frame 2 on), and every row used the preset's render and loss
    settings whatever --try said.  Oracle: what ``track_frame`` is handed, recorded."""
    import torch

    from tsslam_ref import config, data
    from tsslam_ref.device import frame_to_device

    spec = importlib.util.spec_from_file_location("tracking_floor", ROOT / "benchmarks" / "tracking_floor.py")
    tracking_floor = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tracking_floor)
    sequence = data.load_sequence(data.default_sequence_path(), frame_stop=4)
    frames = [frame_to_device(sequence[i], torch.device("cpu"), torch.float32) for i in range(4)]
    truth = torch.eye(4).repeat(4, 1, 1)
    handed = []

    def recording_track_frame(field, rays, init, tracking, settings, generator=None):
        handed.append((rays.directions_cam.clone(), settings.render.n_samples, settings.loss.sdf_weight))
        torch.rand(settings.render.n_samples * 100, generator=generator)  # draws as many numbers as it samples
        return SimpleNamespace(pose=init)

    monkeypatch.setattr(tracking_floor, "track_frame", recording_track_frame)
    base = config.tum_cpu()
    for cfg in (base, config.apply_overrides(base, ["render.n_samples=4", "loss.sdf_weight=7"])):
        tracking_floor.track_all(SimpleNamespace(field=None), cfg, frames, truth)
    preset, changed = handed[:6], handed[6:]
    assert all(torch.equal(a[0], b[0]) for a, b in zip(preset, changed))  # frames 1-3, both starts
    assert {row[1:] for row in preset} == {(base.render.n_samples, base.loss.sdf_weight)}
    assert {row[1:] for row in changed} == {(4, 7.0)}


def test_a_set_is_announced_as_changing_every_row_the_baselines_too(monkeypatch, capsys):
    """``--set spline.knots=adaptive`` runs the baseline and the TS-SLAM row with it, under their usual
    names; the header says so and points to --adaptive (which adds its own row)."""
    module = _bench_system()
    ran = []
    monkeypatch.setattr(module, "run_once", lambda sequence, cfg: ran.append((cfg.method, cfg.spline.knots))
                        or {"failed": "not run in this test"})
    monkeypatch.setattr(sys, "argv", ["bench_system.py", "--frames", "0:6", "--seeds", "0", "--threads", "1",
                                      "--set", "spline.knots=adaptive"])
    module.main()
    out = capsys.readouterr().out
    assert ran == [("coslam", "adaptive"), ("tsslam", "adaptive")]
    assert "--set on every row: spline.knots=adaptive (--adaptive adds an adaptive-knots row instead)" in out, out


def test_a_folder_of_ones_own_is_read_as_run_reads_it(tmp_path, monkeypatch):
    """With a preset, ``run --data`` takes the folder's layout and its own depth scale; the benchmark
    kept the preset's (``tum``, 5000) and refused a folder whose calibration file says 1000."""
    from tsslam_ref import data

    folder = tmp_path / "mine"
    shutil.copytree(data.default_sequence_path(), folder)
    calibration = json.loads((folder / "intrinsics.json").read_text())
    (folder / "intrinsics.json").write_text(json.dumps(dict(calibration, depth_scale=1000.0)))
    module = _bench_system()
    seen = []
    monkeypatch.setattr(module, "run_once", lambda sequence, cfg: seen.append(sequence.depth_scale)
                        or {"failed": "not run in this test"})
    monkeypatch.setattr(sys, "argv", ["bench_system.py", "--data", str(folder), "--frames", "0:6", "--seeds", "0",
                                      "--threads", "1", "--skip", "baseline"])
    module.main()
    assert seen == [1000.0]



def test_a_system_without_a_resident_memory_figure_still_gets_its_table(monkeypatch, capsys, tmp_path):
    """``device.peak_memory`` has no ``peak_rss_mib`` where Python lacks ``resource`` (Windows): the
    benchmark ended with a KeyError after all its runs, before the table and the JSON file."""
    module = _bench_system()
    monkeypatch.setattr(module, "run_once", lambda sequence, cfg: {"failed": "not run in this test"})
    monkeypatch.setattr(module, "peak_memory", lambda device: {})
    monkeypatch.setattr(sys, "argv", ["bench_system.py", "--frames", "0:6", "--seeds", "0", "--threads", "1",
                                      "--skip", "baseline", "--json", str(tmp_path / "rows.json")])
    module.main()
    assert "peak RSS of this process (all runs above): not measured" in capsys.readouterr().out
    assert json.loads((tmp_path / "rows.json").read_text())["peak_rss_mib"] is None


def test_a_tsslam_row_carries_the_spline_offsets_of_its_run():
    """run_once on 8 bundled frames (tiny preset): a TS-SLAM row holds its run's spline offsets (RMS cm
    and deg, as metrics.json), which the loop logged for each of the 7 tracked frames; a Co-SLAM row,
    with no spline, holds none."""
    from tsslam_ref import config, data

    bench = _bench_system()
    sequence = data.load_sequence(data.default_sequence_path(), frame_stop=8)
    rows = {method: bench.run_once(sequence, config.apply_overrides(config.tiny(), [f"method={method}", "seed=0"]))
            for method in ("coslam", "tsslam")}
    assert "spline_offset_cm" not in rows["coslam"] and "spline_offset_deg" not in rows["coslam"]
    assert 0.0 < rows["tsslam"]["spline_offset_cm"] < 5.0 and 0.0 < rows["tsslam"]["spline_offset_deg"] < 5.0
