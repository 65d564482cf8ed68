"""What tracking, local BA and global BA share: pose parametrisations, keyframe rays, one joint loop.

TS-SLAM (Sec. III-D) optimises the same objective, Eq. (10) = L_NeRF + L_DR, in four places that
differ only in which parameters move and which rays are used:

| stage | poses that move | map | rays | L_DR |
|---|---|---|---|---|
| tracking | one frame's pose | frozen | one frame | off |
| local BA refinement | window control points | frozen | window frames | in the window |
| local BA joint | window control points | optimised | window keyframes | in the window |
| global BA | control points outside the window (Co-SLAM: keyframe poses) | optimised | all keyframes + current frame | outside the window |

This module holds the pieces: :class:`PoseIncrement` (a pose as a tangent increment around a base
pose), :class:`DiscretePoses` (Co-SLAM: one pose per slot), :class:`SplinePoses` (TS-SLAM: poses
are evaluations, Eq. 5-6, of a :class:`trajectory.BSplineTrajectory` whose control points are
R_k = Exp(delta_k) R_k^0, t_k), :func:`dynamics_term` (L_DR of that trajectory, for local and
global BA), the :class:`KeyframeDatabase`, and :func:`joint_optimization`, the one loop all BA
stages run.

Rays carry a *slot* in ``frame_ids``; a pose model returns one (4, 4) pose per slot.

Layer 2.5 (shared optimisation pieces): imports config, geometry, render, losses, spline_fit,
trajectory, dynamics; never the optimisers (tracking, local_ba, global_ba) or the system.
"""

import contextlib
import dataclasses
from dataclasses import dataclass
from dataclasses import field as _field
from typing import Callable, Dict, Iterator, List, Optional, Protocol, Sequence, Tuple

import numpy as np
import torch

from . import spline_fit
from .config import DynamicsConfig
from .dynamics import trajectory_dynamics_loss
from .geometry import make_pose, orthonormalize, so3_exp
from .losses import RenderLossSettings, render_loss
from .render import RayBatch
from .times import check_float64_seconds, float64_seconds
from .trajectory import BSplineTrajectory


@contextlib.contextmanager
def frozen(module: torch.nn.Module) -> Iterator[None]:
    """Temporarily turn off gradients for every parameter of ``module`` (a frozen map)."""
    flags = [parameter.requires_grad for parameter in module.parameters()]
    for parameter in module.parameters():
        parameter.requires_grad_(False)
    try:
        yield
    finally:
        for parameter, flag in zip(module.parameters(), flags):
            parameter.requires_grad_(flag)


class PoseIncrement(torch.nn.Module):
    """Camera-to-world poses parametrised around fixed base poses.

    T(delta, t) = [Exp(delta) R_base | t]: delta (..., 3) is a world-frame rotation increment in
    rad, t (..., 3) the translation in m.  At delta = 0 the pose equals the base pose and the
    gradient is finite (no singularity at the identity).
    """

    def __init__(self, base_pose: torch.Tensor):
        super().__init__()
        base_pose = base_pose.detach()
        self.register_buffer("base_rotation", orthonormalize(base_pose[..., :3, :3]))
        self.rotation_delta = torch.nn.Parameter(torch.zeros_like(base_pose[..., :3, 3]))
        self.translation = torch.nn.Parameter(base_pose[..., :3, 3].clone())

    def forward(self) -> torch.Tensor:
        """(..., 4, 4) current camera-to-world poses."""
        return make_pose(so3_exp(self.rotation_delta) @ self.base_rotation, self.translation)

    def optimizer(self, lr_rot: float, lr_trans: float) -> torch.optim.Adam:
        return torch.optim.Adam(
            [{"params": [self.rotation_delta], "lr": lr_rot}, {"params": [self.translation], "lr": lr_trans}]
        )


class PoseModel(Protocol):
    """What :func:`joint_optimization` needs from a trajectory representation."""

    def parameter_groups(self) -> List[dict]:
        """Adam parameter groups (empty: nothing to optimise)."""

    def poses(self) -> torch.Tensor:
        """(P, 4, 4) camera-to-world poses, one per ray slot: differentiable in the parameters, and
        constants (no graph, so no point gradient downstream) when there is nothing to optimise."""


class DiscretePoses(torch.nn.Module):
    """One free pose per slot (Co-SLAM); slots listed in ``fixed`` keep their pose.

    Args:
        poses: (P, 4, 4) initial camera-to-world poses.
        fixed: (P,) bool, True for slots that must not move (Co-SLAM: keyframe 0, and the current
            frame unless ``optim_cur``).
        lr_rot, lr_trans: Adam learning rates.
    """

    def __init__(self, poses: torch.Tensor, fixed: torch.Tensor, lr_rot: float, lr_trans: float):
        super().__init__()
        self.increments = PoseIncrement(poses)
        self.register_buffer("fixed", fixed.to(device=poses.device, dtype=torch.bool))
        self.register_buffer("initial", poses.detach().clone())
        self.moves = not bool(self.fixed.all())  # any slot to optimise
        self.lr_rot, self.lr_trans = lr_rot, lr_trans

    def parameter_groups(self) -> List[dict]:
        if not self.moves:
            return []
        return [
            {"params": [self.increments.rotation_delta], "lr": self.lr_rot},
            {"params": [self.increments.translation], "lr": self.lr_trans},
        ]

    def poses(self) -> torch.Tensor:
        with contextlib.nullcontext() if self.moves else torch.no_grad():
            free_poses = self.increments()
            return torch.where(self.fixed[:, None, None], self.initial, free_poses)


class SplinePoses(torch.nn.Module):
    """Poses of ray slots evaluated on a cubic B-spline whose free control points are optimised.

    Control point k is R_k = Exp(delta_k) R_k^0 and t_k (world frame, m); only the indices in
    ``free`` get parameters, the rest are constants.  Slot s has time ``slot_times[s]`` (float64
    s); slots whose time the trajectory does not cover (:meth:`trajectory.BSplineTrajectory.covers`)
    use ``fallback_poses[s]`` (constant, e.g. the tracked pose of a frame the spline does not reach yet).

    When the trajectory has a ``start_pose``, control point 0 is not a parameter but follows
    control points 1 and 2 so that the curve keeps starting at that pose
    (:func:`spline_fit.first_control_point`): TS-SLAM's gauge, frame 0's pose fixed as Co-SLAM fixes
    keyframe 0.

    Args:
        trajectory: the :class:`trajectory.BSplineTrajectory` to start from (N control points).
        free: indices of the control points to optimise (not 0 when it has a start pose).
        slot_times: (P,) float64 seconds.
        fallback_poses: (P, 4, 4) used outside the domain.
        lr_rot, lr_trans: Adam learning rates for the increments.
    """

    def __init__(self, trajectory: BSplineTrajectory, free: Sequence[int], slot_times: np.ndarray,
                 fallback_poses: torch.Tensor, lr_rot: float, lr_trans: float):
        super().__init__()
        rotations, translations = trajectory.control_rotations, trajectory.control_translations
        start_pose = trajectory.start_pose
        if start_pose is not None and 0 in list(free):
            raise ValueError("SplinePoses: control point 0 follows start_pose and cannot also be free")
        free_mask = torch.zeros(trajectory.n_ctrl, dtype=torch.bool, device=rotations.device)
        free_mask[list(free)] = True
        self.register_buffer("free_mask", free_mask)
        self.start_pose = None if start_pose is None else start_pose.detach().to(translations)
        self.register_buffer("rotations0", rotations.detach().clone())
        self.register_buffer("translations0", translations.detach().clone())
        self.rotation_delta = torch.nn.Parameter(torch.zeros_like(translations))
        self.translation_delta = torch.nn.Parameter(torch.zeros_like(translations))
        self.dt, self.t0, self.convention = trajectory.dt, trajectory.t0, trajectory.convention
        self.knot_timing = trajectory.timing()  # the trajectory's own knot times (none when uniform)
        self.start_weights = trajectory.start_weights()  # the gauge's weights at the domain start (None: uniform)
        self.slot_times = float64_seconds(slot_times, "slot_times")
        self.slot_valid = trajectory.covers(self.slot_times)
        self.register_buffer("fallback", fallback_poses.detach().clone())
        self.moves = bool(free_mask.any())  # any control point to optimise
        self.lr_rot, self.lr_trans = lr_rot, lr_trans

    def parameter_groups(self) -> List[dict]:
        if not self.moves:
            return []
        return [{"params": [self.rotation_delta], "lr": self.lr_rot},
                {"params": [self.translation_delta], "lr": self.lr_trans}]

    def control_points(self) -> Tuple[torch.Tensor, torch.Tensor]:
        """(N, 3, 3) rotations and (N, 3) translations, differentiable in the free points."""
        mask = self.free_mask[:, None].to(self.rotation_delta.dtype)
        rotations = so3_exp(self.rotation_delta * mask) @ self.rotations0
        translations = self.translations0 + self.translation_delta * mask
        if bool(self.free_mask[1:3].any()):  # point 0 only changes when point 1 or 2 can
            rotations, translations = spline_fit.pin_first_control_point(rotations, translations, self.start_pose,
                                                                         self.start_weights)
        return rotations, translations

    def trajectory(self) -> BSplineTrajectory:
        """The current trajectory, differentiable in the free control points (detach it to keep it)."""
        rotations, translations = self.control_points()
        return BSplineTrajectory(rotations, translations, self.dt, self.t0, self.convention, self.start_pose,
                                 **self.knot_timing)

    def poses(self) -> torch.Tensor:
        """(P, 4, 4) slot poses: the spline's where it covers the slot's time, the fallback elsewhere
        (constants when no control point is free)."""
        if not self.slot_valid.any():
            return self.fallback
        inside = torch.as_tensor(self.slot_valid, device=self.fallback.device)
        spline_poses = self.fallback.clone()
        with contextlib.nullcontext() if self.moves else torch.no_grad():
            spline_poses[inside] = self.trajectory().poses(self.slot_times[self.slot_valid]).to(self.fallback.dtype)
        return spline_poses


def dynamics_term(poses: SplinePoses, time_range: Optional[Tuple[float, float]], dynamics: DynamicsConfig,
                  generator: Optional[torch.Generator]) -> Optional[Callable[[], torch.Tensor]]:
    """L_DR (Eq. 10) of the pose model's current trajectory over ``time_range`` = (start, end) s.

    Returns a callable for :func:`joint_optimization`'s ``extra_loss``, or None when the range is
    None (the regulariser is off) or empty, or when no control point is free."""
    if time_range is None or time_range[1] <= time_range[0] or not bool(poses.free_mask.any()):
        return None
    start, end = time_range
    return lambda: trajectory_dynamics_loss(poses.trajectory(), start, end, dynamics, generator)


def with_slot(rays: RayBatch, slot: int) -> RayBatch:
    """The same rays with every ``frame_ids`` set to ``slot`` (the pose they are rendered with)."""
    return RayBatch(rays.directions_cam, rays.rgb, rays.depth, torch.full_like(rays.frame_ids, slot))


def slotted(batches: Sequence[RayBatch]) -> RayBatch:
    """Concatenate ray batches, batch k relabelled to slot k."""
    return RayBatch.cat([with_slot(rays, slot) for slot, rays in enumerate(batches)])


class KeyframeDatabase:
    """Camera-frame rays of every keyframe (Co-SLAM keeps ``n_pixels`` = 5 % of each one's pixels).

    Keyframes get *slots* 0, 1, 2, ... in insertion order; :attr:`frame_indices` and
    :attr:`timestamps` map slots back to frames.  The rays are kept joined in one pool, slot k's
    rows labelled k, whose capacity doubles when it is full (on the CPU, rows not yet written take
    no memory; a GPU reserves them).  Global BA draws from every keyframe's rays at each call, and
    joining them anew for each call took 0.4-1.2 s at 600 keyframes of 640x480.  The pool's rows
    and their order are the join's.
    """

    def __init__(self) -> None:
        self._pool: Optional[RayBatch] = None  # capacity rows; the first self._offsets[-1] are keyframes' rays
        self._offsets: List[int] = [0]  # slot k's rows: self._offsets[k] .. self._offsets[k + 1]
        self.frame_indices: List[int] = []
        self.timestamps: List[float] = []

    def __len__(self) -> int:
        return len(self.frame_indices)

    def add(self, frame_index: int, timestamp: float, rays: RayBatch) -> int:
        """Store a keyframe's rays (their ``frame_ids`` become the slot); returns its slot."""
        check_float64_seconds("timestamp", timestamp)
        slot = len(self)
        start, end = self._offsets[-1], self._offsets[-1] + len(rays)
        capacity = 0 if self._pool is None else len(self._pool)
        if end > capacity:
            self._pool = _grown(self._pool, start, rays, max(end, 2 * capacity))
        for name, values in zip(_RAY_FIELDS, _ray_values(with_slot(rays, slot))):
            getattr(self._pool, name)[start:end] = values
        self._offsets.append(end)
        self.frame_indices.append(int(frame_index))
        self.timestamps.append(float(timestamp))
        return slot

    def slot_rays(self, slot: int) -> RayBatch:
        """The rays of keyframe ``slot`` (a view of the pool; ``frame_ids`` = slot)."""
        return self._pool.subset(slice(self._offsets[slot], self._offsets[slot + 1]))

    def rays(self, slots: Optional[Sequence[int]] = None) -> RayBatch:
        """Rays of ``slots`` (default all) with ``frame_ids`` = position in ``slots``: all of them is
        a view of the pool, a subset a new batch.  ValueError when there is no keyframe."""
        if slots is None and len(self) > 0:
            return self._pool.subset(slice(0, self._offsets[-1]))
        slots = range(len(self)) if slots is None else slots
        return slotted([self.slot_rays(slot) for slot in slots])


_RAY_FIELDS = [f.name for f in dataclasses.fields(RayBatch)]


def _ray_values(rays: RayBatch) -> List[torch.Tensor]:
    return [getattr(rays, name) for name in _RAY_FIELDS]


def _grown(pool: Optional[RayBatch], used: int, like: RayBatch, capacity: int) -> RayBatch:
    """A pool of ``capacity`` rows holding the first ``used`` rows of ``pool`` (None: empty), with
    the dtypes and device of ``like``; the rest unwritten (``torch.empty``)."""
    grown = [torch.empty((capacity, *values.shape[1:]), dtype=values.dtype, device=values.device)
             for values in _ray_values(like)]
    if pool is not None:
        for target, values in zip(grown, _ray_values(pool)):
            target[:used] = values[:used]
    return RayBatch(*grown)


@dataclass
class BAStats:
    """Per-call record of a joint optimisation."""

    losses: List[float] = _field(default_factory=list)
    terms: List[Dict[str, float]] = _field(default_factory=list)
    pose_steps: int = 0


PERMUTATION_POOL_LIMIT = 2**16
"""Pools up to this many rays are drawn from by a permutation of the whole pool; larger ones by
Floyd's algorithm, whose cost does not grow with the pool (see :func:`draw_rays`)."""


def draw_rays(pool: RayBatch, n_rays: int, generator: Optional[torch.Generator]) -> RayBatch:
    """``n_rays`` rays of ``pool`` uniformly without replacement (all if it holds no more).

    Up to :data:`PERMUTATION_POOL_LIMIT` rays, the first ``n_rays`` of ``torch.randperm`` of the
    pool, as every run of the CPU presets draws (about 1000 keyframe rays per keyframe there, so
    20,000 after 100 frames).  A permutation costs time in the pool's size, and global BA draws
    from every keyframe's rays each iteration: at 640x480, 300 keyframes hold 4.6 million rays,
    whose permutation took longer than the rest of the iteration.  Larger pools are drawn from by
    :func:`floyd_sample`, equally uniform, in time proportional to ``n_rays``.
    """
    if n_rays >= len(pool):
        return pool
    if len(pool) <= PERMUTATION_POOL_LIMIT:
        index = torch.randperm(len(pool), generator=generator)[:n_rays]
    else:
        index = floyd_sample(len(pool), n_rays, generator)
    return pool.subset(index.to(pool.depth.device))


def floyd_sample(n: int, k: int, generator: Optional[torch.Generator]) -> torch.Tensor:
    """(k,) int64: k distinct indices in [0, n), every k-subset equally likely (Floyd's algorithm:
    for j = n - k .. n - 1 take t uniform in [0, j], or j itself when t is already taken).  The
    uniform numbers come from ``generator`` (float64, exact for n below 2**53)."""
    uniforms = torch.rand(k, generator=generator, dtype=torch.float64).tolist()
    taken, picks = set(), []
    for j, uniform in zip(range(n - k, n), uniforms):
        pick = min(int(uniform * (j + 1)), j)  # uniform in [0, j]; min() guards u * (j + 1) rounding up to j + 1
        pick = j if pick in taken else pick
        taken.add(pick)
        picks.append(pick)
    return torch.tensor(picks, dtype=torch.long)


def iteration_loss(
    field_model: torch.nn.Module,
    ray_sources: Sequence[Tuple[RayBatch, int]],
    poses: PoseModel,
    loss_settings: RenderLossSettings,
    generator: Optional[torch.Generator],
    extra_loss: Optional[Callable[[], torch.Tensor]],
    smoothness: bool,
) -> Tuple[torch.Tensor, Dict[str, float]]:
    """One iteration's loss of :func:`joint_optimization`: Eq. (4) on fresh rays plus ``extra_loss()``.

    Draws ``n`` rays from every ``(pool, n)`` of ``ray_sources`` and renders each with its slot's
    pose.  Returns the scalar loss and its weighted terms as floats (``dynamics`` for the extra)."""
    rays = RayBatch.cat([draw_rays(pool, n, generator) for pool, n in ray_sources if n > 0 and len(pool) > 0])
    c2w = poses.poses()[rays.frame_ids]  # (R, 4, 4); constants when nothing is optimised (no point gradient)
    loss, terms = render_loss(field_model, rays, c2w, loss_settings, generator=generator, smoothness=smoothness)
    if extra_loss is not None:
        regulariser = extra_loss()
        terms = dict(terms, dynamics=float(regulariser.detach()))
        loss = loss + regulariser
    return loss, terms


def joint_optimization(
    field_model: torch.nn.Module,
    map_optimizer: Optional[torch.optim.Optimizer],
    ray_sources: Sequence[Tuple[RayBatch, int]],
    poses: PoseModel,
    loss_settings: RenderLossSettings,
    iters: int,
    generator: Optional[torch.Generator] = None,
    extra_loss: Optional[Callable[[], torch.Tensor]] = None,
    optimise_map: bool = True,
    pose_accum_step: int = 1,
    smoothness: Optional[bool] = None,
) -> BAStats:
    """Minimise Eq. (10) over the map (optionally) and the parameters of ``poses``.

    Each iteration takes :func:`iteration_loss` (rays drawn from ``ray_sources``, whose
    ``frame_ids`` index ``poses.poses()``, plus ``extra_loss()``) and one map-optimizer step (if
    ``optimise_map``); the pose optimizer (a fresh Adam per call) steps every ``pose_accum_step``
    iterations on the gradients summed in between (Co-SLAM's ``pose_accum_step``).

    Args:
        field_model: the scene field.
        map_optimizer: the run's map optimizer (ignored when ``optimise_map`` is False).
        ray_sources: list of (RayBatch pool, rays per iteration).
        poses: a :class:`PoseModel`.
        loss_settings: rendering and loss settings of :func:`render_loss`.
        iters: iterations.
        generator: random generator for ray draws and depth-sample jitter.
        extra_loss: callable returning a scalar added to every iteration's loss (L_DR).
        optimise_map: False keeps the map frozen (local BA refinement).
        pose_accum_step: pose steps every this many iterations.
        smoothness: add the feature-smoothness term (default: when the map is optimised).

    Returns:
        :class:`BAStats`.  Raises FloatingPointError on a non-finite loss.
    """
    groups = poses.parameter_groups()
    pose_optimizer = torch.optim.Adam(groups) if groups else None
    smoothness = optimise_map if smoothness is None else smoothness
    stats = BAStats()
    context = contextlib.nullcontext() if optimise_map else frozen(field_model)
    with context:
        for iteration in range(iters):
            loss, terms = iteration_loss(field_model, ray_sources, poses, loss_settings, generator, extra_loss,
                                         smoothness)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"joint optimisation loss is not finite at iteration {iteration}: {terms}")
            if optimise_map:
                map_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if optimise_map:
                map_optimizer.step()
            if pose_optimizer is not None and (iteration + 1) % pose_accum_step == 0:
                pose_optimizer.step()
                pose_optimizer.zero_grad(set_to_none=True)
                stats.pose_steps += 1
            stats.losses.append(float(loss.detach()))
            stats.terms.append({key: float(value) for key, value in terms.items()})
    return stats
