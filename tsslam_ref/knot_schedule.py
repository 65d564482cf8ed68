"""Where the SLAM loop's spline intervals end: the knot policy wired into TS-SLAM's schedule (ours).

TS-SLAM (Sec. III-B, Fig. 2) maps one interval of a uniform spline every Δt of sequence time;
its Sec. V names the fixed Δt as a limitation.  With ``spline.knots = "adaptive"`` the loop
(``slam.map_interval``) calls :func:`plan_next_interval` when a frame completes interval n, before
that interval's control point is added: the end of interval n + 1 is set on the trajectory
(:meth:`trajectory.BSplineTrajectory.plan_interval_end`) from the motion tracked over intervals
n - 1 and n (:mod:`tsslam_ref.knot_policy`).  So the next mapping step is triggered, and its
control point placed, by the motion; the first interval is ``spline.dt`` long.  With the default
``"uniform"`` nothing here runs.  With ``spline.last_interval = "last_frame"`` (the default, either
knot type) :func:`end_last_interval` ends the run's last interval just after its last frame.

Layer 4 (system support): reads the loop's state (``slam.SLAMState``) and its config; imports
``knot_policy``.  User doc: docs/system.md, "Adaptive knots".
"""

import dataclasses
import math
from typing import Optional, Tuple

import numpy as np

from . import knot_policy
from .config import Config, SplineConfig

LONGEST_DT = {field.name: field for field in dataclasses.fields(SplineConfig)}["dt"].metadata["range"][1][1]
"""The longest ``spline.dt`` the config allows, s."""


def plan_next_interval(state, frame_index: int, n: int) -> None:
    """Adaptive knots: where interval n + 1 ends, decided once interval n's frames are tracked
    (``frame_index`` is the first frame after it), from the stored poses of intervals n - 1 and n
    (:func:`knot_policy.interval_from_track`; too few frames keep interval n's length), a quarter
    frame after a predicted frame (:func:`knot_policy.snap_after_frame`)."""
    spline_cfg, trajectory = state.cfg.spline, state.trajectory
    previous_start, (start, end) = trajectory.interval(max(n - 1, 0))[0], trajectory.interval(n)
    times = state.timestamps[: frame_index + 1]
    first = int(np.searchsorted(times, previous_start))  # the rule reads only [previous_start, end): copy no older pose
    poses = state.frame_poses[first: frame_index + 1].detach().cpu().double().numpy()
    next_end = knot_policy.next_interval_end(times[first:], poses[:, :3, :3], poses[:, :3, 3],
                                             previous_start, start, end, spline_cfg.dt_min, spline_cfg.dt_max,
                                             spline_cfg.rotation_tolerance, spline_cfg.position_tolerance)
    planned = trajectory.clone()  # a new spline, not a change to the one the other thread may read (--parallel)
    planned.plan_interval_end(n + 1, next_end, assumed_spacing=next_end - end)
    state.trajectory = planned


def end_last_interval(state, last: int) -> None:
    """``spline.last_interval = "last_frame"``: before the run's last, incomplete interval is mapped
    (``slam.tsslam_finish``), end it a quarter frame spacing after the last frame ``last``
    (:func:`knot_policy.last_interval_end`); the knots after it stay assumed at its planned length.
    With ``"planned"`` (the paper's loop), without the spline, or when the last frame is not inside
    the interval, nothing changes.  Why: docs/system.md, "The run's last interval"."""
    if state.cfg.spline.last_interval != "last_frame" or not state.cfg.local_ba.use_spline or last < 1:
        return
    n, times = state.intervals_done, state.timestamps[: last + 1]
    start, end = state.trajectory.interval(n)
    if start <= times[-1] < end:
        new_end = knot_policy.last_interval_end(times, start, end)
        if new_end < end:
            ended = state.trajectory.clone()
            ended.plan_interval_end(n, new_end, assumed_spacing=end - start)
            state.trajectory = ended


def check_frame_spacing(cfg: Config, timestamps, left_out_times=(), frame_step: int = 1) -> None:
    """ValueError when two consecutive frames lie further apart than the shortest spline interval,
    or when, over any stretch the curve approximation fits, that interval would hold fewer than two
    frames in the median.

    An interval holding no frame has nothing to place its control point: it is extrapolated from
    the control polygon, and the next fit frees it with no data, so the curve rings there (2 Hz
    frames with dt = 0.3 s: rotation errors of tens of degrees, exit 0).  The shortest interval is
    ``spline.dt`` with uniform knots; with adaptive knots the first interval's ``spline.dt`` or
    ``spline.dt_min``, whichever is shorter (intervals planned at it then step over frames, and
    the policy, which measures the motion from the frames inside them, never recovers).  A run
    without the spline has no intervals to leave empty.  The shortest interval also needs at least
    two frames in the median (frame spacing <= half of it): with 1.25 (5 Hz frames, dt = 0.25 s)
    the curve approximation's three free control points rest on too few poses and the trajectory
    runs off by metres; with adaptive knots at one frame per interval (12 Hz frames, dt_min =
    0.1 s) the policy has too few frames to measure the motion, keeps the last length, and the
    curve between frames ran tens of metres off.  The median is taken over every stretch of
    ``local_ba.fit_controls`` shortest intervals (:func:`sparse_stretch`), the span one fit rests
    on, so a recording that drops to 5 Hz for a while is refused too.  ``left_out_times``: (M,) stamps
    (s) of frames the loading left out (no ground-truth pose): the refusal names them when they lie
    in the gap or stretch it refuses; ``frame_step``: the selection's step (``--frames START:STOP:STEP``).
    """
    if cfg.method != "tsslam" or not cfg.local_ba.use_spline:
        return
    times = np.asarray(timestamps, dtype=np.float64)
    if len(times) < 2:
        return
    gaps = np.diff(times)
    worst = int(np.argmax(gaps))
    uniform = cfg.spline.knots == "uniform"
    shortest = cfg.spline.dt if uniform else min(cfg.spline.dt, cfg.spline.dt_min)
    which = (f"spline.dt = {cfg.spline.dt} s" if uniform else
             f"the shortest adaptive interval, min(spline.dt, spline.dt_min) = {shortest} s")
    if gaps[worst] > shortest:
        suggestion = math.ceil(max(gaps[worst], 0.0 if uniform else 2.0 * float(np.median(gaps))) * 20.0) / 20.0
        raise ValueError(
            f"frames {worst} and {worst + 1} (t = {times[worst]:.6f} s, {times[worst + 1]:.6f} s) are {gaps[worst]:.3f} s "
            f"apart, more than {which}, so a spline interval would hold no frame to fit its control point; "
            f"{_gap_fix(cfg, suggestion, frame_step)}{_left_out(left_out_times, times[worst], times[worst + 1])}")
    stretch = sparse_stretch(times, cfg.local_ba.fit_controls * shortest, shortest / 2.0 * (1.0 + 1e-6))
    if stretch is not None:  # fewer than two frames per interval there (stamps' rounding aside)
        first, last = stretch
        typical = float(np.median(gaps[first:last]))
        suggestion = math.ceil(2.0 * typical * 20.0 - 1e-6) / 20.0
        raise ValueError(
            f"frames {first} to {last} (t = {times[first]:.6f} s to {times[last]:.6f} s) are {typical:.3f} s apart "
            f"(median), more than half of {which}, so intervals there would hold fewer than two frames, too few to "
            f"place their control points; {_step_fix(frame_step)}use {_longer_intervals(cfg, suggestion)}, or --method "
            f"coslam{_left_out(left_out_times, times[first], times[last])}")


def sparse_stretch(times: np.ndarray, span: float, limit: float) -> Optional[Tuple[int, int]]:
    """The first stretch of ``span`` seconds, frames (first, last), more than half of whose gaps are
    over ``limit`` seconds (so is its median gap, the lower median for an even count), or None.  A
    stretch starts at a frame and ends at the last frame within ``span`` of it; only stretches the
    sequence holds whole count, and a sequence shorter than ``span`` is one stretch.  ``times``:
    (N,) float64 s, increasing."""
    over = np.concatenate([[0], np.cumsum(np.diff(times) > limit)])  # over[k]: gaps over the limit before frame k
    firsts = np.nonzero(times[:-1] + span <= times[-1])[0]
    lasts = np.searchsorted(times, times[firsts] + span, side="right") - 1
    if len(firsts) == 0:
        firsts, lasts = np.array([0]), np.array([len(times) - 1])
    sparse = np.nonzero(2 * (over[lasts] - over[firsts]) > lasts - firsts)[0]
    return (int(firsts[sparse[0]]), int(lasts[sparse[0]])) if len(sparse) else None


HAND_HELD_DT = {field.name: field for field in dataclasses.fields(SplineConfig)}["dt_max"].default
"""Intervals longer than this (s; the knot policy's default upper bound) no longer follow a
hand-held camera: a gap longer than it is a pause or a hole, better cut than spanned."""


def _left_out(left_out_times, start: float, end: float) -> str:
    """The note on frames without ground truth left out between ``start`` and ``end`` (s), or ""."""
    inside = int(np.count_nonzero((np.asarray(left_out_times) > start) & (np.asarray(left_out_times) < end)))
    return (f" ({inside} frame(s) without a ground-truth pose were left out there, which opens a gap the recording "
            f"does not have; --set data.require_gt=false keeps them)") if inside else ""


def _step_fix(frame_step: int) -> str:
    """The first way out when the selection's step spaced the frames: a smaller step, or ""."""
    return f"a smaller --frames step than {frame_step} brings them closer, or " if frame_step > 1 else ""


def _gap_fix(cfg: Config, seconds: float, frame_step: int = 1) -> str:
    """What to do about a gap that needs intervals of at least ``seconds``."""
    if frame_step > 1:
        return _step_fix(frame_step) + f"use {_longer_intervals(cfg, seconds)}, or --method coslam"
    if seconds > LONGEST_DT:  # beyond any interval the config allows
        return (f"no spline interval may be that long (spline.dt at most {LONGEST_DT:g} s): check the time stamps "
                f"(milliseconds read as seconds?), cut the sequence at the gap, or use --method coslam")
    if seconds > HAND_HELD_DT:
        return (f"cut the sequence at the gap (--frames on each side of it) or use --method coslam; "
                f"{_longer_intervals(cfg, seconds)} would run, but intervals over {HAND_HELD_DT:g} s no longer follow "
                f"a hand-held camera's motion")
    return f"use {_longer_intervals(cfg, seconds)}, or --method coslam"


def _longer_intervals(cfg: Config, seconds: float) -> str:
    """The --set options that make the shortest spline interval at least ``seconds`` long."""
    if cfg.spline.knots == "uniform":
        return f"--set spline.dt={seconds:g} (or more)"
    longest = f" --set spline.dt_max={seconds:g}" if seconds > cfg.spline.dt_max else ""  # dt_min <= dt_max
    return f"--set spline.dt_min={seconds:g} --set spline.dt={max(seconds, cfg.spline.dt):g}{longest} (or more)"


def check_knot_settings(cfg: Config) -> None:
    """ValueError naming the values when adaptive knots cannot run (dt_min > dt_max, or no spline)."""
    if cfg.method == "tsslam" and cfg.spline.knots == "adaptive":
        if cfg.spline.dt_min > cfg.spline.dt_max:
            raise ValueError(f"spline.dt_min = {cfg.spline.dt_min} s must be <= spline.dt_max = {cfg.spline.dt_max} s")
        if not cfg.local_ba.use_spline:
            raise ValueError("spline.knots = 'adaptive' needs the spline: local_ba.use_spline must be true")
