"""Launch calfit-fe on one deck and turn its exit code into a typed outcome.

Exit codes (solver_cpp/README.md): 0 converged, 2 bad deck (raised as DeckRejected
with the engine's `FILE:LINE: message`), 3 not converged (an outcome, not an error:
the last converged state is on disk and optimizers carry on), 4 or a signal (raised as
EngineFailed). Every launch has a timeout (EngineFailed when it expires; the process
is killed) and list arguments, never a shell. The engine's own log (its progress lines and
errors, as they come) is written line by line into OUTDIR/engine.log, so that a run stopped
midway keeps what it said; with `echo` the lines are copied to stderr too (a tee with a
deadline: subprocess-tee cannot time a process out, so it is not used here). `calfit solve`
and the pipeline's commands with --verbose echo them.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..core.errors import DeckError, DeckRejected, EngineFailed
from .decks import deck_key, sensitivity_blocks
from .locate import find_engine
from .progress import Progress
from .results import (
    BAD_DECK,
    ENGINE_FAILED,
    NOT_CONVERGED,
    OK,
    TIMEOUT,
    EngineResults,
)

DEFAULT_TIMEOUT_S = 600.0
SENSITIVITY_OUTPUT = "sensitivity"        # objective output: dr/d(engine parameter), one vector per deck line
SENSITIVITY_LINES = "sensitivity_lines"   # in the log instead: the lines, in the row order of their .npy
SENSITIVITY_DIR = "sensitivities"


@dataclass(frozen=True)
class EngineOutcome:
    deck: Path
    outdir: Path
    converged: bool
    returncode: int
    wall_time_s: float
    stdout: str
    stderr: str


ENGINE_LOG = "engine.log"


def _tee(stream, sink: list[str], echo: bool, log, lock: threading.Lock) -> None:
    for line in stream:
        sink.append(line)
        with lock:
            log.write(line)
            log.flush()
            if echo:
                sys.stderr.write(line)
                sys.stderr.flush()


def solve_once(model, deck_text: str, failure: str) -> np.ndarray:
    """One engine run of a model's deck text in a scratch folder, the model's mesh include written beside it: the
    displacement of every node of the deck. RuntimeError(failure) when the engine does not converge (a phantom's
    truth or a one-off solve, not an evaluation of a fit: those go through `Evaluator` and its log)."""
    from .runner import write_mesh_include

    with tempfile.TemporaryDirectory(prefix="calfit-solve-") as scratch:
        write_mesh_include(model, Path(scratch))
        deck = Path(scratch) / "deck.inp"
        deck.write_text(deck_text)
        outcome = run_engine(deck, Path(scratch) / "out", threads=None)
        if not outcome.converged:
            raise RuntimeError(failure)
        return EngineResults(outcome.outdir).displacement()


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
    start = time.perf_counter()
    out: list[str] = []
    err: list[str] = []
    outdir.mkdir(parents=True, exist_ok=True)
    lock = threading.Lock()
    with open(outdir / ENGINE_LOG, "w", encoding="utf-8") as log, \
            subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as process:
        readers = [
            threading.Thread(target=_tee, args=(process.stdout, out, echo, log, lock), daemon=True),
            threading.Thread(target=_tee, args=(process.stderr, err, echo, log, lock), daemon=True),
        ]
        for reader in readers:
            reader.start()
        # A watchdog kills the engine at the deadline; wait() blocks in waitpid meanwhile, so a short run
        # is seen the moment it ends (Popen.wait(timeout) polls with sleeps of up to 50 ms).
        expired = threading.Event()

        def stop() -> None:
            expired.set()
            process.kill()

        watchdog = threading.Timer(timeout_s, stop)
        watchdog.daemon = True
        watchdog.start()
        try:
            returncode = process.wait()
        finally:
            watchdog.cancel()
            for reader in readers:
                reader.join(timeout=5.0)
        if expired.is_set():
            raise EngineFailed(f"calfit-fe on {deck} ran past its {timeout_s:g} s timeout and was stopped")
    stdout, stderr = "".join(out), "".join(err)
    elapsed = time.perf_counter() - start
    if returncode == 2:
        raise DeckRejected(stderr.strip() or f"calfit-fe rejected {deck}")
    if returncode not in (0, 3):
        reason = f"signal {-returncode}" if returncode < 0 else f"exit code {returncode}"
        raise EngineFailed(f"calfit-fe failed on {deck} ({reason}): {stderr.strip()}")
    return EngineOutcome(deck, outdir, returncode == 0, returncode, elapsed, stdout, stderr)


# --- evaluations: cache, run log, parallel execution ---------------------------------------------
#
# An evaluation is one deck run through the engine and scored by an objective
# (orchestrator.fit.objectives). Its key is the SHA-256 of the deck, the mesh it includes and the
# objective's fingerprint (decks.deck_key). Every finished evaluation, failed or not, is
# appended as one JSON line to RUN_DIR/evaluations.jsonl (parameters, status, cost, outputs,
# time) the moment it finishes; an `Evaluator` opened on the same run folder reads that log
# back as its cache, so a command interrupted and started again replays the finished
# evaluations from the log and launches the engine only for the others. The engine runs in
# a job folder under RUN_DIR/jobs (removed afterwards) with one thread (--threads 1): the
# parallelism is across evaluations, in a local process pool (`workers`) or on a Dask
# distributed cluster (`scheduler` address).
#
# Several garment levels (`levels.LevelsModel`: loaded images of one slice under garments of
# different tensions, fitted jointly) make one evaluation of several decks, one per level: the
# model's `decks(theta)` gives them, the task carries the tuple, each runs in its own sub-folder
# of the job (level-1, level-2, ...), the record fails when any level fails (its message names
# the level), its Newton iterations are the sum, and the objective's `level_outputs` scores every
# level's (nodal displacement, output folder) together. The key is then that of the decks joined
# with LEVEL_SEPARATOR; a model of one deck keeps its deck, its key and its job folder as they were.


# A sensitivity column carried along a path of friction is one more back-substitution at every increment: on the
# second paper's leg (2,000 CPE6H, 23 increments) 281 columns added 59 s to an 18 s run, 1/86 of the run each. A
# run's timeout, a guard against a hung engine, grows by twice that per column.
TIMEOUT_COLUMNS_PER_RUN = 40
# A hung engine is one that runs far longer than runs of the same run folder have taken to finish: the timeout is at
# least this many times the longest of them (the second paper's band on 3,990 elements, four processes on two cores:
# runs of 100-345 s, and the differences of a refit's Jacobian stopped at the 120 s default, failing the refit).
HANG_FACTOR = 3.0


def run_timeout(deck_text: str, timeout_s: float) -> float:
    """The timeout of a run of this deck: timeout_s, and more where the engine carries sensitivities along the
    loading path (*FRICTION with *SENSITIVITY): one run's worth per TIMEOUT_COLUMNS_PER_RUN columns (a data line of
    a plain *SENSITIVITY block each, a `NAME=` block one)."""
    if "*FRICTION" not in deck_text or "*SENSITIVITY" not in deck_text:
        return timeout_s
    columns = sum(1 if name else len(lines) for name, lines in sensitivity_blocks(deck_text))
    return timeout_s * (1.0 + columns / TIMEOUT_COLUMNS_PER_RUN)


LOG_NAME = "evaluations.jsonl"
LEVEL_SEPARATOR = "\n** next garment level **\n"   # between the decks of one evaluation in its cache key


def _stopped_sooner(record: dict, item: EngineTask | dict) -> bool:
    """A logged run that its timeout stopped sooner than this task's would be: it is launched again (a run stopped
    is not a failure of its deck; a larger --timeout, or a timeout that grows with the run's work, may finish it)."""
    return (record["status"] == TIMEOUT and isinstance(item, EngineTask)
            and record.get("timeout_s", 0.0) < item.timeout_s)


class EvaluationLog:
    """The append-only JSON-lines log of a run's evaluations, read back as a cache by key.

    A line cut short by a kill (no final newline) is dropped when the log is opened, so the
    next append starts on a clean line. The engine sensitivities of an evaluation (p residual vectors,
    p times the size of the rest) go to SENSITIVITY_DIR/<key>.npy beside the log, written whole before its
    line is, and are read back when the record is asked for: a resumed Levenberg-Marquardt gets the same
    Jacobians, takes the same steps and launches nothing it had finished."""

    _appending = threading.Lock()   # one for every log: appends of whole lines, whichever thread writes them

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.sensitivity_dir = self.path.parent / SENSITIVITY_DIR
        self.records: dict[str, dict] = {}
        self.longest_finished_s = 0.0   # the longest run that finished (`HANG_FACTOR`)
        if self.path.is_file():
            data = self.path.read_bytes()
            complete = data[: data.rfind(b"\n") + 1]
            if len(complete) != len(data):
                with open(self.path, "r+b") as stream:
                    stream.truncate(len(complete))
            for number, line in enumerate(complete.decode().splitlines(), start=1):
                if line.strip():
                    try:
                        record = json.loads(line)
                    except json.JSONDecodeError:
                        raise ValueError(f"{self.path}:{number}: not a JSON line; remove that line or the run folder") from None
                    self._keep(record)
        self._stream = None   # opened on the first append

    def append(self, record: dict) -> None:
        if self._stream is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = open(self.path, "a", encoding="utf-8")
        outputs = dict(record["outputs"])
        sensitivity = outputs.pop(SENSITIVITY_OUTPUT, None)
        if sensitivity:
            outputs[SENSITIVITY_LINES] = list(sensitivity)
            self._write_sensitivity(record["key"], np.array([sensitivity[line] for line in sensitivity], float))
        line = json.dumps({**record, "outputs": outputs}, separators=(",", ":")) + "\n"
        with self._appending:   # evaluators of one run in threads side by side (`diagnose.GarmentRuns`): whole lines
            self._stream.write(line)
            self._stream.flush()
        self._keep(record)

    def _keep(self, record: dict) -> None:
        self.records[record["key"]] = record
        if record["status"] == OK:
            self.longest_finished_s = max(self.longest_finished_s, float(record.get("time_s") or 0.0))

    def get(self, key: str) -> dict:
        """The record of a key, its sensitivities read back from their file when they are not in memory."""
        record = self.records[key]
        outputs = record["outputs"]
        if SENSITIVITY_OUTPUT not in outputs and SENSITIVITY_LINES in outputs:
            path = self.sensitivity_dir / f"{key}.npy"
            if path.is_file():
                rows = np.load(path)
                outputs = {**outputs, SENSITIVITY_OUTPUT: {line: rows[k] for k, line in enumerate(outputs[SENSITIVITY_LINES])}}
                record = self.records[key] = {**record, "outputs": outputs}
        return record

    def _write_sensitivity(self, key: str, rows: np.ndarray) -> None:
        self.sensitivity_dir.mkdir(parents=True, exist_ok=True)
        temporary = self.sensitivity_dir / f".{key}.tmp.npy"
        np.save(temporary, rows)
        temporary.replace(self.sensitivity_dir / f"{key}.npy")

    def close(self) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None

    def __len__(self) -> int:
        return len(self.records)


@dataclass(frozen=True)
class EngineTask:
    """One evaluation to run anywhere: the deck (or the tuple of decks, one per garment level), the mesh it
    includes, where to work."""

    key: str
    theta: tuple[float, ...]
    options: dict
    tag: str
    deck_text: str | tuple[str, ...]
    mesh_text: str
    mesh_sha: str
    scratch: str
    timeout_s: float
    threads: int
    keep_job: bool = False
    echo: bool = False     # the engine's log lines on the worker's stderr as they come (--verbose)


def _scratch_folder(preferred: str) -> Path:
    try:
        folder = Path(preferred)
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:   # a remote Dask worker without the run folder: its own temporary folder
        folder = Path(tempfile.gettempdir()) / "calfit-jobs"
        folder.mkdir(parents=True, exist_ok=True)
    return folder


def _mesh_file(scratch: Path, task: EngineTask) -> Path:
    target = scratch / "meshes" / f"{task.mesh_sha[:24]}.inp"
    if not target.is_file():
        target.parent.mkdir(parents=True, exist_ok=True)
        temporary = target.with_name(f"{target.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        temporary.write_text(task.mesh_text)
        temporary.replace(target)
    return target


def execute_task(task: EngineTask, objective) -> dict:
    """Run one evaluation (in a worker): write the deck, run calfit-fe, score it. Never raises for an
    engine failure: the record's status says what happened and `message` quotes the engine."""
    start = time.perf_counter()
    scratch = _scratch_folder(task.scratch)
    job = scratch / task.key
    record = {"key": task.key, "theta": list(task.theta), "options": task.options, "tag": task.tag,
              "status": OK, "cost": None, "outputs": {}, "message": "", "newton_iterations": None}
    levels = isinstance(task.deck_text, tuple)
    decks = task.deck_text if levels else (task.deck_text,)
    # one garment level: the job folder itself, as before levels existed; several: level-1, level-2, ...
    folders = [job / f"level-{k}" for k in range(1, len(decks) + 1)] if levels else [job]
    level = 0
    try:
        mesh = _mesh_file(scratch, task)
        finished = []
        iterations = 0
        for level, (folder, text) in enumerate(zip(folders, decks), start=1):
            outcome = _run_deck(folder, mesh, text, task)
            results = EngineResults(outcome.outdir)
            iterations += results.total_newton_iterations
            record["newton_iterations"] = iterations
            if not outcome.converged:
                record["status"] = NOT_CONVERGED
                record["message"] = (_level_prefix(level, len(decks), levels) + "no convergence (exit 3): reached "
                                     f"load fraction {results.summary['steps'][-1].get('time_reached', 'unknown')}")
                break
            finished.append((results.displacement(), outcome.outdir))
        else:
            if levels:
                record["outputs"] = objective.level_outputs(finished)
            else:
                record["outputs"] = objective.outputs(*finished[0])
            record["cost"] = float(record["outputs"].pop("cost"))
    except DeckRejected as error:
        record.update(status=BAD_DECK, message=_level_prefix(level, len(decks), levels) + str(error))
    except EngineFailed as error:
        record.update(status=TIMEOUT if "timeout" in str(error) else ENGINE_FAILED,
                      message=_level_prefix(level, len(decks), levels) + str(error))
        if record["status"] == TIMEOUT:
            record["timeout_s"] = task.timeout_s
    finally:
        if not task.keep_job:
            shutil.rmtree(job, ignore_errors=True)
    record["time_s"] = time.perf_counter() - start
    record["finished_at"] = time.time()
    return record


def _run_deck(folder: Path, mesh: Path, text: str, task: EngineTask) -> EngineOutcome:
    """One deck of a task in its folder, beside a link to the shared mesh include."""
    folder.mkdir(parents=True, exist_ok=True)
    link = folder / "mesh.inp"
    if not link.exists():
        os.symlink(Path(mesh).resolve(), link)  # a relative target would resolve from the job folder
    deck = folder / "deck.inp"
    deck.write_text(text)
    return run_engine(deck, folder / "out", threads=task.threads, timeout_s=task.timeout_s, echo=task.echo)


def _level_prefix(level: int, count: int, levels: bool) -> str:
    """How a failure names the garment level it happened at (nothing for a model of one deck)."""
    return f"garment level {level} of {count}: " if levels else ""


_WORKER_OBJECTIVE = None


def _install_objective(objective) -> None:
    global _WORKER_OBJECTIVE
    _WORKER_OBJECTIVE = objective


def _execute_in_pool(task: EngineTask) -> dict:
    return execute_task(task, _WORKER_OBJECTIVE)


class Evaluator:
    """Evaluate a model's parameter vectors with an objective, cached by deck key and logged in run_dir.

    model: has `deck(theta, **options) -> str`, `mesh_text`, `mesh_sha`; objective: has
    `outputs(nodal_u, outdir) -> dict` (with "cost") and `fingerprint`. A model of several garment levels has
    `decks(theta, **options) -> tuple[str, ...]` instead, and its objective `level_outputs([(nodal_u, outdir),
    ...])` (`orchestrator.fit.levels`). workers: local processes
    (1 = in this process); scheduler: a Dask distributed address (then workers is ignored).
    `launched` counts the engine runs of this session (not those replayed from the log).
    progress: show the stage's progress line on stderr (`Progress`), named `label`; cost_is_misfit: the
    objective's cost is a misfit, shown best and last on that line (not for the pressure study's); verbose: every
    engine's own log on stderr as it runs (each job folder keeps it in out/engine.log while it lives: keep_jobs)."""

    def __init__(self, model, objective, run_dir: str | Path, *, workers: int = 1, scheduler: str | None = None,
                 timeout_s: float = 120.0, threads: int = 1, progress: bool = True, keep_jobs: bool = False,
                 label: str = "evaluations", cost_is_misfit: bool = True, verbose: bool = False):
        if hasattr(model, "decks") and not hasattr(objective, "level_outputs"):
            raise ValueError("the model fits several garment levels jointly, and the objective "
                             f"{getattr(objective, 'name', type(objective).__name__)} scores one image: use "
                             "levels.JointDisplacementObjective")
        self.model, self.objective = model, objective
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.log = EvaluationLog(self.run_dir / LOG_NAME)
        self.workers, self.scheduler = max(1, int(workers)), scheduler
        self.timeout_s, self.threads, self.progress, self.keep_jobs = timeout_s, threads, progress, keep_jobs
        self.label, self.cost_is_misfit, self.verbose = label, cost_is_misfit, verbose
        self.launched = 0
        self.replayed = 0
        self._display: Progress | None = None   # one for the evaluator's whole stage, not one per batch
        self._pool = None
        self._client = None
        self._remote_objective = None

    # -- backends --
    def _submit(self, tasks: list[EngineTask]) -> Iterable[dict]:
        """Yield the records of tasks as they finish."""
        if self.scheduler:
            yield from self._submit_dask(tasks)
        elif self.workers == 1 or (len(tasks) == 1 and self._pool is None):
            # one task gains nothing from the pool (a Levenberg-Marquardt step, a diagnosis's probe): run here,
            # without starting the pool's processes and sending the record back through a pipe
            for task in tasks:
                yield execute_task(task, self.objective)
        else:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(max_workers=self.workers, initializer=_install_objective,
                                                 initargs=(self.objective,))
            pending: set[Future] = {self._pool.submit(_execute_in_pool, task) for task in tasks}
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    yield future.result()

    def _submit_dask(self, tasks: list[EngineTask]) -> Iterable[dict]:
        from distributed import Client, as_completed

        if self._client is None:
            self._client = Client(self.scheduler, timeout=30, set_as_default=False)
            self._remote_objective = self._client.scatter(self.objective, broadcast=True, hash=False)
        futures = [self._client.submit(execute_task, task, self._remote_objective, pure=False) for task in tasks]
        for future in as_completed(futures, loop=self._client.loop):
            yield future.result()

    def task(self, theta: Sequence[float], options: dict | None = None, tag: str = "") -> EngineTask | dict:
        """The task of theta, or the record of a deck that cannot even be rendered (status bad_deck)."""
        options = dict(options or {})
        theta = tuple(float(v) for v in theta)
        try:
            if hasattr(self.model, "decks"):   # several garment levels: one deck each, one evaluation
                text = tuple(self.model.decks(theta, **options))
            else:
                text = self.model.deck(theta, **options)
        except DeckError as error:
            key = deck_key(json.dumps([theta, options]), self.model.mesh_sha, self.objective.fingerprint)
            return {"key": key, "theta": list(theta), "options": options, "tag": tag, "status": BAD_DECK, "cost": None,
                    "outputs": {}, "message": str(error), "newton_iterations": None, "time_s": 0.0,
                    "finished_at": time.time()}
        joined = LEVEL_SEPARATOR.join(text) if isinstance(text, tuple) else text
        key = deck_key(joined, self.model.mesh_sha, self.objective.fingerprint)
        timeout = max(max(run_timeout(deck, self.timeout_s) for deck in (text if isinstance(text, tuple) else (text,))),
                      HANG_FACTOR * self.log.longest_finished_s)
        return EngineTask(key, theta, options, tag, text, self.model.mesh_text, self.model.mesh_sha,
                          str(self.run_dir / "jobs"), timeout, self.threads, self.keep_jobs, self.verbose)

    def evaluate(self, thetas: Sequence[Sequence[float]], *, options: dict | None = None, tag: str = "",
                 label: str | None = None) -> list[dict]:
        """Records (see execute_task) of every theta, in order; the finished ones come from the log."""
        items = [self.task(theta, options, tag) for theta in thetas]
        keys = [item["key"] if isinstance(item, dict) else item.key for item in items]
        display = self._stage_display()
        display.begin_batch(len(items), label or tag or None)
        try:
            todo: dict[str, EngineTask] = {}
            unrendered: set[str] = set()
            for key, item in zip(keys, items):
                if (key in self.log.records and not _stopped_sooner(self.log.records[key], item)) or key in todo:
                    continue
                if isinstance(item, dict):   # not even rendered: recorded as it is, no engine launch
                    self.log.append(item)
                    unrendered.add(key)
                else:
                    todo[key] = item
            for key in keys:
                if key in self.log.records and key not in todo:
                    self.replayed += 1
                    display.advance(self.log.records[key], from_log=key not in unrendered)
            for record in self._submit(list(todo.values())):
                self.launched += 1
                self.log.append(record)
                display.advance(record)
        except BaseException:
            display.close()   # the stage ends here (an error, Ctrl-C): its last line stays, the cursor comes back
            raise
        finally:
            display.end_batch()
        return [self.log.get(key) for key in keys]

    def _stage_display(self) -> Progress:
        if self._display is None or self._display.closed:
            self._display = Progress(self.label, self.progress, show_misfit=self.cost_is_misfit)
        return self._display

    def __call__(self, theta: Sequence[float], **options) -> dict:
        return self.evaluate([theta], options=options, label=None)[0]

    def close(self) -> None:
        if self._display is not None:
            self._display.close()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        self.log.close()

    def __enter__(self) -> "Evaluator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_mesh_include(model, folder: Path) -> Path:
    """Write the model's mesh include into folder (atomically) and return its path."""
    target = Path(folder) / "mesh.inp"
    temporary = target.with_suffix(".inp.tmp")
    temporary.write_text(model.mesh_text)
    temporary.replace(target)
    return target
