"""Two runs on one output folder: the second is refused while the first goes, and a killed run's
lock file does not stand in the way of the next one (``run_outputs.output_folder_lock``, flock)."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tsslam_ref import run, run_outputs

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "tsslam_ref" / "assets" / "tum_fr3_teddy_160x120"
QUICK = ["--data", BUNDLED, "--config", "tiny", "--method", "coslam", "--frames", "0:3", "--quiet", "--no-mesh",
         "--set", "tracking.iters=1", "--set", "mapping.first_iters=1", "--set", "mapping.iters=1"]
HOLD = ("import sys; from pathlib import Path; from tsslam_ref.run_outputs import output_folder_lock\n"
        "with output_folder_lock(Path(sys.argv[1])):\n    print('held', flush=True); sys.stdin.read()\n")


def earlier_run(folder: Path) -> dict:
    """Plant an earlier run's files; returns their bytes to compare with afterwards."""
    folder.mkdir()
    (folder / "trajectory.txt").write_text("0.0 0 0 0 0 0 0 1\n")
    (folder / "config.json").write_text("{}\n")
    return {path.name: path.read_bytes() for path in folder.iterdir()}


def files_of(folder: Path) -> dict:
    return {path.name: path.read_bytes() for path in folder.iterdir() if path.name != run_outputs.LOCK_NAME}


@pytest.mark.parametrize("flag", ["--overwrite", "--resume"])
def test_a_run_on_a_folder_another_process_writes_is_refused_and_changes_nothing(tmp_path, capsys, flag):
    out = tmp_path / "run"
    before = earlier_run(out)
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    try:
        assert holder.stdout.readline().strip() == "held"
        code = run.main([str(a) for a in QUICK + ["--out", out, flag]])
        error = capsys.readouterr().err.strip()
        assert code == run.EXIT_BAD_INPUT, error
        assert error.startswith(f"error: another run (process {holder.pid} on {socket.gethostname()} since ")
        assert len(error.splitlines()) == 1
        assert files_of(out) == before
    finally:
        holder.communicate("", timeout=60)
    assert not (out / run_outputs.LOCK_NAME).exists()  # the holder removed its lock as it ended


def test_two_runs_past_the_folder_check_at_once_the_second_is_refused_by_the_lock(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    before = earlier_run(out)
    monkeypatch.setattr(run, "check_output_folder", lambda *args: None)  # both passed it before either locked
    with run_outputs.output_folder_lock(out):
        code = run.main([str(a) for a in QUICK + ["--out", out, "--overwrite"]])
        error = capsys.readouterr().err
        assert code == run.EXIT_BAD_INPUT and "another run (process" in error, error
        assert files_of(out) == before  # --overwrite removed nothing
    assert not (out / run_outputs.LOCK_NAME).exists()


def test_a_killed_runs_lock_is_named_then_taken_over(tmp_path):
    """A killed run leaves its run.lock unlocked (the kernel drops a dead process's flock), whatever
    it says: its process id (which a reboot or a container may give to another process), its host."""
    out = tmp_path / "run"
    earlier_run(out)
    lock = out / run_outputs.LOCK_NAME
    for content in (f"process {os.getpid()} on {socket.gethostname()} since 2026-01-01 00:00:00\n",
                    "process 1 on some-other-host since 2026-01-01 00:00:00\n", ""):
        lock.write_text(content)
        with pytest.raises(ValueError, match="file.s. a killed run left"):
            run_outputs.check_output_folder(out, overwrite=False, resume=False, data_folder=str(BUNDLED))
        run_outputs.check_output_folder(out, overwrite=True, resume=False, data_folder=str(BUNDLED))
        with run_outputs.output_folder_lock(out) as held:
            assert held.read_text().startswith(f"process {os.getpid()} on {socket.gethostname()} since ")
        assert not lock.exists()


def test_the_lock_of_a_run_killed_with_sigkill_is_free_at_once(tmp_path):
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(run_outputs.FolderInUse, match=f"process {holder.pid} "):
        run_outputs.check_output_folder(out, overwrite=True, resume=False, data_folder=str(BUNDLED))
    holder.kill()  # no finally, no unlink: the file stays, the kernel drops the lock
    holder.wait(timeout=60)
    assert (out / run_outputs.LOCK_NAME).read_text().startswith(f"process {holder.pid} ")
    run_outputs.check_output_folder(out, overwrite=True, resume=False, data_folder=str(BUNDLED))
    with run_outputs.output_folder_lock(out):
        pass
    assert list(out.iterdir()) == []


def test_a_held_lock_is_refused_in_the_same_process_too(tmp_path):
    out = tmp_path / "run"
    with run_outputs.output_folder_lock(out):
        with pytest.raises(run_outputs.FolderInUse, match=f"another run .process {os.getpid()} "):
            with run_outputs.output_folder_lock(out):
                pass
        with pytest.raises(run_outputs.FolderInUse, match="another run"):
            run_outputs.check_output_folder(out, overwrite=True, resume=False, data_folder=str(BUNDLED))
        assert (out / run_outputs.LOCK_NAME).exists()  # the refused attempt left the holder's lock alone
    assert not (out / run_outputs.LOCK_NAME).exists()


def test_the_lock_is_removed_when_the_run_raises(tmp_path):
    out = tmp_path / "new" / "run"
    with pytest.raises(KeyboardInterrupt):
        with run_outputs.output_folder_lock(out):
            assert (out / run_outputs.LOCK_NAME).is_file()
            raise KeyboardInterrupt
    assert out.is_dir() and list(out.iterdir()) == []
