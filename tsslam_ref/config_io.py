"""Reading, checking and writing configs: nested dicts, ``--set`` overrides, validation, JSON files.

Layer 0 (base): works on any config of nested dataclasses (``config.Config``) without importing
it; ``config`` re-exports every public name here, so ``config.validate`` and friends keep their
place.

* Overrides are strings ``section.key=value`` (``--set tracking.iters=20`` on the command line),
  parsed as JSON where possible, else kept as strings (:func:`apply_overrides`).
* :func:`validate` checks every value's type against its field and the range the field declares
  (``config.ranged``, next to the field's default): a file, an override or a notebook's edit with
  ``mapping.map_every=0`` or ``tracking.iters="ten"`` fails at once, naming the key, the value and
  what was expected, before any work starts (instead of a division by zero or an empty loop deep
  inside a run).
* :func:`save` writes the resolved config as JSON (every run's ``config.json``);
  :func:`read_json_values` and :func:`set_values` read it back (``config.load``).
"""

import copy
import dataclasses
import difflib
import json
import math
import re
from typing import Any, Dict, Optional, Sequence, Tuple


def to_dict(cfg: Any) -> Dict[str, Any]:
    """Plain nested dict (JSON-serialisable) of a config."""
    return dataclasses.asdict(cfg)


def _has_field(target: Any, name: str) -> bool:
    """Whether ``target`` is a config dataclass with a field ``name`` (not any Python attribute:
    ``__doc__`` or ``real`` are no keys)."""
    return dataclasses.is_dataclass(target) and name in {item.name for item in dataclasses.fields(target)}


def set_values(cfg: Any, values: Dict[str, Any], source: str = "<dict>") -> Any:
    """Set the values of a nested dict ``{section: {key: value}}`` on ``cfg`` in place; returns ``cfg``.

    Unknown sections or keys raise ValueError naming ``source`` and the key; nothing is validated
    here (:func:`validate` does that).
    """
    for key, value in values.items():
        if not _has_field(cfg, key):
            raise ValueError(f"{source}: unknown config section or key '{key}'{_suggestion(cfg, key)}")
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ValueError(f"{source}: section '{key}' must be an object, got {type(value).__name__}")
            for sub_key, sub_value in value.items():
                if f"{key}.{sub_key}" in RETIRED_KEYS:  # written by earlier versions, never read
                    continue
                if not _has_field(current, sub_key):
                    raise ValueError(f"{source}: unknown key '{key}.{sub_key}'{_suggestion(current, sub_key, key)}")
                setattr(current, sub_key, sub_value)
        else:
            setattr(cfg, key, value)
    return cfg


RETIRED_KEYS = ("mesh.voxel_eval",)
"""Keys that earlier versions wrote into config.json but nothing read (Co-SLAM's voxel of the meshes
it writes during a run; this package writes none): skipped when a file is read, refused in ``--set``."""

EARLIER_VALUES = {"spline.last_interval": "planned"}
"""Keys whose default changed after earlier versions had saved configs without them, with the value
those versions ran with: a saved config that lacks the key counts at that value when ``--resume``
compares it with the command (``checkpoint.config_differences``), not at today's default."""


def _suggestion(target: Any, name: str, section: str = "") -> str:
    """' (did you mean 'section.key'?)' for a misspelt key of the config dataclass ``target``, else ''."""
    known = [item.name for item in dataclasses.fields(target)] if dataclasses.is_dataclass(target) else []
    close = difflib.get_close_matches(name, known, n=1)
    return f" (did you mean '{section + '.' if section else ''}{close[0]}'?)" if close else ""


def _type_problem(value: Any, annotation: Any) -> Optional[str]:
    """What is wrong with ``value`` for a field annotated ``annotation`` (None when it fits)."""
    if getattr(annotation, "__origin__", None) is not None and type(None) in getattr(annotation, "__args__", ()):
        if value is None:
            return None
        annotation = next(arg for arg in annotation.__args__ if arg is not type(None))
    if annotation is bool:
        return None if isinstance(value, bool) else "true or false"
    if annotation is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "an integer"
    if annotation is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        return None if ok else "a finite number"
    if annotation is str:
        return None if isinstance(value, str) else "a string"
    return None  # lists (field.bound) are checked where they are used


def _check_range(value: Any, comparison: str, bound: Any) -> Tuple[bool, str]:
    """(whether ``value`` keeps the rule, the rule in words) for a field declared with ``config.ranged``."""
    if comparison == "in":
        return value in bound, "one of " + ", ".join(bound)
    if comparison == "[]":
        return bound[0] <= value <= bound[1], f"an integer in [{bound[0]}, {bound[1]}]"
    if comparison == "(]":
        return bound[0] < value <= bound[1], f"in ({bound[0]}, {bound[1]}]"
    if comparison == "()":
        return bound[0] < value < bound[1], f"in ({bound[0]}, {bound[1]})"
    if comparison == ">":
        return value > bound, f"> {bound}"
    return value >= bound, f">= {bound}"


def validate(cfg: Any, source: str = "config") -> Any:
    """Check every value's type against its field and the range it declares (``config.ranged``).

    Raises ValueError naming ``source``, the key, the value and what was expected; returns
    ``cfg`` unchanged otherwise.  Called by :func:`apply_overrides`, ``config.from_dict`` and
    ``slam.run_slam``.
    """
    sections = [("", cfg)] + [(f.name + ".", getattr(cfg, f.name)) for f in dataclasses.fields(cfg)
                              if dataclasses.is_dataclass(getattr(cfg, f.name))]
    for prefix, section in sections:
        for item in dataclasses.fields(section):
            value = getattr(section, item.name)
            if dataclasses.is_dataclass(value):
                continue
            key = prefix + item.name
            expected = _type_problem(value, item.type)
            if expected is not None:
                raise ValueError(f"{source}: {key} = {value!r} must be {expected}")
            if "range" not in item.metadata or value is None:
                continue
            ok, rule = _check_range(value, *item.metadata["range"])
            if not ok:
                raise ValueError(f"{source}: {key} = {value!r} must be {rule}")
    if not re.fullmatch(r"auto|cpu|cuda(:[0-9]+)?", cfg.device):
        raise ValueError(f"{source}: device = {cfg.device!r} must be auto, cpu, cuda or cuda:N")
    _check_bound(cfg.field.bound, source)
    if cfg.render.far <= cfg.render.near:
        raise ValueError(f"{source}: render.far = {cfg.render.far!r} must be > render.near = {cfg.render.near!r}")
    fits = cfg.method == "tsslam" and cfg.local_ba.use_spline and cfg.local_ba.enabled  # else no curve fit reads it
    if fits and cfg.local_ba.fit_controls > cfg.local_ba.window:
        raise ValueError(f"{source}: local_ba.fit_controls = {cfg.local_ba.fit_controls} must be <= "
                         f"local_ba.window = {cfg.local_ba.window}")
    return cfg


def _check_bound(bound: Any, source: str) -> None:
    """field.bound: None (estimated from frame 0) or [[xmin, xmax], [ymin, ymax], [zmin, zmax]] in m."""
    if bound is None:
        return
    expected = "None or [[xmin, xmax], [ymin, ymax], [zmin, zmax]] of finite numbers with min < max"
    try:
        rows = [[float(v) for v in row] for row in bound]
        ok = len(rows) == 3 and all(len(row) == 2 for row in rows) and not any(
            isinstance(v, bool) for row in bound for v in row)
    except (TypeError, ValueError):
        ok = False
    if ok:
        ok = all(math.isfinite(v) for row in rows for v in row) and all(row[0] < row[1] for row in rows)
    if not ok:
        raise ValueError(f"{source}: field.bound = {bound!r} must be {expected}")


def _parse_value(text: str) -> Any:
    """An override's value: JSON where it parses, Python's True / False / None and number syntax
    (``.5``, ``5.``, ``+3``), else the text."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        if text in ("True", "False"):
            return text == "True"
        if text == "None":
            return None
        for number in (int, float):
            try:
                return number(text)
            except ValueError:
                pass
        return text


def _integral(value: Any, annotation: Any) -> Any:
    """``value`` as an int when the field holds an int and the value is a whole float (``1e3``)."""
    whole = isinstance(value, float) and value.is_integer() and abs(value) < 2**53
    return int(value) if whole and annotation in (int, Optional[int]) else value


def apply_overrides(cfg: Any, overrides: Sequence[str]) -> Any:
    """Return a copy of ``cfg`` with ``section.key=value`` overrides applied.

    Values are parsed as JSON (``3``, ``0.5``, ``true``, ``[[0,1],[0,1],[0,1]]``), else taken as
    strings; string fields keep the text as typed.  Raises ValueError naming the override for an
    unknown key, a malformed string, or a value of the wrong type or out of range (:func:`validate`).
    """
    cfg = copy.deepcopy(cfg)
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override '{item}' is not of the form section.key=value")
        path, text = item.split("=", 1)
        parts = path.strip().split(".")
        target = cfg
        for part in parts[:-1]:
            if not _has_field(target, part):
                raise ValueError(f"override '{item}': unknown section '{part}'{_suggestion(target, part)}")
            target = getattr(target, part)
        if not _has_field(target, parts[-1]) or dataclasses.is_dataclass(getattr(target, parts[-1])):
            hint = _suggestion(target, parts[-1], ".".join(parts[:-1]))
            raise ValueError(f"override '{item}': unknown key '{path}'{hint}")
        annotation = {f.name: f.type for f in dataclasses.fields(target)}[parts[-1]]
        value = _integral(_parse_value(text.strip()), annotation)
        if annotation is str and not isinstance(value, str):
            value = text.strip()  # a string field keeps the text as typed (data.path=2024)
        setattr(target, parts[-1], value)
    return validate(cfg, "overrides " + " ".join(overrides) if overrides else "config")


class _RepeatedKey(ValueError):
    pass


def _refuse_repeated_keys(pairs):
    """json object hook: a key given twice would silently keep its last value."""
    seen = {}
    for key, value in pairs:
        if key in seen:
            raise _RepeatedKey(f"key '{key}' is given twice in one object (values {seen[key]!r} and {value!r})")
        seen[key] = value
    return seen


def read_json_values(path: str) -> Dict[str, Any]:
    """The nested dict of a JSON config file (as :func:`save` writes); ValueError naming ``path``
    when the file is not text, not JSON, not an object or gives a key twice in one object."""
    try:
        with open(path, encoding="utf-8") as handle:
            values = json.load(handle, object_pairs_hook=_refuse_repeated_keys)
    except _RepeatedKey as error:
        raise ValueError(f"{path}: {error}; expected each key once") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file; expected a JSON config object") from None
    except json.JSONDecodeError as error:
        yaml = str(path).endswith((".yaml", ".yml")) or re.match(r"\s*[A-Za-z_][\w-]*\s*:", error.doc) is not None
        hint = ("; YAML (Co-SLAM's config format) is not read: start from a preset (--config tum, scannet, "
                "replica, synthetic) and change values with --set" if yaml else "")
        raise ValueError(f"{path}: not valid JSON ({error}); expected a JSON config object{hint}") from None
    if not isinstance(values, dict):
        raise ValueError(f"{path}: the JSON is a {type(values).__name__}; expected an object "
                         f"{{section: {{key: value}}}} like a run's config.json")
    return values


def save(cfg: Any, path: str) -> None:
    """Write the config as JSON atomically (a new file in the same folder, then rename; files.py)."""
    from .files import atomic_write_text

    atomic_write_text(path, json.dumps(to_dict(cfg), indent=2))
