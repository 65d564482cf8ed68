"""What a smooth curve can reach: the spline fitted to the ground truth, scored like a SLAM run.

For each stretch of a shipped (or given) hand-held trajectory it resamples ``--frames`` frames at
``--fps``, adds ``--noise`` metres of position noise (``numpy.random.default_rng(--seed)``, as the
offline check of chapter 06), fits the spline of every ``--dts`` knot spacing and the adaptive knot
layout (``knot_policy.place_knots`` at the ``SplineConfig`` defaults) by Eq. (11)
(``spline_fit.fit_trajectory``) and prints, against the noise-free ground truth, the rotational
and translational RPE over one frame (``trajectory_metrics.rpe``) with the median frame-to-frame
rotation of the motion itself.  A TS-SLAM run on that motion cannot get below its layout's row
(docs/system.md, "Adaptive knots": why fr2/desk's rotational RPE stays above the baseline's).

Usage: python benchmarks/curve_floor.py [--stretch tum_rgbd_fr2_desk:0 tum_vi_room1:16 ...]
                                        [--frames 60] [--fps 30] [--dts 0.30 0.25 0.15 0.10]
"""

import argparse

import numpy as np
import torch

from tsslam_ref import data, knot_policy, spline_fit, trajectory_metrics
from tsslam_ref.config import SplineConfig
from tsslam_ref.geometry import rotation_angle_deg
from tsslam_ref.synthetic import resample_trajectory
from tsslam_ref.cli_args import OneLineParser, number_in

STRETCHES = ["tum_rgbd_fr2_desk:0", "tum_vi_room1:16", "tum_vi_room1:20", "tum_vi_room2:16"]


def parse_stretch(text: str):
    """'NAME:START' (start in seconds after the recording's first pose) -> (name, start)."""
    name, _, start = text.partition(":")
    try:
        return name, float(start or 0.0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--stretch {text!r}: expected NAME:START_SECONDS, e.g. tum_vi_room1:16") from None


def median_frame_rotation_deg(poses: np.ndarray) -> float:
    """Median rotation angle (deg) between consecutive camera-to-world poses (K, 4, 4)."""
    relative = np.swapaxes(poses[:-1, :3, :3], -1, -2) @ poses[1:, :3, :3]  # R_i^T R_i+1
    return float(np.median(rotation_angle_deg(relative)))


def curve_rows(times: np.ndarray, truth: torch.Tensor, noisy: torch.Tensor, dts, knots: SplineConfig):
    """[(layout, intervals text, RPE dict)] for each uniform spacing and the adaptive layout."""
    layouts = [(f"uniform {dt:.2f} s", f"{dt:.2f}", spline_fit.fit_trajectory(times, noisy, dt)) for dt in dts]
    boundaries = knot_policy.place_knots(times, noisy[:, :3, :3].numpy(), noisy[:, :3, 3].numpy(), knots.dt,
                                         knots.dt_min, knots.dt_max, knots.rotation_tolerance,
                                         knots.position_tolerance)
    lengths = np.diff(boundaries)
    layouts.append(("adaptive", f"{lengths.min():.2f}-{lengths.max():.2f}",
                    spline_fit.fit_trajectory(times, noisy, knots.dt, boundaries=boundaries)))
    return [(name, spacing, trajectory_metrics.rpe(truth.numpy(), fitted.poses(times).numpy(), delta=1))
            for name, spacing, fitted in layouts]


def main(argv=None):
    parser = OneLineParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--stretch", type=parse_stretch, nargs="+", default=[parse_stretch(s) for s in STRETCHES],
                        help="NAME:START, a shipped trajectory (or a TUM-format file) and seconds from its start")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--fps", type=number_in("--fps", 0, 1000, low_open=True), default=30.0)
    parser.add_argument("--dts", type=number_in("--dts", 0, 10, low_open=True), nargs="+", default=[0.30, 0.25, 0.15, 0.10])
    parser.add_argument("--noise", type=number_in("--noise", 0, 1), default=0.001, help="position noise (m) on the fitted poses")
    parser.add_argument("--seed", type=number_in("--seed", 0, 2**32 - 1, integer=True), default=1)
    args = parser.parse_args(argv)
    if args.frames < 4 or min(args.dts) <= 0:
        parser.error(f"--frames must be >= 4 and --dts > 0, got {args.frames} and {args.dts}")
    knots = SplineConfig()
    print(f"{args.frames} frames at {args.fps:g} Hz, {1000 * args.noise:g} mm position noise (seed {args.seed}); "
          f"RPE over one frame of the fitted curve against the ground truth")
    print("| stretch | frame-to-frame rotation (median, deg) | layout | intervals (s) | RPE deg | RPE cm |")
    print("|---|---|---|---|---|---|")
    for name, start in args.stretch:
        try:
            path = data.trajectory_path(name)
            times, truth = resample_trajectory(path, args.frames, args.fps,
                                               start_time=data.trajectory_origin(path) + start)
        except (OSError, ValueError) as error:
            parser.error(f"--stretch {name}:{start:g}: {error}")
        times, truth = times - times[0], torch.as_tensor(truth, dtype=torch.float64)
        noisy = truth.clone()
        noisy[:, :3, 3] += torch.as_tensor(np.random.default_rng(args.seed).normal(scale=args.noise,
                                                                                   size=(args.frames, 3)))
        rotation = median_frame_rotation_deg(truth.numpy())
        for layout, spacing, rpe in curve_rows(times, truth, noisy, args.dts, knots):
            print(f"| {name} from {start:g} s | {rotation:.2f} | {layout} | {spacing} | "
                  f"{rpe['rpe_rot_rmse_deg']:.3f} | {100 * rpe['rpe_trans_rmse_m']:.3f} |")


if __name__ == "__main__":
    main()
