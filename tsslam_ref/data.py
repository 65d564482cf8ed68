"""RGB-D datasets: detection, lazy loading, intrinsics, timestamps, ground truth; the command line.

TS-SLAM §IV-A "Datasets" (TUM RGB-D, ScanNet and the NeuralRGBD synthetic scenes; "we assumed a
constant frame rate of 30 FPS" where a dataset has no timestamps), Eq. (2) ``eq:cal_ray`` for
:func:`back_project`, and Co-SLAM's ``datasets/dataset.py`` @3bb904e (differences in docs/data.md;
Replica is supported because Co-SLAM evaluates on it).  Side layer: imports ``cli_args`` (layer 0)
and ``datasets.*`` (side layer); the ``synthesize`` command and :func:`default_synthetic_path` import
:mod:`tsslam_ref.synthetic` (side layer) lazily.  Documented in docs/data.md; taught in
notebooks/00_data_and_cameras.ipynb.

This module is the public entry point; the readers live in :mod:`tsslam_ref.datasets`.

Conventions: poses are camera-to-world with OpenCV camera axes; depth is metric z (0 = invalid)
and is never truncated here (``depth_trunc`` is applied by the losses); timestamps are float64
seconds of dataset time; pixel centres lie at integer coordinates (see ``Intrinsics``).

Command line::

    python -m tsslam_ref.data info [PATH] [--json]
    python -m tsslam_ref.data synthesize --out DIR [--trajectory FILE|NAME [--start S]] [--frames N] [--size WxH]
                                         [--seed S] [--fps F] [--clean-depth] [--force]
                                         [--mesh-voxel M]
"""

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np

from tsslam_ref.cli_args import OneLineParser, number_in, user_path
from tsslam_ref.datasets.intrinsics import Intrinsics, back_project, pixel_rays
from tsslam_ref.datasets.layouts import (
    DEPTH_SCALES,
    LAYOUTS,
    detect_dataset,
    matching_layouts,
    other_layout_hint,
    parse_folder,
    parse_neural_rgbd,
    parse_replica,
    parse_scannet,
    parse_tum,
    require_dataset_folder,
)
from tsslam_ref.datasets.sequence import Frame, RGBDSequence
from tsslam_ref.datasets.tum_format import TUM_MAX_TIME_DIFF, ground_truth_at, read_tum_trajectory, write_tum_trajectory

__all__ = [
    "Intrinsics", "Frame", "RGBDSequence", "detect_dataset", "load_sequence", "load_from_config",
    "default_sequence_path", "default_synthetic_path", "read_tum_trajectory", "write_tum_trajectory", "ground_truth_at",
    "sequence_info", "back_project", "pixel_rays", "LAYOUTS", "DEPTH_SCALES",
    "SHIPPED_TRAJECTORIES", "trajectory_path", "trajectory_origin",
]

ASSETS = Path(__file__).resolve().parent / "assets"
BUNDLED_TUM = "tum_fr3_teddy_160x120"
SYNTHETIC_CACHE = Path.home() / ".cache" / "tsslam_ref" / "synthetic_room_160x120"


def default_sequence_path() -> Path:
    """The bundled TUM slice: fr3/teddy, ~100 frames at 160x120 (made by data_scripts/make_bundled_tum_slice.py)."""
    path = ASSETS / BUNDLED_TUM
    if not (path / "rgb.txt").is_file():
        raise FileNotFoundError(f"{path}: bundled sequence missing; run data_scripts/make_bundled_tum_slice.py")
    return path


def default_synthetic_path(cache_dir: Optional[Path] = None, verbose: bool = True) -> Path:
    """The default synthetic sequence (60 frames, 160x120, built-in path, seed 0), generated on first
    use into ``~/.cache/tsslam_ref/synthetic_room_160x120`` (or ``cache_dir``); the path is printed."""
    path = Path(cache_dir) if cache_dir is not None else SYNTHETIC_CACHE
    if not (path / "rgb.txt").is_file():
        from tsslam_ref import synthetic  # lazy: side module, only needed on first use

        if verbose:
            print(f"tsslam_ref: generating the default synthetic sequence into {path}", file=sys.stderr)
        synthetic.synthesize(path, n_frames=60, width=160, height=120, fps=30.0, seed=0, overwrite=True)
    return path


SHIPPED_TRAJECTORIES = ("tum_rgbd_fr2_desk", "tum_vi_room1", "tum_vi_room2")
"""Names of the trajectory stretches in ``assets/trajectories/`` (real hand-held motion, TUM format, CC BY 4.0;
made by data_scripts/make_trajectory_stretches.py): fr2/desk 0-4 s, TUM-VI room1 15-24 s, room2 15-20 s."""


def trajectory_path(name_or_path) -> Path:
    """A trajectory file: an existing path as given, else the shipped stretch of that name
    (:data:`SHIPPED_TRAJECTORIES`).  Raises FileNotFoundError naming both choices."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    if str(name_or_path) in SHIPPED_TRAJECTORIES:
        return ASSETS / "trajectories" / f"{name_or_path}.txt"
    raise FileNotFoundError(f"--trajectory {name_or_path}: no such file and not a shipped trajectory "
                            f"(expected a TUM-format file or one of {', '.join(SHIPPED_TRAJECTORIES)})")


def trajectory_origin(path) -> float:
    """The time (float64 s) that ``synthesize --start`` counts from: a ``# origin: SECONDS`` header line
    (a shipped stretch records the first stamp of the full recording it was cut from), else the
    file's smallest timestamp."""
    try:
        with open(path, encoding="utf-8-sig") as handle:  # a byte-order mark would hide the '#'
            for number, line in enumerate(handle, start=1):
                if not line.startswith("#"):
                    break
                if line.startswith("# origin:"):
                    try:
                        return float(line.split(":", 1)[1])
                    except ValueError:
                        raise ValueError(f"{path}:{number}: expected '# origin: SECONDS', got '{line.strip()}'") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file (expected a TUM trajectory: timestamp tx ty tz qx qy qz qw)") from None
    return float(np.min(read_tum_trajectory(path)[0]))


def _select(index, frame_start: int, frame_stop: Optional[int], frame_step: int, path: Path, without_gt: int = 0):
    """Indices of the frames ``[frame_start:frame_stop:frame_step]``; ValueError for none, for a stop
    beyond the last frame, or for two of them less than 1 µs apart.  ``without_gt``: frames already
    left out for want of a ground-truth pose (named in the message)."""
    n = len(index.timestamps)
    if frame_step < 1 or frame_start < 0 or (frame_stop is not None and frame_stop < 0):
        raise ValueError(f"invalid frame range start={frame_start} stop={frame_stop} step={frame_step} (need start, stop >= 0, step >= 1)")
    if frame_stop is not None and frame_stop > n:  # slicing would run fewer frames than asked, silently
        left_out = (f" ({without_gt} frame(s) without a ground-truth pose are left out; data.require_gt=false "
                    f"keeps them)") if without_gt else ""
        raise ValueError(f"{path}: frame range stop={frame_stop} is beyond the {n} usable frames (0 to {n - 1})"
                         f"{left_out}; give a stop of at most {n}, or none (START:) for every frame from START")
    chosen = np.arange(n)[frame_start:frame_stop:frame_step]
    if len(chosen) == 0:
        raise ValueError(f"{path}: frame range start={frame_start} stop={frame_stop} step={frame_step} selects no frame out of {n}")
    _check_microseconds_apart(index.timestamps[chosen], path)
    return chosen


def _layout_of(folder: Path, dataset: str) -> str:
    """The layout of ``folder``: ``dataset`` itself, or detected for 'auto'; raises for a missing
    folder or an unknown layout name."""
    require_dataset_folder(folder)
    try:
        kind = detect_dataset(folder) if dataset == "auto" else dataset
    except ValueError as error:  # a dataset's root (Replica/, a ScanNet download) given for one scene?
        scenes = [f"{child.name} ({matching_layouts(child)[0]})" for child in sorted(folder.iterdir())
                  if child.is_dir() and matching_layouts(child)]
        more = f" and {len(scenes) - 3} more" if len(scenes) > 3 else ""
        raise ValueError(f"{folder} holds dataset folders, not one: {', '.join(scenes[:3])}{more}; pass one of them"
                         if scenes else str(error)) from None
    if kind not in LAYOUTS:
        raise ValueError(f"dataset '{dataset}' unknown; expected 'auto' or one of {sorted(LAYOUTS)}")
    hint = other_layout_hint(folder, kind) if dataset != "auto" else None
    if hint:
        raise ValueError(hint)
    return kind


def _parse_layout(folder: Path, kind: str, fps: float, max_time_diff: float):
    """The frame index (paths, timestamps, ground truth, intrinsics) of ``folder`` in layout ``kind``."""
    if kind == "tum":
        return parse_tum(folder, fps, max_time_diff)
    if kind == "scannet":
        return parse_scannet(folder, fps)
    if kind == "neural_rgbd":
        return parse_neural_rgbd(folder, fps)
    if kind == "replica":
        return parse_replica(folder, fps)
    return parse_folder(folder, fps, max_time_diff)


def _keep_frames_with_gt(index, folder: Path, max_time_diff: float) -> np.ndarray:
    """Drop, in place, the frames of ``index`` whose ground-truth pose is unknown (not finite) and
    return their timestamps (s); ValueError when none is left."""
    known = np.flatnonzero(np.isfinite(index.gt_poses).all(axis=(1, 2)))
    if len(known) == 0:
        span = "" if index.gt_span is None else f", the ground truth {index.gt_span[0]:.6f}-{index.gt_span[1]:.6f} s"
        raise ValueError(f"{folder}: no frame has a ground-truth pose within {max_time_diff} s (the frames span "
                         f"{index.timestamps[0]:.6f}-{index.timestamps[-1]:.6f} s{span}): check that both use the "
                         f"same clock and unit, or run without ground truth (no ATE / RPE) with "
                         f"--set data.require_gt=false (require_gt=False in load_sequence)")
    dropped = np.delete(index.timestamps, known)
    index.rgb_paths = [index.rgb_paths[i] for i in known]
    index.depth_paths = [index.depth_paths[i] for i in known]
    index.timestamps, index.gt_poses = index.timestamps[known], index.gt_poses[known]
    return dropped


def load_sequence(
    path,
    dataset: str = "auto",
    resize_width: Optional[int] = None,
    crop_edge: int = 0,
    depth_scale: Optional[float] = None,
    depth_trunc: Optional[float] = None,
    frame_start: int = 0,
    frame_stop: Optional[int] = None,
    frame_step: int = 1,
    fps: float = 30.0,
    require_gt: bool = True,
    max_time_diff: float = TUM_MAX_TIME_DIFF,
) -> RGBDSequence:
    """Open a dataset folder as a lazy :class:`RGBDSequence`.

    Order of operations: parse the layout (TUM association, GT lookup) -> drop frames without GT
    if ``require_gt`` -> select ``[frame_start:frame_stop:frame_step]`` -> per frame on access:
    crop ``crop_edge`` px per side, then resize to ``resize_width`` (aspect kept, intrinsics
    updated exactly).

    Args:
        path: dataset folder.  dataset: 'auto' or one of :data:`LAYOUTS`.
        resize_width: output width in px, at most the cropped width (never enlarged); None keeps
            the native size.
        crop_edge: pixels removed from every side before resizing.
        depth_scale: PNG value per metre; None = the calibration file's (never overridden: a
            different value is refused), else the layout's standard.
        depth_trunc: stored on the sequence for the losses; depth is never zeroed here.
        frame_start, frame_stop, frame_step: Python slice over the usable frames; a stop past them is refused.
        fps: frame rate for layouts without timestamps (time = frame number / fps).
        require_gt: drop frames whose ground-truth pose is unknown (no effect without GT).
        max_time_diff: association tolerance in s (TUM: 0.02).

    Raises:
        FileNotFoundError / ValueError naming the file and line for bad input; ValueError when no
        frame is left (never a silent empty sequence).
    """
    folder = Path(path)
    kind = _layout_of(folder, dataset)
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    index = _parse_layout(folder, kind, fps, max_time_diff)
    dropped = _keep_frames_with_gt(index, folder, max_time_diff) if require_gt and index.gt_poses is not None else ()
    chosen = _select(index, frame_start, frame_stop, frame_step, folder, len(dropped))
    return RGBDSequence(
        name=folder.resolve().name,
        kind=kind,
        path=folder,
        rgb_paths=[index.rgb_paths[i] for i in chosen],
        depth_paths=[index.depth_paths[i] for i in chosen],
        timestamps=index.timestamps[chosen],
        gt_poses=None if index.gt_poses is None else index.gt_poses[chosen],
        native_intrinsics=index.intrinsics,
        depth_scale=_depth_scale(depth_scale, index.depth_scale, kind, folder),
        crop_edge=crop_edge,
        resize_width=resize_width,
        depth_trunc=depth_trunc, frames_without_gt=len(dropped), times_without_gt=dropped,
        colour_without_depth=index.colour_without_depth, camera_note=index.camera_note,
    )


def _check_microseconds_apart(timestamps: np.ndarray, folder: Path) -> None:
    """ValueError when two frames share a time stamp at the microseconds that trajectory files keep
    (``%.6f``): their poses would be written at one time, and no evaluator could tell them apart."""
    written = np.char.mod("%.6f", timestamps)
    same = np.flatnonzero(written[1:] == written[:-1])
    if same.size:
        i = int(same[0])
        raise ValueError(f"{folder}: frames {i} and {i + 1} are {timestamps[i + 1] - timestamps[i]:.3g} s apart "
                         f"({timestamps[i]!r}, {timestamps[i + 1]!r} s); trajectories keep time stamps to the "
                         f"microsecond, so frames must be at least 1 µs apart")


def _depth_scale(configured: Optional[float], declared: Optional[float], kind: str, folder: Path) -> float:
    """PNG value per metre: the config's, else the calibration file's, else the layout's standard;
    ValueError when the config's contradicts the file's."""
    if configured is not None and declared is not None and configured != declared:
        raise ValueError(f"{folder / 'intrinsics.json'}: 'depth_scale' is {declared:g} (PNG value per metre) "
                         f"but the config's data.depth_scale is {configured:g}; pass --set "
                         f"data.depth_scale={declared:g} to read the depth as the file says, or remove "
                         f"'depth_scale' from the file to use the config's")
    if configured is not None:
        return configured
    return declared if declared is not None else DEPTH_SCALES[kind]


def load_from_config(data_cfg) -> RGBDSequence:
    """:func:`load_sequence` from a :class:`tsslam_ref.config.DataConfig`; path "" = the bundled slice."""
    path = data_cfg.path or default_sequence_path()
    return load_sequence(
        path,
        dataset=data_cfg.dataset,
        resize_width=data_cfg.resize_width,
        crop_edge=data_cfg.crop_edge,
        depth_scale=data_cfg.depth_scale,
        depth_trunc=data_cfg.depth_trunc,
        frame_start=data_cfg.frame_start,
        frame_stop=data_cfg.frame_stop,
        frame_step=data_cfg.frame_step,
        fps=data_cfg.fps,
        require_gt=data_cfg.require_gt,
    )


def timing_summary(timestamps: np.ndarray) -> str:
    """'3.3 s at 30 Hz' (duration, and the rate of the median step) for (N,) float64 seconds: a
    run prints it first, so that frame times read in the wrong unit show at once."""
    if len(timestamps) < 2:
        return "one frame"
    return f"{timestamps[-1] - timestamps[0]:.3g} s at {1.0 / np.median(np.diff(timestamps)):.3g} Hz"


def sequence_info(sequence: RGBDSequence, depth_samples: int = 5) -> dict:
    """Summary of a sequence (the ``info`` command): size, intrinsics, duration, depth coverage.

    ``depth_valid_fraction`` is the mean share of pixels with depth > 0 over ``depth_samples``
    frames spread evenly through the sequence, ``depth_median_m`` the median of their measured depth
    (a check of the depth scale: a room seen from 0.3 m or less is unusual).
    """
    k = sequence.intrinsics
    picks = np.unique(np.linspace(0, len(sequence) - 1, min(depth_samples, len(sequence))).round().astype(int))
    depths = [sequence[int(i)].depth for i in picks]
    valid = [float((depth > 0).mean()) for depth in depths]
    measured = np.concatenate([depth[depth > 0] for depth in depths])
    return {
        "type": sequence.kind,
        "name": sequence.name,
        "path": str(sequence.path),
        "frames": len(sequence),
        "frames_with_gt": sequence.frames_with_gt,
        "colour_without_depth": sequence.colour_without_depth,
        "width": k.width, "height": k.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
        "depth_scale": sequence.depth_scale,
        "duration_s": float(sequence.timestamps[-1] - sequence.timestamps[0]),
        **_spacing(_times_a_run_uses(sequence)),
        "depth_valid_fraction": float(np.mean(valid)),
        "depth_median_m": float(np.median(measured)) if measured.size else float("nan"),
        **({"camera_note": sequence.camera_note} if sequence.camera_note else {}),
    }


def _times_a_run_uses(sequence: RGBDSequence) -> np.ndarray:
    """(M,) stamps (s) of the frames a run keeps: those with a ground-truth pose when the sequence
    has ground truth (``data.require_gt``, the default), else all."""
    if sequence.gt_poses is None:
        return sequence.timestamps
    known = np.isfinite(sequence.gt_poses).all(axis=(1, 2))
    return sequence.timestamps[known] if known.any() else sequence.timestamps


def _spacing(times: np.ndarray) -> dict:
    """Median frame spacing and the largest gap (s) with the frame before it, numbered as a run
    numbers its frames: TS-SLAM refuses gaps longer than its shortest interval and stretches
    sparser than half of it (``knot_schedule``)."""
    if len(times) < 2:
        return {}
    gaps = np.diff(times)
    worst = int(np.argmax(gaps))
    return {"spacing_median_s": float(np.median(gaps)), "largest_gap_s": float(gaps[worst]),
            "largest_gap_after_frame": worst}


def _parse_size(text: str):
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size must look like 160x120, got '{text}'") from None
    if not (8 <= width <= 4096 and 8 <= height <= 4096):
        raise argparse.ArgumentTypeError(f"--size {text}: width and height must be in [8, 4096] pixels")
    return width, height


def _check_synthesize_out(out: Path, force: bool) -> None:
    """Refuse an --out that is a link, a file, or a non-empty folder this command did not write."""
    if out.is_symlink():
        raise ValueError(f"--out {out} is a symbolic link; expected a new folder name or a folder written by this command")
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is a file; expected a folder")
    blocking = next((parent for parent in out.parents if parent.exists() and not parent.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"--out {out}: {blocking} is a file, so no folder can be made inside it")
    if not force and out.is_dir() and any(out.iterdir()):
        raise ValueError(f"--out {out} exists and is not empty; " + (
            "--force replaces it" if (out / "scene.json").is_file() else
            "it was not written by this command (no scene.json), so choose a new folder"))
    if force and out.is_dir() and any(out.iterdir()) and not (out / "scene.json").is_file():
        raise ValueError(f"--out {out} is a non-empty folder without scene.json; --force replaces only a folder "
                         f"written by this command, so choose a new folder")
    from tsslam_ref.synthetic import SEQUENCE_ENTRIES  # lazy: side module

    foreign = sorted(entry.name for entry in out.iterdir() if entry.name not in SEQUENCE_ENTRIES) if force and out.is_dir() else []
    if foreign:
        raise ValueError(f"--out {out} also holds {', '.join(foreign[:5])}{' ...' if len(foreign) > 5 else ''}, which this "
                         f"command did not write; --force replaces the whole folder, so move them out or choose a new folder")


def _print_check(sequence: RGBDSequence, n_files: int) -> None:
    print(f"checked: all {n_files} image files of the {len(sequence)} frames (header, size, mode, PNG checksums); "
          f"depth_valid_fraction is sampled from 5 frames", file=sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m tsslam_ref.data``: the ``info`` and ``synthesize`` commands."""
    parser = OneLineParser(prog="python -m tsslam_ref.data", description="RGB-D dataset tools",
                           epilog="Exit status: 0 done, 2 bad input (one line naming the file and what was expected).")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    info = commands.add_parser("info", help="summarise a dataset folder")
    info.add_argument("path", type=user_path, nargs="?", default="",
                      help="dataset folder (default: the bundled TUM fr3/teddy slice, which a run reads by default)")
    info.add_argument("--json", action="store_true", help="print JSON")
    synth = commands.add_parser("synthesize", help="render a synthetic TUM-layout sequence")
    synth.add_argument("--out", type=user_path, required=True)
    synth.add_argument("--trajectory", type=user_path, default=None,
                       help="TUM-format trajectory file, or a shipped stretch of real motion: "
                            f"{', '.join(SHIPPED_TRAJECTORIES)} (default: built-in path)")
    synth.add_argument("--frames", type=number_in("--frames", 1, 100_000, integer=True), default=60,
                       help="number of frames, 1 to 100000")
    synth.add_argument("--size", type=_parse_size, default=(160, 120), help="WxH, each 8 to 4096 pixels")
    synth.add_argument("--seed", type=number_in("--seed", 0, 2**32 - 1, integer=True), default=0)  # 32 bits count
    synth.add_argument("--fps", type=number_in("--fps", 0, 1000, low_open=True), default=30.0, help="(0, 1000]")
    synth.add_argument("--start", type=float, default=0.0,
                       help="seconds after the trajectory's first pose at which frame 0 is taken (default 0); "
                            "for a shipped stretch, after the first pose of the full recording it was cut from")
    synth.add_argument("--clean-depth", action="store_true")
    synth.add_argument("--mesh-voxel", type=number_in("--mesh-voxel", 0.005, 1.0), default=0.03,
                       help="marching-cubes voxel of gt_mesh.ply (m), 0.005 to 1")
    synth.add_argument("--force", action="store_true", help="replace a non-empty --out folder written by this command")
    return parser


def _info(args: argparse.Namespace) -> int:
    """``info PATH [--json]``: check every frame's files and print the sequence's summary."""
    try:
        sequence = load_sequence(args.path or default_sequence_path(), require_gt=False)
        n_files = sequence.check_files()
        summary = sequence_info(sequence)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    summary["files_checked"] = n_files
    _print_check(sequence, n_files)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key, value in summary.items():  # floats to 6 significant digits; --json keeps every digit
            print(f"{key:>22}: {value:.6g}" if isinstance(value, float) else f"{key:>22}: {value}")
    return 0


def _check_start_covered(trajectory: Path, origin: float, start: float, n_frames: int, fps: float) -> None:
    """ValueError in the command line's terms (--start, seconds after the origin) when the frames
    from ``start`` fall outside the trajectory's time stamps."""
    stamps = read_tum_trajectory(trajectory)[0]
    first, last = float(stamps[0] - origin), float(stamps[-1] - origin)
    latest = last - (n_frames - 1) / fps
    if latest < first:
        raise ValueError(f"{trajectory.name} covers {last - first:.3f} s, too short for {n_frames} frames at {fps:g} fps; "
                         f"use fewer --frames or a higher --fps")
    if not first <= start <= latest:
        raise ValueError(f"--start {start:g} s: {trajectory.name} covers {first:.3f} to {last:.3f} s after its origin, so "
                         f"{n_frames} frames at {fps:g} fps need --start in [{first:.3f}, {latest:.3f}] s")


def _synthesize(args: argparse.Namespace) -> int:
    """``synthesize --out DIR ...``: render a synthetic TUM-layout sequence; prints its folder."""
    from tsslam_ref import synthetic  # lazy: the renderer needs torch
    try:
        _check_synthesize_out(Path(args.out), args.force)
        start_time = None
        trajectory = None if args.trajectory is None else trajectory_path(args.trajectory)
        if args.start != 0.0:
            if args.trajectory is None:
                raise ValueError("--start needs --trajectory (the built-in path starts at 0 s)")
            if not (args.start >= 0.0 and np.isfinite(args.start)):
                raise ValueError(f"--start must be >= 0 seconds and finite, got {args.start}")
        if trajectory is not None:
            start_time = trajectory_origin(trajectory) + args.start
            _check_start_covered(trajectory, start_time - args.start, args.start, args.frames, args.fps)
        out = synthetic.synthesize(
            args.out, trajectory=trajectory, n_frames=args.frames, width=args.size[0], height=args.size[1],
            fps=args.fps, seed=args.seed, clean_depth=args.clean_depth, overwrite=args.force, mesh_voxel=args.mesh_voxel,
            start_time=start_time,
        )
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(out)
    return 0


def main(argv=None) -> int:
    """Command-line entry (see the module docstring).  Returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as stop:  # a usage error (one line already printed) or --help
        return int(stop.code or 0)
    return _info(args) if args.command == "info" else _synthesize(args)


if __name__ == "__main__":
    from tsslam_ref.cli_args import interruptible

    sys.exit(interruptible(main, "python -m tsslam_ref.data"))
