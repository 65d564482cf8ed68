"""Knot policy: the length of the next spline interval from the motion tracking has seen.

Extends TS-SLAM §III-B (Eq. 5-7), whose knots are equally spaced (its Sec. V names fixed
intervals as a limitation).  A cubic B-spline whose control points sit on a smooth motion
approximates it with error ≈ h² |a| / 6 over an interval of length h (a = the motion's second
derivative; the B-spline smooths a quadratic by h²/6 of its curvature).  Asking that error to stay
below a tolerance ε gives h = sqrt(6 ε / |a|): slow, steady motion gets long intervals, turns and
jerks get short ones.  The policy applies this separately to rotation (ε_rot in radians, |a| =
angular acceleration) and translation (ε_pos in metres, |a| = linear acceleration), takes the
shorter, and clips to [dt_min, dt_max].

Accelerations come from second finite differences of the most recent tracked poses (world
positions; rotation increments through the SO(3) log).

Where the knot lands between frames matters as much as the length (:func:`snap_after_frame`).
The newest control point reaches the newest interval only through the cumulative weight
B_3(u) = u³/6 (u = the time's fraction of the interval), so the curve approximation can place it
only from the frames near the interval's end.  A knot right on a frame time leaves the interval's
last frame a whole frame spacing before its end: with three frames per interval they sit at
u = 0, 1/3, 2/3, weights 0, 0.006 and 0.049, and tracking noise reaches the newest point
amplified about 20 times (1 / sqrt(Σ B_3²)).  A knot a quarter of a frame spacing after a frame
puts the last frame at u ≈ 0.92 (weight 0.13): about 7 times, what a uniform 0.3 s interval with
nine frames gives.  So each planned end is moved to a quarter frame spacing after the nearest
predicted frame time.  Pure numpy, deterministic.

Layer 1 (math): imports nothing from the package.
"""

from typing import Tuple

import numpy as np
from scipy.spatial.transform import Rotation


def _check_track(times: np.ndarray, rotations: np.ndarray, positions: np.ndarray) -> None:
    """Raise ValueError naming the bad input. times (K,), rotations (K, 3, 3), positions (K, 3)."""
    if times.ndim != 1 or times.shape[0] < 3:
        raise ValueError(f"times must be a 1-D array of at least 3 tracked times, got shape {times.shape}")
    if rotations.shape != (times.shape[0], 3, 3):
        raise ValueError(f"rotations must have shape ({times.shape[0]}, 3, 3), got {rotations.shape}")
    if positions.shape != (times.shape[0], 3):
        raise ValueError(f"positions must have shape ({times.shape[0]}, 3), got {positions.shape}")
    if np.any(np.diff(times) <= 0):
        j = int(np.flatnonzero(np.diff(times) <= 0)[0])
        raise ValueError(f"times must be strictly increasing, got times[{j}] = {times[j]!r} s and "
                         f"times[{j + 1}] = {times[j + 1]!r} s")


def tracked_accelerations(times, rotations, positions) -> Tuple[float, float]:
    """Peak angular (rad/s²) and linear (m/s²) acceleration of a tracked pose sequence.

    times (K,) float64 s, rotations (K, 3, 3) world-from-camera, positions (K, 3) world metres, K ≥ 3.
    Velocities are finite differences between consecutive poses (angular in the body frame via the
    SO(3) log of R_kᵀ R_{k+1}); accelerations are differences of those over the mid-point spacing.
    """
    times = np.asarray(times, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64)
    _check_track(times, rotations, positions)
    step = np.diff(times)                                               # (K-1,)
    relative = np.einsum("kji,kjl->kil", rotations[:-1], rotations[1:])  # R_kᵀ R_{k+1}
    angular_velocity = Rotation.from_matrix(relative).as_rotvec() / step[:, None]
    linear_velocity = np.diff(positions, axis=0) / step[:, None]
    mid_step = 0.5 * (step[:-1] + step[1:])[:, None]
    angular_acc = np.linalg.norm(np.diff(angular_velocity, axis=0) / mid_step, axis=1)
    linear_acc = np.linalg.norm(np.diff(linear_velocity, axis=0) / mid_step, axis=1)
    return float(angular_acc.max()), float(linear_acc.max())


def interval_for_acceleration(acceleration: float, tolerance: float, dt_max: float) -> float:
    """Longest h with h² · acceleration / 6 ≤ tolerance, capped at dt_max (zero acceleration → dt_max)."""
    if acceleration <= 0.0:
        return dt_max
    return min(dt_max, float(np.sqrt(6.0 * tolerance / acceleration)))


def interval_scale_samples(times, interval: float) -> np.ndarray:
    """Indices of at most three of the (K,) increasing ``times``: the first, the last and the one
    nearest their middle, or fewer when they span less than ``interval`` (s) or hold < 3 times.

    Second differences over the frame spacing Δ amplify tracking noise σ to about 4σ/Δ² (several
    m/s² at 30 Hz for millimetre noise); over samples about an interval apart it is (h/Δ)² times
    smaller, and a spline with intervals h cannot follow faster changes anyway.
    """
    times = np.asarray(times, dtype=np.float64)
    if times.shape[0] < 3 or times[-1] - times[0] < interval:
        return np.arange(0)
    middle = int(np.argmin(np.abs(times - 0.5 * (times[0] + times[-1]))))
    if middle in (0, times.shape[0] - 1):
        return np.arange(0)
    return np.array([0, middle, times.shape[0] - 1])


def next_interval(times, rotations, positions, dt_min: float, dt_max: float,
                  rotation_tolerance: float, position_tolerance: float) -> float:
    """Length (s) of the next spline interval, within [dt_min, dt_max].

    times (K,), rotations (K, 3, 3), positions (K, 3): the recent tracked poses (K ≥ 3).
    rotation_tolerance (rad) and position_tolerance (m): the approximation error allowed per interval.
    """
    if not 0.0 < dt_min <= dt_max:
        raise ValueError(f"need 0 < dt_min <= dt_max, got dt_min={dt_min}, dt_max={dt_max}")
    if rotation_tolerance <= 0.0 or position_tolerance <= 0.0:
        raise ValueError(f"tolerances must be > 0, got rotation_tolerance={rotation_tolerance}, "
                         f"position_tolerance={position_tolerance}")
    angular_acc, linear_acc = tracked_accelerations(times, rotations, positions)
    length = min(interval_for_acceleration(angular_acc, rotation_tolerance, dt_max),
                 interval_for_acceleration(linear_acc, position_tolerance, dt_max))
    return float(np.clip(length, dt_min, dt_max))


def interval_from_track(times, rotations, positions, fallback: float, dt_min: float, dt_max: float,
                        rotation_tolerance: float, position_tolerance: float) -> float:
    """Length (s) of the next interval from a tracked stretch: :func:`next_interval` on its
    :func:`interval_scale_samples` (at least ``dt_min`` apart), or ``fallback`` (s) when they are
    too few.  times (K,) float64 s, rotations (K, 3, 3), positions (K, 3); other arguments as in
    :func:`next_interval`."""
    pick = interval_scale_samples(times, dt_min)
    if pick.size < 3:
        return float(fallback)
    return next_interval(np.asarray(times)[pick], np.asarray(rotations)[pick], np.asarray(positions)[pick],
                         dt_min, dt_max, rotation_tolerance, position_tolerance)


def place_knots(times, rotations, positions, first_interval: float, dt_min: float, dt_max: float,
                rotation_tolerance: float, position_tolerance: float) -> np.ndarray:
    """Interval boundaries the online policy would choose along a whole pose sequence (offline).

    The SLAM loop's rule (``knot_schedule``) replayed on given poses: interval 0 starts at the first
    time and is ``first_interval`` (s) long; once interval n is complete, the end of interval n + 1
    is :func:`interval_from_track` of the poses in intervals n - 1 and n (too few: interval n's
    length).  Unlike the loop, which sees tracked poses that mapping has partly smoothed, this
    sees exactly the poses it is given.

    times (K,) increasing float64 s, rotations (K, 3, 3), positions (K, 3); other arguments as in
    :func:`next_interval`.  Returns the (m + 1,) boundaries e_0 = times[0] < ... < e_m, with
    e_m > times[-1], so that the intervals [e_n, e_n+1) cover every time.
    """
    times = np.asarray(times, dtype=np.float64)
    rotations, positions = np.asarray(rotations, dtype=np.float64), np.asarray(positions, dtype=np.float64)
    _check_track(times, rotations, positions)
    if not first_interval > 0:
        raise ValueError(f"first_interval must be > 0 s, got {first_interval}")
    ends = [float(times[0]), float(times[0]) + float(first_interval)]
    while ends[-1] <= times[-1]:
        n = len(ends) - 2  # interval n = [ends[n], ends[n + 1]) is complete
        ends.append(next_interval_end(times, rotations, positions, ends[max(n - 1, 0)], ends[n], ends[n + 1],
                                      dt_min, dt_max, rotation_tolerance, position_tolerance))
    return np.array(ends)


def next_interval_end(times, rotations, positions, previous_start: float, start: float, end: float,
                      dt_min: float, dt_max: float, rotation_tolerance: float, position_tolerance: float) -> float:
    """End (s) of the interval after [start, end): end + :func:`interval_from_track` of the poses in
    [previous_start, end) (intervals n - 1 and n), falling back to end - start, moved to a quarter
    frame after the nearest predicted frame (:func:`snap_after_frame`).  The one rule of the SLAM
    loop (``knot_schedule``) and of :func:`place_knots`.  times (K,) s, rotations (K, 3, 3),
    positions (K, 3): every pose known so far; other arguments as in :func:`next_interval`."""
    times = np.asarray(times, dtype=np.float64)
    inside = (times >= previous_start) & (times < end)
    length = interval_from_track(times[inside], np.asarray(rotations)[inside], np.asarray(positions)[inside],
                                 end - start, dt_min, dt_max, rotation_tolerance, position_tolerance)
    return snap_after_frame(times[inside], end, end + length)


SNAP_FRACTION = 0.25
"""Where a planned knot sits after the frame it follows, in frame spacings: far enough after it
that timestamp jitter of a few milliseconds (TUM: under 1/8 of a 30 Hz spacing) keeps the frame
inside its interval, close enough that the frame's weight on the newest control point stays near
its largest, 1/6 (module docstring)."""


def median_frame_spacing(times: np.ndarray, name: str) -> float:
    """The median spacing (s) of increasing frame times (K,), K >= 2; ValueError naming ``name``
    when it is not positive."""
    spacing = float(np.median(np.diff(times)))
    if not spacing > 0:
        raise ValueError(f"{name} must be strictly increasing, got median spacing {spacing!r} s")
    return spacing


def snap_after_frame(recent_times, end: float, target: float) -> float:
    """The knot time (s) nearest ``target`` of the form t_last + (j + 1/4) Δ, j >= 1 (t_last: the
    last of ``recent_times`` before ``end``; Δ: their median spacing), so that the interval
    [end, knot) ends a quarter frame after a predicted frame.  ``target`` itself when fewer than
    two recent times are known.  recent_times (K,) increasing float64 s; end, target float s,
    target > end.  Returns a time > end."""
    recent_times = np.asarray(recent_times, dtype=np.float64)
    recent_times = recent_times[recent_times < end]
    if recent_times.shape[0] < 2:
        return float(target)
    spacing = median_frame_spacing(recent_times, "recent_times")
    last = float(recent_times[-1])
    first_candidate = last + (1.0 + SNAP_FRACTION) * spacing
    while first_candidate <= end:  # a gap in the recent frames: predicted frames start after end
        first_candidate += spacing
    steps = max(0, int(np.round((target - first_candidate) / spacing)))
    return first_candidate + steps * spacing


def last_interval_end(times, start: float, end: float) -> float:
    """Where the run's last, incomplete interval [start, end) should end once no frame will close it:
    a quarter frame spacing after its last frame (the spacing: the median of ``times``), never
    later than ``end``.  The last frames then sit near u = 1 of the interval instead of where the
    planned end leaves them (u ≈ 0.55 for 60 frames at 30 Hz with 0.3 s intervals, weight
    B_3 = 0.03), so the new control point is fitted through a weight near the uniform 1/6
    (module docstring).  times (K,) increasing float64 s, K >= 2, the last one in [start, end).
    Returns a time in (t_last, end]."""
    times = np.asarray(times, dtype=np.float64)
    if times.ndim != 1 or times.shape[0] < 2:
        raise ValueError(f"times must be a 1-D array of at least 2 frame times, got shape {times.shape}")
    spacing = median_frame_spacing(times, "times")
    last = float(times[-1])
    if not start <= last < end:
        raise ValueError(f"the last frame time {last!r} s must lie in the interval [{start!r}, {end!r}) s")
    return min(float(end), last + SNAP_FRACTION * spacing)
