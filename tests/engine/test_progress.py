"""The progress line of a stage and --quiet.

- One line per stage (all the batches of one Evaluator): evaluations done (/ total while a large batch runs),
  how many came from the run folder's log, how many failed, the rate, and the best and last misfit.
- Not a terminal (CI, a pipe, pytest's capture): plain lines only, at most one every PROGRESS_PLAIN_EVERY_S and
  one when the stage closes, never an escape sequence, even when FORCE_COLOR or TTY_COMPATIBLE asks for colours.
- A terminal: the line is redrawn in place and stays, complete, when the stage closes; the cursor comes back.
- A stage of a few quick one-evaluation batches (Levenberg-Marquardt steps) shows nothing: no flicker.
- `--quiet`: the commands write nothing on stderr (no progress, no notice), stdout is unchanged: the result
  lines, or one JSON object with --json.
"""

from __future__ import annotations

import io
import json
import re

import pytest

from orchestrator.cli import main
from orchestrator.engine import progress as progress_module
from orchestrator.engine.progress import Progress
from orchestrator.engine.results import BAD_DECK, NOT_CONVERGED, OK

ESCAPE = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture
def plain_environment(monkeypatch):
    """Environment variables that make rich colour a pipe: the plain lines must stay plain regardless."""
    monkeypatch.setenv("FORCE_COLOR", "1")
    monkeypatch.setenv("TTY_COMPATIBLE", "1")
    monkeypatch.setenv("TTY_INTERACTIVE", "1")


@pytest.fixture
def terminal_environment(monkeypatch):
    for name in ("FORCE_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE", "NO_COLOR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("TERM", "xterm-256color")
    monkeypatch.setenv("COLUMNS", "140")


def sweep(progress: Progress, *, from_log: int = 3, failed: int = 2, size: int = 10) -> None:
    """A Monte-Carlo-like batch: `from_log` replayed records first (as the Evaluator does), `failed` failures."""
    progress.begin_batch(size, "noise Monte-Carlo")
    for k in range(size):
        if k >= size - failed:
            record = {"status": NOT_CONVERGED if k % 2 else BAD_DECK, "cost": None}
        else:
            record = {"status": OK, "cost": 0.25 - 0.01 * k}
        progress.advance(record, from_log=k < from_log)
    progress.end_batch()


def test_plain_line_shows_counts_log_failures_and_misfit(plain_environment):
    stream = io.StringIO()
    progress = Progress("montecarlo", stream=stream)
    progress.advance({"status": OK, "cost": 0.3})   # the identified point, one evaluation
    sweep(progress)
    progress.close()
    text = stream.getvalue()
    assert "\x1b" not in text and "\r" not in text
    # the sweep took well under PROGRESS_PLAIN_EVERY_S: one line, when the stage closed
    assert text.splitlines() == [text.strip()]
    assert text.startswith("montecarlo: 11/11 evaluations, misfit best 0.18 last 0.18, 3 from log, 2 failed, ")
    assert re.search(r", [0-9.]+ eval/s, 0:00\n$", text)


def test_plain_lines_come_at_most_every_few_seconds(plain_environment, monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(progress_module, "PROGRESS_PLAIN_EVERY_S", 0.0)   # every evaluation may print
    progress = Progress("montecarlo", stream=stream)
    sweep(progress, size=12)
    progress.close()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 12 + 1
    assert lines[0].startswith("montecarlo / noise Monte-Carlo: 1/12 evaluations, misfit best 0.25 last 0.25, 1 from log")
    assert lines[-2].startswith("montecarlo / noise Monte-Carlo: 12/12 evaluations")
    assert lines[-1].startswith("montecarlo: 12/12 evaluations")
    assert not any("\x1b" in line for line in lines)


def test_short_batches_do_not_flicker_and_long_stages_count_without_a_total(plain_environment, monkeypatch):
    quick = io.StringIO()
    progress = Progress("identify", stream=quick)
    for k in range(5):   # Levenberg-Marquardt steps: batches of one, done in no time
        progress.begin_batch(1)
        progress.advance({"status": OK, "cost": 1.0 / (k + 1)})
        progress.end_batch()
    progress.close()
    assert quick.getvalue() == ""
    # the same stage, had it run longer than PROGRESS_SHOW_AFTER_S: its evaluations counted, no total
    monkeypatch.setattr(progress_module, "PROGRESS_SHOW_AFTER_S", 0.0)
    slow = io.StringIO()
    progress = Progress("identify", stream=slow)
    for k in range(5):
        progress.begin_batch(1)
        progress.advance({"status": OK, "cost": 1.0 / (k + 1)}, from_log=k < 2)
        progress.end_batch()
    progress.close()
    assert slow.getvalue().startswith("identify: 5/5 evaluations, misfit best 0.2 last 0.2, 2 from log, 0 failed")


def test_disabled_and_costs_that_are_not_misfits(plain_environment):
    silent = io.StringIO()
    progress = Progress("montecarlo", enabled=False, stream=silent)
    sweep(progress)
    progress.close()
    assert silent.getvalue() == ""
    pressures = io.StringIO()
    progress = Progress("pressures", show_misfit=False, stream=pressures)
    sweep(progress, from_log=0, failed=0)
    progress.close()
    assert pressures.getvalue().startswith("pressures: 10/10 evaluations, 0 from log, 0 failed, ")
    assert "misfit" not in pressures.getvalue()


def test_terminal_line_is_redrawn_in_place_and_stays(terminal_environment):
    terminal = FakeTerminal()
    progress = Progress("montecarlo", stream=terminal)
    sweep(progress)
    progress.close()
    text = terminal.getvalue()
    assert "\x1b[?25l" in text and text.endswith("\x1b[?25h")   # cursor hidden while drawing, then given back
    frames = [ESCAPE.sub("", frame) for frame in re.split(r"\r\x1b\[2K", text)]
    assert len(frames) >= 2   # drawn, then redrawn over itself
    final = frames[-1].strip()
    assert final.startswith("montecarlo ") and "10/10" in final
    assert "misfit best 0.18 last 0.18 · 3 from log · 2 failed · " in final
    assert "noise Monte-Carlo" in frames[0] and "\n" not in frames[-1].strip()


@pytest.fixture(scope="module")
def identified(drainage_case, tmp_path_factory):
    """The phantom case of conftest.py and a quick identification (200 CPE3) through `calfit identify --quiet
    --json`, with what it printed."""
    case, _ = drainage_case
    run = tmp_path_factory.mktemp("progress") / "run"
    capture = pytest.MonkeyPatch()
    out, err = io.StringIO(), io.StringIO()
    capture.setattr("sys.stdout", out)
    capture.setattr("sys.stderr", err)
    try:
        code = main(["identify", str(case), "--out", str(run), "--elements", "200", "--order", "1", "--workers", "1",
                     "--quiet", "--json"])
    finally:
        capture.undo()
    return case, run, code, out.getvalue(), err.getvalue()


def test_identify_quiet_json_prints_only_the_json(identified):
    _, run, code, out, err = identified
    assert code == 0
    assert err == ""
    result = json.loads(out)   # one JSON object, nothing else on stdout
    assert result["best"]["cost"] > 0 and (run / "identification.json").is_file()


def test_identify_notice_and_quiet(identified, capsys):
    case, run, *_ = identified
    arguments = ["identify", str(case), "--out", str(run), "--elements", "200", "--order", "1", "--workers", "1"]
    assert main(arguments) == 0   # replayed from the run's log
    loud = capsys.readouterr()
    assert f"identification written to {run}/identification.json" in loud.err
    assert main(arguments + ["--quiet"]) == 0
    quiet = capsys.readouterr()
    # the same summary, but for the last line, what each replay took: its stages under 0.05 s are left out, and
    # which those are differs from one replay to the next on a busy machine
    same = [[re.sub(r"\d+\.\d s\b", "<t> s", line) for line in text.splitlines() if not line.startswith("took ")]
            for text in (quiet.out, loud.out)]
    assert quiet.err == "" and same[0] == same[1] and "levenberg-marquardt" in quiet.out
    assert all(text.splitlines()[-1].startswith("took ") for text in (quiet.out, loud.out))


def test_montecarlo_progress_and_quiet(identified, capsys, plain_environment):
    _, run, *_ = identified
    arguments = ["montecarlo", str(run), "--draws", "12", "--workers", "1"]
    assert main(arguments + ["--quiet"]) == 0
    quiet = capsys.readouterr()
    assert quiet.err == ""
    assert "95 % intervals from 12 refitted noise draws" in quiet.out
    assert main(arguments) == 0   # every evaluation replayed from the log, the line says so
    loud = capsys.readouterr()
    assert loud.out.splitlines()[:-1] == quiet.out.splitlines()[:-1]   # the last: engine runs and time
    assert "\x1b" not in loud.err
    assert re.fullmatch(r"montecarlo: 13/13 evaluations, misfit best [0-9.e-]+ last [0-9.e-]+, 13 from log, 0 failed, "
                        r"0:0\d\n", loud.err), loud.err
    assert main(arguments + ["--quiet", "--json"]) == 0
    quiet_json = capsys.readouterr()
    assert quiet_json.err == "" and json.loads(quiet_json.out)["draws"] == 12


def test_quiet_drops_warnings_and_log_records_but_not_errors(capsys):
    import argparse
    import logging
    import warnings

    from orchestrator.cli._common import fail, honours_quiet

    @honours_quiet
    def command(args):
        warnings.warn("a library's warning")
        logging.getLogger("distributed").warning("a library's log record")
        return fail("the error the user must see")

    assert command(argparse.Namespace(quiet=True)) == 2
    assert capsys.readouterr().err == "calfit: the error the user must see\n"
    assert logging.getLogger("distributed").isEnabledFor(logging.WARNING)   # logging as it was after the command


def test_solve_and_leg_slice_demo_quiet(tmp_path, capsys):
    from orchestrator.meshing import leg_slice_deck

    deck = tmp_path / "leg.inp"
    leg_slice_deck(deck, n_elements=400, order=1)
    assert main(["solve", str(deck), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    solved = capsys.readouterr()
    assert solved.err == "" and solved.out.startswith("status      converged")
    assert main(["demo", "--leg-slice", "--out", str(tmp_path / "demo"), "--elements", "400", "--order", "1",
                 "--quiet"]) == 0
    demo = capsys.readouterr()
    assert demo.err == "" and "hydrostatic pressure" in demo.out
