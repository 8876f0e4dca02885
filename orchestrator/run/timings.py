"""Where a command's time goes: the wall time and engine runs of each of its stages.

A command (`calfit identify`, `calfit diagnose`) opens one `StageClock` on its run folder; the code it calls marks
its stages with `stage(name)`, which does nothing when no clock is running (a stage called on its own, a test).
Stages nest: an inner stage's time and runs are its own, not its outer stage's as well, so that the stages and
"other" (what no stage holds: reading the case, writing the records) add up to the whole. A stage entered
several times (the fit of every pass of the skin's uncertainty) is one entry, its `calls` counted.

Engine runs are the evaluations a stage launched, read off the run's log (one line each, `engine.runner`), plus
the one-off solves that go around the log (the skin's uncertainty, `geometry_uncertainty.geometry_columns`), which
their stage declares with `runs(n)`. An evaluation replayed from the log costs no run and is not counted.

identification.json and diagnosis.json keep the clock as "timings" (`StageClock.as_dict`); `timing_line` says it
in one line."""

from __future__ import annotations

import contextvars
import functools
import inspect
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from ..engine.runner import LOG_NAME

_CURRENT: contextvars.ContextVar[StageClock | None] = contextvars.ContextVar("calfit_stage_clock", default=None)


@dataclass
class _Open:
    name: str
    began: float
    logged: int
    inner_s: float = 0.0
    inner_runs: int = 0
    declared: int = 0   # runs outside the log, this stage's and its inner stages'


@dataclass
class StageClock:
    """The stages of one command on one run folder (module text)."""

    run_dir: Path
    began: float = field(default_factory=time.perf_counter)
    stages: dict[str, dict] = field(default_factory=dict)
    _open: list[_Open] = field(default_factory=list)
    _ended: float | None = None

    def logged_runs(self) -> int:
        """The evaluations the run's log holds now (its lines)."""
        path = Path(self.run_dir) / LOG_NAME
        try:
            with open(path, "rb") as stream:
                return sum(chunk.count(b"\n") for chunk in iter(lambda: stream.read(1 << 22), b""))
        except FileNotFoundError:
            return 0

    @contextmanager
    def stage(self, name: str):
        frame = _Open(name, time.perf_counter(), self.logged_runs())
        self._open.append(frame)
        try:
            yield self
        finally:
            self._open.pop()
            elapsed = time.perf_counter() - frame.began
            runs = self.logged_runs() - frame.logged + frame.declared
            entry = self.stages.setdefault(name, {"wall_time_s": 0.0, "engine_runs": 0, "calls": 0})
            entry["wall_time_s"] += elapsed - frame.inner_s
            entry["engine_runs"] += runs - frame.inner_runs
            entry["calls"] += 1
            if self._open:
                self._open[-1].inner_s += elapsed
                self._open[-1].inner_runs += runs
                self._open[-1].declared += frame.declared

    def runs(self, count: int) -> None:
        """Engine runs the open stage made outside the run's log."""
        if self._open:
            self._open[-1].declared += int(count)
        else:   # no stage open: "other"'s
            self.stages.setdefault("other", {"wall_time_s": 0.0, "engine_runs": 0, "calls": 0})["engine_runs"] += count

    def stop(self) -> None:
        self._ended = time.perf_counter()

    def as_dict(self) -> dict:
        """{"wall_time_s", "engine_runs", "stages": [{"stage", "wall_time_s", "engine_runs", "calls"}, ...]}, the
        last stage "other": the whole's time that no stage holds, so that the stages add up to the whole."""
        total = (self._ended or time.perf_counter()) - self.began
        named = [{"stage": name, **values} for name, values in self.stages.items() if name != "other"]
        other = self.stages.get("other", {"engine_runs": 0})
        staged = sum(s["wall_time_s"] for s in named)
        named.append({"stage": "other", "wall_time_s": max(0.0, total - staged), "engine_runs": other["engine_runs"],
                      "calls": 1})
        return {"wall_time_s": total, "engine_runs": sum(s["engine_runs"] for s in named), "stages": named}


@contextmanager
def clocked(run_dir):
    """A StageClock for the command running now, current while it runs (`stage` marks its stages); nested in a
    running one (a command another calls, as identify calls measure), that one's."""
    running = _CURRENT.get()
    if running is not None:
        yield running
        return
    clock = StageClock(Path(run_dir))
    token = _CURRENT.set(clock)
    try:
        yield clock
    finally:
        clock.stop()
        _CURRENT.reset(token)


@contextmanager
def stage(name: str):
    """Mark a stage of the running command (nothing without one)."""
    clock = _CURRENT.get()
    if clock is None:
        yield None
        return
    with clock.stage(name):
        yield clock


def declare_runs(count: int) -> None:
    """Engine runs the current stage made outside the run's log (nothing without a running clock)."""
    clock = _CURRENT.get()
    if clock is not None:
        clock.runs(count)


def timing_line(timings: dict | None) -> str | None:
    """'took 9.8 s: measure 3.1 s, fit 2.0 s (12 engine runs), ...' of a record's "timings"; None without one.
    Stages under 0.05 s are left out of the line (the record keeps them)."""
    if not timings:
        return None
    parts = []
    for entry in timings["stages"]:
        if entry["wall_time_s"] < 0.05 and not entry["engine_runs"]:
            continue
        runs = entry["engine_runs"]
        parts.append(f"{entry['stage']} {entry['wall_time_s']:.1f} s"
                     + (f" ({runs} engine run{'s' if runs != 1 else ''})" if runs else ""))
    runs = timings["engine_runs"]
    return (f"took {timings['wall_time_s']:.1f} s, {runs} engine run{'s' if runs != 1 else ''}: "
            + ", ".join(parts))


def timed(argument: str = "run_dir"):
    """Decorator: the command runs under a clock on its run folder `argument` (`clocked`); `current_timings` then
    gives what it has measured so far, for the record it writes last."""
    def decorate(function):
        signature = inspect.signature(function)

        @functools.wraps(function)
        def clocked_command(*args, **kwargs):
            with clocked(signature.bind(*args, **kwargs).arguments[argument]):
                return function(*args, **kwargs)
        return clocked_command
    return decorate


def current_timings() -> dict | None:
    """`StageClock.as_dict` of the running command's clock so far; None without one."""
    clock = _CURRENT.get()
    return None if clock is None else clock.as_dict()
