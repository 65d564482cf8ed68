"""What the final mesh costs: memory and time of marching cubes' grid query, chunked against whole.

A finished run extracts its mesh at ``mesh.voxel_final`` (0.04 m in ``tum-cpu``), which queries
the SDF at millions of grid points.  ``mesh.extract_mesh`` builds those points one chunk at a time
from their flat indices (``mesh.query_grid``); the baseline, measured in the same run, first builds
the whole (N, 3) float64 grid with ``np.meshgrid`` and queries it in the same chunks (what the
package did before).  Each variant runs ``--repeats`` times, alternating, in a child process of its own (a
process's peak only grows), on the same field: the map fitted to frame 0 of the bundled teddy slice
(``--fit-iters`` iterations, seed 0) with the bound estimated as the loop does.  For each it prints
the memory the extraction adds to the process (peak RSS during it minus RSS before, sampled every
2 ms from ``/proc/self/statm``, so Linux only) and its seconds, the ratio of the medians, and
whether the two meshes' PLY bytes are identical; exit status 1 if they are not.

Usage: python benchmarks/bench_mesh.py [--preset tum-cpu] [--voxel M] [--fit-iters 20] [--repeats 2]
"""

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import threading
import time

import numpy as np
import torch
import trimesh

from tsslam_ref import config, data
from tsslam_ref.cli_args import OneLineParser, number_in
from tsslam_ref import mesh as mesh_module
from tsslam_ref.device import frame_to_device
from tsslam_ref.field import SceneField
from tsslam_ref.losses import RenderLossSettings
from tsslam_ref.mapping import estimate_bound, fit_map, make_map_optimizer

VARIANTS = ("whole", "chunked")


def whole_grid_query(fn, axes, chunk, device, dtype) -> np.ndarray:
    """The baseline: the (N, 3) grid held whole, then queried ``chunk`` points at a time."""
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)  # (Nx, Ny, Nz, 3)
    return mesh_module.query_in_chunks(fn, grid.reshape(-1, 3), chunk, device, dtype).reshape(grid.shape[:3])


def fitted_field(preset: str, fit_iters: int) -> SceneField:
    """The map fitted to frame 0 of the bundled slice (seed 0), bound as the loop estimates it."""
    cfg = config.load(preset)
    sequence = data.load_from_config(cfg.data)
    frame = frame_to_device(sequence[0], torch.device("cpu"), torch.float32)
    pose = torch.as_tensor(sequence[0].pose_c2w, dtype=torch.float32)[None]
    bound = estimate_bound([sequence[0]], pose.double(), cfg.field.bound_margin,
                           max_depth=min(cfg.data.depth_trunc, cfg.render.far))
    field = SceneField(cfg.field, torch.as_tensor(bound, dtype=torch.float32),
                       generator=torch.Generator().manual_seed(0))
    fit_map(field, make_map_optimizer(field, cfg.mapping), [frame], pose, RenderLossSettings.from_config(cfg),
            fit_iters, cfg.mapping.first_n_rays, torch.Generator().manual_seed(0))
    return field


def resident_mib() -> float:
    """This process's resident set size now (MiB), from /proc/self/statm."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def measure(variant: str, preset: str, voxel: float, fit_iters: int) -> dict:
    """Extract the mesh once with ``variant``; the memory it adds, its time and its PLY's hash."""
    torch.set_num_threads(2)
    field = fitted_field(preset, fit_iters)
    if variant == "whole":
        mesh_module.query_grid = whole_grid_query
    peak, done = [0.0], threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], resident_mib())
            time.sleep(0.002)

    before = resident_mib()
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    start = time.perf_counter()
    try:
        mesh = mesh_module.extract_mesh(field, None, voxel)
    finally:  # the sampler stops on an error too, or the child would never exit
        done.set()
    seconds = time.perf_counter() - start
    sampler.join()
    points = int(np.prod([len(axis) for axis in mesh_module._grid_axes(field.bound.numpy(), voxel)]))
    return {"variant": variant, "extra_mib": peak[0] - before, "seconds": seconds, "grid_points": points,
            "faces": len(mesh.faces), "sha256": hashlib.sha256(trimesh.exchange.ply.export_ply(mesh)).hexdigest()}


def run_child(variant: str, args) -> dict:
    command = [sys.executable, os.path.abspath(__file__), "--child", variant, "--preset", args.preset,
               "--voxel", str(args.voxel), "--fit-iters", str(args.fit_iters)]
    child = subprocess.run(command, capture_output=True, text=True)
    if child.returncode != 0:
        last = (child.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise RuntimeError(f"the {variant} measurement failed: {last}")
    return json.loads(child.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = OneLineParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--preset", default="tum-cpu", choices=sorted(config.PRESETS))
    parser.add_argument("--voxel", type=number_in("--voxel", 0, 10, low_open=True), default=None,
                        help="grid spacing in m, in (0, 10] (default: the preset's mesh.voxel_final)")
    parser.add_argument("--fit-iters", type=number_in("--fit-iters", 1, 10**6, integer=True), default=20)
    parser.add_argument("--repeats", type=number_in("--repeats", 1, 1000, integer=True), default=2)
    parser.add_argument("--child", choices=VARIANTS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.voxel is None:
        args.voxel = config.load(args.preset).mesh.voxel_final
    if args.child:
        print(json.dumps(measure(args.child, args.preset, args.voxel, args.fit_iters)))
        return 0
    if not os.path.exists("/proc/self/statm"):
        print("bench_mesh.py reads the resident set size from /proc/self/statm (Linux); not found here")
        return 2
    rows = {variant: [] for variant in VARIANTS}
    try:
        for _ in range(args.repeats):
            for variant in VARIANTS:
                rows[variant].append(run_child(variant, args))
    except RuntimeError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    first = rows["chunked"][0]
    print(f"mesh of the map fitted to teddy frame 0 ({args.preset}, {args.fit_iters} iterations), voxel "
          f"{args.voxel} m: {first['grid_points']:,} grid points, {first['faces']:,} faces")
    print(f"  {'grid':10} {'extra MiB':>22} {'seconds':>20}")
    medians = {}
    for variant in VARIANTS:
        extra = [row["extra_mib"] for row in rows[variant]]
        seconds = [row["seconds"] for row in rows[variant]]
        medians[variant] = statistics.median(extra), statistics.median(seconds)
        print(f"  {variant:10} {' / '.join(f'{value:.0f}' for value in extra):>22} "
              f"{' / '.join(f'{value:.2f}' for value in seconds):>20}")
    print(f"  chunked / whole (medians): memory x{medians['chunked'][0] / max(medians['whole'][0], 1e-9):.2f}, "
          f"time x{medians['chunked'][1] / medians['whole'][1]:.2f}")
    hashes = {row["sha256"] for variant in VARIANTS for row in rows[variant]}
    print("  PLY bytes: " + ("identical in every run" if len(hashes) == 1 else f"DIFFER ({len(hashes)} versions)"))
    return 0 if len(hashes) == 1 else 1


if __name__ == "__main__":
    sys.exit(main())
