"""Tracking: per-frame camera pose optimisation with the map frozen.

TS-SLAM Sec. III-D "Tracking Thread": each new frame's camera-to-world pose is initialised with a
constant-velocity model and optimised on its own by minimising Eq. (10) with lambda_1 = lambda_2 = 0,
i.e. the reconstruction loss L_NeRF of Eq. (4), while the map f_theta stays fixed.  The behaviour
follows Co-SLAM's ``tracking_render`` (its ``coslam.py``, commit 3bb904e):

* one pixel set per frame (uniform, away from the border), reused for every iteration;
* a fresh Adam per frame with separate rotation / translation learning rates;
* the pose of the lowest-loss iteration is kept (``best``); as in Co-SLAM the loss of iteration k
  is evaluated at the pose *before* step k, so the candidates are the poses of iterations 0..N-1.
  The last iteration's backward pass and step would only make a pose that is never evaluated, so
  they are left out (Co-SLAM runs them): the kept pose and every loss are the same, bit for bit.

Differs from Co-SLAM: the rotation is optimised as a tangent-space increment ``delta`` with
R = Exp(delta) R_init (no singularity at the identity, no NaN from a Rodrigues formula that divides
by |w|); Co-SLAM optimises an absolute axis-angle or quaternion.  The map is frozen by turning off
``requires_grad`` of its parameters instead of computing map gradients and not stepping them.

Layer 3 (optimiser): uses geometry, render, losses, bundle; never local_ba or global_ba.
Taught in notebooks/05_tracking.ipynb.
"""

from dataclasses import dataclass
from typing import List, Optional

import torch

from .config import Config, TrackingConfig
from .bundle import PoseIncrement, frozen
from .geometry import invert_pose, make_pose, orthonormalize, so3_exp, so3_log
from .losses import RenderLossSettings, render_loss
from .render import RayBatch


SPACING_RATIO_LIMIT = 1.5
"""Frame spacings whose ratio lies within [1 / this, this] count as equal for the constant-velocity
prediction: real recordings jitter by up to 0.87-1.16 (TUM at 30 Hz), a dropped frame doubles it."""


def motion_scale(timestamps, i: int) -> float:
    """(t_i - t_{i-1}) / (t_{i-1} - t_{i-2}) when frame i follows a gap or a change of frame rate
    (the ratio outside [1 / :data:`SPACING_RATIO_LIMIT`, :data:`SPACING_RATIO_LIMIT`]), else 1 (the
    prediction as Co-SLAM makes it, which assumes equal spacing).  ``timestamps``: (N,) s."""
    if i < 2:
        return 1.0
    ratio = float(timestamps[i] - timestamps[i - 1]) / float(timestamps[i - 1] - timestamps[i - 2])
    return ratio if not 1.0 / SPACING_RATIO_LIMIT <= ratio <= SPACING_RATIO_LIMIT else 1.0


def constant_velocity_init(previous: torch.Tensor, before_previous: Optional[torch.Tensor],
                           scale: float = 1.0) -> torch.Tensor:
    """Constant-velocity prediction T_t = (T_{t-1} T_{t-2}^-1) T_{t-1} (Co-SLAM ``const_speed``).

    Args:
        previous: (4, 4) camera-to-world pose of frame t-1.
        before_previous: (4, 4) pose of frame t-2, or None for the second frame (then T_{t-1}).
        scale: the motion from t-2 to t-1 repeated this many times (:func:`motion_scale`, the
            ratio of the frame spacings): T_t = T_{t-1} Δ^scale with the body-frame motion
            Δ = T_{t-2}^-1 T_{t-1}, its rotation Exp(scale Log R_Δ) and its translation scale t_Δ.
            At 1 the formula above (the same motion: T_{t-1} Δ = T_{t-1} T_{t-2}^-1 T_{t-1}).

    Returns:
        (4, 4) predicted camera-to-world pose of frame t.  At ``scale`` 1 the relative motion is
        applied in the world frame, exactly as Co-SLAM does (the same pose as T_{t-1} Δ); the
        rotation is projected back onto SO(3) (without it the float32 drift grows about 2.4 times
        every frame and the poses blow up after ~20 frames).
    """
    if before_previous is None:
        return previous.clone()
    if scale == 1.0:
        predicted = previous @ invert_pose(before_previous) @ previous
    else:
        motion = invert_pose(before_previous) @ previous  # Δ, body frame of t-2
        rotation = so3_exp(scale * so3_log(orthonormalize(motion[:3, :3])))
        predicted = previous @ make_pose(rotation, scale * motion[:3, 3])
    return make_pose(orthonormalize(predicted[:3, :3]), predicted[:3, 3])


@dataclass
class TrackingResult:
    """What :func:`track_frame` returns."""

    pose: torch.Tensor
    """(4, 4) camera-to-world pose kept (the best one if ``best``)."""
    losses: List[float]
    """Loss of every iteration, evaluated at the pose before that iteration's step."""
    best_iteration: int
    """Iteration whose pose was kept."""


def track_frame(
    field: torch.nn.Module,
    rays: RayBatch,
    init_pose: torch.Tensor,
    tracking: TrackingConfig,
    loss_settings: RenderLossSettings,
    generator: Optional[torch.Generator] = None,
) -> TrackingResult:
    """Optimise one frame's camera-to-world pose against a frozen map.

    Args:
        field: the scene field (its parameters are frozen for the duration of the call).
        rays: (R,) camera-frame rays of this frame with their colour and depth targets.  The same
            rays are used in every iteration.
        init_pose: (4, 4) initial camera-to-world pose (e.g. :func:`constant_velocity_init`).
        tracking: iterations, learning rates and ``best``.
        loss_settings: rendering and loss settings of :func:`render_loss`.
        generator: random generator for the depth-sample jitter.

    Returns:
        :class:`TrackingResult` with the kept pose, detached.
    """
    if not isinstance(tracking, TrackingConfig):
        raise TypeError(f"track_frame takes the tracking settings (cfg.tracking, a TrackingConfig), got "
                        f"{type(tracking).__name__}")
    if not isinstance(init_pose, torch.Tensor) or init_pose.shape != (4, 4):
        raise TypeError(f"track_frame's init_pose must be one (4, 4) torch tensor (camera-to-world), got "
                        f"{type(init_pose).__name__} of shape {tuple(getattr(init_pose, 'shape', ()))}")
    pose_parameters = PoseIncrement(init_pose)
    optimizer = pose_parameters.optimizer(tracking.lr_rot, tracking.lr_trans)
    losses: List[float] = []
    best_loss = float("inf")
    best_pose = init_pose.detach().clone()
    best_iteration = 0
    with frozen(field):
        for iteration in range(tracking.iters):
            pose = pose_parameters()
            loss, _ = render_loss(field, rays, pose, loss_settings, generator=generator)
            value = float(loss.detach())
            losses.append(value)
            if not torch.isfinite(loss):
                break
            if not tracking.best or value < best_loss:
                best_loss, best_pose, best_iteration = value, pose.detach().clone(), iteration
            if iteration == tracking.iters - 1:
                break  # a step now would make a pose that no iteration evaluates
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
    return TrackingResult(pose=best_pose, losses=losses, best_iteration=best_iteration)


def depth_problem(cfg: Config, depth: torch.Tensor) -> str:
    """'; ' + what is wrong with a frame's (H, W) depth in metres (0 = missing) when most of it cannot
    be used: under 10 % of the pixels measured, or most of the measured depth beyond
    min(``data.depth_trunc``, ``render.far``); '' otherwise.  Appended to a tracking failure's message."""
    measured = depth[depth > 0]
    if measured.numel() < 0.1 * depth.numel():
        share = 100 * measured.numel() / depth.numel()
        return f"; only {share:.0f} % of this frame's pixels have a depth: check its depth image"
    limit = min(cfg.data.depth_trunc, cfg.render.far)
    beyond = float((measured >= limit).double().mean())
    if beyond > 0.5:
        return (f"; {100 * beyond:.0f} % of this frame's measured depth lies beyond {limit:g} m (data.depth_trunc, "
                f"render.far): check its depth image")
    return ""


def check_ray_budget(cfg: Config, height: int, width: int) -> None:
    """ValueError naming the key when a frame of ``height`` x ``width`` px (after crop and resize)
    has fewer pixels than a step samples: tracking inside ``tracking.ignore_edge``, the first map."""
    edge = cfg.tracking.ignore_edge
    inner = max(0, height - 2 * edge) * max(0, width - 2 * edge)
    if inner == 0:
        raise ValueError(f"tracking.ignore_edge = {edge} px leaves no pixel of the {width}x{height} frames; "
                         f"expected < {min(height, width) // 2 + min(height, width) % 2}")
    if cfg.tracking.n_rays > inner:
        raise ValueError(f"tracking.n_rays = {cfg.tracking.n_rays} is more than the {inner} pixels of a {width}x{height} "
                         f"frame inside tracking.ignore_edge = {edge} px")
    if cfg.mapping.first_n_rays > height * width:
        raise ValueError(f"mapping.first_n_rays = {cfg.mapping.first_n_rays} is more than the {height * width} pixels "
                         f"of a {width}x{height} frame")
