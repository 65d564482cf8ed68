"""Make the bundled default sequence: a 160x120 slice of TUM RGB-D fr3/teddy in TUM layout.

Reads a TUM sequence folder (``--source``: the first 120 frames of rgbd_dataset_freiburg3_teddy), keeps
its first ``--frames`` associated colour/depth pairs (the first ones of teddy have no ground truth;
the loader drops them), resizes colour (bilinear, antialiased) and depth (nearest) by 1/4 with the
exact intrinsics update of ``Intrinsics.resized`` and writes

    rgb.txt, depth.txt, groundtruth.txt (original lines in the frames' time window),
    rgb/*.png (8-bit), depth/*.png (16-bit, metres x 5000), intrinsics.json, README.md

into tsslam_ref/assets/tum_fr3_teddy_160x120/.  Usage:

    python data_scripts/make_bundled_tum_slice.py [--source DIR] [--out DIR] [--frames 104] [--force]
"""

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from tsslam_ref.cli_args import number_in
from tsslam_ref.data import load_sequence
from tsslam_ref.datasets.tum_format import read_tum_trajectory
from tsslam_ref.files import normal_folder

ROOT = Path(__file__).resolve().parents[1]
README = """# TUM RGB-D fr3/teddy, first {n} frames at {w}x{h} (bundled default sequence)

Made by `data_scripts/make_bundled_tum_slice.py` from `rgbd_dataset_freiburg3_teddy` of the TUM RGB-D
benchmark: colour resized with bilinear filtering, depth with nearest neighbour, by a factor {factor}.
Intrinsics in `intrinsics.json` are the published fr3 values (fx 535.4, fy 539.2, cx 320.1, cy 247.6
at 640x480) updated exactly for the resize (pixel centres at integer coordinates:
fx' = s fx, cx' = s (cx + 0.5) - 0.5).  Depth PNGs: metres x 5000, 0 = no depth.  `groundtruth.txt`
holds the original motion-capture lines (camera-to-world, OpenCV camera axes, qx qy qz qw) in the
frames' time window; the first colour frames come before the first pose and are dropped by the
loader's 0.02 s association rule.

Licence: Creative Commons Attribution 4.0 (CC BY 4.0), as the TUM RGB-D benchmark.
Source: https://cvg.cit.tum.de/data/datasets/rgbd-dataset (Computer Vision Group, TU Munich).
Changes: frames selected and downsampled as described above.

Cite: J. Sturm, N. Engelhard, F. Endres, W. Burgard, D. Cremers, "A Benchmark for the Evaluation of
RGB-D SLAM Systems", Proc. IEEE/RSJ International Conference on Intelligent Robots and Systems (IROS), 2012.
"""


def make_slice(source: Path, out: Path, n_frames: int, width: int, force: bool) -> Path:
    """Write the slice (atomically: a temporary folder renamed into place)."""
    if out.exists() and any(out.iterdir()) and not force:
        raise FileExistsError(f"{out} exists and is not empty; pass --force to replace it")
    sequence = load_sequence(source, dataset="tum", resize_width=width, require_gt=False, frame_stop=n_frames)
    native_width = load_sequence(source, dataset="tum", require_gt=False, frame_stop=1).intrinsics.width
    out.parent.mkdir(parents=True, exist_ok=True)
    temporary = normal_folder(tempfile.mkdtemp(dir=os.path.realpath(out.parent), prefix=f".{out.name}."))
    try:
        _write_slice(source, sequence, n_frames, f"1/{native_width / width:g}", temporary)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)  # nothing half-written is left beside --out
        raise
    if out.exists():
        shutil.rmtree(out)
    temporary.rename(out)
    return out


def _write_slice(source: Path, sequence, n_frames: int, factor: str, temporary: Path) -> None:
    """The slice's files into the folder ``temporary``."""
    k = sequence.intrinsics
    (temporary / "rgb").mkdir()
    (temporary / "depth").mkdir()
    rgb_lines = ["# color images", f"# {n_frames} frames of rgbd_dataset_freiburg3_teddy at {k.width}x{k.height}", "# timestamp filename"]
    depth_lines = ["# depth maps", f"# {n_frames} frames of rgbd_dataset_freiburg3_teddy at {k.width}x{k.height}", "# timestamp filename"]
    for i, frame in enumerate(sequence):
        rgb_name = f"rgb/{sequence.rgb_paths[i].name}"
        depth_name = f"depth/{sequence.depth_paths[i].name}"
        iio.imwrite(temporary / rgb_name, np.round(frame.rgb * 255.0).astype(np.uint8))
        iio.imwrite(temporary / depth_name, np.round(frame.depth * 5000.0).clip(0, 65535).astype(np.uint16))
        rgb_lines.append(f"{sequence.rgb_paths[i].stem} {rgb_name}")
        depth_lines.append(f"{sequence.depth_paths[i].stem} {depth_name}")
    (temporary / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (temporary / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    t_lo, t_hi = sequence.timestamps[0] - 0.05, sequence.timestamps[-1] + 0.05
    gt_lines = []
    for line in (source / "groundtruth.txt").read_text().splitlines():
        fields = line.split()
        if line.startswith("#") or not fields:
            gt_lines.append(line)
        elif t_lo <= float(fields[0]) <= t_hi:
            gt_lines.append(line)
    (temporary / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    read_tum_trajectory(temporary / "groundtruth.txt")  # validate what we wrote
    calibration = dict(k.to_dict(), depth_scale=5000.0,
                       note="fr3 published intrinsics resized exactly; pixel centres at integer coordinates")
    (temporary / "intrinsics.json").write_text(json.dumps(calibration, indent=2) + "\n")
    (temporary / "README.md").write_text(README.format(n=n_frames, w=k.width, h=k.height, factor=factor))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--source", type=Path, required=True, help="TUM folder of rgbd_dataset_freiburg3_teddy (its first 120 frames suffice)")
    parser.add_argument("--out", type=Path, default=ROOT / "tsslam_ref" / "assets" / "tum_fr3_teddy_160x120",
                        help="output folder (default: the bundled sequence's)")
    whole = {"integer": True, "interval": "[1, 10**9]"}
    parser.add_argument("--frames", type=number_in("--frames", 1, 10**9, **whole), default=104,
                        help="associated frames kept (teddy: first 4 lack GT)")
    parser.add_argument("--width", type=number_in("--width", 1, 10**9, **whole), default=160,
                        help="output width in pixels (default 160)")
    parser.add_argument("--force", action="store_true", help="replace a non-empty --out")
    args = parser.parse_args(argv)
    for name in ("rgb.txt", "groundtruth.txt"):
        if not (args.source / name).is_file():
            print(f"error: {args.source} is not a TUM sequence folder with ground truth (no {name})", file=sys.stderr)
            return 2
    try:
        out = make_slice(args.source, args.out, args.frames, args.width, args.force)
    except (OSError, ValueError) as error:  # FileExistsError included
        print(f"error: {error}", file=sys.stderr)
        return 2
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"wrote {out} ({size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
