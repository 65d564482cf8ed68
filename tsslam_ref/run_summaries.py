"""The summaries of a run that ``metrics.json`` keeps, and its per-frame table ``frames.csv``.

Layer 4 (system support), beside ``run_outputs.py``, which writes them.  The loop (``slam.py``)
appends one entry to ``state.log`` per tracked frame: tracking's kept loss, its iterations and
seconds, and the share of the frame's measured surface outside the map's box
(``mapping.share_outside_bound``); TS-SLAM completes each entry with the distance and the angle
between the spline and the frame's own tracked pose when the frame's interval is committed
(``slam.check_spline_follows_tracking``).  :func:`frames_table` turns the log into ``frames.csv``;
:func:`outside_box_summary`, :func:`spline_offset_summary`, :func:`motion_summary` and
:func:`spline_summary` give ``metrics.json``'s ``outside_box``, ``spline_offsets``, ``motion`` and
``spline``.
"""

import sys

import numpy as np

from .geometry import pose_offsets

FRAME_COLUMNS = ("frame", "timestamp_s", "tracking_loss", "tracking_iterations", "tracking_seconds",
                 "outside_box_share", "spline_offset_m", "spline_offset_deg")
"""The columns of ``frames.csv``, one row per frame (empty where a value does not apply)."""
_LOG_KEYS = ("tracking_loss", "tracking_iterations", "tracking_seconds", "outside_box", "spline_offset_m",
             "spline_offset_deg")  # FRAME_COLUMNS[2:] as the log names them


def frames_table(log, timestamps: np.ndarray) -> str:
    """``frames.csv``'s text: a header of :data:`FRAME_COLUMNS`, then one row per frame 0..N-1 of
    ``timestamps`` (N,) float64 s (``%.6f``, as ``trajectory.txt``), with the log entry's values where
    the frame has one (frame 0 is not tracked; Co-SLAM and frames the spline has not reached yet have no
    spline offsets; a run still going has rows only up to its newest tracked frame)."""
    entries = {int(entry["frame"]): entry for entry in log}
    last = max(entries, default=0)
    lines = [",".join(FRAME_COLUMNS)]
    for frame in range(min(len(timestamps), last + 1)):
        entry = entries.get(frame, {})
        values = [str(frame), f"{timestamps[frame]:.6f}"]
        values += [_cell(entry.get(key)) for key in _LOG_KEYS]
        lines.append(",".join(values))
    return "\n".join(lines) + "\n"


def _cell(value) -> str:
    """One CSV cell: empty for None, an integer as it is, a float to 9 significant digits."""
    if value is None:
        return ""
    return str(value) if isinstance(value, (int, np.integer)) else f"{float(value):.9g}"


OUTSIDE_BOX_WARNING = 0.25
"""A tracked frame whose measured surface lies outside the map's box by more than this share gets
the run's one warning (``mapping.share_outside_bound``)."""


def outside_box_summary(log) -> dict:
    """metrics.json's ``outside_box``: the largest share of a tracked frame's measured surface
    outside the map's box, that frame, and how many frames were over :data:`OUTSIDE_BOX_WARNING`."""
    shares = [(entry["outside_box"], entry["frame"]) for entry in log if "outside_box" in entry]
    if not shares:
        return {}
    largest, frame = max(shares)
    over = sum(share > OUTSIDE_BOX_WARNING for share, _ in shares)
    return {"outside_box": {"max_share": largest, "frame": frame, "frames_over_warning": over,
                            "warning_share": OUTSIDE_BOX_WARNING}}


def spline_offset_summary(log) -> dict:
    """metrics.json's ``spline_offsets``: how far TS-SLAM's spline lies from the frames' own poses
    (tracking's, moved by the map update where it ran) when their interval is committed, RMS and largest
    distance (m) and angle (deg) over the frames, and the frames of the largest.  Both tracking's
    noise and motion faster than the knots show here (docs/system.md, "What the spline smoothed
    away")."""
    rows = [(entry["spline_offset_m"], entry["spline_offset_deg"], entry["frame"]) for entry in log
            if "spline_offset_m" in entry]
    if not rows:
        return {}
    distances, angles, frames = (np.asarray(column) for column in zip(*rows))
    return {"spline_offsets": {
        "frames": len(rows), "position_rms_m": float(np.sqrt(np.mean(distances ** 2))),
        "position_max_m": float(distances.max()), "position_max_frame": int(frames[distances.argmax()]),
        "rotation_rms_deg": float(np.sqrt(np.mean(angles ** 2))), "rotation_max_deg": float(angles.max()),
        "rotation_max_frame": int(frames[angles.argmax()])}}


LOST_SPEED = 5.0
"""m/s: an estimated camera centre faster than this between two frames gets a warning.  Twice the
fastest hand-held motion of the real trajectories we know (TUM-VI room1: 2.5 m/s between 30 Hz
samples; TUM RGB-D desk and teddy: 0.5-0.6); a camera that tracking lost jumps faster (a 300 deg/s pan
about a fixed centre, lost: 7.5-8.3 m/s), while the tracking loss may not rise at all."""


def motion_summary(timestamps: np.ndarray, poses: np.ndarray) -> dict:
    """``{"motion": ...}``: the estimate's peak speed (m/s) and angular speed (deg/s) between
    consecutive frames, and their frames; a warning on stderr when the speed passes :data:`LOST_SPEED`.

    Args: timestamps (N,) float64 s, increasing; poses (N, 4, 4) camera-to-world."""
    if len(timestamps) < 2:
        return {}
    spacing = np.diff(timestamps)
    distances, angles = pose_offsets(poses[:-1], poses[1:])  # from frame i to i + 1: |Log(R_i^T R_{i+1})|
    speed, angular_speed = distances / spacing, angles / spacing
    fastest, turning = int(np.argmax(speed)), int(np.argmax(angular_speed))
    if speed[fastest] > LOST_SPEED:
        print(f"warning: the estimated camera moves {speed[fastest]:.1f} m/s from frame {fastest} to {fastest + 1} "
              f"(more than {LOST_SPEED:g} m/s, twice the fastest hand-held motion we know): tracking was most likely "
              f"lost there (the divergence stop watches the loss, which a lost camera need not raise); check "
              f"trajectory.png", file=sys.stderr)
    return {"motion": {"peak_speed_m_s": float(speed[fastest]), "peak_speed_after_frame": fastest,
                       "peak_angular_speed_deg_s": float(angular_speed[turning]),
                       "peak_angular_speed_after_frame": turning}}


def spline_summary(trajectory, knots: str) -> dict:
    """Where a TS-SLAM run's knots went: the knot rule, the domain's interval count, their lengths
    (min / mean / max, s) and the interval boundaries (float64 s, as the frames' stamps; the last
    one is the domain's end, past the last frame)."""
    start, end = trajectory.domain()
    boundaries = [start]
    while boundaries[-1] < end:
        boundaries.append(trajectory.interval(len(boundaries) - 1)[1])
    boundaries = np.asarray(boundaries, dtype=np.float64)
    lengths = np.diff(boundaries)
    return {"knots": knots, "intervals": int(len(lengths)), "interval_min_s": float(lengths.min()),
            "interval_mean_s": float(lengths.mean()), "interval_max_s": float(lengths.max()),
            "interval_boundaries_s": boundaries.tolist()}
