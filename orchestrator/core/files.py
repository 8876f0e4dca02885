"""The run folder's JSON files: written whole or not at all, read with a sentence that names the command which
writes them.

A file is written to a hidden temporary beside it and renamed over it (`Path.replace`, atomic on POSIX), so a
command stopped mid-write leaves the previous version, never half a file. This module sits below every room of
the pipeline (measure, study, identify, diagnose) so that each writes its results without importing another.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import RunFolderError


def atomic_write_text(path: Path, text: str) -> None:
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(text, encoding="utf-8")
    temporary.replace(path)


def write_json(path: Path, data: dict) -> None:
    atomic_write_text(Path(path), json.dumps(data, indent=2) + "\n")


def read_json(path: Path, made_by: str) -> dict:
    """The JSON file at `path`; RunFolderError naming `made_by`, the command that writes it, when it is missing."""
    path = Path(path)
    if not path.is_file():
        raise RunFolderError(f"{path} does not exist: run `{made_by}` first")
    return json.loads(path.read_text(encoding="utf-8"))


def replace_folder(staging: Path, folder: Path) -> None:
    """Move a fully written staging folder to its final place, replacing an old one only at the very end."""
    if folder.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
        os.rename(folder, old / folder.name)
        os.rename(staging, folder)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(staging, folder)


@contextmanager
def staged_folders(*folders: Path) -> Iterator[tuple[Path, ...]]:
    """Hidden staging folders, one beside each of `folders`, to write into; when the block ends normally each is
    moved to its folder in turn (`replace_folder`), and when anything is raised (Ctrl-C included) every staging
    folder not yet moved is removed, so a folder is replaced whole or left as it was."""
    folders = tuple(Path(folder) for folder in folders)
    staging = []
    try:
        for folder in folders:
            folder.parent.mkdir(parents=True, exist_ok=True)
            staging.append(Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent)))
        yield tuple(staging)
        while staging:
            replace_folder(staging[0], folders[len(folders) - len(staging)])
            staging.pop(0)
    finally:
        for left in staging:
            shutil.rmtree(left, ignore_errors=True)
