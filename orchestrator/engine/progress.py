"""The progress line of a stage on stderr: what an Evaluator reports as its evaluations finish, drawn in place on a
terminal (rich) and as plain lines anywhere else (tests/engine/test_progress.py)."""

from __future__ import annotations

import sys
import time

from .results import OK

PROGRESS_MIN_BATCH = 8        # a batch this large shows the stage's line at once, with its total
PROGRESS_SHOW_AFTER_S = 2.0   # smaller batches (LM steps, one Jacobian) show it only once the stage has run this long
PROGRESS_REDRAW_S = 0.2       # a terminal's line is redrawn at most 5 times a second
PROGRESS_PLAIN_EVERY_S = 10.0 # elsewhere (CI, a pipe, a file): one plain line this often at most, and one at the end
PROGRESS_TITLE_WIDTH, PROGRESS_BAR_WIDTH = 32, 20   # characters of the terminal line


class Progress:
    """The progress of one stage (every batch one Evaluator runs) on stderr: the stage's label (and the batch's,
    while a large one runs), evaluations done (/ total while a batch of known size runs), how many came from the
    run folder's log, how many failed, engine evaluations per second, and the best and the last misfit.

    One line per stage, not one per batch: Levenberg-Marquardt and Nelder-Mead run many batches of one
    evaluation, which would otherwise each get a line or none. The line appears when a batch of at least
    PROGRESS_MIN_BATCH starts, or once the stage has run PROGRESS_SHOW_AFTER_S, so that a stage of a few quick
    evaluations (or replayed from the log) does not flicker. On a terminal it is redrawn in place (rich Live) when
    an evaluation finishes, at most every PROGRESS_REDRAW_S, and stays as the stage's summary when it closes;
    there is no refresh thread, so that the worker processes forked meanwhile inherit no lock held by one.
    Anywhere else (CI logs, pipes, files) a plain line, without control characters or colours, is printed every
    PROGRESS_PLAIN_EVERY_S at most and once when the stage closes. Silent when disabled."""

    def __init__(self, label: str, enabled: bool = True, *, show_misfit: bool = True, stream=None):
        self.label, self.enabled, self.show_misfit = label, enabled, show_misfit
        self.done = self.from_log = self.failed = 0
        self.best: float | None = None
        self.last: float | None = None
        self.total: int | None = None        # known while a batch of at least PROGRESS_MIN_BATCH runs
        self.batch_label: str | None = None
        self.closed = False
        self.start = time.perf_counter()
        self._stream = stream                 # default: sys.stderr when the line first shows (pytest swaps it)
        self._shown = False
        self._live = None                     # rich Live, on a terminal only
        self._console = None                  # the rich Console it draws on, or that prints the plain lines
        self._last_draw = self.start

    # -- what the evaluator reports --
    def begin_batch(self, size: int, label: str | None = None) -> None:
        if size >= PROGRESS_MIN_BATCH:
            self.total, self.batch_label = self.done + size, label
            self._draw(show=True, force=True)

    def advance(self, record: dict, *, from_log: bool = False) -> None:
        self.done += 1
        self.from_log += from_log
        if record["status"] != OK:
            self.failed += 1
        elif record.get("cost") is not None:
            self.last = float(record["cost"])
            self.best = self.last if self.best is None else min(self.best, self.last)
        self._draw(force=self.total is not None and self.done >= self.total)

    def end_batch(self) -> None:
        self.total = self.batch_label = None

    def close(self) -> None:
        """The stage is over: its line, complete, stays on a terminal; elsewhere it is printed once more."""
        if self.closed:
            return
        self.closed = True
        self.total, self.batch_label = self.done, None
        if not self.enabled:
            return
        if not self._shown and time.perf_counter() - self.start >= PROGRESS_SHOW_AFTER_S:
            self._show()
        if self._live is not None:
            self._live.stop()   # draws the final state and gives the cursor back
        elif self._console is not None:
            self._print_plain()

    # -- the text --
    def title(self) -> str:
        if self.batch_label and self.batch_label != self.label:
            return f"{self.label} / {self.batch_label}"   # ASCII: the plain lines may go to a file read anywhere
        return self.label

    def count(self) -> str:
        return f"{self.done}/{self.total}" if self.total is not None else str(self.done)

    def details(self) -> list[str]:
        """The misfit first: the one piece kept when a narrow terminal cuts the line short."""
        parts = []
        if self.show_misfit and self.best is not None:
            parts.append(f"misfit best {self.best:.4g} last {self.last:.4g}")
        parts += [f"{self.from_log} from log", f"{self.failed} failed"]
        launched = self.done - self.from_log
        if launched:
            rate = launched / max(time.perf_counter() - self.start, 1e-9)
            digits = 2 if rate < 1 else 1 if rate < 10 else 0   # two or three significant figures
            parts.append(f"{rate:.{digits}f} eval/s")
        return parts

    def elapsed(self) -> str:
        seconds = int(time.perf_counter() - self.start)
        hours, rest = divmod(seconds, 3600)
        return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"

    def plain_line(self) -> str:
        return f"{self.title()}: {self.count()} evaluations, {', '.join(self.details())}, {self.elapsed()}"

    # -- drawing --
    def _draw(self, *, show: bool = False, force: bool = False) -> None:
        if not self.enabled or self.closed:
            return
        now = time.perf_counter()
        if not self._shown:
            if not (show or now - self.start >= PROGRESS_SHOW_AFTER_S):
                return
            self._show()
        if self._live is not None:
            if force or now - self._last_draw >= PROGRESS_REDRAW_S:
                self._live.refresh()
                self._last_draw = now
        elif now - self._last_draw >= PROGRESS_PLAIN_EVERY_S:
            self._print_plain()
            self._last_draw = now

    def _show(self) -> None:
        from rich.console import Console
        from rich.live import Live

        self._shown = True
        stream = self._stream if self._stream is not None else sys.stderr
        console = Console(file=stream)
        # rich alone would call a pipe a terminal under FORCE_COLOR or TTY_COMPATIBLE=1; a line redrawn in place
        # needs a real one (and TERM not dumb, TTY_INTERACTIVE not 0)
        if _is_tty(stream) and console.is_interactive:
            self._console = console
            self._live = Live(get_renderable=self._renderable, console=console, auto_refresh=False,
                              transient=False, redirect_stdout=False, redirect_stderr=False)
            self._live.start(refresh=True)
        else:
            self._console = Console(file=stream, force_terminal=False, force_interactive=False, color_system=None,
                                    highlight=False, emoji=False)
        self._last_draw = time.perf_counter()

    def _print_plain(self) -> None:
        self._console.print(self.plain_line(), markup=False, highlight=False, soft_wrap=True)
        self._console.file.flush()

    def _renderable(self):
        """One terminal line, cut to the terminal's width (a wrapped line would be redrawn over several)."""
        from rich.progress_bar import ProgressBar
        from rich.table import Table
        from rich.text import Text

        width = self._console.width
        title, count, elapsed = _cut(self.title(), PROGRESS_TITLE_WIDTH), self.count(), self.elapsed()
        bar_width = PROGRESS_BAR_WIDTH if width >= 100 else 0
        room = width - len(title) - len(count) - len(elapsed) - (bar_width + 1 if bar_width else 0) - 4
        cells = [Text(title, style="bold")]
        if bar_width:
            cells.append(ProgressBar(total=self.total, completed=self.done, width=bar_width, pulse=self.total is None,
                                     animation_time=time.perf_counter()))
        cells += [Text(count), Text(elapsed, style="dim"), Text(_cut(" · ".join(self.details()), room), style="cyan")]
        grid = Table.grid(padding=(0, 1))
        grid.add_row(*cells)
        return grid


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[: max(width - 1, 0)] + "…"


def _is_tty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):   # no isatty, or closed
        return False
