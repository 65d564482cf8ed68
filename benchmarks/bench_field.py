"""Field iteration cost: forward + backward + Adam step of Co-SLAM's map (results in docs/map.md).

For each preset (tum-cpu, synthetic-cpu, and the full tum / synthetic sample counts) and each ray
count (256, 1024, 4096) it times one map iteration on random points in [-3, 3]^3 m inside the map's
6.5 m box (the TUM fr1_desk box) with samples per ray = n_samples + n_range_d of the preset, on CPU and on CUDA
when available.  It prints the median and minimum milliseconds of the default path (the compiled
CPU kernel where it builds, ``hash_kernel.py``; the PyTorch fast path on CUDA), the peak memory,
and, measured in the same run, the PyTorch fast path (``field.compiled_kernel=false`` and
``field.compiled_oneblob=false``: the path a GPU takes) and the plain reference path
(``field.fast_gather=false``, no compiled kernel either) with their ratios to the default.

Target (ours): 1024 rays x 43 samples, table 2^16, 2 threads, float32, under 100 ms.

Usage: python benchmarks/bench_field.py [--repeats 10] [--rays 256 1024 4096] [--presets ...]
"""

import statistics
import time

import torch

from tsslam_ref import config, hash_kernel
from tsslam_ref.field import SceneField
from tsslam_ref.mapping import make_map_optimizer
from tsslam_ref.device import peak_memory, tune_cpu_allocator
from tsslam_ref.cli_args import OneLineParser, number_in

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
    (``device.peak_memory``; tracemalloc does not see torch's CPU allocations)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        time_iterations(field, optimizer, points, 1, device)
        return torch.cuda.max_memory_allocated(device) / 2**20
    return peak_memory(device).get("peak_rss_mib", float("nan"))  # nan where Python has no `resource` (Windows)


def main(argv=None):
    parser = OneLineParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--repeats", type=number_in("--repeats", 1, 10000, integer=True), default=10)
    parser.add_argument("--rays", type=number_in("--rays", 1, 10000000, integer=True), nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--presets", nargs="+", choices=sorted(config.PRESETS), default=["tum-cpu", "synthetic-cpu", "tum", "synthetic"])
    parser.add_argument("--threads", type=number_in("--threads", 1, 1024, integer=True), default=2)
    parser.add_argument("--no-reference", action="store_true", help="time only the default path (skip the PyTorch fast path and the reference path)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    allocator = tune_cpu_allocator()
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {args.threads} threads, float32, points in [-3, 3]^3 m (6.5 m box), medians of {args.repeats}, "
          f"glibc allocator tuned: {allocator}")
    if hash_kernel.available():
        print(f"compiled CPU kernel: yes (OneBlob's AVX2 copy: {'yes' if hash_kernel.oneblob_uses_avx2() else 'no'})")
    else:
        print(f"compiled CPU kernel: no ({hash_kernel.load_error()})")
    print(f"{'device':6} {'preset':14} {'log2T':>5} {'samples':>7} {'rays':>5} {'default ms':>10} {'(min)':>7} "
          f"{'torch ms':>9} {'torch/def':>9} {'ref ms':>9} {'ref/def':>8} {'peak MiB':>9}")
    paths = {"default": (True, True), "torch": (True, False), "reference": (False, False)}  # fast_gather, compiled
    # "compiled" switches both compiled kernels, the hash grid's and OneBlob's (field.compiled_oneblob)
    for device in devices:
        for preset in args.presets:
            cfg = config.load(preset)
            samples = cfg.render.n_samples + cfg.render.n_range_d
            generator = torch.Generator().manual_seed(0)
            for n_rays in args.rays:
                points = (torch.rand(n_rays * samples, 3, generator=generator) * 6.0 - 3.0).to(device)
                row = {}
                for path, (fast_gather, compiled) in paths.items():
                    if args.no_reference and path != "default":
                        continue
                    if path == "torch" and (device.type != "cpu" or not hash_kernel.available()):
                        continue  # the default already is the PyTorch fast path
                    cfg.field.fast_gather, cfg.field.compiled_kernel = fast_gather, compiled
                    cfg.field.compiled_oneblob = compiled
                    field = SceneField(cfg.field, BOX, generator=torch.Generator().manual_seed(0)).to(device)
                    optimizer = make_map_optimizer(field, cfg.mapping)
                    row[path] = time_iterations(field, optimizer, points, args.repeats, device)
                    if path == "default":
                        peak = peak_memory_mb(field, optimizer, points, device)
                default_ms, default_min = row["default"]
                torch_ms = row.get("torch", (float("nan"),))[0]
                ref_ms = row.get("reference", (float("nan"),))[0]
                print(f"{device.type:6} {preset:14} {cfg.field.log2_hashmap_size:>5} {samples:>7} {n_rays:>5} "
                      f"{default_ms:>10.1f} {default_min:>7.1f} {torch_ms:>9.1f} {torch_ms / default_ms:>9.2f} "
                      f"{ref_ms:>9.1f} {ref_ms / default_ms:>8.2f} {peak:>9.0f}")
    print("peak MiB on CPU is the process max RSS so far (includes earlier rows).")


if __name__ == "__main__":
    main()
