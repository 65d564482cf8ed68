"""Spline conformance kit, the command line (TS-SLAM §III-B/§III-C, Eq. (5)-(9)).

Side module (CLI), on top of :mod:`tsslam_ref.conformance` (the maths), :mod:`tsslam_ref.conformance_hints`
(what a failure probably means) and :mod:`tsslam_ref.spline`; :func:`format_report` prints a comparison.
Everything it needs ships inside the package: the test vectors (assets/spline_vectors/*.json) and
the reference (assets/spline_kit.md: conventions, formulas, golden values and their provenance).

    python -m tsslam_ref.spline_kit list
    python -m tsslam_ref.spline_kit docs
    python -m tsslam_ref.spline_kit inputs FOLDER             # the shipped inputs, for your code
    python -m tsslam_ref.spline_kit evaluate INPUT.json -o OUTPUT.json [--force] [--jacobians]
    python -m tsslam_ref.spline_kit check REFERENCE CANDIDATE.json [--atol 1e-10] [--rtol 1e-10]
    python -m tsslam_ref.spline_kit check-all FOLDER [--allow-missing]  # FOLDER/<vector name>.json

Exit codes: 0 pass (a candidate without Jacobian keys passes on its values; ``check-all`` counts
such vectors as "Jacobians unchecked"), 1 a check failed (also an incomplete or misspelt set of
Jacobian keys; ``check-all``: also a malformed candidate, or a shipped vector
missing from FOLDER unless ``--allow-missing``), 2 bad input (the message names the file, key and
value; ``check-all``: FOLDER holds none of the shipped names), nothing overwritten.  The default
tolerances sit between float64 and float32 rounding (:data:`conformance.DEFAULT_RTOL`).

Overwrite rule: files this kit wrote carry ``"written_by": "tsslam_ref.spline_kit"`` and are
replaced on a re-run; any other existing file is kept unless ``--force`` is given.
"""

import argparse
import json
import os
import sys
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from tsslam_ref import conformance, conformance_hints
from tsslam_ref.files import atomic_write_text
from tsslam_ref.cli_args import OneLineParser, user_path

VECTOR_DIR = Path(__file__).resolve().parent / "assets" / "spline_vectors"
REFERENCE_DOC = Path(__file__).resolve().parent / "assets" / "spline_kit.md"
WRITTEN_BY = "tsslam_ref.spline_kit"


def shipped_vectors() -> List[Path]:
    """Paths of the shipped vector files, sorted by name."""
    return sorted(VECTOR_DIR.glob("*.json"))


def resolve_reference(name: str) -> str:
    """A path, or the name of a shipped vector (with or without .json)."""
    if os.path.exists(name):
        return name
    candidate = VECTOR_DIR / (name if name.endswith(".json") else name + ".json")
    return str(candidate) if candidate.exists() else name


def _kit_file(path: str) -> Optional[dict]:
    """The JSON object in ``path`` if this kit wrote it (``written_by``), else None (also for a file
    that cannot be read or is no object)."""
    try:
        data = conformance.load_json(path)
    except conformance.ConformanceError:
        return None
    return data if data.get("written_by") == WRITTEN_BY else None


def _written_by_kit(path: str) -> bool:
    return _kit_file(path) is not None


def _still_the_input(path: str) -> bool:
    """A file 'inputs' wrote and nobody evaluated: written by this kit, no output keys."""
    data = _kit_file(path)
    return data is not None and not set(conformance.OUTPUT_KEYS) & set(data)


def write_json_atomic(path: str, data: dict, force: bool = False) -> None:
    """Write JSON atomically with the user's normal mode (``files.atomic_write_text``).

    An existing file is replaced only if this kit wrote it (``written_by``) or ``force``;
    otherwise FileExistsError with a message that says so.
    """
    _refuse_foreign(path, force)
    atomic_write_text(path, json.dumps(data) + "\n")


def _refuse_foreign(path: str, force: bool, outcome: str = "") -> None:
    """IsADirectoryError when ``path`` is a folder; FileExistsError when it exists, the kit did not
    write it and ``force`` is off.  ``outcome``: what the refusal left, said first in the message."""
    if os.path.isdir(path) and not os.path.islink(path):
        raise IsADirectoryError(f"{path}: is a folder, expected a file name to write ({outcome}move it away first)")
    if os.path.exists(path) and not force and not _written_by_kit(path):
        raise FileExistsError(f"{path} exists and was not written by this kit; pass --force to overwrite it "
                              f"({outcome}files the kit wrote are replaced on a re-run)")


def _epilog() -> str:
    return (f"Shipped vectors: {VECTOR_DIR} (see 'list'). Reference (conventions, formulas, golden values): "
            f"{REFERENCE_DOC} (see 'docs').")


def _build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m tsslam_ref.spline_kit", epilog=_epilog(),
                                     description="Cubic B-spline trajectory conformance kit: evaluate our "
                                                 "reference and check your implementation against it.")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    commands.add_parser("list", help="list the shipped vectors (name, convention, representation, sizes)",
                        epilog=_epilog())
    commands.add_parser("docs", help="print the kit's reference (conventions, formulas, golden values)")
    inputs = commands.add_parser("inputs", help="write the input part of every shipped vector to FOLDER/<name>.json")
    inputs.add_argument("folder", type=user_path)
    inputs.add_argument("--force", action="store_true", help="overwrite files this kit did not write")
    run = commands.add_parser("evaluate", help="evaluate R, p, v, a, omega, omegadot at the input times",
                              epilog=_epilog())
    run.add_argument("input", type=user_path, help="input JSON (convention, dt, t0, rotvecs, translations, times[, representation]; "
                                   "or knots instead of convention, dt, t0)")
    run.add_argument("-o", "--output", type=user_path, required=True, help="output JSON path (inputs echoed + outputs)")
    run.add_argument("--force", action="store_true", help="overwrite an existing file this kit did not write")
    run.add_argument("--jacobians", action="store_true",
                     help="also write J_first and the Jacobians J_R, J_p, J_v, J_a, J_omega_body, J_omegadot_body "
                          "(M x 4 x 3 x 3) w.r.t. the 4 active control points (R_k <- Exp(delta) R_k, P_k <- P_k + tau; "
                          "see 'docs')")
    for name, help_text in (("check", "compare a candidate result with a reference (a file or a shipped name)"),
                            ("check-all", "check FOLDER/<name>.json against every shipped vector <name>")):
        check = commands.add_parser(name, help=help_text, epilog=_epilog())
        if name == "check":
            check.add_argument("reference", type=user_path, help="reference JSON, or the name of a shipped vector")
            check.add_argument("candidate", type=user_path)
        else:
            check.add_argument("folder", type=user_path)
            check.add_argument("--allow-missing", action="store_true",
                               help="a deliberate partial check: exit 0 when every vector present passes (the "
                                    "missing ones are still listed); by default a missing vector fails")
        check.add_argument("--atol", type=float, default=conformance.DEFAULT_ATOL,
                           help=f"absolute tolerance (default {conformance.DEFAULT_ATOL})")
        check.add_argument("--rtol", type=float, default=conformance.DEFAULT_RTOL,
                           help=f"relative tolerance times max|ref| per quantity (default {conformance.DEFAULT_RTOL}; "
                                f"correct float64 code agrees to ~1e-14 of the scale, float32 code needs --rtol 1e-5)")
    return parser


def _list() -> int:
    print(f"shipped vectors in {VECTOR_DIR}:")
    for path in shipped_vectors():
        data = conformance.load_json(str(path))
        timing = (f"knots={len(data['knots'])} ({data['knots'][0]} .. {data['knots'][-1]} s)" if "knots" in data
                  else f"dt={data['dt']} t0={data['t0']}")
        print(f"  {path.stem:<28} {data.get('representation', 'split'):<6} {data.get('convention', '-'):<7} "
              f"n_ctrl={len(data['rotvecs']):<3} times={len(data['times']):<4} {timing}")
    print("run your code on each input ('inputs FOLDER'), save FOLDER/<name>.json, then 'check-all FOLDER'")
    return 0


def _inputs(folder: str, force: bool) -> int:
    """Every shipped vector's input part to ``folder``; refused before writing any when one target
    exists that the kit did not write (without ``force``)."""
    os.makedirs(folder, exist_ok=True)
    for path in shipped_vectors():
        _refuse_foreign(os.path.join(folder, path.name), force, outcome="nothing was written; ")
    for path in shipped_vectors():
        data = conformance.load_json(str(path))
        subset = {key: data[key] for key in conformance.INPUT_KEYS + conformance.OPTIONAL_INPUT_KEYS if key in data}
        subset["written_by"] = WRITTEN_BY
        target = os.path.join(folder, path.name)
        write_json_atomic(target, subset, force=force)
        print(f"wrote {target}")
    return 0


def format_report(report: dict, reference_name: str = "reference", candidate_name: str = "candidate") -> str:
    """Human-readable report: the error definition, one line per quantity, the worst time of each
    failing quantity, missing times and hints."""
    width = max([14] + [len(row["quantity"]) for row in report["rows"]])  # J_omegadot_body is 15
    lines = [f"{candidate_name} against {reference_name}: error = max |cand - ref| over times and components; "
             f"scale = max |ref|; pass if error <= atol + rtol * scale "
             f"(atol {report['atol']:g}, rtol {report['rtol']:g})",
             f"{'quantity':<{width}} {'error':>10} {'scale':>10} {'error/scale':>11} {'bound':>10}  result"]
    for row in report["rows"]:
        lines.append(f"{row['quantity']:<{width}} {row['error']:10.3e} {row['scale']:10.3e} {row['scaled']:11.3e} "
                     f"{row['bound']:10.3e}  {'ok' if row['ok'] else 'FAIL'}")
    for row in report["rows"]:
        if row["ok"]:
            continue
        where = f"index {row['index']}, t = {row['time']!r} s"
        if row["segment"] is not None:
            where += f", {_segment_label(row['segment'], report['knots'])}, u = {row['u']!r}"
        lines.append(f"  {row['quantity']} worst at {where}:")
        lines += _worst_values(row, report.get("J_first"))
        lines.append(f"    error {row['error']:.3e} (bound {row['bound']:.3e})")
    window = report["window"]
    if window is not None:
        lines.append(f"J_first        FAIL: {window['count']} time(s) with another active window; first at index "
                     f"{window['index']}, t = {window['time']!r} s: candidate {window['cand']}, reference "
                     f"{window['ref']} (index convention or knot rule)")
    if report.get("jacobian_keys"):
        lines.append(f"Jacobians      FAIL: {report['jacobian_keys']}")
    matched, missing, dropped = len(report["times"]), report["missing"], report["dropped"]
    if dropped.size:
        shown = ", ".join(repr(float(t)) for t in dropped[:3]) + (" ..." if dropped.size > 3 else "")
        lines.append(f"times          FAIL: {candidate_name} leaves out {dropped.size} reference time(s) before t_max "
                     f"(missing: {shown}); evaluate at every reference time (only t_max, which a half-open "
                     f"domain drops, may be left out)")
    if missing.size > dropped.size:
        lines.append(f"note: {candidate_name} leaves out t_max = {float(missing[-1])!r} s (a half-open domain drops "
                     f"it); checked on its {matched} times")
    for note in report["notes"]:
        lines.append(f"note: {note}")
    for hint in report["hints"]:
        lines.append(f"hint: {hint}")
    return "\n".join(lines)


def _worst_values(row: dict, first: Optional[np.ndarray]) -> List[str]:
    """The ref and cand lines of a failing quantity at its worst time: the value (R row by row), or
    for a Jacobian (4 x 3 x 3 at that time) the block i and entry (row, col) with the largest error,
    then that block, row by row."""
    ref, cand = np.asarray(row["ref"]), np.asarray(row["cand"])
    lines = []
    if ref.shape == conformance.JACOBIAN_SHAPE:
        i, r, c = np.unravel_index(int(np.argmax(np.abs(cand - ref))), ref.shape)
        point = f" = {int(first[row['index']]) + i}" if first is not None else ""
        lines.append(f"    block i = {i} (control point J_first + {i}{point}), entry (row {r}, col {c}) = "
                     f"(output component {r}, perturbation component {c}): ref {float(ref[i, r, c])!r}, cand "
                     f"{float(cand[i, r, c])!r}; block {i} row by row:")
        ref, cand = ref[i], cand[i]
    for label, value in (("ref", ref), ("cand", cand)):
        shown = np.array2string(value.reshape(-1), precision=12, separator=", ", max_line_width=400)
        lines.append(f"    {label:<4} {shown}")
    return lines


def _segment_label(segment: int, knot_vector: Optional[np.ndarray]) -> str:
    """Where segment ``segment`` lies: uniform t_k = t0 + k dt, or its two entries of 'knots'."""
    if knot_vector is None:
        return f"segment [t_{segment}, t_{segment + 1}) with t_k = t0 + k dt"
    start, end = float(knot_vector[segment + 2]), float(knot_vector[segment + 3])
    return f"segment {segment} = [knots[{segment + 2}], knots[{segment + 3}]) = [{start!r}, {end!r}) s"


def _check(reference_path: str, candidate_path: str, atol: float, rtol: float, reference_name: str = "") -> dict:
    """Print the report of one check and its verdict; returns the report (``ok``, ``jacobians``).
    ``reference_name``: the reference as the user named it (default its path)."""
    report = conformance_hints.check(conformance.load_json(reference_path), conformance.load_json(candidate_path),
                                     atol, rtol, reference_path, candidate_path)
    print(format_report(report, reference_name or reference_path, candidate_path))
    print("PASS" if report["ok"] else "FAIL")
    return report


def _check_all(folder: str, atol: float, rtol: float, allow_missing: bool = False) -> int:
    """Check FOLDER/<name>.json against every shipped vector; print one block each, a summary and a
    last line with the counts.  Returns 0 only when every shipped vector was there and passed (with
    ``allow_missing``: every one that was there), 1 otherwise, 2 when FOLDER holds none of them."""
    conformance.check_tolerances(atol, rtol)
    if not os.path.isdir(folder):
        raise conformance.ConformanceError(f"{folder}: no such folder (check-all wants the folder of your "
                                           f"outputs, FOLDER/<name>.json)")
    results, jacobians = {}, {}  # jacobians: name -> "checked" / "unchecked" for passing vectors that hold them
    for path in shipped_vectors():
        candidate = os.path.join(folder, path.name)
        if not os.path.exists(candidate) or _still_the_input(candidate):
            results[path.stem] = "missing"
            continue
        print(f"== {path.stem}")
        try:
            report = _check(str(path), candidate, atol, rtol, reference_name=f"shipped {path.stem}")
            results[path.stem] = "PASS" if report["ok"] else "FAIL"
            if report["ok"] and report["jacobians"]:
                jacobians[path.stem] = report["jacobians"]
        except conformance.ConformanceError as error:
            print(f"error: {error}")
            results[path.stem] = "error"
    print("== summary")
    for name, result in results.items():
        path = os.path.join(folder, name + ".json")
        unchecked = " (Jacobians not checked: the candidate holds none)" if jacobians.get(name) == "unchecked" else ""
        shown = (result + unchecked if result != "missing" else f"missing (no {path})" if not os.path.exists(path) else
                 f"missing ({path} is still the input 'inputs' wrote: no outputs)")
        print(f"  {name:<28} {shown}")
    counts = {key: sum(result == key for result in results.values()) for key in ("PASS", "FAIL", "error", "missing")}
    if counts["missing"] == len(results):
        print(f"error: {folder} holds none of the shipped names (see 'list')", file=sys.stderr)
        return 2
    _note_unknown_files(folder, results)
    ok = counts["FAIL"] == counts["error"] == 0 and (allow_missing or counts["missing"] == 0)
    print(_counts_line(counts, len(results), allow_missing, ok, _jacobian_counts(jacobians)))
    return 0 if ok else 1


def _jacobian_counts(jacobians: dict) -> str:
    """The last line's tail: of the passing vectors whose reference holds Jacobians, how many had
    them checked (the candidate held them) and how many not ('' when there is none)."""
    if not jacobians:
        return ""
    checked = sum(status == "checked" for status in jacobians.values())
    return (f"; Jacobians checked in {checked} of the {len(jacobians)} passing vector(s) that hold them, "
            f"{len(jacobians) - checked} unchecked")


def _note_unknown_files(folder: str, results: dict) -> None:
    """Name the .json files in FOLDER that are no shipped vector (a misspelt name reads as missing)."""
    unknown = sorted(name for name in os.listdir(folder) if name.endswith(".json") and name[:-5] not in results)
    if unknown:
        shown = ", ".join(unknown[:5]) + (" ..." if len(unknown) > 5 else "")
        print(f"note: {len(unknown)} file(s) in {folder} are no shipped name and were not checked: {shown}")


def _counts_line(counts: dict, total: int, allow_missing: bool, ok: bool, jacobians: str = "") -> str:
    """The last line of check-all: the verdict and how many vectors passed, failed, were bad, missing
    (then ``jacobians``, :func:`_jacobian_counts`)."""
    line = (f"{counts['PASS']} of {total} shipped vectors passed, {counts['FAIL']} failed, "
            f"{counts['error']} malformed, {counts['missing']} missing{jacobians}")
    if not counts["missing"]:
        return f"{'PASS' if ok else 'FAIL'}: {line}"
    if allow_missing:
        return f"{'PASS (partial, --allow-missing)' if ok else 'FAIL'}: {line}"
    return (f"FAIL: {line} (every shipped vector must be checked; write the missing ones, or pass "
            f"--allow-missing for a deliberate partial check)")


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Command-line entry; returns the exit code (0 ok, 1 check failed, 2 bad input)."""
    args = _build_parser().parse_args(argv)
    try:
        if args.command == "list":
            return _list()
        if args.command == "docs":
            print(f"{REFERENCE_DOC}\n")
            print(REFERENCE_DOC.read_text(encoding="utf-8"))
            return 0
        if args.command == "inputs":
            return _inputs(args.folder, args.force)
        if args.command == "evaluate":
            data = conformance.load_json(args.input)
            output = conformance.evaluate_input(data, args.input, jacobians=args.jacobians)
            output = {"written_by": WRITTEN_BY, **output}
            write_json_atomic(args.output, output, force=args.force)
            print(f"wrote {len(output['times'])} samples to {args.output}")
            return 0
        if args.command == "check":
            conformance.check_tolerances(args.atol, args.rtol)
            reference = resolve_reference(args.reference)
            report = _check(reference, args.candidate, args.atol, args.rtol, reference_name=args.reference)
            return 0 if report["ok"] else 1
        return _check_all(args.folder, args.atol, args.rtol, args.allow_missing)
    except BrokenPipeError:  # the reader of our output went away: cli_args.interruptible ends quietly
        raise
    except (conformance.ConformanceError, ValueError, OSError) as error:  # OSError: FileExistsError, no such folder, ...
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    from tsslam_ref.cli_args import interruptible

    sys.exit(interruptible(main, "python -m tsslam_ref.spline_kit"))
