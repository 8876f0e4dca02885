"""Kill a calfit command part-way and count its engine launches: the helpers of the resume tests.

A command is killed with SIGKILL (no handler runs, as when a machine loses power) once its run folder's log
holds a given number of evaluations, together with every process it started (its engines and workers: a machine
that loses power loses them too; an engine left running would note its launch after the count was read); a wrapper around calfit-fe counts the engine launches, so that a test can
tell the evaluations read back from the log from those run again."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

from orchestrator.engine.locate import find_engine
from orchestrator.engine.runner import LOG_NAME


def calfit_command(*arguments) -> list[str]:
    return [sys.executable, "-m", "orchestrator.cli", *map(str, arguments)]


def counting_wrapper(folder: Path):
    """An engine wrapper that notes each launch in folder/launches.txt, and a function that reads the count."""
    counter = folder / "launches.txt"
    wrapper = folder / "calfit-fe-counting"
    wrapper.write_text(f'#!/bin/bash\necho launch >> "{counter}"\nexec "{find_engine()}" "$@"\n')
    wrapper.chmod(wrapper.stat().st_mode | stat.S_IEXEC)
    return wrapper, lambda: len(counter.read_text().splitlines()) if counter.exists() else 0


def log_lines(run: Path) -> list[dict]:
    """The run's logged evaluations, its complete lines only: the command may be writing the last one as it is read
    (a line is whole once its newline is written; `EvaluationLog` drops a cut line on opening for the same reason)."""
    path = run / LOG_NAME
    if not path.exists():
        return []
    text = path.read_text()
    return [json.loads(line) for line in text[: text.rfind("\n") + 1].splitlines()]


def kill_after(command, environment, run: Path, evaluations: int, *, deadline_s: float = 300.0) -> None:
    """Start the command and SIGKILL it once the run's log holds `evaluations` lines."""
    process = subprocess.Popen(command, env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    try:
        deadline = time.monotonic() + deadline_s
        while len(log_lines(run)) < evaluations and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert process.poll() is None, "the command finished before it could be interrupted"
        os.killpg(process.pid, signal.SIGKILL)
    finally:
        process.wait(timeout=60)
