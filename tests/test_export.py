"""The continuous export (``--export-rate``): its sample times at the size of real timestamps.

Oracle: exact rational arithmetic (``fractions.Fraction``) for t_i = start + i / rate.
"""

from fractions import Fraction
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import data
from tsslam_ref.export import coslam_output_poses, export_continuous, export_times, spline_output_poses
from tsslam_ref.geometry import make_pose
from tsslam_ref.run_outputs import write_partial_outputs
from tsslam_ref.trajectory import BSplineTrajectory

STAMP = 1520530328.18968  # a TUM RGB-D timestamp (s): float64 resolves about 2.4e-7 s here


@pytest.mark.parametrize("rate", [40.0, 80.0, 120.0, 200.0, 433.0, 1000.0])
def test_export_times_are_start_plus_i_over_rate_and_stay_inside_the_domain(rate):
    start, end = STAMP, STAMP + 1.8
    times = export_times(start, end, rate)
    exact = [Fraction(start) + Fraction(i) / Fraction(rate) for i in range(len(times) + 1)]
    assert np.all(times < end) and np.all(np.diff(times) > 0)
    assert exact[len(times)] >= Fraction(end) - Fraction(np.spacing(end))  # no sample left out before the end
    ulp = np.spacing(start)
    assert max(abs(Fraction(float(t)) - x) for t, x in zip(times, exact)) <= ulp  # no drift along the file


@pytest.mark.parametrize("rate", [10.0, 30.0, 50.0])
def test_an_export_from_time_zero_keeps_a_last_frame_on_its_grid(rate):
    """Synthetic sequences start at t = 0: with the last frame on the sample grid (k / rate), the
    export's last row is that frame's time (export_continuous passes the float after it as the end).
    By construction: the frame is grid time k, so the export holds rows 0 to k."""
    for k in range(1, 120):
        last_frame = k / rate  # the grid's own float64 time i / rate for i = k
        times = export_times(0.0, float(np.nextafter(last_frame, np.inf)), rate)
        assert len(times) == k + 1 and times[-1] == last_frame, (k, rate)


@pytest.mark.parametrize("rate", [40, 80, 120, 200])
def test_export_of_a_spline_at_timestamp_size_writes_every_sample(tmp_path, rate):
    """np.arange accumulated its step and put the last of these times past the domain's end."""
    trajectory = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(6, 1, 1),
                                   torch.zeros(6, 3, dtype=torch.float64), 0.3, STAMP - 0.6)
    start, end = trajectory.domain()
    last_frame = np.nextafter(end, -np.inf)  # the latest a frame of a finished state can be
    frames_to_the_end = SimpleNamespace(trajectory=trajectory, timestamps=np.array([start, last_frame]), done=2)
    rows = export_continuous(frames_to_the_end, rate, tmp_path / "export.txt")
    assert rows[0, 0] == start and rows[-1, 0] < end and len(rows) == len(export_times(start, end, rate))
    assert np.loadtxt(tmp_path / "export.txt").shape == rows.shape


def test_the_export_writes_stamps_as_trajectory_txt_does_and_reads_back_as_a_trajectory(tmp_path):
    """Stamps of 1.5e9 s printed with 9 decimals showed float64's binary noise (STAMP came out as
    ...189679861): they are written to the microsecond, as trajectory.txt writes them, so the
    first row's stamp is the frame's own text.  The evaluator reads the 14-column export as a
    trajectory (its first 8 columns).  Out-of-range rates are refused by the function itself."""
    trajectory = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(6, 1, 1),
                                   torch.zeros(6, 3, dtype=torch.float64), 0.3, STAMP - 0.6)
    start, _ = trajectory.domain()
    state = SimpleNamespace(trajectory=trajectory, timestamps=np.array([start, start + 0.2]), done=2)
    rows = export_continuous(state, 30.0, tmp_path / "export.txt")
    first = (tmp_path / "export.txt").read_text().splitlines()[1].split()[0]
    assert first == f"{STAMP:.6f}" == "1520530328.189680", first
    times, poses = data.read_tum_trajectory(tmp_path / "export.txt")
    assert len(times) == len(rows) and np.allclose(times, rows[:, 0], rtol=0, atol=5e-7)
    assert np.allclose(poses, np.eye(4), atol=1e-9)
    for rate in (0.0, -1.0, float("nan"), float("inf"), 1e8):
        with pytest.raises(ValueError, match=r"export rate must be in \(0, 1000\] Hz"):
            export_continuous(state, rate, tmp_path / "refused.txt")
    assert not (tmp_path / "refused.txt").exists()


def test_the_export_stops_at_the_last_frame_not_at_the_end_of_the_last_interval(tmp_path):
    """Past the last frame the spline is held by nothing; the export ends at that frame's time,
    which it includes when a sample falls on it."""
    trajectory = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(6, 1, 1),
                                   torch.zeros(6, 3, dtype=torch.float64), 0.25, 100.0 - 0.5)
    start, end = trajectory.domain()  # [100.0, 100.75)
    state = SimpleNamespace(trajectory=trajectory, timestamps=np.array([100.0, 100.3, 100.5, 100.7]), done=3)
    rows = export_continuous(state, 10.0, tmp_path / "export.txt")
    assert np.allclose(rows[:, 0], 100.0 + np.arange(6) / 10.0, rtol=0, atol=1e-12)  # 100.0 .. 100.5, frame 2's time
    state.done = 4
    assert export_continuous(state, 10.0, tmp_path / "export.txt")[-1, 0] == pytest.approx(100.7)


def test_a_state_whose_spline_stops_before_its_last_frame_is_refused(tmp_path):
    """A checkpoint's state has frames past its spline (its last interval is fitted only when the
    run finishes); the export used to stop at the spline's end without a word."""
    trajectory = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(6, 1, 1),
                                   torch.zeros(6, 3, dtype=torch.float64), 0.25, 100.0 - 0.5)  # [100.0, 100.75)
    state = SimpleNamespace(trajectory=trajectory, timestamps=np.array([100.0, 100.5, 100.8]), done=3)
    with pytest.raises(ValueError, match="last processed frame is at 100.800000 s.*finish"):
        export_continuous(state, 10.0, tmp_path / "export.txt")
    assert not (tmp_path / "export.txt").exists()


def test_a_last_frame_on_the_half_open_end_of_the_spline_is_refused(tmp_path):
    """The domain [100.0, 100.75) leaves out its end: a last frame at exactly 100.75 s is not covered
    yet, so the export refuses rather than stopping one sample short of it."""
    trajectory = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(6, 1, 1),
                                   torch.zeros(6, 3, dtype=torch.float64), 0.25, 100.0 - 0.5)
    state = SimpleNamespace(trajectory=trajectory, timestamps=np.array([100.0, 100.5, 100.75]), done=3)
    with pytest.raises(ValueError, match="last processed frame is at 100.750000 s"):
        export_continuous(state, 10.0, tmp_path / "export.txt")


def test_coslam_output_re_anchors_each_frame_on_its_moved_keyframe():
    """Oracle by hand: keyframe 0 was tracked at the identity and frame 1 at x = 1 m, so frame 1's
    relative pose is T_1 T_0^-1 = [I | (1, 0, 0)]; global BA then turns keyframe 0 by 90 degrees
    about z.  Co-SLAM reports T_1 = relative @ T_0' = [Rz(90) | (1, 0, 0)] (not T_0' @ relative,
    which would put frame 1 at (0, 1, 0))."""
    turned = np.eye(4)
    turned[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    relative = np.eye(4)
    relative[0, 3] = 1.0
    state = SimpleNamespace(frame_poses=torch.tensor(np.stack([turned, relative])), done=2,
                            relative_to_keyframe={1: torch.tensor(relative)}, keyframe_of_frame={1: 0})
    expected = turned.copy()
    expected[:3, 3] = [1.0, 0.0, 0.0]
    np.testing.assert_allclose(coslam_output_poses(state).numpy(), np.stack([turned, expected]), atol=1e-12)


@pytest.mark.parametrize("use_spline", [True, False])
def test_spline_output_uses_the_spline_only_where_it_covers_and_is_switched_on(use_spline):
    """Oracle by hand: control points all at [I | (1, 2, 3)] make the spline that constant pose on
    its domain [100.0, 100.75); frames at 100.2 and 100.6 s get it, the frame at 100.8 s (past the
    domain) keeps its own pose, and with local_ba.use_spline off every frame keeps its own pose."""
    trajectory = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(6, 1, 1),
                                   torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64).repeat(6, 1), 0.25, 99.5)
    frame_poses = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    frame_poses[:, :3, 3] = torch.tensor([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [5.0, 5.0, 5.0]])
    state = SimpleNamespace(trajectory=trajectory, frame_poses=frame_poses, done=3,
                            timestamps=np.array([100.2, 100.6, 100.8, 101.0]),
                            cfg=SimpleNamespace(local_ba=SimpleNamespace(use_spline=use_spline)))
    expected = frame_poses[:3].clone()
    if use_spline:
        expected[:2, :3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    torch.testing.assert_close(spline_output_poses(state), expected, rtol=0, atol=1e-12)


def test_quaternions_of_a_turn_through_180_degrees_stay_in_one_hemisphere(tmp_path):
    """A yaw from 150 to 210 degrees crosses qw = 0; forcing qw >= 0 wrote q then about -q on
    neighbouring rows (their linear midpoint was no rotation at all).  Oracles: the rotation each
    row stands for (scipy), and the sign of neighbouring rows' dot products."""
    angles = np.radians(np.linspace(150.0, 210.0, 31))
    rotations = Rotation.from_euler("y", angles[:, None]).as_matrix()
    poses = make_pose(torch.as_tensor(rotations), torch.zeros(31, 3, dtype=torch.float64)).numpy()
    data.write_tum_trajectory(tmp_path / "turn.txt", 1.5e9 + np.arange(31) / 30.0, poses)
    rows = np.loadtxt(tmp_path / "turn.txt")
    quaternions = rows[:, 4:8]
    assert np.all(np.sum(quaternions[1:] * quaternions[:-1], axis=1) > 0.99)
    assert quaternions[0, 3] >= 0
    assert np.allclose(Rotation.from_quat(quaternions).as_matrix(), rotations, atol=1e-8)
    controls = torch.as_tensor(Rotation.from_euler("y", np.radians(np.linspace(140.0, 220.0, 8))[:, None]).as_matrix())
    trajectory = BSplineTrajectory(controls, torch.zeros(8, 3, dtype=torch.float64), 0.25, 100.0 - 0.5)
    start, end = trajectory.domain()
    state = SimpleNamespace(trajectory=trajectory, timestamps=np.array([start, end - 0.01]), done=2)
    exported = export_continuous(state, 100.0, tmp_path / "export.txt")[:, 4:8]
    assert np.all(np.sum(exported[1:] * exported[:-1], axis=1) > 0.99) and exported[0, 3] >= 0
    assert np.allclose(Rotation.from_quat(exported).as_matrix(),
                       trajectory.evaluate(np.loadtxt(tmp_path / "export.txt")[:, 0]).rotation.numpy(), atol=1e-8)


def test_exported_columns_follow_a_moving_spline(tmp_path):
    """A spline that moves and turns on every axis, exported at 400 Hz.  The columns are t, the
    camera-to-world position (world, m), its quaternion (x, y, z, w), the world-frame velocity
    (m/s) and the body-frame angular velocity (rad/s) (docs/cli.md).  Oracles: the spline evaluated
    at the written times (columns 1-7, quaternions read with scipy), and central differences of the
    written poses themselves, h = 1 / 400 s: v_world = (p_{i+1} - p_{i-1}) / 2h and w_body =
    Log(R_{i-1}^T R_{i+1}) / 2h (scipy's rotation vector).  Both are second order in h: the
    position's error is at most h^2 / 6 max|p'''|, p''' = (P_{k+3} - 3 P_{k+2} + 3 P_{k+1} - P_k) /
    dt^3 of the control points (1.2e-5 m/s here), the rotation's is of the same order, and the
    file's 1e-9 rounding adds 1e-9 / h = 4e-7; the tolerance 1e-4 is eight times that.  Swapping two
    position columns (x and y differ by about 1 m) or the v and w blocks (|v| exceeds |w| by 0.3 and
    more on every row) misses by far more."""
    dt, n_ctrl, rate = 0.25, 8, 400.0
    k = torch.arange(n_ctrl, dtype=torch.float64)[:, None]
    offset = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    translations = offset + torch.cat([0.3 * k, -0.2 * k + 0.05 * k**2, 0.1 * torch.sin(1.3 * k)], dim=1)
    rotvecs = torch.cat([0.15 * k, 0.1 * torch.cos(k), -0.08 * k + 0.02 * k**2], dim=1)
    trajectory = BSplineTrajectory(torch.as_tensor(Rotation.from_rotvec(rotvecs.numpy()).as_matrix()), translations, dt,
                                   100.0 - 0.5)
    start, end = trajectory.domain()
    state = SimpleNamespace(trajectory=trajectory, timestamps=np.array([start, end - 0.01]), done=2)
    export_continuous(state, rate, tmp_path / "export.txt")
    rows = np.loadtxt(tmp_path / "export.txt")
    times, positions, rotations = rows[:, 0], rows[:, 1:4], Rotation.from_quat(rows[:, 4:8])
    evaluated = trajectory.evaluate(times)
    assert np.allclose(positions, evaluated.translation.numpy(), rtol=0, atol=2e-9)
    assert np.allclose(rotations.as_matrix(), evaluated.rotation.numpy(), atol=1e-8)
    jerk = (translations[3:] - 3 * translations[2:-1] + 3 * translations[1:-2] - translations[:-3]) / dt**3
    step = 1.0 / rate
    assert np.allclose(np.diff(times), step, rtol=0, atol=1e-9)
    assert step**2 / 6 * float(jerk.norm(dim=-1).max()) < 1.25e-5  # the bound of the position's difference
    velocity = (positions[2:] - positions[:-2]) / (2 * step)
    omega = (rotations[:-2].inv() * rotations[2:]).as_rotvec() / (2 * step)
    speed_gap = np.linalg.norm(velocity, axis=1) - np.linalg.norm(omega, axis=1)
    assert np.linalg.norm(omega, axis=1).min() > 0.6 and speed_gap.min() > 0.3, speed_gap.min()  # turns; v, w unlike
    assert np.abs(rows[1:-1, 8:11] - velocity).max() < 1e-4
    assert np.abs(rows[1:-1, 11:14] - omega).max() < 1e-4


def test_the_trajectory_written_during_a_run_has_each_processed_frame_with_its_own_stamp(tmp_path):
    """run_outputs.write_partial_outputs after 3 of 5 frames (a Co-SLAM state): 3 lines in the
    TUM format "t tx ty tz qx qy qz qw", each frame's own time stamp and camera-to-world pose.
    Oracle: the poses built here and scipy's (x, y, z, w) quaternions, read back with np.loadtxt."""
    rotations = Rotation.from_rotvec([[0.1 * i, -0.2, 0.05 * i] for i in range(5)])
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, :3, :3] = rotations.as_matrix()
    poses[:, :3, 3] = [[i, 2.0 * i, -0.5 * i] for i in range(5)]
    state = SimpleNamespace(cfg=SimpleNamespace(method="coslam"), frame_poses=torch.from_numpy(poses), done=3,
                            relative_to_keyframe={}, keyframe_of_frame={}, timestamps=STAMP + 0.1 * np.arange(5), log=[])
    write_partial_outputs(state, tmp_path)
    rows = np.loadtxt(tmp_path / "trajectory.txt", ndmin=2)
    assert rows.shape == (3, 8)
    assert np.allclose(rows[:, 0], STAMP + 0.1 * np.arange(3), rtol=0, atol=1e-6)
    assert np.allclose(rows[:, 1:4], poses[:3, :3, 3], atol=1e-9)
    expected = rotations.as_quat()[:3]
    assert np.allclose(np.abs(np.sum(rows[:, 4:] * expected, axis=1)), 1.0, atol=1e-9)  # q or -q


@pytest.mark.parametrize("span, rate, rows", [(0.3, 2.0, 1), (0.5, 2.0, 2), (0.3, 10.0, 4), (0.0, 30.0, 1)])
def test_a_run_warns_before_it_starts_when_the_export_would_hold_one_row(capsys, span, rate, rows):
    """Rows counted by hand: times 0, 1/rate, ... up to the last frame (the span) included."""
    from tsslam_ref import run

    run._note_sparse_export(rate, 1.3e9 + np.array([0.0, span]))
    err = capsys.readouterr().err
    assert (f"will hold {rows} row" in err) == (rows < 2), err


def test_the_spline_summary_lists_the_intervals_of_uneven_knots():
    """Knots pushed at chosen times (the oracle): 7 control points, paper convention -> 4 intervals
    from the start time, each as long as the gap pushed."""
    from tsslam_ref.run_summaries import spline_summary

    trajectory = BSplineTrajectory.empty(STAMP, 0.3, torch.zeros(1, dtype=torch.float64))
    gaps = [0.3, 0.3, 0.3, 0.1, 0.2, 0.4]  # t_1 - t_0, ...: the intervals of the domain are the last four
    knots = STAMP - 0.6 + np.concatenate([[0.0], np.cumsum(gaps)])
    for time in knots:
        trajectory.push_back(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), knot_time=time)
    summary = spline_summary(trajectory, "adaptive")
    assert summary["intervals"] == 4 and summary["knots"] == "adaptive"
    np.testing.assert_allclose(np.diff(summary["interval_boundaries_s"]), [0.3, 0.1, 0.2, 0.4], atol=1e-6)
    assert (summary["interval_min_s"], summary["interval_max_s"]) == pytest.approx((0.1, 0.4), abs=1e-6)


def test_the_trajectory_figure_draws_the_estimate_aligned_as_the_ate_aligns_it_on_equal_axes():
    """An estimate that is the ground truth turned 90 degrees and shifted: aligned, its curve lies on the
    ground truth's (the oracle: the planted positions); the axes span one common length."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tsslam_ref import run_outputs, trajectory_metrics

    t = np.linspace(0.0, 1.0, 20)
    gt = np.tile(np.eye(4), (20, 1, 1))
    gt[:, :3, 3] = np.stack([t, 0.1 * np.sin(6 * t), 0.02 * t], axis=1)  # a flat, wide path: x spans 50x z
    turn = make_pose(torch.from_numpy(Rotation.from_euler("z", 90, degrees=True).as_matrix()), torch.tensor([3.0, 0, 0]))
    estimate = turn.double().numpy() @ gt
    known = np.ones(20, dtype=bool)
    result = trajectory_metrics.ate(gt, estimate)
    figure = run_outputs._trajectory_figure(plt, estimate[:, :3, 3], (gt, known), result)
    axis = figure.axes[0]
    drawn = np.array(axis.lines[0].get_data_3d()).T
    np.testing.assert_allclose(drawn, gt[:, :3, 3], atol=1e-9)
    spans = [np.diff(limits)[0] for limits in (axis.get_xlim(), axis.get_ylim(), axis.get_zlim())]
    assert spans == pytest.approx([spans[0]] * 3) and "aligned as for the ATE" in axis.get_title()
    plt.close(figure)
