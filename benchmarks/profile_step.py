"""Where one iteration's time goes: torch.profiler on a tracking and a global-BA iteration.

The numbers behind docs/system.md, "Where the time goes".  On the bundled TUM teddy slice with a
preset (default ``tum-cpu``) it fits the map to frame 0 (``--fit-iters`` iterations, so the field
is not at its random start), then profiles

* one **tracking** iteration: ``tracking.n_rays`` rays of frame 1 (512 x 43 samples on ``tum-cpu``),
  pose increment -> render_loss -> backward -> pose Adam step, the map frozen;
* one **global-BA / map-update** iteration: ``mapping.n_rays`` rays drawn from frames 0-4 with
  one pose per frame, render_loss with the smoothness term -> backward -> map and pose Adam steps.

For each it prints the median wall time of ``--repeats`` plain runs (no profiler) and the top
operators by self CPU time, per run averaged over three profiled runs (their share of the profiled
total).  Absolute times depend on the machine's load; compare shares, or rows of the same run.

``--tracking-rays 32 64 ... 1024`` instead times the tracking iteration at each ray count and fits
time = fixed + per-ray x rays by least squares: what a smaller ray budget can save, and how much
of an iteration does not shrink with the rays.

Usage: python benchmarks/profile_step.py [--preset tum-cpu] [--repeats 20] [--top 15] [--threads 2]
                                         [--tracking-rays N [N ...]]
"""

import dataclasses
import statistics
import time

import torch
from torch.profiler import ProfilerActivity, profile

from tsslam_ref import config, data
from tsslam_ref.bundle import DiscretePoses, PoseIncrement, frozen
from tsslam_ref.device import frame_to_device, tune_cpu_allocator
from tsslam_ref.field import SceneField
from tsslam_ref.losses import RenderLossSettings, render_loss
from tsslam_ref.mapping import FramePixels, estimate_bound, fit_map, make_map_optimizer
from tsslam_ref.cli_args import OneLineParser, number_in


def build(cfg, fit_iters: int):
    """Field fitted to frame 0 of the bundled slice, the first five frames, their GT poses (5, 4, 4)."""
    sequence = data.load_from_config(cfg.data)
    frames = [frame_to_device(sequence[i], torch.device("cpu"), torch.float32) for i in range(5)]
    poses = torch.stack([torch.as_tensor(sequence[i].pose_c2w, dtype=torch.float32) for i in range(5)])
    bound = estimate_bound([sequence[0]], poses[:1].double(), cfg.field.bound_margin,
                           max_depth=min(cfg.data.depth_trunc, cfg.render.far))
    field = SceneField(cfg.field, torch.as_tensor(bound, dtype=torch.float32),
                       generator=torch.Generator().manual_seed(0))
    optimizer = make_map_optimizer(field, cfg.mapping)
    settings = RenderLossSettings.from_config(cfg)
    generator = torch.Generator().manual_seed(0)
    fit_map(field, optimizer, frames[:1], poses[:1], settings, fit_iters, cfg.mapping.first_n_rays, generator)
    return field, optimizer, frames, poses, settings, generator


def tracking_step(cfg, field, frames, poses, settings, generator):
    """A callable running one tracking iteration on frame 1 (fresh rays drawn once, as tracking does)."""
    rays = frames[1].sampled_rays(cfg.tracking.n_rays, generator, cfg.tracking.ignore_edge)
    increment = PoseIncrement(poses[1])
    pose_optimizer = increment.optimizer(cfg.tracking.lr_rot, cfg.tracking.lr_trans)

    def step():
        with frozen(field):
            loss, _ = render_loss(field, rays, increment(), settings, generator=generator)
            pose_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            pose_optimizer.step()

    return step


def ba_step(cfg, field, optimizer, frames, poses, settings, generator):
    """A callable running one global-BA iteration: map + frames 1-4's poses, smoothness term on."""
    pixels = FramePixels(frames)
    fixed = torch.zeros(len(frames), dtype=torch.bool)
    fixed[0] = True
    pose_model = DiscretePoses(poses, fixed, cfg.mapping.lr_rot, cfg.mapping.lr_trans)
    pose_optimizer = torch.optim.Adam(pose_model.parameter_groups())

    def step():
        rays = pixels.sample(cfg.mapping.n_rays, generator)
        optimizer.zero_grad(set_to_none=True)
        pose_optimizer.zero_grad(set_to_none=True)
        loss, _ = render_loss(field, rays, pose_model.poses()[rays.frame_ids], settings, generator, smoothness=True)
        loss.backward()
        optimizer.step()
        pose_optimizer.step()

    return step


def median_ms(step, repeats: int) -> float:
    for _ in range(3):
        step()
    timings = []
    for _ in range(repeats):
        start = time.perf_counter()
        step()
        timings.append(1000 * (time.perf_counter() - start))
    return statistics.median(timings)


def profile_table(step, top: int) -> str:
    """Top operators by self CPU time of 3 profiled runs, with their share of the total."""
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(3):
            step()
    events = prof.key_averages()
    total = sum(event.self_cpu_time_total for event in events)
    rows = sorted(events, key=lambda event: event.self_cpu_time_total, reverse=True)[:top]
    lines = [f"  {'operator':44} {'self ms/it':>10} {'share':>6} {'calls/it':>8}"]
    for event in rows:
        lines.append(f"  {event.key[:44]:44} {event.self_cpu_time_total / 3000:>10.2f} "
                     f"{100 * event.self_cpu_time_total / total:>5.1f}% {event.count / 3:>8.0f}")
    lines.append(f"  {'all operators':44} {total / 3000:>10.2f}")
    return "\n".join(lines)


def tracking_ray_scaling(cfg, field, frames, poses, settings, generator, ray_counts, repeats: int) -> str:
    """Median tracking-iteration time at each ray count, and the least-squares line through them."""
    rows, times = [f"  {'rays':>6} {'ms':>8}"], []
    for n_rays in ray_counts:
        scaled = dataclasses.replace(cfg, tracking=dataclasses.replace(cfg.tracking, n_rays=n_rays))
        times.append(median_ms(tracking_step(scaled, field, frames, poses, settings, generator), repeats))
        rows.append(f"  {n_rays:>6} {times[-1]:>8.2f}")
    if len(set(ray_counts)) >= 2:
        per_ray, fixed = statistics.linear_regression(ray_counts, times)
        rows.append(f"  fit: {fixed:.2f} ms fixed + {per_ray:.4f} ms per ray")
    return "\n".join(rows)


TUM_PRESETS = [name for name in sorted(config.PRESETS) if config.load(name).data.dataset in ("tum", "auto")]
"""The presets that can read the bundled TUM slice this script profiles on (``replica`` and
``scannet`` name other layouts)."""


def main(argv=None):
    parser = OneLineParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--preset", default="tum-cpu", choices=TUM_PRESETS,
                        help="a preset for the bundled TUM slice (default tum-cpu)")
    parser.add_argument("--repeats", type=number_in("--repeats", 1, 10000, integer=True), default=20)
    parser.add_argument("--top", type=number_in("--top", 1, 10000, integer=True), default=15)
    parser.add_argument("--threads", type=number_in("--threads", 1, 1024, integer=True), default=2)
    parser.add_argument("--fit-iters", type=number_in("--fit-iters", 1, 100000, integer=True), default=50)
    parser.add_argument("--tracking-rays", type=int, nargs="+", default=None,
                        help="time the tracking iteration at these ray counts (and fit a line) instead of profiling")
    args = parser.parse_args(argv)
    if args.tracking_rays is not None and min(args.tracking_rays) < 1:
        parser.error(f"--tracking-rays must be positive, got {args.tracking_rays}")
    torch.set_num_threads(args.threads)
    tune_cpu_allocator()
    cfg = config.load(args.preset)
    field, optimizer, frames, poses, settings, generator = build(cfg, args.fit_iters)
    samples = cfg.render.n_samples + cfg.render.n_range_d
    if args.tracking_rays is not None:
        print(f"torch {torch.__version__}, {args.threads} threads, preset {args.preset}, "
              f"tracking iteration x {samples} samples, median of {args.repeats}")
        print(tracking_ray_scaling(cfg, field, frames, poses, settings, generator, args.tracking_rays, args.repeats))
        return
    steps = {
        f"tracking iteration ({cfg.tracking.n_rays} rays x {samples} samples)":
            tracking_step(cfg, field, frames, poses, settings, generator),
        f"global-BA iteration ({cfg.mapping.n_rays} rays x {samples} samples, smoothness on)":
            ba_step(cfg, field, optimizer, frames, poses, settings, generator),
    }
    print(f"torch {torch.__version__}, {args.threads} threads, preset {args.preset}")
    for name, step in steps.items():
        print(f"\n{name}: median {median_ms(step, args.repeats):.1f} ms over {args.repeats} runs")
        print(profile_table(step, args.top))


if __name__ == "__main__":
    main()
