"""Launch calfit-fe on one deck and turn its exit code into a typed outcome.

Exit codes (solver_cpp/README.md): 0 converged, 2 bad deck (raised as DeckRejected
with the engine's `FILE:LINE: message`), 3 not converged (an outcome, not an error:
the last converged state is on disk and optimizers carry on), 4 or a signal (raised as
EngineFailed). Every launch has a timeout (EngineFailed when it expires; the process
is killed) and list arguments, never a shell. With `echo`, the engine's progress lines
are copied to stderr while they are captured (a tee with a deadline: subprocess-tee
cannot time a process out, so it is not used here).
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from .engine import find_engine

DEFAULT_TIMEOUT_S = 600.0


class EngineError(RuntimeError):
    """Base class of the engine's failures."""


class DeckRejected(EngineError):
    """calfit-fe exited 2: the deck or mesh is wrong; the message names file and line."""


class EngineFailed(EngineError):
    """calfit-fe exited 4, was killed by a signal, or ran past its timeout."""


@dataclass(frozen=True)
class EngineOutcome:
    deck: Path
    outdir: Path
    converged: bool
    returncode: int
    wall_time_s: float
    stdout: str
    stderr: str


def _tee(stream, sink: list[str], echo: bool) -> None:
    for line in stream:
        sink.append(line)
        if echo:
            sys.stderr.write(line)
            sys.stderr.flush()


def run_engine(
    deck: str | Path,
    outdir: str | Path | None = None,
    *,
    threads: int | None = 1,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    echo: bool = False,
) -> EngineOutcome:
    """Run calfit-fe on `deck`, writing into `outdir` (default: beside the deck)."""
    deck = Path(deck)
    outdir = Path(outdir) if outdir is not None else deck.with_suffix(".out")
    command = [str(find_engine()), str(deck), "-o", str(outdir)]
    if threads:
        command += ["--threads", str(threads)]
    if not echo:
        command.append("--quiet")
    start = time.perf_counter()
    out: list[str] = []
    err: list[str] = []
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as process:
        readers = [
            threading.Thread(target=_tee, args=(process.stdout, out, echo), daemon=True),
            threading.Thread(target=_tee, args=(process.stderr, err, echo), daemon=True),
        ]
        for reader in readers:
            reader.start()
        try:
            returncode = process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            raise EngineFailed(f"calfit-fe on {deck} ran past its {timeout_s:g} s timeout and was stopped") from None
        finally:
            for reader in readers:
                reader.join(timeout=5.0)
    stdout, stderr = "".join(out), "".join(err)
    elapsed = time.perf_counter() - start
    if returncode == 2:
        raise DeckRejected(stderr.strip() or f"calfit-fe rejected {deck}")
    if returncode not in (0, 3):
        reason = f"signal {-returncode}" if returncode < 0 else f"exit code {returncode}"
        raise EngineFailed(f"calfit-fe failed on {deck} ({reason}): {stderr.strip()}")
    return EngineOutcome(deck, outdir, returncode == 0, returncode, elapsed, stdout, stderr)
