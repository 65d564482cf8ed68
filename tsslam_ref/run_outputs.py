"""What a finished (or running) command-line run writes: trajectory, metrics, mesh, plots.

Layer 4 (system support).  :func:`write_outputs` writes ``trajectory.txt``, ``frames.csv`` (one row
per frame, ``run_summaries.py``), ``metrics.json`` (ATE / RPE against the ground truth, the runtime
table, the peak memory, and the reconstruction metrics after Co-SLAM-style culling when a
ground-truth mesh is known), ``mesh.ply``, the continuous export and the plots of a finished run;
:func:`write_partial_outputs` writes the trajectory and ``frames.csv`` so far while the run goes.
Every file is written atomically (``files.py``).  Which names are a run's
(:func:`is_output_name`), the checks on an output folder before a run (:func:`check_output_folder`)
and the removal of an earlier run's files (``--overwrite``) live here too.  ``run.py`` prepares the
run and calls these.
"""

import json
import os
import re
import socket
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, List

try:
    import fcntl
except ImportError:  # Windows: runs do not lock their folder
    fcntl = None

import numpy as np

from . import data as data_module
from . import trajectory_metrics as trajectory_metrics_module
from .device import peak_memory, run_environment
from .files import atomic_path, atomic_write_text, is_temporary_of
from .run_summaries import (OUTSIDE_BOX_WARNING, frames_table, motion_summary, outside_box_summary,
                            spline_offset_summary, spline_summary)

OUTPUT_NAMES = ("trajectory.txt", "frames.csv", "metrics.json", "mesh.ply", "config.json", "trajectory.png",
                "errors.png", "checkpoint.pt")
"""Files a run writes into its folder (plus ``trajectory_<rate>hz.txt``); ``--overwrite`` removes only these."""
_EXPORT_NAME = re.compile(r"trajectory_[0-9.e+-]+hz\.txt")


def is_output_name(name: str) -> bool:
    """Whether ``name`` is a file that a run of ours writes (see :data:`OUTPUT_NAMES`)."""
    return name in OUTPUT_NAMES or _EXPORT_NAME.fullmatch(name) is not None


def check_output_folder(out: Path, overwrite: bool, resume: bool, data_folder: str) -> None:
    """Refuse an unusable ``--out`` before anything is written (``run.prepare`` calls it): ValueError
    naming the folder and what to do."""
    if out.exists() and out.resolve() == Path(data_folder).resolve():  # e.g. trajectory.txt is a layout's GT
        raise ValueError(f"--out {out} is the dataset folder itself: the run's files would mix with the data's "
                         f"(and --overwrite would replace files of the same name); choose another folder")
    if out.is_symlink() and not out.exists():
        raise ValueError(f"output folder {out} is a symbolic link to a missing target ({out.readlink()}); "
                         f"expected a folder or a new name")
    if out.exists() and not out.is_dir():
        raise ValueError(f"output path {out} exists and is not a folder; expected a folder or a new name")
    if not out.exists():
        if resume:
            raise ValueError(f"--resume given but the output folder {out} does not exist")
        parent = out.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise ValueError(f"cannot create the output folder {out}: {parent} is not a folder")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise ValueError(f"cannot create the output folder {out}: no permission to write in {parent}")
        return
    if not os.access(out, os.W_OK | os.X_OK):
        raise ValueError(f"output folder {out}: no permission to write in it")
    _refuse_if_held(out)
    names = [entry.name for entry in out.iterdir()]
    if names and not (overwrite or resume):
        ours = sorted(name for name in names if is_output_name(name))
        leftovers = [name for name in names if is_temporary_of(name, is_output_name) or name == LOCK_NAME]
        if ours or leftovers:  # a run removes the leftovers too
            removed = ours + ([f"{len(leftovers)} file(s) a killed run left"] if leftovers else [])
            kept = len(names) - len(ours) - len(leftovers)
            others = f" and keep {kept} other {'entry' if kept == 1 else 'entries'}" if kept else ""
            replaced = f"it would replace {', '.join(removed)}{others}"
        else:
            replaced = f"none of its {len(names)} entries is a file a run writes"
        or_resume = " or --resume to continue it" if (out / "checkpoint.pt").is_file() else ""  # else refused
        raise ValueError(f"output folder {out} is not empty; pass --overwrite to replace the files of an earlier run "
                         f"({replaced}){or_resume}")
    for name in names:
        entry = out / name
        if is_output_name(name) and entry.is_dir() and not entry.is_symlink():
            raise ValueError(f"{entry} is a folder; a run writes a file of that name, so move it away first")


def remove_previous_outputs(out: Path) -> List[Path]:
    """Remove the files an earlier run of ours wrote in ``out`` (:func:`is_output_name`), links
    included (the link, never its target); every other file stays.  Returns what was removed."""
    removed = []
    for entry in sorted(out.iterdir()):
        if is_output_name(entry.name) and (entry.is_symlink() or entry.is_file()):
            entry.unlink()
            removed.append(entry)
    return removed


class FolderInUse(ValueError):
    """Another going run holds the output folder (:func:`output_folder_lock`)."""


LOCK_NAME = "run.lock"
"""The file a going run holds locked in its folder (``flock``; it names the process, host and start
time); the run removes it as it ends.  A killed run's file is left, unlocked: the kernel released the
lock with the process, so the next run takes it."""


@contextmanager
def output_folder_lock(out: Path) -> Iterator[Path]:
    """Create ``out`` and hold it for this process while the block runs: a second run on the same
    folder (``--resume`` or ``--overwrite`` beside a going run, from any process) gets
    :class:`FolderInUse` naming the other run.  Without ``fcntl`` (Windows) nothing is locked."""
    out.mkdir(parents=True, exist_ok=True)
    lock = out / LOCK_NAME
    if fcntl is None:
        yield lock
        return
    while True:
        handle = open(lock, "a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            raise FolderInUse(_in_use_message(out)) from None
        try:
            if os.path.samestat(os.fstat(handle.fileno()), os.stat(lock)):
                break  # the file at the name, not one the run before us removed as we opened it
        except FileNotFoundError:  # removed as we opened it: open the new one
            pass
        handle.close()
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"process {os.getpid()} on {socket.gethostname()} since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        handle.flush()
        yield lock
    finally:
        lock.unlink(missing_ok=True)  # while still locked: no other run holds this file
        handle.close()


def _refuse_if_held(out: Path) -> None:
    """:class:`FolderInUse` when a going run holds ``out``'s lock (checked without taking it)."""
    lock = out / LOCK_NAME
    if fcntl is None or not lock.is_file():
        return
    with open(lock) as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FolderInUse(_in_use_message(out)) from None


def _in_use_message(out: Path) -> str:
    try:
        holder = (out / LOCK_NAME).read_text().strip() or "its details not written yet"
    except OSError:
        holder = "its details unreadable"
    return f"another run ({holder}) is writing {out}; wait for it to end or choose another --out"


SMALL_CROP_SHARE = 0.025
"""A crop of more than this share of the width per side (16 px of 640; Co-SLAM's presets crop 8-10)
is a full-size preset's crop on smaller frames: the run notes it."""


def data_notes(sequence) -> List[str]:
    """What the run says about its data before it starts: frames left out, a camera chosen by default."""
    notes = []
    if sequence.frames_without_gt:
        notes.append(f"{sequence.frames_without_gt} frame(s) of {sequence.path} have no ground-truth pose and are not "
                     f"used (--frames counts the frames that have one); --set data.require_gt=false keeps them")
    if sequence.colour_without_depth:
        notes.append(f"{sequence.colour_without_depth} colour image(s) in {sequence.path / 'rgb.txt'} have no depth "
                     f"image within 0.02 s and are not used")
    width, height, crop = sequence.native_intrinsics.width, sequence.native_intrinsics.height, sequence.crop_edge
    if crop > SMALL_CROP_SHARE * width:  # a full-size preset's crop (10 px of 640) on small frames
        unenlarged = sequence.resize_width is not None and sequence.resize_width > width - 2 * crop
        notes.append(f"these frames are {width}x{height} px: data.crop_edge = {crop} px per side (made for 640-px "
                     f"frames) removes {100 * 2 * crop / width:.0f} % of their width"
                     + (f", and data.resize_width = {sequence.resize_width} does not enlarge them" if unenlarged
                        else "")
                     + "; for frames this small use --config tum-cpu or synthetic-cpu, or --set data.crop_edge=0")
    return notes + ([sequence.camera_note] if sequence.camera_note else [])


def close_progress(progress) -> None:
    """Close the progress bar (None: there is none)."""
    if progress is not None:
        progress.close()


def advance(progress, state, reached: dict) -> None:
    """One frame done: move the progress bar (None: there is none), and warn once when the frame's
    measured surface lies mostly outside the map's box, set from frame 0's view."""
    if progress is not None:
        progress.update(1)
    # the frame just done: with --parallel, tracking has logged frames ahead of it
    entry = next((entry for entry in reversed(state.log) if entry.get("frame") == state.done - 1), {})
    if entry.get("outside_box", 0.0) > OUTSIDE_BOX_WARNING and not reached.get("outside_box_warned"):
        reached["outside_box_warned"] = True
        low, high = state.field.bound[:, 0].tolist(), state.field.bound[:, 1].tolist()
        box = ", ".join(f"[{a:.2f}, {b:.2f}]" for a, b in zip(low, high))
        origin = "set from frame 0's view" if state.cfg.field.bound is None else "field.bound"
        say = progress.write if progress is not None else print  # tqdm's write keeps the bar whole
        say(f"warning: frame {entry['frame']}: {100 * entry['outside_box']:.0f} % of its measured surface lies outside "
            f"the map's box ({box} m, {origin}); the map cannot hold that surface and the mesh misses it. If the "
            f"camera leaves the box, give one that covers the scene: --set "
            f"'field.bound=[[xmin,xmax],[ymin,ymax],[zmin,zmax]]' (metres, world frame)", file=sys.stderr)


def data_error_advice(out: Path, reached: dict, error: Exception, data_folder: str) -> str:
    """What to do after the loop stopped on ``error`` (``reached``: the progress record, its
    ``checkpoint`` the frames the last checkpoint holds): a frame of the data that could not be read
    (its message names a file under ``data_folder``), or another cause."""
    if data_folder and data_folder in str(error):
        if (out / "checkpoint.pt").is_file():
            return (f"after replacing the file, run the same command with --resume to continue from its checkpoint "
                    f"({reached['checkpoint']} frames done); after removing the frame from the lists instead, "
                    f"with --overwrite")
        return "after fixing the data, run the same command with --overwrite"
    return f"after fixing the cause, run the same command with {restart_advice(out)}"


def restart_advice(out: Path) -> str:
    """How a stopped run in ``out`` starts again: from its checkpoint when it has one."""
    return "--resume (from its checkpoint) or --overwrite" if (out / "checkpoint.pt").is_file() else "--overwrite"


def write_partial_outputs(state, out: Path) -> None:
    """The trajectory estimated so far as ``out/trajectory.txt`` (TUM format) and the per-frame log
    so far as ``out/frames.csv``, each atomically."""
    from .export import estimated_trajectory

    poses = estimated_trajectory(state).detach().cpu().double().numpy()
    data_module.write_tum_trajectory(out / "trajectory.txt", state.timestamps[: len(poses)], poses, overwrite=True)
    atomic_write_text(out / "frames.csv", frames_table(state.log, state.timestamps[: len(poses)]))


def export_file_name(rate_hz: float) -> str:
    """``trajectory_<rate>hz.txt`` with every digit of the rate as given (33.33333 and 33.33334 Hz
    are two files, not one that the second run replaces)."""
    return f"trajectory_{rate_hz:.15g}hz.txt"


def ground_truth_known(sequence):
    """(gt (N, 4, 4) float64 camera-to-world, known (N,) bool: a finite GT pose), or None when the
    sequence has no ground truth."""
    if sequence.gt_poses is None:
        return None
    gt = np.asarray(sequence.gt_poses, dtype=np.float64)
    return gt, np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)


def _known_ground_truth(sequence):
    """:func:`ground_truth_known`, or None when fewer than 3 frames have a GT pose (too few to align)."""
    ground_truth = ground_truth_known(sequence)
    return ground_truth if ground_truth is not None and ground_truth[1].sum() >= 3 else None


def trajectory_metrics(sequence, timestamps: np.ndarray, poses: np.ndarray) -> dict:
    """ATE / RPE against the sequence's ground truth (frames with a finite GT pose)."""
    ground_truth = _known_ground_truth(sequence)
    if ground_truth is None:
        return {}
    gt, known = ground_truth
    return trajectory_metrics_module.evaluate_trajectory(timestamps[known], gt[known], timestamps, poses)


def reconstruction_metrics(mesh, gt_mesh, sequence, seed: int) -> dict:
    """Accuracy / completion / ratio of the run's mesh by the run's protocol
    (``reconstruction_metrics.culled_metrics``: both meshes culled with the ground-truth cameras of
    every second frame, raw camera, 50,000 points); a ``reconstruction_note`` (meshes of ten-fold
    different sizes, nothing left after culling) is also printed as a warning."""
    from .reconstruction_metrics import CULL_EVERY, culled_metrics  # lazy: trimesh, only when there is a GT mesh

    cameras = len(range(0, len(sequence), CULL_EVERY))
    print(f"scoring the mesh against gt_mesh.ply: culling both meshes with {cameras} ground-truth cameras "
          f"(at 640x480 about 0.4 s each; --no-mesh skips it)", flush=True)
    result = culled_metrics(mesh, gt_mesh, sequence, seed)
    if "reconstruction_note" in result:
        print(f"warning: reconstruction metrics: {result['reconstruction_note']}", file=sys.stderr)
    return result


def save_plots(out: Path, sequence, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """``trajectory.png`` (positions on equal axes; with at least 3 ground-truth poses the estimate
    aligned onto them as the ATE aligns it) and ``errors.png`` (that position error over time)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ground_truth = _known_ground_truth(sequence)
    result = None
    if ground_truth is not None:
        gt, known = ground_truth
        result = trajectory_metrics_module.ate(gt[known], poses[known])
    figure = _trajectory_figure(plt, poses[:, :3, 3], ground_truth, result)
    with atomic_path(out / "trajectory.png") as temporary:
        figure.savefig(temporary, dpi=80, format="png")
    plt.close(figure)
    if result is not None:
        figure, axis = plt.subplots(figsize=(6, 3))
        axis.plot(timestamps[known] - timestamps[0], np.asarray(result["errors_m"]) * 100)
        axis.set_xlabel("time since first frame [s]"), axis.set_ylabel("position error [cm]")
        axis.set_title(f"ATE per frame, after one rigid alignment fitted on these {int(known.sum())} frames",
                       fontsize=9)
        figure.tight_layout()
        with atomic_path(out / "errors.png") as temporary:
            figure.savefig(temporary, dpi=80, format="png")
        plt.close(figure)


def _trajectory_figure(plt, positions: np.ndarray, ground_truth, result):
    """3-D plot of (N, 3) estimated positions, aligned onto the ground truth when ``result`` (the
    :func:`ate` of the known frames) is given; equal axis scales, a dot at each start."""
    figure = plt.figure(figsize=(6, 5))
    axis = figure.add_subplot(projection="3d")
    curves = []
    if result is None:
        curves.append((positions, "estimate", "tab:red", "-"))
        title = "camera positions (camera-to-world), no ground truth to align to"
    else:
        gt, known = ground_truth
        curves.append((np.asarray(result["est_positions_aligned_m"]), "estimate, aligned", "tab:red", "-"))
        curves.append((gt[known, :3, 3], "ground truth", "k", "--"))
        title = f"camera positions, estimate aligned as for the ATE ({result['ate_rmse_m'] * 100:.2f} cm)"
    for points, label, colour, style in curves:
        axis.plot(*points.T, label=label, color=colour, linestyle=style)
        axis.scatter(*points[:1].T, color=colour, s=20)  # the start
    every = np.concatenate([points for points, *_ in curves])
    centre, half = every.mean(axis=0), max(float(np.ptp(every, axis=0).max()) / 2.0, 1e-3)
    axis.set_xlim(centre[0] - half, centre[0] + half), axis.set_ylim(centre[1] - half, centre[1] + half)
    axis.set_zlim(centre[2] - half, centre[2] + half)
    axis.set_box_aspect((1, 1, 1))
    for side in (axis.xaxis, axis.yaxis, axis.zaxis):  # few ticks: long metre labels overlap otherwise
        side.set_major_locator(plt.MaxNLocator(4))
    axis.set_xlabel("x [m]"), axis.set_ylabel("y [m]"), axis.set_zlabel("z [m]")
    axis.set_title(title, fontsize=9)
    axis.legend(fontsize=8)
    return figure


def _why_no_metrics(sequence) -> str:
    """The closing line's words when a run has no ATE / RPE."""
    ground_truth = ground_truth_known(sequence)
    if ground_truth is None or not ground_truth[1].any():
        return "no ground-truth poses, so no ATE / RPE"
    return f"only {int(ground_truth[1].sum())} frames with a ground-truth pose, so no ATE / RPE (they need 3)"


def mesh_outputs(plan, field) -> dict:
    """Write ``mesh.ply`` of the final map; returns the reconstruction metrics (when a GT mesh is
    known), or a ``mesh_note`` when the map holds no surface to mesh or its grid is too large: the
    run's trajectory and metrics are written either way."""
    from .mesh import extract_mesh, save_mesh

    cfg = plan.cfg
    try:
        mesh = extract_mesh(field, None, cfg.mesh.voxel_final, sdf_cutoff=cfg.mesh.sdf_cutoff)
    except ValueError as error:
        note = f"no mesh.ply: {error}"
        print(f"warning: {note}", file=sys.stderr)
        return {"mesh_note": note}
    save_mesh(mesh, plan.out / "mesh.ply", overwrite=True)
    if plan.gt_mesh is None or len(mesh.faces) == 0:
        return {}
    return reconstruction_metrics(mesh, plan.gt_mesh, plan.sequence, cfg.seed)


def write_outputs(plan, result) -> None:
    """trajectory.txt, metrics.json, mesh.ply, the continuous export and the plots of a finished run.

    ``plan`` is ``run.Plan`` (its args, cfg, sequence, out and gt_mesh), ``result`` what
    ``slam.run_slam`` returns.
    """
    args, cfg, sequence, out = plan.args, plan.cfg, plan.sequence, plan.out
    from .export import export_continuous

    data_module.write_tum_trajectory(out / "trajectory.txt", result.timestamps, result.poses, overwrite=True)
    atomic_write_text(out / "frames.csv", frames_table(result.state.log, result.timestamps))
    camera = sequence.intrinsics  # as the run used it: after crop and resize
    metrics = {"method": cfg.method, "sequence": sequence.name, "frames": int(len(sequence)),
               "frames_per_second": result.frames_per_second,
               "camera": {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, "width": camera.width,
                          "height": camera.height, "depth_scale": sequence.depth_scale}}
    metrics.update(trajectory_metrics(sequence, result.timestamps, result.poses))
    if cfg.method == "tsslam" and cfg.local_ba.use_spline:
        metrics["spline"] = spline_summary(result.state.trajectory, cfg.spline.knots)
    metrics.update(outside_box_summary(result.state.log))
    metrics.update(spline_offset_summary(result.state.log))
    metrics.update(motion_summary(result.timestamps, result.poses))
    metrics["runtime"] = result.state.timings.table()
    metrics["environment"] = run_environment(plan.device, result.state.field)
    if plan.environment is not None and plan.environment != metrics["environment"]:  # resumed elsewhere
        metrics["environment_at_start"] = plan.environment
    if not args.no_mesh:
        metrics.update(mesh_outputs(plan, result.state.field))
    if args.export_rate is not None:
        export_continuous(result.state, args.export_rate, out / export_file_name(args.export_rate))
    save_plots(out, sequence, result.timestamps, result.poses)
    metrics.update(peak_memory(plan.device))  # after the mesh and the plots: the whole run's peak
    atomic_write_text(out / "metrics.json", json.dumps(_jsonable(metrics), indent=2))  # last: it marks a finished run
    checkpoint_path = out / "checkpoint.pt"
    if checkpoint_path.exists() and not args.checkpoint_every:
        checkpoint_path.unlink()
    summary = ", ".join(f"{key} {metrics[key]:.4f}" for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg") if key in metrics)
    parts = [f"done: {_frames_done(len(sequence), result)}", summary or _why_no_metrics(sequence)]
    if "spline_offsets" in metrics:
        offsets = metrics["spline_offsets"]
        parts.append(f"spline from the tracked poses: RMS {100 * offsets['position_rms_m']:.2f} cm, "
                     f"{offsets['rotation_rms_deg']:.2f} deg")
    if "peak_rss_mib" in metrics:
        parts.append(f"peak RSS {metrics['peak_rss_mib']:.0f} MiB")
    print("; ".join(parts + [f"outputs in {out}"]))


def _jsonable(value):
    """``value`` with numpy arrays and scalars as lists and numbers (arrays over 16 values in a dict dropped)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items() if not (isinstance(v, np.ndarray) and v.size > 16)}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def _frames_done(n_frames: int, result) -> str:
    """'100 frames at 0.95 frames/s', or what a resumed run processed itself."""
    if result.frames_per_second is None:
        return f"{n_frames} frames, all from the checkpoint (none left to process)"
    if result.frames_processed < n_frames:
        return (f"{n_frames} frames, {result.frames_processed} of them after the checkpoint at "
                f"{result.frames_per_second:.2f} frames/s")
    return f"{n_frames} frames at {result.frames_per_second:.2f} frames/s"
