"""Every tensor operation of the SLAM loop is device-agnostic, checked without a GPU.

Oracle: PyTorch's own device rules for CUDA tensors, enforced by ``device_audit.VirtualDevice``
(an accelerator stand-in that marks tensors instead of moving them).  The first tests show that
the stand-in raises on each mistake CUDA raises on; then both methods, the adaptive knots, the
two-thread loop and the command line run on the stand-in, on the PyTorch paths of the hash grid
and the OneBlob encoding that a GPU takes, and must give exactly the plain CPU run's trajectory (the stand-in moves
nothing, so any difference would be a bug of the stand-in itself).
"""

import numpy as np
import pytest
import torch

from device_audit import VIRTUAL, DeviceMixError, VirtualDevice, on_virtual
from tsslam_ref import config, data, device as device_module, run, slam, synthetic


@pytest.fixture(scope="module")
def small_sequence(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthetic") / "room"
    synthetic.synthesize(folder, n_frames=14, width=64, height=48, fps=30.0, seed=0, clean_depth=True, mesh_voxel=0.1)
    return folder


def small_config(method: str, knots: str = "uniform") -> config.Config:
    cfg = config.tiny()
    cfg.method = method
    cfg.spline.dt = 0.2
    cfg.local_ba.window = 4
    cfg.tracking.iters = 4
    cfg.field.compiled_kernel = False  # the hash grid's PyTorch path, the one a GPU runs
    cfg.field.compiled_oneblob = False  # and the OneBlob encoding's (the stand-in is a CPU device to the field)
    return config.apply_overrides(cfg, [f"spline.knots={knots}"])


def test_the_stand_in_raises_where_cuda_raises():
    with VirtualDevice():
        on_device = torch.ones(4, 3, device=VIRTUAL)
        assert on_virtual(on_device) and on_device.device == VIRTUAL
        assert on_virtual(on_device * 2 + torch.tensor(1.0))  # a 0-d CPU tensor mixes, as on CUDA
        assert on_virtual(on_device[torch.tensor([0, 2])])  # CPU indices index a GPU tensor
        assert not on_virtual(on_device.cpu()) and float(on_device.sum()) == 12.0
        with pytest.raises(DeviceMixError, match="mixed with CPU"):
            on_device - torch.zeros(3)
        with pytest.raises(DeviceMixError, match="NumPy"):
            np.asarray(on_device)
        with pytest.raises(DeviceMixError, match="CPU generator"):
            torch.rand(3, device=VIRTUAL, generator=torch.Generator().manual_seed(0))
        with pytest.raises(DeviceMixError, match="CPU generator"):
            on_device.uniform_(generator=torch.Generator().manual_seed(0))
        with pytest.raises(DeviceMixError, match="index on the accelerator"):
            torch.zeros(4)[torch.tensor([0, 2], device=VIRTUAL)]
        with pytest.raises(DeviceMixError, match="advanced index"):
            on_device[torch.tensor([0, 2])] = torch.zeros(2, 3)
        on_device[0:2] = torch.zeros(2, 3)  # a slice copies from the CPU
        on_device[torch.tensor([0, 2])] = torch.tensor(5.0)  # and so does a 0-d value through an index
        assert on_virtual(on_device) and float(on_device.sum()) == 33.0  # rows 5, 0, 5, 1
        with pytest.raises(DeviceMixError, match="joins"):
            torch.stack([on_device.sum(), torch.tensor(1.0)])
        parameter = torch.nn.Parameter(torch.zeros(3, device=VIRTUAL))
        assert on_virtual(parameter) and on_virtual(torch.func.jacrev(lambda x: x * 2)(parameter))
        module = torch.nn.Linear(3, 2).to(VIRTUAL)
        assert all(on_virtual(p) for p in module.parameters()) and on_virtual(module(on_device))


def test_the_spline_kit_runs_with_control_points_on_the_stand_in_and_numpy_times():
    from tsslam_ref import knots, se3_spline, spline, spline_jacobians
    from tsslam_ref.geometry import so3_exp

    generator = torch.Generator().manual_seed(0)
    rotations = so3_exp(0.3 * torch.randn(8, 3, dtype=torch.float64, generator=generator))
    translations = torch.randn(8, 3, dtype=torch.float64, generator=generator)
    times = np.linspace(0.35, 0.75, 5)  # seconds, inside the domain of dt = 0.1, t0 = 0.1
    knot_vector = knots.uniform_knots(8, 0.1, 0.1)
    calls = [lambda R, p: spline.evaluate(R, p, times, 0.1, 0.1, derivatives=2),
             lambda R, p: knots.evaluate(R, p, times, knot_vector, derivatives=2),
             lambda R, p: se3_spline.evaluate(R, p, times, 0.1, 0.1, derivatives=2),
             lambda R, p: tuple(v for k, v in spline_jacobians.jacobians(R, p, times, 0.1, 0.1).items() if k != "first")]
    for call in calls:
        plain = call(rotations, translations)
        with VirtualDevice():
            moved = call(rotations.to(VIRTUAL), translations.to(VIRTUAL))
            assert all(on_virtual(value) for value in moved)
        assert all(torch.equal(a, b) for a, b in zip(moved, plain))


@pytest.mark.parametrize("method, knots", [("tsslam", "uniform"), ("coslam", "uniform"), ("tsslam", "adaptive")])
def test_the_loop_runs_on_an_accelerator_stand_in_with_the_cpu_trajectory(small_sequence, method, knots):
    sequence = data.load_sequence(small_sequence)
    cfg = small_config(method, knots)
    plain = slam.run_slam(sequence, cfg, device=torch.device("cpu"))
    with VirtualDevice():
        checked = slam.run_slam(sequence, cfg, device=VIRTUAL)
    np.testing.assert_array_equal(checked.poses, plain.poses)


def test_the_curve_approximation_fits_on_the_cpu_and_hands_back_control_points_on_the_device(small_sequence,
                                                                                             monkeypatch):
    """Oracle: the devices the fit is called with (a spy on ``spline_fit.fit_control_points``) and the
    plain CPU run's trajectory, which the stand-in run must equal (nothing is moved, only marked)."""
    from tsslam_ref import spline_fit
    fitted_on = []
    real_fit = spline_fit.fit_control_points

    def spy(times, poses, *args, **kwargs):
        fitted_on.append([on_virtual(value) for value in (poses, kwargs["init_rotations"], kwargs["init_translations"])])
        return real_fit(times, poses, *args, **kwargs)

    monkeypatch.setattr(spline_fit, "fit_control_points", spy)
    sequence = data.load_sequence(small_sequence)
    cfg = small_config("tsslam")
    plain = slam.run_slam(sequence, cfg, device=torch.device("cpu"))
    n_plain_fits, fitted_on[:] = len(fitted_on), []
    states = []
    with VirtualDevice():
        checked = slam.run_slam(sequence, cfg, device=VIRTUAL, on_frame=states.append)
        trajectory = states[-1].trajectory
        assert on_virtual(trajectory.control_rotations) and on_virtual(trajectory.control_translations)
    assert len(fitted_on) == n_plain_fits > 0 and not any(any(flags) for flags in fitted_on)
    np.testing.assert_array_equal(checked.poses, plain.poses)


@pytest.mark.parametrize("method", ["tsslam", "coslam"])
def test_the_command_line_in_two_threads_runs_on_the_stand_in(small_sequence, tmp_path, monkeypatch, method):
    monkeypatch.setattr(device_module, "resolve_device", lambda name: VIRTUAL)
    out = tmp_path / "out"
    arguments = ["--data", str(small_sequence), "--config", "tiny", "--method", method, "--out", str(out), "--quiet",
                 "--parallel", "--set", "field.compiled_kernel=false", "--set", "field.compiled_oneblob=false",
                 "--set", "tracking.iters=4"]
    if method == "tsslam":
        arguments += ["--export-rate", "60"]
    with VirtualDevice():
        assert run.main(arguments) == 0
    assert (out / "trajectory.txt").is_file() and (out / "mesh.ply").is_file()


def test_a_cuda_device_number_the_machine_lacks_is_refused_naming_it(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # a one-GPU machine, as CUDA reports it
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert device_module.resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(ValueError, match=r"device 'cuda:1' was asked for but this machine has 1 CUDA device"):
        device_module.resolve_device("cuda:1")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"device 'cuda:1' was asked for but torch.cuda.is_available\(\) is False"):
        device_module.resolve_device("cuda:1")


def test_a_frame_on_the_device_keeps_its_dtype_shape_pixel_order_and_sampling_border():
    """frame_to_device on a 5 x 7 frame whose pixels encode (row, col): depth = 1 + row + col / 100.
    Oracle by hand: height 5, width 7, float64 throughout, all_rays in row-major order with
    d = ((col - cx) / fx, (row - cy) / fy, 1), sampled rays at least ignore_edge = 2 px from the border."""
    rows, cols = np.meshgrid(np.arange(5), np.arange(7), indexing="ij")
    depth = (1 + rows + cols / 100).astype(np.float32)
    rgb = np.stack([rows / 10, cols / 100, np.zeros_like(depth)], -1).astype(np.float32)
    intrinsics = data.Intrinsics(fx=10.0, fy=20.0, cx=3.0, cy=2.0, width=7, height=5)
    frame = data.Frame(index=3, timestamp=0.5, rgb=rgb, depth=depth, intrinsics=intrinsics, pose_c2w=None)
    on_device = device_module.frame_to_device(frame, torch.device("cpu"), torch.float64)
    assert (on_device.height, on_device.width) == (5, 7)
    assert on_device.rgb.dtype == on_device.depth.dtype == torch.float64
    rays = on_device.all_rays()
    expected_dirs = np.stack([(cols - 3.0) / 10.0, (rows - 2.0) / 20.0, np.ones_like(depth)], -1).reshape(-1, 3)
    np.testing.assert_allclose(rays.directions_cam.numpy(), expected_dirs, atol=1e-12)
    np.testing.assert_array_equal(rays.depth.numpy(), depth.reshape(-1).astype(np.float64))
    sampled = on_device.sampled_rays(3, torch.Generator().manual_seed(0), ignore_edge=2)
    sampled_rows = np.round(sampled.rgb[:, 0].numpy() * 10)
    sampled_cols = np.round(sampled.rgb[:, 1].numpy() * 100)
    assert set(sampled_rows) == {2.0} and set(sampled_cols) <= {2.0, 3.0, 4.0}  # the 1 x 3 inner pixels


def test_render_image_puts_a_numpy_pose_on_the_fields_device(small_sequence):
    """render_image invites a NumPy pose; it took the device from the pose (the CPU), so a map on
    the GPU met CPU rays."""
    from tsslam_ref.field import SceneField
    from tsslam_ref.render import render_image

    cfg = small_config("tsslam")
    sequence = data.load_sequence(small_sequence)
    field = SceneField(cfg.field, [[-3.0, 3.0], [-3.0, 3.0], [-3.0, 3.0]], generator=torch.Generator().manual_seed(0))
    pose = sequence.gt_poses[0]
    plain = render_image(field, pose, sequence.intrinsics, cfg.render, chunk=1024)
    with VirtualDevice():
        moved = render_image(field.to(VIRTUAL), pose, sequence.intrinsics, cfg.render, chunk=1024)
        assert on_virtual(moved["depth"]) and on_virtual(moved["rgb"])
    assert torch.equal(moved["depth"], plain["depth"]) and torch.equal(moved["rgb"], plain["rgb"])


def test_a_map_off_the_cpu_asks_for_no_cpu_kernel(small_sequence):
    """The compiled kernels are CPU only: a GPU run built them anyway (about 30 s) and, without a
    compiler, recorded a kernel_error that did not apply.  'meta' stands in for the GPU (the
    stand-in above reports itself as a CPU device)."""
    cfg = config.tiny()
    assert cfg.field.compiled_kernel and cfg.field.compiled_oneblob
    assert device_module.field_settings_for(torch.device("cpu"), cfg.field) is cfg.field
    state = slam.initial_state(data.load_sequence(small_sequence), cfg, torch.device("meta"))
    assert state.field.grid.table.device.type == "meta"
    assert not state.field.grid.compiled and not state.field.oneblob.compiled
    assert "kernel_error" not in device_module.map_kernels(state.field, torch.device("meta"))
    assert cfg.field.compiled_kernel  # the run's config (checkpoint, metrics.json) is unchanged


def test_a_trajectory_answers_covers_for_times_on_the_device_as_evaluate_takes_them():
    from tsslam_ref.trajectory import BSplineTrajectory

    trajectory = BSplineTrajectory.empty(0.0, 0.1, torch.eye(4, dtype=torch.float64)[None])
    times = np.array([-0.05, 0.0, 0.05, 0.1, 0.3])
    expected = trajectory.covers(times)
    with VirtualDevice():
        assert np.array_equal(trajectory.covers(torch.from_numpy(times).to(VIRTUAL)), expected)
