"""The run's outputs: each method's per-frame trajectory and TS-SLAM's continuous trajectory file.

* TS-SLAM reports the spline's pose at every frame's timestamp (:func:`spline_output_poses`).
* The Co-SLAM baseline reports keyframes as global BA left them and every other frame re-anchored on
  its preceding keyframe (Co-SLAM's ``pose_relative``, :func:`coslam_output_poses`).
* :func:`export_continuous` samples the spline at any rate with velocities (``--export-rate``).

Every pose is camera-to-world, OpenCV axes; times are float64 seconds.  The functions read a
``slam.SLAMState`` (fields ``cfg``, ``done``, ``timestamps``, ``frame_poses``, ``trajectory``,
``keyframe_of_frame``, ``relative_to_keyframe``) and change nothing in it.

Layer 4 (system support): imports ``geometry`` and ``files`` only; used by ``slam`` and ``run``.
"""


import numpy as np
import torch

from .files import atomic_path
from .geometry import make_pose, trajectory_to_tum

MAX_EXPORT_RATE = 1000.0
"""Largest export rate (Hz): far above any camera's frame rate, and it bounds the file size."""


def spline_output_poses(state) -> torch.Tensor:
    """(done, 4, 4): the spline's poses where it reaches, the frame poses elsewhere."""
    poses = state.frame_poses[: state.done].clone()
    if state.trajectory is None or not state.cfg.local_ba.use_spline:
        return poses
    times = state.timestamps[: state.done]
    covered = np.nonzero(state.trajectory.covers(times))[0]
    if len(covered) > 0:
        poses[covered] = state.trajectory.poses(times[covered]).to(poses.dtype)
    return poses


def coslam_output_poses(state) -> torch.Tensor:
    """(done, 4, 4) Co-SLAM's reported trajectory: keyframes as optimised, others re-anchored on
    their preceding keyframe with the relative pose they had after tracking (pose_relative)."""
    poses = state.frame_poses[: state.done].clone()
    for i, relative in state.relative_to_keyframe.items():
        if i < state.done:
            poses[i] = relative @ state.frame_poses[state.keyframe_of_frame[i]]
    return poses


def estimated_trajectory(state) -> torch.Tensor:
    """(done, 4, 4) the method's output poses for the frames processed so far."""
    if state.cfg.method == "tsslam":
        return spline_output_poses(state)
    return coslam_output_poses(state)


def export_times(start: float, end: float, rate_hz: float) -> np.ndarray:
    """(T,) float64 times start + i / rate_hz, i = 0, 1, ..., all < end (seconds)."""
    count = int(np.ceil((end - start) * rate_hz)) + 1
    times = start + np.arange(count, dtype=np.float64) / rate_hz
    return times[times < end]


def export_continuous(state, rate_hz: float, path) -> np.ndarray:
    """Sample the spline at ``rate_hz`` over the frames' time span and write one line per time, atomically.

    The times are t_i = start + i / rate_hz from the domain's start (the first frame) up to the
    last processed frame's time (``state.timestamps[state.done - 1]``), and before the domain's
    half-open end.  The spline goes on past the last frame to the end of its last interval, held
    there by no frame (an extrapolation that can run metres off): that part is not written.  Each
    time is computed from its index: accumulating steps, as ``np.arange`` does, drifts at the
    magnitude of real timestamps (1e9 s) and could put the last time past the end.  The last row is
    the last grid time at or before the last frame (up to 1 / rate_hz before it).  A state whose
    spline does not reach its last frame yet (a checkpoint's, before ``slam.finish_run`` fitted the
    last interval) is refused.
    Columns: t tx ty tz qx qy qz qw vx vy vz wx wy wz, with v the world-frame linear velocity
    (m/s) and w the body-frame angular velocity (rad/s); quaternions as in ``trajectory.txt``
    (:func:`geometry.trajectory_to_tum`).  Replaces ``path`` atomically (``files.atomic_path``; the
    caller owns the folder).  Returns the (T, 14) float64 rows."""
    if not 0 < rate_hz <= MAX_EXPORT_RATE:  # NaN fails too
        raise ValueError(f"the export rate must be in (0, {MAX_EXPORT_RATE:g}] Hz, got {rate_hz}")
    start, end = state.trajectory.domain()
    last_frame = float(state.timestamps[state.done - 1])
    if end <= last_frame:
        raise ValueError(f"the spline covers [{start:.6f}, {end:.6f}) s but the last processed frame is at "
                         f"{last_frame:.6f} s: its last interval is not fitted yet (a checkpoint's state); finish "
                         f"the state first, e.g. slam.run_slam(sequence, cfg, state=state)")
    times = export_times(start, min(end, float(np.nextafter(last_frame, np.inf))), rate_hz)
    sample = state.trajectory.evaluate(times, derivatives=1)
    poses = make_pose(sample.rotation, sample.translation).detach().cpu().double().numpy()
    rows = np.concatenate([times[:, None], trajectory_to_tum(poses), sample.velocity_world.detach().cpu().double().numpy(),
                           sample.omega_body.detach().cpu().double().numpy()], axis=1)
    with atomic_path(path) as temporary, open(temporary, "w") as stream:
        stream.write(f"# t tx ty tz qx qy qz qw vx vy vz wx wy wz: t in s (as the frames' stamps), camera-to-world "
                     f"pose (position m, unit quaternion qx qy qz qw), OpenCV axes; v world frame m/s, w body frame "
                     f"rad/s; every {1.0 / rate_hz:.9g} s ({rate_hz:.15g} Hz) from the first frame up to the last one\n")
        np.savetxt(stream, rows, fmt=["%.6f"] + ["%.9f"] * 13)  # stamps to the microsecond, as trajectory.txt
    return rows
