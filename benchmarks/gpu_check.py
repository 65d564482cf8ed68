"""GPU check: the same computations on CUDA and on the CPU, both methods end to end, and timings.

Two kinds of agreement, because a SLAM run is chaotic: a difference in the last bit of one sum
(the two devices add in different orders) grows over the frames, so one seed's trajectories part
by centimetres although no computation is wrong (measured on an H200: 2.5 cm for TS-SLAM and 9.6
cm for Co-SLAM over 40 frames, while a CPU run itself moves that much from one seed to the next).
So it checks

* **kernels, same inputs**: the map (colour, SDF and the gradients of the hash table, the MLPs and
  the points at 4096 random points, float32; the CPU with its compiled kernels against the device
  on the PyTorch path, which a GPU takes) and the spline (pose, velocity, acceleration, angular rate and
  angular acceleration at 200 times, float64) on the CPU and on ``--device``.  Passes when the
  largest difference, relative to the largest value, is below 1e-4 (float32) and 1e-10 (float64);
* **runs, same seeds**: both methods (TS-SLAM, Co-SLAM baseline) on the bundled TUM fr3/teddy slice
  (``tum-cpu``) for each of ``--seeds`` on both devices.  It prints each seed's ATE / RPE and the
  largest distance between the two runs' positions (for information), and passes when the two
  devices' mean ATE differ by at most the CPU runs' seed range (largest minus smallest ATE) plus
  ``--tolerance-cm`` (default 0.5 cm);
* **time**: frames per second and the runtime table of each run (ms per iteration of tracking,
  local BA, global BA, map update; first seed), and one map iteration (forward + backward + Adam)
  at 1024 rays x 43 samples on each device, as ``bench_field.py`` times it.

It writes every figure to ``--json`` (default ``runs/gpu_check.json``; an existing file is kept
unless ``--overwrite``).  Exit status: 0 every check holds, 1 one does not, 2 the device cannot be
used.  On a machine without CUDA, ``--device cpu`` runs the whole script as a dry run (the map's
compiled kernels against its PyTorch path, which agree to rounding; the spline and the runs CPU
against CPU, exactly).  Run it as a script (``python benchmarks/gpu_check.py``), not with ``-m``.

Usage: python benchmarks/gpu_check.py [--frames 0:20] [--seeds 0 1 2] [--device cuda] [--threads 2] [--json FILE]

tests/test_gpu_check.py checks its pieces on the CPU (the kernel comparison, the pass rule, the
refusals); the figures are in the README's "Results".
"""

import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Dict

import numpy as np
import torch

from tsslam_ref import config, data, slam, spline
from tsslam_ref.device import resolve_device, tune_cpu_allocator
from tsslam_ref.field import SceneField
from tsslam_ref.files import atomic_write_text
from tsslam_ref.geometry import pose_offsets, so3_exp
from tsslam_ref.mapping import make_map_optimizer
from tsslam_ref.run import parse_frames, trajectory_metrics
from tsslam_ref.cli_args import OneLineParser, number_in

from bench_field import BOX, time_iterations  # benchmarks/ is on the path when this script runs



def run_method(sequence, cfg: config.Config, device: torch.device) -> Dict[str, object]:
    """One SLAM run on ``device``: (N, 4, 4) float64 poses, metrics in cm, frames/s, runtime table."""
    torch.manual_seed(cfg.seed)
    start = time.perf_counter()
    result = slam.run_slam(sequence, cfg, device=device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    wall = time.perf_counter() - start
    metrics = trajectory_metrics(sequence, result.timestamps, result.poses)
    return {"poses": np.asarray(result.poses, dtype=np.float64), "frames_per_second": len(sequence) / wall,
            "ate_cm": 100 * metrics["ate_rmse_m"], "rpe_cm": 100 * metrics["rpe_trans_rmse_m"],
            "runtime": result.state.timings.table()}


def agreement(cpu_poses: np.ndarray, device_poses: np.ndarray) -> Dict[str, float]:
    """Largest and RMS position distance (cm) and largest rotation angle (deg) between two (N, 4, 4) runs."""
    distance, angle = pose_offsets(cpu_poses, device_poses)
    distance = distance * 100
    return {"max_position_cm": float(distance.max()), "rms_position_cm": float(np.sqrt(np.mean(distance**2))),
            "max_rotation_deg": float(angle.max())}


def relative_difference(cpu: torch.Tensor, other: torch.Tensor) -> float:
    """max |cpu - other| / max |cpu| (0 for two zero tensors)."""
    scale = float(cpu.abs().max())
    return float((cpu - other.cpu()).abs().max()) / scale if scale > 0 else float((other.abs().max()))


def points_in_box(n_points: int, seed: int) -> torch.Tensor:
    """(n_points, 3) uniform points in ``BOX``, drawn on the CPU from ``seed`` (the same on every device)."""
    low, high = torch.tensor(BOX).T
    return low + (high - low) * torch.rand(n_points, 3, generator=torch.Generator().manual_seed(seed))


def field_agreement(cfg: config.Config, device: torch.device, n_points: int = 4096) -> Dict[str, float]:
    """Colour, SDF, every parameter's gradient and the points' gradient (what tracking and BA use) of
    one map forward + backward at the same (n_points, 3) points with the same weights: the CPU with
    the config's kernels against ``device`` on the PyTorch path a GPU takes (on the CPU too, so that
    a dry run compares the two paths, which agree to rounding); relative difference per output."""
    cpu_field = SceneField(cfg.field, BOX, generator=torch.Generator().manual_seed(0))
    pytorch_path = dataclasses.replace(cfg.field, compiled_kernel=False, compiled_oneblob=False)
    other_field = SceneField(pytorch_path, BOX)
    other_field.load_state_dict(cpu_field.state_dict())
    other_field = other_field.to(device)
    outputs = {}
    for field, where in ((cpu_field, "cpu"), (other_field, "device")):
        points = points_in_box(n_points, seed=1).to(device if where == "device" else "cpu").requires_grad_(True)
        rgb, sdf = field(points)
        (rgb.square().mean() + sdf.square().mean()).backward()
        outputs[where] = {"rgb": rgb.detach(), "sdf": sdf.detach(), "grad points": points.grad,
                          **{f"grad {name}": parameter.grad for name, parameter in field.named_parameters()}}
    return {name: relative_difference(value, outputs["device"][name]) for name, value in outputs["cpu"].items()}


def spline_agreement(device: torch.device, n_ctrl: int = 8, n_times: int = 200) -> Dict[str, float]:
    """Pose and derivatives (Eq. 5-9) of one float64 spline at the same times on both devices."""
    generator = torch.Generator().manual_seed(2)
    rotations = so3_exp(0.5 * torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64))
    translations = torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64)
    dt, t0 = 0.1, 0.0
    t_min, t_max = spline.valid_time_range(n_ctrl, dt, t0)
    times = np.linspace(t_min, t_max, n_times)
    samples = {where: spline.evaluate(rotations.to(where), translations.to(where), times, dt, t0, derivatives=2)
               for where in (torch.device("cpu"), device)}
    cpu, other = samples[torch.device("cpu")], samples[device]
    return {name: relative_difference(getattr(cpu, name), getattr(other, name)) for name in cpu._fields}


def time_map_iteration(cfg: config.Config, device: torch.device, n_rays: int = 1024, repeats: int = 10) -> float:
    """Median ms of one map iteration at ``n_rays`` x (n_samples + n_range_d), timed by bench_field.py."""
    field = SceneField(cfg.field, BOX, generator=torch.Generator().manual_seed(0)).to(device)
    optimizer = make_map_optimizer(field, cfg.mapping)
    points = points_in_box(n_rays * (cfg.render.n_samples + cfg.render.n_range_d), seed=0)
    median, _ = time_iterations(field, optimizer, points.to(device), repeats, device)
    return median


def stage_cell(runtime: Dict[str, Dict[str, float]], stage: str) -> str:
    entry = runtime.get(stage)
    return "-" if entry is None else f"{entry['ms_per_iteration']:.1f} x {entry['iterations_per_call']:.3g}"


FLOAT32_TOLERANCE, FLOAT64_TOLERANCE = 1e-4, 1e-10


def check_kernels(cfg: config.Config, device: torch.device, report: Dict[str, object]) -> bool:
    """The map and the spline at the same inputs on both devices; prints and records the differences."""
    field = field_agreement(cfg, device)
    curve = spline_agreement(device)
    ok = max(field.values()) <= FLOAT32_TOLERANCE and max(curve.values()) <= FLOAT64_TOLERANCE
    report["kernels"] = {"field_relative_difference": field, "spline_relative_difference": curve, "passed": ok}
    print(f"kernels: {'agree' if ok else 'DIFFER'} - map (float32) largest relative difference "
          f"{max(field.values()):.1e} ({max(field, key=field.get)}; limit {FLOAT32_TOLERANCE:.0e}), "
          f"spline (float64) {max(curve.values()):.1e} ({max(curve, key=curve.get)}; limit {FLOAT64_TOLERANCE:.0e})")
    return ok


def check_runs(sequence, base: config.Config, device: torch.device, seeds, tolerance_cm: float,
               report: Dict[str, object]) -> bool:
    """Both methods for every seed on both devices; passes when the mean ATEs differ by at most the
    CPU's seed range plus ``tolerance_cm``."""
    passed = True
    for method in ("tsslam", "coslam"):
        entry = {"seeds": {}}
        for seed in seeds:
            cfg = config.apply_overrides(base, [f"method={method}"])
            cfg.seed = seed
            cpu = run_method(sequence, cfg, torch.device("cpu"))
            other = run_method(sequence, cfg, device)
            match = agreement(cpu["poses"], other["poses"])
            entry["seeds"][seed] = {"agreement": match, **{f"{where}_{key}": run[key] for where, run in (("cpu", cpu), ("device", other))
                                                          for key in ("ate_cm", "rpe_cm", "frames_per_second", "runtime")}}
            print(f"  {method}, seed {seed}: ATE {cpu['ate_cm']:.2f} / {other['ate_cm']:.2f} cm, RPE {cpu['rpe_cm']:.3f} / "
                  f"{other['rpe_cm']:.3f} cm (CPU / {device.type}); positions part by at most {match['max_position_cm']:.2f} cm")
        cpu_ate = np.array([value["cpu_ate_cm"] for value in entry["seeds"].values()])
        device_ate = np.array([value["device_ate_cm"] for value in entry["seeds"].values()])
        allowed = float(cpu_ate.max() - cpu_ate.min()) + tolerance_cm
        difference = abs(float(device_ate.mean() - cpu_ate.mean()))
        entry.update(cpu_mean_ate_cm=float(cpu_ate.mean()), device_mean_ate_cm=float(device_ate.mean()),
                     allowed_difference_cm=allowed, passed=difference <= allowed)
        passed &= entry["passed"]
        report["methods"][method] = entry
        print(f"  {method}: {'agrees' if entry['passed'] else 'DIFFERS'} - mean ATE {cpu_ate.mean():.2f} cm (CPU, range "
              f"{cpu_ate.min():.2f}-{cpu_ate.max():.2f}) against {device_ate.mean():.2f} cm ({device.type}); "
              f"difference {difference:.2f} cm, allowed {allowed:.2f} cm")
    return passed


def print_timings(report: Dict[str, object], device: torch.device) -> None:
    print("\n| method | device | frames/s | tracking ms x it | LBA init | LBA others | GBA | map update |")
    print("|---|---|---|---|---|---|---|---|")
    for method, entry in report["methods"].items():
        first = next(iter(entry["seeds"].values()))
        for where in ("cpu", "device"):
            runtime = first[f"{where}_runtime"]
            cells = " | ".join(stage_cell(runtime, stage) for stage in ("tracking", "lba_init", "lba_others", "global_ba", "map_update"))
            print(f"| {method} | {'cpu' if where == 'cpu' else device.type} | {first[f'{where}_frames_per_second']:.2f} | {cells} |")


def _unwritable(path: Path) -> str:
    """Why ``path`` cannot be written (a folder, under a file, in a folder not writable), or ""."""
    if path.is_dir():
        return "is a folder"
    ancestor = next(parent for parent in path.resolve().parents if parent.exists())
    if not ancestor.is_dir():
        return f"{ancestor} is a file, not a folder"
    return "" if os.access(ancestor, os.W_OK) else f"the folder {ancestor} is not writable"


def main(argv=None) -> int:
    parser = OneLineParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--frames", default="0:20", help="START:STOP[:STEP] of the bundled slice (default 0:20)")
    parser.add_argument("--seeds", type=number_in("--seeds", 0, 2**32 - 1, integer=True, interval="[0, 2**32 - 1]"),
                        nargs="+", default=[0, 1, 2])
    parser.add_argument("--device", default="cuda", help="the device checked against the CPU (default cuda)")
    parser.add_argument("--tolerance-cm", type=number_in("--tolerance-cm", 0, 1000, low_open=True), default=0.5,
                        help="allowed mean-ATE difference beyond the CPU's seed range (default 0.5)")
    parser.add_argument("--threads", type=number_in("--threads", 1, 1024, integer=True), default=2, help="CPU threads of the CPU runs (default 2)")
    parser.add_argument("--json", default="runs/gpu_check.json")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    args = parser.parse_args(argv)
    if os.path.exists(args.json) and not args.overwrite:
        print(f"error: --json {args.json} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    unwritable = _unwritable(Path(args.json))  # found out only after every run otherwise
    if unwritable:
        print(f"error: --json {args.json}: {unwritable}", file=sys.stderr)
        return 2
    base = config.load("tum-cpu")
    try:
        device = resolve_device(args.device)
    except (ValueError, RuntimeError) as error:
        print(f"error: --device {args.device}: {error}", file=sys.stderr)
        return 2
    try:
        base.data.frame_start, base.data.frame_stop, base.data.frame_step = parse_frames(args.frames)
        sequence = data.load_from_config(base.data)
    except ValueError as error:
        print(f"error: --frames {args.frames}: {error}", file=sys.stderr)
        return 2
    if len(sequence) < 3:
        print(f"error: --frames {args.frames} selects {len(sequence)} frame(s); the check needs at least 3 (ATE "
              f"aligns 3 poses)", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    tune_cpu_allocator()
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"{sequence.name}: {len(sequence)} frames, tum-cpu, seeds {args.seeds}; CPU ({args.threads} threads) "
          f"against {device} ({name})")
    report: Dict[str, object] = {"device": str(device), "device_name": name, "frames": len(sequence), "seeds": args.seeds,
                                 "tolerance_cm": args.tolerance_cm, "methods": {}}
    passed = check_kernels(base, device, report)
    passed &= check_runs(sequence, base, device, args.seeds, args.tolerance_cm, report)
    print_timings(report, device)
    report["map_iteration_ms"] = {"cpu": time_map_iteration(base, torch.device("cpu")),
                                  "device": time_map_iteration(base, device)}
    print(f"\nmap iteration, 1024 rays x {base.render.n_samples + base.render.n_range_d} samples: "
          f"cpu {report['map_iteration_ms']['cpu']:.1f} ms, {device} {report['map_iteration_ms']['device']:.1f} ms")
    report["passed"] = passed
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.json, json.dumps(report, indent=2))
    print(f"{'PASS' if passed else 'FAIL'}: written to {args.json}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
