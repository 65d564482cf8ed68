"""System benchmark: TS-SLAM vs the Co-SLAM baseline (same code, same preset) and the ablations.

Prints, in the form of the paper's tables:

* accuracy: ATE RMSE and RPE RMSE (cm, RPE over 1 frame) per method, mean over seeds, and the
  ratio of TS-SLAM to the baseline measured in the same run (paper Tables I-III); for each TS-SLAM
  seed also its intervals and how far the spline lay from the tracked poses (RMS, as ``metrics.json``'s
  ``spline_offsets``: what the spline smoothed away);
* runtime: ms per iteration x iterations per call for tracking, local-BA init / others and global
  BA, and the "FPS" both as wall-clock frames per second of the sequential loop and as the paper's
  theoretical throughput 1000 / (tracking ms x iterations) (paper Table IV);
* with ``--ablations``: w/o B-S., w/o DR, w/o LBA, with local BA's joint stage (off by default),
  the paper's schedule without our map update between intervals (``mapping.tsslam_map_every=0``)
  and a dt sweep (paper Table V);
* with ``--adaptive``: TS-SLAM with knots placed by the motion (``spline.knots=adaptive``, ours,
  beyond the paper) on the same seeds as the main rows, and its wall-clock frames per second
  against uniform TS-SLAM's of the same run; ``--skip baseline tsslam`` leaves out rows already
  measured;
* a control row that is not a SLAM method: the spline of the preset's dt fitted offline to the
  baseline's final trajectory (:func:`tsslam_ref.spline_fit.fit_trajectory`).  It asks whether the
  spline helps because TS-SLAM learns it with the map, or only because it smooths.

    python benchmarks/bench_system.py                              # bundled TUM slice, tum-cpu
    python -m tsslam_ref.data synthesize --trajectory tum_vi_room1 --start 16 --out data/room1_16
    python benchmarks/bench_system.py --data data/room1_16 --config synthetic-cpu --seeds 0 1 2 --json out.json
    python benchmarks/bench_system.py --ablations --dts 0.15 0.25 0.35
    python benchmarks/bench_system.py --adaptive --dts 0.15 --ablation-seeds 0 1 2 --seeds 0 1 2

The JSON file (``--json``) holds ``settings`` (preset, data, frames, seeds, each row's overrides),
``results`` (per row: every seed's metrics and runtime, and their mean) and the process's peak RSS.

``--against FILE`` compares this run with a stored JSON file of the same preset, sequence, frames and
seeds (for example the shipped ``tsslam_ref/assets/results/teddy_tum-cpu_3seeds.json``): for each
row in both it prints the mean ATE and RPE against the stored seeds' range ("identical" when every
seed's numbers are equal bit for bit, else "inside", "below" or "above" the range), frames/s and
ms per iteration now / stored, the peak RSS of both, and the code that wrote the file when it is not
this one (``settings.tsslam_ref``: version and source digest).  What a speed change needs to show:

    python benchmarks/bench_system.py --seeds 0 1 2 --skip baseline \
        --against tsslam_ref/assets/results/teddy_tum-cpu_3seeds.json

The README's "Results" section lists the commands behind each of its tables; the synthetic sequences
are rendered along the trajectory stretches that ship with the package (``--trajectory NAME``).

Every number comes from runs made by this script; nothing is hard-coded.
"""

import argparse
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch

from tsslam_ref import config, data, parallel, run_summaries, slam, spline_fit
from tsslam_ref.cli_args import OneLineParser, number_in
from tsslam_ref.device import compute_environment, map_kernels, peak_memory, source_version, tune_cpu_allocator
from tsslam_ref.run import atomic_write_text, trajectory_metrics
from tsslam_ref.run_outputs import ground_truth_known


CONTROL = "Co-SLAM + spline fit (offline control)"
ADAPTIVE = "TS-SLAM, adaptive knots"


def metrics_cm(sequence, timestamps: np.ndarray, poses: np.ndarray) -> Dict[str, float]:
    """:func:`tsslam_ref.run.trajectory_metrics` (ATE, RPE over 1 frame) in cm and degrees."""
    metrics = trajectory_metrics(sequence, timestamps, poses)
    return {"ate_cm": 100 * metrics["ate_rmse_m"], "rpe_cm": 100 * metrics["rpe_trans_rmse_m"],
            "rpe_deg": metrics["rpe_rot_rmse_deg"]}


def spline_fit_control(sequence, result: slam.SLAMResult, dt: float) -> Dict[str, float]:
    """Metrics of the spline (knot spacing ``dt``) fitted to a finished run's output poses."""
    fitted = spline_fit.fit_trajectory(result.timestamps, torch.as_tensor(result.poses, dtype=torch.float64), dt)
    return metrics_cm(sequence, result.timestamps, fitted.poses(result.timestamps).numpy())


def benchmark_device(cfg: config.Config) -> torch.device:
    """The config's device, with "auto" meaning the CPU (the benchmark's tables are CPU figures)."""
    return torch.device(cfg.device if cfg.device != "auto" else "cpu")


def run_once(sequence, cfg: config.Config) -> Dict[str, float]:
    """One SLAM run -> metrics in cm plus the runtime table (or the failure message).  A baseline
    run also gives the control row's metrics (``"spline_fit"``)."""
    torch.manual_seed(cfg.seed)
    start = time.perf_counter()
    try:
        run_loop = parallel.run_slam_in_two_threads if cfg.parallel else slam.run_slam
        result = run_loop(sequence, cfg, device=benchmark_device(cfg))
    except slam.TrackingFailure as failure:
        return {"failed": str(failure)}
    wall = time.perf_counter() - start
    runtime = result.state.timings.table()
    row = dict(metrics_cm(sequence, result.timestamps, result.poses),
               wall_fps=len(sequence) / wall, runtime=runtime,
               map_kernels=map_kernels(result.state.field, benchmark_device(cfg)))
    if cfg.method == "coslam":
        row["spline_fit"] = spline_fit_control(sequence, result, cfg.spline.dt)
    if cfg.method == "tsslam" and result.state.intervals_done:
        row["intervals"] = int(result.state.intervals_done)
        # the frames' time span over the intervals mapped (docs/system.md's "intervals (mean)"), not the knots' span
        row["mean_interval_s"] = float(result.timestamps[-1] - result.timestamps[0]) / result.state.intervals_done
        offsets = run_summaries.spline_offset_summary(result.state.log).get("spline_offsets")
        if offsets:  # what the spline smoothed away (docs/system.md): RMS over the frames, as metrics.json
            row["spline_offset_cm"], row["spline_offset_deg"] = 100 * offsets["position_rms_m"], offsets["rotation_rms_deg"]
    if "tracking" in runtime:
        tracking = runtime["tracking"]
        row["theoretical_fps"] = 1000.0 / (tracking["ms_per_iteration"] * tracking["iterations_per_call"])
    return row


def mean_rows(rows: List[Dict]) -> Dict[str, float]:
    good = [row for row in rows if "failed" not in row]
    if not good:
        return {"failed": rows[0]["failed"]}
    keys = [key for key in ("ate_cm", "rpe_cm", "rpe_deg", "wall_fps", "theoretical_fps") if key in good[0]]
    summary = {key: float(np.mean([row[key] for row in good])) for key in keys}
    summary.update({key + "_std": float(np.std([row[key] for row in good])) for key in ("ate_cm", "rpe_cm")})
    summary["runs"] = len(good)
    summary["failed_runs"] = len(rows) - len(good)
    return summary


def mean_runtime(rows: List[Dict]) -> Dict[str, Dict[str, float]]:
    """Per loop stage, ms per iteration and iterations per call averaged over the rows (seeds) that ran it."""
    stages = dict.fromkeys(stage for row in rows for stage in row["runtime"])
    return {stage: {key: float(np.mean([row["runtime"][stage][key] for row in rows if stage in row["runtime"]]))
                    for key in ("ms_per_iteration", "iterations_per_call")} for stage in stages}


def runtime_line(name: str, runtime: Dict[str, Dict[str, float]]) -> str:
    def cell(stage):
        if stage not in runtime:
            return "-"
        entry = runtime[stage]
        return f"{entry['ms_per_iteration']:.0f} x {entry['iterations_per_call']:.3g}"  # LBA init: a mean count

    return (f"| {name} | {cell('tracking')} | {cell('lba_init')} | {cell('lba_others')} | {cell('global_ba')} "
            f"| {cell('map_update')} | {cell('first_frame_mapping')} |")


def print_ratios(results: Dict[str, Dict]) -> None:
    """Each measured row against the baseline of the same run (ATE and RPE ratios)."""
    if "Co-SLAM (baseline)" not in results or "failed" in results["Co-SLAM (baseline)"]["mean"]:
        return
    baseline = results["Co-SLAM (baseline)"]["mean"]
    print()
    for name, result in results.items():
        mean = result["mean"]
        if name != "Co-SLAM (baseline)" and "failed" not in mean:
            note = " (paper: RPE -78.5 % on TUM, -40.5 % on ScanNet)" if name == "TS-SLAM" else ""
            print(f"{name} / baseline: ATE x{mean['ate_cm'] / baseline['ate_cm']:.2f}, "
                  f"RPE x{mean['rpe_cm'] / baseline['rpe_cm']:.2f}{note}")


def adaptive_speed_line(results: Dict[str, Dict]) -> str:
    """The adaptive-knots row's frames per second against uniform TS-SLAM's of the same run
    (wall clock, means over seeds), or "" when either row is missing or failed."""
    rows = [results.get(name, {}).get("mean", {}) for name in (ADAPTIVE, "TS-SLAM")]
    if any("wall_fps" not in row for row in rows):
        return ""
    adaptive, uniform = rows
    return (f"{ADAPTIVE} / TS-SLAM: frames/s x{adaptive['wall_fps'] / uniform['wall_fps']:.2f} "
            f"({adaptive['wall_fps']:.2f} against {uniform['wall_fps']:.2f}; runs of one process, one after another)")


def write_rows(path: str, settings: Dict, results: Dict, **extra) -> None:
    """The ``--json`` file: ``settings``, ``results`` and ``extra`` (the peak RSS at the end), atomically."""
    atomic_write_text(Path(path), json.dumps({"settings": settings, "results": results, **extra}, indent=2))


SAME_RUN_KEYS = ("preset", "sequence", "frames", "frame_range", "seeds", "ablation_seeds", "data_fingerprint")
"""Settings that must agree for a stored file's rows to be runs on the same frames with the same
seeds; ``--set`` may differ (a candidate setting against the stored presets).  ``data_fingerprint``
is compared where the stored file has one (files written before it was recorded lack it)."""


def data_fingerprint(sequence) -> str:
    """What tells two folders of one name apart: the image size, the frames' time stamps and the
    first frame's colour and depth as loaded (pixels, not file bytes, which differ by encoder),
    hashed (SHA-1, hex)."""
    first = sequence[0]
    digest = hashlib.sha1(f"{sequence.intrinsics.width}x{sequence.intrinsics.height}".encode())
    for array in (np.asarray(sequence.timestamps, dtype=np.float64), first.rgb, first.depth):
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def load_stored(path: str, settings: Dict) -> Dict:
    """The stored ``--json`` file at ``path``, checked against this benchmark's ``settings``.

    Raises:
        ValueError: naming the file and the first setting that differs, or what is missing.
    """
    try:
        stored = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"--against {path}: cannot read a benchmark JSON file ({error})") from None
    if not isinstance(stored, dict) or not isinstance(stored.get("settings"), dict) or not isinstance(stored.get("results"), dict):
        raise ValueError(f"--against {path}: expected a file written by --json, with 'settings' and 'results'")
    for key in SAME_RUN_KEYS:
        if key == "data_fingerprint" and key not in stored["settings"]:
            continue  # said in the comparison's closing lines
        if stored["settings"].get(key) != settings[key]:
            raise ValueError(f"--against {path}: its {key} is {stored['settings'].get(key)!r}, this run's is "
                             f"{settings[key]!r}; compare runs of the same preset, sequence, frames and seeds")
    return stored


def spread_verdict(rows_now: List[Dict], rows_stored: List[Dict], key: str) -> str:
    """Where the mean of ``key`` over this run's seeds falls against the stored seeds' values."""
    now = [row[key] for row in rows_now]
    stored = [row[key] for row in rows_stored]
    if now == stored:
        return "identical"
    mean = float(np.mean(now))
    if mean < min(stored):
        return "below"
    return "inside" if mean <= max(stored) else "above"


def per_seed(rows: List[Dict], key: str) -> str:
    """The seeds' values of ``key``, "a / b / c"."""
    return " / ".join(f"{row[key]:.3f}" for row in rows)


def stage_ratio(rows_now: List[Dict], rows_stored: List[Dict], stage: str) -> str:
    """Mean ms per iteration of a loop stage, now / stored, or "-" where a side lacks it."""
    def mean_ms(rows):
        values = [row["runtime"][stage]["ms_per_iteration"] for row in rows if stage in row.get("runtime", {})]
        return float(np.mean(values)) if values else None

    now, stored = mean_ms(rows_now), mean_ms(rows_stored)
    return "-" if now is None or stored is None else f"{now:.0f} / {stored:.0f}"


def _mib(value: Optional[float]) -> str:
    return "not measured (no `resource` module on this system)" if value is None else f"{value:.0f} MiB"


def comparison_lines(results: Dict, stored: Dict, environment: Dict, peak_rss_mib: Optional[float]) -> List[str]:
    """The ``--against`` table: every row measured now and stored, seed by seed the same runs."""
    lines = ["| row | ATE mean (cm): now / stored seeds | RPE mean (cm): now / stored seeds | ATE, RPE vs stored "
             "| frames/s now / stored | tracking ms/it now / stored | GBA ms/it | map update ms/it |",
             "|---|---|---|---|---|---|---|---|"]
    missing = [name for name in results if name not in stored["results"]]
    for name, result in results.items():
        if name in missing:
            continue
        rows_now = result["rows"]
        rows_stored = stored["results"][name]["rows"]
        if any("failed" in row for row in rows_now + rows_stored) or len(rows_now) != len(rows_stored):
            lines.append(f"| {name} | failed or incomplete on one side | | | | | | |")
            continue
        verdicts = ", ".join(spread_verdict(rows_now, rows_stored, key) for key in ("ate_cm", "rpe_cm"))
        fps = (f"{np.mean([row['wall_fps'] for row in rows_now]):.2f} / "
               f"{np.mean([row['wall_fps'] for row in rows_stored]):.2f}" if "wall_fps" in rows_stored[0] else "-")
        lines.append(f"| {name} | {np.mean([row['ate_cm'] for row in rows_now]):.3f} / {per_seed(rows_stored, 'ate_cm')} "
                     f"| {np.mean([row['rpe_cm'] for row in rows_now]):.3f} / {per_seed(rows_stored, 'rpe_cm')} | {verdicts} | {fps} "
                     f"| {stage_ratio(rows_now, rows_stored, 'tracking')} | {stage_ratio(rows_now, rows_stored, 'global_ba')} "
                     f"| {stage_ratio(rows_now, rows_stored, 'map_update')} |")
    if missing:
        lines.append(f"not in the stored file: {', '.join(missing)}")
    stored_rss = stored.get("peak_rss_mib")
    lines.append(f"peak RSS: {_mib(peak_rss_mib)} now, "
                 + (f"{stored_rss:.0f} MiB stored" if stored_rss is not None else "not in the stored file"))
    lines.extend(environment_lines(stored["settings"].get("environment") or {}, environment))
    stored_code = stored["settings"].get("tsslam_ref")
    if stored_code is None:  # a speed-up is a code change: "identical" rows show it kept every bit
        lines.append(f"code: the stored file does not record which code wrote it (an earlier version); "
                     f"now tsslam_ref {source_version()}")
    elif stored_code != source_version():
        lines.append(f"code: stored by tsslam_ref {stored_code}, now {source_version()}")
    if "data_fingerprint" not in stored["settings"]:
        lines.append("the stored file does not record the data's fingerprint (image size, time stamps, first "
                     "images): only the sequence's name, frame count and range were compared")
    return lines


def environment_lines(stored: Dict, now: Dict) -> List[str]:
    """What differs between the stored run's environment and this one's, in one line, or none.

    A file written before ``map_kernels`` was recorded says nothing about the map's code path; then
    a run of this one off the compiled kernels (no compiler, ``TSSLAM_NO_COMPILED_KERNEL``) is named.
    """
    differing = {key: (stored[key], now.get(key)) for key in sorted(stored) if stored[key] != now.get(key)}
    kernels = now.get("map_kernels", {})
    if "map_kernels" not in stored and any(path != "compiled" for key, path in kernels.items() if key != "kernel_error"):
        differing["map_kernels"] = ("not recorded", kernels)
    if not differing:
        return []
    listed = "; ".join(f"{key}: stored {was}, now {is_}" for key, (was, is_) in differing.items())
    return [f"environment differs ({listed}): the same seed gives the same numbers only with the same kernels, "
            "map code path and threads"]


def _seed(option: str):
    """A seed option's values: integers the run's generator keeps whole, as ``run --seed`` takes them."""
    return number_in(option, 0, 2**32 - 1, integer=True, interval="[0, 2**32 - 1]")


def main() -> None:
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="", help="dataset folder (default: the config's data.path, which the "
                                                   "presets leave empty: the bundled TUM slice)")
    parser.add_argument("--config", default="tum-cpu")
    parser.add_argument("--frames", default=None, help="START:STOP[:STEP]")
    parser.add_argument("--seeds", type=_seed("--seeds"), nargs="+", default=[0])
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--ablations", action="store_true", help="also run w/o B-S., w/o DR, w/o LBA, + LBA joint stage and the paper schedule")
    parser.add_argument("--dts", type=number_in("--dts", 0, 10, low_open=True, hint="spline.dt's range, seconds"),
                        nargs="+", default=[], help="dt values for the sweep (s)")
    parser.add_argument("--ablation-seeds", type=_seed("--ablation-seeds"), nargs="+", default=None,
                        help="seeds for the ablation and dt-sweep rows (default: the first of --seeds)")
    parser.add_argument("--adaptive", action="store_true",
                        help="also run TS-SLAM with knots placed by the motion (spline.knots=adaptive) on --seeds")
    parser.add_argument("--skip", nargs="+", default=[], choices=["baseline", "tsslam"],
                        help="leave out the Co-SLAM baseline (and with it the offline control) or the default TS-SLAM row")
    parser.add_argument("--threads", type=number_in("--threads", 1, 1024, integer=True), default=2)
    parser.add_argument("--json", default=None, help="write every row to this JSON file")
    parser.add_argument("--overwrite", action="store_true", help="allow replacing an existing --json file")
    parser.add_argument("--against", default=None, metavar="FILE",
                        help="compare with a stored --json file of the same preset, sequence, frames and seeds")
    args = parser.parse_args()
    if args.json and os.path.exists(args.json) and not args.overwrite:
        parser.error(f"--json {args.json} exists; pass --overwrite to replace it")
    if args.json and not Path(args.json).resolve().parent.is_dir():  # found out only after the first run
        parser.error(f"--json {args.json}: the folder {Path(args.json).parent} does not exist")
    torch.set_num_threads(args.threads)
    tune_cpu_allocator()

    try:
        base = config.load(args.config)
        if args.data:  # read as `run --data` reads it: the folder's layout and depth scale with a preset
            config.read_data_folder(base, args.data, args.config)
        base = config.apply_overrides(base, args.overrides)
        if args.frames:
            from tsslam_ref.run import parse_frames

            base.data.frame_start, base.data.frame_stop, base.data.frame_step = parse_frames(args.frames)
        sequence = data.load_from_config(base.data)
    except (ValueError, OSError) as error:  # run.BadInput is a ValueError
        parser.error(str(error))
    ground_truth = ground_truth_known(sequence)
    with_ground_truth = 0 if ground_truth is None else int(ground_truth[1].sum())
    if with_ground_truth < 3:
        parser.error(f"sequence {sequence.name} ({base.data.path or 'bundled'}, frames {args.frames or 'all'}): "
                     f"{with_ground_truth} of {len(sequence)} frames have a ground-truth pose; "
                     "ATE and RPE need at least 3 (widen --frames or use a sequence with ground truth)")
    variants = {"Co-SLAM (baseline)": ["method=coslam"], "TS-SLAM": ["method=tsslam"]}
    if args.adaptive:
        variants[ADAPTIVE] = ["method=tsslam", "spline.knots=adaptive"]
    for skipped, name in (("baseline", "Co-SLAM (baseline)"), ("tsslam", "TS-SLAM")):
        if skipped in args.skip:
            del variants[name]
    if args.ablations:
        variants["w/o B-S."] = ["method=tsslam", "local_ba.use_spline=false"]
        variants["w/o DR"] = ["method=tsslam", "local_ba.use_dynamics=false"]
        variants["w/o LBA"] = ["method=tsslam", "local_ba.enabled=false"]
        variants["+ LBA joint stage"] = ["method=tsslam", "local_ba.joint_iters=10"]  # the paper's stage 3, off by default
        variants["paper schedule"] = ["method=tsslam", "mapping.tsslam_map_every=0"]  # no map update between intervals
    for dt in args.dts:
        variants[f"TS-SLAM dt={dt:g} s"] = ["method=tsslam", f"spline.dt={dt}"]
    if not variants:
        parser.error(f"--skip {' '.join(args.skip)} leaves nothing to run (add --adaptive, --ablations or --dts)")

    environment = compute_environment(benchmark_device(base))
    print(f"sequence {sequence.name}: {len(sequence)} frames, {sequence.intrinsics.width}x{sequence.intrinsics.height}, "
          f"preset {base.name}, seeds {args.seeds}, {args.threads} threads, {environment['cpu_capability']} CPU kernels")
    if args.overrides:  # they change every row below, the baseline's too, under the same names
        print(f"--set on every row: {' '.join(args.overrides)} (--adaptive adds an adaptive-knots row instead)")
    main_variants = ("Co-SLAM (baseline)", "TS-SLAM", ADAPTIVE)
    ablation_seeds = args.ablation_seeds if args.ablation_seeds is not None else args.seeds[:1]
    settings = {"preset": base.name, "data": base.data.path or "bundled", "sequence": sequence.name,
                "frames": len(sequence), "frame_range": args.frames, "threads": args.threads,
                "data_fingerprint": data_fingerprint(sequence),
                "overrides": args.overrides, "seeds": args.seeds, "ablation_seeds": ablation_seeds,
                "variants": variants, "environment": environment, "tsslam_ref": source_version(),
                "control": f"spline of dt = {base.spline.dt} s fitted to the baseline's poses"}
    stored = None
    if args.against:
        try:
            stored = load_stored(args.against, settings)
        except ValueError as error:
            parser.error(str(error))
    results = {}
    for name, overrides in variants.items():
        rows = []
        for seed in (args.seeds if name in main_variants else ablation_seeds):
            cfg = config.apply_overrides(base, overrides + [f"seed={seed}"])
            row = run_once(sequence, cfg)
            rows.append(row)
            if "map_kernels" in row:  # which code ran the map: known once a run has built one
                environment.setdefault("map_kernels", row["map_kernels"])
            summary = "failed: " + row["failed"] if "failed" in row else (
                f"ATE {row['ate_cm']:.2f} cm, RPE {row['rpe_cm']:.3f} cm / {row['rpe_deg']:.3f} deg, {row['wall_fps']:.2f} frames/s"
                + (f", {row['intervals']} intervals (frames' time span / intervals: {row['mean_interval_s']:.3f} s)"
                   if "intervals" in row else "")
                + (f", spline from tracking: RMS {row['spline_offset_cm']:.2f} cm / {row['spline_offset_deg']:.2f} deg"
                   if "spline_offset_cm" in row else ""))
            print(f"  {name:22s} seed {seed}: {summary}", flush=True)
            results[name] = {"rows": rows, "mean": mean_rows(rows)}
            if name == "Co-SLAM (baseline)":
                control = [row.get("spline_fit", row) for row in rows]
                results[CONTROL] = {"rows": control, "mean": mean_rows(control)}
            if args.json:  # after every run, so that an interrupted benchmark keeps what it measured
                write_rows(args.json, settings, results)

    print("\n(mean +- standard deviation over the seeds, population form: numpy.std)")
    print("| method | ATE RMSE (cm) | RPE RMSE (cm) | RPE (deg) | runs |")
    print("|---|---|---|---|---|")
    for name, result in results.items():
        mean = result["mean"]
        if "failed" in mean:
            print(f"| {name} | fails | fails | fails | 0 |")
            continue
        print(f"| {name} | {mean['ate_cm']:.2f} +- {mean['ate_cm_std']:.2f} | {mean['rpe_cm']:.3f} +- {mean['rpe_cm_std']:.3f} "
              f"| {mean['rpe_deg']:.3f} | {mean['runs']} |")
    print_ratios(results)

    print("\n(means over each row's seeds)")
    print("| method | tracking ms x it | LBA init ms x it | LBA others ms x it | GBA ms x it | map update ms x it | first frame ms x it | wall FPS | theoretical FPS |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, result in results.items():
        good = [row for row in result["rows"] if "failed" not in row and "runtime" in row]
        if good:
            runtime = mean_runtime(good)
            tracking = runtime.get("tracking")
            theoretical = f"{1000.0 / (tracking['ms_per_iteration'] * tracking['iterations_per_call']):.2f}" if tracking else "-"
            print(f"{runtime_line(name, runtime)} {result['mean']['wall_fps']:.2f} | {theoretical} |")
    speed_line = adaptive_speed_line(results)
    if speed_line:
        print(speed_line)
    peak_rss_mib = peak_memory(torch.device("cpu")).get("peak_rss_mib")  # None where Python has no `resource`
    print(f"\npeak RSS of this process (all runs above): {_mib(peak_rss_mib)}")
    if args.json:
        write_rows(args.json, settings, results, peak_rss_mib=peak_rss_mib)
    if stored is not None:
        print(f"\nagainst {args.against} (its --set {stored['settings'].get('overrides')}, this run's {args.overrides}):")
        print("\n".join(comparison_lines(results, stored, environment, peak_rss_mib)))


if __name__ == "__main__":
    main()
