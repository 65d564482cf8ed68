"""files.py: atomic writes with the user's normal mode, links replaced (never written through),
cleanup of our own stray temporary files only."""

import os
import stat

import pytest

from tsslam_ref import files


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield 0o640  # what open(path, "w") gives under this umask
    os.umask(old)


def test_a_new_file_gets_the_mode_open_would_give(tmp_path, umask_027):
    files.atomic_write_text(tmp_path / "a.txt", "hello\n")
    with open(tmp_path / "b.txt", "w") as stream:  # the oracle: what a plain open() makes
        stream.write("x")
    assert (tmp_path / "a.txt").read_text() == "hello\n"
    assert stat.S_IMODE(os.stat(tmp_path / "a.txt").st_mode) == stat.S_IMODE(os.stat(tmp_path / "b.txt").st_mode) == umask_027
    assert files.normal_mode() == umask_027
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]  # no temporary left


def test_a_link_at_the_name_is_replaced_and_its_target_kept(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    target = outside / "precious.txt"
    target.write_bytes(b"user data")
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.png").symlink_to(target)
    files.atomic_write_bytes(run / "trajectory.png", b"\x89PNG new")
    assert target.read_bytes() == b"user data"
    assert not (run / "trajectory.png").is_symlink()
    assert (run / "trajectory.png").read_bytes() == b"\x89PNG new"
    (run / "dangling.txt").symlink_to(outside / "missing.txt")
    files.atomic_write_text(run / "dangling.txt", "new")
    assert not (outside / "missing.txt").exists() and (run / "dangling.txt").read_text() == "new"


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with files.atomic_path(path) as temporary:
            temporary.write_text("half")
            raise KeyboardInterrupt
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


def test_a_folder_at_the_name_is_refused(tmp_path):
    (tmp_path / "mesh.ply").mkdir()
    with pytest.raises(IsADirectoryError, match="mesh.ply"):
        files.atomic_write_text(tmp_path / "mesh.ply", "x")


def test_only_our_stray_temporaries_are_removed(tmp_path):
    outside = tmp_path / "outside.txt"
    outside.write_text("keep")
    run = tmp_path / "run"
    run.mkdir()
    ours = [".trajectory.txt.ab12cd_3.tmp", ".checkpoint.pt.zzzzzzzz.tmp"]
    theirs = [".notes.txt.ab12cd34.tmp", "user.tmp", ".trajectory.txt.tmp", "trajectory.txt",
              "tmp_backup1.tmp", "tmpdata2024.tmp", "tmpk2j4h5g6.ply.tmp",
              "metrics.json.backup01.tmp"]  # a user's names, whatever their shape (ours start with a dot)
    for name in ours + theirs:
        (run / name).write_text(name)
    (run / ".metrics.json.q1w2e3r4.tmp").symlink_to(outside)
    removed = files.remove_stray_temporaries(run, lambda name: name in ("trajectory.txt", "checkpoint.pt", "metrics.json"))
    assert sorted(p.name for p in removed) == sorted(ours + [".metrics.json.q1w2e3r4.tmp"])
    assert sorted(p.name for p in run.iterdir()) == sorted(theirs)
    assert outside.read_text() == "keep"


def test_the_temporary_is_one_that_the_cleanup_after_a_kill_recognises(tmp_path):
    """A write killed half-way leaves its temporary; it must be hidden and named after its output
    (``.<name>.<8 characters>.tmp``) so that remove_stray_temporaries finds it the next time."""
    with files.atomic_path(tmp_path / "trajectory.txt") as temporary:
        temporary.write_text("half")
        assert temporary.parent == tmp_path and temporary.name.startswith(".trajectory.txt.")
        removed = files.remove_stray_temporaries(tmp_path, lambda name: name == "trajectory.txt")
        assert removed == [temporary]  # what a killed process would have left
        temporary.write_text("whole")  # the write goes on
    assert (tmp_path / "trajectory.txt").read_text() == "whole"


def test_a_link_to_a_folder_at_the_name_is_replaced_and_the_folder_kept(tmp_path):
    """Only a real folder is refused; a link at the name is replaced, whatever it points to."""
    folder = tmp_path / "users_folder"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    (tmp_path / "mesh.ply").symlink_to(folder)
    files.atomic_write_text(tmp_path / "mesh.ply", "ply")
    assert not (tmp_path / "mesh.ply").is_symlink() and (tmp_path / "mesh.ply").read_text() == "ply"
    assert [p.name for p in folder.iterdir()] == ["notes.txt"] and (folder / "notes.txt").read_text() == "mine"


def test_a_dangling_link_named_like_our_temporary_is_removed(tmp_path):
    """remove_stray_temporaries unlinks a link of our name even when its target is gone."""
    (tmp_path / ".metrics.json.a1b2c3d4.tmp").symlink_to(tmp_path / "gone")
    assert files.remove_stray_temporaries(tmp_path, lambda name: name == "metrics.json") == [
        tmp_path / ".metrics.json.a1b2c3d4.tmp"]
    assert list(tmp_path.iterdir()) == []


def test_a_path_through_a_link_and_up_is_written_where_the_system_finds_it(tmp_path, monkeypatch):
    """'out/../x' with 'out' a link: the system resolves '..' from the link's target, while
    ``mkstemp`` made a relative folder absolute as text (into another folder), so every write failed."""
    (tmp_path / "real" / "inner").mkdir(parents=True)
    (tmp_path / "real" / "run").mkdir()  # 'out/../run' is this folder; there is no tmp_path / "run"
    (tmp_path / "out").symlink_to(tmp_path / "real" / "inner")
    monkeypatch.chdir(tmp_path)
    files.atomic_write_text("out/../run/x.txt", "written")
    assert (tmp_path / "real" / "run" / "x.txt").read_text() == "written"
    assert [path.name for path in (tmp_path / "real" / "run").iterdir()] == ["x.txt"]  # no stray temporary
