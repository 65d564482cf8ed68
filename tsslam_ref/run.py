"""Command line: run TS-SLAM (or the Co-SLAM baseline) on a sequence and write every output.

    python -m tsslam_ref.run                       # bundled TUM fr3/teddy slice, tum-cpu preset
    python -m tsslam_ref.run --data PATH --config tum-cpu --method coslam --out runs/teddy
    python -m tsslam_ref.run --set tracking.iters=30 --set spline.dt=0.2 --frames 0:60

Outputs in ``--out`` (default ``runs/<sequence>-<method>``):

* ``trajectory.txt`` - TUM format (timestamp tx ty tz qx qy qz qw), camera-to-world, OpenCV axes,
  one line per input frame at the frame's own timestamp;
* ``metrics.json`` - ate_rmse_m, rpe_trans_rmse_m, rpe_rot_rmse_deg, n_matched (when ground truth is
  known), frames, frames_per_second (of the frames this process ran; null when a resume had none left),
  the runtime table, the reconstruction metrics when a ground-truth mesh is next to the data
  (``gt_mesh.ply``, written by the synthetic generator), ``environment``
  (:func:`tsslam_ref.device.run_environment`: the code's version and source digest, and what besides
  the seed fixes the numbers) and the peak memory (``peak_rss_mib``; ``peak_gpu_allocated_mib`` on CUDA);
* ``mesh.ply`` - the final map's mesh (marching cubes at ``mesh.voxel_final``);
* ``config.json`` - the resolved config; ``trajectory.png`` and ``errors.png`` - plots;
* ``checkpoint.pt`` - the whole state every ``--checkpoint-every`` frames (``--resume`` continues);
* ``trajectory_<rate>hz.txt`` with velocities when ``--export-rate`` is given (TS-SLAM only).

A run refuses to write into an existing non-empty output folder unless ``--overwrite`` (or
``--resume``) is given.  Every output is written atomically as a new file with the user's normal
mode (``files.py``); partial outputs (trajectory so far, checkpoint) are written while the run goes,
so an interrupted run leaves readable files.

The command works in two steps: :func:`prepare` checks every argument, the config, the device,
the data (every frame's image headers) and the output folder, and loads a checkpoint for
``--resume``, writing nothing; :func:`execute` then runs and writes.  Exit status: 0 done, 2 bad
input (one line naming the file, key or value; nothing written), 3 tracking failure, 130
interrupted (Ctrl-C; ``--resume`` continues from the last checkpoint).  docs/cli.md has the table.

Layer 4 (system).
"""

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from . import checkpoint as checkpoint_module
from . import config as config_module
from . import data as data_module
from . import device as device_module
from . import knot_schedule, tracking
from .cli_args import OneLineParser, escape_what_output_cannot_encode, number_in, silence_stdout
from .cli_args import stop_on_sigterm_as_on_ctrl_c, user_path
from .files import OutputWriteError, atomic_write_text, remove_stray_temporaries
from .run_outputs import reconstruction_metrics, save_plots, trajectory_metrics  # noqa: F401  (re-exported)
from .run_outputs import OUTPUT_NAMES, is_output_name, remove_previous_outputs  # noqa: F401  (re-exported)
from .run_outputs import advance, check_output_folder, data_error_advice, data_notes, export_file_name
from .run_outputs import restart_advice, write_outputs
from .run_outputs import FolderInUse, close_progress, output_folder_lock, write_partial_outputs
from .export import MAX_EXPORT_RATE, export_times

EXIT_OK, EXIT_BAD_INPUT, EXIT_TRACKING_FAILURE, EXIT_INTERRUPTED = 0, 2, 3, 130

RESULT_NEUTRAL = ("--checkpoint-every", "--export-rate", "--no-mesh", "--quiet")
"""Options that may differ on ``--resume``: they change what is written, never the trajectory."""


class BadInput(ValueError):
    """Bad command-line input; the message names the option, key, file or value."""


def parse_frames(text: Optional[str]):
    """'START:STOP[:STEP]' -> (start, stop or None, step); 0 <= START < STOP, STEP >= 1."""
    if text is None:
        return None
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise BadInput(f"--frames must be START:STOP[:STEP], got '{text}'")
    try:
        start = int(parts[0]) if parts[0] else 0
        stop = int(parts[1]) if parts[1] else None
        step = int(parts[2]) if len(parts) == 3 and parts[2] else 1
    except ValueError:
        raise BadInput(f"--frames must be integers START:STOP[:STEP], got '{text}'") from None
    if start < 0 or (stop is not None and stop < 0):
        raise BadInput(f"--frames {text}: START and STOP count frames from the first one and must be >= 0 "
                       f"(negative positions are not supported)")
    if step <= 0 or (stop is not None and stop <= start):
        raise BadInput(f"--frames '{text}' selects no frames (need 0 <= START < STOP and STEP > 0)")
    return start, stop, step


_seed = number_in("--seed", 0, 2**32 - 1, integer=True, interval="[0, 2**32 - 1]")  # the generator keeps 32 bits
_export_rate = number_in("--export-rate", 0, MAX_EXPORT_RATE, low_open=True,
                         hint="samples per second; leave the option out for no export")
_checkpoint_every = number_in("--checkpoint-every", 0, 10**9, integer=True, hint="frames; 0 for no checkpoint")
_threads = number_in("--threads", 1, 1024, integer=True)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m tsslam_ref.run",
        description="Run TS-SLAM (or the Co-SLAM baseline) on an RGB-D sequence.",
        epilog="Exit status: 0 done, 2 bad input (nothing written), 3 tracking failure, 130 interrupted.",
    )
    parser.add_argument("--data", type=user_path, default="", help="dataset folder (default: the bundled TUM fr3/teddy slice)")
    parser.add_argument("--dataset", default=None, choices=["auto", "tum", "scannet", "neural_rgbd", "replica", "folder", "synthetic"],
                        help="dataset layout (default: detected from the folder); 'synthetic' = a folder written by `python -m tsslam_ref.data synthesize`")
    parser.add_argument("--config", type=user_path, default=None, help="preset name (%s) or a config.json; default tum-cpu" % ", ".join(config_module.PRESETS))
    parser.add_argument("--method", default=None, choices=["tsslam", "coslam"], help="trajectory representation (default tsslam)")
    parser.add_argument("--out", type=user_path, default=None, help="output folder (default runs/<sequence>-<method>)")
    parser.add_argument("--seed", type=_seed, default=None, help="random seed, an integer in [0, 2**32 - 1] (default from the config: 0)")
    parser.add_argument("--device", default=None, choices=["cpu", "cuda", "auto"], help="compute device (default auto)")
    parser.add_argument("--frames", default=None, help="START:STOP[:STEP] frame selection, 0 <= START < STOP <= frames")
    parser.add_argument("--parallel", action="store_true",
                        help="track and map in two threads (not deterministic; default: the sequential loop)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="config override, e.g. --set tracking.iters=20 (repeatable)")
    parser.add_argument("--export-rate", type=_export_rate, default=None, metavar="HZ",
                        help=f"also export the continuous trajectory at this rate, (0, {MAX_EXPORT_RATE:g}] Hz, with velocities (tsslam)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the files of an earlier run in a non-empty output folder (other files are kept)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt (same command otherwise)")
    parser.add_argument("--checkpoint-every", type=_checkpoint_every, default=25,
                        help="frames between checkpoints, >= 1, or 0 = never (default 25)")
    parser.add_argument("--threads", type=_threads, default=None,
                        help="CPU threads for PyTorch and the compiled map kernels, 1 to 1024 (default: PyTorch's "
                             "choice, one per core); with the CPU kernels it decides a seed's last bits")
    parser.add_argument("--no-mesh", action="store_true", help="skip the final mesh")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def _join_dash_values(argv: List[str]) -> List[str]:
    """'--frames -3:8' -> '--frames=-3:8' so that argparse does not take the value for an option."""
    joined, i = [], 0
    while i < len(argv):
        if argv[i] == "--frames" and i + 1 < len(argv) and argv[i + 1].startswith("-") and argv[i + 1][1:2].isdigit():
            joined.append(f"--frames={argv[i + 1]}")
            i += 2
            continue
        joined.append(argv[i])
        i += 1
    return joined


def resolve_config(args) -> config_module.Config:
    """Preset or file, then command-line options, then ``--set`` overrides."""
    cfg = config_module.load(args.config or "tum-cpu")
    cfg.method, cfg.device = args.method or cfg.method, args.device or cfg.device
    cfg.seed = cfg.seed if args.seed is None else args.seed
    if args.data:  # the user's own folder: its layout and depth scale, unless a config file says
        config_module.read_data_folder(cfg, args.data, args.config)
    if args.parallel:
        cfg.parallel = True
    if args.dataset:
        cfg.data.dataset = "tum" if args.dataset == "synthetic" else args.dataset
    frames = parse_frames(args.frames)
    if frames is not None:
        cfg.data.frame_start, cfg.data.frame_stop, cfg.data.frame_step = frames
    cfg = config_module.apply_overrides(cfg, args.overrides)
    if not cfg.data.path and cfg.data.dataset not in ("auto", "tum"):  # it named the layout, not the folder
        raise BadInput(f"data.dataset = '{cfg.data.dataset}' (preset {cfg.name}) reads {cfg.data.dataset} folders, "
                       f"but no --data names one: give it, e.g. --data PATH/TO/SCENE (without it the run reads the "
                       f"bundled TUM slice)")
    if cfg.data.path:  # the folder itself, not a path from where this command ran: --resume compares it
        cfg.data.path = str(Path(cfg.data.path).expanduser().resolve())
    return cfg


def _checked_sequence(cfg, frames: Optional[str]):
    """The sequence of ``cfg.data``, checked as far as it can be before the run: at least 2 frames,
    their spacing against the spline's intervals, every file's header, frame 0 decoded (the map is
    placed from its depth; an all-zero depth is refused) and its size against the ray counts."""
    sequence = data_module.load_from_config(cfg.data)
    if len(sequence) < 2:
        chosen = (cfg.data.frame_start, cfg.data.frame_stop, cfg.data.frame_step)
        selection = (f"--frames {frames} selects" if frames and parse_frames(frames) == chosen
                     else f"{sequence.path} has" if chosen == (0, None, 1)
                     else "data.frame_start:frame_stop:frame_step = {}:{}:{} selects".format(*chosen))
        raise BadInput(f"{selection} {len(sequence)} frame; a run needs at least 2")
    knot_schedule.check_frame_spacing(cfg, sequence.timestamps, sequence.times_without_gt, cfg.data.frame_step)
    sequence.check_files()
    first = sequence[0]
    tracking.check_ray_budget(cfg, *first.depth.shape)  # the loop's own check, on the processed size
    _warn_if_depth_beyond_range(cfg, sequence, first.depth)
    return sequence


def _warn_if_depth_beyond_range(cfg, sequence, depth: np.ndarray) -> None:
    """A warning (the run goes on) when most of frame 0's measured depth lies beyond the range the
    map uses, min(data.depth_trunc, render.far), or its median is nearer than 0.3 m: the usual signs
    of a wrong depth scale (a map built from a few pixels; millimetre PNGs read at 5000 per metre)."""
    limit = min(cfg.data.depth_trunc, cfg.render.far)
    measured = depth[depth > 0]
    if measured.size and np.mean(measured < limit) < 0.5:
        print(f"warning: {100 * np.mean(measured >= limit):.0f} % of frame 0's measured depth lies beyond {limit:g} m "
              f"(data.depth_trunc, render.far; median {np.median(measured):.2f} m); check the depth scale "
              f"(data.depth_scale = {sequence.depth_scale:g} PNG values per metre)", file=sys.stderr)
    elif measured.size and np.median(measured) < 0.3:
        print(f"warning: frame 0's median measured depth is {np.median(measured):.2f} m; unless the camera films a "
              f"close-up, check the depth scale (data.depth_scale = {sequence.depth_scale:g} PNG values per metre; "
              f"millimetre PNGs have 1000)", file=sys.stderr)


@dataclass
class Plan:
    """What :func:`prepare` checked and loaded; :func:`execute` runs it."""

    args: argparse.Namespace
    cfg: config_module.Config
    sequence: Any
    out: Path
    device: torch.device
    state: Any = None  # the resumed loop state, or None
    finished: bool = False  # --resume of a run that already finished
    gt_mesh: Any = None  # the ground-truth mesh beside the data (gt_mesh.ply), read before the run
    environment: Optional[dict] = None  # device.run_environment when the run started (resumed: the checkpoint's)


def _read_gt_mesh(path: Path):
    """The ground-truth mesh for the reconstruction metrics, read as ``eval mesh`` reads it;
    BadInput naming a broken file."""
    from .reconstruction_metrics import read_mesh  # lazy: trimesh, only when there is a GT mesh

    try:
        return read_mesh(path)
    except ValueError as error:
        raise BadInput(f"ground-truth mesh {error}; fix it, or remove it to skip the reconstruction metrics") from None


def _finished_run(out: Path) -> bool:
    try:
        metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(metrics, dict) and "frames" in metrics and not metrics.get("failed", False)


def _note_sparse_export(rate_hz: float, timestamps: np.ndarray) -> None:
    """Warn (stderr) when ``--export-rate`` gives fewer than two rows over the frames' span, (N,) s."""
    span = float(timestamps[-1] - timestamps[0])
    rows = len(export_times(0.0, float(np.nextafter(span, np.inf)), rate_hz))  # up to the last frame, as the export
    if rows < 2:
        print(f"note: --export-rate {rate_hz:g} Hz is one row every {1.0 / rate_hz:g} s; the frames span {span:.6g} s, "
              f"so the continuous trajectory will hold {rows} row", file=sys.stderr)


def prepare(args: argparse.Namespace) -> Plan:
    """Check everything and load what the run needs; writes nothing.

    Raises:
        ValueError (``BadInput``, ``CheckpointError``, the config's and the loaders' errors) or
        FileNotFoundError, naming the option, key, file or value.
    """
    if args.resume and args.overwrite:
        raise BadInput("--resume and --overwrite exclude each other: --resume continues the run in --out, "
                       "--overwrite starts it again")
    device_module.source_version()  # the code as the run starts (cached): what metrics.json and checkpoints record
    cfg = resolve_config(args)
    if args.export_rate is not None and cfg.method != "tsslam":
        raise BadInput(f"--export-rate needs --method tsslam (a continuous trajectory); the method is {cfg.method}")
    if args.export_rate is not None and not cfg.local_ba.use_spline:
        raise BadInput("--export-rate needs the spline (a continuous trajectory); this config has "
                       "local_ba.use_spline = false")
    knot_schedule.check_knot_settings(cfg)  # now, before the output folder is touched
    try:
        device = device_module.resolve_device(cfg.device)
    except RuntimeError as error:  # torch's own message for a device it does not know
        raise BadInput(f"device {cfg.device!r} cannot be used ({error})") from None
    sequence = _checked_sequence(cfg, args.frames)
    if args.export_rate is not None:
        _note_sparse_export(args.export_rate, sequence.timestamps)
    out = Path(args.out) if args.out else Path("runs") / f"{sequence.name}-{cfg.method}"
    check_output_folder(out, args.overwrite, args.resume, sequence.path)
    plan = Plan(args=args, cfg=cfg, sequence=sequence, out=out, device=device)
    gt_mesh_path = Path(sequence.path) / "gt_mesh.ply"
    if not args.no_mesh and gt_mesh_path.exists() and sequence.gt_poses is not None:  # culling needs GT cameras
        plan.gt_mesh = _read_gt_mesh(gt_mesh_path)  # a broken file is named now, not after the run
    elif not args.no_mesh and gt_mesh_path.exists():
        print(f"note: {gt_mesh_path} is not scored: culling needs ground-truth camera poses, which the data lacks")
    if args.resume:
        _prepare_resume(plan)
    return plan


def _prepare_resume(plan: Plan) -> None:
    """Check ``--resume`` against what ``plan.out`` holds (the same settings and frames) and load its
    checkpoint into ``plan``; a finished run without a checkpoint is compared with its config.json."""
    path, cfg, sequence = plan.out / "checkpoint.pt", plan.cfg, plan.sequence
    if not path.is_file() and _finished_run(plan.out):  # a finished run made with --checkpoint-every 0
        saved = plan.out / "config.json"
        try:
            saved_config = config_module.read_json_values(str(saved))
        except (OSError, ValueError):
            saved_config = None  # nothing to compare with: the run is done either way
        if saved_config is not None:
            _refuse_other_settings(checkpoint_module.config_differences(saved_config, cfg, saved.name), saved)
        plan.finished = True
        return
    if not path.is_file():
        raise BadInput(f"--resume given but {path} does not exist (no checkpoint was written: the run stopped "
                       f"before its first checkpoint, or ran with --checkpoint-every 0)")
    values = checkpoint_module.read(path)
    _refuse_other_settings(checkpoint_module.config_differences(checkpoint_module.config_of(values), cfg), path)
    saved_times = values["timestamps"].numpy()
    if saved_times.shape != sequence.timestamps.shape or not np.array_equal(saved_times, sequence.timestamps):
        common = min(len(saved_times), len(sequence))
        differ = np.flatnonzero(saved_times[:common] != sequence.timestamps[:common])
        first = int(differ[0]) if differ.size else common
        raise BadInput(f"--resume refused: the frames of {sequence.path} differ from those in {path} "
                       f"({len(saved_times)} frames saved, {len(sequence)} now; the first difference at frame {first})")
    plan.finished = _finished_run(plan.out)
    if plan.finished and plan.args.export_rate is None:
        return
    try:  # a finished run's state too, when --export-rate asks for its continuous trajectory
        plan.state = checkpoint_module.from_plain(values, plan.device)
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as error:
        raise checkpoint_module.CheckpointError(f"{path}: the checkpoint's content does not fit ({error})") from None
    plan.environment = _resume_environment(values.get("environment"), plan)


def _refuse_other_settings(changes: List[str], path: Path) -> None:
    """BadInput naming the first setting that differs from the run saved in ``path`` (if any does)."""
    if changes:
        raise BadInput(f"--resume refused, {path} was made with other settings: {changes[0]}"
                       + (f" (and {len(changes) - 1} more)" if len(changes) > 1 else "")
                       + f"; only {', '.join(RESULT_NEUTRAL)} may change on --resume (--device and --threads too, "
                         f"with a warning)")


def _resume_environment(saved: Optional[dict], plan: Plan) -> dict:
    """The environment the run started in, warning (one line) when this process differs from it:
    the rest of the run then cannot match an uninterrupted one bit for bit."""
    now = device_module.run_environment(plan.device, plan.state.field)
    changes = checkpoint_module.environment_changes(saved, now)
    if changes:
        will = "will not" if any(saved[key] != now.get(key) for key in saved) else "may not"  # else: unrecorded
        print(f"warning: resuming in another environment than the run started in ({'; '.join(changes)}); " + (
              f"the export {will} match one the run itself had written bit for bit" if plan.finished else
              f"the frames from {plan.state.done} on {will} match an uninterrupted run bit for bit, and "
              f"metrics.json records both (environment_at_start)"), file=sys.stderr)
    return saved if isinstance(saved, dict) else now


def save_checkpoint(state, path: Path, environment: Optional[dict] = None) -> None:
    """The whole loop state as plain data (``checkpoint.py``), atomically, with the run's environment."""
    checkpoint_module.save(state, path, environment)


def load_checkpoint(path: Path, device=None):
    """The loop state saved by :func:`save_checkpoint` (no code runs while it is read)."""
    return checkpoint_module.load(path, device)


def _open_output_folder(plan: Plan) -> None:
    """Create ``plan.out``, remove an earlier run's outputs for ``--overwrite`` and half-written
    temporaries, and save the resolved config (not on ``--resume``: the saved one stays)."""
    out = plan.out
    out.mkdir(parents=True, exist_ok=True)
    if plan.args.overwrite:
        remove_previous_outputs(out)
    remove_stray_temporaries(out, is_output_name)
    if not plan.args.resume:
        config_module.save(plan.cfg, str(out / "config.json"))


def _progress_bar(plan: Plan):
    """A tqdm bar over the sequence's frames (starting at a resumed state's frame), or None for --quiet."""
    if plan.args.quiet:
        return None
    from tqdm import tqdm

    return tqdm(total=len(plan.sequence), desc=f"{plan.cfg.method} on {plan.sequence.name}", unit="frame",
                initial=plan.state.done if plan.state else 0)


def _frame_callback(plan: Plan, progress, reached: Dict[str, int]):
    """The loop's per-frame callback: it records the frames done in ``reached``, moves the bar, and
    every ``--checkpoint-every`` frames and after the last one writes the trajectory and frames.csv so far
    and the checkpoint (a finished run's then holds every frame: ``--export-rate`` re-fits only the last interval)."""
    every, out = plan.args.checkpoint_every, plan.out

    def on_frame(current) -> None:
        reached["done"] = current.done
        advance(progress, current, reached)  # the bar, and a warning once a frame looks past the map's box
        if every and (current.done % every == 0 or current.done == len(plan.sequence)):
            # the checkpoint first: trajectory.txt never gets ahead of it
            if plan.environment is None:
                plan.environment = device_module.run_environment(plan.device, current.field)
            save_checkpoint(current, out / "checkpoint.pt", plan.environment)
            reached["checkpoint"] = current.done
            write_partial_outputs(current, out)

    return on_frame


def _interrupted(plan: Plan, progress, reached: Dict[str, int]) -> int:
    """Say where an interrupted run stopped and how to continue it; returns EXIT_INTERRUPTED."""
    close_progress(progress)
    checkpoint_path = plan.out / "checkpoint.pt"
    if checkpoint_path.is_file():  # this run's, or the one it resumed from (with --checkpoint-every 0)
        where = (f"the checkpoint in {checkpoint_path} holds {reached['checkpoint']} frames; "
                 f"run the same command with --resume to continue")
    else:
        where = "no checkpoint was written; run the same command with --overwrite to start again"
    print(f"interrupted with {reached['done']} of {len(plan.sequence)} frames done; {where}", file=sys.stderr)
    return EXIT_INTERRUPTED


def _tracking_failed(plan: Plan, progress, failure: Exception) -> int:
    """Report a tracking failure on stderr and in metrics.json; returns EXIT_TRACKING_FAILURE."""
    close_progress(progress)
    print(f"error: the run failed: {failure}", file=sys.stderr)
    atomic_write_text(plan.out / "metrics.json", json.dumps({"failed": True, "reason": str(failure)}, indent=2))
    return EXIT_TRACKING_FAILURE


def _export_finished_run(plan: Plan) -> int:
    """Write a finished run's continuous trajectory at ``--export-rate`` from its checkpoint, as the
    run would have (the loop only fits the last interval again); no other file is touched."""
    from . import slam
    from .export import export_continuous

    result = slam.run_slam(plan.sequence, plan.cfg, device=plan.device, state=plan.state)
    path = plan.out / export_file_name(plan.args.export_rate)
    export_continuous(result.state, plan.args.export_rate, path)
    print(f"{plan.out} holds a finished run (metrics.json); wrote {path.name} from its checkpoint, the other files "
          f"unchanged")
    return EXIT_OK


def execute(plan: Plan) -> int:
    """Run the prepared command and write its outputs; returns the exit status."""
    cfg, sequence, out, state = plan.cfg, plan.sequence, plan.out, plan.state
    if plan.finished and state is not None:  # --export-rate on a finished run that kept its checkpoint
        return _export_finished_run(plan)
    if plan.finished:
        skipped = (" (--export-rate needs the run's checkpoint, which --checkpoint-every 0 removed)"
                   if plan.args.export_rate else "")
        print(f"{out} holds a finished run (metrics.json); nothing to resume{skipped}. Use --overwrite to run it again.")
        return EXIT_OK
    from . import parallel, slam

    _open_output_folder(plan)
    if state is not None:
        print(f"resuming at frame {state.done} of {len(sequence)}")
    device_module.tune_cpu_allocator()
    progress = _progress_bar(plan)
    reached = {"done": state.done if state else 0, "checkpoint": state.done if state else 0}
    on_frame = _frame_callback(plan, progress, reached)
    environment = device_module.compute_environment(plan.device)
    kernels = environment.get("gpu") or f"{environment['cpu_capability']} kernels, {environment['threads']} threads"
    print(f"{cfg.method}: {len(sequence)} frames of {sequence.name} ({sequence.kind}, "
          f"{data_module.timing_summary(sequence.timestamps)}), preset {cfg.name}, device {plan.device} ({kernels}), "
          f"output {out}")
    for note in data_notes(sequence):  # frames left out, a camera chosen by default
        print(f"note: {note}")
    for ignored in config_module.overrides_without_effect(cfg.method, plan.args.overrides, cfg):
        print(f"note: --set {ignored}")
    try:
        run_loop = parallel.run_slam_in_two_threads if cfg.parallel else slam.run_slam
        result = run_loop(sequence, cfg, device=plan.device, state=state, on_frame=on_frame)
    except KeyboardInterrupt:
        return _interrupted(plan, progress, reached)
    except slam.TrackingFailure as failure:
        return _tracking_failed(plan, progress, failure)
    except (ValueError, OSError) as error:  # a frame that cannot be read (checked cheaply before the run)
        close_progress(progress)
        if isinstance(error, OutputWriteError):  # not the data: the output folder stopped taking files (main)
            raise
        advice = data_error_advice(out, reached, error, str(sequence.path))
        print(f"error: {error}; the outputs so far are in {out}: {advice}", file=sys.stderr)
        return EXIT_BAD_INPUT
    close_progress(progress)
    write_outputs(plan, result)
    return EXIT_OK


def main(argv: Optional[List[str]] = None) -> int:
    """Command-line entry: :func:`prepare` (checks, no writes), then :func:`execute`."""
    argv = _join_dash_values(list(sys.argv[1:] if argv is None else argv))
    args = build_parser().parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    stop_on_sigterm_as_on_ctrl_c()
    escape_what_output_cannot_encode()
    try:
        plan = prepare(args)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted while checking the input; nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    try:
        with output_folder_lock(plan.out):
            return execute(plan)
    except FolderInUse as error:  # another run writes there (nothing was touched)
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        resumable = (plan.out / "checkpoint.pt").is_file() and not (plan.out / "metrics.json").is_file()
        how = ("again: the finished run's files are unchanged" if plan.finished else
               "with --resume to finish them from its checkpoint" if resumable else "with --overwrite to run it again")
        print(f"interrupted while writing the outputs in {plan.out}; run the same command {how}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # stdout piped into a reader that quit (`| head`)
        silence_stdout()
        print(f"error: standard output was closed (the reader of a pipe quit), so the run in {plan.out} stopped; "
              f"run the same command with {restart_advice(plan.out)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as error:  # the output folder stopped taking files (disk full, permissions changed)
        print(f"error: cannot write the outputs in {plan.out}: {error}; what was written before is intact "
              f"(files are replaced whole), free the space or fix the folder and run with {restart_advice(plan.out)}",
              file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
