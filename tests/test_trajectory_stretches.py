"""The shipped trajectory stretches (tsslam_ref/assets/trajectories/) and ``data synthesize --trajectory NAME``.

Oracles: the numbers in the files themselves (parse, finite, unit quaternions, increasing stamps), the
README's own ``data synthesize`` commands (what the stretches must cover), and the full ground-truth
files the stretches were cut from (rendering from either must give the same frames, bit for bit).
"""

import re
import shlex
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from tsslam_ref import data

ROOT = Path(__file__).resolve().parents[1]
STRETCHES = ROOT / "tsslam_ref" / "assets" / "trajectories"


def header(path: Path) -> dict:
    """The ``# key: value`` lines of a stretch's header."""
    keys = {}
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        match = re.match(r"# (\w+): (.*)", line)
        if match:
            keys[match.group(1)] = match.group(2)
    return keys


def readme_synthesize_commands():
    """(argument list) of every ``python -m tsslam_ref.data synthesize`` line of the README that uses
    ``--trajectory``."""
    commands = []
    for line in (ROOT / "README.md").read_text().splitlines():
        if "tsslam_ref.data synthesize" in line and "--trajectory " in line and "FILE" not in line:
            words = shlex.split(line.strip().strip("`"))
            commands.append(words[words.index("synthesize") + 1:])
    return commands


def option(words, name, default):
    return words[words.index(name) + 1] if name in words else default


def test_every_shipped_name_has_a_file_and_nothing_else_ships():
    assert sorted(p.stem for p in STRETCHES.glob("*.txt")) == sorted(data.SHIPPED_TRAJECTORIES)
    for name in data.SHIPPED_TRAJECTORIES:
        assert data.trajectory_path(name) == STRETCHES / f"{name}.txt"


@pytest.mark.parametrize("name", data.SHIPPED_TRAJECTORIES)
def test_stretch_parses_and_is_sane(name):
    path = STRETCHES / f"{name}.txt"
    assert path.stat().st_size < 120_000  # small
    keys = header(path)
    assert "Creative Commons Attribution 4.0" in keys["licence"]
    assert ("Sturm" in keys["licence"] and "IROS 2012" in keys["licence"]) or \
           ("Schubert" in keys["licence"] and "IROS 2018" in keys["licence"])
    assert keys["source"] and keys["cut"]
    table = np.loadtxt(path, comments="#")
    assert table.shape[1] == 8 and len(table) > 100 and np.isfinite(table).all()
    assert np.all(np.diff(table[:, 0]) > 0)  # strictly increasing stamps
    assert np.allclose(np.linalg.norm(table[:, 4:8], axis=1), 1.0, atol=1e-3)  # unit quaternions (4-6 digits)
    stamps, poses = data.read_tum_trajectory(path)
    assert np.array_equal(stamps, table[:, 0]) and np.allclose(poses[:, :3, 3], table[:, 1:4])
    origin = float(keys["origin"])
    assert data.trajectory_origin(path) == origin and origin <= stamps[0]


def test_readme_commands_are_covered():
    commands = readme_synthesize_commands()
    assert len(commands) >= 4, "the README's results name their synthesize commands"
    for words in commands:
        name = option(words, "--trajectory", None)
        assert name in data.SHIPPED_TRAJECTORIES, f"README renders along {name}, which does not ship"
        stamps = data.read_tum_trajectory(data.trajectory_path(name))[0]
        first = data.trajectory_origin(data.trajectory_path(name)) + float(option(words, "--start", 0.0))
        last = first + (int(option(words, "--frames", 60)) - 1) / float(option(words, "--fps", 30.0))
        assert stamps[0] <= first and last <= stamps[-1], (words, stamps[0], first, last, stamps[-1])


def test_bad_trajectory_name_is_refused(tmp_path, capsys):
    status = data.main(["synthesize", "--out", str(tmp_path / "out"), "--trajectory", "tum_vi_room9"])
    message = capsys.readouterr().err
    assert status == 2 and "tum_vi_room9" in message and "tum_vi_room1" in message
    assert not (tmp_path / "out").exists()


def test_start_before_a_stretch_is_refused(tmp_path, capsys):
    """room1's stretch starts 15 s into the recording: --start 0 cannot be served from it."""
    status = data.main(["synthesize", "--out", str(tmp_path / "out"), "--trajectory", "tum_vi_room1", "--frames", "2"])
    assert status == 2 and "tum_vi_room1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def render(tmp_path: Path, tag: str, trajectory: str, words) -> Path:
    """Run ``data synthesize`` with the README command's options, another trajectory source, a small size."""
    out = tmp_path / tag
    argv = ["synthesize", "--out", str(out), "--trajectory", trajectory, "--size", "32x24", "--mesh-voxel", "0.25"]
    for name in ("--start", "--frames", "--fps", "--seed"):
        if name in words:
            argv += [name, option(words, name, None)]
    assert data.main(argv) == 0
    return out


@pytest.mark.shared_data
def test_stretch_renders_the_same_frames_as_the_full_file(shared_data, tmp_path):
    """Every README command gives bit-identical frames and ground truth from the stretch and from the
    full recording, so the README's numbers stand for a clone."""
    for index, words in enumerate(readme_synthesize_commands()):
        name = option(words, "--trajectory", None)
        full = shared_data / "trajectories" / f"{name}_groundtruth.txt"
        stretch_lines = [line for line in data.trajectory_path(name).read_text().splitlines() if not line.startswith("#")]
        assert set(stretch_lines) <= set(full.read_text().splitlines())  # original lines, unchanged
        a = render(tmp_path, f"stretch{index}", name, words)
        b = render(tmp_path, f"full{index}", str(full), words)
        assert (a / "groundtruth.txt").read_bytes() == (b / "groundtruth.txt").read_bytes()
        assert (a / "rgb.txt").read_bytes() == (b / "rgb.txt").read_bytes()
        names = sorted(p.name for p in (a / "rgb").iterdir())
        assert names == sorted(p.name for p in (b / "rgb").iterdir()) and len(names) == int(option(words, "--frames", 60))
        for folder in ("rgb", "depth"):
            for file in names:
                assert np.array_equal(iio.imread(a / folder / file), iio.imread(b / folder / file)), (words, folder, file)


def test_synthesize_help_lists_the_shipped_names(capsys):
    assert data.main(["synthesize", "--help"]) == 0  # the command line returns its exit status
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    for name in data.SHIPPED_TRAJECTORIES:
        assert name in text
