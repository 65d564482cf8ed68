"""Tracking and mapping in two threads (``--parallel``), as the paper's system runs them.

TS-SLAM Sec. III-D (and Co-SLAM's ``coslam.py``) run a tracking thread and a mapping thread side
by side: tracking estimates every frame against the latest finished map while mapping (global BA
for Co-SLAM; local + global BA per ``dt`` interval for TS-SLAM) works on the frames already
tracked.  The sequential loop of ``slam.run_slam`` is the default because it is deterministic; this
module is the optional concurrent schedule.

How the two threads share the state (``slam.SLAMState``):

* The main thread tracks frame ``i`` (``slam.track``) against a *snapshot* of the map, a copy the
  mapping thread publishes after each job that optimised the map; the map being optimised is
  never read while it changes.  Tracking may run at most ``lag`` frames ahead of mapping (Co-SLAM: ``map_every``;
  TS-SLAM: the frames of one ``dt`` interval), then it waits.
* The mapping thread runs, frame after frame, what the sequential loop does after tracking
  (``coslam_after_tracking`` / ``tsslam_after_tracking``) on a *view* of the state: its own copy of
  the pose table and of the recent-frame rays.  It commits the poses of the frames it has seen, the
  spline and the rays it dropped back under the lock, then publishes a new map snapshot if the
  job changed the map.
* One ``threading.Lock`` guards every read and write of shared state; no optimisation runs while
  holding it.  An exception in either thread stops both and is raised in the caller.

Not deterministic: which map snapshot a frame is tracked against depends on timing.  On two CPU
cores both threads share the cores, so the gain is small; on a GPU the threads overlap better.
``on_frame`` is called from the mapping thread (under the lock) when a frame's whole step is done,
so a checkpoint written there is consistent.

Layer 4 (system): uses slam; nothing below imports it.
"""

import copy
import dataclasses
import math
import queue
import threading
from typing import Callable, Optional

import numpy as np
import torch

from . import slam


def tracking_lag(state: "slam.SLAMState") -> int:
    """Frames tracking may run ahead of mapping, one mapping period: ``map_every`` (Co-SLAM), one dt
    interval (TS-SLAM), or ``tsslam_map_every`` when TS-SLAM also maps between intervals and that is shorter."""
    cfg = state.cfg
    if cfg.method == "coslam":
        return max(1, cfg.mapping.map_every)
    spacing = float(np.median(np.diff(state.timestamps))) if len(state.timestamps) > 1 else cfg.spline.dt
    interval = max(1, int(math.ceil(cfg.spline.dt / max(spacing, 1e-9))))
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
    keyframe bookkeeping) or are append-only (timings, log)."""
    rays = {j: batch for j, batch in state.frame_rays.items() if j <= frame_index}
    return dataclasses.replace(state, tracked_poses=state.tracked_poses.clone(), frame_rays=rays)


def commit(state: "slam.SLAMState", view: "slam.SLAMState", frame_index: int) -> None:
    """Copy the mapping thread's results for frames <= ``frame_index`` into the shared state."""
    state.tracked_poses[: frame_index + 1] = view.tracked_poses[: frame_index + 1]
    for dropped in [j for j in state.frame_rays if j <= frame_index and j not in view.frame_rays]:
        del state.frame_rays[dropped]
    state.spline = view.spline
    state.done = frame_index + 1


def run_tracking_and_mapping(sequence, state: "slam.SLAMState", device: torch.device, dtype: torch.dtype,
                             on_frame: Optional[Callable[["slam.SLAMState"], None]] = None) -> None:
    """Process frames ``state.done..`` of ``sequence`` with tracking and mapping in two threads.

    Frame 0 (first-frame mapping) must already be done.  Returns when every frame's step is
    committed (``state.done == len(sequence)``); raises what either thread raised.
    """
    if state.done < 1:
        raise ValueError("run_tracking_and_mapping starts after frame 0 (first_frame_mapping)")
    after_tracking = slam.coslam_after_tracking if state.cfg.method == "coslam" else slam.tsslam_after_tracking
    lock = threading.Lock()
    progress = threading.Condition(lock)  # notified when a mapping job is committed or fails
    jobs: "queue.Queue" = queue.Queue()
    snapshot = {"field": copy.deepcopy(state.field)}
    failures = []
    lag = tracking_lag(state)

    def mapping_worker() -> None:
        while True:
            frame = jobs.get()
            if frame is None:
                return
            try:
                with lock:
                    view = mapping_view(state, frame.index)
                    map_updates = global_ba_calls(state)
                after_tracking(view, frame)  # the slow part, outside the lock
                # A new snapshot only when this job optimised the map (most frames only keyframe).
                field_copy = copy.deepcopy(state.field) if global_ba_calls(state) != map_updates else None
                with lock:
                    commit(state, view, frame.index)
                    if field_copy is not None:
                        snapshot["field"] = field_copy
                    if on_frame is not None:
                        on_frame(state)
                    progress.notify_all()
            except BaseException as error:  # noqa: BLE001 - handed to the main thread
                with lock:
                    failures.append(error)
                    progress.notify_all()
                return

    worker = threading.Thread(target=mapping_worker, name="tsslam-mapping", daemon=True)
    worker.start()
    try:
        for i in range(state.done, len(sequence)):
            with lock:
                progress.wait_for(lambda: failures or state.done >= i - lag)
                if failures:
                    break
                field_model = snapshot["field"]
            frame = slam.frame_to_device(sequence[i], device, dtype)
            slam.track(state, frame, field_model=field_model, lock=lock)
            jobs.put(frame)
    finally:
        jobs.put(None)
        worker.join()
    if failures:
        raise failures[0]
