"""timings.py: the per-stage runtime table that metrics.json reports.

Oracle: counts written out by hand, and the table's definition (ms per iteration = 1000 s / iterations).
"""

import time

import pytest

from tsslam_ref.timings import Timings


def test_stage_counts_calls_iterations_and_time_and_skips_a_failed_body():
    timings = Timings()
    with timings.stage("global_ba", 20):
        time.sleep(0.01)
    with timings.stage("global_ba", 20):
        pass
    with timings.stage("tracking") as record:
        record.iterations = 7  # known only at the end of the body
    with pytest.raises(RuntimeError):
        with timings.stage("tracking", 3):
            raise RuntimeError("diverged")
    assert timings.calls == {"global_ba": 2, "tracking": 1}
    assert timings.iterations == {"global_ba": 40, "tracking": 7}
    assert timings.seconds["global_ba"] >= 0.01
    row = timings.table()["global_ba"]
    assert row["calls"] == 2 and row["iterations_per_call"] == 20
    assert row["ms_per_iteration"] == pytest.approx(1000.0 * timings.seconds["global_ba"] / 40)
    assert timings.table()["tracking"]["total_s"] == timings.seconds["tracking"]
