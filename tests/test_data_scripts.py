"""The dataset download scripts, run with a stand-in ``curl`` that serves a small archive laid out as
the real one is (no network): the scenes must land where the script says and the loader looks.

Archive layouts: NeuralRGBD's ``neural_rgbd_data.zip`` holds the scene folders at its top level
(Co-SLAM unzips it inside ``data/neural_rgbd_data``); NICE-SLAM's ``Replica.zip`` holds one folder,
``Replica/``, with the scenes in it.
"""

import os
import subprocess
import zipfile
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parent.parent / "data_scripts"


def _serve(tmp_path, members):
    """A zip of ``members`` (name -> text) and a ``curl`` on PATH that copies it to its -o file."""
    archive = tmp_path / "served.zip"
    with zipfile.ZipFile(archive, "w") as handle:
        for name, text in members.items():
            handle.writestr(name, text)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "curl").write_text(f'#!/bin/sh\nwhile [ "$1" != "-o" ]; do shift; done\ncp "{archive}" "$2"\n')
    (bin_dir / "curl").chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}


def _run(script, dest, env):
    result = subprocess.run(["bash", str(SCRIPTS / script), str(dest)], env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return result


def test_neural_rgbd_scenes_land_inside_the_destination(tmp_path):
    env = _serve(tmp_path, {"breakfast_room/poses.txt": "1", "kitchen/poses.txt": "2"})
    dest = tmp_path / "datasets" / "nrgbd"  # not the default name
    _run("download_neural_rgbd.sh", dest, env)
    assert (dest / "breakfast_room" / "poses.txt").read_text() == "1" and (dest / "kitchen").is_dir()
    assert sorted(p.name for p in dest.parent.iterdir()) == ["nrgbd"]  # nothing loose beside it, no zip left
    assert "have" in _run("download_neural_rgbd.sh", dest, env).stdout  # a second call downloads nothing


def test_replica_scenes_land_inside_a_destination_of_any_name(tmp_path):
    env = _serve(tmp_path, {"Replica/room0/traj.txt": "0", "Replica/office0/traj.txt": "1"})
    dest = tmp_path / "datasets" / "replica_nice"
    _run("download_replica.sh", dest, env)
    assert (dest / "room0" / "traj.txt").read_text() == "0" and (dest / "office0").is_dir()
    assert sorted(p.name for p in dest.parent.iterdir()) == ["replica_nice"]
