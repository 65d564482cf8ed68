"""Signs of lost tracking that the loss does not show: the estimate's speed between frames (a lost
camera jumps; its loss may even fall, on surface the map has not learned) and a failure's frame
depth (a frame whose depth lies beyond the map's range was reported as diverged motion)."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import config
from tsslam_ref.run_summaries import motion_summary
from tsslam_ref.tracking import depth_problem


def poses_from(positions: np.ndarray, rotations: Rotation) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(positions), 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = rotations.as_matrix(), positions
    return poses


def test_the_peak_speeds_match_scipy_and_only_a_jump_is_warned_about(capsys):
    rng = np.random.default_rng(0)
    times = np.cumsum(rng.uniform(0.03, 0.04, 40)) + 1.3e9  # float64 seconds of a real clock
    positions = np.cumsum(rng.normal(0, 0.01, (40, 3)), axis=0)
    rotations = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.02, (40, 3)), axis=0))
    summary = motion_summary(times, poses_from(positions, rotations))["motion"]
    speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) / np.diff(times)
    turn = np.degrees((rotations[:-1].inv() * rotations[1:]).magnitude()) / np.diff(times)
    assert summary["peak_speed_m_s"] == speed.max() and summary["peak_speed_after_frame"] == np.argmax(speed)
    np.testing.assert_allclose(summary["peak_angular_speed_deg_s"], turn.max(), rtol=1e-6)
    assert summary["peak_angular_speed_after_frame"] == np.argmax(turn)
    assert capsys.readouterr().err == ""  # hand-held speeds: no word
    positions[25:] += [0.3, 0.0, 0.0]  # 30 cm in one frame: about 9 m/s
    jumped = motion_summary(times, poses_from(positions, rotations))["motion"]
    assert jumped["peak_speed_m_s"] > 5.0 and jumped["peak_speed_after_frame"] == 24
    warning = capsys.readouterr().err
    assert warning.startswith("warning: the estimated camera moves") and "from frame 24 to 25" in warning
    assert motion_summary(times[:1], poses_from(positions[:1], rotations[:1])) == {}


def test_the_lost_camera_warning_starts_at_the_documented_5_m_per_s(capsys):
    """docs/system.md: a warning when the estimate moves faster than 5 m/s between two frames.
    By hand: frames 0.1 s apart, one step of 0.45 m (4.5 m/s, no word) or 0.55 m (5.5 m/s, warned)."""
    times = 1.3e9 + 0.1 * np.arange(6)
    still = Rotation.identity(6)
    for step, warned in ((0.45, False), (0.55, True)):
        positions = np.zeros((6, 3))
        positions[3:, 1] = step
        summary = motion_summary(times, poses_from(positions, still))["motion"]
        assert summary["peak_speed_m_s"] == pytest.approx(step / 0.1) and summary["peak_speed_after_frame"] == 2
        assert ("more than 5 m/s" in capsys.readouterr().err) == warned, step


def test_a_failed_frames_depth_beyond_the_maps_range_or_missing_is_named():
    cfg = config.tum_cpu()  # depth_trunc 5 m, far 5 m
    near = torch.full((120, 160), 2.0)
    assert depth_problem(cfg, near) == ""
    far = near.clone()
    far[:, :100] = 6.0  # 62 % beyond 5 m
    assert depth_problem(cfg, far) == ("; 62 % of this frame's measured depth lies beyond 5 m (data.depth_trunc, "
                                       "render.far): check its depth image")
    holes = torch.zeros_like(near)
    holes[:10, :100] = 2.0  # 5 % measured
    assert depth_problem(cfg, holes) == "; only 5 % of this frame's pixels have a depth: check its depth image"
