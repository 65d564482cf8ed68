"""The camera trajectory: one cubic B-spline type for the window, local BA, global BA and the pose models.

TS-SLAM Sec. III-B represents the trajectory by control points {R_k, t_k} at knot times
t_k = t0 + k dt; the pose at time t is the cumulative cubic B-spline of Eq. (5)-(6)
(:func:`spline.evaluate`).  :class:`BSplineTrajectory` holds the control points with dt, t0, the
index convention and, once the first interval is fitted, the pose the curve must start at (the
gauge, :func:`spline_fit.pin_first_control_point`).  It grows at the back and shrinks at the front
like basalt's ``knots_push_back`` / ``knots_pop_front``.

Intervals and domain (paper convention, offset o = 2; basalt o = 0):

* interval n is [t_{n+o}, t_{n+o+1}); the first one starts at the first frame's time, so an empty
  trajectory for a sequence starting at t_first has t0 = t_first - o dt (:meth:`BSplineTrajectory.empty`);
* with N >= 4 control points the trajectory **covers** the half-open time range
  [t_o, t_{N-3+o}), the intervals 0..N-4: a frame lies in exactly one interval, and a frame at
  the end time belongs to the next one, not yet fitted.  This is the one membership rule
  (:meth:`BSplineTrajectory.covers`); :func:`spline.evaluate` also accepts the end time itself.

Knot times.  A uniform trajectory (the paper's) has t_k = t0 + k dt for every integer k.  A
non-uniform one stores the times of a run of knots (``knots``, index ``knot_offset`` for the first
stored one) and continues them with spacing dt beyond both ends of that run; the curve is the
non-uniform spline of :mod:`tsslam_ref.knots` on the knots t_{k-o}..t_{N+1-o}.  So ``dt`` is the
nominal spacing: the whole spacing of a uniform trajectory, and for a non-uniform one the spacing
assumed for knots not stored yet.  In the paper convention ``push_back(..., knot_time=T)`` of
control point N sets t_N = T, the end of the interval that point adds; the basis of the last two
intervals also depends on t_{N+1} and t_{N+2}, which stay assumed (last + dt) until their own
control points arrive, so a push changes the curve on the last intervals a little (the price of
choosing knots online; a uniform push changes nothing there).

Layer 1 (math): imports ``spline``, ``knots`` and ``geometry`` only.
Taught in notebooks/01_bspline_trajectory.ipynb and notebooks/06_local_ba.ipynb.
"""

import warnings
from typing import Optional, Tuple

import numpy as np
import torch

from . import knots as knots_module
from . import spline as spline_module
from .geometry import make_pose, pose_offsets, so3_exp, so3_log
from .times import check_float64_seconds, float64_seconds

_ROTATION_JUMP_WARN = 0.5 * np.pi


class BSplineTrajectory:
    """Control points plus dt, t0, the index convention and the optional start pose.

    Holds plain tensors (not an nn.Module): the pose models of ``bundle`` keep their own
    parametrisation (tangent increments) and build a new trajectory from it.  Methods return new
    objects except :meth:`push_back` and :meth:`pop_front`, which edit it in place.

    Args:
        control_rotations: (N, 3, 3) body-to-world; control_translations: (N, 3) world, m.
        dt: knot spacing (s).  t0: time of control point 0 (s).
        convention: "paper" or "basalt" (:mod:`tsslam_ref.spline`).
        start_pose: (4, 4) camera-to-world pose the curve starts at (control point 0 follows
            points 1 and 2 in BA), or None.
        knots: None (uniform, t_k = t0 + k dt) or (L,) strictly increasing float64 times of knots
            knot_offset .. knot_offset + L − 1 (s), a run that holds knot 0 (knot_offset <= 0 < L +
            knot_offset) with t_0 = t0; knots outside it continue with spacing dt.
    """

    def __init__(self, control_rotations: torch.Tensor, control_translations: torch.Tensor, dt: float, t0: float,
                 convention: str = "paper", start_pose: Optional[torch.Tensor] = None,
                 knots: Optional[np.ndarray] = None, knot_offset: int = 0):
        if control_rotations.dim() != 3 or control_rotations.shape[1:] != (3, 3):
            raise ValueError(f"BSplineTrajectory takes (N, 3, 3) rotations, got {tuple(control_rotations.shape)}")
        if control_translations.shape != (control_rotations.shape[0], 3):
            raise ValueError(f"BSplineTrajectory takes (N, 3) translations for N = {control_rotations.shape[0]} "
                             f"rotations, got {tuple(control_translations.shape)}")
        spline_module.first_segment_offset(convention)  # ValueError for an unknown convention
        check_float64_seconds("dt", dt)
        check_float64_seconds("t0", t0)  # a float32 stamp near 1.3e9 s is up to 64 s off
        if not dt > 0:
            raise ValueError(f"knot spacing dt must be > 0 s, got {dt}")
        self.control_rotations = control_rotations
        self.control_translations = control_translations
        self.dt = float(dt)
        self.t0 = float(t0)
        self._pops = None  # (t0 before the first pop_front, pops since), uniform knots
        self.convention = convention
        self.start_pose = start_pose
        self._knots, self.knot_offset = None, 0
        if knots is not None:
            self._set_knots(knots, knot_offset)

    def _set_knots(self, knots, knot_offset: int) -> None:
        """Store a checked run of knot times; t0 must be its knot 0."""
        check_float64_seconds("knots", knots)
        values = np.array(knots, dtype=np.float64).reshape(-1)
        knot_offset = int(knot_offset)
        if not knot_offset <= 0 < values.shape[0] + knot_offset:
            raise ValueError(f"knots must hold knot 0: knot_offset = {knot_offset} with {values.shape[0]} knots")
        if not np.all(np.isfinite(values)):
            j = int(np.flatnonzero(~np.isfinite(values))[0])
            raise ValueError(f"knot times must be finite, got {float(values[j])!r} s at stored index {j}")
        steps = np.diff(values)
        if np.any(steps <= 0):
            j = int(np.flatnonzero(steps <= 0)[0])
            raise ValueError(f"knot times must be finite and strictly increasing, got {float(values[j])!r} s then "
                             f"{float(values[min(j + 1, len(values) - 1)])!r} s at stored index {j}")
        if values[-knot_offset] != self.t0:
            raise ValueError(f"t0 = {self.t0!r} s must equal knot 0 of the knot times, {float(values[-knot_offset])!r} s")
        self._knots, self.knot_offset = values, knot_offset

    @property
    def uniform(self) -> bool:
        """True when every knot is t0 + k dt (no stored knot times)."""
        return self._knots is None

    def timing(self) -> dict:
        """Keyword arguments (``knots``, ``knot_offset``) that carry the knot times into a new trajectory."""
        return {} if self._knots is None else {"knots": self._knots.copy(), "knot_offset": self.knot_offset}

    def start_weights(self) -> Optional[Tuple[float, float]]:
        """(B̃_1, B̃_2) of control points 1 and 2 at the domain start (:func:`knots.start_weights`),
        for the start-pose gauge (:func:`spline_fit.pin_first_control_point`); None when uniform."""
        if self._knots is None:
            return None
        return knots_module.start_weights(self.knot_vector(max(self.n_ctrl, 4)))

    @classmethod
    def empty(cls, first_time: float, dt: float, like: torch.Tensor, convention: str = "paper") -> "BSplineTrajectory":
        """No control points yet; interval 0 starts at ``first_time`` (s).  ``like``: dtype and device."""
        check_float64_seconds("first_time", first_time)
        check_float64_seconds("dt", dt)
        offset = spline_module.first_segment_offset(convention)
        return cls(like.new_zeros(0, 3, 3), like.new_zeros(0, 3), dt, float(first_time) - offset * float(dt), convention)

    @classmethod
    def from_rotvecs(cls, rotvecs: torch.Tensor, translations: torch.Tensor, dt: float, t0: float,
                     convention: str = "paper") -> "BSplineTrajectory":
        """Build from (N, 3) rotation vectors (rad) and (N, 3) translations (m)."""
        return cls(so3_exp(rotvecs), translations, dt, t0, convention)

    def with_controls(self, control_rotations: torch.Tensor, control_translations: torch.Tensor) -> "BSplineTrajectory":
        """The same timing and start pose with other control points, detached: (M, 3, 3), (M, 3)."""
        return BSplineTrajectory(control_rotations.detach(), control_translations.detach(), self.dt, self.t0,
                                 self.convention, self.start_pose, **self.timing())

    # --- sizes, knots, intervals, domain
    @property
    def n_ctrl(self) -> int:
        """N, the number of control points."""
        return int(self.control_translations.shape[0])

    def __len__(self) -> int:
        return self.n_ctrl

    def knot_time(self, k: int) -> float:
        """t_k (s): t0 + k dt when uniform; else the stored time, continued with spacing dt outside the run."""
        if self._knots is None:
            return self.t0 + k * self.dt
        index = k - self.knot_offset
        if index < 0:
            return float(self._knots[0]) + index * self.dt
        if index >= len(self._knots):
            return float(self._knots[-1]) + (index - len(self._knots) + 1) * self.dt
        return float(self._knots[index])

    def knot_times(self) -> np.ndarray:
        """(N,) float64 times t_k of the control points (s)."""
        if self._knots is None:
            return self.t0 + self.dt * np.arange(self.n_ctrl, dtype=np.float64)
        return np.array([self.knot_time(k) for k in range(self.n_ctrl)], dtype=np.float64)

    def knot_vector(self, n_ctrl: Optional[int] = None) -> np.ndarray:
        """(n + 2,) the knots of :mod:`tsslam_ref.knots`: t_{j-o}, j = 0..n+1 (o: first-segment offset).

        n_ctrl: n, default N; a larger n gives the knots the trajectory would have with n points.
        """
        offset = spline_module.first_segment_offset(self.convention)
        n_ctrl = self.n_ctrl if n_ctrl is None else int(n_ctrl)
        return np.array([self.knot_time(j + offset - 2) for j in range(n_ctrl + 2)], dtype=np.float64)

    def knot_time_before(self, k: int, steps: int) -> float:
        """t_{k-steps} (s).  Uniform: computed as t_k - steps dt, the arithmetic the uniform loop has
        always used for its time ranges (so a uniform run's frame selections stay bit for bit)."""
        if self._knots is None:
            return self.knot_time(k) - steps * self.dt
        return self.knot_time(k - steps)

    def interval_start_knot(self, n: int) -> int:
        """Index k of the knot t_k where interval n starts: n + o (o: the convention's first-segment offset)."""
        return n + spline_module.first_segment_offset(self.convention)

    def interval(self, n: int) -> Tuple[float, float]:
        """[start, end) of interval n (s): [t_{n+o}, t_{n+o+1})."""
        k = self.interval_start_knot(n)
        return self.knot_time(k), self.knot_time(k + 1)

    def domain(self) -> Tuple[float, float]:
        """(start, end) in s of the covered times [start, end); empty (start == end) below 4 points."""
        if self.n_ctrl < 4:
            start = self.interval(0)[0]
            return start, start
        if self._knots is None:
            return spline_module.valid_time_range(self.n_ctrl, self.dt, self.t0, self.convention)
        return knots_module.valid_time_range(self.knot_vector())

    def covers(self, times) -> np.ndarray:
        """(times' shape) bool: start <= t < end, the one membership rule (module docstring)."""
        start, end = self.domain()
        times = float64_seconds(times, "times")  # tensors on any device, as evaluate() takes them
        return (times >= start) & (times < end)

    # --- evaluation
    def evaluate(self, times, derivatives: int = 0) -> "spline_module.SplineSample":
        """:func:`spline.evaluate` (uniform) or :func:`knots.evaluate` of this trajectory (derivatives 0, 1 or 2)."""
        if self._knots is not None:
            return knots_module.evaluate(self.control_rotations, self.control_translations, times,
                                         self.knot_vector(), derivatives)
        return spline_module.evaluate(self.control_rotations, self.control_translations, times, self.dt, self.t0,
                                      self.convention, derivatives)

    def poses(self, times) -> torch.Tensor:
        """(*times.shape, 4, 4) camera-to-world poses T_wc(t), times in the closed domain (float64 s)."""
        sample = self.evaluate(times)
        return make_pose(sample.rotation, sample.translation)

    def offsets(self, times, poses: torch.Tensor) -> Tuple[np.ndarray, np.ndarray]:
        """How far ``poses`` (F, 4, 4) lie from the curve at ``times`` (F,) s: (F,) distances (m)
        between the camera centres and (F,) angles (deg) of R(t)^T R, float64."""
        return pose_offsets(self.poses(times).detach().to("cpu", torch.float64).numpy(),
                            poses.detach().to("cpu", torch.float64).numpy())

    # --- growing and shrinking (in place)
    def push_back(self, rotation: torch.Tensor, translation: torch.Tensor, knot_time: Optional[float] = None) -> None:
        """Add control point N.  rotation (3, 3), translation (3,).  Warns on a jump > pi/2.

        knot_time: t_N in s, after t_{N-1}; None keeps the current t_N (t_{N-1} + dt unless stored).
        A time other than the current t_N makes the trajectory non-uniform and forgets the
        knots stored after N (they were assumed).
        """
        if rotation.shape != (3, 3) or translation.shape != (3,):
            raise ValueError(f"push_back expects (3, 3) and (3,), got {tuple(rotation.shape)} and {tuple(translation.shape)}")
        rotation = rotation.to(self.control_rotations)
        translation = translation.to(self.control_translations)
        if self.n_ctrl > 0:
            angle = float(torch.linalg.vector_norm(so3_log(self.control_rotations[-1].T @ rotation)))
            if angle > _ROTATION_JUMP_WARN:
                warnings.warn(f"pushed control rotation is {angle:.3f} rad from the previous one (> pi/2)")
        if knot_time is not None:
            check_float64_seconds("knot_time", knot_time)
        if knot_time is not None and float(knot_time) != self.knot_time(self.n_ctrl):
            self._set_knot(self.n_ctrl, float(knot_time))
        self.control_rotations = torch.cat([self.control_rotations, rotation[None]], dim=0)
        self.control_translations = torch.cat([self.control_translations, translation[None]], dim=0)

    def _set_knot(self, k: int, time: float) -> None:
        """t_k = time (k >= 1 after knot 0), keeping the knots before k and dropping those after it."""
        if self.n_ctrl == 0 and k == 0:
            self.t0 = time
            self._knots, self.knot_offset = (None, 0) if self._knots is None else (np.array([time]), 0)
            return
        previous = self.knot_time(k - 1)
        if not time > previous:
            raise ValueError(f"knot_time = {time!r} s must come after the previous knot, {previous!r} s")
        first = min(self.knot_offset, 0) if self._knots is not None else 0
        kept = [self.knot_time(j) for j in range(first, k)]
        self._set_knots(np.array(kept + [time], dtype=np.float64), first)

    def plan_interval_end(self, n: int, end_time: float, assumed_spacing: Optional[float] = None) -> None:
        """Decide the end time (s) of interval n before its control point arrives: t_{n+o+1} = end_time.

        Only intervals the trajectory does not cover yet (n >= N - 3) can be planned; the knots
        after it are forgotten (they were assumed).  ``assumed_spacing`` (s): the knots after it are
        assumed that far apart until they are planned (three are stored), instead of ``dt``.  The
        newest control point's weight in the newest interval depends on them: with intervals much
        shorter than the assumed spacing it shrinks, and the curve approximation, fitting the
        interval's poses through that small weight, throws the point far off.  The knot policy's
        hook (``knot_schedule.py``).
        """
        if n < self.n_ctrl - 3:
            raise ValueError(f"interval {n} is already covered by the {self.n_ctrl} control points; only "
                             f"intervals >= {max(self.n_ctrl - 3, 0)} can be planned")
        check_float64_seconds("end_time", end_time)
        check_float64_seconds("assumed_spacing", 0.0 if assumed_spacing is None else assumed_spacing)
        offset = spline_module.first_segment_offset(self.convention)
        self._set_knot(n + offset + 1, float(end_time))
        if assumed_spacing is not None:
            if not assumed_spacing > 0:
                raise ValueError(f"assumed_spacing must be > 0 s, got {assumed_spacing}")
            assumed = float(end_time) + float(assumed_spacing) * np.arange(1, 4, dtype=np.float64)
            self._knots = np.concatenate([self._knots, assumed])

    def pop_front(self) -> None:
        """Drop control point 0 and advance t0 by dt; the curve is unchanged where still defined.

        ``start_pose`` goes too (as in :meth:`window`): it is the pose of the start just dropped, and BA,
        which pins control point 0 to it, would move the new start there."""
        if self.n_ctrl <= 4:
            raise ValueError(f"pop_front would leave {self.n_ctrl - 1} control points; a cubic spline needs 4")
        self.start_pose = None
        self.control_rotations = self.control_rotations[1:]
        self.control_translations = self.control_translations[1:]
        if self._knots is None:  # t0 = origin + pops·dt, not t0 += dt, whose rounding adds up pop after pop
            if self._pops is None or self._pops[0] + self._pops[1] * self.dt != self.t0:
                self._pops = (self.t0, 0)  # the first pop, or t0 was set since
            origin, pops = self._pops[0], self._pops[1] + 1
            self._pops = (origin, pops)
            self.t0 = origin + pops * self.dt
            return
        self.t0 = self.knot_time(1)
        keep_from = max(0, -2 - (self.knot_offset - 1))  # keep knots -2.. (the basalt convention reads them)
        self._knots, self.knot_offset = self._knots[keep_from:], self.knot_offset - 1 + keep_from

    def window(self, first: int, stop: int) -> "BSplineTrajectory":
        """Control points [first, stop) as a new trajectory (views), t0 moved to knot ``first``."""
        if not 0 <= first < stop <= self.n_ctrl or stop - first < 4:
            raise ValueError(f"window [{first}, {stop}) must lie in [0, {self.n_ctrl}] with >= 4 points")
        if self._knots is None:
            return BSplineTrajectory(self.control_rotations[first:stop], self.control_translations[first:stop],
                                     self.dt, self.t0 + first * self.dt, self.convention)
        run = np.array([self.knot_time(k) for k in range(first - 2, stop + 3)], dtype=np.float64)  # all it reads
        return BSplineTrajectory(self.control_rotations[first:stop], self.control_translations[first:stop],
                                 self.dt, self.knot_time(first), self.convention, knots=run, knot_offset=-2)

    # --- tensor helpers
    def to(self, *args, **kwargs) -> "BSplineTrajectory":
        """Copy with tensors moved / cast as ``Tensor.to(*args, **kwargs)``."""
        start = None if self.start_pose is None else self.start_pose.to(*args, **kwargs)
        return BSplineTrajectory(self.control_rotations.to(*args, **kwargs),
                                 self.control_translations.to(*args, **kwargs), self.dt, self.t0, self.convention, start,
                                 **self.timing())

    def detach(self) -> "BSplineTrajectory":
        return self.with_controls(self.control_rotations, self.control_translations)

    def clone(self) -> "BSplineTrajectory":
        return BSplineTrajectory(self.control_rotations.clone(), self.control_translations.clone(), self.dt, self.t0,
                                 self.convention, None if self.start_pose is None else self.start_pose.clone(),
                                 **self.timing())

    def __repr__(self) -> str:
        start, end = self.domain()
        return (f"BSplineTrajectory(n_ctrl={self.n_ctrl}, dt={self.dt}, t0={self.t0}, uniform={self.uniform}, "
                f"convention={self.convention!r}, covers=[{start}, {end}), "
                f"dtype={self.control_translations.dtype})")
