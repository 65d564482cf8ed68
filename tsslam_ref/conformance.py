"""Spline conformance kit: evaluate a spline from JSON and compare two result files.

TS-SLAM §III-B/§III-C, Eq. (5)-(9): lets another implementation (C++, JAX, a port of this
package) check itself against ours with shared test vectors (tsslam_ref/assets/spline_vectors).

Side module (command line).  Imports ``spline`` and ``geometry``.  Run as

    python -m tsslam_ref.spline evaluate INPUT.json -o OUTPUT.json [--force]
    python -m tsslam_ref.spline check REFERENCE.json CANDIDATE.json [--atol 1e-9] [--rtol 1e-7]

Input JSON keys: ``convention`` ("paper" | "basalt"), ``dt`` and ``t0`` (s), ``rotvecs`` (N x 3,
rad), ``translations`` (N x 3, m), ``times`` (M, s).  Output JSON keys: ``times`` (M), ``R``
(M x 3 x 3), ``p``, ``v``, ``a`` (M x 3, world), ``omega_body``, ``omegadot_body`` (M x 3, body),
all float64; a vector file holds the input keys and the output keys together.

``check`` passes a quantity when max |cand − ref| ≤ atol + rtol · max |ref| (default atol 1e-9,
rtol 1e-7; float64 implementations agree to ~1e-14).  Exit codes: 0 pass, 1 fail, 2 bad input
(malformed file, out-of-domain time, refused overwrite).  docs/spline.md describes the format.
"""

import argparse
import json
import math
import os
import sys
import tempfile
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from tsslam_ref import spline
from tsslam_ref.geometry import so3_exp

INPUT_KEYS = ("convention", "dt", "t0", "rotvecs", "translations", "times")
OUTPUT_KEYS = ("R", "p", "v", "a", "omega_body", "omegadot_body")
OUTPUT_SHAPES = {"R": (3, 3), "p": (3,), "v": (3,), "a": (3,), "omega_body": (3,), "omegadot_body": (3,)}
DEFAULT_ATOL = 1e-9
DEFAULT_RTOL = 1e-7


class ConformanceError(ValueError):
    """Malformed input or output file (exit code 2)."""


def _array(data: dict, key: str, shape_tail: Sequence[int], source: str) -> np.ndarray:
    if key not in data:
        raise ConformanceError(f"{source}: missing key {key!r}")
    try:
        value = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ConformanceError(f"{source}: key {key!r} is not a numeric array ({error})") from None
    if value.ndim != 1 + len(shape_tail) or tuple(value.shape[1:]) != tuple(shape_tail):
        wanted = " x ".join(["M"] + [str(n) for n in shape_tail])
        raise ConformanceError(f"{source}: key {key!r} must be {wanted}, got shape {value.shape}")
    if not np.all(np.isfinite(value)):
        raise ConformanceError(f"{source}: key {key!r} contains non-finite values")
    return value


def _scalar(data: dict, key: str, source: str) -> float:
    if key not in data:
        raise ConformanceError(f"{source}: missing key {key!r}")
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConformanceError(f"{source}: key {key!r} must be a finite number, got {value!r}")
    return float(value)


def load_json(path: str) -> dict:
    """Read a JSON object; ConformanceError naming the file on failure."""
    try:
        with open(path, "r", encoding="utf-8") as handle:
            data = json.load(handle)
    except OSError as error:
        raise ConformanceError(f"{path}: cannot read ({error.strerror})") from None
    except json.JSONDecodeError as error:
        raise ConformanceError(f"{path}: invalid JSON at line {error.lineno}: {error.msg}") from None
    if not isinstance(data, dict):
        raise ConformanceError(f"{path}: top level must be a JSON object")
    return data


def parse_input(data: dict, source: str = "input") -> dict:
    """Validate the input keys; returns convention, dt, t0 and float64 arrays."""
    convention = data.get("convention")
    if convention not in spline.CONVENTIONS:
        raise ConformanceError(f"{source}: key 'convention' must be one of {spline.CONVENTIONS}, got {convention!r}")
    dt = _scalar(data, "dt", source)
    if dt <= 0:
        raise ConformanceError(f"{source}: key 'dt' must be > 0, got {dt}")
    parsed = {"convention": convention, "dt": dt, "t0": _scalar(data, "t0", source)}
    parsed["rotvecs"] = _array(data, "rotvecs", (3,), source)
    parsed["translations"] = _array(data, "translations", (3,), source)
    parsed["times"] = _array(data, "times", (), source)
    if parsed["rotvecs"].shape[0] != parsed["translations"].shape[0]:
        raise ConformanceError(f"{source}: 'rotvecs' and 'translations' must have the same length")
    if parsed["rotvecs"].shape[0] < 4:
        raise ConformanceError(f"{source}: key 'rotvecs' needs at least 4 control points")
    return parsed


def evaluate_input(data: dict, source: str = "input") -> Dict[str, list]:
    """Evaluate a parsed-or-raw input dict in float64; returns the output dict (lists).

    Raises ConformanceError (malformed) or ValueError (a time outside the domain).
    """
    parsed = parse_input(data, source)
    rotations = so3_exp(torch.as_tensor(parsed["rotvecs"]))
    translations = torch.as_tensor(parsed["translations"])
    sample = spline.evaluate(rotations, translations, parsed["times"], parsed["dt"], parsed["t0"],
                             parsed["convention"], derivatives=2)
    values = [sample.rotation, sample.translation, sample.velocity_world, sample.acceleration_world,
              sample.omega_body, sample.omegadot_body]
    output = {"times": parsed["times"].tolist()}
    output.update({key: value.detach().cpu().numpy().tolist() for key, value in zip(OUTPUT_KEYS, values)})
    return output


def write_json_atomic(path: str, data: dict, force: bool = False) -> None:
    """Write JSON via a temp file in the same folder and os.replace; refuse to overwrite unless force."""
    if os.path.exists(path) and not force:
        raise FileExistsError(f"{path} exists; pass --force to overwrite it")
    folder = os.path.dirname(os.path.abspath(path))
    handle, tmp_path = tempfile.mkstemp(prefix=".tmp_", suffix=".json", dir=folder)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as stream:
            json.dump(data, stream)
            stream.write("\n")
        os.chmod(tmp_path, 0o644)  # mkstemp creates 0600; results are meant to be shared
        os.replace(tmp_path, path)
    except BaseException:
        if os.path.exists(tmp_path):
            os.remove(tmp_path)
        raise


def compare(reference: dict, candidate: dict, atol: float = DEFAULT_ATOL, rtol: float = DEFAULT_RTOL,
            reference_name: str = "reference", candidate_name: str = "candidate") -> List[dict]:
    """Per-quantity errors.  Each row: quantity, max_abs, max_ref, rel (= max_abs / max_ref),
    bound (= atol + rtol·max_ref), ok.  ``times`` must agree to 1e-12 s.  Raises ConformanceError."""
    ref_times = _array(reference, "times", (), reference_name)
    cand_times = _array(candidate, "times", (), candidate_name)
    if ref_times.shape != cand_times.shape or np.max(np.abs(ref_times - cand_times), initial=0.0) > 1e-12:
        raise ConformanceError(f"{candidate_name}: key 'times' differs from {reference_name}")
    rows = []
    for key in OUTPUT_KEYS:
        ref = _array(reference, key, OUTPUT_SHAPES[key], reference_name)
        cand = _array(candidate, key, OUTPUT_SHAPES[key], candidate_name)
        if ref.shape != cand.shape:
            raise ConformanceError(f"{candidate_name}: key {key!r} has shape {cand.shape}, reference {ref.shape}")
        max_abs = float(np.max(np.abs(cand - ref), initial=0.0))
        max_ref = float(np.max(np.abs(ref), initial=0.0))
        bound = atol + rtol * max_ref
        rows.append({"quantity": key, "max_abs": max_abs, "max_ref": max_ref,
                     "rel": max_abs / max_ref if max_ref > 0 else max_abs, "bound": bound, "ok": max_abs <= bound})
    return rows


def format_table(rows: List[dict]) -> str:
    lines = [f"{'quantity':<14} {'max abs err':>12} {'max rel err':>12} {'bound':>10}  result"]
    for row in rows:
        lines.append(f"{row['quantity']:<14} {row['max_abs']:12.3e} {row['rel']:12.3e} {row['bound']:10.2e}  "
                     f"{'ok' if row['ok'] else 'FAIL'}")
    return "\n".join(lines)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tsslam_ref.spline",
                                     description="B-spline trajectory conformance kit (docs/spline.md).")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("evaluate", help="evaluate R, p, v, a, omega, omegadot at the input times")
    run.add_argument("input", help="input JSON (convention, dt, t0, rotvecs, translations, times)")
    run.add_argument("-o", "--output", required=True, help="output JSON path")
    run.add_argument("--force", action="store_true", help="overwrite an existing output")
    check = commands.add_parser("check", help="compare a candidate result with a reference")
    check.add_argument("reference")
    check.add_argument("candidate")
    check.add_argument("--atol", type=float, default=DEFAULT_ATOL, help=f"absolute tolerance (default {DEFAULT_ATOL})")
    check.add_argument("--rtol", type=float, default=DEFAULT_RTOL,
                       help=f"relative tolerance times max|ref| per quantity (default {DEFAULT_RTOL})")
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Command-line entry; returns the exit code (0 ok, 1 check failed, 2 bad input)."""
    args = _build_parser().parse_args(argv)
    try:
        if args.command == "evaluate":
            data = load_json(args.input)
            output = evaluate_input(data, args.input)
            write_json_atomic(args.output, output, force=args.force)
            print(f"wrote {len(output['times'])} samples to {args.output}")
            return 0
        rows = compare(load_json(args.reference), load_json(args.candidate), args.atol, args.rtol,
                       args.reference, args.candidate)
        print(format_table(rows))
        passed = all(row["ok"] for row in rows)
        print("PASS" if passed else "FAIL")
        return 0 if passed else 1
    except (ConformanceError, FileExistsError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
