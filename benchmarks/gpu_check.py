"""GPU check: both methods on the bundled sequence on CUDA, compared with the same run on the CPU, and timed.

For each method (TS-SLAM, Co-SLAM baseline) it runs the loop on the bundled TUM fr3/teddy slice
(``tum-cpu`` preset, same seed) once on the CPU and once on ``--device`` (default ``cuda``), then prints

* agreement: the largest and the RMS distance between the two runs' per-frame camera positions (cm),
  the largest rotation difference (deg), and both runs' ATE / RPE (cm).  The two devices sum in a
  different order, so the runs are not bit-identical; the check passes when the largest position
  difference is below ``--tolerance-cm`` (default 1 cm, a fifth of the teddy ATE) and the ATE of
  the two runs differs by less than the same amount;
* time: frames per second of each run and the runtime table (ms per iteration of tracking, local BA,
  global BA, map update), and one map iteration (forward + backward + Adam) at 1024 rays x 43
  samples on each device, as ``bench_field.py`` times it.

It writes every figure to ``--json`` (default ``runs/gpu_check.json``; an existing file is kept
unless ``--overwrite``).  Exit status: 0 agreement holds, 1 it does not, 2 the device cannot be used.
On a machine without CUDA, ``--device cpu`` runs the whole script as a dry run (CPU against CPU,
which must agree exactly).

Usage: python benchmarks/gpu_check.py [--frames 0:40] [--seed 0] [--device cuda] [--json FILE]

Nothing here runs in the tests; the figures go to the README's "Results" when a GPU was used.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Dict

import numpy as np
import torch

from tsslam_ref import config, data, slam
from tsslam_ref.device import resolve_device, tune_cpu_allocator
from tsslam_ref.field import SceneField
from tsslam_ref.files import atomic_write_text
from tsslam_ref.geometry import rotation_angle_deg
from tsslam_ref.mapping import make_map_optimizer
from tsslam_ref.run import parse_frames, trajectory_metrics

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
    distance = np.linalg.norm(cpu_poses[:, :3, 3] - device_poses[:, :3, 3], axis=-1) * 100
    relative = np.swapaxes(cpu_poses[:, :3, :3], -1, -2) @ device_poses[:, :3, :3]
    return {"max_position_cm": float(distance.max()), "rms_position_cm": float(np.sqrt(np.mean(distance**2))),
            "max_rotation_deg": float(rotation_angle_deg(relative).max())}


def time_map_iteration(cfg: config.Config, device: torch.device, n_rays: int = 1024, repeats: int = 10) -> float:
    """Median ms of one map iteration at ``n_rays`` x (n_samples + n_range_d), timed by bench_field.py."""
    field = SceneField(cfg.field, BOX, generator=torch.Generator().manual_seed(0)).to(device)
    optimizer = make_map_optimizer(field, cfg.mapping)
    generator = torch.Generator(device="cpu").manual_seed(0)
    low, high = torch.tensor(BOX).T
    points = low + (high - low) * torch.rand(n_rays * (cfg.render.n_samples + cfg.render.n_range_d), 3, generator=generator)
    median, _ = time_iterations(field, optimizer, points.to(device), repeats, device)
    return median


def stage_cell(runtime: Dict[str, Dict[str, float]], stage: str) -> str:
    entry = runtime.get(stage)
    return "-" if entry is None else f"{entry['ms_per_iteration']:.1f} x {entry['iterations_per_call']:.0f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default="0:40", help="START:STOP[:STEP] of the bundled slice (default 0:40)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cuda", help="the device checked against the CPU (default cuda)")
    parser.add_argument("--tolerance-cm", type=float, default=1.0)
    parser.add_argument("--threads", type=int, default=2, help="CPU threads of the CPU runs (default 2)")
    parser.add_argument("--json", default="runs/gpu_check.json")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    args = parser.parse_args(argv)
    if os.path.exists(args.json) and not args.overwrite:
        print(f"error: --json {args.json} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    try:
        device = resolve_device(args.device)
        frames = parse_frames(args.frames)
    except (ValueError, RuntimeError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    tune_cpu_allocator()
    base = config.load("tum-cpu")
    base.seed = args.seed
    base.data.frame_start, base.data.frame_stop, base.data.frame_step = frames
    sequence = data.load_from_config(base.data)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"{sequence.name}: {len(sequence)} frames, tum-cpu, seed {args.seed}; CPU ({args.threads} threads) against {device} ({name})")

    report: Dict[str, object] = {"device": str(device), "device_name": name, "frames": len(sequence), "seed": args.seed,
                                 "tolerance_cm": args.tolerance_cm, "methods": {}}
    passed = True
    for method in ("tsslam", "coslam"):
        cfg = config.apply_overrides(base, [f"method={method}"])
        cpu = run_method(sequence, cfg, torch.device("cpu"))
        other = run_method(sequence, cfg, device)
        match = agreement(cpu["poses"], other["poses"])
        ok = match["max_position_cm"] <= args.tolerance_cm and abs(cpu["ate_cm"] - other["ate_cm"]) <= args.tolerance_cm
        passed &= ok
        report["methods"][method] = {"agreement": match, "passed": ok,
                                     **{f"{where}_{key}": run[key] for where, run in (("cpu", cpu), ("device", other))
                                        for key in ("ate_cm", "rpe_cm", "frames_per_second", "runtime")}}
        print(f"  {method}: {'agrees' if ok else 'DIFFERS'} - positions differ by at most {match['max_position_cm']:.3f} cm "
              f"(RMS {match['rms_position_cm']:.3f}), rotations by {match['max_rotation_deg']:.3f} deg; "
              f"ATE {cpu['ate_cm']:.2f} / {other['ate_cm']:.2f} cm, RPE {cpu['rpe_cm']:.3f} / {other['rpe_cm']:.3f} cm "
              f"(CPU / {device.type})")
    print("\n| method | device | frames/s | tracking ms x it | LBA init | LBA others | GBA | map update |")
    print("|---|---|---|---|---|---|---|---|")
    for method, entry in report["methods"].items():
        for where in ("cpu", "device"):
            runtime = entry[f"{where}_runtime"]
            cells = " | ".join(stage_cell(runtime, stage) for stage in ("tracking", "lba_init", "lba_others", "global_ba", "map_update"))
            print(f"| {method} | {'cpu' if where == 'cpu' else device.type} | {entry[f'{where}_frames_per_second']:.2f} | {cells} |")
    field_cfg = config.load("tum-cpu")
    report["map_iteration_ms"] = {"cpu": time_map_iteration(field_cfg, torch.device("cpu")),
                                  str(device): time_map_iteration(field_cfg, device)}
    print(f"\nmap iteration, 1024 rays x {field_cfg.render.n_samples + field_cfg.render.n_range_d} samples: "
          + ", ".join(f"{where} {ms:.1f} ms" for where, ms in report["map_iteration_ms"].items()))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.json, json.dumps(report, indent=2))
    print(f"{'PASS' if passed else 'FAIL'}: written to {args.json}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
