"""Knot policy: interval lengths from tracked motion, checked against hand-derived expectations."""

import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import config, knot_policy, knot_schedule
from tsslam_ref.trajectory import BSplineTrajectory

ARGS = dict(dt_min=0.05, dt_max=0.4, rotation_tolerance=0.005, position_tolerance=0.005)


def _track(angle_fn, position_fn, n=7, rate=30.0):
    times = np.arange(n) / rate
    rotations = Rotation.from_rotvec(np.stack([[0.0, 0.0, angle_fn(t)] for t in times])).as_matrix()
    positions = np.stack([position_fn(t) for t in times])
    return times, rotations, positions


def test_constant_velocity_gives_dt_max():
    track = _track(lambda t: 0.8 * t, lambda t: np.array([0.3 * t, -0.1 * t, 0.05 * t]))
    assert knot_policy.next_interval(*track, **ARGS) == ARGS["dt_max"]


def test_known_linear_acceleration_matches_formula():
    # x = a t²/2 with a = 2 m/s²: exact second difference, so h = sqrt(6 ε / a)
    track = _track(lambda t: 0.0, lambda t: np.array([t * t, 0.0, 0.0]))
    angular, linear = knot_policy.tracked_accelerations(*track)
    assert angular == pytest.approx(0.0, abs=1e-9) and linear == pytest.approx(2.0, rel=1e-9)
    assert knot_policy.next_interval(*track, **ARGS) == pytest.approx(np.sqrt(6 * 0.005 / 2.0), rel=1e-9)


def test_sharp_turn_shortens_interval_and_stays_in_bounds():
    steady = _track(lambda t: 0.5 * t, lambda t: np.zeros(3))
    turn = _track(lambda t: 2.0 * t * t, lambda t: np.zeros(3))   # 4 rad/s² angular acceleration
    violent = _track(lambda t: 100.0 * t * t, lambda t: np.zeros(3))
    lengths = [knot_policy.next_interval(*x, **ARGS) for x in (steady, turn, violent)]
    assert lengths[0] > lengths[1] > lengths[2]
    assert lengths[1] == pytest.approx(np.sqrt(6 * 0.005 / 4.0), rel=1e-6)
    assert lengths[2] == ARGS["dt_min"]
    assert all(ARGS["dt_min"] <= h <= ARGS["dt_max"] for h in lengths)


def test_the_peak_acceleration_of_a_longer_track_is_its_largest_not_its_mean():
    """One jolt among ten second differences: the turn starts at frame 6 (0 -> 1.2 rad/s in one
    frame spacing, 36 rad/s²), the motion at frame 3 (0 -> 0.3 m/s, 9 m/s²); all else is steady.
    By hand the peaks are 36 and 9 (their means over the track would be 3.6 and 0.9)."""
    track = _track(lambda t: 1.2 * max(0.0, t - 6 / 30), lambda t: np.array([0.3 * max(0.0, t - 3 / 30), 0.0, 0.0]),
                   n=12)
    angular, linear = knot_policy.tracked_accelerations(*track)
    assert angular == pytest.approx(36.0, rel=1e-9) and linear == pytest.approx(9.0, rel=1e-9)
    assert knot_policy.next_interval(*track, **ARGS) == ARGS["dt_min"]  # sqrt(6 * 0.005 / 36) = 0.029 s


def test_bad_input_names_value():
    track = _track(lambda t: 0.0, lambda t: np.zeros(3))
    with pytest.raises(ValueError, match="dt_min"):
        knot_policy.next_interval(*track, **{**ARGS, "dt_min": 0.5})
    with pytest.raises(ValueError, match="strictly increasing"):
        knot_policy.next_interval(track[0][::-1].copy(), *track[1:], **ARGS)


def test_interval_scale_samples_are_first_middle_last_or_none():
    times = 2.0 + np.arange(10) / 30.0
    assert knot_policy.interval_scale_samples(times, 0.1).tolist() == [0, 4, 9]  # 4 and 5 tie: the first
    assert knot_policy.interval_scale_samples(times, 0.5).size == 0  # spans 0.3 s < 0.5 s
    assert knot_policy.interval_scale_samples(times[:2], 0.01).size == 0


def test_interval_scale_samples_see_a_known_acceleration_without_the_frame_noise():
    """x = a t²/2 plus 1 mm tracking noise: frame-spacing differences report tens of m/s², the
    interval-scale samples the true 2 m/s² within the noise's (h/Δ)²-smaller effect."""
    rng = np.random.default_rng(0)
    track = _track(lambda t: 0.0, lambda t: np.array([t * t, 0.0, 0.0]), n=19)
    noisy = (track[0], track[1], track[2] + 0.001 * rng.standard_normal(track[2].shape))
    assert knot_policy.tracked_accelerations(*noisy)[1] > 5.0
    pick = knot_policy.interval_scale_samples(noisy[0], 0.3)
    linear = knot_policy.tracked_accelerations(*(array[pick] for array in noisy))[1]
    assert abs(linear - 2.0) < 0.5, linear


def test_place_knots_follows_the_motion_and_covers_every_time():
    # 1 s at constant angular velocity, then 1 s turning with angular acceleration 8 rad/s^2:
    # hand-derived interval lengths: dt_max while steady, sqrt(6 * 0.005 / 8) = 0.061 -> dt_min in the turn
    rate, steady = 30.0, 1.0

    def angle(t):
        return 0.5 * t + (4.0 * (t - steady) ** 2 if t > steady else 0.0)

    times, rotations, positions = _track(angle, lambda t: np.zeros(3), n=60, rate=rate)
    args = dict(ARGS, dt_min=0.1)
    ends = knot_policy.place_knots(times, rotations, positions, 0.3, **args)
    lengths = np.diff(ends)
    assert ends[0] == times[0] and ends[-2] <= times[-1] < ends[-1]
    assert lengths[0] == 0.3
    steady_lengths = lengths[(ends[1:] < steady - 0.1) & (np.arange(len(lengths)) > 0)]
    turn_lengths = lengths[ends[:-1] > steady + 0.4]
    half_frame = 0.5 / rate  # knots move to a quarter frame after the nearest frame
    assert steady_lengths.size and np.all(np.abs(steady_lengths - args["dt_max"]) <= half_frame + 1e-12)
    assert turn_lengths.size and np.all(np.abs(turn_lengths - args["dt_min"]) <= half_frame + 1e-12)


def test_planned_knots_sit_a_quarter_frame_after_a_frame():
    """Every knot after the first interval lands 1/4 of the frame spacing after a frame time, also
    with timestamp jitter (the knot follows the median spacing), so each interval's last frame is
    near its end, where the newest control point's weight u^3/6 is largest."""
    rng = np.random.default_rng(1)
    rate = 30.0
    times, rotations, positions = _track(lambda t: 0.5 * t + 3.0 * t * t, lambda t: np.array([t, 0.0, 0.0]),
                                         n=90, rate=rate)
    jittered = times + rng.uniform(-0.002, 0.002, times.shape)
    for stamps, tolerance in ((times, 1e-9), (jittered, 0.24 / rate)):  # jittered: 0 < knot - frame < 1/2 frame
        ends = knot_policy.place_knots(stamps, rotations, positions, 0.3, **dict(ARGS, dt_min=0.1))
        for knot in ends[2:-1]:
            before = stamps[stamps < knot].max()
            assert abs((knot - before) - 0.25 / rate) <= tolerance, (knot, before)
        last_u = [(stamps[(stamps >= a) & (stamps < b)].max() - a) / (b - a) for a, b in zip(ends[1:-2], ends[2:-1])]
        assert min(last_u) > 0.85  # a knot on a frame would leave u <= 2/3 at three frames per interval


def test_snap_after_frame_hand_computed():
    times = np.arange(10) / 30.0  # frames at k/30 s; the last before 0.3 s is 8/30
    assert knot_policy.snap_after_frame(times, 0.3, 0.4) == pytest.approx(8 / 30 + 4.25 / 30)
    assert knot_policy.snap_after_frame(times, 0.3, 0.2) == pytest.approx(8 / 30 + 1.25 / 30)  # never before end
    assert knot_policy.snap_after_frame(times[:1], 0.3, 0.37) == 0.37  # one frame: no spacing known


def test_place_knots_names_bad_input():
    times, rotations, positions = _track(lambda t: t, lambda t: np.zeros(3), n=10)
    with pytest.raises(ValueError, match="first_interval"):
        knot_policy.place_knots(times, rotations, positions, 0.0, **ARGS)
    times[4] = times[3]
    with pytest.raises(ValueError, match=r"times\[3\]"):
        knot_policy.place_knots(times, rotations, positions, 0.3, **ARGS)


def test_frames_further_apart_than_the_uniform_knot_spacing_are_refused():
    """An interval without a frame leaves its control point to extrapolation and a fit with no data
    (the curve rings): a gap longer than the shortest interval is refused, naming it and the way out."""
    cfg = config.tiny()
    cfg.method, cfg.spline.dt = "tsslam", 0.3
    times = 1341841873.0 + np.array([0.0, 0.1, 0.2, 0.55, 0.6])
    with pytest.raises(ValueError, match=r"frames 2 and 3 .* 0\.350 s apart, more than spline\.dt = 0\.3 s.*spline\.dt=0\.35"):
        knot_schedule.check_frame_spacing(cfg, times)
    knot_schedule.check_frame_spacing(cfg, times[:3])  # 0.1 s apart: fine
    cfg.spline.knots, cfg.spline.dt_min = "adaptive", 0.1  # its shortest interval: the 0.35 s gap is refused too
    with pytest.raises(ValueError, match=r"more than the shortest adaptive interval, min\(spline\.dt, spline\.dt_min\) = 0\.1 s"
                                         r".*--set spline\.dt_min=0\.35 --set spline\.dt=0\.35"):
        knot_schedule.check_frame_spacing(cfg, times)
    cfg.spline.dt_min = cfg.spline.dt = 0.35
    knot_schedule.check_frame_spacing(cfg, times)
    five_hz = 1341841873.0 + np.arange(12) / 5.0  # no gap over dt = 0.25 s, but 1.25 frames per interval
    cfg = config.tiny()
    cfg.method, cfg.spline.dt = "tsslam", 0.25
    with pytest.raises(ValueError, match=r"0\.200 s apart \(median\), more than half of spline\.dt = 0\.25 s.*spline\.dt=0\.4"):
        knot_schedule.check_frame_spacing(cfg, five_hz)
    cfg.spline.dt = 0.4
    knot_schedule.check_frame_spacing(cfg, five_hz)
    for key, value in (("method", "coslam"), ("use_spline", False), ("dt", 0.7)):
        other = config.tiny()
        other.method, other.spline.dt = "tsslam", 0.3
        section = other if key == "method" else other.local_ba if key == "use_spline" else other.spline
        setattr(section, key, value)
        knot_schedule.check_frame_spacing(other, times)
    milliseconds = np.array([0.0, 33.0, 67.0, 100.0])  # stamps in ms read as s: no dt can span 33 s
    with pytest.raises(ValueError, match=r"34\.000 s apart.*spline\.dt at most 10 s\): check the time stamps "
                                         r"\(milliseconds read as seconds\?\)") as refused:
        knot_schedule.check_frame_spacing(config.tiny(), milliseconds)
    assert "--set spline.dt=" not in str(refused.value)  # not a value the config would refuse in turn


def brute_force_sparse_stretch(times, span, limit):
    """sparse_stretch's oracle: every stretch's sorted gaps, one stretch at a time, and their (lower) median."""
    whole = [(first, int(np.searchsorted(times, times[first] + span, side="right")) - 1)
             for first in range(len(times) - 1) if times[first] + span <= times[-1]] or [(0, len(times) - 1)]
    for first, last in whole:
        gaps = np.sort(np.diff(times[first:last + 1]))
        if len(gaps) and gaps[(len(gaps) - 1) // 2] > limit:  # a stretch without a gap: one longer than span
            return first, last
    return None


def test_a_recording_that_slows_down_for_a_while_is_refused_where_it_does():
    """30 Hz frames, then 5 Hz for 12 frames (no gap over dt = 0.25 s, a 30 Hz median): the median
    over the whole recording passed it, and TS-SLAM ended metres off with exit 0.  Oracle: the
    brute-force median of every stretch of 3 x dt (the curve approximation's span), which must
    agree with sparse_stretch on these and on jittered, holed and random recordings."""
    cfg = config.tiny()
    cfg.method, cfg.spline.dt = "tsslam", 0.25
    assert cfg.local_ba.fit_controls == 3
    thirty = np.arange(20) / 30.0
    slowing = 1341841873.0 + np.concatenate([thirty, thirty[-1] + 0.2 * np.arange(1, 13)])
    expected = brute_force_sparse_stretch(slowing, 0.75, 0.125)
    assert expected is not None and expected[1] > 19  # the stretch reaches into the 5 Hz frames
    first, last = expected
    with pytest.raises(ValueError, match=rf"frames {first} to {last} \(t = .*\) are 0\.200 s apart \(median\), more than "
                                         r"half of spline\.dt = 0\.25 s.*spline\.dt=0\.4"):
        knot_schedule.check_frame_spacing(cfg, slowing)
    adaptive = config.apply_overrides(cfg, ["spline.knots=adaptive", "spline.dt_min=0.1"])
    ten_hz_after = 1341841873.0 + np.concatenate([thirty, thirty[-1] + 0.0999 * np.arange(1, 16)])
    with pytest.raises(ValueError, match=r"0\.100 s apart \(median\), more than half of the shortest adaptive"):
        knot_schedule.check_frame_spacing(adaptive, ten_hz_after)
    rng = np.random.default_rng(0)
    holed = np.delete(np.arange(60) / 30.0, np.arange(20, 26))  # six frames dropped: one 0.233 s gap
    jittered = np.arange(60) / 30.0 + rng.uniform(-0.01, 0.01, 60)
    knot_schedule.check_frame_spacing(cfg, 1341841873.0 + holed)
    knot_schedule.check_frame_spacing(cfg, 1341841873.0 + jittered)
    for times in (slowing, ten_hz_after, holed, jittered, *(np.cumsum(rng.exponential(0.08, 40)) for _ in range(50))):
        for span, limit in ((0.75, 0.125), (0.3, 0.05), (5.0, 0.1)):
            assert knot_schedule.sparse_stretch(times, span, limit) == brute_force_sparse_stretch(times, span, limit)


def test_a_gap_opened_by_frames_without_ground_truth_or_a_pause_is_named_as_such():
    """A refusal after frames without a ground-truth pose were left out blamed a gap the recording
    does not have and suggested a longer spline.dt; a pause of 1.5 s suggested spline.dt = 1.55,
    which runs with TS-SLAM's RPE above the baseline's.  Both now name the better way out."""
    cfg = config.tiny()
    cfg.method, cfg.spline.dt = "tsslam", 0.25
    recorded = 1341841873.0 + np.arange(40) / 30.0
    holed, left_out = np.delete(recorded, np.arange(10, 19)), recorded[10:19]
    with pytest.raises(ValueError, match=r"9 frame\(s\) without a ground-truth pose were left out there.*"
                                         r"--set data\.require_gt=false keeps them"):
        knot_schedule.check_frame_spacing(cfg, holed, left_out)
    before_frame_0 = recorded[0] - np.arange(1, 5) / 30.0  # as the bundled slice's four: they open no gap
    with pytest.raises(ValueError) as refused:
        knot_schedule.check_frame_spacing(cfg, holed, before_frame_0)
    assert "ground-truth" not in str(refused.value)
    with pytest.raises(ValueError, match=r"0\.433 s apart.*a smaller --frames step than 13 brings them closer, or use "
                                         r"--set spline\.dt=0\.45"):
        knot_schedule.check_frame_spacing(cfg, recorded[::13], frame_step=13)
    adaptive = config.apply_overrides(cfg, ["spline.knots=adaptive"])
    with pytest.raises(ValueError, match=r"--set spline\.dt_max=0\.9 \(or more\)") as refused:
        knot_schedule.check_frame_spacing(adaptive, recorded[::13])
    suggested = re.findall(r"--set (spline\.\w+=[\d.]+)", str(refused.value))  # dt_min above dt_max was refused
    following = config.apply_overrides(adaptive, suggested)
    knot_schedule.check_knot_settings(following)
    knot_schedule.check_frame_spacing(following, recorded[::13])
    paused = 1341841873.0 + np.concatenate([np.arange(15) / 30.0, 14 / 30.0 + 1.536 + np.arange(15) / 30.0])
    with pytest.raises(ValueError, match=r"1\.536 s apart.*cut the sequence at the gap \(--frames on each side of it\) or "
                                         r"use --method coslam; --set spline\.dt=1\.55 \(or more\) would run, but "
                                         r"intervals over 0\.4 s no longer follow"):
        knot_schedule.check_frame_spacing(cfg, paused)


def test_unevenly_spaced_samples_recover_a_known_acceleration():
    """interval_scale_samples picks first, middle and last of an even count of frames, so the two
    steps differ (4 and 5 frame spacings for 10 frames).  For x = a t²/2 the second difference over
    the mean of the two steps is exact: hand-derived a = 2 m/s² and 4 rad/s², h = sqrt(6 ε / 4)."""
    times = np.array([0.0, 0.1, 0.35])
    rotations = Rotation.from_rotvec(np.stack([[0.0, 2.0 * t * t, 0.0] for t in times])).as_matrix()
    positions = np.stack([[0.0, 0.0, t * t] for t in times])
    angular, linear = knot_policy.tracked_accelerations(times, rotations, positions)
    assert angular == pytest.approx(4.0, rel=1e-9) and linear == pytest.approx(2.0, rel=1e-9)
    assert knot_policy.next_interval(times, rotations, positions, **ARGS) == pytest.approx(np.sqrt(6 * 0.005 / 4.0), rel=1e-9)


def test_snap_never_ends_an_interval_before_its_first_predicted_frame():
    """An end within a quarter frame after the last frame (the first interval's end is not snapped):
    frames at k/30 s, end 0.27 s, last frame before it 8/30 s.  The next predicted frame is 9/30 s,
    so the earliest knot is 9/30 + 1/120 s; 8/30 + 1/120 = 0.275 s would leave [0.27, 0.275) without a frame."""
    times = np.arange(10) / 30.0
    for target in (0.28, 0.3, 0.31):
        assert knot_policy.snap_after_frame(times, 0.27, target) == pytest.approx(9 / 30 + 0.25 / 30, abs=1e-12)
    assert knot_policy.snap_after_frame(times, 0.27, 0.36) == pytest.approx(11 / 30 + 0.25 / 30, abs=1e-12)


def test_adaptive_frame_spacing_check_uses_the_first_interval_when_it_is_the_shortest():
    """Adaptive knots start with an interval of spline.dt: with dt = 0.2 s below dt_min = 0.3 s, a
    0.25 s gap can leave that first interval without a frame, so it is refused naming 0.2 s."""
    cfg = config.tiny()
    cfg.method, cfg.spline.knots = "tsslam", "adaptive"
    cfg.spline.dt, cfg.spline.dt_min, cfg.spline.dt_max = 0.2, 0.3, 0.4
    times = 1341841873.0 + np.array([0.0, 0.1, 0.35, 0.45])
    with pytest.raises(ValueError, match=r"frames 1 and 2 .* 0\.250 s apart, more than the shortest adaptive interval, "
                                         r"min\(spline\.dt, spline\.dt_min\) = 0\.2 s"):
        knot_schedule.check_frame_spacing(cfg, times)
    cfg.spline.dt = 0.26
    knot_schedule.check_frame_spacing(cfg, times)


def test_adaptive_knots_need_two_frames_per_shortest_interval_as_uniform_knots_do():
    """12 Hz frames (0.083 s apart) with dt_min = 0.1 s: no gap exceeds the shortest interval, but the
    intervals snapped one frame each and the policy, short of frames, kept that length to the end
    (the curve between frames ran tens of metres off, exit 0).  Refused; 2 x 0.083 s -> 0.2 s."""
    cfg = config.tiny()
    cfg.method, cfg.spline.knots = "tsslam", "adaptive"
    cfg.spline.dt, cfg.spline.dt_min, cfg.spline.dt_max = 0.3, 0.1, 0.4
    twelve_hz = 1341841873.0 + np.arange(16) / 12.0
    with pytest.raises(ValueError, match=r"0\.083 s apart \(median\), more than half of the shortest adaptive interval, "
                                         r"min\(spline\.dt, spline\.dt_min\) = 0\.1 s.*--set spline\.dt_min=0\.2 "
                                         r"--set spline\.dt=0\.3"):
        knot_schedule.check_frame_spacing(cfg, twelve_hz)
    knot_schedule.check_frame_spacing(cfg, 1341841873.0 + np.arange(16) / 20.0)  # 20 Hz: two frames per 0.1 s
    thirty_hz = 1341841873.0 + np.arange(16) / 30.0
    cfg.spline.dt_min = 0.04  # one frame per 0.04 s interval at 30 Hz
    with pytest.raises(ValueError, match=r"0\.033 s apart \(median\).*--set spline\.dt_min=0\.1 "):
        knot_schedule.check_frame_spacing(cfg, thirty_hz)
    cfg.spline.dt_min = 0.01  # a gap over the shortest interval: the suggestion holds two frames, not one
    with pytest.raises(ValueError, match=r"0\.033 s apart, more than the shortest adaptive interval.*"
                                         r"--set spline\.dt_min=0\.1 "):
        knot_schedule.check_frame_spacing(cfg, thirty_hz)


def test_snap_uses_the_median_frame_spacing_across_a_dropped_frame():
    """Frames at k/30 s with frame 5 dropped: the spacing is still 1/30 s (median; the mean would be
    0.0375 s), so the knot nearest 0.4 s after an end at 0.3 s is 8/30 + 4.25/30 s, by hand."""
    times = np.delete(np.arange(10) / 30.0, 5)
    assert knot_policy.snap_after_frame(times, 0.3, 0.4) == pytest.approx(8 / 30 + 4.25 / 30, abs=1e-12)


def test_frame_spacing_check_finds_a_gap_after_the_first_frame():
    """The largest gap can be the very first one (a slow start): frames 0 and 1, 0.4 s apart, are
    refused with spline.dt = 0.3 s."""
    cfg = config.tiny()
    cfg.method, cfg.spline.dt = "tsslam", 0.3
    times = 1341841873.0 + np.array([0.0, 0.4, 0.5, 0.6, 0.7])
    with pytest.raises(ValueError, match=r"frames 0 and 1 .* 0\.400 s apart, more than spline\.dt = 0\.3 s"):
        knot_schedule.check_frame_spacing(cfg, times)


def test_plan_next_interval_reads_the_stored_poses_of_the_last_two_intervals():
    """The loop's planning step on a hand-made state: frames at k/30 s, intervals 0 = [0, 0.3) and
    1 = [0.3, 0.6), frame 18 (t = 0.6 s) completes interval 1; the camera rests, then moves as
    x = (t - 0.3)².  By hand, from frames 0, 8, 17 (first, middle, last of both intervals):
    x = 0, 0, (8/30)², a = ((8/30)² / (9/30)) / (17/60) = 0.8366 m/s², h = sqrt(6 · 0.004 / a) = 0.1694 s;
    the target 0.7694 s snaps to 17/30 + 1.25/30 + 5/30 = 23.25/30 s.  Reading interval 1 alone
    (a = 2: 21.25/30 s) or dropping frame 0 (a = 1: 22.25/30 s) gives another knot."""
    cfg = config.tiny()
    cfg.spline.dt_min, cfg.spline.dt_max, cfg.spline.position_tolerance = 0.1, 0.4, 0.004
    times = np.arange(30) / 30.0
    poses = torch.eye(4, dtype=torch.float64).repeat(30, 1, 1)
    poses[:, 0, 3] = torch.as_tensor(np.maximum(times - 0.3, 0.0) ** 2)
    poses[19:, :3, 3] = 50.0  # frames after frame 18 are not tracked yet: they must not be read
    planned = []
    ends = [0.0, 0.3, 0.6]
    trajectory = SimpleNamespace(interval=lambda n: (ends[n], ends[n + 1]),
                                 plan_interval_end=lambda n, end, assumed_spacing: planned.append((n, end, assumed_spacing)))
    trajectory.clone = lambda: trajectory
    state = SimpleNamespace(cfg=cfg, trajectory=trajectory, timestamps=times, frame_poses=poses)
    knot_schedule.plan_next_interval(state, 18, 1)
    assert len(planned) == 1 and planned[0][0] == 2
    assert planned[0][1] == pytest.approx(23.25 / 30, abs=1e-9)
    assert planned[0][2] == pytest.approx(23.25 / 30 - 0.6, abs=1e-9)


def test_planning_the_next_interval_leaves_the_spline_it_read_unchanged():
    """With --parallel the mapping thread plans on a view of the state whose spline the tracking
    thread reads under the lock; the plan changed that spline in place, outside the lock.  Oracle:
    the read spline's knots before and after, and the planned end by hand (the test above)."""
    cfg = config.tiny()
    cfg.spline.dt_min, cfg.spline.dt_max, cfg.spline.position_tolerance = 0.1, 0.4, 0.004
    times = np.arange(30) / 30.0
    poses = torch.eye(4, dtype=torch.float64).repeat(30, 1, 1)
    poses[:, 0, 3] = torch.as_tensor(np.maximum(times - 0.3, 0.0) ** 2)
    read = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(5, 1, 1), torch.zeros(5, 3, dtype=torch.float64),
                             0.3, -0.6)  # interval n starts at t0 + (n + 2) dt (the paper's indices)
    assert read.interval(1) == pytest.approx((0.3, 0.6))
    knots_before = read.knot_vector(8).copy()
    state = SimpleNamespace(cfg=cfg, trajectory=read, timestamps=times, frame_poses=poses)
    knot_schedule.plan_next_interval(state, 18, 1)
    np.testing.assert_array_equal(read.knot_vector(8), knots_before)
    assert state.trajectory is not read
    assert state.trajectory.interval(2)[1] == pytest.approx(23.25 / 30, abs=1e-9)


def test_last_interval_end_is_a_quarter_frame_after_the_last_frame_and_never_later_than_planned():
    """Frames every 1/30 s; the last interval is [0.6, 0.9).  By hand: a last frame at 19/30 s gives
    19.25/30 s; one at 26.8/30 s would give 27.05/30 s > 0.9, so the planned 0.9 s stays."""
    times = np.arange(20) / 30.0
    assert knot_policy.last_interval_end(times, 0.6, 0.9) == pytest.approx(19.25 / 30.0, abs=1e-12)
    late = np.append(np.arange(26) / 30.0, 26.8 / 30.0)
    assert knot_policy.last_interval_end(late, 0.6, 0.9) == 0.9
    with pytest.raises(ValueError, match=r"last frame time .* must lie in the interval"):
        knot_policy.last_interval_end(times, 0.7, 0.9)
    with pytest.raises(ValueError, match="at least 2 frame times"):
        knot_policy.last_interval_end(times[:1], 0.0, 0.3)
