"""Exceptions of the imaging room.

`CaseError` is the one exception a user sees for a bad case folder (DESIGN.md,
"The case folder"): its message is one sentence that names the offending file
and says how to fix it. `ImagingError` covers images that cannot be processed
(a segmentation that finds no leg, an alignment without bones).
"""

from __future__ import annotations

from pathlib import Path


class ImagingError(ValueError):
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
