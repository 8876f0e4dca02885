"""One command at a time in a run folder.

Two commands writing the same run folder (its evaluation log, setup, results) would interleave their
writes. Every pipeline command takes an exclusive lock on RUN_DIR/.calfit.lock (`fcntl.flock`, released by
the kernel when the process ends, however it ends) and writes who holds it there; a second command on the
same folder stops at once with a sentence naming the holder. A command that calls another in the same
process (identify measures first) holds the lock once: the depth is counted per folder in this process.
Only the commands that make a run folder (measure, identify) create it; the others stop when it is missing
rather than leave an empty folder behind a mistyped path. A command that made the folder and then fails (a
case it refuses, a folder that does not exist) removes it again, with the folders it made above it, when it
holds nothing but the lock (in a folder that was there, the lock it made): a refused command leaves nothing
behind, and never removes a folder it did not make or anything written in it. An interrupted command (KeyboardInterrupt) keeps its folder as it is.
"""

from __future__ import annotations

import fcntl
import functools
import inspect
import json
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from .errors import RunFolderBusy, RunFolderError

LOCK_NAME = ".calfit.lock"
_held: dict[str, list] = {}   # folder -> [open lock file, depth]: a lock is one per process by nature


@contextmanager
def run_folder_lock(run_dir, create: bool = False):
    """Hold RUN_DIR for the duration of the block (made first when `create`); RunFolderBusy if another
    process holds it, RunFolderError if it is missing and not to be made."""
    folder = Path(run_dir).resolve()
    key = str(folder)
    if key in _held:
        _held[key][1] += 1
        try:
            yield
        finally:
            _held[key][1] -= 1
        return
    made: list[Path] = []   # the folders made here, deepest first
    if create:
        for place in (folder, *folder.parents):
            if place.is_dir():
                break
            if place.exists():
                raise RunFolderError(f"{run_dir} cannot be a run folder: {place} is a file; give the path of a "
                                     "folder (a new one is made)")
            made.append(place)
        folder.mkdir(parents=True, exist_ok=True)
    elif not folder.is_dir():
        raise RunFolderError(f"{run_dir} is not a run folder: run `calfit identify CASE_DIR --out {run_dir}` first")
    lock_made = not (folder / LOCK_NAME).exists()
    stream = open(folder / LOCK_NAME, "a+")
    try:
        fcntl.flock(stream, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        stream.seek(0)
        holder = stream.read().strip()
        stream.close()
        raise RunFolderBusy(f"{folder} is in use by another calfit command ({_describe(holder)}): wait for it to "
                            "finish, or give this one another run folder") from None
    stream.seek(0)
    stream.truncate()
    stream.write(json.dumps({"pid": os.getpid(), "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:2]]),
                             "since": time.strftime("%Y-%m-%d %H:%M:%S")}))
    stream.flush()
    _held[key] = [stream, 1]
    try:
        yield
    except Exception:
        _release(key, stream)
        _remove_if_empty(made or ([folder] if lock_made else []), folders=bool(made))
        raise
    except BaseException:
        _release(key, stream)
        raise
    else:
        _release(key, stream)


def _release(key: str, stream) -> None:
    del _held[key]
    stream.seek(0)
    stream.truncate()
    fcntl.flock(stream, fcntl.LOCK_UN)
    stream.close()


def _remove_if_empty(made: list[Path], folders: bool = True) -> None:
    """Remove what a failed command made: its folders (deepest first) while they hold nothing but an empty lock
    (folders), else the lock it made in a folder that was there before."""
    for place in made:
        lock = place / LOCK_NAME
        try:
            if lock.is_file() and lock.stat().st_size == 0 and (not folders or len(list(place.iterdir())) == 1):
                lock.unlink()
            if folders:
                place.rmdir()   # refuses a folder that is not empty: what was written in it stays
        except OSError:
            return


def _describe(holder: str) -> str:
    try:
        info = json.loads(holder)
        return f"pid {info['pid']}, {info['command']}, since {info['since']}"
    except (ValueError, KeyError, TypeError):
        return "holder unknown"


def holds_run_folder(argument: str = "run_dir", create: bool = False):
    """Decorator: the function runs holding the lock of its `argument` (a run folder, made first when
    `create`)."""
    def decorate(function):
        signature = inspect.signature(function)

        @functools.wraps(function)
        def locked(*args, **kwargs):
            with run_folder_lock(signature.bind(*args, **kwargs).arguments[argument], create):
                return function(*args, **kwargs)
        return locked
    return decorate
