"""Command line: run TS-SLAM (or the Co-SLAM baseline) on a sequence and write every output.

    python -m tsslam_ref.run                       # bundled TUM fr3/teddy slice, tum-cpu preset
    python -m tsslam_ref.run --data PATH --config tum-cpu --method coslam --out runs/teddy
    python -m tsslam_ref.run --set tracking.iters=30 --set spline.dt=0.2 --frames 0:60

Outputs in ``--out`` (default ``runs/<sequence>-<method>``):

* ``trajectory.txt`` - TUM format (timestamp tx ty tz qx qy qz qw), camera-to-world, OpenCV axes,
  one line per input frame at the frame's own timestamp;
* ``metrics.json`` - ate_rmse_m, rpe_trans_rmse_m, rpe_rot_rmse_deg, n_matched (when ground truth is
  known), frames, frames_per_second, the runtime table, and the reconstruction metrics when a
  ground-truth mesh is next to the data (``gt_mesh.ply``, written by the synthetic generator);
* ``mesh.ply`` - the final map's mesh (marching cubes at ``mesh.voxel_final``);
* ``config.json`` - the resolved config; ``trajectory.png`` and ``errors.png`` - plots;
* ``checkpoint.pt`` - the whole state every ``--checkpoint-every`` frames (``--resume`` continues);
* ``trajectory_<rate>hz.txt`` with velocities when ``--export-rate`` is given (TS-SLAM only).

A run refuses to write into an existing non-empty output folder unless ``--overwrite`` (or
``--resume``) is given.  Partial outputs (trajectory so far) are written atomically while the run
goes, so an interrupted run leaves readable files.

Layer 4 (system).
"""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch

from . import config as config_module
from . import data as data_module
from . import eval as eval_module


def parse_frames(text: Optional[str]):
    """'START:STOP[:STEP]' -> (start, stop or None, step)."""
    if text is None:
        return None
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"--frames must be START:STOP[:STEP], got '{text}'")
    try:
        start = int(parts[0]) if parts[0] else 0
        stop = int(parts[1]) if parts[1] else None
        step = int(parts[2]) if len(parts) == 3 and parts[2] else 1
    except ValueError as error:
        raise ValueError(f"--frames must be integers START:STOP[:STEP], got '{text}'") from error
    if step <= 0 or start < 0 or (stop is not None and stop <= start):
        raise ValueError(f"--frames '{text}' selects no frames (need 0 <= START < STOP and STEP > 0)")
    return start, stop, step


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tsslam_ref.run",
        description="Run TS-SLAM (or the Co-SLAM baseline) on an RGB-D sequence.",
    )
    parser.add_argument("--data", default="", help="dataset folder (default: the bundled TUM fr3/teddy slice)")
    parser.add_argument("--dataset", default=None, choices=["auto", "tum", "scannet", "neural_rgbd", "replica", "folder", "synthetic"],
                        help="dataset layout (default: detected from the folder); 'synthetic' = a folder written by `python -m tsslam_ref.data synthesize`")
    parser.add_argument("--config", default=None, help="preset name (%s) or a config.json; default tum-cpu" % ", ".join(config_module.PRESETS))
    parser.add_argument("--method", default=None, choices=["tsslam", "coslam"], help="trajectory representation (default tsslam)")
    parser.add_argument("--out", default=None, help="output folder (default runs/<sequence>-<method>)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default from the config: 0)")
    parser.add_argument("--device", default=None, choices=["cpu", "cuda", "auto"], help="compute device (default auto)")
    parser.add_argument("--frames", default=None, help="START:STOP[:STEP] frame selection")
    parser.add_argument("--parallel", action="store_true",
                        help="track and map in two threads (not deterministic; default: the sequential loop)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="config override, e.g. --set tracking.iters=20 (repeatable)")
    parser.add_argument("--export-rate", type=float, default=None, metavar="HZ",
                        help="also export the continuous trajectory at this rate with velocities (tsslam)")
    parser.add_argument("--overwrite", action="store_true", help="allow writing into an existing non-empty output folder")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    parser.add_argument("--checkpoint-every", type=int, default=25, help="frames between checkpoints (0 = never)")
    parser.add_argument("--no-mesh", action="store_true", help="skip the final mesh")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def resolve_config(args) -> config_module.Config:
    """Preset or file, then command-line options, then ``--set`` overrides."""
    cfg = config_module.load(args.config or "tum-cpu")
    if args.method:
        cfg.method = args.method
    if args.seed is not None:
        cfg.seed = args.seed
    if args.device:
        cfg.device = args.device
    if args.data:
        cfg.data.path = args.data
    if args.parallel:
        cfg.parallel = True
    if args.dataset:
        cfg.data.dataset = "tum" if args.dataset == "synthetic" else args.dataset
    frames = parse_frames(args.frames)
    if frames is not None:
        cfg.data.frame_start, cfg.data.frame_stop, cfg.data.frame_step = frames
    return config_module.apply_overrides(cfg, args.overrides)


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and ``os.replace``."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "w") as stream:
        stream.write(text)
    os.replace(temporary, path)


def prepare_output(out: Path, overwrite: bool, resume: bool) -> None:
    """Create ``out``; refuse a non-empty existing folder unless overwrite/resume."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"output path {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not (overwrite or resume):
        raise FileExistsError(f"output folder {out} is not empty; pass --overwrite to replace its files or --resume to continue")
    out.mkdir(parents=True, exist_ok=True)


def save_checkpoint(state, path: Path) -> None:
    """The whole loop state (map, optimizer, poses, keyframes, RNG) via torch.save, atomically."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    os.close(handle)
    generator_state = state.generator.get_state() if state.generator is not None else None
    generator = state.generator
    state.generator = None
    try:
        torch.save({"state": state, "generator_state": generator_state}, temporary)
    finally:
        state.generator = generator
    os.replace(temporary, path)


def load_checkpoint(path: Path):
    payload = torch.load(path, weights_only=False)
    state = payload["state"]
    if not hasattr(state, "tracking_output"):  # a checkpoint written before the field existed
        state.tracking_output = {}
    state.generator = torch.Generator(device="cpu")
    if payload["generator_state"] is not None:
        state.generator.set_state(payload["generator_state"])
    return state


def write_partial_trajectory(state, out: Path) -> None:
    from .export import estimated_trajectory

    poses = estimated_trajectory(state).detach().cpu().double().numpy()
    data_module.write_tum_trajectory(out / "trajectory.txt", state.timestamps[: len(poses)], poses, overwrite=True)


def trajectory_metrics(sequence, timestamps: np.ndarray, poses: np.ndarray) -> dict:
    """ATE / RPE against the sequence's ground truth (frames with a finite GT pose)."""
    if sequence.gt_poses is None:
        return {}
    gt = np.asarray(sequence.gt_poses, dtype=np.float64)
    known = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
    if known.sum() < 3:
        return {}
    return eval_module.evaluate_trajectory(timestamps[known], gt[known], timestamps, poses)


def reconstruction_metrics(mesh, gt_mesh, sequence, seed: int) -> dict:
    """Accuracy / completion / ratio after Co-SLAM-style culling of both meshes.

    Both meshes are culled (frustum + occlusion, eval.cull_mesh) with the ground-truth cameras of
    every second frame, so that only what the sequence observed is compared (Co-SLAM culls with the
    GT poses too, spec section 6.2; it also adds hand-picked virtual cameras, which we do not have).
    """
    intrinsics = sequence.intrinsics
    camera = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width, intrinsics.height)
    poses = np.asarray(sequence.gt_poses)[::2]
    culled = eval_module.cull_mesh(mesh, poses, camera)
    culled_gt = eval_module.cull_mesh(gt_mesh, poses, camera)
    if len(culled.faces) == 0 or len(culled_gt.faces) == 0:
        return {"reconstruction_note": "nothing left after culling"}
    return eval_module.mesh_metrics(culled, culled_gt, n_points=50_000, threshold=0.05, seed=seed)


def save_plots(out: Path, sequence, timestamps: np.ndarray, poses: np.ndarray, metrics: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure = plt.figure(figsize=(6, 5))
    axis = figure.add_subplot(projection="3d")
    axis.plot(*poses[:, :3, 3].T, label="estimate", color="tab:red")
    if sequence.gt_poses is not None:
        gt = np.asarray(sequence.gt_poses)
        axis.plot(*gt[:, :3, 3].T, label="ground truth", color="k", linestyle="--")
    axis.set_xlabel("x [m]"), axis.set_ylabel("y [m]"), axis.set_zlabel("z [m]")
    axis.set_title(f"camera-to-world positions, ATE {metrics.get('ate_rmse_m', float('nan')) * 100:.2f} cm")
    axis.legend()
    figure.savefig(out / "trajectory.png", dpi=80)
    plt.close(figure)
    if sequence.gt_poses is not None:
        gt = np.asarray(sequence.gt_poses)
        known = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
        if known.sum() >= 3:
            result = eval_module.ate(gt[known], poses[known])
            figure, axis = plt.subplots(figsize=(6, 3))
            axis.plot(timestamps[known] - timestamps[0], np.asarray(result["errors_m"]) * 100)
            axis.set_xlabel("time since first frame [s]"), axis.set_ylabel("position error after alignment [cm]")
            figure.tight_layout()
            figure.savefig(out / "errors.png", dpi=80)
            plt.close(figure)


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = resolve_config(args)
        sequence = data_module.load_from_config(cfg.data)
    except (ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path("runs") / f"{sequence.name}-{cfg.method}"
    try:
        prepare_output(out, args.overwrite, args.resume)
    except (ValueError, FileExistsError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    from . import device as device_module
    from . import parallel, slam
    from .mesh import extract_mesh, save_mesh

    config_module.save(cfg, str(out / "config.json"))
    state = None
    checkpoint_path = out / "checkpoint.pt"
    if args.resume:
        if not checkpoint_path.exists():
            print(f"error: --resume given but {checkpoint_path} does not exist", file=sys.stderr)
            return 2
        state = load_checkpoint(checkpoint_path)
        print(f"resuming at frame {state.done} of {len(sequence)}")

    device = device_module.resolve_device(cfg.device)
    device_module.tune_cpu_allocator()
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        progress = tqdm(total=len(sequence), desc=f"{cfg.method} on {sequence.name}", unit="frame",
                        initial=state.done if state else 0)

    def on_frame(current) -> None:
        if progress is not None:
            progress.update(1)
        if args.checkpoint_every and current.done % args.checkpoint_every == 0:
            write_partial_trajectory(current, out)
            save_checkpoint(current, checkpoint_path)

    print(f"{cfg.method}: {len(sequence)} frames of {sequence.name} ({sequence.kind}), preset {cfg.name}, device {device}, output {out}")
    try:
        run_loop = parallel.run_slam_in_two_threads if cfg.parallel else slam.run_slam
        result = run_loop(sequence, cfg, device=device, state=state, on_frame=on_frame)
    except slam.TrackingFailure as failure:
        if progress is not None:
            progress.close()
        print(f"error: the run failed: {failure}", file=sys.stderr)
        atomic_write_text(out / "metrics.json", json.dumps({"failed": True, "reason": str(failure)}, indent=2))
        return 3
    if progress is not None:
        progress.close()
    data_module.write_tum_trajectory(out / "trajectory.txt", result.timestamps, result.poses, overwrite=True)
    metrics = {"method": cfg.method, "sequence": sequence.name, "frames": int(len(sequence)),
               "frames_per_second": result.frames_per_second}
    metrics.update(trajectory_metrics(sequence, result.timestamps, result.poses))
    metrics["runtime"] = result.state.timings.table()
    if not args.no_mesh:
        mesh = extract_mesh(result.state.field, None, cfg.mesh.voxel_final, sdf_cutoff=cfg.mesh.sdf_cutoff)
        save_mesh(mesh, out / "mesh.ply", overwrite=True)
        gt_mesh_path = Path(sequence.path) / "gt_mesh.ply"
        if gt_mesh_path.exists() and len(mesh.faces) > 0:
            import trimesh

            gt_mesh = trimesh.load(gt_mesh_path, force="mesh")
            metrics.update(reconstruction_metrics(mesh, gt_mesh, sequence, cfg.seed))
    if args.export_rate:
        if cfg.method != "tsslam":
            print("warning: --export-rate needs --method tsslam (a continuous trajectory); skipped", file=sys.stderr)
        else:
            from .export import export_continuous

            export_continuous(result.state, args.export_rate, out / f"trajectory_{args.export_rate:g}hz.txt")
    atomic_write_text(out / "metrics.json", json.dumps(_jsonable(metrics), indent=2))
    save_plots(out, sequence, result.timestamps, result.poses, metrics)
    if checkpoint_path.exists() and not args.checkpoint_every:
        checkpoint_path.unlink()
    summary = ", ".join(f"{key} {metrics[key]:.4f}" for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg") if key in metrics)
    print(f"done: {len(sequence)} frames at {result.frames_per_second:.2f} frames/s; {summary}; outputs in {out}")
    return 0


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items() if not (isinstance(v, np.ndarray) and v.size > 16)}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


if __name__ == "__main__":
    sys.exit(main())
