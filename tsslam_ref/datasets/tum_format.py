"""TUM RGB-D text formats: file lists, trajectories, timestamp association, pose interpolation.

TS-SLAM §IV-A (TUM RGB-D benchmark); Sturm et al., IROS 2012 (file formats and the 0.02 s
association rule of ``associate.py``).  Side layer.  Taught in notebooks/00_data_and_cameras.ipynb.

* File lists (``rgb.txt``, ``depth.txt``): ``timestamp filename`` per line, ``#`` comments.
* Trajectories (``groundtruth.txt``): ``timestamp tx ty tz qx qy qz qw``, camera-to-world,
  quaternion scalar-last.  Timestamps are float64 seconds and must not decrease.

| symbol | variable | shape | unit |
|---|---|---|---|
| t | ``timestamps`` | (N,) float64 | s |
| T_wc | ``poses`` | (N, 4, 4) float64 | m |
"""

import re
from pathlib import Path
from typing import List, Tuple

import numpy as np

from tsslam_ref.files import atomic_write_text
from tsslam_ref.geometry import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix, trajectory_to_tum, tum_to_pose
from tsslam_ref.times import float64_seconds

TUM_MAX_TIME_DIFF = 0.02
"""Association tolerance (s) of TUM's associate.py."""
QUATERNION_NORM_TOLERANCE = 0.01
"""Largest |norm - 1| of a trajectory line's quaternion.  It is normalised on reading, so any
precision passes (TUM's 4 decimals are off by 1e-4 at most); a norm off by more means columns in
another order or a broken writer."""


def _data_lines(path: Path, commas: bool = True):
    """Yield (line_number, fields, text) for the non-comment, non-blank lines of a text file.

    Fields are separated by white space, and by commas too when ``commas`` (numeric rows)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: " + ("is a folder; expected a text file" if path.is_dir() else "file not found"))
    with open(path, "rb") as handle:
        for number, raw in enumerate(handle, start=1):
            try:
                line = raw.decode("utf-8-sig" if number == 1 else "utf-8")  # a byte-order mark some editors write
            except UnicodeDecodeError:
                raise ValueError(f"{path}:{number}: not text (bytes that are not UTF-8); expected a text file "
                                 f"of whitespace-separated values") from None
            if "\x00" in line:
                raise ValueError(f"{path}:{number}: not text (a NUL byte); expected a text file of whitespace-separated values")
            stripped = line.strip()
            if stripped and not stripped.startswith("#"):
                yield number, (stripped.replace(",", " ") if commas else stripped).split(), stripped


def _decimal_comma_hint(text: str, columns: Tuple[int, ...]) -> str:
    """A hint for a line written with decimal commas ('1,5'), which are read as separators, or ''.

    That is a line of ``columns`` whitespace-separated fields whose first (the timestamp) is digits, a comma, digits."""
    fields = text.split()
    if len(fields) in columns and re.fullmatch(r"[+-]?\d+,\d+", fields[0]):
        return "; the line looks written with decimal commas ('1,5'): write decimal points ('1.5')"
    return ""


def read_file_list(path) -> Tuple[np.ndarray, List[str], List[int]]:
    """Read a TUM file list (``rgb.txt`` / ``depth.txt``): ``timestamp filename`` per line.

    Returns:
        timestamps (N,) float64 s, file names relative to the list's folder, line numbers (1-based).

    Raises:
        ValueError: '<file>:<line>: ...' for a malformed line (other than two fields), an empty list, a non-finite
            timestamp, or a timestamp not larger than the previous one (a repeated stamp would
            make two frames of one instant).
    """
    stamps, names, numbers = [], [], []
    for number, fields, text in _data_lines(path, commas=False):
        if "," in fields[0]:  # a comma-separated line; otherwise a comma belongs to the file name
            fields = " ".join(fields).replace(",", " ").split()
        if len(fields) != 2:  # a third field is either another column or a file name with a space: neither is read
            hint = _decimal_comma_hint(text, (2,)) or (" (a file name cannot hold spaces here, and no other column "
                                                       "is read)" if len(fields) > 2 else "")
            raise ValueError(f"{path}:{number}: expected 'timestamp filename', got {len(fields)} field(s) "
                             f"'{' '.join(fields)}'{hint}")
        try:
            stamp = float(fields[0])
        except ValueError:
            raise ValueError(f"{path}:{number}: timestamp '{fields[0]}' is not a number") from None
        if not np.isfinite(stamp):
            raise ValueError(f"{path}:{number}: timestamp '{fields[0]}' is not a finite number")
        if stamps and stamp == stamps[-1]:
            raise ValueError(f"{path}:{number}: timestamp {fields[0]} repeats line {numbers[-1]}'s; expected one line per time stamp")
        if stamps and stamp < stamps[-1]:
            raise ValueError(f"{path}:{number}: timestamp {fields[0]} is earlier than the previous line's {stamps[-1]:.6f} (timestamps out of order)")
        stamps.append(stamp)
        names.append(fields[1])
        numbers.append(number)
    if not stamps:
        raise ValueError(f"{path}: no entries (expected lines 'timestamp filename')")
    return np.asarray(stamps, dtype=np.float64), names, numbers


def listed_file(folder: Path, listing: Path, line: int, name: str) -> Path:
    """``folder / name`` for a file named on line ``line`` of ``listing``, checked to stay inside.

    A list may name files in the dataset folder and its sub-folders only: an absolute path, a
    path through '..' that leaves the folder, or a symbolic link whose target lies outside the
    folder is refused (a dataset list should not make the program read, say, a file in /etc).
    Symbolic links whose targets stay inside the folder are allowed.

    Raises:
        ValueError: '<listing>:<line>: ...' for a path leaving the folder.
        FileNotFoundError: '<listing>:<line>: ...' for a missing file.
    """
    if Path(name).is_absolute():
        raise ValueError(f"{listing}:{line}: '{name}' is an absolute path; expected a path relative to the dataset folder {folder}")
    path = folder / name
    root = folder.resolve()
    if not path.resolve().is_relative_to(root):
        raise ValueError(f"{listing}:{line}: '{name}' leads outside the dataset folder {root} "
                         f"(to {path.resolve()}); expected a file inside it")
    if not path.is_file():
        raise FileNotFoundError(f"{listing}:{line}: listed file '{name}' not found{_missing_file_hint(folder, name)}")
    return path


def _missing_file_hint(folder: Path, name: str) -> str:
    """Why a listed name that works on Windows or macOS is missing here: a backslash separator, or
    a name that differs from the file's only in case (their disks ignore case)."""
    if "\\" in name:
        return " (the list separates folders with '\\', as on Windows: write '/')"
    parent = (folder / name).parent
    if parent.is_dir():
        same = [entry.name for entry in parent.iterdir() if entry.name.lower() == Path(name).name.lower()]
        if same:
            return f" (the folder holds '{same[0]}': names differ in case, which Windows and macOS disks ignore)"
    return ""


def read_tum_trajectory(path, unique_stamps: bool = False) -> Tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``timestamp tx ty tz qx qy qz qw`` per line, '#' comments.

    Returns:
        timestamps (N,) float64 s and camera-to-world poses (N, 4, 4) float64.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: '<file>:<line>: ...' for a line without 8 numbers (14, a continuous export of
            ours, read as its first 8), a quaternion whose norm
            is 0 or off 1 by more than :data:`QUATERNION_NORM_TOLERANCE`, a decreasing timestamp,
            a repeated one when ``unique_stamps`` (an estimate: one pose per frame; recorded ground
            truth such as TUM fr2/desk repeats a few stamps), or a file with no poses.
    """
    stamps, rows, numbers = [], [], []
    for number, fields, text in _data_lines(path):
        if len(fields) == 14:  # our continuous export: the pose, then velocities (vx vy vz wx wy wz), not read here
            fields = fields[:8]
        if len(fields) != 8:
            raise ValueError(f"{path}:{number}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw' (or the 14 of a "
                             f"continuous export), got {len(fields)} fields{_decimal_comma_hint(text, (8, 14))}")
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise ValueError(f"{path}:{number}: non-numeric value in '{' '.join(fields)}'") from None
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{path}:{number}: non-finite value in '{' '.join(fields)}'")
        if np.linalg.norm(values[4:8]) < 1e-12:
            raise ValueError(f"{path}:{number}: zero quaternion")
        if abs(np.linalg.norm(values[4:8]) - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise ValueError(f"{path}:{number}: quaternion qx qy qz qw = {' '.join(fields[4:8])} has norm "
                             f"{np.linalg.norm(values[4:8]):.6g}; expected a unit quaternion (norm within "
                             f"{QUATERNION_NORM_TOLERANCE:g} of 1) in the order 'timestamp tx ty tz qx qy qz qw'")
        if unique_stamps and stamps and values[0] == stamps[-1]:
            raise ValueError(f"{path}:{number}: timestamp {fields[0]} repeats line {numbers[-1]}'s; expected one pose per time stamp")
        if stamps and values[0] < stamps[-1]:
            raise ValueError(f"{path}:{number}: timestamp {fields[0]} is earlier than the previous line's (timestamps out of order)")
        stamps.append(values[0])
        numbers.append(number)
        rows.append(values[1:])
    if not stamps:
        raise ValueError(f"{path}: no poses (expected lines 'timestamp tx ty tz qx qy qz qw')")
    return np.asarray(stamps, dtype=np.float64), tum_to_pose(np.asarray(rows))


ROTATION_TOLERANCE = 1e-2
"""Largest |RᵀR − I| entry a written pose may have: far above float32 drift over long runs, far
below a reflection (one flipped axis), a scaled matrix or a visible shear."""


def _check_rotations(poses: np.ndarray, known: np.ndarray, timestamps: np.ndarray) -> None:
    """ValueError naming the first known pose whose 3x3 block is no rotation (a quaternion would
    write some other rotation in its place, silently)."""
    rotations = poses[known, :3, :3]
    deviation = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2), initial=0.0)
    bad = np.flatnonzero((deviation > ROTATION_TOLERANCE) | (np.linalg.det(rotations) <= 0))
    if bad.size:
        j = int(np.flatnonzero(known)[bad[0]])
        determinant = np.linalg.det(poses[j, :3, :3])
        raise ValueError(f"poses[{j}] (t = {timestamps[j]:.6f} s) is not a rotation: det {determinant:.4g}, largest "
                         f"|RᵀR − I| entry {deviation[bad[0]]:.3g} (a flipped camera axis gives det −1); a TUM "
                         f"quaternion cannot hold it")


def write_tum_trajectory(path, timestamps, poses, overwrite: bool = False) -> Path:
    """Write camera-to-world poses as a TUM trajectory, atomically (``files.atomic_write_text``).

    Stamps are written with ``%.6f`` (microseconds), positions and quaternions with ``%.9f``; the
    first quaternion has qw >= 0, each next one lies in the hemisphere of the one before
    (:func:`geometry.trajectory_to_tum`).  Rows whose pose holds NaN are skipped (unknown
    ground truth).

    Args:
        path: output file.
        timestamps: (N,) float64 s (float32 is refused: it cannot hold the stamps).
        poses: (N, 4, 4) camera-to-world; each 3x3 block a rotation (ValueError otherwise).
        overwrite: replace an existing file; otherwise FileExistsError.
    """
    path = Path(path)
    timestamps = float64_seconds(timestamps, "timestamps").reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (timestamps.shape[0], 4, 4):
        raise ValueError(f"poses must have shape ({timestamps.shape[0]}, 4, 4) to match the timestamps, got {poses.shape}")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    known = np.isfinite(poses).all(axis=(1, 2))
    _check_rotations(poses, known, timestamps)
    values = trajectory_to_tum(poses[known])  # no q -> -q jump between neighbouring lines
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, OpenCV camera axes)"]
    for stamp, row in zip(timestamps[known], values):
        lines.append(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in row))
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, "\n".join(lines) + "\n")  # a new file; a link at ``path`` is replaced, not followed
    return path


def associate_nearest(query: np.ndarray, reference: np.ndarray, max_time_diff: float) -> np.ndarray:
    """Index of the nearest reference stamp for every query stamp, -1 where none is within tolerance.

    Args:
        query: (N,) float64 s.  reference: (M,) float64 s, non-decreasing.
        max_time_diff: tolerance in s (TUM: 0.02).

    Returns:
        (N,) int64 indices into ``reference`` (ties go to the earlier stamp).
    """
    query = np.asarray(query, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    right = np.clip(np.searchsorted(reference, query), 1, len(reference) - 1) if len(reference) > 1 else np.zeros(len(query), int)
    left = np.maximum(right - 1, 0)
    pick_left = np.abs(query - reference[left]) <= np.abs(reference[right] - query)
    nearest = np.where(pick_left, left, right)
    nearest[np.abs(reference[nearest] - query) > max_time_diff] = -1
    return nearest.astype(np.int64)


def _slerp(rotation_a: np.ndarray, rotation_b: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Rotation a Exp(f Log(a^T b)) via quaternions.  (N, 3, 3), (N, 3, 3), (N,) -> (N, 3, 3)."""
    qa = matrix_to_quaternion_xyzw(rotation_a)
    qb = matrix_to_quaternion_xyzw(rotation_b)
    dot = np.sum(qa * qb, axis=-1)
    qb = np.where(dot[:, None] < 0, -qb, qb)  # shortest arc
    dot = np.abs(dot).clip(max=1.0)
    angle = np.arccos(dot)
    sin = np.sin(angle)
    small = sin < 1e-9  # nearly equal rotations: linear blend avoids 0/0
    safe = np.where(small, 1.0, sin)
    weight_a = np.where(small, 1.0 - fraction, np.sin((1.0 - fraction) * angle) / safe)
    weight_b = np.where(small, fraction, np.sin(fraction * angle) / safe)
    return quaternion_xyzw_to_matrix(weight_a[:, None] * qa + weight_b[:, None] * qb)


def interpolate_poses(query: np.ndarray, timestamps: np.ndarray, poses: np.ndarray, max_gap: float) -> np.ndarray:
    """Poses at ``query`` times: positions linear, rotations slerp, between bracketing samples.

    A query time exactly at a sample returns that sample.  Where the bracketing samples are more
    than ``max_gap`` apart, or the query lies outside [t_0, t_{M-1}], the result is NaN.

    Args:
        query: (N,) float64 s.  timestamps: (M,) float64 s, non-decreasing.
        poses: (M, 4, 4) camera-to-world.  max_gap: largest usable sample spacing (s).

    Returns:
        (N, 4, 4) float64 poses, NaN-filled where unknown.
    """
    query = np.asarray(query, dtype=np.float64)
    timestamps = np.asarray(timestamps, dtype=np.float64)
    out = np.full((len(query), 4, 4), np.nan)
    if len(timestamps) == 0:
        return out
    right = np.searchsorted(timestamps, query, side="left")  # first sample >= query
    exact = (right < len(timestamps)) & (timestamps[np.minimum(right, len(timestamps) - 1)] == query)
    out[exact] = poses[right[exact]]
    inner = ~exact & (right > 0) & (right < len(timestamps))
    if inner.any():
        i1 = right[inner]
        i0 = i1 - 1
        gap = timestamps[i1] - timestamps[i0]
        usable = gap <= max_gap
        i0, i1, gap = i0[usable], i1[usable], gap[usable]
        fraction = (query[inner][usable] - timestamps[i0]) / gap
        pose = np.zeros((len(i0), 4, 4))
        pose[:, :3, :3] = _slerp(poses[i0, :3, :3], poses[i1, :3, :3], fraction)
        pose[:, :3, 3] = (1.0 - fraction[:, None]) * poses[i0, :3, 3] + fraction[:, None] * poses[i1, :3, 3]
        pose[:, 3, 3] = 1.0
        rows = np.flatnonzero(inner)[usable]
        out[rows] = pose
    return out


def ground_truth_at(timestamps: np.ndarray, gt_times: np.ndarray, gt_poses: np.ndarray, max_time_diff: float) -> np.ndarray:
    """Ground-truth pose at each of ``timestamps`` (N,) s, as the loaders give it to a frame:
    NaN unless a GT stamp lies within ``max_time_diff`` s (TUM's rule); the value is interpolated
    between the bracketing GT samples (gap <= 2 max_time_diff), else the nearest sample's.

    Returns:
        (N, 4, 4) float64 camera-to-world poses, NaN where unknown.
    """
    nearest = associate_nearest(timestamps, gt_times, max_time_diff)
    poses = interpolate_poses(timestamps, gt_times, gt_poses, max_gap=2.0 * max_time_diff)
    fallback = (nearest >= 0) & ~np.isfinite(poses).all(axis=(1, 2))
    poses[fallback] = gt_poses[nearest[fallback]]
    poses[nearest < 0] = np.nan
    return poses
