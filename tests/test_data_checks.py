"""Dataset input that used to load into wrong results without a word: pose files whose count
differs from the frames', colour of another aspect ratio than the depth, pose matrices that are
not rigid transforms.

Oracles: counts, sizes and matrices written by hand into tiny synthetic folders (helpers of
test_data.py); scipy rotations for the poses that must still load.
"""

import json

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from test_data import _depth, _folder_layout, _random_poses, _rgb
from tsslam_ref import data


def make_replica(folder, frames, poses, size=(16, 12)):
    """Replica layout with ``frames`` frame/depth pairs of ``size`` and ``poses`` (M, 4, 4) in traj.txt."""
    (folder / "results").mkdir(parents=True)
    width, height = size
    for i in range(frames):
        iio.imwrite(folder / f"results/frame{i:06d}.jpg", _rgb(width, height, 20 * i))
        iio.imwrite(folder / f"results/depth{i:06d}.png", _depth(width, height, 2.0, 6553.5))
    np.savetxt(folder / "traj.txt", np.asarray(poses).reshape(-1, 16))
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 12.0, "fy": 12.0, "cx": 7.5, "cy": 5.5}))
    return folder


def test_replica_images_of_another_size_without_a_calibration_file_ask_for_one(tmp_path):
    folder = make_replica(tmp_path / "room0", 2, _random_poses(2))
    (folder / "intrinsics.json").unlink()
    with pytest.raises(ValueError, match=r"depth000000\.png: 16x12 image but no intrinsics\.json/calibration\.txt .*"
                                         r"the release's values \(600, 600, 599\.5, 339\.5\) are for 1200x680"):
        data.load_sequence(folder)


def test_neural_rgbd_frames_missing_on_each_side_are_not_paired_by_order(tmp_path):
    """img3 missing in images/ and depth1 in depth_filtered/: the counts agree, the numbers do not."""
    folder = make_neural_rgbd(tmp_path / "kitchen", 4, _random_poses(4))
    (folder / "images/img3.png").unlink()
    (folder / "depth_filtered/depth1.png").unlink()
    np.savetxt(folder / "poses.txt", _random_poses(3).reshape(-1, 4))
    with pytest.raises(ValueError, match=r"images/img1\.png pairs with .*depth2\.png by order, but their frame numbers"):
        data.load_sequence(folder)


def test_a_layout_named_for_a_folder_of_another_layout_names_the_one_it_has(tmp_path):
    """A NeuralRGBD scene run as the tum layout (Co-SLAM calls these scenes 'synthetic', and
    --dataset synthetic means a TUM-layout folder): was 'rgb.txt: file not found'."""
    folder = make_neural_rgbd(tmp_path / "kitchen", 2, _random_poses(2))
    with pytest.raises(ValueError, match=r"kitchen lacks rgb\.txt, depth\.txt of the 'tum' layout but has every "
                                         r"entry of the 'neural_rgbd' layout"):
        data.load_sequence(folder, dataset="tum")
    assert len(data.load_sequence(folder, dataset="neural_rgbd")) == 2


def make_neural_rgbd(folder, frames, poses_gl):
    """NeuralRGBD layout with ``frames`` 8x6 image pairs and ``poses_gl`` (M, 4, 4) in poses.txt."""
    (folder / "images").mkdir(parents=True)
    (folder / "depth_filtered").mkdir()
    for i in range(frames):
        iio.imwrite(folder / f"images/img{i}.png", _rgb(8, 6, i))
        iio.imwrite(folder / f"depth_filtered/depth{i}.png", _depth(8, 6, 1.0, 1000))
    np.savetxt(folder / "poses.txt", np.asarray(poses_gl).reshape(-1, 4))
    (folder / "focal.txt").write_text("7.0\n")  # the release's 554.256 is for 640x480 renders
    return folder


# ------------------------------------------------------------------------------------------------
# One pose per frame


@pytest.mark.parametrize("poses", [4, 2])
def test_replica_traj_with_another_count_of_poses_than_frames_is_refused(tmp_path, poses):
    """Replica's traj.txt has one line per frame; 4 (or 2) lines for 3 frames was matched by order."""
    folder = make_replica(tmp_path / "room0", 3, _random_poses(poses))
    with pytest.raises(ValueError, match=rf"traj\.txt: {poses} poses for 3 frames in .*results; expected exactly one"):
        data.load_sequence(folder)


@pytest.mark.parametrize("poses", [12, 10])
def test_neural_rgbd_poses_with_another_count_than_images_is_refused(tmp_path, poses):
    folder = make_neural_rgbd(tmp_path / "breakfast_room", 11, _random_poses(poses))
    with pytest.raises(ValueError, match=rf"poses\.txt: {poses} poses for 11 frames in .*images; expected exactly one"):
        data.load_sequence(folder)


def test_one_pose_per_frame_still_loads_with_unknown_poses(tmp_path):
    """NeuralRGBD marks unknown poses with nan: they count as poses and stay unknown."""
    poses_gl = _random_poses(3, seed=4)
    poses_gl[1] = np.nan
    folder = make_neural_rgbd(tmp_path / "scene", 3, poses_gl)
    sequence = data.load_sequence(folder, require_gt=False)
    assert len(sequence) == 3 and sequence.frames_with_gt == 2 and sequence[1].pose_c2w is None
    np.testing.assert_allclose(sequence[2].pose_c2w[:3, 3], poses_gl[2, :3, 3])


# ------------------------------------------------------------------------------------------------
# Poses must be rigid transforms


def _not_rigid(kind):
    """A pose (4, 4) whose rotation block is ``kind``: scaled 1.01, sheared, mirrored (det -1), or
    the whole matrix transposed (translation in the bottom row)."""
    pose = _random_poses(1, seed=7)[0]
    if kind == "scaled":
        pose[:3, :3] *= 1.01
    elif kind == "sheared":
        pose[:3, :3] = pose[:3, :3] @ np.array([[1.0, 0.05, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    elif kind == "mirrored":
        pose[:3, 0] *= -1.0
    else:
        pose = pose.T.copy()
    return pose


EXPECTED_WORDS = {"scaled": r"\|R\^T R - I\| = 0\.0201 and det 1\.0303", "sheared": r"\|R\^T R - I\| = 0\.05",
                  "mirrored": r"\|R\^T R - I\| = [0-9.e-]+ and det -1\b", "transposed": r"bottom row [-0-9.e ]+ 1;"}


@pytest.mark.parametrize("kind", ["scaled", "sheared", "mirrored", "transposed"])
def test_replica_pose_that_is_not_rigid_is_refused_naming_its_line(tmp_path, kind):
    poses = _random_poses(3)
    poses[2] = _not_rigid(kind)
    folder = make_replica(tmp_path / "room0", 3, poses)
    with pytest.raises(ValueError, match=r"traj\.txt:3: the pose for results/frame000002\.jpg is not a rigid "
                                         r"transform: .*" + EXPECTED_WORDS[kind]):
        data.load_sequence(folder)


@pytest.mark.parametrize("kind", ["scaled", "mirrored"])
def test_neural_rgbd_pose_that_is_not_rigid_is_refused_naming_its_line(tmp_path, kind):
    poses = _random_poses(3)
    poses[1] = _not_rigid(kind)
    folder = make_neural_rgbd(tmp_path / "scene", 3, poses)
    with pytest.raises(ValueError, match=r"poses\.txt:5: the pose for images/img1\.png .*" + EXPECTED_WORDS[kind]):
        data.load_sequence(folder)


def _scannet(folder, poses, fmt="%.18e"):
    for sub in ("color", "depth", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True)
    for n, pose in enumerate(poses):
        Image.fromarray(np.full((12, 16, 3), 40 * n, np.uint8)).save(folder / f"color/{n * 10}.jpg", quality=100)
        iio.imwrite(folder / f"depth/{n * 10}.png", _depth(8, 6, 1.5 + n, 1000))
        np.savetxt(folder / f"pose/{n * 10}.txt", pose, fmt=fmt)
    np.savetxt(folder / "intrinsic/intrinsic_depth.txt", [[6.1, 0, 3.6, 0], [0, 6.2, 2.7, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    return folder


def test_scannet_pose_that_is_not_rigid_is_refused_and_inf_poses_stay_unknown(tmp_path):
    poses = _random_poses(3)
    poses[1] = -np.inf  # ScanNet's invalid pose: unknown ground truth, as before
    folder = _scannet(tmp_path / "scene0000_00", poses)
    sequence = data.load_sequence(folder, require_gt=False)
    assert sequence.frames_with_gt == 2 and sequence[1].pose_c2w is None
    np.savetxt(folder / "pose/20.txt", _not_rigid("scaled"))
    with pytest.raises(ValueError, match=r"pose/20\.txt:1: the pose for frame 20 .*" + EXPECTED_WORDS["scaled"]):
        data.load_sequence(folder)


@pytest.mark.parametrize("fmt", ["%.6g", "%.4f"])
def test_poses_printed_with_a_few_digits_still_load(tmp_path, fmt):
    """Real files print 6-9 significant digits (ScanNet '%g'-like); 4 decimals pass too."""
    poses = _random_poses(3, seed=11)
    sequence = data.load_sequence(_scannet(tmp_path / "scene", poses, fmt))
    np.testing.assert_allclose(sequence.gt_poses, poses, atol=1e-4)
    replica = make_replica(tmp_path / "room0", 3, poses)
    np.savetxt(replica / "traj.txt", poses.reshape(-1, 16), fmt=fmt)
    np.testing.assert_allclose(data.load_sequence(replica).gt_poses, poses, atol=1e-4)


def test_groundtruth_quaternion_far_from_unit_norm_is_refused(tmp_path):
    """TUM-format ground truth (folder and tum layouts): a quaternion of norm 2 was normalised silently;
    columns in another order give such norms.  TUM's own 4-decimal quaternions still load."""
    folder = _folder_layout(tmp_path / "capture", ["1.0", "2.0"])
    rows = ["1.0 0 0 0 0.0000 0.7071 0.0000 0.7071", "2.0 0 0 0 0 1.4142 0 1.4142"]
    (folder / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    with pytest.raises(ValueError, match=r"groundtruth\.txt:3: quaternion qx qy qz qw = 0 1\.4142 0 1\.4142 has "
                                         r"norm 1\.99998; expected a unit quaternion"):
        data.load_sequence(folder)
    (folder / "groundtruth.txt").write_text("\n".join([rows[0], rows[0].replace("1.0", "2.0", 1)]) + "\n")
    rotation = data.load_sequence(folder).gt_poses[1, :3, :3]  # about y by 90 degrees
    np.testing.assert_allclose(rotation, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-4)


# ------------------------------------------------------------------------------------------------
# Colour of another aspect ratio than the depth


def test_scannet_colour_of_1296x968_for_640x480_depth_is_resized(tmp_path):
    """Real ScanNet: colour 1296x968 (aspect 1.339) for depth 640x480 (1.333), 0.4 % apart: accepted,
    resized edge onto edge (a red | blue split at the colour's middle lands at the depth's middle)."""
    folder = _scannet(tmp_path / "scene0000_00", _random_poses(1))
    colour = np.zeros((968, 1296, 3), np.uint8)
    colour[:, :648, 0] = 255
    colour[:, 648:, 2] = 255
    Image.fromarray(colour).save(folder / "color/0.jpg", quality=100)
    iio.imwrite(folder / "depth/0.png", _depth(640, 480, 1.5, 1000))
    np.savetxt(folder / "intrinsic/intrinsic_depth.txt",  # scene0000_00's depth camera
               [[577.59, 0, 318.91, 0], [0, 578.73, 242.68, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    sequence = data.load_sequence(folder)
    assert sequence.check_files() == 2
    rgb = sequence[0].rgb
    assert rgb.shape == (480, 640, 3)
    assert rgb[240, 318, 0] > 0.9 and rgb[240, 318, 2] < 0.1 and rgb[240, 321, 2] > 0.9 and rgb[240, 321, 0] < 0.1


@pytest.mark.parametrize("colour_size", [(32, 18), (33, 24)])  # 16:9 for 4:3 depth (33 % apart); 3.1 % apart
def test_colour_of_another_aspect_ratio_than_the_depth_is_refused(tmp_path, colour_size):
    folder = _folder_layout(tmp_path / "capture", ["1.0", "2.0"])  # 8x6 depth
    iio.imwrite(folder / "rgb/2.0.png", _rgb(*colour_size, 0))
    sequence = data.load_sequence(folder)
    width, height = colour_size
    words = rf"rgb/2\.0\.png: colour image is {width}x{height} \(aspect [0-9.]+\) but the depth images are 8x6 .*within 1 %"
    with pytest.raises(ValueError, match=words):
        sequence[1]
    with pytest.raises(ValueError, match=words):
        sequence.check_files()
    sequence[0]  # the other frame still reads



@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_colour_with_an_exif_orientation_tag_is_read_as_stored(tmp_path, suffix):
    """A phone's tag 6 ("turn 90 degrees to display") is not applied: the 8x6 colour keeps its stored
    rows and columns, as its 8x6 depth does (turned, it would be 6x8 and the aspect check would refuse
    it).  Oracle: the stored pixels, bit for bit for the PNG; the JPEG's left half red, right half blue."""
    folder = _folder_layout(tmp_path / "capture", ["1.0", "2.0"])  # 8x6 depth
    stored = np.zeros((6, 8, 3), np.uint8)
    stored[:, :4, 0] = 255
    stored[:, 4:, 2] = 255
    image = Image.fromarray(stored)
    tags = image.getexif()
    tags[0x0112] = 6  # EXIF Orientation
    (folder / "rgb/2.0.png").unlink()
    image.save(folder / f"rgb/2.0{suffix}", exif=tags.tobytes(), **({"quality": 100} if suffix == ".jpg" else {}))
    with Image.open(folder / f"rgb/2.0{suffix}") as written:
        assert written.getexif().get(0x0112) == 6
    sequence = data.load_sequence(folder)
    assert sequence.check_files() == 4
    rgb = sequence[1].rgb
    assert rgb.shape == (6, 8, 3)
    if suffix == ".png":
        np.testing.assert_array_equal(rgb, stored.astype(np.float32) / 255.0)
    assert (rgb[:, :3, 0] > 0.9).all() and (rgb[:, :3, 2] < 0.1).all()
    assert (rgb[:, 5:, 2] > 0.9).all() and (rgb[:, 5:, 0] < 0.1).all()

def test_replica_reads_the_intrinsics_of_its_calibration_file(tmp_path):
    """A Replica folder with intrinsics.json (fx 12, cx 7.5, cy 5.5 for its 16x12 renders, as written
    by make_replica) uses those values, not the 1200x680 release's built-in ones."""
    folder = make_replica(tmp_path / "replica", 2, _random_poses(2))
    assert data.load_sequence(folder).intrinsics == data.Intrinsics(12.0, 12.0, 7.5, 5.5, 16, 12)
