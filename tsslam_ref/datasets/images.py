"""Reading colour and 16-bit depth images; crop and resize with the pixel-centre convention.

Co-SLAM dataset code (``datasets/dataset.py``: colour /255, depth PNG / depth scale,
colour resized to the depth size).  Side layer.  Taught in notebooks/00_data_and_cameras.ipynb.

Resizing uses PIL, whose sampling grid maps image edges onto edges (pixel centres at integers,
see ``intrinsics``): colour with bilinear filtering (antialiased when shrinking), depth with
nearest neighbour so that no depth value is invented between a foreground and a background
surface.  Depth 0 means "no measurement" everywhere.
"""

from pathlib import Path
from typing import Optional, Tuple

import imageio.v3 as iio
import numpy as np
from PIL import Image


def read_rgb(path) -> np.ndarray:
    """Colour image -> (H, W, 3) float32 in [0, 1] (8- or 16-bit; grey is repeated, alpha dropped).

    Raises:
        FileNotFoundError: naming the file.  ValueError: naming the file for an unreadable image.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: colour image not found")
    try:
        image = iio.imread(path)
    except Exception as error:  # imageio raises many types for corrupt files
        raise ValueError(f"{path}: cannot read colour image ({error})") from error
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)  # (H, W, 3)
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        raise ValueError(f"{path}: expected an (H, W, 3) colour image, got shape {image.shape}")
    image = image[..., :3]
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    if image.dtype == np.uint16:
        return image.astype(np.float32) / 65535.0
    raise ValueError(f"{path}: unsupported colour dtype {image.dtype} (expected uint8 or uint16)")


def read_depth(path, depth_scale: float) -> np.ndarray:
    """16-bit depth PNG -> (H, W) float32 metres (value / depth_scale), 0 = invalid.

    Raises:
        FileNotFoundError: naming the file.
        ValueError: naming the file when the image is not single-channel 16-bit.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: depth image not found")
    try:
        image = iio.imread(path)
    except Exception as error:
        raise ValueError(f"{path}: cannot read depth image ({error})") from error
    if image.dtype != np.uint16 or image.ndim != 2:
        raise ValueError(
            f"{path}: depth must be a single-channel 16-bit PNG, got dtype {image.dtype} and shape {image.shape}"
        )
    return image.astype(np.float32) / np.float32(depth_scale)


def image_size(path) -> Tuple[int, int]:
    """(width, height) of an image file, reading only its header."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image not found")
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, ValueError) as error:  # PIL's UnidentifiedImageError is an OSError
        raise ValueError(f"{path}: cannot read it as an image ({error}); expected a PNG (depth: 16-bit) or JPEG "
                         f"file") from None


DEPTH_MODES = ("I;16", "I;16L", "I;16B")
"""PIL modes of a single-channel 16-bit image (what a depth PNG must be)."""
COLOUR_MODES = ("RGB", "RGBA", "L", "I;16", "I;16L", "I;16B")
"""PIL modes :func:`read_rgb` turns into colour (8- or 16-bit RGB / RGBA / grey)."""


def check_image(path, role: str, size: Optional[Tuple[int, int]] = None) -> Tuple[int, int]:
    """Check an image file without decoding its pixels; returns its (width, height).

    Reads the header (format, mode, size) and, for PNG, walks every chunk and its checksum
    (PIL's ``verify``), which finds truncated and damaged files.  ``role`` is "depth" (a
    single-channel 16-bit image is required) or "colour" (8- or 16-bit RGB, RGBA or grey).
    ``size`` (width, height), when given, must match.

    Raises:
        FileNotFoundError: naming the file.  ValueError: naming the file and what was expected.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {role} image not found")
    expected = "a single-channel 16-bit PNG" if role == "depth" else "an 8- or 16-bit RGB, RGBA or grey image"
    try:
        with Image.open(path) as image:
            mode, found_size, kind = image.mode, image.size, image.format
            image.verify()
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
        reason = str(error) or type(error).__name__
        raise ValueError(f"{path}: not a readable {role} image ({reason}); expected {expected}") from None
    allowed = DEPTH_MODES if role == "depth" else COLOUR_MODES
    if mode not in allowed or (role == "depth" and kind != "PNG"):
        raise ValueError(f"{path}: {role} image is {kind} mode {mode}; expected {expected}")
    if size is not None and tuple(found_size) != tuple(size):
        raise ValueError(f"{path}: {role} image is {found_size[0]}x{found_size[1]}; expected {size[0]}x{size[1]} "
                         f"like the sequence's calibration")
    return found_size


COLOUR_ASPECT_TOLERANCE = 0.01
"""Largest relative difference between the colour's and the depth's aspect ratio (width / height).
Colour is resized to the depth size and shares the depth's intrinsics; ScanNet's 1296x968 colour for
640x480 depth differs by 0.4 %, a 16:9 colour for 4:3 depth by 33 %."""


def check_colour_aspect(path, colour_size: Tuple[int, int], depth_size: Tuple[int, int]) -> None:
    """ValueError naming the colour file ``path`` when its (width, height) ``colour_size`` has
    another aspect ratio than the depth's ``depth_size`` by more than :data:`COLOUR_ASPECT_TOLERANCE`
    (resizing it to the depth size would stretch it, and its pixels would miss the depth's)."""
    (colour_w, colour_h), (depth_w, depth_h) = colour_size, depth_size
    difference = (colour_w / colour_h) / (depth_w / depth_h) - 1.0
    if abs(difference) > COLOUR_ASPECT_TOLERANCE:
        raise ValueError(
            f"{path}: colour image is {colour_w}x{colour_h} (aspect {colour_w / colour_h:.4f}) but the depth images "
            f"are {depth_w}x{depth_h} (aspect {depth_w / depth_h:.4f}), {100 * abs(difference):.1f} % apart; colour "
            f"is resized to the depth size and uses the depth's intrinsics, so expected the depth's aspect ratio "
            f"within {100 * COLOUR_ASPECT_TOLERANCE:g} % (register or crop the colour to the depth's view first)")


def resize_rgb(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float32 -> (height, width, 3) float32, bilinear (antialiased), edges onto edges."""
    if rgb.shape[1] == width and rgb.shape[0] == height:
        return rgb
    channels = [
        np.asarray(Image.fromarray(rgb[..., c]).resize((width, height), Image.Resampling.BILINEAR))
        for c in range(3)
    ]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)  # (height, width, 3)


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) float32 -> (height, width) float32 by nearest neighbour (no mixed depths)."""
    if depth.shape[1] == width and depth.shape[0] == height:
        return depth
    image = Image.fromarray(depth.astype(np.float32))
    return np.asarray(image.resize((width, height), Image.Resampling.NEAREST)).astype(np.float32)


def crop(image: np.ndarray, edge: int) -> np.ndarray:
    """Remove ``edge`` pixels from every side of an (H, W, ...) image."""
    if edge == 0:
        return image
    return image[edge:-edge, edge:-edge]


def output_size(width: int, height: int, crop_edge: int, resize_width: Optional[int]) -> Tuple[int, int]:
    """Size after cropping ``crop_edge`` per side, then shrinking to ``resize_width`` (aspect kept;
    images no wider than that keep their size).

    Raises:
        ValueError: naming the values when the crop or the width leave no pixels.
    """
    if crop_edge < 0 or 2 * crop_edge >= min(width, height):
        raise ValueError(f"crop_edge={crop_edge} is invalid for a {width}x{height} image")
    cropped_w, cropped_h = width - 2 * crop_edge, height - 2 * crop_edge
    if resize_width is None:
        return cropped_w, cropped_h
    if resize_width < 1:
        raise ValueError(f"resize_width must be >= 1, got {resize_width}")
    if resize_width >= cropped_w:  # never enlarge: no information gained, only cost (and memory without bound)
        return cropped_w, cropped_h
    return int(resize_width), max(1, int(round(cropped_h * resize_width / cropped_w)))
