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

from test_data import _depth, _random_poses, _rgb
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


def make_neural_rgbd(folder, frames, poses_gl):
    """NeuralRGBD layout with ``frames`` 8x6 image pairs and ``poses_gl`` (M, 4, 4) in poses.txt."""
    (folder / "images").mkdir(parents=True)
    (folder / "depth_filtered").mkdir()
    for i in range(frames):
        iio.imwrite(folder / f"images/img{i}.png", _rgb(8, 6, i))
        iio.imwrite(folder / f"depth_filtered/depth{i}.png", _depth(8, 6, 1.0, 1000))
    np.savetxt(folder / "poses.txt", np.asarray(poses_gl).reshape(-1, 4))
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
