"""Wall-clock time per stage of the loop, for the runtime table (``metrics.json`` -> ``runtime``).

Each stage is timed with a context manager around its work::

    with state.timings.stage("global_ba", cfg.mapping.iters):
        ...

and :meth:`Timings.table` reports ms per iteration, iterations per call, calls and total seconds
per stage (the paper's runtime table divides the time of a stage by its iterations).

Layer 4 (system support): imports nothing of the package; used by ``slam`` and ``parallel``.
"""

import contextlib
import time
from dataclasses import dataclass, field
from typing import Dict, Iterator


@dataclass
class StageRecord:
    """What one timed call counts; the body may set :attr:`iterations` once it knows them."""

    iterations: int = 0


@dataclass
class Timings:
    """Seconds, iterations and calls per stage name, summed over the run."""

    seconds: Dict[str, float] = field(default_factory=dict)
    iterations: Dict[str, int] = field(default_factory=dict)
    calls: Dict[str, int] = field(default_factory=dict)

    def add(self, stage: str, seconds: float, iterations: int) -> None:
        """Count one call of ``stage`` that took ``seconds`` for ``iterations`` iterations."""
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds
        self.iterations[stage] = self.iterations.get(stage, 0) + iterations
        self.calls[stage] = self.calls.get(stage, 0) + 1

    @contextlib.contextmanager
    def stage(self, name: str, iterations: int = 0) -> Iterator[StageRecord]:
        """Time the ``with`` body as one call of stage ``name`` with ``iterations`` iterations.

        Yields a :class:`StageRecord` whose ``iterations`` the body may change (tracking knows its
        count only at the end).  A body that raises is not counted."""
        record = StageRecord(iterations)
        start = time.perf_counter()
        yield record
        self.add(name, time.perf_counter() - start, record.iterations)

    def table(self) -> Dict[str, Dict[str, float]]:
        """Per stage: ms per iteration, iterations per call, calls, total seconds.  A stage that ran
        no iteration (the curve approximation with ``local_ba.fit_iters=0`` or local BA off) reports
        its ms per call as ``ms_per_iteration``, beside ``iterations_per_call`` 0."""
        rows = {}
        for stage, seconds in self.seconds.items():
            iterations = self.iterations[stage] or max(self.calls[stage], 1)
            rows[stage] = {
                "ms_per_iteration": 1000.0 * seconds / iterations,
                "iterations_per_call": self.iterations[stage] / max(self.calls[stage], 1),
                "calls": self.calls[stage],
                "total_s": seconds,
            }
        return rows
