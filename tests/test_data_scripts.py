"""The dataset download scripts, run with a stand-in ``curl`` that serves a small archive laid out as
the real one is (no network): the scenes must land where the script says and the loader looks.

Archive layouts: NeuralRGBD's ``neural_rgbd_data.zip`` holds the scene folders at its top level
(Co-SLAM unzips it inside ``data/neural_rgbd_data``); NICE-SLAM's ``Replica.zip`` holds one folder,
``Replica/``, with the scenes in it.
"""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np

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


def _serve_by_name(tmp_path, archives):
    """A ``curl`` on PATH that serves ``archives`` (URL file name -> archive path) and logs each URL;
    a name it does not hold fails as curl -f does (exit 22)."""
    bin_dir = tmp_path / "bin_by_name"
    bin_dir.mkdir()
    log = tmp_path / "curl.log"
    table = "\n".join(f'  {name}) cp "{path}" "$out" ;;' for name, path in archives.items())
    (bin_dir / "curl").write_text(
        '#!/bin/sh\nwhile [ "$#" -gt 1 ]; do [ "$1" = "-o" ] && out="$2"; url="$2"; shift; done\nurl="$1"\n'
        f'echo "$url" >> "{log}"\ncase "$(basename "$url")" in\n{table}\n  *) exit 22 ;;\nesac\n')
    (bin_dir / "curl").chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}, log


def _zip(path, members):
    with zipfile.ZipFile(path, "w") as handle:
        for name, text in members.items():
            handle.writestr(name, text)
    return path


def test_a_cut_download_fails_and_the_next_run_fetches_it_again(tmp_path):
    """The scripts said "wrote" and exited 0 after a failed unzip, then skipped the half-unpacked
    folder on every later run.  Oracle: the exit status, the folder's contents, curl's log."""
    good = _zip(tmp_path / "good.zip", {"Replica/room0/results/frame000000.jpg": "x", "Replica/room0/traj.txt": "0"})
    cut = tmp_path / "cut.zip"
    cut.write_bytes(good.read_bytes()[:60])
    dest = tmp_path / "datasets" / "Replica"
    env, log = _serve_by_name(tmp_path, {"Replica.zip": cut})
    result = subprocess.run(["bash", str(SCRIPTS / "download_replica.sh"), str(dest)], env=env, capture_output=True,
                            text=True)
    assert result.returncode != 0 and "wrote" not in result.stdout and "damaged" in result.stderr, result
    assert not (dest / "room0").exists()
    (tmp_path / "again").mkdir()
    env, _ = _serve_by_name(tmp_path / "again", {"Replica.zip": good})
    assert "wrote" in _run("download_replica.sh", dest, env).stdout
    assert (dest / "room0" / "traj.txt").read_text() == "0"
    assert sorted(p.name for p in dest.parent.iterdir()) == ["Replica"]  # no zip or scratch folder left


def _real_curl_from_files(tmp_path, folder, ranges=True):
    """The real ``curl`` on PATH behind a wrapper that serves the URL's file name from ``folder`` as a
    file:// URL (curl resumes those as it does HTTP) and logs the bytes each call downloaded.  With
    ``ranges=False`` a resume is refused as curl refuses it from a server without byte ranges (exit 33)."""
    real = shutil.which("curl")
    assert real, "these tests run the real curl"
    bin_dir = tmp_path / "bin_real"
    bin_dir.mkdir()
    log = tmp_path / "downloaded.log"
    refuse = "" if ranges else 'for arg in "$@"; do [ "$arg" = "-C" ] && exit 33; done\n'
    (bin_dir / "curl").write_text(  # the URL is the last argument, the file after -o; log the bytes added
        f'#!/bin/sh\n{refuse}previous=""\n'
        'for arg in "$@"; do url="$arg"; [ "$previous" = "-o" ] && out="$arg"; previous="$arg"; done\n'
        f'file="{folder}/$(basename "$url")"\n'
        'n=$#; i=1\nfor arg in "$@"; do [ "$i" -lt "$n" ] && set -- "$@" "$arg"; i=$((i + 1)); done\nshift "$n"\n'
        'before=0; [ -f "$out" ] && before=$(wc -c < "$out")\n'
        f'status=0; "{real}" -sS "$@" "file://$file" || status=$?\n'
        'after=0; [ -f "$out" ] && after=$(wc -c < "$out")\n'
        f'echo $((after - before)) >> "{log}"\nexit "$status"\n')
    (bin_dir / "curl").chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}, log


def test_a_cut_download_resumes_from_its_part_file_and_one_that_cannot_starts_over(tmp_path):
    """A cut download of a multi-gigabyte archive started again from zero on every run. Oracle: real
    curl's count of downloaded bytes and the unpacked scene."""
    served = tmp_path / "served"
    served.mkdir()
    whole = _zip(served / "Replica.zip", {"Replica/room0/traj.txt": "0",
                                          "Replica/room0/results/depth000000.png": "y" * 4000})
    size = whole.stat().st_size
    dest = tmp_path / "datasets" / "Replica"
    dest.parent.mkdir()
    Path(f"{dest}.zip.part").write_bytes(whole.read_bytes()[:1500])  # what a cut run left
    env, log = _real_curl_from_files(tmp_path, served)
    assert "wrote" in _run("download_replica.sh", dest, env).stdout
    assert (dest / "room0" / "traj.txt").read_text() == "0"
    assert log.read_text().split() == [str(size - 1500)]  # only the rest came
    assert sorted(p.name for p in dest.parent.iterdir()) == ["Replica"]

    other = tmp_path / "other"
    other.mkdir()
    Path(f"{other / 'Replica'}.zip.part").write_bytes(b"bytes of an older archive, served without ranges")
    env, log = _real_curl_from_files(other, served, ranges=False)
    result = _run("download_replica.sh", other / "Replica", env)
    assert "could not resume" in result.stderr and "wrote" in result.stdout, result
    assert (other / "Replica" / "room0" / "traj.txt").read_text() == "0"
    assert log.read_text().split() == [str(size)]  # the whole archive, once


def _http_error_curl(tmp_path, code):
    """A ``curl`` on PATH that answers every request with HTTP ``code``, as curl -f does: the code on
    stdout (the scripts ask for it with -w), exit 22, the -o file untouched."""
    bin_dir = tmp_path / f"bin_{code}"
    bin_dir.mkdir(parents=True)
    (bin_dir / "curl").write_text(f"#!/bin/sh\necho {code}\nexit 22\n")
    (bin_dir / "curl").chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}


def test_an_http_error_keeps_the_part_and_a_whole_part_is_used_as_it_is(tmp_path):
    """A server error (404, 5xx) must not throw away the bytes a cut run left: the next run resumes
    them.  A range past the end (416: the part is whole, a run killed before its rename) goes on to
    the archive test instead of fetching gigabytes again."""
    dest = tmp_path / "datasets" / "Replica"
    dest.parent.mkdir()
    part = Path(f"{dest}.zip.part")
    part.write_bytes(b"the first bytes of the archive")
    for script, folder in (("download_replica.sh", dest), ("download_tum.sh", tmp_path / "TUM")):
        result = subprocess.run(["bash", str(SCRIPTS / script), str(folder)],
                                env=_http_error_curl(tmp_path / script, 404), capture_output=True, text=True)
        assert result.returncode != 0 and "wrote" not in result.stdout, result
    assert part.read_bytes() == b"the first bytes of the archive"
    part.write_bytes(_zip(tmp_path / "whole.zip", {"Replica/room0/traj.txt": "0"}).read_bytes())
    (tmp_path / "whole").mkdir()
    assert "wrote" in _run("download_replica.sh", dest, _http_error_curl(tmp_path / "whole", 416)).stdout
    assert (dest / "room0" / "traj.txt").read_text() == "0" and not part.exists()


def test_tum_sequences_unpack_whole_and_a_failed_host_is_an_error(tmp_path):
    import tarfile

    names = ["rgbd_dataset_freiburg1_desk", "rgbd_dataset_freiburg2_xyz", "rgbd_dataset_freiburg3_long_office_household"]
    archives = {}
    for name in names:
        (tmp_path / "src" / name).mkdir(parents=True)
        (tmp_path / "src" / name / "rgb.txt").write_text(name)
        archives[f"{name}.tgz"] = tmp_path / f"{name}.tgz"
        with tarfile.open(archives[f"{name}.tgz"], "w:gz") as handle:
            handle.add(tmp_path / "src" / name, arcname=name)
    dest = tmp_path / "TUM"
    env, log = _serve_by_name(tmp_path, {key: path for key, path in archives.items() if "freiburg3" not in key})
    result = subprocess.run(["bash", str(SCRIPTS / "download_tum.sh"), str(dest)], env=env, capture_output=True,
                            text=True)
    assert result.returncode == 1 and "could not download freiburg3" in result.stderr, result
    assert (dest / names[0] / "rgb.txt").read_text() == names[0] and not (dest / names[2]).exists()
    assert len(log.read_text().splitlines()) == 4  # one URL for each of the first two, both hosts for the third
    (tmp_path / "second").mkdir()
    env, log = _serve_by_name(tmp_path / "second", archives)
    assert _run("download_tum.sh", dest, env).stdout.count("have") == 2
    assert (dest / names[2] / "rgb.txt").read_text() == names[2]
    assert log.read_text().split() == [f"https://cvg.cit.tum.de/rgbd/dataset/freiburg3/{names[2]}.tgz"]


def test_help_prints_the_usage_and_an_option_is_not_taken_for_the_destination(tmp_path):
    """``--help`` was taken as the destination folder and started the download into ./--help."""
    env, log = _serve_by_name(tmp_path, {})
    for script in ("download_tum.sh", "download_neural_rgbd.sh", "download_replica.sh"):
        shown = subprocess.run(["bash", str(SCRIPTS / script), "--help"], env=env, capture_output=True, text=True,
                               cwd=tmp_path)
        assert shown.returncode == 0 and f"Usage: bash data_scripts/{script}" in shown.stdout, shown
        refused = subprocess.run(["bash", str(SCRIPTS / script), "-x"], env=env, capture_output=True, text=True,
                                 cwd=tmp_path)
        assert refused.returncode == 2 and "unknown option -x" in refused.stderr
    assert not log.exists() and not (tmp_path / "--help").exists()


def test_trajectory_stretches_refuse_nanosecond_stamps_and_write_all_or_none(tmp_path):
    """TUM-VI ships its motion capture in nanoseconds: at 1.5e18, origin + 24 rounds back to the
    origin, and the script wrote a one-pose "stretch" with exit 0.  Oracle: the stamps as written."""
    source, out = tmp_path / "gt", tmp_path / "out"
    source.mkdir()
    pose = "0 0 0 0 0 0 1"
    for name, scale in (("tum_rgbd_fr2_desk", 1.0), ("tum_vi_room1", 1e9), ("tum_vi_room2", 1.0)):
        stamps = 1.5e9 + np.arange(0.0, 30.0, 0.01)
        (source / f"{name}_groundtruth.txt").write_text("".join(f"{t * scale:.0f} {pose}\n" if scale > 1 else
                                                                f"{t:.4f} {pose}\n" for t in stamps))
    result = subprocess.run([sys.executable, str(SCRIPTS / "make_trajectory_stretches.py"), "--source", str(source),
                             "--out", str(out)], capture_output=True, text=True)
    assert result.returncode == 2 and "tum_vi_room1_groundtruth.txt" in result.stderr, result
    assert "are the stamps seconds?" in result.stderr and "Traceback" not in result.stderr
    assert not out.exists()  # the fr2/desk stretch, cut first, is not written either


def test_the_vector_script_replaces_its_own_files_and_refuses_anothers_in_one_line(tmp_path):
    """A second run refused the files the first had written ("was not written by this kit"), with a
    traceback; a refusal came after the files before it were rewritten.  Oracle: the files'
    contents and modification times after each run."""
    script = [sys.executable, str(SCRIPTS / "make_spline_test_vectors.py"), "--out", str(tmp_path)]
    assert subprocess.run(script, capture_output=True, text=True).returncode == 0
    again = subprocess.run(script, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    mine = Path(again.stdout.strip().splitlines()[-1].split(":")[0])  # the file it writes last
    mine.write_text('{"mine": 1}\n')
    before = {path.name: path.stat().st_mtime_ns for path in tmp_path.iterdir()}
    refused = subprocess.run(script, capture_output=True, text=True)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "--force" in refused.stderr, refused
    assert mine.read_text() == '{"mine": 1}\n'
    assert {path.name: path.stat().st_mtime_ns for path in tmp_path.iterdir()} == before  # none rewritten


def test_the_slice_script_leaves_nothing_behind_when_it_fails_and_states_its_factor(tmp_path):
    """A failure after the images were written left a hidden scratch folder beside --out (inside the
    package's assets by default), and the README said "by a factor 1/4" at any width.  Oracle: the
    folder listing, and the widths given (the bundled 160 px frames made 80 px: 1/2)."""
    import shutil

    bundled = SCRIPTS.parent / "tsslam_ref" / "assets" / "tum_fr3_teddy_160x120"
    source = tmp_path / "teddy"
    shutil.copytree(bundled, source)
    script = [sys.executable, str(SCRIPTS / "make_bundled_tum_slice.py"), "--source", str(source), "--frames", "8",
              "--width", "80"]
    made = subprocess.run(script + ["--out", str(tmp_path / "out" / "good")], capture_output=True, text=True)
    assert made.returncode == 0, made.stderr
    assert "by a factor 1/2." in (tmp_path / "out" / "good" / "README.md").read_text()
    lines = (source / "groundtruth.txt").read_text().splitlines()
    first_data = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    lines[first_data + 3] = lines[first_data + 3].rsplit(" ", 1)[0] + " not-a-number"  # inside the frames' window
    (source / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    failed = subprocess.run(script + ["--out", str(tmp_path / "out" / "bad")], capture_output=True, text=True)
    assert failed.returncode == 2 and failed.stderr.startswith("error: ") and "Traceback" not in failed.stderr, failed
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["good"]
