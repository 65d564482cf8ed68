"""The five folder layouts: detection and parsing into file lists, timestamps and poses.

TS-SLAM §IV-A "Datasets" evaluates on TUM RGB-D, ScanNet and the NeuralRGBD synthetic scenes
(Co-SLAM adds Replica); the layouts, intrinsics and depth scales follow Co-SLAM's
``datasets/dataset.py`` @3bb904e (docs/data.md lists where we differ), plus a generic
folder layout of ours.  Side layer.
Formats are documented in docs/data.md; taught in notebooks/00_data_and_cameras.ipynb.

Every parser converts poses to camera-to-world with OpenCV camera axes (x right, y down,
z forward) and returns a :class:`LayoutIndex`; :func:`tsslam_ref.data.load_sequence` then selects
frames and builds the lazy sequence.  Bad input raises an error naming the file (and line).
"""

import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from tsslam_ref.datasets.images import image_size
from tsslam_ref.datasets.intrinsics import (
    NEURAL_RGBD_FOCAL,
    REPLICA_INTRINSICS,
    TUM_INTRINSICS,
    Intrinsics,
    read_calibration,
)
from tsslam_ref.datasets.tum_format import (associate_nearest, ground_truth_at, listed_file, read_file_list,
                                            read_tum_trajectory)
from tsslam_ref.geometry import opengl_to_opencv_pose

DEPTH_SCALES = {"tum": 5000.0, "scannet": 1000.0, "neural_rgbd": 1000.0, "replica": 6553.5, "folder": 1000.0}
"""Standard PNG value per metre of each layout (Co-SLAM configs; folder: ours, millimetres)."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
CALIBRATION_FORMATS = ('intrinsics.json ({"fx": ..., "fy": ..., "cx": ..., "cy": ...}, pixels; optional "width", '
                       '"height", "depth_scale") or calibration.txt (one line: fx fy cx cy [width height])')

LAYOUTS = {
    "tum": "rgb.txt + depth.txt (+ groundtruth.txt), files listed relative to the folder",
    "scannet": "color/<n>.jpg + depth/<n>.png + pose/<n>.txt + intrinsic/intrinsic_depth.txt",
    "neural_rgbd": "images/*.png + depth_filtered/*.png (or depth/) + poses.txt",
    "replica": "results/frame%06d.jpg + results/depth%06d.png + traj.txt",
    "folder": "rgb/ + depth/ (same file names) + intrinsics.json or calibration.txt (+ groundtruth.txt)",
}


@dataclass
class LayoutIndex:
    """What a layout parser found: one entry per usable frame, before frame selection."""

    kind: str
    rgb_paths: List[Path]
    depth_paths: List[Path]
    timestamps: np.ndarray  # (N,) float64 s
    gt_poses: Optional[np.ndarray]  # (N, 4, 4) float64, NaN rows unknown; None = no GT in the dataset
    intrinsics: Intrinsics  # of the stored depth images
    depth_scale: Optional[float]  # from a calibration file, else None (use DEPTH_SCALES)
    gt_span: Optional[Tuple[float, float]] = None  # first and last time of the ground-truth file, s
    colour_without_depth: int = 0  # TUM: colour stamps left out, no depth stamp within the tolerance
    camera_note: str = ""  # TUM: said when the camera is fr3's by default (no calibration file, no camera name)


def natural_key(name: str):
    """Sort key that orders 'img2' before 'img10'."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _images(folder: Path, prefix: str = "") -> List[Path]:
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.name.startswith(prefix)]
    return sorted(files, key=lambda p: natural_key(p.name))


def require_dataset_folder(folder: Path) -> None:
    """FileNotFoundError naming ``folder`` unless it is a folder (a file given instead is said so)."""
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: " + ("is a file; expected a dataset folder" if folder.exists() else "dataset folder not found"))


def _require_dir(path: Path) -> None:
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: folder not found")


def _stems_match(rgb_paths: List[Path], depth_paths: List[Path], rgb_dir: Path, depth_dir: Path) -> None:
    rgb_stems = [p.stem for p in rgb_paths]
    depth_stems = [p.stem for p in depth_paths]
    for paths, stems in ((rgb_paths, rgb_stems), (depth_paths, depth_stems)):
        counts = Counter(stems)  # once per folder, not a count per file
        twice = [path.name for path in paths if counts[path.stem] > 1][:4]
        if twice:  # x.png and x.jpg: two images for one frame
            raise ValueError(f"{paths[0].parent}: {', '.join(twice)} share a file name stem; each frame needs one "
                             f"image per folder (remove or rename the others)")
    if rgb_stems != depth_stems:
        missing = sorted(set(rgb_stems) ^ set(depth_stems), key=natural_key)[:5]
        raise ValueError(
            f"{rgb_dir} ({len(rgb_stems)} images) and {depth_dir} ({len(depth_stems)} images) must hold the "
            f"same file names; unmatched: {missing}"
        )


def _calibrated_intrinsics(folder: Path, first_depth: Path) -> Optional[tuple]:
    """(Intrinsics, depth_scale or None) from intrinsics.json / calibration.txt, else None."""
    calibration = read_calibration(folder)
    if calibration is None:
        return None
    width, height = image_size(first_depth)
    if "width" in calibration and (calibration["width"], calibration["height"]) != (width, height):
        raise ValueError(
            f"{folder}: calibration is for {calibration['width']}x{calibration['height']} images but "
            f"{first_depth} is {width}x{height}"
        )
    _check_plausible(calibration, width, height, folder)
    k = Intrinsics(calibration["fx"], calibration["fy"], calibration["cx"], calibration["cy"], width, height)
    return k, calibration.get("depth_scale")


def _check_plausible(calibration: dict, width: int, height: int, folder: Path) -> None:
    """ValueError for a calibration no pinhole image of ``width`` x ``height`` has: the principal
    point outside the image, or a focal length under a tenth of the image size (a field of view
    over 157 deg; normalised intrinsics, fx = 0.5-1.5, are the usual cause)."""
    for focal, centre, size in (("fx", "cx", width), ("fy", "cy", height)):
        if not -0.5 <= calibration[centre] <= size - 0.5:
            raise ValueError(f"{folder}: calibration {centre} = {calibration[centre]:g} lies outside the "
                             f"{width}x{height} images (pixels [-0.5, {size - 0.5:g}]); expected the principal "
                             f"point in pixels")
        if calibration[focal] < size / 10:
            raise ValueError(f"{folder}: calibration {focal} = {calibration[focal]:g} is under a tenth of the image "
                             f"size ({size} px): a field of view over 157 deg; expected the focal length in pixels, "
                             f"not normalised by the image size")


def _builtin_camera(intrinsics: Intrinsics, first_depth: Path, folder: Path, what: str) -> Intrinsics:
    """``intrinsics`` (a layout's built-in camera, ``what`` names it) when the depth images have its
    size; else ValueError asking for the folder's own calibration."""
    size = image_size(first_depth)
    if size != (intrinsics.width, intrinsics.height):
        raise ValueError(f"{first_depth}: {size[0]}x{size[1]} image but no intrinsics.json/calibration.txt in "
                         f"{folder}; {what} are for {intrinsics.width}x{intrinsics.height} images: add the camera "
                         f"of these images as {CALIBRATION_FORMATS}")
    return intrinsics


def tum_camera(folder: Path) -> str:
    """'freiburg1' | 'freiburg2' | 'freiburg3' from the folder name (fr3 when none is named)."""
    return named_tum_camera(folder) or "freiburg3"


def named_tum_camera(folder: Path) -> Optional[str]:
    """The TUM camera the folder's name names ('freiburg1', 'fr2', ...), or None."""
    name = folder.resolve().name.lower()
    for number in ("1", "2", "3"):
        if f"freiburg{number}" in name or re.search(rf"(^|[^a-z0-9])fr{number}([^0-9]|$)", name):
            return f"freiburg{number}"
    return None


def parse_tum(folder: Path, fps: float, max_time_diff: float) -> LayoutIndex:
    """TUM RGB-D: rgb.txt, depth.txt, groundtruth.txt; association by nearest stamp (0.02 s).

    Each colour frame takes the nearest depth stamp within ``max_time_diff`` (frames without
    one are dropped: no depth, no RGB-D frame) and its ground truth
    (:func:`tsslam_ref.datasets.tum_format.ground_truth_at`).  The frame timestamp is the colour
    stamp.  Intrinsics: ``intrinsics.json`` / ``calibration.txt`` in the folder if present (our
    resized slices and synthetic sequences), else the published values of the camera named by the
    folder (freiburg1/2/3, fr3 by default).
    """
    rgb_times, rgb_names, rgb_lines = read_file_list(folder / "rgb.txt")
    depth_times, depth_names, depth_lines = read_file_list(folder / "depth.txt")
    depth_index = associate_nearest(rgb_times, depth_times, max_time_diff)
    keep = np.flatnonzero(depth_index >= 0)
    if len(keep) == 0:
        raise ValueError(f"{folder}: no colour stamp in rgb.txt has a depth stamp in depth.txt within {max_time_diff} s")
    rgb_paths, depth_paths = [], []
    for i in keep:
        j = depth_index[i]
        for listing, name, line in (("rgb.txt", rgb_names[i], rgb_lines[i]), ("depth.txt", depth_names[j], depth_lines[j])):
            listed_file(folder, folder / listing, line, name)
        rgb_paths.append(folder / rgb_names[i])
        depth_paths.append(folder / depth_names[j])
    timestamps = rgb_times[keep]
    gt_file = folder / "groundtruth.txt"
    if not gt_file.is_file() and (folder / "pose.txt").is_file():
        gt_file = folder / "pose.txt"
    gt_poses, gt_span = None, None
    if gt_file.is_file():
        gt_times, gt_all = read_tum_trajectory(gt_file)
        gt_poses = ground_truth_at(timestamps, gt_times, gt_all, max_time_diff)
        gt_span = (gt_times[0], gt_times[-1])
    calibrated = _calibrated_intrinsics(folder, depth_paths[0])
    camera_note = ""
    if calibrated is not None:
        intrinsics, depth_scale = calibrated
    else:
        camera = TUM_INTRINSICS[tum_camera(folder)]
        intrinsics, depth_scale = _builtin_camera(camera, depth_paths[0], folder, "the published TUM values"), None
        if named_tum_camera(folder) is None:  # fr1 data in a renamed folder: 3.5 % off in fx, silently
            camera_note = (f"{folder.name}: no intrinsics.json and no freiburg1/2/3 in the folder's name, so the camera "
                           f"is freiburg3's (fx {camera.fx}); for fr1 or fr2 data name the folder so or add intrinsics.json")
    return LayoutIndex("tum", rgb_paths, depth_paths, timestamps, gt_poses, intrinsics, depth_scale, gt_span,
                       colour_without_depth=len(rgb_times) - len(keep), camera_note=camera_note)


def _read_matrix_lines(path: Path, per_line: int, what: str):
    """All numbers of a text file as (-1, 4, 4) matrices, ``per_line`` (4 or 16) numbers per line.

    Returns:
        matrices (M, 4, 4) float64 and, per matrix, the number (1-based) of its file's line that
        holds its first row.

    Raises:
        FileNotFoundError / ValueError naming the file (and line) for missing or malformed content.
    """
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: file not found ({what})")
    values, line_numbers = [], []
    with open(path, encoding="utf-8-sig") as handle:  # a byte-order mark (Windows editors) is no data
        for number, line in enumerate(handle, start=1):
            fields = line.split()
            if not fields:
                continue
            try:
                numbers = [float(f) for f in fields]
            except ValueError:
                raise ValueError(f"{path}:{number}: non-numeric value in '{line.strip()}' ({what})") from None
            if len(numbers) != per_line:
                raise ValueError(f"{path}:{number}: expected {per_line} numbers per line ({what}), got {len(numbers)}")
            values.extend(numbers)
            line_numbers.append(number)
    if not values or len(values) % 16:
        raise ValueError(f"{path}: holds {len(values)} numbers, not a whole number of 4x4 matrices ({what})")
    return np.asarray(values).reshape(-1, 4, 4), line_numbers[:: 16 // per_line]


POSE_TOLERANCE = 1e-3
"""Largest |R^T R - I| (max over entries) and |bottom row - (0, 0, 0, 1)| of a pose read from text:
poses printed with 4 or more decimals stay far below it; a scale of 1.001 or a shear does not."""


def check_rigid_poses(poses: np.ndarray, path: Path, line_numbers: List[int], frame_names: List[str]) -> None:
    """ValueError naming ``path``:line and the frame for the first finite pose (N, 4, 4) whose 3x3
    block is not a rotation (|R^T R - I| > :data:`POSE_TOLERANCE` or det <= 0) or whose bottom row is
    not 0 0 0 1.  Poses holding inf / NaN (unknown ground truth) are not checked."""
    finite = np.isfinite(poses).all(axis=(1, 2))
    poses = np.where(finite[:, None, None], poses, np.eye(4))  # unknown poses pass, without inf arithmetic
    rotations = poses[:, :3, :3]
    deviation = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2))
    determinant = np.linalg.det(rotations)
    bottom = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = np.flatnonzero(finite & ((deviation > POSE_TOLERANCE) | (determinant <= 0) | (bottom > POSE_TOLERANCE)))
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{path}:{line_numbers[i]}: the pose for {frame_names[i]} is not a rigid transform: its 3x3 block "
            f"has |R^T R - I| = {deviation[i]:.3g} and det {determinant[i]:.6g}, its bottom row "
            f"{' '.join(f'{v:g}' for v in poses[i, 3])}; expected a rotation (|R^T R - I| <= {POSE_TOLERANCE:g}, "
            f"det +1, not a scaled, sheared or mirrored matrix) and a bottom row 0 0 0 1")


def _one_pose_per_frame(poses: np.ndarray, path: Path, frames: int, images: Path) -> None:
    """ValueError naming ``path`` and both counts unless it holds exactly one pose per frame."""
    if len(poses) != frames:
        raise ValueError(f"{path}: {len(poses)} poses for {frames} frames in {images}; expected exactly one pose "
                         f"per frame, in the frames' order")


def _invalid_to_nan(poses: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(poses).all(axis=(1, 2))
    poses = poses.copy()
    poses[bad] = np.nan
    return poses


def _intrinsics_from(path: Path, fx, fy, cx, cy, width: int, height: int) -> Intrinsics:
    """:class:`Intrinsics`, with a refusal (non-positive or non-finite focal length) naming ``path``,
    the file the values came from (for NeuralRGBD without ``focal.txt``: the built-in value)."""
    try:
        return Intrinsics(float(fx), float(fy), float(cx), float(cy), width, height)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def parse_scannet(folder: Path, fps: float) -> LayoutIndex:
    """ScanNet export: color/<n>.jpg, depth/<n>.png (mm), pose/<n>.txt (c2w OpenCV; inf -> NaN),
    intrinsic/intrinsic_depth.txt.  Colour is resized to the depth size; time = n / fps."""
    for sub in ("color", "depth", "pose"):
        _require_dir(folder / sub)
    depth_paths = [p for p in _images(folder / "depth") if p.suffix.lower() == ".png"]  # .PNG too
    if not depth_paths:
        raise ValueError(f"{folder / 'depth'}: no depth PNGs")
    colour = {p.stem: p for p in _images(folder / "color")}
    rgb_paths, poses, numbers = [], [], []
    for depth_path in depth_paths:
        if depth_path.stem not in colour:
            raise FileNotFoundError(f"{folder / 'color'}: no colour image for {depth_path.name}")
        pose_path = folder / "pose" / f"{depth_path.stem}.txt"
        if not pose_path.is_file():
            raise FileNotFoundError(f"{pose_path}: pose file not found for {depth_path.name}")
        if not depth_path.stem.isdigit():
            raise ValueError(f"{depth_path}: ScanNet frame names must be integers (frame numbers)")
        rgb_paths.append(colour[depth_path.stem])
        matrices, lines = _read_matrix_lines(pose_path, 4, "4x4 camera-to-world pose")
        if len(matrices) != 1:
            raise ValueError(f"{pose_path}: {len(matrices)} 4x4 matrices; expected one camera-to-world pose")
        check_rigid_poses(matrices, pose_path, lines, [f"frame {depth_path.stem}"])
        poses.append(matrices[0])
        numbers.append(int(depth_path.stem))
    k_path = folder / "intrinsic" / "intrinsic_depth.txt"
    if not k_path.is_file():
        raise FileNotFoundError(f"{k_path}: ScanNet depth intrinsics not found (export them with SensReader)")
    k = _read_matrix_lines(k_path, 4, "4x4 intrinsic matrix")[0][0]
    width, height = image_size(depth_paths[0])
    intrinsics = _intrinsics_from(k_path, k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
    _check_plausible({"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2]}, width, height, k_path)
    timestamps = np.asarray(numbers, dtype=np.float64) / fps
    return LayoutIndex("scannet", rgb_paths, depth_paths, timestamps, _invalid_to_nan(np.stack(poses)), intrinsics, None)


def parse_neural_rgbd(folder: Path, fps: float) -> LayoutIndex:
    """NeuralRGBD synthetic: images/, depth_filtered/ (else depth/), poses.txt (4 lines per c2w,
    OpenGL axes -> converted); fx = fy = 554.256... or focal.txt; cx = W/2, cy = H/2; time = i / fps."""
    depth_dir = folder / "depth_filtered"
    if not depth_dir.is_dir():
        depth_dir = folder / "depth"
    _require_dir(folder / "images")
    _require_dir(depth_dir)
    rgb_paths = _images(folder / "images")
    depth_paths = _images(depth_dir)
    if not rgb_paths:
        raise ValueError(f"{folder / 'images'}: no images")
    if len(rgb_paths) != len(depth_paths):
        raise ValueError(f"{folder / 'images'} has {len(rgb_paths)} images but {depth_dir} has {len(depth_paths)}")
    for rgb_path, depth_path in zip(rgb_paths, depth_paths):  # img<i>.png with depth<i>.png
        if re.sub(r"\D", "", rgb_path.stem) != re.sub(r"\D", "", depth_path.stem):
            raise ValueError(f"{rgb_path} pairs with {depth_path} by order, but their frame numbers differ "
                             f"(a frame missing on each side?); expected images/img<i> with {depth_dir.name}/depth<i>")
    poses_gl, lines = _read_matrix_lines(folder / "poses.txt", 4, "4 lines per 4x4 pose")
    _one_pose_per_frame(poses_gl, folder / "poses.txt", len(rgb_paths), folder / "images")
    check_rigid_poses(poses_gl, folder / "poses.txt", lines, [f"images/{p.name}" for p in rgb_paths])
    calibrated = _calibrated_intrinsics(folder, depth_paths[0])
    intrinsics = calibrated[0] if calibrated else _neural_rgbd_camera(folder, depth_paths[0])
    poses = opengl_to_opencv_pose(_invalid_to_nan(poses_gl))
    timestamps = np.arange(len(rgb_paths), dtype=np.float64) / fps
    return LayoutIndex("neural_rgbd", rgb_paths, depth_paths, timestamps, poses, intrinsics,
                       calibrated[1] if calibrated else None)


def _neural_rgbd_camera(folder: Path, first_depth: Path) -> Intrinsics:
    """fx = fy from ``focal.txt`` (else the release's 554.256 for 640x480 renders), cx = W/2, cy = H/2."""
    focal_path = folder / "focal.txt"
    width, height = image_size(first_depth)
    if not focal_path.is_file():
        release = Intrinsics(NEURAL_RGBD_FOCAL, NEURAL_RGBD_FOCAL, 320.0, 240.0, 640, 480)
        without = "without focal.txt the release's values (fx = fy = 554.256)"
        return _builtin_camera(release, first_depth, folder, without)
    try:
        focal = float(focal_path.read_text(encoding="utf-8-sig").split()[0])
    except (ValueError, IndexError):
        raise ValueError(f"{focal_path}:1: expected one number (the focal length in pixels)") from None
    return _intrinsics_from(focal_path, focal, focal, width / 2.0, height / 2.0, width, height)


def parse_replica(folder: Path, fps: float) -> LayoutIndex:
    """Replica (NICE-SLAM release): results/frame%06d.jpg, results/depth%06d.png, traj.txt (16
    numbers per line, c2w OpenCV); 1200x680, fx = fy = 600, cx 599.5, cy 339.5; time = i / fps."""
    results = folder / "results"
    _require_dir(results)
    rgb_paths = _images(results, "frame")
    depth_paths = [p for p in _images(results, "depth") if p.suffix.lower() == ".png"]
    if not rgb_paths:
        raise ValueError(f"{results}: no frame*.jpg images")
    if [p.stem[5:] for p in rgb_paths] != [p.stem[5:] for p in depth_paths]:
        raise ValueError(f"{results}: frame*.jpg ({len(rgb_paths)}) and depth*.png ({len(depth_paths)}) do not pair up")
    poses, lines = _read_matrix_lines(folder / "traj.txt", 16, "16 numbers per line")
    _one_pose_per_frame(poses, folder / "traj.txt", len(rgb_paths), results)
    check_rigid_poses(poses, folder / "traj.txt", lines, [f"results/{p.name}" for p in rgb_paths])
    calibrated = _calibrated_intrinsics(folder, depth_paths[0])
    intrinsics = calibrated[0] if calibrated else _builtin_camera(REPLICA_INTRINSICS, depth_paths[0], folder,
                                                                  "the release's values (600, 600, 599.5, 339.5)")
    timestamps = np.arange(len(rgb_paths), dtype=np.float64) / fps
    return LayoutIndex("replica", rgb_paths, depth_paths, timestamps, _invalid_to_nan(poses),
                       intrinsics, calibrated[1] if calibrated else None)


def parse_folder(folder: Path, fps: float, max_time_diff: float) -> LayoutIndex:
    """Generic folder (ours): rgb/ and depth/ with the same file names (sorted naturally),
    intrinsics.json or calibration.txt, optional groundtruth.txt / trajectory.txt (TUM format).

    Timestamps (:func:`folder_timestamps`): stems with a decimal point are seconds
    ('1341841873.273798.png'); integer stems are frame numbers (number / fps, so gaps in the
    numbering stay gaps in time) when they step by less than 10, else milliseconds, microseconds
    or nanoseconds ('1520530328189680000.png'), whichever makes the step a frame spacing; stems
    that are not all numbers give index / fps.  Numeric stems are ordered by value.  GT is
    associated to those stamps as in the TUM layout.
    """
    _require_dir(folder / "rgb")
    _require_dir(folder / "depth")
    rgb_paths = _images(folder / "rgb")
    depth_paths = [p for p in _images(folder / "depth") if p.suffix.lower() == ".png"]
    if not rgb_paths:
        raise ValueError(f"{folder / 'rgb'}: no images")
    _stems_match(rgb_paths, depth_paths, folder / "rgb", folder / "depth")
    calibrated = _calibrated_intrinsics(folder, depth_paths[0])
    if calibrated is None:
        raise FileNotFoundError(f"{folder}: needs the camera as {CALIBRATION_FORMATS}")
    timestamps = folder_timestamps([p.stem for p in rgb_paths], fps, folder / "rgb")
    order = np.argsort(timestamps, kind="stable")  # '0.1' after '0.033333', whatever the sort by name said
    rgb_paths, depth_paths = [rgb_paths[i] for i in order], [depth_paths[i] for i in order]
    timestamps = timestamps[order]
    if np.any(np.diff(timestamps) <= 0):
        repeated = rgb_paths[int(np.flatnonzero(np.diff(timestamps) <= 0)[0]) + 1].name
        raise ValueError(f"{folder / 'rgb'}: two file names give the same time ({repeated}); each frame needs its own")
    gt_poses, gt_span = None, None
    for name in ("groundtruth.txt", "trajectory.txt"):
        if (folder / name).is_file():
            gt_times, gt_all = read_tum_trajectory(folder / name)
            gt_poses = ground_truth_at(timestamps, gt_times, gt_all, max_time_diff)
            gt_span = (gt_times[0], gt_times[-1])
            break
    return LayoutIndex("folder", rgb_paths, depth_paths, timestamps, gt_poses, calibrated[0], calibrated[1], gt_span)


def folder_timestamps(stems, fps: float, folder: Path = Path(".")) -> np.ndarray:
    """(N,) float64 seconds from the ``folder`` layout's file stems (rule in :func:`parse_folder`).

    Integer stems: a median step under 10 means frame numbers (n / fps); otherwise the unit is the
    first of milliseconds, microseconds, nanoseconds that puts the median step between 1 ms and 1 s
    (a camera's frame spacing); ValueError naming ``folder`` when none does.
    """
    try:
        values = [float(stem) for stem in stems]
    except ValueError:
        return np.arange(len(stems), dtype=np.float64) / fps
    if any("." in stem or "e" in stem.lower() for stem in stems):
        return np.asarray(values, dtype=np.float64)  # seconds
    numbers = np.asarray([int(stem) for stem in stems], dtype=np.int64)
    step = float(np.median(np.abs(np.diff(np.sort(numbers))))) if len(numbers) > 1 else 1.0
    if step < 10:
        return numbers.astype(np.float64) / fps  # frame numbers
    for unit in (1e-3, 1e-6, 1e-9):
        if 1e-3 <= step * unit <= 1.0:
            return numbers.astype(np.float64) * unit
    raise ValueError(f"{folder}: integer file names {stems[0]}, {stems[1]}, ... step by {step:g}, which is no frame "
                     f"spacing in ms, us or ns; name the files by their time in seconds with a decimal point")


def _looks_like(folder: Path) -> dict:
    """For each layout, the missing entries (empty list = matches)."""
    def missing(*names):
        return [n for n in names if not (folder / n).exists()]
    neural_depth = "depth_filtered" if (folder / "depth_filtered").is_dir() else "depth"
    return {
        "tum": missing("rgb.txt", "depth.txt"),
        "scannet": missing("color", "depth", "pose"),
        "neural_rgbd": missing("images", neural_depth, "poses.txt"),
        "replica": missing("results", "traj.txt"),
        "folder": missing("rgb", "depth")
        + ([] if read_calibration_exists(folder) else [f"the camera: {CALIBRATION_FORMATS}"]),
    }


def matching_layouts(folder: Path) -> List[str]:
    """The layouts whose entries ``folder`` has (usually one; none for a folder of another kind)."""
    return [kind for kind, missing in _looks_like(folder).items() if not missing]


def read_calibration_exists(folder: Path) -> bool:
    return (folder / "intrinsics.json").is_file() or (folder / "calibration.txt").is_file()


def other_layout_hint(folder: Path, kind: str) -> Optional[str]:
    """When ``folder`` lacks entries of layout ``kind`` but has every entry of another layout: a
    sentence naming both (for a layout given by name, as ``--dataset``); else None."""
    checks = _looks_like(folder)
    matching = [other for other, missing in checks.items() if not missing and other != kind]
    if not checks[kind] or not matching:
        return None
    return (f"{folder} lacks {', '.join(checks[kind])} of the '{kind}' layout but has every entry of the "
            f"'{matching[0]}' layout ({LAYOUTS[matching[0]]}): name that one, or 'auto'")


def detect_dataset(path) -> str:
    """Layout of a dataset folder: 'tum' | 'scannet' | 'neural_rgbd' | 'replica' | 'folder'.

    Raises:
        FileNotFoundError: the folder does not exist.
        ValueError: no layout matches; the message lists every layout tried and what was missing.
    """
    folder = Path(path)
    require_dataset_folder(folder)
    checks = _looks_like(folder)
    for kind, missing in checks.items():
        if not missing:
            return kind
    tried = "; ".join(f"{kind} [{LAYOUTS[kind]}] missing {', '.join(missing)}" for kind, missing in checks.items())
    raise ValueError(f"{folder}: not a recognised RGB-D dataset folder. Layouts tried: {tried}")
