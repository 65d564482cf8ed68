"""checkpoint.py: plain data only (a planted pickle never runs), exact round trip, clear refusals."""

import copy
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import tsslam_ref
from tsslam_ref import checkpoint, config, data, device, files, slam, synthetic


class Payload:
    """Unpickling this calls os.system, which creates the marker file."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def cheap_config(method: str) -> config.Config:
    cfg = config.tiny()
    cfg.method = method
    cfg.spline.dt = 0.1
    cfg.local_ba.window = 3
    cfg.tracking.ignore_edge = 2
    cfg.tracking.iters = 2
    cfg.tracking.n_rays = 32
    cfg.mapping.first_iters = 3
    cfg.mapping.iters = 1
    cfg.mapping.n_rays = cfg.mapping.first_n_rays = 64
    cfg.render.n_samples = 8
    cfg.render.n_range_d = 2
    return config.validate(cfg)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """(state rebuilt by checkpoint.from_plain, values read straight from the running loop's state)."""
    folder = tmp_path_factory.mktemp("synthetic") / "room"
    synthetic.synthesize(folder, n_frames=6, width=48, height=36, fps=30.0, seed=0, clean_depth=True, mesh_voxel=0.2)
    sequence = data.load_sequence(folder)
    kept = {}

    def keep(current):
        if current.done == 5:  # after a spline interval: spline, frame rays, keyframes all filled
            # no copy here: to_plain must not share the tensors the loop keeps writing into
            kept["state"] = checkpoint.from_plain(checkpoint.to_plain(current))
            kept["live"] = {  # the oracle: copied from the loop's own objects, not through checkpoint.py
                "done": current.done, "intervals_done": current.intervals_done,
                "generator_state": current.generator.get_state().clone(),
                "frame_poses": current.frame_poses.detach().clone(), "timestamps": np.array(current.timestamps),
                "log": [dict(entry) for entry in current.log], "seconds": dict(current.timings.seconds),
                "keyframe_indices": list(current.keyframes.frame_indices),
                "tracked_frames": sorted(current.tracking_output), "window_frames": sorted(current.window_rays),
                "control_translations": current.trajectory.control_translations.detach().clone(),
                "optimizer_state": copy.deepcopy(current.map_optimizer.state_dict()["state"])}

    slam.run_slam(sequence, cheap_config("tsslam"), device=torch.device("cpu"), on_frame=keep)
    kept["live"]["sequence"] = sequence
    return kept["state"], kept["live"]


@pytest.fixture(scope="module")
def state(recorded):
    return recorded[0]


def _flat(value, prefix=""):
    """Every leaf of a plain checkpoint dict, keyed by its path."""
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            out.update(_flat(item, f"{prefix}/{key}"))
        return out
    if isinstance(value, (list, tuple)):
        out = {}
        for index, item in enumerate(value):
            out.update(_flat(item, f"{prefix}/{index}"))
        return out
    return {prefix: value}


def test_a_saved_state_reads_back_identically(state, tmp_path):
    path = tmp_path / "checkpoint.pt"
    checkpoint.save(state, path)
    assert state.trajectory is not None and state.trajectory.n_ctrl >= 4 and len(state.keyframes) >= 1 and state.window_rays
    before, after = _flat(checkpoint.to_plain(state)), _flat(checkpoint.to_plain(checkpoint.load(path)))
    assert before.keys() == after.keys()
    for key in before:
        if isinstance(before[key], torch.Tensor):
            assert before[key].dtype == after[key].dtype and torch.equal(before[key], after[key]), key
        else:
            assert before[key] == after[key], key
    assert torch.equal(checkpoint.load(path).generator.get_state(), state.generator.get_state())


def test_a_checkpoint_stores_each_keyframes_rays_and_nothing_beside_them(state, tmp_path):
    """The loop keeps keyframe rays in one pool with spare capacity; torch.save writes a tensor's
    whole storage, so each keyframe's rays must reach the file as tensors of their own: every
    stored keyframe tensor's storage holds exactly its own bytes (no unwritten capacity, no other
    keyframe's rays).  Two more keyframes are added to a copy of the state, so the pool has grown."""
    state = copy.deepcopy(state)
    for extra in range(2):
        state.keyframes.add(0, 0.5 + extra, state.keyframes.slot_rays(0))
    path = tmp_path / "checkpoint.pt"
    checkpoint.save(state, path)
    stored = torch.load(path, weights_only=True)["keyframes"]["rays"]
    assert len(stored) == len(state.keyframes) >= 3
    for slot, rays in enumerate(stored):
        assert torch.equal(rays["depth"], state.keyframes.slot_rays(slot).depth)
        for name, values in rays.items():
            assert values.untyped_storage().nbytes() == values.numel() * values.element_size(), (slot, name)



@pytest.mark.parametrize("inside", [KeyboardInterrupt, OSError])
def test_torch_saves_runtime_error_is_told_apart_a_ctrl_c_from_a_failed_write(state, tmp_path, monkeypatch, inside):
    """torch's zip writer reports a failed write (a full disk), and a Ctrl-C inside it, as a
    RuntimeError: the run printed a traceback and exit 1 instead of its one line and exit 2 / 130."""
    target = tmp_path / "checkpoint.pt"
    target.write_bytes(b"the previous checkpoint")

    def failing_save(values, path):
        try:
            raise inside()
        except inside:
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 8384 vs 8296")

    monkeypatch.setattr(torch, "save", failing_save)
    with pytest.raises(KeyboardInterrupt if inside is KeyboardInterrupt else files.OutputWriteError) as raised:
        checkpoint.save(state, target)
    assert inside is KeyboardInterrupt or str(target) in str(raised.value)
    assert target.read_bytes() == b"the previous checkpoint" and [p.name for p in tmp_path.iterdir()] == [target.name]

    def device_fault(values, path):  # any other RuntimeError stays itself: not a full disk
        raise RuntimeError("CUDA error: an illegal memory access was encountered")

    monkeypatch.setattr(torch, "save", device_fault)
    with pytest.raises(RuntimeError, match="illegal memory access") as raised:
        checkpoint.save(state, target)
    assert not isinstance(raised.value, OSError) and target.read_bytes() == b"the previous checkpoint"


@pytest.mark.parametrize("inside_torch_file", [False, True])
def test_a_planted_pickle_never_runs(tmp_path, inside_torch_file):
    marker = tmp_path / "marker"
    path = tmp_path / "checkpoint.pt"
    if inside_torch_file:
        torch.save({"format": checkpoint.FORMAT, "version": checkpoint.VERSION, "config": Payload(marker)}, path)
    else:
        path.write_bytes(pickle.dumps(Payload(marker), protocol=2))
    with pytest.raises(checkpoint.CheckpointError, match="checkpoint.pt: not a readable tsslam_ref checkpoint") as error:
        checkpoint.load(path)
    assert not marker.exists()
    assert "trust" not in str(error.value)  # torch's advice to load it unsafely is not repeated
    if inside_torch_file:
        assert "Python objects other than tensors" in str(error.value)


def test_a_run_folder_given_as_the_checkpoint_names_the_file_inside(tmp_path):
    with pytest.raises(checkpoint.CheckpointError, match="is a folder, not a checkpoint file .*checkpoint.pt"):
        checkpoint.load(tmp_path)


def test_damaged_and_foreign_files_are_refused_naming_the_file(state, tmp_path):
    good = tmp_path / "good.pt"
    checkpoint.save(state, good)
    content = good.read_bytes()
    cases = {
        "empty.pt": (b"", "the checkpoint is empty"),
        "truncated.pt": (content[: len(content) // 2], "not a readable tsslam_ref checkpoint"),
        "random.pt": (np.random.default_rng(0).bytes(4096), "not a readable tsslam_ref checkpoint"),
    }
    for name, (payload, message) in cases.items():
        (tmp_path / name).write_bytes(payload)
        with pytest.raises(checkpoint.CheckpointError, match=f"{name}: {message}"):
            checkpoint.load(tmp_path / name)
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(checkpoint.CheckpointError, match="foreign.pt: not a tsslam_ref checkpoint"):
        checkpoint.load(tmp_path / "foreign.pt")
    plain = checkpoint.to_plain(state)
    plain["version"] = checkpoint.VERSION + 1
    torch.save(plain, tmp_path / "newer.pt")
    with pytest.raises(checkpoint.CheckpointError, match=f"newer.pt: checkpoint version {checkpoint.VERSION + 1}"):
        checkpoint.load(tmp_path / "newer.pt")
    plain = checkpoint.to_plain(state)
    del plain["frame_poses"]
    torch.save(plain, tmp_path / "partial.pt")
    with pytest.raises(checkpoint.CheckpointError, match="partial.pt: checkpoint entry 'frame_poses' is missing"):
        checkpoint.load(tmp_path / "partial.pt")


def test_knot_times_survive_a_checkpoint_and_older_checkpoints_load_as_uniform(state, tmp_path):
    uneven = state.trajectory.clone()
    uneven.plan_interval_end(uneven.n_ctrl - 3, uneven.domain()[1] + 0.037)
    state_uneven = checkpoint.from_plain(checkpoint.to_plain(state))
    state_uneven.trajectory = uneven
    checkpoint.save(state_uneven, tmp_path / "uneven.pt")
    back = checkpoint.load(tmp_path / "uneven.pt").trajectory
    assert not back.uniform and np.array_equal(back.knot_vector(uneven.n_ctrl + 1), uneven.knot_vector(uneven.n_ctrl + 1))
    plain = checkpoint.to_plain(state)
    assert plain["trajectory"]["knot_times"] is None  # a uniform run stores no knot times
    for key in ("knot_times", "knot_offset"):  # as written before knot times were saved
        del plain["trajectory"][key]
    older = checkpoint.from_plain(plain).trajectory
    assert older.uniform and older.dt == state.trajectory.dt and older.t0 == state.trajectory.t0


def test_a_flipped_bit_in_a_tensor_is_refused_not_resumed(state, tmp_path):
    """torch.load does not check the zip's CRC-32: a flipped bit in the map's table loaded and a
    resumed run ended with another trajectory at exit 0.  The stored CRCs are the oracle."""
    import zipfile

    path = tmp_path / "flipped.pt"
    checkpoint.save(state, path)
    with zipfile.ZipFile(path) as archive:
        largest = max(archive.infolist(), key=lambda info: info.file_size)
    content = bytearray(path.read_bytes())
    header = content.index(largest.filename.encode(), largest.header_offset)  # the local header's file name
    payload = header + len(largest.filename) + 64  # well inside the stored (uncompressed) tensor bytes
    content[payload + largest.file_size // 2] ^= 0x10
    path.write_bytes(bytes(content))
    with pytest.raises(checkpoint.CheckpointError, match=r"flipped.pt: the checkpoint is corrupt \(entry .* CRC"):
        checkpoint.load(path)


def test_entries_that_disagree_with_the_frame_count_are_refused_naming_the_entry(state, tmp_path):
    """A pose table of another length, or a frame number past the frames done, used to load and
    fail frames later inside the loop with a traceback."""
    done = state.done
    cases = {
        "short_poses": (lambda plain: plain.update(frame_poses=plain["frame_poses"][:-1]), "'frame_poses' has shape"),
        "keyframe_past_done": (lambda plain: plain["keyframes"]["frame_indices"].__setitem__(0, done + 3),
                               f"'keyframes/frame_indices' names frame {done + 3}"),
        "tracked_past_done": (lambda plain: plain["tracking_output"].update({done + 1: torch.eye(4)}),
                              f"'tracking_output' names frame {done + 1}"),
        "uneven_keyframes": (lambda plain: plain["keyframes"]["timestamps"].pop(), "'keyframes' holds lists of different"),
    }
    for name, (damage, message) in cases.items():
        plain = checkpoint.to_plain(state)
        damage(plain)
        torch.save(plain, tmp_path / f"{name}.pt")
        with pytest.raises(checkpoint.CheckpointError, match=f"{name}.pt: checkpoint entry {message}"):
            checkpoint.load(tmp_path / f"{name}.pt")
    checkpoint.save(state, tmp_path / "good.pt")
    assert checkpoint.load(tmp_path / "good.pt").done == done  # the real state passes every check


def test_a_loaded_checkpoint_holds_the_running_loops_values(recorded, tmp_path):
    """The round-trip test above compares two states that both went through from_plain, so a value
    from_plain forgets (reset to its default) is forgotten on both sides; here the oracle is the
    running loop's own state, copied when the checkpoint was taken."""
    state, live = recorded
    assert live["intervals_done"] >= 1 and live["log"] and live["done"] == 5  # a run with something to restore
    checkpoint.save(state, tmp_path / "checkpoint.pt")
    back = checkpoint.load(tmp_path / "checkpoint.pt")
    assert back.done == live["done"] and back.intervals_done == live["intervals_done"]
    assert torch.equal(back.generator.get_state(), live["generator_state"])
    assert not torch.equal(torch.Generator().get_state(), live["generator_state"])  # a fresh generator differs
    assert torch.equal(back.frame_poses, live["frame_poses"]) and np.array_equal(back.timestamps, live["timestamps"])
    assert back.log == live["log"] and back.timings.seconds == live["seconds"]
    assert list(back.keyframes.frame_indices) == live["keyframe_indices"]
    assert sorted(back.tracking_output) == live["tracked_frames"] and sorted(back.window_rays) == live["window_frames"]
    assert torch.equal(back.trajectory.control_translations, live["control_translations"])


def test_a_checkpoint_after_the_last_frame_loads(state, tmp_path):
    """A checkpoint taken after the last frame (done = number of frames) is valid."""
    plain = checkpoint.to_plain(state)
    plain["done"] = len(plain["timestamps"])
    torch.save(plain, tmp_path / "finished.pt")
    assert checkpoint.load(tmp_path / "finished.pt").done == len(plain["timestamps"])


def test_knot_times_that_start_before_knot_zero_survive_a_checkpoint(state, tmp_path):
    """Knot times stored from before knot 0 (knot_offset -1, as a curve fit from poses stores them)
    come back as written (hand-chosen times)."""
    spline = state.trajectory
    knots = spline.t0 + np.array([-0.07, 0.0, 0.09, 0.21, 0.3, 0.42, 0.5, 0.61, 0.73, 0.8])[: spline.n_ctrl + 3]
    uneven = type(spline)(spline.control_rotations, spline.control_translations, spline.dt, spline.t0,
                          spline.convention, spline.start_pose, knots=knots, knot_offset=-1)
    with_knots = checkpoint.from_plain(checkpoint.to_plain(state))
    with_knots.trajectory = uneven
    checkpoint.save(with_knots, tmp_path / "knots.pt")
    timing = checkpoint.load(tmp_path / "knots.pt").trajectory.timing()
    assert timing["knot_offset"] == -1 and np.array_equal(timing["knots"], knots)


def test_a_loaded_checkpoint_keeps_the_map_optimizers_moments(recorded, tmp_path):
    """Co-SLAM keeps one Adam for the whole run: a resumed run must continue with its step counts and
    moment estimates, copied from the running loop's optimizer (a fresh Adam has none)."""
    state, live = recorded
    assert live["optimizer_state"]  # the map was optimised before the checkpoint
    checkpoint.save(state, tmp_path / "checkpoint.pt")
    restored = checkpoint.load(tmp_path / "checkpoint.pt").map_optimizer.state_dict()["state"]
    assert restored.keys() == live["optimizer_state"].keys()
    for index, values in live["optimizer_state"].items():
        assert restored[index].keys() == values.keys()
        for name, value in values.items():
            assert torch.equal(torch.as_tensor(restored[index][name]), torch.as_tensor(value)), (index, name)


def test_frames_tracked_ahead_of_mapping_are_left_out_so_the_checkpoint_loads(state, tmp_path):
    """With --parallel the checkpoint is written by the mapping thread while tracking has run up to
    one mapping period ahead: its entries for frames past ``done`` made the file refuse itself
    ("names frame 6, outside the 6 frames done").  They are left out, to be tracked again."""
    ahead = copy.copy(state)
    done = state.done
    ahead.tracking_output = {**state.tracking_output, done: torch.eye(4), done + 1: torch.eye(4)}
    ahead.window_rays = {**state.window_rays, done: next(iter(state.window_rays.values()))}
    checkpoint.save(ahead, tmp_path / "parallel.pt")
    back = checkpoint.load(tmp_path / "parallel.pt")
    assert back.done == done
    assert sorted(back.tracking_output) == sorted(state.tracking_output)
    assert sorted(back.window_rays) == sorted(state.window_rays)
    assert all(frame < done for frame in back.tracking_output)


def test_frames_tracked_ahead_of_mapping_leave_no_log_entry_or_tracking_time(state, tmp_path):
    """The same checkpoint kept the ahead frames' log entries and tracking calls, so a resumed run
    (which tracks them again) logged those frames twice and counted their tracking twice in the
    runtime table.  Oracle: the state as it was before the two frames were tracked ahead."""
    ahead = copy.copy(state)
    done, timings = state.done, state.timings
    ahead.timings = type(timings)(dict(timings.seconds), dict(timings.iterations), dict(timings.calls))
    ahead.log = [dict(entry) for entry in state.log]
    for frame in (done, done + 1):  # what slam.track adds for each frame it tracks
        ahead.timings.add("tracking", 0.75, 7)
        ahead.log.append({"frame": frame, "tracking_loss": 1.0, "tracking_seconds": 0.75, "tracking_iterations": 7,
                          "outside_box": 0.9})
    checkpoint.save(ahead, tmp_path / "parallel.pt")
    back = checkpoint.load(tmp_path / "parallel.pt")
    assert [entry["frame"] for entry in back.log] == [entry["frame"] for entry in state.log]
    assert back.timings.calls["tracking"] == timings.calls["tracking"]
    assert back.timings.iterations["tracking"] == timings.iterations["tracking"]
    assert back.timings.seconds["tracking"] == pytest.approx(timings.seconds["tracking"], abs=1e-12)
    assert back.timings.seconds == pytest.approx(timings.seconds) and back.timings.calls == timings.calls


def test_a_state_loaded_on_the_cpu_is_refused_by_a_run_on_another_device_naming_the_fix(recorded):
    """``run_slam(..., state=checkpoint.load(path))`` on a CUDA machine resolved 'auto' to CUDA and
    failed frames later with a tensor on the wrong device; 'meta' stands in for the GPU here."""
    from tsslam_ref.device import state_on_device

    state, live = recorded
    assert state_on_device(state, torch.device("cpu")) is state
    with pytest.raises(ValueError, match=r"lives on cpu, the run on meta: load it there, "
                                         r"checkpoint.load\(path, device='meta'\)"):
        state_on_device(state, torch.device("meta"))
    with pytest.raises(ValueError, match="lives on cpu, the run on meta"):
        slam.prepare_run(live["sequence"], state.cfg, torch.device("meta"), state)


def test_the_recorded_code_digest_follows_the_source_not_its_place_line_ends_or_caches(tmp_path):
    """metrics.json and a checkpoint record ``device.source_version()``; a resume compares it, so an
    edited package is named.  Oracle: a copy of the package elsewhere has the same digest, with CRLF
    line ends too (a Windows checkout); compiled caches and data beside the code leave it alone; a
    one-line edit of any source file, or a new module, changes it."""
    digest = device.source_version.__wrapped__  # not the cached answer of an earlier call
    package = Path(tsslam_ref.__file__).parent
    moved = tmp_path / "elsewhere" / "tsslam_ref"
    shutil.copytree(package, moved, ignore=shutil.ignore_patterns("__pycache__", "assets"))  # data, not code
    original = digest(package)
    assert original.startswith(f"{tsslam_ref.__version__}, source ") and digest(moved) == original
    (moved / "__pycache__").mkdir()
    (moved / "__pycache__" / "spline.cpython-311.pyc").write_bytes(os.urandom(64))
    (moved / "assets").mkdir()
    (moved / "assets" / "notes.txt").write_text("a user's file")
    spline_source = moved / "spline.py"
    spline_source.write_bytes(spline_source.read_bytes().replace(b"\n", b"\r\n"))
    assert digest(moved) == original
    for edited in ("spline.py", "datasets/tum_format.py", "csrc/hash_grid.cpp", "new_module.py"):
        changed = tmp_path / edited.replace("/", "_") / "tsslam_ref"
        shutil.copytree(moved, changed)
        with open(changed / edited, "a") as source:
            source.write("\n")
        assert digest(changed) != original, edited
    assert digest(tmp_path / "no_such_folder").endswith("source unknown")  # nothing to read (a zip import)


def test_a_checkpoint_of_an_earlier_version_without_the_code_digest_says_it_does_not_record_it():
    now = {"tsslam_ref": "0.1.0, source 0123456789ab", "torch": "2.13.0+cpu"}
    assert checkpoint.environment_changes({"torch": "2.13.0+cpu"}, now) == [
        "the checkpoint, of an earlier version, does not record tsslam_ref (now '0.1.0, source 0123456789ab')"]
    assert checkpoint.environment_changes(dict(now), now) == []


@pytest.mark.parametrize("method", ["tsslam", "coslam"])
def test_a_config_saved_before_a_default_changed_counts_at_the_value_it_ran_with(method):
    """spline.last_interval became "last_frame" after versions that saved no such key and ran the
    paper's "planned": resuming such a TS-SLAM run under today's default is refused, naming the key
    and the value it ran with, and accepted with that value; a Co-SLAM run never reads the key."""
    saved = config.to_dict(config.load("tum-cpu"))
    saved["method"] = method
    assert saved["spline"].pop("last_interval") == "last_frame"  # today's default, which the file lacks
    today = config.load("tum-cpu")
    today.method = method
    as_then = config.apply_overrides(copy.deepcopy(today), ["spline.last_interval=planned"])
    differences = checkpoint.config_differences(saved, today)
    if method == "tsslam":
        assert differences == ['spline.last_interval was "planned" by default (the checkpoint, of an earlier version, '
                               'lacks it), this command gives "last_frame"']
        assert checkpoint.config_differences(saved, as_then) == []
    else:
        assert differences == []
    saved["spline"]["last_interval"] = "last_frame"  # a file that has the key counts at its own value
    assert checkpoint.config_differences(saved, today) == []
