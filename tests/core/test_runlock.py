"""One command at a time in a run folder (`orchestrator.core.run_lock`): a second process is told who holds the folder,
the same process may nest commands, and the lock goes with the process however it ends."""

import subprocess
import sys
import time

import pytest

from orchestrator.core.errors import RunFolderBusy
from orchestrator.core.run_lock import LOCK_NAME, holds_run_folder, run_folder_lock

HOLDER = """
import sys, time
from orchestrator.core.run_lock import run_folder_lock
with run_folder_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def _hold(folder, seconds):
    process = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder), str(seconds)], stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "held"
    return process


def test_a_second_process_is_told_who_holds_the_folder(tmp_path):
    holder = _hold(tmp_path, 30)
    try:
        with pytest.raises(RunFolderBusy, match=rf"in use by another calfit command \(pid {holder.pid}, .* since"):
            with run_folder_lock(tmp_path):
                pass
    finally:
        holder.kill()
        holder.communicate()
    with run_folder_lock(tmp_path):     # a killed holder leaves the folder free
        assert (tmp_path / LOCK_NAME).read_text().startswith("{")


def test_the_same_process_nests_commands_and_releases_at_the_end(tmp_path):
    @holds_run_folder()
    def inner(run_dir):
        return "inner"

    @holds_run_folder()
    def outer(case, run_dir):
        return inner(run_dir)

    assert outer("case", run_dir=tmp_path) == "inner"
    holder = _hold(tmp_path, 0.2)     # released: another process takes it at once
    holder.communicate(timeout=30)
    assert holder.returncode == 0


def test_the_lock_waits_for_nobody(tmp_path):
    holder = _hold(tmp_path, 30)
    try:
        began = time.monotonic()
        with pytest.raises(RunFolderBusy):
            with run_folder_lock(tmp_path):
                pass
        assert time.monotonic() - began < 5.0    # says so at once instead of hanging
    finally:
        holder.kill()
        holder.communicate()


def test_a_calfit_command_on_a_busy_folder_says_so_and_writes_nothing(tmp_path):
    holder = _hold(tmp_path, 60)
    try:
        before = sorted(p.name for p in tmp_path.iterdir())
        second = subprocess.run([sys.executable, "-m", "orchestrator.cli", "diagnose", str(tmp_path)],
                                capture_output=True, text=True, timeout=120)
        assert second.returncode != 0
        assert f"is in use by another calfit command (pid {holder.pid}" in second.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == before
    finally:
        holder.kill()
        holder.communicate()


@pytest.mark.parametrize("command", ["montecarlo", "pressures", "diagnose", "report", "paraview"])
def test_a_command_on_a_missing_run_folder_says_so_and_creates_nothing(tmp_path, command):
    """Only measure and identify make a run folder; a mistyped path to any other stage leaves nothing behind."""
    missing = tmp_path / "no-such-run"
    finished = subprocess.run([sys.executable, "-m", "orchestrator.cli", command, str(missing)], capture_output=True,
                              text=True, timeout=120)
    assert finished.returncode == 2
    assert f"{missing} is not a run folder: run `calfit identify CASE_DIR --out {missing}` first" in finished.stderr
    assert not missing.exists()


def test_a_failed_command_removes_the_folders_it_made_while_they_are_empty(tmp_path):
    run = tmp_path / "runs" / "run"
    with pytest.raises(ValueError):
        with run_folder_lock(run, create=True):
            raise ValueError("the case is refused")
    assert list(tmp_path.iterdir()) == []


def test_a_failed_or_interrupted_command_keeps_what_it_wrote(tmp_path):
    """The work done before the failure stays (run the command again to resume); an interrupted command keeps even
    an empty folder, as it always has."""
    written = tmp_path / "written"
    with pytest.raises(RuntimeError):
        with run_folder_lock(written, create=True):
            (written / "evaluations.jsonl").write_text("{}\n")
            raise RuntimeError("an engine failure")
    assert (written / "evaluations.jsonl").is_file()
    interrupted = tmp_path / "interrupted"
    with pytest.raises(KeyboardInterrupt):
        with run_folder_lock(interrupted, create=True):
            raise KeyboardInterrupt
    assert interrupted.is_dir()


def test_a_failed_command_never_removes_a_folder_it_did_not_make(tmp_path):
    with pytest.raises(ValueError):
        with run_folder_lock(tmp_path, create=True):
            raise ValueError("refused")
    assert tmp_path.is_dir() and not (tmp_path / LOCK_NAME).exists()
