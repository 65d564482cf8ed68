"""Tracking and the shared BA pieces (tracking.py, bundle.py), checked against an exact map.

The oracle: an *analytic* scene (the procedural room of tsslam_ref.synthetic) wrapped as a field,
frames rendered from it at known poses.  With an exact map the true pose is the loss minimum, so
tracking from a perturbed start must move towards it.
"""

import copy

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import config, spline, tracking
from tsslam_ref.analytic import AnalyticField
from tsslam_ref.bundle import (DiscretePoses, KeyframeDatabase, PoseIncrement, SplinePoses, dynamics_term, frozen,
                               iteration_loss, joint_optimization)
from tsslam_ref.bundle import draw_rays as bundle_draw
from tsslam_ref.dynamics import trajectory_dynamics_loss
from tsslam_ref.geometry import invert_pose, make_pose, so3_exp, so3_log
from tsslam_ref.render import RayBatch, frame_rays, rays_to_world, sample_pixels
from tsslam_ref.trajectory import BSplineTrajectory
from tsslam_ref.synthetic import ProceduralRoom, builtin_trajectory, default_intrinsics, render_rgbd
from tsslam_ref.losses import RenderLossSettings, render_loss
from tsslam_ref.tracking import check_ray_budget, constant_velocity_init, track_frame


@pytest.fixture(scope="module")
def scene_setup():
    scene = ProceduralRoom(seed=0)
    intrinsics = default_intrinsics(80, 60)
    pose = builtin_trajectory(np.array([0.5]))[0]
    rgb, depth = render_rgbd(scene, pose, intrinsics, clean=True)
    cfg = config.tiny()
    cfg.render.n_samples, cfg.render.n_range_d = 24, 11
    return scene, intrinsics, pose, rgb, depth, cfg


def _rays(rgb, depth, intrinsics, n, seed, frame_id=0):
    generator = torch.Generator().manual_seed(seed)
    rows, cols = sample_pixels(depth.shape[0], depth.shape[1], n, ignore_edge=2, generator=generator)
    return frame_rays(rgb, depth, intrinsics, rows, cols, frame_id=frame_id)


def _pose_error(a: torch.Tensor, b: torch.Tensor):
    relative = invert_pose(a) @ b
    return float(torch.linalg.vector_norm(relative[:3, 3])), float(torch.linalg.vector_norm(so3_log(relative[:3, :3])))


def _perturb(pose: torch.Tensor, rotvec, translation) -> torch.Tensor:
    delta = make_pose(so3_exp(torch.tensor(rotvec, dtype=pose.dtype)), torch.tensor(translation, dtype=pose.dtype))
    return delta @ pose


def test_constant_velocity_init_is_exact_for_constant_world_motion():
    """T_k = M^k T_0 (a constant world-frame motion M) is predicted exactly from T_{k-1}, T_{k-2}."""
    step = make_pose(so3_exp(torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)), torch.tensor([0.1, 0.0, -0.05], dtype=torch.float64))
    start = make_pose(so3_exp(torch.tensor([0.3, 0.2, -1.0], dtype=torch.float64)), torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64))
    poses = [start]
    for _ in range(3):
        poses.append(step @ poses[-1])
    predicted = constant_velocity_init(poses[2], poses[1])
    assert torch.allclose(predicted, poses[3], atol=1e-12)
    assert torch.equal(constant_velocity_init(poses[0], None), poses[0])


def test_across_a_gap_the_prediction_repeats_the_motion_once_per_missing_spacing():
    """Frames at 0, 1/30 and 6/30 s (four dropped): Co-SLAM's prediction repeats one frame's motion
    and starts tracking four frames' motion away.  Oracle (scipy): a camera turning at a constant
    rate about its own centre, and one moving at a constant body-frame velocity, six spacings on
    from frame 0; a jitter of 1.16 (real TUM stamps) and equal spacing keep Co-SLAM's formula."""
    assert tracking.motion_scale(np.array([0.0, 1 / 30, 6 / 30]), 2) == pytest.approx(5.0)
    assert tracking.motion_scale(np.array([0.0, 0.2, 0.2 + 0.2 / 6]), 2) == pytest.approx(1 / 6)
    assert tracking.motion_scale(np.array([0.0, 0.032, 0.032 + 0.032 * 1.16]), 2) == 1.0
    assert tracking.motion_scale(np.array([0.0, 0.032]), 1) == 1.0
    start = make_pose(so3_exp(torch.tensor([0.3, 0.2, -1.0], dtype=torch.float64)), torch.tensor([1.0, 2.0, 0.5],
                                                                                                  dtype=torch.float64))
    rate = np.array([0.01, 0.02, -0.03])  # rad per spacing, body frame
    turning = [start @ make_pose(torch.from_numpy(Rotation.from_rotvec(k * rate).as_matrix()), torch.zeros(3,
                                 dtype=torch.float64)) for k in (0, 1, 6)]
    predicted = constant_velocity_init(turning[1], turning[0], scale=5.0)
    assert torch.allclose(predicted, turning[2], atol=1e-12)
    velocity = torch.tensor([0.01, -0.004, 0.02], dtype=torch.float64)  # m per spacing, body frame
    moving = [start @ make_pose(torch.eye(3, dtype=torch.float64), k * velocity) for k in (0, 1, 6)]
    assert torch.allclose(constant_velocity_init(moving[1], moving[0], scale=5.0), moving[2], atol=1e-12)
    step = make_pose(so3_exp(torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)), 0.1 * velocity)
    general = [start, step @ start]  # a turn and a move at once: at scale 1, Co-SLAM's formula M T_{t-1}
    assert torch.allclose(constant_velocity_init(general[1], general[0], scale=1.0), step @ general[1], atol=1e-12)


def _quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z), normalised first (as pytorch3d's, which Co-SLAM uses on ScanNet)."""
    w, x, y, z = q / q.norm()
    return torch.stack([torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
                        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
                        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])])


def test_the_scannet_rotation_rate_turns_as_far_per_step_as_coslams_quaternion():
    """Co-SLAM optimises a quaternion on ScanNet at lr 1e-3; Adam moves each of its components by
    about lr, which turns the camera about twice as far as a tangent increment at the same lr.
    Oracle: one Adam step of each parametrisation on the same loss from ten random rotations; the
    preset's rates (tracking and BA) must turn within 25 % of the quaternion's step."""
    scannet = config.load("scannet")
    rng = np.random.default_rng(0)
    for _ in range(10):
        start = torch.from_numpy(Rotation.random(random_state=rng).as_matrix())
        target = torch.from_numpy(Rotation.random(random_state=rng).as_matrix())
        quaternion = torch.tensor(np.roll(Rotation.from_matrix(start.numpy()).as_quat(), 1), requires_grad=True)
        delta = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        turns = []
        for parameter, lr, rotation in ((quaternion, 1e-3, lambda: _quaternion_to_matrix(quaternion)),
                                        (delta, scannet.tracking.lr_rot, lambda: so3_exp(delta) @ start)):
            optimizer = torch.optim.Adam([parameter], lr=lr)
            ((rotation() - target) ** 2).sum().backward()
            optimizer.step()
            turns.append(Rotation.from_matrix((rotation() @ start.T).detach().numpy()).magnitude())
        assert 0.8 < turns[1] / turns[0] < 1.25, turns
    assert scannet.mapping.lr_rot == scannet.tracking.lr_rot


def test_pose_increment_starts_at_base_and_has_finite_gradients_at_zero():
    base = make_pose(so3_exp(torch.tensor([[0.0, 0.0, 0.0], [1.0, -2.0, 0.5]], dtype=torch.float64)),
                     torch.tensor([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]], dtype=torch.float64))
    increment = PoseIncrement(base)
    assert torch.allclose(increment(), base, atol=1e-15)
    increment().sum().backward()
    assert torch.isfinite(increment.rotation_delta.grad).all()
    assert torch.autograd.gradcheck(lambda d: make_pose(so3_exp(d) @ base[:, :3, :3], base[:, :3, 3]),
                                    (torch.zeros(2, 3, dtype=torch.float64, requires_grad=True),))


def test_pose_increment_turns_the_base_rotation_in_the_world_frame():
    """T(delta, t) = [Exp(delta) R_base | t] (the docstring: delta is a world-frame increment, applied
    after the base).  Oracle: scipy's Rotation.from_rotvec(delta) @ R_base; the body-frame
    R_base Exp(delta) differs by about 0.1 here."""
    base_rotation = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    delta = np.array([0.05, 0.2, -0.1])
    base = torch.eye(4, dtype=torch.float64)
    base[:3, :3], base[:3, 3] = torch.as_tensor(base_rotation), torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    increment = PoseIncrement(base)
    with torch.no_grad():
        increment.rotation_delta.copy_(torch.as_tensor(delta))
    expected = Rotation.from_rotvec(delta).as_matrix() @ base_rotation
    pose = increment().detach().numpy()
    np.testing.assert_allclose(pose[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], [1.0, 2.0, 3.0], atol=0)
    assert np.abs(base_rotation @ Rotation.from_rotvec(delta).as_matrix() - expected).max() > 0.05


def test_spline_control_point_increments_turn_the_base_rotation_in_the_world_frame():
    """SplinePoses: R_k = Exp(delta_k) R_k^0 (the docstring; local BA and TS-SLAM's global BA move the
    control points by it), as PoseIncrement does for one pose; a point that is not free keeps R_k^0
    whatever its increment holds.  Oracle: scipy's Rotation.from_rotvec(delta) @ R_k^0; the
    body-frame R_k^0 Exp(delta) differs by about 0.1 here."""
    bases = Rotation.from_rotvec([[0.4, -1.1, 0.7], [0.2, 0.3, -0.9], [-0.6, 0.1, 0.5], [1.0, 0.4, 0.2],
                                  [0.3, -0.5, 0.8], [0.0, 0.9, -0.4]]).as_matrix()
    translations = torch.arange(18, dtype=torch.float64).reshape(6, 3) * 0.1
    trajectory = BSplineTrajectory(torch.as_tensor(bases), translations, 0.25, 0.0)
    model = SplinePoses(trajectory, [2, 3], np.array([0.5, 0.6]), torch.eye(4, dtype=torch.float64).repeat(2, 1, 1),
                        1e-2, 1e-2)
    deltas = np.array([[0.05, 0.2, -0.1], [-0.15, 0.1, 0.12]])
    with torch.no_grad():
        model.rotation_delta[2:4] = torch.as_tensor(deltas)
        model.rotation_delta[4] = torch.tensor([0.3, 0.3, 0.3])  # not free: no effect
    rotations, moved = (value.detach().numpy() for value in model.control_points())
    for k, delta in zip((2, 3), deltas):
        expected = Rotation.from_rotvec(delta).as_matrix() @ bases[k]
        np.testing.assert_allclose(rotations[k], expected, atol=1e-12)
        assert np.abs(bases[k] @ Rotation.from_rotvec(delta).as_matrix() - expected).max() > 0.05
    np.testing.assert_allclose(rotations[[0, 1, 4, 5]], bases[[0, 1, 4, 5]], atol=0)
    np.testing.assert_allclose(moved, translations.numpy(), atol=0)


def test_frozen_restores_each_parameter_flag_it_found():
    """By hand: a module with one trainable and one already-frozen parameter; inside ``frozen``
    neither needs a gradient, afterwards each is back as it was (the frozen one stays frozen)."""
    module = torch.nn.Linear(2, 2)
    module.bias.requires_grad_(False)
    with frozen(module):
        assert [parameter.requires_grad for parameter in module.parameters()] == [False, False]
    assert (module.weight.requires_grad, module.bias.requires_grad) == (True, False)


def test_tracking_recovers_a_perturbed_pose_against_an_exact_map(scene_setup):
    scene, intrinsics, pose, rgb, depth, cfg = scene_setup
    field = AnalyticField(scene, cfg.render.truncation)
    true_pose = torch.as_tensor(pose, dtype=torch.float32)
    start = _perturb(true_pose, [0.0, 0.02, -0.015], [0.03, -0.02, 0.02])
    cfg.tracking.iters, cfg.tracking.lr_rot, cfg.tracking.lr_trans, cfg.tracking.best = 60, 3e-3, 3e-3, True
    rays = _rays(rgb, depth, intrinsics, 512, seed=1)
    result = track_frame(field, rays, start, cfg.tracking, RenderLossSettings.from_config(cfg),
                         generator=torch.Generator().manual_seed(2))
    start_t, start_r = _pose_error(start, true_pose)
    end_t, end_r = _pose_error(result.pose, true_pose)
    assert end_t < 0.3 * start_t and end_r < 0.5 * start_r, (start_t, end_t, start_r, end_r)
    assert result.losses[result.best_iteration] == min(result.losses)
    assert result.losses[-1] < 0.5 * result.losses[0]


def test_tracking_keeps_the_pose_before_the_step_of_the_best_iteration(scene_setup):
    """With best=False the kept pose is the one evaluated last (Co-SLAM): the last step is unused."""
    scene, intrinsics, pose, rgb, depth, cfg = scene_setup
    field = AnalyticField(scene, cfg.render.truncation)
    start = _perturb(torch.as_tensor(pose, dtype=torch.float32), [0.0, 0.0, 0.01], [0.02, 0.0, 0.0])
    cfg.tracking.iters, cfg.tracking.best = 1, False
    result = track_frame(field, _rays(rgb, depth, intrinsics, 128, seed=3), start, cfg.tracking,
                         RenderLossSettings.from_config(cfg))
    assert torch.allclose(result.pose, start, atol=1e-6)


def test_tracking_equals_the_plain_loop_that_also_steps_after_the_last_iteration(scene_setup):
    """track_frame leaves out the last backward pass and step; the oracle, a plain Co-SLAM loop that
    runs them, keeps the same pose and losses bit for bit (the step it adds is never evaluated)."""
    scene, intrinsics, pose, rgb, depth, base_cfg = scene_setup
    cfg = copy.deepcopy(base_cfg)
    field = AnalyticField(scene, cfg.render.truncation)
    start = _perturb(torch.as_tensor(pose, dtype=torch.float32), [0.01, -0.02, 0.01], [0.02, -0.01, 0.03])
    rays = _rays(rgb, depth, intrinsics, 256, seed=7)
    settings = RenderLossSettings.from_config(cfg)
    for best in (True, False):
        cfg.tracking.iters, cfg.tracking.best = 6, best
        result = track_frame(field, rays, start, cfg.tracking, settings, generator=torch.Generator().manual_seed(8))
        increment = PoseIncrement(start)
        optimizer = increment.optimizer(cfg.tracking.lr_rot, cfg.tracking.lr_trans)
        generator, losses, kept, kept_loss = torch.Generator().manual_seed(8), [], None, float("inf")
        for _ in range(cfg.tracking.iters):
            current = increment()
            loss, _ = render_loss(field, rays, current, settings, generator=generator)
            losses.append(float(loss.detach()))
            if not best or losses[-1] < kept_loss:
                kept, kept_loss = current.detach().clone(), losses[-1]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        assert result.losses == losses
        assert torch.equal(result.pose, kept)
        assert not torch.equal(increment().detach(), kept)  # the oracle's extra step did move the pose


def test_joint_optimization_moves_free_poses_only_and_accumulates(scene_setup):
    """Two keyframe slots, slot 0 fixed; with the map frozen only slot 1 moves, towards the truth."""
    scene, intrinsics, pose, rgb, depth, cfg = scene_setup
    field = AnalyticField(scene, cfg.render.truncation)
    second_pose = builtin_trajectory(np.array([0.8]))[0]
    rgb2, depth2 = render_rgbd(scene, second_pose, intrinsics, clean=True)
    truth = torch.as_tensor(np.stack([pose, second_pose]), dtype=torch.float32)
    initial = truth.clone()
    initial[1] = _perturb(truth[1], [0.0, -0.015, 0.0], [-0.02, 0.03, 0.0])
    database = KeyframeDatabase()
    database.add(0, 0.5, _rays(rgb, depth, intrinsics, 400, seed=4))
    database.add(1, 0.8, _rays(rgb2, depth2, intrinsics, 400, seed=5))
    model = DiscretePoses(initial, torch.tensor([True, False]), lr_rot=3e-3, lr_trans=3e-3)
    stats = joint_optimization(field, None, [(database.rays(), 512)], model, RenderLossSettings.from_config(cfg), iters=90,
                               generator=torch.Generator().manual_seed(6), optimise_map=False, pose_accum_step=3)
    assert stats.pose_steps == 30
    result = model.poses().detach()
    assert torch.equal(result[0], initial[0])
    before, _ = _pose_error(initial[1], truth[1])
    after, _ = _pose_error(result[1], truth[1])
    assert after < 0.6 * before, (before, after)  # Adam at lr 3e-3 with sample jitter settles near 1 cm


def test_joint_optimization_steps_the_poses_only_after_every_full_accumulation(scene_setup):
    """Co-SLAM's pose_accum_step k: a pose step after iterations k, 2k, ... (1-based), on the summed
    gradients.  By hand for k = 2: 1 iteration gives no step (the pose stays where it started),
    5 iterations give 2 steps."""
    scene, intrinsics, pose, rgb, depth, cfg = scene_setup
    field = AnalyticField(scene, cfg.render.truncation)
    start = _perturb(torch.as_tensor(pose, dtype=torch.float32), [0.0, 0.01, 0.0], [0.02, 0.0, 0.0])[None]
    sources = [(_rays(rgb, depth, intrinsics, 64, seed=12), 64)]
    for iters, steps in ((1, 0), (5, 2)):
        model = DiscretePoses(start, torch.tensor([False]), lr_rot=3e-3, lr_trans=3e-3)
        stats = joint_optimization(field, None, sources, model, RenderLossSettings.from_config(cfg), iters=iters,
                                   generator=torch.Generator().manual_seed(13), optimise_map=False, pose_accum_step=2)
        assert stats.pose_steps == steps
        moved = float((model.poses().detach() - start).abs().max())
        assert (moved < 1e-6) == (steps == 0), moved  # one Adam step moves a coordinate by ~lr = 3e-3


def test_the_dynamics_term_is_added_to_the_ba_loss_and_its_gradients(scene_setup):
    """Eq. (10) = L_NeRF + L_DR.  A zig-zag spline (accelerations of several m/s^2 against a_max =
    5 m/s^2) near the frame's pose, two slots rendered with it; the same ray draws and depth jitter
    with and without the term.  Oracle: trajectory_dynamics_loss of a separate copy of the starting
    trajectory at the same sample times; its value and its gradient in the free control
    translations must be exactly the difference (loss and gradient) the term makes."""
    scene, intrinsics, pose, rgb, depth, cfg = scene_setup
    field = AnalyticField(scene, cfg.render.truncation)
    n_ctrl, dt, t0, free = 6, 0.25, 0.0, [2, 3, 4, 5]
    zigzag = torch.tensor([[0.0, 0.0, 0.0], [0.06, -0.04, 0.0], [0.0, 0.0, 0.03]] * 2, dtype=torch.float64)
    rotations = torch.as_tensor(pose[:3, :3]).expand(n_ctrl, 3, 3)
    rotations = so3_exp(0.04 * zigzag.roll(1, dims=-1)) @ rotations
    translations = torch.as_tensor(pose[:3, 3]) + zigzag
    slot_times, time_range = np.array([0.6, 1.1]), (0.5, 1.25)  # the domain is [0.5, 1.25]
    pool = RayBatch.cat([_rays(rgb, depth, intrinsics, 64, seed=7, frame_id=slot) for slot in (0, 1)])
    settings, sources = RenderLossSettings.from_config(cfg), [(pool, 96)]

    def spline_model():
        trajectory = BSplineTrajectory(rotations.clone(), translations.clone(), dt, t0)
        return SplinePoses(trajectory, free=free, slot_times=slot_times, fallback_poses=torch.eye(4).repeat(2, 1, 1),
                           lr_rot=1e-2, lr_trans=1e-2)

    def dynamics_of(model):
        return dynamics_term(model, time_range, cfg.dynamics, torch.Generator().manual_seed(11))

    control_translations = translations.clone().requires_grad_(True)
    oracle = trajectory_dynamics_loss(BSplineTrajectory(rotations, control_translations, dt, t0), *time_range,
                                      cfg.dynamics, torch.Generator().manual_seed(11))
    oracle_gradient = torch.autograd.grad(oracle, control_translations)[0]
    oracle, expected_gradient = float(oracle.detach()), torch.zeros_like(oracle_gradient)
    expected_gradient[free] = oracle_gradient[free]  # the fixed points have no parameter
    assert oracle > 0.5 and float(expected_gradient.abs().max()) > 0.1  # not a vanishing term
    with_model, without_model = spline_model(), spline_model()
    with_dynamics, terms = iteration_loss(field, sources, with_model, settings, torch.Generator().manual_seed(5),
                                          dynamics_of(with_model), smoothness=False)
    without, _ = iteration_loss(field, sources, without_model, settings, torch.Generator().manual_seed(5), None,
                                smoothness=False)
    assert float(with_dynamics.detach()) == pytest.approx(float(without.detach()) + oracle, rel=1e-6)
    assert terms["dynamics"] == pytest.approx(oracle, rel=1e-9)
    gradient_with = torch.autograd.grad(with_dynamics, with_model.translation_delta)[0]
    gradient_without = torch.autograd.grad(without, without_model.translation_delta)[0]
    assert torch.allclose(gradient_with - gradient_without, expected_gradient, rtol=1e-5, atol=1e-6)
    runs = {}
    for name, use_dynamics in (("with", True), ("without", False)):  # the loop BA runs adds it too
        model = spline_model()
        runs[name] = joint_optimization(field, None, sources, model, settings, iters=1,
                                        generator=torch.Generator().manual_seed(5), optimise_map=False,
                                        extra_loss=dynamics_of(model) if use_dynamics else None)
    assert runs["with"].losses[0] == pytest.approx(runs["without"].losses[0] + oracle, rel=1e-6)


def test_a_pose_model_with_nothing_to_optimise_leaves_the_map_gradient_and_the_loss_bit_for_bit(scene_setup,
                                                                                                  compiled_kernel):
    """With nothing to optimise (every slot fixed; a spline with no free control point) a pose
    model's poses are constants, so iteration_loss computes no point gradient.  Oracle: render_loss
    on the same rays and generator state with the same poses as a leaf that carries a gradient, the
    graph the loop used to build: the loss and every map gradient must be equal bit for bit, on the
    compiled kernel and the MLPs' part-wise first layer, which take other paths then."""
    from tsslam_ref.field import SceneField
    _, intrinsics, pose, rgb, depth, cfg = scene_setup
    settings = RenderLossSettings.from_config(cfg)
    rays_of_two_frames = [_rays(rgb, depth, intrinsics, 60, seed, frame_id=slot) for slot, seed in ((0, 1), (1, 2))]
    sources = [(RayBatch.cat(rays_of_two_frames), 80)]
    pose = torch.as_tensor(pose, dtype=torch.float64)
    poses = torch.stack([pose, _perturb(pose, [0.01, 0.0, 0.02], [0.02, 0.0, -0.01])]).float()
    model = DiscretePoses(poses, torch.ones(2, dtype=torch.bool), 1e-2, 1e-2)
    assert model.parameter_groups() == [] and torch.equal(model.poses(), poses)
    translations = torch.rand(6, 3, generator=torch.Generator().manual_seed(1))
    spline = BSplineTrajectory.from_rotvecs(torch.zeros(6, 3), translations, 0.25, -0.5)  # domain [0, 0.75) s
    no_free, with_free = (SplinePoses(spline, free, np.array([0.1, 0.3]), torch.eye(4).repeat(2, 1, 1), 1e-2, 1e-2)
                          for free in ([], [3]))
    assert no_free.parameter_groups() == [] and not no_free.poses().requires_grad
    assert with_free.poses().requires_grad and torch.equal(no_free.poses(), with_free.poses().detach())
    results = []
    for detached in (True, False):
        field = SceneField(cfg.field, [[-1.0, 4.0]] * 3, generator=torch.Generator().manual_seed(0))
        assert field.grid.uses_compiled_kernel(torch.zeros(1, 3))
        generator = torch.Generator().manual_seed(7)
        if detached:  # the loop's path
            loss, _ = iteration_loss(field, sources, model, settings, generator, None, smoothness=True)
        else:  # the oracle: the same draws, the same poses as a leaf that carries a gradient
            rays = RayBatch.cat([bundle_draw(pool, n, generator) for pool, n in sources])
            c2w = poses[rays.frame_ids].clone().requires_grad_(True)
            loss, _ = render_loss(field, rays, c2w, settings, generator=generator, smoothness=True)
        loss.backward()
        assert not model.poses().requires_grad and model.increments.translation.grad is None  # no pose graph
        results.append([loss.detach()] + [p.grad for p in field.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*results))
    assert float(results[0][1].abs().max()) > 0


def test_keyframe_database_relabels_slots():
    database = KeyframeDatabase()
    for slot in range(3):
        n = 5 + slot
        database.add(10 * slot, float(slot), frame_rays(np.zeros((4, 4, 3), np.float32), np.ones((4, 4), np.float32),
                                                       (2.0, 2.0, 1.5, 1.5), torch.arange(n) % 4, torch.arange(n) // 4 % 4))
    rays = database.rays([2, 0])
    assert rays.frame_ids.tolist() == [0] * 7 + [1] * 5
    assert database.frame_indices == [0, 10, 20]


def test_spline_poses_are_local_and_fall_back_outside_the_domain():
    """Only the free control points get gradients; slots outside the domain keep their fallback."""
    n_ctrl, dt, t0 = 7, 0.25, 0.0
    generator = torch.Generator().manual_seed(0)
    rotations = so3_exp(0.3 * torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64))
    translations = torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64)
    fallback = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1) * 7.0
    times = np.array([0.55, 1.3, 5.0])  # the domain is [0.5, 1.5]
    trajectory = BSplineTrajectory(rotations, translations, dt, t0)
    model = SplinePoses(trajectory, free=range(n_ctrl), slot_times=times, fallback_poses=fallback, lr_rot=1e-3, lr_trans=1e-3)
    poses = model.poses()
    assert torch.equal(poses[2], fallback[2])
    # t = 0.55 lies in [t_2, t_3): control points 0..3; t = 1.3 in [t_5, t_6): control points 3..6
    for slot, active in ((0, [0, 1, 2, 3]), (1, [3, 4, 5, 6])):
        grads = torch.autograd.grad(model.poses()[slot].sum(), [model.rotation_delta, model.translation_delta])
        for grad in grads:
            touched = sorted(set(torch.nonzero(grad.abs().sum(-1)).reshape(-1).tolist()))
            assert set(touched) <= set(active) and len(touched) >= 2, (slot, touched)
    fixed_model = SplinePoses(trajectory, free=[5, 6], slot_times=times, fallback_poses=fallback, lr_rot=1e-3,
                              lr_trans=1e-3)
    grad = torch.autograd.grad(fixed_model.poses()[1].sum(), [fixed_model.translation_delta])[0]
    assert float(grad[:5].abs().max()) == 0.0 and float(grad[5:].abs().max()) > 0.0


@pytest.mark.parametrize("first_free", [1, 2])
def test_spline_poses_with_a_start_pose_keep_frame_0_while_points_1_and_2_move(first_free):
    """The TS-SLAM gauge: with ``start_pose`` the curve's first pose stays put under Adam steps on a
    loss that pulls every pose, although control points 1 and 2 move (or only point 2, point 1
    held: point 0 must follow either)."""
    n_ctrl, dt, t0 = 6, 0.25, 0.0
    generator = torch.Generator().manual_seed(1)
    rotations = so3_exp(0.1 * torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64))
    translations = torch.randn(n_ctrl, 3, generator=generator, dtype=torch.float64)
    times = np.linspace(0.5, 1.25, 7)  # the domain is [0.5, 1.25]; times[0] is the start
    first = spline.evaluate(rotations, translations, times[:1], dt, t0)
    start_pose = make_pose(first.rotation[0], first.translation[0])
    trajectory = BSplineTrajectory(rotations, translations, dt, t0, start_pose=start_pose)
    model = SplinePoses(trajectory, free=range(first_free, n_ctrl), slot_times=times,
                        fallback_poses=torch.eye(4, dtype=torch.float64).repeat(7, 1, 1), lr_rot=1e-2, lr_trans=1e-2)
    optimizer = torch.optim.Adam(model.parameter_groups())
    for _ in range(20):
        optimizer.zero_grad()
        model.poses()[:, :3, 3].sum().backward()  # pulls every position along -(1, 1, 1)
        optimizer.step()
    moved_rotations, moved_translations = model.control_points()
    assert float((moved_translations[1:3] - translations[1:3]).detach().norm()) > 0.1
    assert torch.allclose(model.poses()[0], start_pose, atol=1e-10)
    with pytest.raises(ValueError, match="control point 0"):
        SplinePoses(trajectory, free=range(n_ctrl), slot_times=times,
                    fallback_poses=torch.eye(4, dtype=torch.float64).repeat(7, 1, 1), lr_rot=1e-2, lr_trans=1e-2)


def test_constant_velocity_init_stays_on_so3_over_many_frames():
    """float32 drift must not compound: 200 predictions in a row stay orthonormal."""
    step = make_pose(so3_exp(torch.tensor([0.01, 0.02, -0.015])), torch.tensor([0.01, 0.0, 0.005]))
    poses = [torch.eye(4), step.clone()]
    for _ in range(200):
        poses.append(constant_velocity_init(poses[-1], poses[-2]))
    rotation = poses[-1][:3, :3]
    assert torch.allclose(rotation.T @ rotation, torch.eye(3), atol=1e-5)
    assert torch.allclose(poses[-1], torch.linalg.matrix_power(step, 201), atol=1e-3)


def test_adam_caps_a_frames_correction_near_iterations_times_learning_rate(scene_setup):
    """Why ``synthetic-cpu`` tracks at lr 3e-3 (docs/system.md, "Tracking's step-size cap").

    Adam moves each parameter by at most about lr per step, so in 20 iterations the rotation
    increment stays within sqrt(3) x 20 x lr of the start, however hard an exact map pulls.  From a
    4.4 deg turn in place (TUM-VI room2's turn per frame) Co-SLAM's 1e-3 corrects little of it; 3e-3
    ends clearly closer to the true pose."""
    scene, intrinsics, pose, rgb, depth, base_cfg = scene_setup
    field = AnalyticField(scene, base_cfg.render.truncation)
    true_pose = torch.as_tensor(pose, dtype=torch.float32)
    turn = np.deg2rad(4.4)
    turn_in_place = make_pose(so3_exp(torch.tensor([0.0, turn, 0.0], dtype=torch.float32)), torch.zeros(3))  # camera frame
    start = true_pose @ turn_in_place
    rays = _rays(rgb, depth, intrinsics, 512, seed=4)
    start_r = _pose_error(start, true_pose)[1]
    end_r = {}
    for lr in (1e-3, 3e-3):
        cfg = copy.deepcopy(base_cfg)
        cfg.tracking.iters, cfg.tracking.lr_rot, cfg.tracking.lr_trans, cfg.tracking.best = 20, lr, lr, True
        result = track_frame(field, rays, start, cfg.tracking, RenderLossSettings.from_config(cfg),
                             generator=torch.Generator().manual_seed(5))
        end_r[lr] = _pose_error(result.pose, true_pose)[1]
        moved = _pose_error(result.pose, start)[1]
        assert moved <= 1.2 * np.sqrt(3) * cfg.tracking.iters * lr, (lr, moved)
    assert end_r[1e-3] > 0.7 * start_r, (start_r, end_r)
    assert end_r[3e-3] < end_r[1e-3] - np.deg2rad(0.3), (start_r, end_r)


def test_ray_budget_counts_inner_pixels_for_tracking_and_the_whole_frame_for_the_first_map():
    """Oracle, counted by hand: a 20 x 10 px frame with ignore_edge = 2 has (10 − 4)(20 − 4) = 96
    pixels to track from and 200 for the first map; one ray more than each is refused, no fewer."""
    cfg = config.tiny()
    cfg.tracking.ignore_edge, cfg.tracking.n_rays, cfg.mapping.first_n_rays = 2, 96, 200
    check_ray_budget(cfg, 10, 20)
    cfg.tracking.n_rays = 97
    with pytest.raises(ValueError, match="tracking.n_rays = 97 is more than the 96 pixels"):
        check_ray_budget(cfg, 10, 20)
    cfg.tracking.n_rays, cfg.mapping.first_n_rays = 96, 201
    with pytest.raises(ValueError, match="mapping.first_n_rays = 201 is more than the 200 pixels"):
        check_ray_budget(cfg, 10, 20)
    cfg.tracking.ignore_edge = 5
    with pytest.raises(ValueError, match="leaves no pixel of the 20x10 frames; expected < 5"):
        check_ray_budget(cfg, 10, 20)


def test_track_frame_refuses_the_whole_config_for_its_tracking_settings():
    cfg = config.tiny()
    with pytest.raises(TypeError, match=r"takes the tracking settings \(cfg.tracking, a TrackingConfig\), got Config"):
        track_frame(None, None, torch.eye(4), cfg, None)


def test_track_frame_and_the_loss_name_a_numpy_pose_instead_of_failing_inside_torch():
    cfg = config.tiny()
    with pytest.raises(TypeError, match=r"init_pose must be one \(4, 4\) torch tensor .* got ndarray of shape \(4, 4\)"):
        track_frame(None, None, np.eye(4), cfg.tracking, None)
    with pytest.raises(TypeError, match=r"got Tensor of shape \(2, 4, 4\)"):
        track_frame(None, None, torch.eye(4).expand(2, 4, 4), cfg.tracking, None)
    with pytest.raises(TypeError, match=r"c2w must be a torch tensor, got ndarray: torch.as_tensor\(c2w\)"):
        rays_to_world(torch.zeros(5, 3), np.eye(4))


def test_floyd_sample_draws_every_subset_equally_often_without_repeats():
    """Oracle: the uniform distribution over the 20 three-element subsets of six (a chi-square test
    at p = 1e-6: 19 degrees of freedom, threshold 61.6); and at the size of a long run's keyframe
    pool, n_rays distinct indices inside it, with every part of the pool reached."""
    from collections import Counter
    from itertools import combinations

    from tsslam_ref.bundle import floyd_sample

    generator = torch.Generator().manual_seed(0)
    draws = 20000
    counts = Counter(tuple(sorted(floyd_sample(6, 3, generator).tolist())) for _ in range(draws))
    assert set(counts) == set(combinations(range(6), 3))
    expected = draws / 20
    assert sum((count - expected) ** 2 / expected for count in counts.values()) < 61.6, counts
    picks = floyd_sample(4_600_000, 1024, generator)
    assert picks.dtype == torch.long and len(set(picks.tolist())) == 1024
    assert 0 <= int(picks.min()) and int(picks.max()) < 4_600_000
    assert len(set((picks // 460_000).tolist())) == 10  # every tenth of the pool


def test_draw_rays_permutes_small_pools_and_samples_large_ones_without_repeats():
    """Up to PERMUTATION_POOL_LIMIT rays the draw is the first n of torch.randperm with the same
    generator state (what every CPU-preset run draws); above it, n distinct rays of the pool."""
    from tsslam_ref.bundle import PERMUTATION_POOL_LIMIT

    def pool_of(n):
        return RayBatch(directions_cam=torch.zeros(n, 3), rgb=torch.zeros(n, 3), depth=torch.arange(n, dtype=torch.float32),
                        frame_ids=torch.zeros(n, dtype=torch.long))

    small = pool_of(PERMUTATION_POOL_LIMIT)
    drawn = bundle_draw(small, 100, torch.Generator().manual_seed(3))
    assert torch.equal(drawn.depth.long(), torch.randperm(len(small), generator=torch.Generator().manual_seed(3))[:100])
    large = pool_of(PERMUTATION_POOL_LIMIT + 1)
    drawn = bundle_draw(large, 1000, torch.Generator().manual_seed(3))
    assert len(drawn) == 1000 and len(set(drawn.depth.long().tolist())) == 1000
