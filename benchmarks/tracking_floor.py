"""Tracking alone against a map fitted with ground-truth poses: what the tracker itself resolves.

The numbers behind docs/system.md, "Tracking alone, against a map fitted at the true poses".  A
SLAM run mixes two error sources, the map built from estimated poses and the tracker's own
convergence.  This script takes the first out: on the bundled TUM teddy slice (or ``--data``) it
fits the map to every ``--map-every``-th frame of the first ``--frames`` frames at their
ground-truth poses (``--map-iters`` iterations of ``--map-rays`` rays), freezes it, and tracks every
frame with the package's ``tracking.track_frame``, twice:

* **from the ground truth**: each frame starts at its true pose, so what remains is where the
  tracking loss's minimum (as Adam finds it in the preset's iterations) lies;
* **from constant velocity**: each frame starts from the prediction of the two frames tracked
  before it, as in the SLAM loop, so what is added is how far tracking gets from a real start.

For each start it prints the ATE and RPE (metres -> cm, degrees), the Sim(3) scale of the tracked
poses against the ground truth (above 1: the tracked path is shorter) and the mean error along the
direction travelled since frame 0 (negative: behind the camera), and the milliseconds per frame.
``--try KEY=VALUE[,KEY=VALUE...]`` adds a row pair for a changed setting of ``tracking``,
``render`` or ``loss`` (for example ``tracking.iters=40`` or
``tracking.lr_rot=1e-3,tracking.lr_trans=1e-3``), tracked on the same frozen map with the same rays
(drawn once, by their own generator: a setting that draws more or fewer random numbers cannot
change them) and the same seed for the depth samples.  The frames are loaded with the preset's
image size and crop (``data.resize_width``, ``data.crop_edge``), as the SLAM loop loads them.
Deterministic for a given seed.

Usage: python benchmarks/tracking_floor.py [--frames 40] [--map-every 5] [--preset tum-cpu]
                                           [--try KEY=VALUE[,...]] ... [--seed 0] [--threads 2]
"""

import time
from typing import Dict, List

import numpy as np
import torch

from tsslam_ref import config, data, slam
from tsslam_ref.cli_args import OneLineParser, number_in
from tsslam_ref.device import frame_to_device, tune_cpu_allocator
from tsslam_ref.losses import RenderLossSettings
from tsslam_ref.mapping import fit_map
from tsslam_ref.tracking import constant_velocity_init, track_frame
from tsslam_ref.trajectory_metrics import evaluate_trajectory


def fit_ground_truth_map(sequence, cfg: config.Config, frames: List, ground_truth: torch.Tensor, map_every: int,
                         iters: int, n_rays: int):
    """The loop's initial state with its map fitted to every ``map_every``-th frame at its true pose
    (ground_truth (N, 4, 4) camera-to-world)."""
    state = slam.initial_state(sequence, cfg, torch.device("cpu"))
    chosen = list(range(0, len(frames), map_every))
    poses = ground_truth[chosen]
    fit_map(state.field, state.map_optimizer, [frames[i] for i in chosen], poses, state.loss_settings,
            iters=iters, n_rays=n_rays, generator=state.generator)
    return state


TRY_SECTIONS = ("tracking", "render", "loss")
"""What ``--try`` may change: the map is fitted once, with the preset's settings, and the frames
are loaded once."""


def track_all(state, cfg: config.Config, frames: List, ground_truth: torch.Tensor) -> Dict[str, object]:
    """Track frames 1.. from their true poses and from constant velocity; (N, 4, 4) poses of each
    (frame 0 at its true pose) and the median seconds per constant-velocity frame.  The rays come
    from a generator of their own (seed ``cfg.seed``), the depth samples of each start from
    another (seeds ``cfg.seed`` + 1 and + 2)."""
    ray_generator = torch.Generator().manual_seed(cfg.seed)
    rays = [None] + [frame.sampled_rays(cfg.tracking.n_rays, ray_generator, ignore_edge=cfg.tracking.ignore_edge)
                     for frame in frames[1:]]
    settings = RenderLossSettings.from_config(cfg)
    truth_samples, predicted_samples = (torch.Generator().manual_seed(cfg.seed + k) for k in (1, 2))
    from_truth, from_prediction, seconds = [ground_truth[0]], [ground_truth[0]], []
    for i in range(1, len(frames)):
        from_truth.append(track_frame(state.field, rays[i], ground_truth[i], cfg.tracking, settings,
                                      generator=truth_samples).pose)
        before = from_prediction[-2] if i >= 2 else None
        start = time.perf_counter()
        from_prediction.append(track_frame(state.field, rays[i], constant_velocity_init(from_prediction[-1], before),
                                           cfg.tracking, settings, generator=predicted_samples).pose)
        seconds.append(time.perf_counter() - start)
    return {"ground truth": torch.stack(from_truth), "constant velocity": torch.stack(from_prediction),
            "seconds": float(np.median(seconds))}


def scores(sequence, ground_truth: np.ndarray, poses: np.ndarray) -> Dict[str, float]:
    """One table row's figures for (N, 4, 4) poses against the (N, 4, 4) ground truth: ATE and RPE
    (cm, degrees), the Sim(3) scale and the mean error along the direction travelled since frame 0 (cm)."""
    times = sequence.timestamps[: len(poses)]
    rigid = evaluate_trajectory(times, ground_truth, times, poses)
    similar = evaluate_trajectory(times, ground_truth, times, poses, with_scale=True)
    travelled = ground_truth[1:, :3, 3] - ground_truth[:1, :3, 3]
    error = poses[1:, :3, 3] - ground_truth[1:, :3, 3]
    along = np.sum(travelled * error, axis=1) / np.maximum(np.linalg.norm(travelled, axis=1), 1e-9)
    return {"ate_cm": 100 * rigid["ate_rmse_m"], "rpe_cm": 100 * rigid["rpe_trans_rmse_m"],
            "rpe_deg": rigid["rpe_rot_rmse_deg"], "scale": similar["scale"], "along_cm": 100 * float(along.mean())}


def table_cells(figures: Dict[str, float]) -> str:
    """:func:`scores` as the table's cells."""
    return (f"{figures['ate_cm']:6.2f} | {figures['rpe_cm']:6.2f} | {figures['rpe_deg']:6.3f} | "
            f"{figures['scale']:6.4f} | {figures['along_cm']:+6.2f}")


def main() -> None:
    parser = OneLineParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--data", default="", help="dataset folder (default: the bundled TUM slice)")
    parser.add_argument("--preset", default="tum-cpu")
    parser.add_argument("--frames", type=number_in("--frames", 3, 100000, integer=True), default=40, help="first N frames (default 40)")
    parser.add_argument("--map-every", type=number_in("--map-every", 1, 100000, integer=True), default=5)
    parser.add_argument("--map-iters", type=number_in("--map-iters", 1, 100000, integer=True), default=400)
    parser.add_argument("--map-rays", type=number_in("--map-rays", 1, 10**7, integer=True), default=2048)
    parser.add_argument("--try", dest="variants", action="append", default=[], metavar="KEY=VALUE[,KEY=VALUE]")
    parser.add_argument("--seed", type=number_in("--seed", 0, 2**32 - 1, integer=True), default=0)
    parser.add_argument("--threads", type=number_in("--threads", 1, 1024, integer=True), default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    tune_cpu_allocator()
    try:  # a preset, setting or folder that is not there: one line, as the other benchmarks say it
        base = config.apply_overrides(config.load(args.preset), [f"seed={args.seed}"])
        variants = [("preset", base)] + [(text, config.apply_overrides(base, text.split(","))) for text in args.variants]
        for text in args.variants:
            for key in (item.split("=", 1)[0].strip() for item in text.split(",")):
                if key.split(".", 1)[0] not in TRY_SECTIONS:
                    raise ValueError(f"--try {text}: {key} is not a setting of {', '.join(TRY_SECTIONS)} (the map is "
                                     f"fitted and the frames are loaded once, with the preset's settings)")
        sequence = data.load_sequence(args.data or data.default_sequence_path(), frame_stop=args.frames,
                                      resize_width=base.data.resize_width, crop_edge=base.data.crop_edge)
    except (ValueError, OSError) as error:
        parser.error(str(error))
    if sequence.gt_poses is None:
        raise SystemExit(f"{sequence.name}: no ground-truth poses; this script needs them for the map and the scores")
    frames = [frame_to_device(sequence[i], torch.device("cpu"), torch.float32) for i in range(len(sequence))]
    ground_truth = torch.as_tensor(np.asarray(sequence.gt_poses, dtype=np.float64), dtype=torch.float32)
    if not torch.isfinite(ground_truth).all():
        raise SystemExit(f"{sequence.name}: a frame has no ground-truth pose in the first {len(frames)} frames")
    start = time.perf_counter()
    state = fit_ground_truth_map(sequence, base, frames, ground_truth, args.map_every, args.map_iters, args.map_rays)
    mapped = list(range(0, len(frames), args.map_every))
    shown = ", ".join(str(i) for i in mapped[:4]) + (", ..." if len(mapped) > 4 else "")
    print(f"{sequence.name}: {len(frames)} frames, map fitted at the true poses of frames {shown} "
          f"({args.map_iters} x {args.map_rays} rays, {time.perf_counter() - start:.0f} s), preset {base.name}, "
          f"seed {args.seed}\n")
    print("| setting | start | ATE cm | RPE cm | RPE deg | Sim(3) scale | along-path cm | ms per frame |")
    print("|---|---|---|---|---|---|---|---|")
    truth = ground_truth.double().numpy()
    for name, cfg in variants:
        tracked = track_all(state, cfg, frames, ground_truth)
        for start_name in ("ground truth", "constant velocity"):
            poses = tracked[start_name].detach().double().numpy()
            shown = f"{1000 * tracked['seconds']:.0f}" if start_name == "constant velocity" else ""
            print(f"| {name} | {start_name} | {table_cells(scores(sequence, truth, poses))} | {shown} |", flush=True)


if __name__ == "__main__":
    main()
