"""``Frame`` and the lazy ``RGBDSequence``: one RGB-D frame with its camera and ground truth.

TS-SLAM §IV-A: sequences of RGB-D frames with timestamps (30 FPS assumed where a dataset has none)
and ground-truth camera-to-world poses.  Side layer.  Taught in notebooks/00_data_and_cameras.ipynb.

A sequence holds file paths, timestamps and poses only; ``sequence[i]`` reads, crops and resizes
frame i on demand, so a 3000-frame sequence costs a few hundred kB of memory.

| name | shape | unit / frame |
|---|---|---|
| ``rgb`` | (H, W, 3) float32 | [0, 1] |
| ``depth`` | (H, W) float32 | m, 0 = invalid (z in the camera frame, not ray length) |
| ``pose_c2w`` | (4, 4) float64 | camera-to-world, OpenCV camera axes |
| ``timestamps`` | (N,) float64 | s, dataset time |
"""

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import numpy as np

from tsslam_ref.datasets.images import (check_colour_aspect, check_image, crop, output_size, read_depth, read_rgb,
                                        resize_depth, resize_rgb)
from tsslam_ref.datasets.intrinsics import Intrinsics


@dataclass
class Frame:
    """One RGB-D frame as loaded (after crop and resize)."""

    index: int
    """Position in the sequence as loaded (0 .. len - 1)."""
    timestamp: float
    """float64 seconds (dataset time; index / fps where the dataset has none)."""
    rgb: np.ndarray
    """(H, W, 3) float32 in [0, 1]."""
    depth: np.ndarray
    """(H, W) float32 metres, 0 = invalid."""
    intrinsics: Intrinsics
    pose_c2w: Optional[np.ndarray]
    """(4, 4) float64 ground truth, camera-to-world, OpenCV axes; None where unknown."""


class RGBDSequence:
    """Lazy RGB-D sequence: frames are read on ``__getitem__``; nothing big is kept in memory.

    Attributes:
        name: folder name.  kind: "tum" | "scannet" | "neural_rgbd" | "replica" | "folder".
        path: dataset folder.  intrinsics: camera after crop/resize (``uncropped_intrinsics``:
        the same resize without the crop).
        timestamps: (N,) float64 s.  gt_poses: (N, 4, 4) float64 with NaN-filled rows where
        unknown, or None when the dataset has no ground truth.  depth_scale: PNG value per metre.
        depth_trunc: carried for the losses; the loader never zeroes depth beyond it.
        native_intrinsics: camera of the stored depth images before crop/resize.
        rgb_paths, depth_paths: the files, one per frame.
        frames_without_gt: frames of the folder left out before the selection because their
        ground-truth pose is unknown (``require_gt``); ``times_without_gt``: their (M,) stamps (s).
        colour_without_depth: TUM colour images left out because no depth image was taken within
        the association tolerance (0.02 s); 0 for the other layouts.
        camera_note: why the camera may not be the data's (a TUM folder whose name names no camera
        and that has no calibration file gets freiburg3's); "" otherwise.
    """

    def __init__(
        self,
        name: str,
        kind: str,
        path: Path,
        rgb_paths: List[Path],
        depth_paths: List[Path],
        timestamps: np.ndarray,
        gt_poses: Optional[np.ndarray],
        native_intrinsics: Intrinsics,
        depth_scale: float,
        crop_edge: int = 0,
        resize_width: Optional[int] = None,
        depth_trunc: Optional[float] = None,
        frames_without_gt: int = 0,
        colour_without_depth: int = 0,
        camera_note: str = "",
        times_without_gt=(),
    ):
        if not (len(rgb_paths) == len(depth_paths) == len(timestamps)):
            raise ValueError(
                f"{path}: {len(rgb_paths)} colour, {len(depth_paths)} depth files and {len(timestamps)} timestamps differ"
            )
        if len(timestamps) == 0:
            raise ValueError(f"{path}: the sequence has no frames after association and frame selection")
        if gt_poses is not None and gt_poses.shape != (len(timestamps), 4, 4):
            raise ValueError(f"{path}: gt_poses has shape {gt_poses.shape}, expected ({len(timestamps)}, 4, 4)")
        if not depth_scale > 0:
            raise ValueError(f"depth_scale must be > 0, got {depth_scale}")
        self.name = name
        self.kind = kind
        self.path = Path(path)
        self.rgb_paths = [Path(p) for p in rgb_paths]
        self.depth_paths = [Path(p) for p in depth_paths]
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.gt_poses = None if gt_poses is None else np.asarray(gt_poses, dtype=np.float64)
        self.native_intrinsics = native_intrinsics
        self.depth_scale = float(depth_scale)
        self.crop_edge = int(crop_edge)
        self.resize_width = resize_width
        self.depth_trunc = depth_trunc
        self.frames_without_gt = int(frames_without_gt)
        self.times_without_gt = np.asarray(times_without_gt, dtype=np.float64)
        self.colour_without_depth = int(colour_without_depth)
        self.camera_note = camera_note
        width, height = output_size(native_intrinsics.width, native_intrinsics.height, self.crop_edge, resize_width)
        edge = self.crop_edge
        self.intrinsics = native_intrinsics.cropped(edge, edge, edge, edge).resized(width, height)

    @property
    def uncropped_intrinsics(self) -> Intrinsics:
        """The camera of the whole stored image (no ``crop_edge``) at the working width
        (``resize_width``): the raw camera's frustum, which Co-SLAM culls meshes with.  Equals
        :attr:`intrinsics` when nothing is cropped."""
        native = self.native_intrinsics
        return native.resized(*output_size(native.width, native.height, 0, self.resize_width))

    def __len__(self) -> int:
        return len(self.timestamps)

    def __repr__(self) -> str:
        k = self.intrinsics
        return (f"RGBDSequence(name={self.name!r}, kind={self.kind!r}, frames={len(self)}, "
                f"size={k.width}x{k.height}, path='{self.path}')")

    def __getitem__(self, i: int) -> Frame:
        """Read frame ``i`` (negative indices count from the end).  ValueError naming the file for a
        depth image of another size than the calibration's or with no valid depth at all, or a
        colour image of another aspect ratio than the depth's (beyond 1 %)."""
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"sequence indices must be integers, got {type(i).__name__}")
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for a sequence of {n} frames")
        i = int(i) % n
        native = self.native_intrinsics
        depth = read_depth(self.depth_paths[i], self.depth_scale)  # (H0, W0)
        if depth.shape != (native.height, native.width):
            raise ValueError(
                f"{self.depth_paths[i]}: depth is {depth.shape[1]}x{depth.shape[0]}, expected "
                f"{native.width}x{native.height} like the sequence's calibration"
            )
        rgb = read_rgb(self.rgb_paths[i])  # (Hc, Wc, 3), any size of the depth's aspect ratio
        check_colour_aspect(self.rgb_paths[i], (rgb.shape[1], rgb.shape[0]), (native.width, native.height))
        rgb = resize_rgb(rgb, native.width, native.height)  # (H0, W0, 3)
        rgb, depth = crop(rgb, self.crop_edge), crop(depth, self.crop_edge)
        rgb = resize_rgb(rgb, self.intrinsics.width, self.intrinsics.height)  # (H, W, 3)
        depth = resize_depth(depth, self.intrinsics.width, self.intrinsics.height)  # (H, W)
        if not np.any(depth > 0):
            raise ValueError(f"{self.depth_paths[i]}: depth is 0 (no measurement) at every pixel; "
                             f"expected depth in every frame")
        pose = None
        if self.gt_poses is not None and np.isfinite(self.gt_poses[i]).all():
            pose = self.gt_poses[i].copy()
        return Frame(i, float(self.timestamps[i]), rgb, depth, self.intrinsics, pose)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def check_files(self) -> int:
        """Check every frame's two image files cheaply (header, size, mode, PNG checksums).

        Depth must be a single-channel 16-bit PNG of the calibration's size; colour an 8- or
        16-bit RGB, RGBA or grey image of any size with the depth's aspect ratio within 1 % (it is
        resized to the depth's).  No pixel is
        decoded, so a 3000-frame sequence takes seconds.  Returns the number of files checked.

        Raises:
            ValueError / FileNotFoundError naming the first bad file and what was expected.
        """
        native = self.native_intrinsics
        for rgb_path, depth_path in zip(self.rgb_paths, self.depth_paths):
            check_image(depth_path, "depth", (native.width, native.height))
            colour_size = check_image(rgb_path, "colour")
            check_colour_aspect(rgb_path, colour_size, (native.width, native.height))
        return 2 * len(self)

    @property
    def frames_with_gt(self) -> int:
        """Number of frames whose ground-truth pose is known."""
        if self.gt_poses is None:
            return 0
        return int(np.isfinite(self.gt_poses).all(axis=(1, 2)).sum())
