"""The errors a user sees, one hierarchy: every kind derives from `CalfitError`, which the command line catches
once and reports as its message (one sentence naming the file, the line or the option, and the fix) with exit
code 2, never a traceback.

The kinds keep the built-in class their callers have long caught (ValueError for bad input, RuntimeError for a
failed computation) beside `CalfitError`:

| kind | raised when |
|---|---|
| `CaseError` (an `ImagingError`) | a case folder is missing something or is inconsistent: ``<file>: <what is wrong>; <how to fix it>.`` |
| `ImagingError` | images cannot be processed as asked (no leg found, an alignment without bones) |
| `RunFolderError`, `RunFolderBusy` | a run folder lacks a file an earlier command writes; another command holds it |
| `MaterialError` | a tissue law that cannot be written or fitted |
| `EffectError` | an unknown effect, or one the run's mesh cannot carry |
| `MeshingError` | the curves or the request cannot give a valid mesh |
| `DeckError` | a deck cannot be rendered from the given values |
| `EngineError`, `DeckRejected`, `EngineFailed`, `EngineNotFoundError` | calfit-fe failed, refused a deck, or is not installed |
| `ResultsError` | a run folder of the engine does not hold what was asked of it |
"""

from __future__ import annotations

from pathlib import Path


class CalfitError(Exception):
    """Every error calfit reports to a user: its message says what is wrong and how to mend it."""


class ImagingError(CalfitError, ValueError):
    """An image cannot be processed as asked."""


class CaseError(ImagingError):
    """A case folder is missing something or is inconsistent.

    The message reads ``<file>: <what is wrong>; <how to fix it>.``
    """

    def __init__(self, file: Path | str, problem: str, fix: str):
        self.file = Path(file)
        self.problem = problem
        self.fix = fix
        super().__init__(f"{self.file}: {problem}; {fix}.")


class RunFolderError(CalfitError, ValueError):
    """A run folder is missing a file that an earlier command writes."""


class RunFolderBusy(RunFolderError):
    """Another command holds the run folder."""


class MaterialError(CalfitError, ValueError):
    """A tissue law that cannot be written or fitted (an unknown law, a constant the law has not)."""


class EffectError(CalfitError, ValueError):
    """An unknown effect, or one that the mesh of the run cannot carry."""


class MeshingError(CalfitError, RuntimeError):
    """The curves or the request cannot give a valid mesh; the message says why."""


class DeckError(CalfitError, ValueError):
    """A deck cannot be rendered from the given values (a missing variable, a non-positive constant)."""


class EngineError(CalfitError, RuntimeError):
    """Base class of the engine's failures."""


class DeckRejected(EngineError):
    """calfit-fe exited 2: the deck or mesh is wrong; the message names file and line."""


class EngineFailed(EngineError):
    """calfit-fe exited 4, was killed by a signal, or ran past its timeout."""


class EngineNotFoundError(EngineError):
    """calfit-fe is not installed where calfit looks for it; the message says how to build it."""


class ResultsError(CalfitError, RuntimeError):
    """An engine run folder does not hold what was asked of it (a step, a sensitivity)."""
