"""Tests for tsslam_ref.data: intrinsics updates, the five layouts, bad input, real TUM data, the CLI.

Oracles: blob centroids through PIL resizing (intrinsics), brute-force association loops and
scipy's Slerp over the raw groundtruth.txt lines (real data), hand-computed matrices.
"""

import json
import re
import os
import tracemalloc

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation, Slerp

from tsslam_ref import config, data
from tsslam_ref.config import DataConfig
from tsslam_ref.datasets.images import output_size, resize_rgb
from tsslam_ref.datasets.tum_format import associate_nearest, ground_truth_at

FR3 = dict(fx=535.4, fy=539.2, cx=320.1, cy=247.6)


# ------------------------------------------------------------------------------------------------
# helpers writing tiny datasets


def _rgb(width, height, value):
    image = np.zeros((height, width, 3), np.uint8)
    image[..., 0] = value
    image[..., 1] = np.arange(width, dtype=np.uint8)[None, :]
    return image


def _depth(width, height, metres, scale):
    return np.full((height, width), round(metres * scale), np.uint16)


def _random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.5, size=(n, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    return poses


def _tum_line(stamp, pose):
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()  # scipy: x, y, z, w
    return f"{stamp:.4f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q))


def make_tum(folder, rgb_stamps, depth_stamps, gt_stamps, gt_poses, size=(8, 6), calibration=True):
    """TUM layout with 8x6 images; depth of frame i is 1 + 0.1 i metres."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    width, height = size
    rgb_lines = ["# color images", "# timestamp filename"]
    for i, stamp in enumerate(rgb_stamps):
        iio.imwrite(folder / f"rgb/{stamp:.6f}.png", _rgb(width, height, 10 * i))
        rgb_lines.append(f"{stamp:.6f} rgb/{stamp:.6f}.png")
    depth_lines = ["# depth maps"]
    for i, stamp in enumerate(depth_stamps):
        iio.imwrite(folder / f"depth/{stamp:.6f}.png", _depth(width, height, 1.0 + 0.1 * i, 5000))
        depth_lines.append(f"{stamp:.6f} depth/{stamp:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt = ["# timestamp tx ty tz qx qy qz qw"] + [_tum_line(s, p) for s, p in zip(gt_stamps, gt_poses)]
    (folder / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if calibration:
        (folder / "intrinsics.json").write_text(json.dumps({"fx": 7.0, "fy": 7.5, "cx": 3.5, "cy": 2.5}))
    return folder


@pytest.fixture
def tum_folder(tmp_path):
    t0 = 1341841873.0
    rgb = t0 + np.array([0.00, 0.033, 0.066, 0.100, 0.133, 0.166])
    depth = rgb + 0.001
    depth[3] += 0.025  # frame 3 has no depth within 0.02 s -> always dropped
    gt_stamps = t0 + np.arange(0.02, 0.20, 0.01)  # frame 0 (t0) is 0.02 s before the first pose: kept
    gt = _random_poses(len(gt_stamps))
    return make_tum(tmp_path / "tum", rgb, depth, gt_stamps, gt), rgb, gt_stamps, gt


# ------------------------------------------------------------------------------------------------
# Intrinsics


def _blob(width, height, u, v, sigma):
    uu, vv = np.meshgrid(np.arange(width), np.arange(height))
    value = np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * sigma**2)).astype(np.float32)
    return np.repeat(value[..., None], 3, -1)


def _centroid(image):
    weight = image[..., 0].astype(np.float64)
    vv, uu = np.mgrid[: image.shape[0], : image.shape[1]]
    return (weight * uu).sum() / weight.sum(), (weight * vv).sum() / weight.sum()


@pytest.mark.parametrize("new_size", [(160, 120), (200, 90), (320, 240)])
def test_scaled_intrinsics_follow_a_resized_image(new_size):
    """A 3-D point's projection with the scaled K lands on the blob's centroid in the PIL-resized image."""
    k = data.Intrinsics(**FR3, width=640, height=480)
    point_cam = np.array([0.31, -0.17, 1.9])
    u, v, _ = k.matrix() @ point_cam / point_cam[2]
    image = _blob(640, 480, u, v, sigma=12.0)
    resized = resize_rgb(image, *new_size)
    small = k.resized(*new_size)
    u2, v2, _ = small.matrix() @ point_cam / point_cam[2]
    cu, cv = _centroid(resized)
    assert (small.width, small.height) == new_size
    assert abs(cu - u2) < 0.02 and abs(cv - v2) < 0.02


def test_cropped_intrinsics_follow_a_cropped_image():
    k = data.Intrinsics(**FR3, width=640, height=480)
    point_cam = np.array([-0.2, 0.1, 2.0])
    u, v, _ = k.matrix() @ point_cam / point_cam[2]
    image = _blob(640, 480, u, v, sigma=5.0)[8:-10, 12:-4]  # top 8, bottom 10, left 12, right 4
    crop = k.cropped(12, 8, 4, 10)
    u2, v2, _ = crop.matrix() @ point_cam / point_cam[2]
    cu, cv = _centroid(image)
    assert (crop.width, crop.height) == (640 - 16, 480 - 18)
    assert abs(cu - u2) < 1e-3 and abs(cv - v2) < 1e-3


def test_intrinsics_matrix_and_bad_values():
    k = data.Intrinsics(10.0, 11.0, 4.5, 3.5, 10, 8)
    np.testing.assert_array_equal(k.matrix(), [[10, 0, 4.5], [0, 11, 3.5], [0, 0, 1]])
    assert k.matrix().dtype == np.float64
    assert k.scaled(2.0) == data.Intrinsics(20.0, 22.0, 9.5, 7.5, 20, 16)  # pixel (4.5) centre -> 9.5
    with pytest.raises(ValueError, match="fx"):
        data.Intrinsics(-1.0, 1.0, 0.0, 0.0, 4, 4)
    with pytest.raises(ValueError, match="leaves no pixels"):
        k.cropped(5, 0, 5, 0)
    with pytest.raises(ValueError, match="> 0"):
        k.scaled(0.0)


# ------------------------------------------------------------------------------------------------
# TUM layout (tiny fixture)


def test_tum_association_and_require_gt(tum_folder):
    folder, rgb, gt_stamps, gt = tum_folder
    sequence = data.load_sequence(folder)
    # frame 3 lacks depth; frame 0 is exactly 0.02 s from the first pose (kept, nearest pose);
    # frame 5 (t0 + 0.166) lies inside the GT window.
    assert data.detect_dataset(folder) == "tum"
    np.testing.assert_array_equal(sequence.timestamps, rgb[[0, 1, 2, 4, 5]])
    assert sequence.timestamps.dtype == np.float64
    assert sequence.intrinsics == data.Intrinsics(7.0, 7.5, 3.5, 2.5, 8, 6)
    frame = sequence[3]
    assert frame.index == 3 and frame.timestamp == rgb[4]
    assert frame.rgb.shape == (6, 8, 3) and frame.rgb.dtype == np.float32
    np.testing.assert_allclose(frame.rgb[0, :, 1], np.arange(8) / 255.0, atol=1e-7)
    np.testing.assert_allclose(frame.depth, 1.4, atol=1e-6)  # depth file number 4
    # GT: slerp/linear between bracketing 100 Hz lines (scipy oracle)
    slerp = Slerp(gt_stamps, Rotation.from_matrix(gt[:, :3, :3]))
    np.testing.assert_allclose(frame.pose_c2w[:3, :3], slerp([rgb[4]]).as_matrix()[0], atol=1e-6)
    expected_t = np.array([np.interp(rgb[4], gt_stamps, gt[:, c, 3]) for c in range(3)])
    np.testing.assert_allclose(frame.pose_c2w[:3, 3], expected_t, atol=1e-6)
    np.testing.assert_allclose(sequence[0].pose_c2w, gt[0], atol=1e-6)  # before the first pose: nearest


def test_tum_require_gt_false_keeps_frames_without_pose(tmp_path):
    t0 = 100.0
    rgb = t0 + np.arange(5) / 30.0
    gt_stamps = t0 + 0.1 + np.arange(5) * 0.01
    folder = make_tum(tmp_path / "t", rgb, rgb, gt_stamps, _random_poses(5))
    strict = data.load_sequence(folder)
    loose = data.load_sequence(folder, require_gt=False)
    assert len(loose) == 5 and len(strict) == 2  # only frames at 0.1 and 0.133 have a pose
    assert np.isnan(loose.gt_poses[0]).all() and loose[0].pose_c2w is None
    assert loose.frames_with_gt == 2


def test_frame_range_and_stride(tum_folder):
    folder, rgb, _, _ = tum_folder
    sequence = data.load_sequence(folder, frame_start=1, frame_stop=5, frame_step=2)
    np.testing.assert_array_equal(sequence.timestamps, rgb[[1, 4]])
    assert [f.index for f in sequence] == [0, 1]
    with pytest.raises(ValueError, match="selects no frame"):
        data.load_sequence(folder, frame_start=10)


def test_tum_folder_name_selects_camera(tmp_path):
    stamps = 10.0 + np.arange(2) / 30
    for name, expected in [("rgbd_dataset_freiburg1_desk", (517.3, 516.5, 318.6, 255.3)),
                           ("fr2_xyz", (520.9, 521.0, 325.1, 249.7)), ("my_capture", (535.4, 539.2, 320.1, 247.6))]:
        folder = make_tum(tmp_path / name, stamps, stamps, stamps, _random_poses(2), size=(640, 480), calibration=False)
        k = data.load_sequence(folder).intrinsics
        assert (k.fx, k.fy, k.cx, k.cy) == expected


def test_the_tum_preset_reads_coslams_496_by_368_image(tmp_path):
    """Co-SLAM resizes TUM's 640x480 to 512x384 and crops 8 px per side: 496x368, fx 535.4 x 0.8
    (its spec; it then floors, which we do not).  The preset cropped 8 native px and kept 624x464."""
    stamps = 10.0 + np.arange(2) / 30
    folder = make_tum(tmp_path / "fr3", stamps, stamps, stamps, _random_poses(2), size=(640, 480), calibration=False)
    settings = config.tum().data
    k = data.load_sequence(folder, crop_edge=settings.crop_edge, resize_width=settings.resize_width).intrinsics
    assert (k.width, k.height) == (496, 368)
    np.testing.assert_allclose([k.fx, k.fy], [535.4 * 0.8, 539.2 * 0.8])


def test_crop_and_resize_update_intrinsics(tmp_path):
    stamps = 10.0 + np.arange(2) / 30
    folder = make_tum(tmp_path / "fr3", stamps, stamps, stamps, _random_poses(2), size=(640, 480), calibration=False)
    sequence = data.load_sequence(folder, crop_edge=8, resize_width=156)
    k = sequence.intrinsics
    s = 156 / 624  # width 640 - 16 = 624 -> 156; height 464 -> 116
    assert (k.width, k.height) == (156, 116)
    np.testing.assert_allclose([k.fx, k.cx], [535.4 * s, s * (320.1 - 8 + 0.5) - 0.5])
    np.testing.assert_allclose([k.fy, k.cy], [539.2 * 116 / 464, 116 / 464 * (247.6 - 8 + 0.5) - 0.5])
    frame = sequence[1]
    assert frame.rgb.shape == (116, 156, 3) and frame.depth.shape == (116, 156)
    np.testing.assert_allclose(frame.depth, 1.1, atol=1e-6)  # nearest resize keeps values


def test_depth_resize_never_mixes_surfaces(tmp_path):
    """Resized depth holds only values of the original (an edge 1 m | 3 m and holes stay exact), each
    at its place, and the resized colour stays on the depth's pixels.

    64x48 -> 20x15 is a scale of s = 3.2 on both axes.  Edges onto edges (module docstring): output
    pixel j's centre falls at (j + 0.5) s in input edge coordinates, and nearest neighbour takes the
    input pixel containing it, floor((j + 0.5) s): columns 0..19 -> 1, 4, 8, 11, 14, 17, 20, 24, 27,
    30, ...  The edge between input columns 28 (1 m) and 29 (3 m) lands between output columns 8
    (input 27) and 9 (input 30).  The hole at input rows 10..19, columns 5..8 is hit by output rows
    3, 4, 5 (inputs 11, 14, 17) and output column 2 (input 8 or 7: (2 + 0.5) s = 8 is on a pixel
    border, both holes); rows 2 and 6 read inputs 8 and 20, columns 1 and 3 read 4 and 11: no hole.
    The colour image is red left of the edge and blue right of it; bilinear with antialiasing
    averages over +-s input pixels around (j + 0.5) s, so output columns 0..7 (reaching up to
    input 26.8) are pure red, 10..19 (from 30.4) pure blue, and 8, 9 a mix.
    """
    stamps = 10.0 + np.arange(1) / 30
    folder = make_tum(tmp_path / "t", stamps, stamps, stamps, _random_poses(1), size=(64, 48))
    depth = np.full((48, 64), 5000, np.uint16)
    depth[:, 29:] = 15000
    depth[10:20, 5:9] = 0
    iio.imwrite(folder / f"depth/{stamps[0]:.6f}.png", depth)
    colour = np.zeros((48, 64, 3), np.uint8)
    colour[:, :29, 0] = 255
    colour[:, 29:, 2] = 255
    iio.imwrite(folder / f"rgb/{stamps[0]:.6f}.png", colour)
    frame = data.load_sequence(folder, resize_width=20)[0]
    resized = frame.depth
    assert resized.shape == (15, 20) and frame.rgb.shape == (15, 20, 3)
    assert set(np.unique(resized).round(6)) <= {0.0, 1.0, 3.0} and (resized == 0).any()
    expected = np.full((15, 20), 1.0, np.float32)
    expected[:, 9:] = 3.0  # 1 m on the left of the edge, as in the input
    expected[3:6, 2] = 0.0  # the hole, at its scaled rows and column
    np.testing.assert_allclose(resized, expected, atol=1e-6)
    red, blue = frame.rgb[..., 0], frame.rgb[..., 2]
    np.testing.assert_allclose(red[:, :8], 1.0, atol=1e-6)  # pure red where the depth is 1 m
    np.testing.assert_allclose(blue[:, 10:], 1.0, atol=1e-6)  # pure blue where it is 3 m
    assert np.all(blue[:, :8] < 1e-6) and np.all(red[:, 10:] < 1e-6)
    assert np.all((0.05 < red[:, 8:10]) & (red[:, 8:10] < 0.95))  # the mixed columns straddle the depth edge


def test_depth_is_not_truncated(tmp_path):
    stamps = 10.0 + np.arange(2) / 30
    folder = make_tum(tmp_path / "t", stamps, stamps, stamps, _random_poses(2))
    sequence = data.load_sequence(folder, depth_trunc=0.5)
    assert sequence.depth_trunc == 0.5 and np.all(sequence[0].depth > 0.9)


def test_loading_is_lazy(tmp_path):
    """3000 frames (hard links to one image pair) load without reading pixels; frames are read on access."""
    folder = tmp_path / "big"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    iio.imwrite(folder / "rgb/base.png", _rgb(64, 48, 1))
    iio.imwrite(folder / "depth/base.png", _depth(64, 48, 2.0, 5000))
    lines_rgb, lines_depth = [], []
    for i in range(3000):
        stamp = 1000.0 + i / 30
        os.link(folder / "rgb/base.png", folder / f"rgb/{i}.png")
        os.link(folder / "depth/base.png", folder / f"depth/{i}.png")
        lines_rgb.append(f"{stamp:.6f} rgb/{i}.png")
        lines_depth.append(f"{stamp:.6f} depth/{i}.png")
    (folder / "rgb.txt").write_text("\n".join(lines_rgb))
    (folder / "depth.txt").write_text("\n".join(lines_depth))
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 50, "fy": 50, "cx": 31.5, "cy": 23.5}))
    tracemalloc.start()
    sequence = data.load_sequence(folder)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(sequence) == 3000 and sequence.gt_poses is None
    # 3000 decoded frames would need 3000 * 64*48*16 B = 147 MB; what remains is the lists and the
    # resolved path of every file (checked to stay inside the folder), a few kB per frame
    assert peak < 25e6
    iio.imwrite(folder / "depth/2999.png", _depth(64, 48, 3.0, 5000))  # replaces the link
    np.testing.assert_allclose(sequence[2999].depth, 3.0, atol=1e-6)


# ------------------------------------------------------------------------------------------------
# Bad input


def test_missing_folder():
    with pytest.raises(FileNotFoundError, match="no_such_folder"):
        data.load_sequence("/nonexistent/no_such_folder")


def test_unknown_layout_lists_layouts(tmp_path):
    with pytest.raises(ValueError) as error:
        data.detect_dataset(tmp_path)
    for kind in ("tum", "scannet", "neural_rgbd", "replica", "folder"):
        assert kind in str(error.value)


def test_listed_file_absent_names_list_and_line(tum_folder):
    folder = tum_folder[0]
    name = (folder / "rgb.txt").read_text().splitlines()[4].split()[1]  # line 5 = third entry
    (folder / name).unlink()
    with pytest.raises(FileNotFoundError, match=r"rgb\.txt:5: .*not found"):
        data.load_sequence(folder)


@pytest.mark.parametrize("entry, words", [
    ("{stamp} {name} depth/other.png", "got 3 field(s)"),  # another column would be ignored
    ("{stamp} rgb/my frame.png", "a file name cannot hold spaces here"),  # once 'rgb/my' not found
    ("{stamp}", "got 1 field(s)"),
    ("{comma_stamp} {name}", "looks written with decimal commas"),  # read as 3 fields otherwise
])
def test_a_list_line_without_exactly_two_fields_is_refused_naming_the_line(tum_folder, entry, words):
    folder = tum_folder[0]
    lines = (folder / "rgb.txt").read_text().splitlines()
    stamp, name = lines[4].split()  # line 5
    lines[4] = entry.format(stamp=stamp, name=name, comma_stamp=stamp.replace(".", ","))
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"rgb\.txt:5: expected 'timestamp filename'") as error:
        data.load_sequence(folder)
    assert words in str(error.value), str(error.value)


def test_malformed_line_names_file_and_line(tum_folder):
    folder = tum_folder[0]
    lines = (folder / "depth.txt").read_text().splitlines()
    lines[2] = "abc depth/x.png"
    (folder / "depth.txt").write_text("\n".join(lines))
    with pytest.raises(ValueError, match=r"depth\.txt:3: timestamp 'abc'"):
        data.load_sequence(folder)
    gt = (folder / "groundtruth.txt").read_text().splitlines()
    gt[3] = "1.0 2.0 3.0"
    (folder / "groundtruth.txt").write_text("\n".join(gt))
    with pytest.raises(ValueError, match=r"groundtruth\.txt:4: expected 8 numbers") as error:
        data.read_tum_trajectory(folder / "groundtruth.txt")
    assert "decimal commas" not in str(error.value)


def test_a_trajectory_written_with_decimal_commas_is_named_as_such(tum_folder):
    """A locale that writes '1,5' gives 16 comma-split fields; the error says why, not only the count."""
    folder = tum_folder[0]
    gt = (folder / "groundtruth.txt").read_text().splitlines()
    gt[3] = gt[3].replace(".", ",")
    (folder / "groundtruth.txt").write_text("\n".join(gt))
    with pytest.raises(ValueError, match=r"groundtruth\.txt:4: expected 8 numbers .*got 16 fields; the line looks "
                                         r"written with decimal commas"):
        data.read_tum_trajectory(folder / "groundtruth.txt")


def test_timestamps_out_of_order(tum_folder):
    folder = tum_folder[0]
    lines = (folder / "rgb.txt").read_text().splitlines()
    lines[3], lines[4] = lines[4], lines[3]
    (folder / "rgb.txt").write_text("\n".join(lines))
    with pytest.raises(ValueError, match=r"rgb\.txt:5: .*out of order"):
        data.load_sequence(folder)


def test_depth_png_not_16_bit(tum_folder):
    folder = tum_folder[0]
    name = (folder / "depth.txt").read_text().splitlines()[1].split()[1]
    iio.imwrite(folder / name, np.zeros((6, 8), np.uint8))
    sequence = data.load_sequence(folder)
    with pytest.raises(ValueError, match=rf"{os.path.basename(name)}: depth must be a single-channel 16-bit PNG"):
        sequence[0]


def test_a_frame_without_any_depth_is_refused_naming_its_file(tum_folder):
    folder = tum_folder[0]
    name = (folder / "depth.txt").read_text().splitlines()[1].split()[1]
    shape = iio.imread(folder / name).shape
    iio.imwrite(folder / name, np.zeros(shape, np.uint16))  # a valid 16-bit PNG holding only "no depth"
    sequence = data.load_sequence(folder)
    with pytest.raises(ValueError, match=rf"{os.path.basename(name)}: depth is 0 \(no measurement\) at every pixel"):
        sequence[0]
    sequence[1]  # the other frames still read


def test_no_depth_within_tolerance_is_an_error_not_empty(tmp_path):
    stamps = 10.0 + np.arange(3) / 30
    folder = make_tum(tmp_path / "t", stamps, stamps + 1.0, stamps, _random_poses(3))
    with pytest.raises(ValueError, match="within 0.02 s"):
        data.load_sequence(folder)


# ------------------------------------------------------------------------------------------------
# Other layouts


def _scannet_scene(folder, numbers, poses, depth_metres, colour_size=(8, 6), depth_suffix=".png"):
    """A ScanNet export of 8x6 depth (mm): color/<n>.jpg (grey 40 x its index), depth/<n><suffix>,
    pose/<n>.txt for each frame number n; intrinsic/ made, left empty."""
    for sub in ("color", "depth", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True)
    for i, (n, pose, metres) in enumerate(zip(numbers, poses, depth_metres)):
        colour = np.full((colour_size[1], colour_size[0], 3), 40 * i, np.uint8)
        Image.fromarray(colour).save(folder / f"color/{n}.jpg", quality=100)
        iio.imwrite(folder / f"depth/{n}{depth_suffix}", _depth(8, 6, metres, 1000))
        np.savetxt(folder / f"pose/{n}.txt", pose)
    return folder


def test_scannet_layout(tmp_path):
    poses = _random_poses(3)
    stored = poses.copy()
    stored[1, 0, 0] = -np.inf  # ScanNet's invalid poses
    folder = _scannet_scene(tmp_path / "scene0000_00", [0, 10, 20], stored, [1.5, 2.5, 3.5], colour_size=(16, 12))
    np.savetxt(folder / "intrinsic/intrinsic_depth.txt", [[6.1, 0, 3.6, 0], [0, 6.2, 2.7, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert data.detect_dataset(folder) == "scannet"
    loose = data.load_sequence(folder, require_gt=False)
    assert np.isnan(loose.gt_poses[1]).all()
    sequence = data.load_sequence(folder)
    np.testing.assert_allclose(sequence.timestamps, [0.0, 20 / 30])  # frame numbers / 30 FPS
    assert sequence.intrinsics == data.Intrinsics(6.1, 6.2, 3.6, 2.7, 8, 6)
    frame = sequence[1]
    assert frame.rgb.shape == (6, 8, 3)  # colour resized to the depth size
    np.testing.assert_allclose(frame.rgb, 80 / 255, atol=2 / 255)
    np.testing.assert_allclose(frame.depth, 3.5, atol=1e-6)
    np.testing.assert_allclose(frame.pose_c2w, poses[2], atol=1e-12)
    np.savetxt(folder / "intrinsic/intrinsic_depth.txt", [[0, 0, 3.6, 0], [0, 6.2, 2.7, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    with pytest.raises(ValueError, match=r"intrinsic_depth\.txt: .*fx, fy > 0"):  # once without the file's name
        data.load_sequence(folder)
    (folder / "intrinsic/intrinsic_depth.txt").unlink()
    with pytest.raises(FileNotFoundError, match="intrinsic_depth.txt"):
        data.load_sequence(folder)
    np.savetxt(folder / "pose/20.txt", np.concatenate([poses[2], poses[0]]))  # two matrices in one pose file
    with pytest.raises(ValueError, match=r"20\.txt: 2 4x4 matrices; expected one"):
        data.load_sequence(folder)


def test_neural_rgbd_release_images_take_its_focal_length(tmp_path):
    folder = tmp_path / "kitchen"
    (folder / "images").mkdir(parents=True)
    (folder / "depth_filtered").mkdir()
    iio.imwrite(folder / "images/img0.png", _rgb(640, 480, 0))
    iio.imwrite(folder / "depth_filtered/depth0.png", _depth(640, 480, 1.0, 1000))
    np.savetxt(folder / "poses.txt", np.eye(4))
    k = data.load_sequence(folder).intrinsics
    focal = 320.0 / np.tan(np.radians(30.0))  # NeuralRGBD's 640 px renders with a 60 deg field of view
    assert k.fx == pytest.approx(focal, rel=1e-12) and k.fy == pytest.approx(focal, rel=1e-12)
    assert (k.cx, k.cy, k.width, k.height) == (320.0, 240.0, 640, 480)


def test_scannet_intrinsics_of_another_image_size_are_refused(tmp_path):
    """A downsampled export that kept the 640x480 intrinsic_depth.txt: cx = 318.9 on 8x6 depth."""
    folder = _scannet_scene(tmp_path / "scene0000_00", [0], [np.eye(4)], [1.5])
    np.savetxt(folder / "intrinsic/intrinsic_depth.txt",
               [[577.59, 0, 318.91, 0], [0, 578.73, 242.68, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    with pytest.raises(ValueError, match=r"intrinsic_depth\.txt: calibration cx = 318\.91 lies outside the 8x6 images"):
        data.load_sequence(folder)


def test_neural_rgbd_layout_converts_opengl_poses(tmp_path):
    folder = tmp_path / "breakfast_room"
    (folder / "images").mkdir(parents=True)
    (folder / "depth_filtered").mkdir()
    poses_gl = _random_poses(11, seed=3)
    for i in range(11):  # natural order: img2 before img10
        iio.imwrite(folder / f"images/img{i}.png", _rgb(8, 6, i))
        iio.imwrite(folder / f"depth_filtered/depth{i}.png", _depth(8, 6, 1.0 + 0.01 * i, 1000))
    np.savetxt(folder / "poses.txt", poses_gl.reshape(-1, 4))
    with pytest.raises(ValueError, match=r"depth0\.png: 8x6 image but no intrinsics\.json/calibration\.txt .*"
                                         r"without focal\.txt the release's values .* are for 640x480 images"):
        data.load_sequence(folder)
    (folder / "focal.txt").write_text("7.0\n")
    sequence = data.load_sequence(folder)
    assert sequence.kind == "neural_rgbd"
    assert sequence.intrinsics == data.Intrinsics(7.0, 7.0, 4.0, 3.0, 8, 6)
    frame = sequence[10]
    np.testing.assert_allclose(frame.depth, 1.1, atol=1e-6)
    gl = poses_gl[10]  # OpenGL camera looks along -z and has y up
    np.testing.assert_allclose(frame.pose_c2w[:3, 0], gl[:3, 0])
    np.testing.assert_allclose(frame.pose_c2w[:3, 1], -gl[:3, 1])
    np.testing.assert_allclose(frame.pose_c2w[:3, 2], -gl[:3, 2])
    np.testing.assert_allclose(frame.pose_c2w[:3, 3], gl[:3, 3])
    (folder / "focal.txt").write_text("300.5\n")
    assert data.load_sequence(folder).intrinsics.fx == 300.5
    (folder / "focal.txt").write_text("-500\n")
    with pytest.raises(ValueError, match=r"focal\.txt: .*fx, fy > 0"):
        data.load_sequence(folder)
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 6.5, "fy": 6.6, "cx": 3.5, "cy": 2.5}))
    assert data.load_sequence(folder).intrinsics == data.Intrinsics(6.5, 6.6, 3.5, 2.5, 8, 6)  # before focal.txt
    (folder / "poses.txt").write_text("1 0 0\n")
    with pytest.raises(ValueError, match=r"poses\.txt:1: expected 4 numbers"):
        data.load_sequence(folder)


def test_replica_layout(tmp_path):
    folder = tmp_path / "room0"
    (folder / "results").mkdir(parents=True)
    poses = _random_poses(2, seed=5)
    for i in range(2):
        Image.fromarray(np.full((680, 1200, 3), 100, np.uint8)).save(folder / f"results/frame{i:06d}.jpg")
        iio.imwrite(folder / f"results/depth{i:06d}.png", _depth(1200, 680, 2.0, 6553.5))
    np.savetxt(folder / "traj.txt", poses.reshape(2, 16))
    sequence = data.load_sequence(folder, frame_start=1)
    assert sequence.kind == "replica" and len(sequence) == 1
    assert sequence.intrinsics == data.Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)  # not floored
    frame = sequence[0]
    np.testing.assert_allclose(frame.depth, round(2.0 * 6553.5) / 6553.5, atol=1e-6)
    np.testing.assert_allclose(frame.pose_c2w, poses[1], atol=1e-12)
    assert frame.timestamp == pytest.approx(1 / 30)


def test_generic_folder_layout(tmp_path):
    folder = tmp_path / "capture"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    stamps = 50.0 + np.arange(4) / 15.0
    for i, stamp in enumerate(stamps):
        iio.imwrite(folder / f"rgb/{stamp:.6f}.png", _rgb(8, 6, i))
        iio.imwrite(folder / f"depth/{stamp:.6f}.png", _depth(8, 6, 0.8, 1000))
    (folder / "calibration.txt").write_text("# fx fy cx cy\n9 9 3.5 2.5\n")
    poses = _random_poses(4)
    (folder / "groundtruth.txt").write_text("\n".join(_tum_line(s, p) for s, p in zip(stamps, poses)))
    sequence = data.load_sequence(folder)
    assert sequence.kind == "folder"
    np.testing.assert_allclose(sequence.timestamps, np.round(stamps, 6))
    np.testing.assert_allclose(sequence[2].depth, 0.8, atol=1e-6)  # mm default scale
    np.testing.assert_allclose(sequence[2].pose_c2w, poses[2], atol=1e-6)
    (folder / "calibration.txt").write_text("9 9 3.5\n")
    with pytest.raises(ValueError, match=r"calibration\.txt:1: expected"):
        data.load_sequence(folder)


def test_a_folder_without_its_camera_is_told_both_calibration_formats(tmp_path):
    """The message pointed at a docs file that an installed package does not have; it now spells
    out both formats, and what it says is enough: a file written from it is read."""
    folder = _folder_layout(tmp_path / "capture", ["000000", "000001"])
    (folder / "calibration.txt").unlink()
    for dataset, error in (("folder", FileNotFoundError), ("auto", ValueError)):  # named, or detected
        with pytest.raises(error) as refusal:
            data.load_sequence(folder, dataset=dataset)
        message = str(refusal.value)
        assert '"fx"' in message and "calibration.txt (one line: fx fy cx cy" in message and "docs/" not in message
    (folder / "intrinsics.json").write_text('{"fx": 9, "fy": 9, "cx": 3.5, "cy": 2.5}')
    assert data.load_sequence(folder).intrinsics.fx == 9
    tum = _tum_folder_without_calibration(tmp_path / "rgbd_dataset_freiburg1_desk")
    for image in (tum / "depth").iterdir():  # not the built-in camera's 640x480
        Image.fromarray(np.full((6, 8), 5000, np.uint16)).save(image)
    with pytest.raises(ValueError, match=r"add the camera of these images as intrinsics\.json \(") as refusal:
        data.load_sequence(tum)
    assert "calibration.txt (one line" in str(refusal.value) and "docs/" not in str(refusal.value)


def _folder_layout(folder, stems, depth_mm=800):
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for i, stem in enumerate(stems):
        iio.imwrite(folder / f"rgb/{stem}.png", _rgb(8, 6, i))
        iio.imwrite(folder / f"depth/{stem}.png", _depth(8, 6, depth_mm / 1000, 1000))
    (folder / "calibration.txt").write_text("9 9 3.5 2.5\n")
    return folder


def test_a_first_depth_image_that_is_no_image_is_named_with_what_was_expected(tmp_path):
    folder = _folder_layout(tmp_path / "capture", ["000000", "000001"])
    (folder / "depth/000000.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match=r"000000\.png: cannot read it as an image .*expected a PNG"):
        data.load_sequence(folder)


def test_folder_layout_refuses_two_images_of_one_frame(tmp_path):
    """rgb/000001.png and rgb/000001.jpg: one stem, two files (the stem lists then differed by
    nothing and the error read 'unmatched: []')."""
    folder = _folder_layout(tmp_path / "capture", ["000000", "000001", "000002"])
    iio.imwrite(folder / "rgb/000001.jpg", _rgb(8, 6, 1))
    with pytest.raises(ValueError, match=r"rgb: 000001\.(png|jpg), 000001\.(png|jpg) share a file name stem"):
        data.load_sequence(folder)


@pytest.mark.parametrize("stems, seconds", [
    (["000000", "000001", "000003"], [0.0, 1 / 15, 3 / 15]),  # frame numbers at fps 15, the gap kept
    (["0", "9", "18"], [0.0, 9 / 15, 18 / 15]),  # a step under 10: still frame numbers (docs/data.md)
    (["0", "10", "20"], [0.0, 0.01, 0.02]),  # a step of 10: milliseconds, as docs/data.md warns
    (["1520530328189680000", "1520530328223013000"], [1520530328.18968, 1520530328.223013]),  # nanoseconds
    (["1520530328189680", "1520530328223013"], [1520530328.18968, 1520530328.223013]),  # microseconds
    (["1520530328189", "1520530328223"], [1520530328.189, 1520530328.223]),  # milliseconds
    (["0.0", "0.1", "0.033333", "0.066667"], [0.0, 0.033333, 0.066667, 0.1]),  # seconds, by value
])
def test_folder_layout_reads_frame_numbers_nanoseconds_and_seconds(tmp_path, stems, seconds):
    sequence = data.load_sequence(_folder_layout(tmp_path / "capture", stems), fps=15.0)
    np.testing.assert_allclose(sequence.timestamps, seconds, rtol=0, atol=1e-6)
    by_time = sorted(stems, key=float)  # each frame keeps its own images: colour value i of stem i
    assert [int(sequence[i].rgb[0, 0, 0] * 255 + 0.5) for i in range(len(stems))] == [stems.index(s) for s in by_time]


@pytest.mark.parametrize("calibration, words", [
    ({"fx": 9, "fy": 9, "cx": 3.5, "cy": 2.5, "width": 8}, ["intrinsics.json", "'width' and 'height' come together"]),
    ({"fx": 0, "fy": 9, "cx": 3.5, "cy": 2.5}, ["intrinsics.json", "'fx' must be > 0, got 0"]),
    ({"fx": 9, "fy": 9, "cx": 3.5, "cy": 2.5, "depth_scale": 0}, ["intrinsics.json", "'depth_scale' must be > 0"]),
    ({"fx": 9, "fy": 9, "cx": 3.5, "cy": 2.5, "depth-scale": 1000, "k1": 0.1},  # a misspelt key would fall back silently
     ["intrinsics.json", "unknown key(s) 'depth-scale', 'k1'", "lens distortion is not modelled"]),
    ({"fx": 9, "fy": 9, "cx": 796.5, "cy": 2.5}, ["capture", "cx = 796.5 lies outside the 8x6 images"]),
    ({"fx": 0.5, "fy": 0.5, "cx": 0.5, "cy": 0.5}, ["capture", "fx = 0.5 is under a tenth", "normalised"]),
])
def test_bad_calibration_values_name_the_file(tmp_path, calibration, words):
    folder = _folder_layout(tmp_path / "capture", ["1.0", "2.0"])
    (folder / "calibration.txt").unlink()
    (folder / "intrinsics.json").write_text(json.dumps(calibration))
    with pytest.raises(ValueError) as error:
        data.load_sequence(folder)
    assert all(word in str(error.value) for word in words), str(error.value)
    (folder / "intrinsics.json").unlink()
    for line, words in [("nan 9 3.5 2.5", "every number must be finite"),
                        ("9 9 3.5 2.5 nan 6", "every number must be finite"),  # once a bare int() error
                        ("9 9 3.5 2.5 8.5 6", "'width' must be a whole number of pixels, got 8.5")]:
        (folder / "calibration.txt").write_text(f"# fx fy cx cy\n{line}\n")
        with pytest.raises(ValueError, match=r"calibration\.txt:2: " + re.escape(words)):
            data.load_sequence(folder)


def test_a_depth_scale_that_contradicts_the_data_folder_is_refused_not_preferred(tmp_path):
    folder = _folder_layout(tmp_path / "capture", ["1.0", "2.0"])
    (folder / "calibration.txt").unlink()
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 9, "fy": 9, "cx": 3.5, "cy": 2.5, "depth_scale": 1000}))
    np.testing.assert_allclose(data.load_sequence(folder)[0].depth, 0.8, atol=1e-6)  # the file's scale
    np.testing.assert_allclose(data.load_sequence(folder, depth_scale=1000)[0].depth, 0.8, atol=1e-6)
    with pytest.raises(ValueError) as error:  # a preset's 5000 would read 0.16 m
        data.load_sequence(folder, depth_scale=5000)
    for words in ("intrinsics.json", "'depth_scale' is 1000", "data.depth_scale is 5000", "--set data.depth_scale=1000"):
        assert words in str(error.value), str(error.value)


def test_lists_written_with_a_byte_order_mark_are_read(tum_folder):
    folder, rgb, _, _ = tum_folder
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        (folder / name).write_bytes(b"\xef\xbb\xbf" + (folder / name).read_bytes())
    assert len(data.load_sequence(folder)) == 5  # as without the mark (frame 3 has no depth)


def test_file_names_with_commas_and_comma_separated_lists(tum_folder):
    folder, rgb, _, _ = tum_folder
    (folder / "rgb").rename(folder / "rgb,left")  # a comma inside a file name
    lines = (folder / "rgb.txt").read_text().replace(" rgb/", " rgb,left/")
    (folder / "rgb.txt").write_text(lines)
    sequence = data.load_sequence(folder)
    assert len(sequence) == 5 and sequence[4].rgb.shape == (6, 8, 3)
    depth_lines = (folder / "depth.txt").read_text().splitlines()  # 'stamp,name' and 'stamp, name' still read
    (folder / "depth.txt").write_text("\n".join(line.replace(" ", "," if i % 2 else ", ", 1) if not line.startswith("#")
                                                else line for i, line in enumerate(depth_lines)) + "\n")
    assert len(data.load_sequence(folder)) == 5


# ------------------------------------------------------------------------------------------------
# Trajectory files


def test_tum_trajectory_write_read(tmp_path):
    stamps = 1341841873.0 + np.arange(5) * 0.0333
    poses = _random_poses(5)
    path = data.write_tum_trajectory(tmp_path / "traj.txt", stamps, poses)
    text = path.read_text().splitlines()
    assert text[0].startswith("#") and text[1].split()[0] == f"{stamps[0]:.6f}"
    # scipy as the independent quaternion oracle (x, y, z, w)
    quat = np.array([float(v) for v in text[2].split()[4:]])
    assert min(np.abs(quat - Rotation.from_matrix(poses[1, :3, :3]).as_quat()).max(),
               np.abs(quat + Rotation.from_matrix(poses[1, :3, :3]).as_quat()).max()) < 1e-8
    read_stamps, read_poses = data.read_tum_trajectory(path)
    np.testing.assert_allclose(read_stamps, stamps, atol=1e-6, rtol=0)
    np.testing.assert_allclose(read_poses, poses, atol=1e-8)
    with pytest.raises(FileExistsError):
        data.write_tum_trajectory(path, stamps, poses)
    data.write_tum_trajectory(path, stamps[:2], poses[:2], overwrite=True)
    assert len(data.read_tum_trajectory(path)[0]) == 2


# ------------------------------------------------------------------------------------------------
# Real data: TUM fr3/teddy, first 120 frames


def _raw_list(path):
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return [float(r[0]) for r in rows], [r[1] for r in rows]


def test_real_tum_teddy(shared_data):
    folder = shared_data / "tum_fr3_teddy_120"
    rgb_t, _ = _raw_list(folder / "rgb.txt")
    depth_t, _ = _raw_list(folder / "depth.txt")
    gt = np.loadtxt(folder / "groundtruth.txt", comments="#")
    # independent brute-force association: nearest within 0.02 s
    expected = [t for t in rgb_t if min(abs(t - d) for d in depth_t) <= 0.02 and np.abs(gt[:, 0] - t).min() <= 0.02]
    sequence = data.load_sequence(folder)
    assert len(sequence) == len(expected) == 116
    np.testing.assert_array_equal(sequence.timestamps, expected)
    assert sequence.gt_poses.shape == (116, 4, 4) and np.isfinite(sequence.gt_poses).all()
    k = sequence.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (535.4, 539.2, 320.1, 247.6, 640, 480)
    frame = sequence[0]
    valid = frame.depth[frame.depth > 0]
    assert 0.3 < valid.min() and valid.max() < 10.0 and valid.size > 0.5 * frame.depth.size
    raw = iio.imread(sequence.depth_paths[0])
    np.testing.assert_allclose(frame.depth, raw / 5000.0, rtol=1e-6)
    # frame 0 lies just before the first 100 Hz pose (within 0.02 s): the nearest line, TUM's rule
    t0 = sequence.timestamps[0]
    if t0 < gt[0, 0]:
        assert gt[0, 0] - t0 <= 0.02
        np.testing.assert_allclose(frame.pose_c2w[:3, 3], gt[0, 1:4], atol=1e-12)
        np.testing.assert_allclose(frame.pose_c2w[:3, :3], Rotation.from_quat(gt[0, 4:8]).as_matrix(), atol=1e-9)
    # later frames: scipy Slerp / linear interpolation between the two bracketing raw lines
    for i in (1, 60, 115):
        t = sequence.timestamps[i]
        j = np.searchsorted(gt[:, 0], t)
        slerp = Slerp(gt[j - 1 : j + 1, 0], Rotation.from_quat(gt[j - 1 : j + 1, 4:8]))
        pose = sequence.gt_poses[i]
        np.testing.assert_allclose(pose[:3, :3], slerp([t]).as_matrix()[0], atol=1e-6)
        w = (t - gt[j - 1, 0]) / (gt[j, 0] - gt[j - 1, 0])
        np.testing.assert_allclose(pose[:3, 3], (1 - w) * gt[j - 1, 1:4] + w * gt[j, 1:4], atol=1e-9)
        nearest = np.abs(gt[:, 0] - t).argmin()
        assert np.linalg.norm(pose[:3, 3] - gt[nearest, 1:4]) < 0.01


def test_bundled_slice_matches_source(shared_data):
    bundled = data.load_from_config(DataConfig())  # path "" -> the bundled slice
    assert bundled.path == data.default_sequence_path() and len(bundled) == 100
    k = bundled.intrinsics
    np.testing.assert_allclose([k.fx, k.fy, k.cx, k.cy], [535.4 / 4, 539.2 / 4, (320.1 + 0.5) / 4 - 0.5, (247.6 + 0.5) / 4 - 0.5])
    assert (k.width, k.height) == (160, 120)
    source = data.load_sequence(shared_data / "tum_fr3_teddy_120")
    np.testing.assert_array_equal(bundled.timestamps, source.timestamps[:100])
    np.testing.assert_allclose(bundled.gt_poses, source.gt_poses[:100], atol=1e-12)
    small, full = bundled[50], source[50]
    np.testing.assert_allclose(small.rgb.mean(axis=(0, 1)), full.rgb.mean(axis=(0, 1)), atol=0.01)
    assert abs(np.median(small.depth[small.depth > 0]) - np.median(full.depth[full.depth > 0])) < 0.02


# ------------------------------------------------------------------------------------------------
# Command line


def test_cli_info(tum_folder, capsys):
    assert data.main(["info", str(tum_folder[0]), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    for key in ("type", "frames", "frames_with_gt", "width", "height", "fx", "fy", "cx", "cy", "duration_s",
                "depth_valid_fraction"):
        assert key in summary
    assert summary["type"] == "tum" and summary["frames"] == 5 and summary["depth_valid_fraction"] == 1.0
    assert summary["colour_without_depth"] == 1  # the fixture's frame 3: its depth is 0.026 s away
    assert summary["depth_median_m"] == pytest.approx(1.2)  # frames at 1.0, 1.1, 1.2, 1.4, 1.5 m (3 is dropped)
    stamps = np.delete(tum_folder[1], 3)  # the fixture's colour stamps but the one without depth
    assert summary["largest_gap_s"] == pytest.approx(np.max(np.diff(stamps)), abs=1e-9)
    assert summary["largest_gap_after_frame"] == int(np.argmax(np.diff(stamps)))
    assert summary["spacing_median_s"] == pytest.approx(np.median(np.diff(stamps)), abs=1e-9)


def test_colour_without_depth_counts_only_association_drops(tum_folder):
    """Six colour stamps, one without depth within 0.02 s: counted before the frame selection and apart
    from the frames left out for lacking ground truth."""
    sequence = data.load_sequence(tum_folder[0], frame_start=2)
    assert sequence.colour_without_depth == 1 and sequence.frames_without_gt == 0 and len(sequence) == 3
    assert data.load_sequence(tum_folder[0], max_time_diff=0.03).colour_without_depth == 0


def test_a_run_notes_colour_images_without_depth(tmp_path, monkeypatch, capsys):
    """The note is printed with the run's first lines, before any frame is tracked (the loop is
    replaced by one that stops at once)."""
    from tsslam_ref import run, slam

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop

    rgb = 100.0 + np.arange(6) / 30.0
    depth = rgb + 0.001
    depth[2] += 0.03
    folder = make_tum(tmp_path / "tum", rgb, depth, rgb, _random_poses(6), size=(64, 48))
    monkeypatch.setattr(slam, "run_slam", stop)
    with pytest.raises(Stop):
        run.main(["--data", str(folder), "--config", "tiny", "--quiet", "--out", str(tmp_path / "out")])
    note = f"note: 1 colour image(s) in {folder / 'rgb.txt'} have no depth image within 0.02 s"
    assert note in capsys.readouterr().out


def test_cli_info_rejects_non_dataset(tmp_path, capsys):
    assert data.main(["info", str(tmp_path)]) == 2
    assert "Layouts tried" in capsys.readouterr().err


def test_module_entry_point_exit_status(tmp_path):
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "tsslam_ref.data", "info", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 2 and "Layouts tried" in result.stderr


def test_default_synthetic_path_generates_once(tmp_path, monkeypatch):
    from tsslam_ref import synthetic

    calls = []

    def fake_synthesize(out_dir, **kwargs):
        calls.append((out_dir, kwargs))
        out_dir.mkdir(parents=True)
        (out_dir / "rgb.txt").write_text("")
        return out_dir

    monkeypatch.setattr(synthetic, "synthesize", fake_synthesize)
    cache = tmp_path / "cache"
    assert data.default_synthetic_path(cache, verbose=False) == cache
    assert data.default_synthetic_path(cache, verbose=False) == cache
    assert len(calls) == 1 and calls[0][1]["n_frames"] == 60 and calls[0][1]["seed"] == 0


def test_folder_layout_refuses_integer_names_of_no_known_unit(tmp_path):
    folder = _folder_layout(tmp_path / "capture", ["10", "5000000010"])  # a 5e9 step: 5 s even in ns
    with pytest.raises(ValueError, match=r"capture/rgb: integer file names 10, 5000000010, \.\.\. step by 5e\+09"):
        data.load_sequence(folder)


def test_frames_closer_than_a_microsecond_are_refused(tum_folder):
    """Trajectory files keep microseconds (%.6f): two frames 0.4 µs apart would share a stamp."""
    folder, rgb, _, _ = tum_folder
    lines = (folder / "rgb.txt").read_text().splitlines()
    stamp = lines[3].split()[0]  # the second frame
    close = f"{float(lines[2].split()[0]) + 4e-7:.7f}"
    (folder / "rgb.txt").write_text("\n".join(lines).replace(f"{stamp} ", f"{close} ", 1) + "\n")
    with pytest.raises(ValueError, match=r"frames 0 and 1 are [0-9.e-]+ s apart .* at least 1 µs apart"):
        data.load_sequence(folder)


def test_timing_summary_states_the_duration_and_the_median_rate():
    """The run's first line carries it, so frame times read in the wrong unit (file stems 0, 10, 20
    taken as milliseconds for frames 1/3 s apart) show as 100 Hz at once."""
    assert data.timing_summary(np.arange(100) / 30.0) == "3.3 s at 30 Hz"
    assert data.timing_summary(np.array([0.0, 0.01, 0.02, 0.5])) == "0.5 s at 100 Hz"  # the median step
    assert data.timing_summary(np.array([7.0])) == "one frame"


def test_calibration_txt_reads_fx_fy_cx_cy_width_height_in_that_order(tmp_path):
    """calibration.txt's documented order 'fx fy cx cy width height': four distinct values written by
    hand must come back in the same slots (a reader taking 'fx cx fy cy' would swap fy and cx)."""
    folder = _folder_layout(tmp_path / "capture", ["1.0", "2.0"])
    (folder / "calibration.txt").write_text("# fx fy cx cy width height\n9.5 10.25 3.75 2.125 8 6\n")
    assert data.load_sequence(folder).intrinsics == data.Intrinsics(9.5, 10.25, 3.75, 2.125, 8, 6)


def test_colour_of_16_bits_and_with_alpha_reads_as_rgb_in_0_1(tmp_path):
    """A 16-bit grey PNG is value / 65535 on all three channels and an RGBA PNG drops its alpha
    (values written by hand: 32768 / 65535 = 0.500008; RGBA (10, 20, 30, 255) -> (10, 20, 30) / 255)."""
    stamps = 10.0 + np.arange(1) / 30
    folder = make_tum(tmp_path / "t", stamps, stamps, stamps, _random_poses(1))
    path = folder / f"rgb/{stamps[0]:.6f}.png"
    iio.imwrite(path, np.full((6, 8), 32768, np.uint16))
    np.testing.assert_allclose(data.load_sequence(folder)[0].rgb[2, 3], np.full(3, 32768 / 65535), atol=1e-6)
    iio.imwrite(path, np.tile(np.array([10, 20, 30, 255], np.uint8), (6, 8, 1)))
    np.testing.assert_allclose(data.load_sequence(folder)[0].rgb[2, 3], np.array([10, 20, 30]) / 255, atol=1e-6)


def test_resized_height_is_the_nearest_whole_pixel_to_the_aspect_ratio():
    """Replica's 1200x680 at width 160: 680 * 160 / 1200 = 90.67 px -> 91 rows (nearest, not the
    floor 90, which would stretch y by 1 %); after a 10 px crop, 660 * 160 / 1180 = 89.49 -> 89."""
    assert output_size(1200, 680, 0, 160) == (160, 91)
    assert output_size(1200, 680, 10, 160) == (160, 89)


def test_a_resize_width_above_the_image_width_keeps_the_native_size_instead_of_enlarging():
    """The CPU presets' 160 on images of 80x60 of the user's own: no enlargement (it would only add
    cost, and a huge value would take the memory without bound); the same width is no change."""
    assert output_size(80, 60, 0, 160) == (80, 60)
    assert output_size(80, 60, 2, 100000) == (76, 56)  # cropped, not enlarged
    assert output_size(160, 120, 0, 160) == (160, 120)


def test_crop_edge_removes_that_many_pixels_from_every_side(tmp_path):
    """crop_edge=2 on a 16x12 depth whose value encodes its pixel (row * 16 + column + 1, in mm at
    scale 1000): frame.depth must be the input's rows 2..9 and columns 2..13, i.e. depth[2:-2, 2:-2]."""
    stamps = 10.0 + np.arange(1) / 30
    folder = make_tum(tmp_path / "t", stamps, stamps, stamps, _random_poses(1), size=(16, 12))
    code = (np.arange(12)[:, None] * 16 + np.arange(16)[None, :] + 1).astype(np.uint16)  # (12, 16)
    iio.imwrite(folder / f"depth/{stamps[0]:.6f}.png", code)
    frame = data.load_sequence(folder, crop_edge=2, depth_scale=1.0)[0]
    np.testing.assert_array_equal(frame.depth, code[2:-2, 2:-2].astype(np.float32))


def test_colour_of_twice_the_depth_size_is_cropped_on_the_depth_pixels(tmp_path):
    """Colour at 32x24 for 16x12 depth, crop_edge=2: the colour is first brought to the depth size,
    then cropped, so output column j shows depth column j + 2.  Oracle: colour column c holds the ramp
    4 c + 2; depth column d covers colour columns 2d, 2d + 1 (centre 2d + 0.5), and a symmetric
    bilinear filter keeps a ramp, so output column j reads 4 (2 (j + 2) + 0.5) + 2 = 8 j + 20."""
    stamps = 10.0 + np.arange(1) / 30
    folder = make_tum(tmp_path / "t", stamps, stamps, stamps, _random_poses(1), size=(16, 12))
    colour = np.zeros((24, 32, 3), np.uint8)
    colour[..., 0] = 4 * np.arange(32) + 2
    iio.imwrite(folder / f"rgb/{stamps[0]:.6f}.png", colour)
    frame = data.load_sequence(folder, crop_edge=2)[0]
    assert frame.rgb.shape == (8, 12, 3)
    np.testing.assert_allclose(frame.rgb[4, :, 0] * 255, 8 * np.arange(12) + 20, atol=0.5)


def test_association_ties_go_to_the_earlier_stamp():
    """A colour stamp exactly halfway between two depth stamps (0.5 between 0.25 and 0.75, exact in
    binary) takes the earlier one, as documented; a stamp nearer the later one takes the later one."""
    np.testing.assert_array_equal(associate_nearest(np.array([0.5, 0.625]), np.array([0.25, 0.75]), 0.3), [0, 1])


def test_ground_truth_rotation_interpolates_along_the_shorter_arc():
    """GT samples at yaw +170 deg and -170 deg (20 deg apart across 180 deg): halfway between, the pose
    is yaw 180 deg, a quarter of the way yaw 175 deg (scipy's Slerp as oracle), not the long way
    round through yaw 0."""
    yaws = Rotation.from_euler("z", [[170.0], [-170.0]], degrees=True)
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[:, :3, :3] = yaws.as_matrix()
    got = ground_truth_at(np.array([0.005, 0.0025]), np.array([0.0, 0.01]), poses, 0.02)
    expected = Slerp([0.0, 0.01], yaws)([0.005, 0.0025]).as_matrix()
    np.testing.assert_allclose(got[:, :3, :3], expected, atol=1e-9)
    np.testing.assert_allclose(expected[0], Rotation.from_euler("z", 180.0, degrees=True).as_matrix(), atol=1e-9)


def test_ground_truth_interpolates_across_a_gap_of_up_to_twice_the_tolerance():
    """GT at 0 s (x = 0 m) and 0.03 s (x = 3 m), tolerance 0.02 s: the gap 0.03 s <= 2 * 0.02 s, so a
    frame at 0.01 s gets the interpolated x = 1 m (by hand), not the nearest sample's 0 m; with
    samples 0.05 s apart it gets the nearest sample's pose."""
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, 0, 3] = 3.0
    np.testing.assert_allclose(ground_truth_at(np.array([0.01]), np.array([0.0, 0.03]), poses, 0.02)[0, 0, 3], 1.0)
    np.testing.assert_allclose(ground_truth_at(np.array([0.01]), np.array([0.0, 0.05]), poses, 0.02)[0, 0, 3], 0.0)


def test_frame_range_counts_only_frames_with_ground_truth(tmp_path):
    """Frames 0..4 at 30 Hz, GT only from 0.1 s: frames 3 and 4 are usable, so the range [0:1] is frame
    3 and the stride [::2] is frame 3 alone (the slice is over the usable frames, as documented)."""
    rgb = 100.0 + np.arange(5) / 30.0
    folder = make_tum(tmp_path / "t", rgb, rgb, 100.1 + np.arange(5) * 0.01, _random_poses(5))
    np.testing.assert_allclose(data.load_sequence(folder, frame_stop=1).timestamps, np.round(rgb[[3]], 6), rtol=0, atol=1e-9)
    np.testing.assert_allclose(data.load_sequence(folder, frame_step=2).timestamps, np.round(rgb[[3]], 6), rtol=0, atol=1e-9)


def test_depth_scale_of_the_calibration_file_is_used_when_none_is_configured(tmp_path):
    """intrinsics.json says 4000 PNG values per metre and the depth PNG holds 3200: 0.8 m (by hand),
    not the folder layout's standard 1000 (3.2 m)."""
    folder = _folder_layout(tmp_path / "capture", ["1.0", "2.0"], depth_mm=3200)
    (folder / "calibration.txt").unlink()
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 9, "fy": 9, "cx": 3.5, "cy": 2.5, "depth_scale": 4000}))
    sequence = data.load_sequence(folder)
    assert sequence.depth_scale == 4000
    np.testing.assert_allclose(sequence[0].depth, 0.8, atol=1e-6)


def test_load_from_config_passes_every_frame_setting(tum_folder):
    """DataConfig's frame_start / frame_stop / frame_step reach the loader: [1:5:2] of the usable
    frames (colour stamps 0, 1, 2, 4, 5 of the fixture) is stamps 1 and 4, as load_sequence gives."""
    folder, rgb, _, _ = tum_folder
    sequence = data.load_from_config(DataConfig(path=str(folder), frame_start=1, frame_stop=5, frame_step=2))
    np.testing.assert_array_equal(sequence.timestamps, rgb[[1, 4]])


def test_resized_intrinsics_have_exactly_the_requested_size():
    """resized(w, h) scales by w / W, and W * (w / W) can fall a hair below w in floating point (1200 *
    (55 / 1200) = 54.99999...); the size must still be the requested w x h for every w and h (oracle:
    the request itself)."""
    k = data.Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
    sizes = [(k.resized(w, 1 + w * 679 // 1199).width, k.resized(w, 1 + w * 679 // 1199).height) for w in range(1, 1201)]
    assert sizes == [(w, 1 + w * 679 // 1199) for w in range(1, 1201)]


def test_each_frame_reads_the_depth_file_its_stamp_associates_to(tmp_path):
    """depth.txt starts two stamps earlier than rgb.txt, so colour line i pairs with depth line i + 2
    (nearest stamp, 1 ms apart); make_tum writes depth line k as 1 + 0.1 k metres, so frame i must
    read 1 + 0.1 (i + 2) m, the file named on the depth line, not on the depth line of the same number."""
    rgb = 20.0 + np.arange(4) / 30.0
    depth = np.concatenate([20.0 - np.array([2.0, 1.0]) / 30.0, rgb]) + 0.001
    folder = make_tum(tmp_path / "t", rgb, depth, rgb, _random_poses(4))
    sequence = data.load_sequence(folder)
    np.testing.assert_allclose([sequence[i].depth.mean() for i in range(4)], 1.0 + 0.1 * (np.arange(4) + 2), atol=1e-6)


@pytest.mark.parametrize("block, words", [
    (np.diag([1.0, 1.0, -1.0]), ["det -1"]),  # one flipped camera axis: was written as the identity
    (2.0 * np.eye(3), ["det 8"]),
    (np.array([[1.0, 0.075, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), ["largest |RᵀR − I| entry 0.075"]),  # a shear
])
def test_a_pose_that_is_no_rotation_is_refused_not_written_as_another(tmp_path, block, words):
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[1, :3, :3] = block
    with pytest.raises(ValueError, match=r"poses\[1\] \(t = 1.000000 s\) is not a rotation") as refusal:
        data.write_tum_trajectory(tmp_path / "t.txt", [0.0, 1.0, 2.0], poses)
    assert all(word in str(refusal.value) for word in words) and not (tmp_path / "t.txt").exists()
    drifted = np.tile(np.eye(4), (3, 1, 1))  # float32 rounding of a long chain of rotations: written
    drifted[1, :3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix().astype(np.float32) * (1 + 1e-5)
    data.write_tum_trajectory(tmp_path / "t.txt", [0.0, 1.0, 2.0], drifted)


def _tum_folder_without_calibration(folder):
    """Two 640x480 frames in TUM layout, no intrinsics.json: the camera comes from the folder's name."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for stamp in ("1.000000", "1.033333"):
        Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(folder / "rgb" / f"{stamp}.png")
        Image.fromarray(np.full((480, 640), 5000, np.uint16)).save(folder / "depth" / f"{stamp}.png")
    for listing, kind in (("rgb.txt", "rgb"), ("depth.txt", "depth")):
        (folder / listing).write_text("".join(f"{s} {kind}/{s}.png\n" for s in ("1.000000", "1.033333")))
    return folder


def test_a_tum_folder_naming_no_camera_says_it_gets_freiburg3s():
    """fr1 data in a folder called 'desk' was read with fr3's camera (fx 535.4 against 517.3) without
    a word; the sequence now carries a note (printed by the run and by `data info`), and a folder that
    names its camera gets that camera and no note."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as root:
        unnamed = data.load_sequence(_tum_folder_without_calibration(Path(root) / "desk"))
        assert unnamed.intrinsics.fx == 535.4 and "no freiburg1/2/3 in the folder's name" in unnamed.camera_note
        assert data.sequence_info(unnamed, depth_samples=1)["camera_note"] == unnamed.camera_note
        from tsslam_ref.run_outputs import data_notes

        assert data_notes(unnamed) == [unnamed.camera_note]  # the run's notes before it starts
        named = data.load_sequence(_tum_folder_without_calibration(Path(root) / "rgbd_dataset_freiburg1_desk"))
        assert named.intrinsics.fx == 517.3 and named.camera_note == ""
        assert "camera_note" not in data.sequence_info(named, depth_samples=1)
        assert data.load_sequence(data.default_sequence_path()).camera_note == ""  # its intrinsics.json decides


def test_a_datasets_root_given_for_one_scene_names_the_scenes_inside(tmp_path):
    """A Replica/ or ScanNet root passed as --data got only the generic list of layouts tried; the
    message now names the scene folders inside (and a folder of another kind keeps the list)."""
    for name in ("scene_b", "scene_a"):
        _tum_folder_without_calibration(tmp_path / "root" / name)
    (tmp_path / "root" / "notes").mkdir()
    with pytest.raises(ValueError, match=r"root holds dataset folders, not one: scene_a \(tum\), scene_b \(tum\); "
                                         r"pass one of them"):
        data.load_sequence(tmp_path / "root")
    with pytest.raises(ValueError, match="not a recognised RGB-D dataset folder. Layouts tried"):
        data.load_sequence(tmp_path / "root" / "notes")


def test_the_frames_left_out_for_want_of_ground_truth_keep_their_stamps():
    """The bundled slice's first four colour frames come before the first motion-capture pose (its
    README): the loader leaves them out and keeps their stamps, which the frame-spacing check reads
    to say whether they opened a gap.  Oracle: the first four stamps of the slice's rgb.txt."""
    listed = [float(line.split()[0]) for line in (data.default_sequence_path() / "rgb.txt").read_text().splitlines()
              if line and not line.startswith("#")]
    sequence = data.load_sequence(data.default_sequence_path())
    assert sequence.frames_without_gt == 4
    np.testing.assert_array_equal(sequence.times_without_gt, listed[:4])
    assert sequence.timestamps[0] == listed[4]
    assert len(data.load_sequence(data.default_sequence_path(), require_gt=False).times_without_gt) == 0


def test_info_measures_gaps_over_the_frames_a_run_keeps():
    """data info measured the largest gap over every frame, ground truth or not; a run keeps only
    frames with ground truth and numbers them from there (4 fewer on the bundled slice).  Oracle:
    the run's own sequence (require_gt, the default)."""
    kept = data.load_sequence(data.default_sequence_path()).timestamps
    info = data.sequence_info(data.load_sequence(data.default_sequence_path(), require_gt=False))
    assert info["largest_gap_after_frame"] == int(np.argmax(np.diff(kept)))
    assert info["largest_gap_s"] == np.max(np.diff(kept)) and info["frames"] == len(kept) + 4


def _bom(path):
    """The file as Windows Notepad ('UTF-8 with BOM') or PowerShell 5 saves it: a byte-order mark first."""
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())


def test_files_saved_with_a_byte_order_mark_and_upper_case_depth_names_are_read(tmp_path):
    """Only the TUM lists took a UTF-8 byte-order mark: calibration.txt, intrinsics.json and a
    ScanNet pose file with one were refused with their invisible first character quoted, and
    ScanNet depth named '.PNG' (a Windows export) was 'no depth PNGs'."""
    folder = _folder_layout(tmp_path / "capture", ["000000", "000001"])
    (folder / "calibration.txt").write_text("# camera\n9 9 3.5 2.5\n")
    _bom(folder / "calibration.txt")
    assert data.load_sequence(folder).intrinsics.fx == 9
    (folder / "calibration.txt").unlink()
    (folder / "intrinsics.json").write_text('{"fx": 9, "fy": 8, "cx": 3.5, "cy": 2.5}')
    _bom(folder / "intrinsics.json")
    assert data.load_sequence(folder).intrinsics.fy == 8
    poses = _random_poses(2)
    scannet = _scannet_scene(tmp_path / "scene0000_00", [0, 1], poses, [1.5, 1.5], depth_suffix=".PNG")
    for n in range(2):
        _bom(scannet / f"pose/{n}.txt")
    np.savetxt(scannet / "intrinsic/intrinsic_depth.txt", [[6, 0, 3.5, 0], [0, 6, 2.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    _bom(scannet / "intrinsic/intrinsic_depth.txt")
    sequence = data.load_sequence(scannet)
    np.testing.assert_allclose(sequence[1].pose_c2w, poses[1], atol=1e-12)


def test_synthesize_counts_start_from_the_origin_line_of_a_file_with_a_byte_order_mark(tmp_path):
    """With a byte-order mark the '# origin:' line was not seen, so --start counted from the first
    stamp instead (15 s off on a shipped stretch), silently."""
    path = tmp_path / "stretch.txt"
    lines = ["# origin: 100.0"] + [_tum_line(115.0 + i / 30, pose) for i, pose in enumerate(_random_poses(3))]
    path.write_text("\n".join(lines) + "\n")
    assert data.trajectory_origin(path) == 100.0
    _bom(path)
    assert data.trajectory_origin(path) == 100.0


@pytest.mark.parametrize("listed, hint", [("rgb\\{}.png", "separates folders with '\\', as on Windows"),
                                          ("rgb/{}.PNG", "the folder holds '{}.png': names differ in case")])
def test_a_listed_name_that_only_windows_or_macos_would_find_says_why(tum_folder, listed, hint):
    """A list written on Windows (backslashes) or naming a file in another case (their disks
    ignore case) works there and failed here with a bare 'not found'."""
    folder = tum_folder[0]
    lines = (folder / "rgb.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    stamp = lines[first].split()[0]
    lines[first] = f"{stamp} {listed.format(stamp)}"
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(FileNotFoundError, match=re.escape(hint.format(stamp))):
        data.load_sequence(folder)
