"""Make the shipped trajectory stretches: short cuts of real hand-held motion in TUM format.

The README's synthetic results render the procedural room along a few seconds of real camera motion.
This script cuts those seconds out of the full ground-truth files and writes them, with a header that
names the source, the licence and the cut, into tsslam_ref/assets/trajectories/:

    tum_rgbd_fr2_desk.txt   TUM RGB-D fr2/desk, 0 s .. 4 s after its first pose
    tum_vi_room1.txt        TUM-VI room1, 15 s .. 24 s after its first pose (the README uses 16 s and 20 s)
    tum_vi_room2.txt        TUM-VI room2, 15 s .. 20 s after its first pose (the README uses 16 s)

Data lines are copied unchanged (original timestamps and digits), so every pose read from a stretch is
bit-identical to the same pose read from the full file.  The cut keeps the last line at or before
``origin + begin`` through the first line at or after ``origin + end``, so a pose interpolated at any
time in [begin, end] uses the same two lines as in the full file.  ``origin`` is the first (smallest)
timestamp of the full file; the header records it as ``# origin: <seconds>`` and
``python -m tsslam_ref.data synthesize --trajectory NAME --start S`` measures ``S`` from it, so a
stretch renders exactly the frames the full file renders with the same command.

Inputs (TUM trajectory format, ``timestamp tx ty tz qx qy qz qw``, ``#`` comments), downloaded by the user:

* ``tum_rgbd_fr2_desk_groundtruth.txt``: ``groundtruth.txt`` of ``rgbd_dataset_freiburg2_desk`` from the
  TUM RGB-D benchmark (https://cvg.cit.tum.de/data/datasets/rgbd-dataset).
* ``tum_vi_room1_groundtruth.txt``, ``tum_vi_room2_groundtruth.txt``: the motion-capture ground truth of
  TUM-VI ``dataset-room1_512_16`` and ``dataset-room2_512_16`` (https://cvg.cit.tum.de/data/datasets/visual-inertial-dataset)
  in TUM format (seconds, position, quaternion x y z w; IMU body frame).

Usage:

    python data_scripts/make_trajectory_stretches.py --source DIR [--out DIR] [--force]
"""

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "tsslam_ref" / "assets" / "trajectories"

TUM_RGBD = ("Creative Commons Attribution 4.0; TUM RGB-D benchmark: J. Sturm, N. Engelhard, F. Endres, "
            "W. Burgard, D. Cremers, \"A Benchmark for the Evaluation of RGB-D SLAM Systems\", IROS 2012")
TUM_VI = ("Creative Commons Attribution 4.0; TUM-VI benchmark: D. Schubert, T. Goll, N. Demmel, V. Usenko, "
          "J. Stueckler, D. Cremers, \"The TUM VI Benchmark for Evaluating Visual-Inertial Odometry\", IROS 2018")

STRETCHES = {
    "tum_rgbd_fr2_desk": dict(
        source="tum_rgbd_fr2_desk_groundtruth.txt", begin=0.0, end=4.0, licence=TUM_RGBD,
        what="TUM RGB-D fr2/desk (rgbd_dataset_freiburg2_desk) ground truth: hand-held Kinect, motion capture, "
             "camera-to-world, OpenCV camera axes"),
    "tum_vi_room1": dict(
        source="tum_vi_room1_groundtruth.txt", begin=15.0, end=24.0, licence=TUM_VI,
        what="TUM-VI room1 (dataset-room1_512_16) ground truth: hand-held rig, motion capture, IMU body frame"),
    "tum_vi_room2": dict(
        source="tum_vi_room2_groundtruth.txt", begin=15.0, end=20.0, licence=TUM_VI,
        what="TUM-VI room2 (dataset-room2_512_16) ground truth: hand-held rig, motion capture, IMU body frame"),
}


def data_lines(path: Path):
    """(stamp, line) for every data line of a TUM trajectory, in file order."""
    rows = []
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            rows.append((float(stripped.replace(",", " ").split()[0]), stripped))
    if not rows:
        raise ValueError(f"{path}: no poses")
    return rows


def cut(rows, begin: float, end: float):
    """The origin (first stamp) and the lines from the last one at or before origin + begin through the
    first one at or after origin + end."""
    stamps = np.array([stamp for stamp, _ in rows])
    if np.any(np.diff(stamps) < 0):
        raise ValueError("timestamps decrease")
    origin = float(stamps.min())
    first = int(np.searchsorted(stamps, origin + begin, side="right")) - 1
    last = int(np.searchsorted(stamps, origin + end, side="left"))
    if first < 0 or last >= len(stamps):
        raise ValueError(f"the file covers 0..{stamps[-1] - origin:.3f} s, not {begin}..{end} s")
    if not stamps[last] - stamps[first] >= end - begin:  # e.g. nanoseconds: origin + 24 rounds back to origin
        raise ValueError(f"the lines kept for {begin}..{end} s span {stamps[last] - stamps[first]:.6g}: are the stamps "
                         f"seconds? (the first is {origin:.6g}; TUM format needs seconds, TUM-VI's mocap0/data.csv "
                         f"has nanoseconds)")
    return origin, [line for _, line in rows[first:last + 1]], stamps[first] - origin, stamps[last] - origin


def stretch_text(name: str, source: Path) -> str:
    """The file of stretch ``name`` cut from ``source``: header and original lines."""
    spec = STRETCHES[name]
    origin, lines, covered_from, covered_to = cut(data_lines(source), spec["begin"], spec["end"])
    assert float(repr(origin)) == origin
    header = [
        f"# {name}: a stretch of {spec['what']}",
        f"# source: {spec['source']} (original lines and timestamps, unchanged)",
        f"# licence: {spec['licence']}",
        f"# cut: {spec['begin']:g} s .. {spec['end']:g} s after the full file's first pose, widened to the nearest "
        f"lines outside (covers {covered_from:.4f} .. {covered_to:.4f} s)",
        "# made by data_scripts/make_trajectory_stretches.py; `--start S` of `python -m tsslam_ref.data synthesize` "
        "counts from the origin below",
        f"# origin: {origin!r}",
        "# timestamp tx ty tz qx qy qz qw",
    ]
    return "\n".join(header + lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--source", type=Path, required=True,
                        help="folder with the full ground-truth files (" + ", ".join(s["source"] for s in STRETCHES.values()) + ")")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT.relative_to(ROOT)})")
    parser.add_argument("--force", action="store_true", help="replace existing stretches")
    args = parser.parse_args(argv)
    missing = [spec["source"] for spec in STRETCHES.values() if not (args.source / spec["source"]).is_file()]
    if missing:
        print(f"error: {args.source}: missing {', '.join(missing)} (TUM-format ground truth, see this script's docstring)",
              file=sys.stderr)
        return 2
    existing = [name for name in STRETCHES if (args.out / f"{name}.txt").exists()]
    if existing and not args.force:
        print(f"error: {args.out} already has {', '.join(existing)}; pass --force to replace", file=sys.stderr)
        return 2
    texts = {}
    for name, spec in STRETCHES.items():  # every stretch cut before any file is written: all or none
        try:
            texts[name] = stretch_text(name, args.source / spec["source"])
        except ValueError as error:
            print(f"error: {args.source / spec['source']}: {error}", file=sys.stderr)
            return 2
    args.out.mkdir(parents=True, exist_ok=True)
    for name, text in texts.items():
        path = args.out / f"{name}.txt"
        path.write_text(text)
        print(f"wrote {path} ({path.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
