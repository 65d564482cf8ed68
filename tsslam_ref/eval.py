"""Evaluation command line: trajectory metrics (ATE, RPE) and mesh metrics (Accuracy, Completion).

``python -m tsslam_ref.eval trajectory GT EST`` and ``python -m tsslam_ref.eval mesh REC GT``.

The metrics live in :mod:`tsslam_ref.trajectory_metrics` (association, Horn alignment, ATE, RPE)
and :mod:`tsslam_ref.reconstruction_metrics` (culling, Accuracy / Completion, Depth L1); this
module re-exports their public names, so ``eval.ate(...)`` and ``eval.mesh_metrics(...)`` work.

Side layer (reads TUM files with :mod:`tsslam_ref.data`).  Taught in notebooks/08_evaluation.ipynb;
protocol and deviations in docs/evaluation.md.
"""

import json
import os
import sys
from typing import Dict, Optional, Sequence

import numpy as np
import trimesh

from tsslam_ref.data import ground_truth_at, read_tum_trajectory
from tsslam_ref.reconstruction_metrics import (  # noqa: F401  (re-exported)
    NEAR_PLANE_M,
    OCCLUSION_EPS_M,
    RASTER_PIXEL_BUDGET,
    RUN_POINTS,
    cull_mesh,
    culled_metrics,
    depth_l1,
    mesh_metrics,
    mesh_sizes_differ,
    read_mesh,
    render_depth_zbuffer,
)
from tsslam_ref.trajectory_metrics import (  # noqa: F401  (re-exported)
    DEFAULT_MAX_DIFF_S,
    associate,
    ate,
    evaluate_trajectory,
    horn_alignment,
    rpe,
    trajectory_errors_over_time,
)

__all__ = [
    "DEFAULT_MAX_DIFF_S", "NEAR_PLANE_M", "OCCLUSION_EPS_M", "RASTER_PIXEL_BUDGET", "RUN_POINTS", "associate", "ate",
    "cull_mesh", "culled_metrics", "depth_l1", "evaluate_trajectory", "horn_alignment", "main", "mesh_metrics",
    "mesh_sizes_differ", "read_mesh", "render_depth_zbuffer", "rpe", "trajectory_errors_over_time",
]


# --------------------------------------------------------------------------------------------
# Files and command line


def _warn_if_other_units(rec: trimesh.Trimesh, gt: trimesh.Trimesh, rec_path: str, gt_path: str) -> None:
    """One line on stderr when the meshes' sizes differ ten-fold or more (the metrics are then
    meaningless; the command still prints them)."""
    sizes = mesh_sizes_differ(rec, gt)
    if sizes is not None:
        print(f"warning: {rec_path} spans {sizes[0]:.3g} and {gt_path} {sizes[1]:.3g} (bounding-box diagonals): "
              f"both must be in metres, of the same scene", file=sys.stderr)


def _as_the_run_culled(rec: trimesh.Trimesh, gt: trimesh.Trimesh, args) -> Dict[str, object]:
    """:func:`culled_metrics` with the sequence and seed of the run in folder ``args.cull_like``."""
    from tsslam_ref import config as config_module
    from tsslam_ref.data import load_from_config

    saved = os.path.join(args.cull_like, "config.json")
    if not os.path.isfile(saved):
        raise ValueError(f"--cull-like {args.cull_like}: no config.json there; expected the output folder of a run")
    cfg = config_module.load(saved)
    if not args.data and cfg.data.path and not os.path.isabs(os.path.expanduser(cfg.data.path)):
        raise ValueError(f"--cull-like {args.cull_like}: its config.json records the data folder as "
                         f"'{cfg.data.path}', relative to wherever that run started (an earlier version); pass --data")
    recorded, cfg.data.path = cfg.data.path, args.data or cfg.data.path
    try:
        sequence = load_from_config(cfg.data)
    except (ValueError, OSError) as error:  # the data moved, or changed since the run
        where = "--data" if args.data else f"the data folder its config.json records ({recorded or 'the bundled slice'})"
        raise ValueError(f"--cull-like {args.cull_like}: {where} cannot be read as the run's data ({error}); pass "
                         f"--data with where that data is now") from None
    if sequence.gt_poses is None:
        raise ValueError(f"--cull-like {args.cull_like}: its data {sequence.path} has no ground-truth poses to "
                         f"cull with")
    seed = cfg.seed if args.seed is None else args.seed
    return culled_metrics(rec, gt, sequence, seed, args.threshold, args.points or RUN_POINTS)


def _print_result(result: Dict[str, object], keys: Sequence[str], as_json: bool) -> None:
    chosen = {key: result[key] for key in keys}
    if as_json:
        print(json.dumps(chosen))
    else:
        for key, value in chosen.items():
            print(f"{key}: {value:.6f}" if isinstance(value, float) else f"{key}: {value}")


def _build_parser():
    """The command line: ``trajectory GT EST`` and ``mesh REC GT`` with their options."""
    from tsslam_ref.cli_args import OneLineParser, number_in, user_path

    parser = OneLineParser(prog="python -m tsslam_ref.eval",  # not __doc__: `python -OO` drops it
                           description="Trajectory metrics (ATE, RPE) and mesh metrics (Accuracy, Completion).",
                           epilog="Exit status: 0 done, 2 bad input (one line naming the file and what was expected).")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    trajectory = commands.add_parser("trajectory", help="ATE/RPE of EST against GT (TUM format files)")
    trajectory.add_argument("gt", type=user_path, help="ground truth, 'timestamp tx ty tz qx qy qz qw' per line")
    trajectory.add_argument("est", type=user_path, help="estimate, same format, camera-to-world; one line per time stamp")
    trajectory.add_argument("--max-diff", type=number_in("--max-diff", 0, 10, low_open=True), default=DEFAULT_MAX_DIFF_S,
                            help=f"association tolerance (s), in (0, 10]; default {DEFAULT_MAX_DIFF_S}")
    trajectory.add_argument("--scale", action="store_true", help="Sim(3) alignment (estimate scale)")
    trajectory.add_argument("--delta", type=number_in("--delta", 1, 10**9, integer=True), default=1,
                            help="RPE interval in matched frames, >= 1; default 1")
    trajectory.add_argument("--interpolate", action="store_true",
                            help="score against the ground truth interpolated at the estimate's stamps, as a run scores "
                                 "itself (needs a GT stamp within --max-diff), instead of the nearest GT sample")
    trajectory.add_argument("--json", action="store_true", help="print one JSON object")
    mesh = commands.add_parser("mesh", help="accuracy/completion of REC against GT meshes")
    mesh.add_argument("rec", type=user_path, help="reconstructed mesh (.ply, .obj), in metres")
    mesh.add_argument("gt", type=user_path, help="ground-truth mesh of the same scene, in metres")
    mesh.add_argument("--threshold", type=number_in("--threshold", 0, 100, low_open=True), default=0.05,
                      help="completion-ratio threshold (m), in (0, 100]; default 0.05")
    mesh.add_argument("--points", type=number_in("--points", 1, 10**8, integer=True), default=None,
                      help="surface samples per mesh, 1 to 1e8; default 200000 (50000 with --cull-like)")
    mesh.add_argument("--seed", type=number_in("--seed", 0, 2**63 - 1, integer=True), default=None,
                      help="sampling seed; default 0 (the run's seed with --cull-like)")
    mesh.add_argument("--cull-like", type=user_path, metavar="RUN", default=None,
                      help="cull both meshes as the run in folder RUN did (its config.json: data, frames, seed) and "
                           "score them by its protocol: metrics.json's reconstruction numbers")
    mesh.add_argument("--data", type=user_path, default=None, metavar="PATH",
                      help="with --cull-like: the run's dataset folder where it is now (default: the folder its "
                           "config.json records)")
    mesh.add_argument("--json", action="store_true", help="print one JSON object")
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m tsslam_ref.eval trajectory GT EST`` or ``... mesh REC GT``; bad input -> exit 2."""
    args = _build_parser().parse_args(argv)
    try:
        if args.command == "trajectory":
            gt_times, gt_poses = read_tum_trajectory(args.gt)
            n_gt_read = len(gt_times)
            est_times, est_poses = read_tum_trajectory(args.est, unique_stamps=True)  # one pose per frame
            if args.interpolate:  # GT at the estimate's own stamps, then matched one to one
                at_estimate = ground_truth_at(est_times, gt_times, gt_poses, args.max_diff)
                known = np.all(np.isfinite(at_estimate.reshape(len(at_estimate), -1)), axis=1)
                if not known.any():
                    raise ValueError(f"no stamp of {args.est} has a pose of {args.gt} within {args.max_diff} s (the "
                                     f"estimate spans [{est_times[0]:.6f}, {est_times[-1]:.6f}] s, the ground truth "
                                     f"[{gt_times[0]:.6f}, {gt_times[-1]:.6f}] s); check that both use the same clock")
                gt_times, gt_poses = est_times[known], at_estimate[known]
            result = evaluate_trajectory(
                gt_times, gt_poses, est_times, est_poses, args.max_diff, args.scale, args.delta
            )
            result["n_gt"] = n_gt_read  # the poses read, not those interpolated at the estimate's stamps
            keys = ["ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "n_matched", "n_est", "n_gt", "delta_frames",
                    "scale"]
        else:
            if args.data is not None and args.cull_like is None:
                raise ValueError("--data names the data of the run given by --cull-like; give --cull-like RUN too")
            rec, gt = read_mesh(args.rec), read_mesh(args.gt)
            _warn_if_other_units(rec, gt, args.rec, args.gt)
            keys = ["accuracy_m", "completion_m", "completion_ratio", "threshold_m", "n_points"]
            if args.cull_like is None:
                result = mesh_metrics(rec, gt, args.points or 200_000, args.threshold, args.seed or 0)
            else:
                result = _as_the_run_culled(rec, gt, args)
                keys = list(result) if "reconstruction_note" in result else keys + ["sampling_seed"]
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    _print_result(result, keys, args.json)
    return 0


if __name__ == "__main__":
    from tsslam_ref.cli_args import interruptible

    sys.exit(interruptible(main, "python -m tsslam_ref.eval"))
