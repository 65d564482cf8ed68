"""frames.csv, the per-frame table a run writes (run_summaries.frames_table), against logs built here."""

import csv
import io

import numpy as np

from tsslam_ref.run_summaries import FRAME_COLUMNS, frames_table

STAMP = 1305031102.175304  # a TUM-sized time stamp: float64 keeps its microseconds


def _read(text):
    return list(csv.DictReader(io.StringIO(text)))


def test_frames_table_has_one_row_per_frame_with_the_log_values_where_they_apply():
    """Five frames, frames 1-3 tracked (frame 3's entry before frame 2's, as a resumed log may not be),
    frames 1 and 2 with spline offsets: rows 0-3 (none for frames not tracked yet), time stamps to the
    microsecond, integers as integers, floats to 9 digits, empty cells where nothing applies."""
    log = [{"frame": 1, "tracking_loss": 0.125, "tracking_iterations": 20, "tracking_seconds": 0.4,
            "outside_box": 0.0, "spline_offset_m": 0.0031, "spline_offset_deg": 0.25},
           {"frame": 3, "tracking_loss": 1.0 / 3.0, "tracking_iterations": 19, "tracking_seconds": 0.5,
            "outside_box": 0.3},
           {"frame": 2, "tracking_loss": 0.25, "tracking_iterations": np.int64(20), "tracking_seconds": 0.45,
            "outside_box": 0.01, "spline_offset_m": np.float64(0.002), "spline_offset_deg": 0.5}]
    times = STAMP + np.arange(5) / 30.0
    text = frames_table(log, times)
    assert text.splitlines()[0] == ",".join(FRAME_COLUMNS)
    rows = _read(text)
    assert [row["frame"] for row in rows] == ["0", "1", "2", "3"]
    for row, time in zip(rows, times):  # microseconds, as trajectory.txt
        assert len(row["timestamp_s"].split(".")[1]) == 6 and abs(float(row["timestamp_s"]) - time) <= 5e-7
    assert all(rows[0][column] == "" for column in FRAME_COLUMNS[2:])  # frame 0: given its pose, not tracked
    assert rows[1]["tracking_iterations"] == "20" and rows[2]["tracking_iterations"] == "20"
    assert rows[3]["tracking_loss"] == "0.333333333" and rows[3]["outside_box_share"] == "0.3"
    assert rows[3]["spline_offset_m"] == "" and rows[3]["spline_offset_deg"] == ""
    assert (rows[1]["spline_offset_m"], rows[2]["spline_offset_deg"]) == ("0.0031", "0.5")


def test_frames_table_of_a_log_with_no_tracked_frame_is_frame_0_alone():
    rows = _read(frames_table([], STAMP + np.arange(3)))
    assert len(rows) == 1 and rows[0]["frame"] == "0" and rows[0]["tracking_loss"] == ""
