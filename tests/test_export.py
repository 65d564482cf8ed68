"""The continuous export (``--export-rate``): its sample times at the size of real timestamps.

Oracle: exact rational arithmetic (``fractions.Fraction``) for t_i = start + i / rate.
"""

from fractions import Fraction
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from tsslam_ref.export import export_continuous, export_times
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


@pytest.mark.parametrize("rate", [40, 80, 120, 200])
def test_export_of_a_spline_at_timestamp_size_writes_every_sample(tmp_path, rate):
    """np.arange accumulated its step and put the last of these times past the domain's end."""
    trajectory = BSplineTrajectory(torch.eye(3, dtype=torch.float64).repeat(6, 1, 1),
                                   torch.zeros(6, 3, dtype=torch.float64), 0.3, STAMP - 0.6)
    start, end = trajectory.domain()
    frames_past_the_end = SimpleNamespace(trajectory=trajectory, timestamps=np.array([start, end + 1.0]), done=2)
    rows = export_continuous(frames_past_the_end, rate, tmp_path / "export.txt")
    assert rows[0, 0] == start and rows[-1, 0] < end and len(rows) == len(export_times(start, end, rate))
    assert np.loadtxt(tmp_path / "export.txt").shape == rows.shape


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
