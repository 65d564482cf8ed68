"""Saving and loading the SLAM loop's state (``checkpoint.pt``) in a format that cannot run code.

A checkpoint is a ``torch.save`` file holding only plain data: tensors, numbers, strings, lists
and dicts.  It is read back with ``torch.load(weights_only=True)``, which refuses every other
Python object, so a crafted file cannot execute anything while it is read.  The objects of the
loop (the map, its optimizer, keyframes, the spline) are rebuilt from that data here.

The file starts with a format tag and a version; :func:`load` checks both and the structure, and
raises :class:`CheckpointError` (a ``ValueError``) naming the file for an empty, truncated,
corrupt or foreign file or another version.

The last checkpoint of a finished run holds the loop's state after its last frame, before
``slam.finish_run`` fits the spline's last interval, so its ``frame_poses`` differ from the run's
``trajectory.txt`` near the end (1.4 cm in an 8-frame teddy run).  To get the finished state
from it: ``slam.run_slam(sequence, cfg, state=checkpoint.load(path))`` with the run's sequence and
config (it tracks nothing more; it fits the last interval), as ``--resume --export-rate`` does.

Layer 4 (system): used by ``run.py``; knows the state of ``slam.py``.
"""

import json
import re
import zipfile
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from . import config as config_module
from .config_io import EARLIER_VALUES, RETIRED_KEYS
from .data import default_sequence_path
from .files import atomic_path

FORMAT = "tsslam_ref-checkpoint"
VERSION = 1


class CheckpointError(ValueError):
    """The file is not a checkpoint this version can resume from; the message names the file."""


def _rays_to_plain(rays) -> Dict[str, torch.Tensor]:
    return {"directions_cam": rays.directions_cam, "rgb": rays.rgb, "depth": rays.depth, "frame_ids": rays.frame_ids}


def _rays_from_plain(values: Dict[str, torch.Tensor]):
    from .render import RayBatch

    return RayBatch(values["directions_cam"], values["rgb"], values["depth"], values["frame_ids"])


def _keyframe_rays(keyframes) -> List[Dict[str, torch.Tensor]]:
    """Each keyframe's rays as tensors of their own.  They are views of the keyframe pool, and
    torch.save writes a view's whole storage: the other keyframes' rays and the pool's unwritten
    capacity would go into every checkpoint."""
    return [{name: values.clone() for name, values in _rays_to_plain(keyframes.slot_rays(slot)).items()}
            for slot in range(len(keyframes))]


def _snapshot(value):
    """``value`` with every tensor in its nested dicts / lists replaced by a detached copy."""
    if isinstance(value, torch.Tensor):
        return value.detach().clone()
    if isinstance(value, dict):
        return {key: _snapshot(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_snapshot(item) for item in value]
    return value


def to_plain(state) -> Dict[str, Any]:
    """The state of ``slam.SLAMState`` as nested dicts / lists of tensors, numbers and strings: a
    snapshot that shares no tensor with the running state (the loop keeps writing into its poses,
    spline and map optimizer's moments), so a state rebuilt by :func:`from_plain` is independent."""
    return _snapshot(_plain_view(state))


def _of_frames_done(entries: Dict[int, Any], done: int) -> Dict[int, Any]:
    """The per-frame entries of the frames done (frame 0 counts once it is mapped).  With
    ``--parallel`` tracking runs ahead of mapping; the frames it tracked past ``done`` are left out
    and tracked again after a resume."""
    limit = max(int(done), 1)
    return {int(frame): value for frame, value in entries.items() if int(frame) < limit}


def _records_of_frames_done(state) -> Tuple[List[dict], Dict[str, dict]]:
    """The log and the timings of the frames done: with ``--parallel`` the frames tracked past
    ``done`` also left a log entry and a tracking call, which a resume would count twice (it
    tracks them again); each entry's ``tracking_seconds`` and ``tracking_iterations`` come off."""
    limit = max(int(state.done), 1)
    log = [dict(entry) for entry in state.log if int(entry.get("frame", 0)) < limit]
    ahead = [entry for entry in state.log if int(entry.get("frame", 0)) >= limit]
    seconds, iterations, calls = (dict(state.timings.seconds), dict(state.timings.iterations),
                                  dict(state.timings.calls))
    for entry in ahead:
        seconds["tracking"] = seconds.get("tracking", 0.0) - float(entry.get("tracking_seconds", 0.0))
        iterations["tracking"] = iterations.get("tracking", 0) - int(entry.get("tracking_iterations", 0))
        calls["tracking"] = calls.get("tracking", 0) - 1
    if calls.get("tracking", 1) <= 0:  # every tracking call was ahead: the stage has not run yet
        for table in (seconds, iterations, calls):
            table.pop("tracking", None)
    return log, {"seconds": seconds, "iterations": iterations, "calls": calls}


def _plain_view(state) -> Dict[str, Any]:
    """:func:`to_plain`'s dict before the copy: its tensors are the running state's own."""
    trajectory = None
    if state.trajectory is not None:
        spline = state.trajectory
        trajectory = {"dt": float(spline.dt), "t0": float(spline.t0),
                      "control_rotations": spline.control_rotations.detach(),
                      "control_translations": spline.control_translations.detach(),
                      "convention": str(spline.convention),
                      "start_pose": None if spline.start_pose is None else spline.start_pose.detach(),
                      "knot_times": None if spline.uniform else torch.from_numpy(spline.timing()["knots"]),
                      "knot_offset": int(spline.knot_offset)}
    keyframes = state.keyframes
    log, timings = _records_of_frames_done(state)
    per_frame = {key: _of_frames_done(getattr(state, key), state.done)
                 for key in ("tracking_output", "keyframe_of_frame", "relative_to_keyframe", "window_rays")}
    return {
        "format": FORMAT,
        "version": VERSION,
        "config": json.dumps(config_module.to_dict(state.cfg)),
        "field": state.field.state_dict(),
        "map_optimizer": state.map_optimizer.state_dict(),
        "keyframes": {"rays": _keyframe_rays(keyframes),
                      "frame_indices": [int(i) for i in keyframes.frame_indices],
                      "timestamps": [float(t) for t in keyframes.timestamps]},
        "timestamps": torch.from_numpy(np.asarray(state.timestamps, dtype=np.float64).copy()),
        "frame_poses": state.frame_poses.detach(),
        "tracking_output": {k: v.detach() for k, v in per_frame["tracking_output"].items()},
        "done": int(state.done),
        "keyframe_of_frame": {k: int(v) for k, v in per_frame["keyframe_of_frame"].items()},
        "relative_to_keyframe": {k: v.detach() for k, v in per_frame["relative_to_keyframe"].items()},
        "trajectory": trajectory,
        "intervals_done": int(state.intervals_done),
        "window_rays": {k: _rays_to_plain(v) for k, v in per_frame["window_rays"].items()},
        "generator_state": None if state.generator is None else state.generator.get_state(),
        "timings": timings,
        "log": log,
    }


def _trajectory_from_plain(plain: Dict[str, Any], device):
    """The spline of :func:`to_plain`; checkpoints written before knot times were saved are uniform."""
    from .trajectory import BSplineTrajectory

    knot_times = plain.get("knot_times")
    timing = {} if knot_times is None else {"knots": knot_times.numpy().astype(np.float64),
                                            "knot_offset": int(plain.get("knot_offset", 0))}
    return BSplineTrajectory(plain["control_rotations"].to(device), plain["control_translations"].to(device),
                             plain["dt"], plain["t0"], plain["convention"],
                             None if plain["start_pose"] is None else plain["start_pose"].to(device), **timing)


def from_plain(values: Dict[str, Any], device=None):
    """Rebuild a ``slam.SLAMState`` from :func:`to_plain`'s dict (tensors moved to ``device``)."""
    from .bundle import KeyframeDatabase
    from .device import field_settings_for
    from .field import SceneField
    from .mapping import make_map_optimizer
    from .slam import SLAMState
    from .timings import Timings

    cfg = config_module.from_dict(json.loads(values["config"]), source="the checkpoint's config")
    device = torch.device(device) if device is not None else values["frame_poses"].device
    dtype = getattr(torch, cfg.dtype)
    field_model = SceneField(field_settings_for(device, cfg.field), values["field"]["bound"]).to(device, dtype)
    field_model.load_state_dict(values["field"])
    optimizer = make_map_optimizer(field_model, cfg.mapping)
    optimizer.load_state_dict(values["map_optimizer"])
    keyframes = KeyframeDatabase()
    for rays, index, stamp in zip(values["keyframes"]["rays"], values["keyframes"]["frame_indices"],
                                  values["keyframes"]["timestamps"]):
        keyframes.add(index, stamp, _rays_from_plain({k: v.to(device) for k, v in rays.items()}))
    trajectory = None
    if values["trajectory"] is not None:
        trajectory = _trajectory_from_plain(values["trajectory"], device)
    generator = torch.Generator(device="cpu")
    if values["generator_state"] is not None:
        generator.set_state(values["generator_state"])
    timings = Timings(seconds=dict(values["timings"]["seconds"]), iterations=dict(values["timings"]["iterations"]),
                      calls=dict(values["timings"]["calls"]))
    return SLAMState(
        cfg=cfg,
        field=field_model,
        map_optimizer=optimizer,
        keyframes=keyframes,
        timestamps=values["timestamps"].numpy().astype(np.float64),
        frame_poses=values["frame_poses"].to(device),
        tracking_output={int(k): v.to(device) for k, v in values["tracking_output"].items()},
        done=int(values["done"]),
        keyframe_of_frame={int(k): int(v) for k, v in values["keyframe_of_frame"].items()},
        relative_to_keyframe={int(k): v.to(device) for k, v in values["relative_to_keyframe"].items()},
        trajectory=trajectory,
        intervals_done=int(values["intervals_done"]),
        window_rays={int(k): _rays_from_plain({n: t.to(device) for n, t in v.items()})
                     for k, v in values["window_rays"].items()},
        generator=generator,
        timings=timings,
        log=[dict(entry) for entry in values["log"]],
    )


_WRITER_FAILURE = re.compile(r"inline_container|PytorchStreamWriter|iostream error")
"""How torch's zip writer words a failed write: other RuntimeErrors (a CUDA fault) stay what they are."""


def save(state, path, environment: Optional[Dict[str, Any]] = None) -> Path:
    """Write the loop state to ``path`` atomically (a new file, the user's normal mode), with the
    ``environment`` the run started in (``device.run_environment``), which ``--resume`` compares."""
    plain = _plain_view(state)  # written at once, so no copy of the tensors (the keyframe rays excepted)
    if environment is not None:
        plain["environment"] = environment
    with atomic_path(path) as temporary:
        try:
            torch.save(plain, temporary)
        except RuntimeError as error:  # torch's zip writer turns a failed write, or a Ctrl-C in it, into this
            chain, cause = [], error
            while cause is not None:
                chain.append(cause)
                cause = cause.__context__
            interrupt = next((cause for cause in chain if isinstance(cause, KeyboardInterrupt)), None)
            if interrupt is not None:
                raise interrupt from None
            if any(_WRITER_FAILURE.search(str(cause)) for cause in chain):
                raise OSError(f"torch.save: {error} (a full disk or a file-size limit?)") from error
            raise
    return Path(path)


def _flatten(values: Dict[str, Any], prefix: str = "") -> Dict[str, Any]:
    flat = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = value
    return flat


def _data_folder(path: str) -> str:
    """The data folder a config names, absolute ('' is the bundled sequence)."""
    return str(Path(path).resolve()) if path else str(default_sequence_path())


def config_differences(saved: Dict[str, Any], cfg: config_module.Config,
                       saved_in: str = "the checkpoint") -> List[str]:
    """'key: saved -> now' for every config value that differs from the saved config (``saved_in``
    names where it was saved, for the message); not ``device``, whose resolved value
    :func:`environment_changes` compares (a warning), nor keys that earlier versions saved and nothing
    read (``config_io.RETIRED_KEYS``).  A key that earlier versions did not save counts at its default,
    or at the value they ran with where the default has changed since (``config_io.EARLIER_VALUES``)."""
    old, new = _flatten(saved), _flatten(config_module.to_dict(cfg))
    old = {key: value for key, value in old.items() if key not in RETIRED_KEYS}
    # a key a later version added is absent from an earlier version's file: it has the value loading that
    # file gives it (the preset's the file names, as config.load sets a file's values on that preset), or
    # the value that version ran with where the default has changed since
    preset = config_module.PRESETS.get(saved.get("name"), config_module.Config)
    defaults = {**_flatten(config_module.to_dict(preset())), **EARLIER_VALUES}
    changes = []
    for key in sorted(set(old) | set(new)):
        before, after = old.get(key, defaults.get(key, "<absent>")), new.get(key, "<absent>")
        if key == "device":  # "auto" and "cpu" may name one device: the one used is compared as environment
            continue
        if key in EARLIER_VALUES and key not in old and config_module.overrides_without_effect(cfg.method, [key], cfg):
            continue  # what an earlier version ran with does not matter where the run does not read the key
        if key == "data.path" and isinstance(before, str) and isinstance(after, str):
            same = _data_folder(before) == _data_folder(after)
        else:
            same = json.dumps(before) == json.dumps(after)
        if not same:
            where = f"in {saved_in}" if key in old else f"by default ({saved_in}, of an earlier version, lacks it)"
            changes.append(f"{key} was {json.dumps(before)} {where}, this command gives {json.dumps(after)}")
    return changes


def environment_changes(saved: Optional[Dict[str, Any]], now: Dict[str, Any]) -> List[str]:
    """'key was X when the run started, now Y' for each entry of ``device.run_environment`` that
    differs (the code, PyTorch, device, CPU kernels, threads, map kernels); none for a checkpoint
    without one.  An entry the checkpoint lacks was not recorded by the version that wrote it."""
    if not isinstance(saved, dict):
        return []
    return [f"{key} was {saved[key]!r} when the run started, now {now.get(key)!r}" if key in saved else
            f"the checkpoint, of an earlier version, does not record {key} (now {now[key]!r})"
            for key in sorted(set(saved) | set(now)) if saved.get(key) != now.get(key)]


def _check_crc(path: Path) -> None:
    """CheckpointError naming the entry when a stored CRC-32 does not match its bytes: torch.load
    does not check them, and a flipped bit in a tensor would resume a different run without a word.
    A file that is not a zip archive is left to torch.load's own refusal."""
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, RuntimeError):
        return
    if bad is not None:
        raise CheckpointError(f"{path}: the checkpoint is corrupt (entry {bad} fails its CRC check); "
                              f"start the run again with --overwrite")


def read(path) -> Dict[str, Any]:
    """The checked plain dict of a checkpoint file (no Python object is ever constructed from it).

    Raises:
        CheckpointError: naming the file, for a missing, empty, truncated, corrupt, foreign or
            other-version file.
    """
    path = Path(path)
    if path.is_dir():
        inside = " (a run keeps it as checkpoint.pt in its output folder: pass that file)"
        raise CheckpointError(f"{path} is a folder, not a checkpoint file{inside}")
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{path}: the checkpoint is empty (0 bytes); expected a file written by tsslam_ref.run")
    _check_crc(path)
    try:
        values = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for corrupt, truncated or foreign files
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        if "Weights only load failed" in reason:  # torch's advice to load it unsafely is not ours to give
            reason = "it holds Python objects other than tensors, numbers, strings, lists and dicts, never loaded here"
        raise CheckpointError(f"{path}: not a readable tsslam_ref checkpoint ({reason[:200]})") from None
    if not isinstance(values, dict) or values.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a tsslam_ref checkpoint (no '{FORMAT}' format tag)")
    if values.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {values.get('version')!r}; this version of tsslam_ref "
                              f"reads version {VERSION} (start the run again with --overwrite)")
    expected = {"config": str, "field": dict, "map_optimizer": dict, "keyframes": dict, "timestamps": torch.Tensor,
                "frame_poses": torch.Tensor, "tracking_output": dict, "done": int, "keyframe_of_frame": dict,
                "relative_to_keyframe": dict, "intervals_done": int, "window_rays": dict, "timings": dict,
                "log": list}
    for key, kind in expected.items():
        if not isinstance(values.get(key), kind):
            raise CheckpointError(f"{path}: checkpoint entry '{key}' is missing or not a {kind.__name__}")
    if not 0 <= values["done"] <= len(values["timestamps"]):
        raise CheckpointError(f"{path}: checkpoint says {values['done']} frames done of {len(values['timestamps'])}")
    _check_rows(path, values)
    return values


def _check_rows(path: Path, values: Dict[str, Any]) -> None:
    """CheckpointError naming the entry when the per-frame entries disagree with the frame count:
    a pose table of another length, or a frame number outside the sequence, would fail only
    frames later, inside the loop."""
    n_frames = len(values["timestamps"])
    if tuple(values["frame_poses"].shape) != (n_frames, 4, 4):
        raise CheckpointError(f"{path}: checkpoint entry 'frame_poses' has shape {tuple(values['frame_poses'].shape)}, "
                              f"expected ({n_frames}, 4, 4) for its {n_frames} time stamps")
    keyframes = values["keyframes"]
    lengths = {key: len(keyframes.get(key) or []) for key in ("rays", "frame_indices", "timestamps")}
    if len(set(lengths.values())) != 1:
        raise CheckpointError(f"{path}: checkpoint entry 'keyframes' holds lists of different lengths {lengths}")
    frame_numbers = {"keyframes/frame_indices": list(keyframes["frame_indices"])}
    for key in ("tracking_output", "keyframe_of_frame", "relative_to_keyframe", "window_rays"):
        frame_numbers[key] = list(values[key])
    limit = max(values["done"], 1)  # frame 0 is mapped before it counts as done
    for key, numbers in frame_numbers.items():
        outside = [number for number in numbers if not 0 <= int(number) < limit]
        if outside:
            raise CheckpointError(f"{path}: checkpoint entry '{key}' names frame {outside[0]}, outside the "
                                  f"{values['done']} frames done (0-{limit - 1})")


def load(path, device=None):
    """Read and rebuild the state saved by :func:`save` (see :func:`read` for the checks)."""
    values = read(path)
    try:
        return from_plain(values, device)
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as error:
        raise CheckpointError(f"{path}: the checkpoint's content does not fit ({error})") from None


def config_of(values: Dict[str, Any]) -> Dict[str, Any]:
    """The saved config (nested dict) of a checkpoint read by :func:`read`."""
    return json.loads(values["config"])


__all__ = ["FORMAT", "VERSION", "CheckpointError", "save", "read", "load", "config_of", "config_differences",
           "environment_changes", "to_plain", "from_plain"]
