"""Pinhole intrinsics with exact crop and resize updates; calibration files.

TS-SLAM §III-A Eq. (2) ``eq:cal_ray`` (x = t + d R K^-1 [u, v, 1]^T, the pixel ray) and §IV-A
(datasets); Co-SLAM's dataset code.  Side layer: imports ``geometry`` (the pixel ray).
Taught in notebooks/00_data_and_cameras.ipynb.

Pixel convention (used everywhere in tsslam_ref): **pixel centres lie at integer coordinates**.
Pixel ``(u, v)`` (column, row) covers ``[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]``, the image covers
``[-0.5, W - 0.5] x [-0.5, H - 0.5]``, and the ray through the centre of pixel ``(u, v)`` has the
camera-frame direction ``((u - cx) / fx, (v - cy) / fy, 1)`` (OpenCV axes, x right, y down, z forward).

Resizing an image from W to W' pixels maps the continuous coordinate ``x`` to
``x' = s (x + 0.5) - 0.5`` with ``s = W' / W`` (image *edges* map onto edges, as PIL and OpenCV's
area/bilinear resize do), hence ``fx' = s fx`` and ``cx' = s (cx + 0.5) - 0.5``.  Cropping ``left``
pixels gives ``cx' = cx - left``.  Co-SLAM floors fx, fy, cx, cy to integers and scales cx by s
alone; we do neither (docs/data.md, "Deviations").

| symbol | variable | unit |
|---|---|---|
| f_x, f_y | ``fx``, ``fy`` | px |
| c_x, c_y | ``cx``, ``cy`` | px (integer = a pixel centre) |
| W, H | ``width``, ``height`` | px |
"""

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from tsslam_ref.geometry import pixel_to_ray

INTRINSICS_JSON = "intrinsics.json"
"""Calibration file of the generic folder layout (also read in a TUM-layout folder)."""
CALIBRATION_TXT = "calibration.txt"
"""Alternative calibration file: one non-comment line ``fx fy cx cy [width height]``."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera of a (possibly cropped and resized) image; pixel centres at integers."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(float(v)) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Intrinsics need finite fx, fy > 0 and finite cx, cy; got {values}")
        if int(self.width) != self.width or int(self.height) != self.height:
            raise ValueError(f"Intrinsics width/height must be integers, got {self.width}x{self.height}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Intrinsics width/height must be positive, got {self.width}x{self.height}")
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def matrix(self) -> np.ndarray:
        """K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], (3, 3) float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, sx: float, sy: Optional[float] = None) -> "Intrinsics":
        """Intrinsics after resizing the image by factors ``sx`` (width) and ``sy`` (height).

        fx' = sx fx,  cx' = sx (cx + 0.5) - 0.5  (and the same with sy for y): image edges map
        onto image edges, pixel centres sit at integers.  The new size is ``round(W sx)`` x
        ``round(H sy)``; pass factors that make these exact (``W' / W``), as
        :meth:`resized` does.

        Args:
            sx: width factor (> 0).
            sy: height factor (> 0); None means ``sx``.

        Raises:
            ValueError: for a factor <= 0 or an image that would have no pixels.
        """
        sy = sx if sy is None else sy
        if not (sx > 0 and sy > 0):
            raise ValueError(f"scale factors must be > 0, got sx={sx}, sy={sy}")
        width, height = int(round(self.width * sx)), int(round(self.height * sy))
        if width < 1 or height < 1:
            raise ValueError(f"scaling {self.width}x{self.height} by ({sx}, {sy}) leaves no pixels")
        return Intrinsics(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=sx * (self.cx + 0.5) - 0.5,
            cy=sy * (self.cy + 0.5) - 0.5,
            width=width,
            height=height,
        )

    def resized(self, width: int, height: int) -> "Intrinsics":
        """Intrinsics after resizing the image to exactly ``width`` x ``height`` pixels (same size: unchanged)."""
        if (width, height) == (self.width, self.height):
            return self
        return self.scaled(width / self.width, height / self.height)

    def cropped(self, left: int, top: int, right: int, bottom: int) -> "Intrinsics":
        """Intrinsics after removing ``left``/``top``/``right``/``bottom`` pixels: cx' = cx - left.

        Raises:
            ValueError: for a negative crop or one that removes the whole image.
        """
        crops = (left, top, right, bottom)
        if any(int(c) != c or c < 0 for c in crops):
            raise ValueError(f"crop amounts must be non-negative integers, got {crops}")
        width = self.width - left - right
        height = self.height - top - bottom
        if width < 1 or height < 1:
            raise ValueError(f"cropping {crops} from a {self.width}x{self.height} image leaves no pixels")
        return Intrinsics(self.fx, self.fy, self.cx - left, self.cy - top, width, height)

    def to_dict(self) -> dict:
        """Plain dict (the keys of ``intrinsics.json``)."""
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height}


# Published pinhole values, full 640x480 images (TUM RGB-D web page "File Formats / intrinsic
# camera calibration"; the same numbers as Co-SLAM's configs/Tum/*.yaml).  fr1 and fr2 are
# distorted (see TUM_DISTORTION); we do not undistort (docs/data.md).
TUM_INTRINSICS = {
    "freiburg1": Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
    "freiburg2": Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480),
    "freiburg3": Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}
TUM_DISTORTION = {
    "freiburg1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "freiburg2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "freiburg3": (0.0, 0.0, 0.0, 0.0, 0.0),
}
REPLICA_INTRINSICS = Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
NEURAL_RGBD_FOCAL = 554.2562584220408  # 320 / tan(30 deg): 640 px renders with a 60 deg field of view


def _checked_calibration(values: dict, where) -> dict:
    """``values`` if its focal lengths, image size and depth scale are positive; else ValueError
    naming ``where`` (the file, or file:line).  ``width`` and ``height`` come together."""
    if not all(math.isfinite(value) for value in values.values()):
        raise ValueError(f"{where}: every number must be finite, got {values}")
    if ("width" in values) != ("height" in values):
        raise ValueError(f"{where}: 'width' and 'height' come together (the image size in px); give both or neither")
    for key in ("fx", "fy", "width", "height", "depth_scale"):
        if key in values and not values[key] > 0:
            raise ValueError(f"{where}: '{key}' must be > 0, got {values[key]!r}")
    for key in ("width", "height"):
        if key in values:
            if values[key] != int(values[key]):
                raise ValueError(f"{where}: '{key}' must be a whole number of pixels, got {values[key]!r}")
            values[key] = int(values[key])
    return values


def _read_intrinsics_json(json_path: Path) -> dict:
    """The checked calibration of an ``intrinsics.json`` (see :func:`read_calibration`)."""
    try:
        values = json.loads(json_path.read_text(encoding="utf-8-sig"))
    except UnicodeDecodeError:
        raise ValueError(f"{json_path}: not a text file; expected a JSON object with fx, fy, cx, cy") from None
    except json.JSONDecodeError as error:
        raise ValueError(f"{json_path}: not valid JSON ({error})") from None
    if not isinstance(values, dict):
        raise ValueError(f"{json_path}: expected a JSON object with fx, fy, cx, cy")
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in values]
    if missing:
        raise ValueError(f"{json_path}: missing keys {missing} (expected fx, fy, cx, cy[, width, height, depth_scale])")
    unknown = sorted(set(values) - {"fx", "fy", "cx", "cy", "width", "height", "depth_scale", "note"})
    if unknown:  # a misspelt depth_scale would fall back to the layout's silently
        raise ValueError(f"{json_path}: unknown key(s) {', '.join(map(repr, unknown))}; expected fx, fy, cx, cy and "
                         f"optionally width, height, depth_scale, with free text under 'note' (lens distortion "
                         f"is not modelled: undistort the images first)")
    out = {}
    for key in ("fx", "fy", "cx", "cy", "width", "height", "depth_scale"):
        if key in values:
            if not isinstance(values[key], (int, float)) or isinstance(values[key], bool) or not math.isfinite(values[key]):
                raise ValueError(f"{json_path}: '{key}' must be a finite number, got {values[key]!r}")
            out[key] = values[key]
    return _checked_calibration(out, json_path)


def read_calibration(folder: Path) -> Optional[dict]:
    """Read ``intrinsics.json`` (preferred) or ``calibration.txt`` from ``folder``.

    ``intrinsics.json``: an object with fx, fy, cx, cy (px) and optionally width, height (px) and
    depth_scale (PNG value per metre).  ``calibration.txt``: '#' comments, then one line
    ``fx fy cx cy`` or ``fx fy cx cy width height``.

    Returns:
        dict with keys fx, fy, cx, cy and, when given, width, height, depth_scale; None when
        neither file exists.

    Raises:
        ValueError: naming the file (and line) for malformed content.
    """
    json_path = Path(folder) / INTRINSICS_JSON
    if json_path.is_file():
        return _read_intrinsics_json(json_path)
    text_path = Path(folder) / CALIBRATION_TXT
    if text_path.is_file():
        try:
            text = text_path.read_text(encoding="utf-8-sig")
        except UnicodeDecodeError:
            raise ValueError(f"{text_path}: not a text file; expected a line 'fx fy cx cy [width height]'") from None
        for number, line in enumerate(text.splitlines(), start=1):
            stripped = line.strip()
            if not stripped or stripped.startswith("#"):
                continue
            parts = stripped.split()
            try:
                numbers = [float(p) for p in parts]
            except ValueError:
                numbers = None
            if numbers is None or len(numbers) not in (4, 6):
                raise ValueError(
                    f"{text_path}:{number}: expected 'fx fy cx cy' or 'fx fy cx cy width height', got '{stripped}'"
                )
            out = dict(zip(("fx", "fy", "cx", "cy", "width", "height"), numbers))
            return _checked_calibration(out, f"{text_path}:{number}")
        raise ValueError(f"{text_path}: no calibration line found (expected 'fx fy cx cy [width height]')")
    return None


def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame directions ((u - cx)/fx, (v - cy)/fy, 1) through every pixel centre.

    Returns:
        (H, W, 3) float64, OpenCV camera axes; a point at depth z on pixel (u, v) is z * ray[v, u].
    """
    v, u = np.mgrid[: intrinsics.height, : intrinsics.width].astype(np.float64)  # (H, W) each
    return pixel_to_ray(u, v, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)


def back_project(depth: np.ndarray, intrinsics: Intrinsics, pose_c2w: Optional[np.ndarray] = None) -> np.ndarray:
    """Points seen by every pixel (Eq. (2) ``eq:cal_ray`` at the measured depth).

    x_c = z K^-1 (u, v, 1)^T,  x_w = R_wc x_c + t_wc when a pose is given.

    Args:
        depth: (H, W) metres (0 = invalid; such pixels give the camera centre).
        intrinsics: camera of ``depth``.  pose_c2w: (4, 4) camera-to-world or None (camera frame).

    Returns:
        (H, W, 3) float64 points in the world (or camera) frame, metres.
    """
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"depth has shape {depth.shape}, intrinsics are for {intrinsics.height}x{intrinsics.width}")
    points = pixel_rays(intrinsics) * np.asarray(depth, dtype=np.float64)[..., None]  # (H, W, 3)
    if pose_c2w is None:
        return points
    pose = np.asarray(pose_c2w, dtype=np.float64)
    return points @ pose[:3, :3].T + pose[:3, 3]  # (H, W, 3)
