"""Locate the calfit-fe executable.

Search order (as for any packaged compiled tool): the ``CALFIT_FE`` environment
variable, the copy installed inside this package by ``pip install``, the build
tree of an editable install, then ``PATH``.
"""

from __future__ import annotations

import os
import shutil
import sysconfig
from importlib import resources
from pathlib import Path

from ..core.errors import EngineNotFoundError

ENGINE_NAME = "calfit-fe"
ENV_OVERRIDE = "CALFIT_FE"


def _candidates() -> list[Path]:
    found: list[Path] = []
    try:
        found.append(Path(str(resources.files("orchestrator") / "bin" / ENGINE_NAME)))
    except (ModuleNotFoundError, TypeError):
        pass
    # An editable install keeps the package in the source tree while scikit-build-core
    # installs the executable into site-packages/orchestrator/bin.
    found.append(Path(sysconfig.get_paths()["platlib"]) / "orchestrator" / "bin" / ENGINE_NAME)
    repo = Path(__file__).resolve().parents[2]   # orchestrator/engine/locate.py -> the checkout
    found.extend(sorted(repo.glob(f"build/*/solver_cpp/{ENGINE_NAME}")))
    return found


def find_engine() -> Path:
    """Return the path of calfit-fe, or raise EngineNotFoundError saying how to build it."""
    override = os.environ.get(ENV_OVERRIDE)
    if override:
        path = Path(override)
        if path.is_file() and os.access(path, os.X_OK):
            return path
        raise EngineNotFoundError(f"{ENV_OVERRIDE}={override} is not an executable file")
    for path in _candidates():
        if path.is_file() and os.access(path, os.X_OK):
            return path
    on_path = shutil.which(ENGINE_NAME)
    if on_path:
        return Path(on_path)
    raise EngineNotFoundError(
        f"{ENGINE_NAME} not found: run `make setup` (or `pip install -e .`) in the calfit checkout, "
        f"or set {ENV_OVERRIDE} to the executable"
    )
