"""Field iteration cost: forward + backward + Adam step of Co-SLAM's map (shared/spec/cpu-budget.md).

For each preset (tum-cpu, synthetic-cpu, and the full tum / synthetic sample counts) and each ray
count (256, 1024, 4096) it times one map iteration on random points inside a 6.5 m box (the TUM
fr1_desk box size) with samples per ray = n_samples + n_range_d of the preset, on CPU and on CUDA
when available.  It prints the median and minimum milliseconds, the peak memory, and the ratio
fast path / reference path (FieldConfig.fast_gather) measured in the same run.

Target (cpu-budget.md): 1024 rays x 43 samples, table 2^16, 2 threads, float32, under 100 ms.

Usage: python benchmarks/bench_field.py [--repeats 10] [--rays 256 1024 4096] [--presets ...]
"""

import argparse
import resource
import statistics
import time

import torch

from tsslam_ref import config
from tsslam_ref.field import SceneField
from tsslam_ref.mapping import make_map_optimizer
from tsslam_ref.slam import tune_cpu_allocator

BOX = [[-3.5, 3.0], [-3.0, 3.0], [-3.0, 3.0]]  # TUM fr1_desk (Co-SLAM), 6.5 m


def time_iterations(field, optimizer, points, repeats, device):
    """Median and minimum ms of forward + backward + step over ``repeats`` runs after 2 warm-ups."""

    def one():
        optimizer.zero_grad(set_to_none=True)
        rgb, sdf = field(points)
        (rgb.square().mean() + sdf.square().mean()).backward()
        optimizer.step()

    for _ in range(2):
        one()
    timings = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        one()
        if device.type == "cuda":
            torch.cuda.synchronize()
        timings.append((time.perf_counter() - start) * 1000)
    return statistics.median(timings), min(timings)


def peak_memory_mb(field, optimizer, points, device):
    """Peak MiB: CUDA allocator peak of one iteration, or on CPU the process max RSS so far
    (resource.getrusage; tracemalloc does not see torch's CPU allocations)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        time_iterations(field, optimizer, points, 1, device)
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB (Linux)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--rays", type=int, nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--presets", nargs="+", default=["tum-cpu", "synthetic-cpu", "tum", "synthetic"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-reference", action="store_true", help="skip the reference path")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    allocator = tune_cpu_allocator()
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {args.threads} threads, float32, box 6.5 m, medians of {args.repeats}, "
          f"glibc allocator tuned: {allocator}")
    print(f"{'device':6} {'preset':14} {'log2T':>5} {'samples':>7} {'rays':>5} {'fast ms':>9} {'(min)':>7} "
          f"{'ref ms':>9} {'ref/fast':>8} {'peak MiB':>9}")
    for device in devices:
        for preset in args.presets:
            cfg = config.load(preset)
            samples = cfg.render.n_samples + cfg.render.n_range_d
            generator = torch.Generator().manual_seed(0)
            for n_rays in args.rays:
                points = (torch.rand(n_rays * samples, 3, generator=generator) * 6.0 - 3.0).to(device)
                row = {}
                for fast in ([True] if args.no_reference else [True, False]):
                    cfg.field.fast_gather = fast
                    field = SceneField(cfg.field, BOX, generator=torch.Generator().manual_seed(0)).to(device)
                    optimizer = make_map_optimizer(field, cfg.mapping)
                    row[fast] = time_iterations(field, optimizer, points, args.repeats, device)
                    if fast:
                        peak = peak_memory_mb(field, optimizer, points, device)
                fast_ms, fast_min = row[True]
                ref_ms = row[False][0] if False in row else float("nan")
                print(f"{device.type:6} {preset:14} {cfg.field.log2_hashmap_size:>5} {samples:>7} {n_rays:>5} "
                      f"{fast_ms:>9.1f} {fast_min:>7.1f} {ref_ms:>9.1f} {ref_ms / fast_ms:>8.2f} {peak:>9.0f}")
    print("peak MiB on CPU is the process max RSS so far (includes earlier rows).")


if __name__ == "__main__":
    main()
