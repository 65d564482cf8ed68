"""Tracking and mapping in two threads (``--parallel``), as the paper's system runs them.

TS-SLAM Sec. III-D (and Co-SLAM's ``coslam.py``) run a tracking thread and a mapping thread side
by side: tracking estimates every frame against the latest finished map while mapping (global BA
for Co-SLAM; local + global BA per ``dt`` interval for TS-SLAM) works on the frames already
tracked.  The sequential loop of ``slam.run_slam`` is the default because it is deterministic;
:func:`run_slam_in_two_threads` is the optional concurrent schedule, chosen by the caller
(``run.py`` with ``--parallel``).

How the two threads share the state (``slam.SLAMState``):

* The main thread tracks frame ``i`` (``slam.track``) against a *snapshot* of the map, a copy the
  mapping thread publishes after each job that optimised the map; the map being optimised is
  never read while it changes.  Tracking may run at most ``lag`` frames ahead of mapping (Co-SLAM: ``map_every``;
  TS-SLAM: the frames of one spline interval, or ``mapping.tsslam_map_every`` frames if fewer),
  then it waits.
* The mapping thread runs, frame after frame, what the sequential loop does after tracking
  (``slam.after_tracking``) on a *view* of the state: its own copy of the pose table and of the
  recent-frame rays.  It commits the poses of the frames it has seen, the spline, its interval
  count and the rays it dropped back under the lock, then publishes a new map snapshot if the
  job changed the map.
* One ``threading.Lock`` guards every read and write of shared state; no optimisation runs while
  holding it.  An exception in either thread stops both and is raised in the caller.

Not deterministic: which map snapshot a frame is tracked against depends on timing.  On two CPU
cores both threads share the cores, so the gain is small; on a GPU the threads overlap better.
``on_frame`` is called from the mapping thread (under the lock) when a frame's whole step is done,
so a checkpoint written there is consistent.

Layer 4 (system): uses slam and device; only ``run`` imports it.
"""

import copy
import dataclasses
import math
import queue
import sys
import threading
import time
from typing import Callable, Optional

import numpy as np
import torch

from . import slam
from .config import Config
from .device import frame_to_device


def tracking_lag(state: "slam.SLAMState") -> int:
    """Frames tracking may run ahead of mapping, one mapping period: ``map_every`` (Co-SLAM), one
    spline interval (TS-SLAM: dt, or with adaptive knots the length of the next interval to map),
    or ``tsslam_map_every`` when TS-SLAM also maps between intervals and that is shorter."""
    cfg = state.cfg
    if cfg.method == "coslam":
        return max(1, cfg.mapping.map_every)
    length = cfg.spline.dt
    if cfg.spline.knots == "adaptive" and state.trajectory is not None:
        start, end = state.trajectory.interval(state.intervals_done)
        length = end - start
    spacing = float(np.median(np.diff(state.timestamps))) if len(state.timestamps) > 1 else length
    interval = max(1, int(math.ceil(length / max(spacing, 1e-9) - 1e-6)))  # 0.3 s / (1 / 30 s) is 9 frames, not 10
    return min(interval, cfg.mapping.tsslam_map_every) if cfg.mapping.tsslam_map_every > 0 else interval


def global_ba_calls(state: "slam.SLAMState") -> int:
    """Global BA runs so far: every mapping step of either method ends with one, TS-SLAM's map
    updates between intervals are one too, and only these change the map, so a new count means a
    new map to publish."""
    return state.timings.calls.get("global_ba", 0) + state.timings.calls.get("map_update", 0)


def mapping_view(state: "slam.SLAMState", frame_index: int) -> "slam.SLAMState":
    """A state for the mapping thread at frame ``frame_index``: its own pose table and the rays of
    frames up to ``frame_index`` (as the sequential loop would hold them), everything else shared.

    Shared objects are only touched by the mapping thread (map, optimizer, keyframes, spline,
    keyframe bookkeeping) or are append-only (timings; the log, whose entries the mapping thread only
    completes with the spline offsets of the frames it commits); the spline and its interval count
    are replaced, never changed in place, so the view's own copies go back in :func:`commit`."""
    rays = {j: batch for j, batch in state.window_rays.items() if j <= frame_index}
    return dataclasses.replace(state, frame_poses=state.frame_poses.clone(), window_rays=rays)


def commit(state: "slam.SLAMState", view: "slam.SLAMState", frame_index: int) -> None:
    """Copy the mapping thread's results for frames <= ``frame_index`` into the shared state."""
    state.frame_poses[: frame_index + 1] = view.frame_poses[: frame_index + 1]
    for dropped in [j for j in state.window_rays if j <= frame_index and j not in view.window_rays]:
        del state.window_rays[dropped]
    state.trajectory = view.trajectory
    state.intervals_done = view.intervals_done
    state.done = frame_index + 1


def run_slam_in_two_threads(sequence, cfg: Config, device: Optional[torch.device] = None,
                            state: Optional["slam.SLAMState"] = None,
                            on_frame: Optional[Callable[["slam.SLAMState"], None]] = None) -> "slam.SLAMResult":
    """:func:`slam.run_slam` with tracking and mapping in two threads (same arguments and result).

    Frame 0 (the first map) runs first, alone; then :func:`run_tracking_and_mapping`.  The run's
    config (checkpoints, ``metrics.json``) says ``parallel`` whatever ``cfg`` says."""
    cfg = dataclasses.replace(cfg, parallel=True)
    state, device, dtype = slam.prepare_run(sequence, cfg, device, state)
    start, first_new = time.perf_counter(), state.done
    if state.done == 0:
        slam.start_map(state, frame_to_device(sequence[0], device, dtype))
        state.done = 1
        if on_frame is not None:
            on_frame(state)
    if state.done < len(sequence):
        run_tracking_and_mapping(sequence, state, device, dtype, on_frame)
    return slam.finish_run(sequence, state, device, dtype, start, first_new)


def run_tracking_and_mapping(sequence, state: "slam.SLAMState", device: torch.device, dtype: torch.dtype,
                             on_frame: Optional[Callable[["slam.SLAMState"], None]] = None) -> None:
    """Process frames ``state.done..`` of ``sequence`` with tracking and mapping in two threads.

    Frame 0 (first-frame mapping) must already be done.  Returns when every frame's step is
    committed (``state.done == len(sequence)``); raises what either thread raised.
    """
    if state.done < 1:
        raise ValueError("run_tracking_and_mapping starts after frame 0 (slam.start_map)")
    lock = threading.Lock()
    progress = threading.Condition(lock)  # notified when a mapping job is committed or fails
    jobs: "queue.Queue" = queue.Queue()
    snapshot = {"field": copy.deepcopy(state.field)}
    failures = []
    stop = threading.Event()  # set when the main thread stops early: queued jobs are dropped
    finished = threading.Event()  # set by the mapping thread as it ends (join_through_interrupts waits on it)

    def mapping_worker() -> None:
        try:
            while True:
                frame = jobs.get()
                if frame is None or stop.is_set():
                    return
                map_one_frame(state, frame, progress, snapshot, on_frame)
        except BaseException as error:  # noqa: BLE001 - handed to the main thread
            with lock:
                failures.append(error)
                progress.notify_all()
        finally:
            finished.set()

    worker = threading.Thread(target=mapping_worker, name="tsslam-mapping", daemon=True)
    worker.start()
    try:
        for i in range(state.done, len(sequence)):
            with lock:
                # The lead is re-read at every wake-up: with adaptive knots it follows the next
                # interval to map, which the mapping thread plans as it goes.
                progress.wait_for(lambda: failures or state.done >= i - tracking_lag(state))
                if failures:
                    break
                field_model = snapshot["field"]
            frame = frame_to_device(sequence[i], device, dtype)
            slam.track(state, frame, field_model=field_model, lock=lock)
            jobs.put(frame)
    except BaseException:
        stop.set()  # Ctrl-C or a failure: finish the job under way, skip the queued ones
        raise
    finally:
        jobs.put(None)
        join_through_interrupts(worker, stop, finished)
    if failures:
        raise failures[0]


def map_one_frame(state: "slam.SLAMState", frame, progress: threading.Condition, snapshot: dict,
                  on_frame: Optional[Callable[["slam.SLAMState"], None]]) -> None:
    """The mapping thread's job for one tracked frame: ``slam.after_tracking`` on a view of the
    state, outside the lock; then, under ``progress``'s lock, the commit, a new map snapshot if the
    job optimised the map (most frames only keyframe), ``on_frame`` and a notification."""
    with progress:
        view = mapping_view(state, frame.index)
        map_updates = global_ba_calls(state)
    slam.after_tracking(view, frame)  # the slow part, outside the lock
    field_copy = copy.deepcopy(state.field) if global_ba_calls(state) != map_updates else None
    with progress:
        commit(state, view, frame.index)
        if field_copy is not None:
            snapshot["field"] = field_copy
        if on_frame is not None:
            on_frame(state)
        progress.notify_all()


def join_through_interrupts(worker: threading.Thread, stop: threading.Event, finished: threading.Event) -> None:
    """Wait for ``worker`` to end even through Ctrl-C (which also sets ``stop``), then raise
    KeyboardInterrupt if one came.

    Python would otherwise go on to exit (or write the outputs) while the mapping thread is inside
    PyTorch, and the process aborts (exit 134) or reads a state in the middle of a BA step.  The
    wait is on ``finished``, which the worker sets as it ends, not on ``Thread.join``: a Ctrl-C
    inside ``join`` of a thread still running makes Python 3.11 take the thread for ended (its
    ``is_alive()`` turns False).  The wait is one mapping job (a few seconds at most)."""
    interrupted = False
    while True:
        try:
            finished.wait()
            worker.join()  # the thread is past its last job: this returns at once
            break
        except KeyboardInterrupt:
            stop.set()
            if not interrupted:
                print("waiting for the mapping step under way to finish ...", file=sys.stderr)
            interrupted = True
    if interrupted:
        raise KeyboardInterrupt
