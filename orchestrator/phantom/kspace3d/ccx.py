"""CalculiX (ccx) as the k-space phantom's 3D solver: one run of a deck in a job folder, its nodal displacements.

`run_ccx` writes the deck, runs `ccx -i JOB` in the folder with a timeout (never a shell), and reads the last
block of nodal displacements that `*NODE PRINT, NSET=NALL` wrote to JOB.dat. A run that fails (no executable,
a timeout, a non-zero exit, an *ERROR line, no displacement block: ccx stops without converging) raises
`CcxError` with one sentence naming the job folder and the fix. The counts of increments and Newton iterations
come from ccx's own log on stdout.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CCX = "ccx"
DEFAULT_TIMEOUT_S = 1800.0


class CcxError(RuntimeError):
    """CalculiX did not give a solution (the message says why and what to do)."""


@dataclass(frozen=True)
class CcxRun:
    """One ccx run: nodal displacements (n, 3) in node-id order, wall time, increments and iterations."""

    displacement_mm: np.ndarray
    wall_s: float
    increments: int
    iterations: int
    folder: Path


def ccx_available() -> bool:
    return shutil.which(CCX) is not None


def run_ccx(deck_text: str, folder: Path, n_nodes: int, *, job: str = "leg3d", timeout_s: float = DEFAULT_TIMEOUT_S,
            threads: int | None = None) -> CcxRun:
    """Run the deck in `folder` (created) and return its last displacements of nodes 1..n_nodes."""
    if not ccx_available():
        raise CcxError("CalculiX (ccx) is not on PATH; install it (apt-get install calculix-ccx) to solve the 3D leg")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{job}.inp").write_text(deck_text, encoding="utf-8")
    threads = threads or os.cpu_count() or 1
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), CCX_NPROC_STIFFNESS=str(threads),
               CCX_NPROC_EQUATION_SOLVER=str(threads), CCX_NPROC_RESULTS=str(threads))
    start = time.perf_counter()
    try:
        process = subprocess.run([CCX, "-i", job], cwd=folder, env=env, capture_output=True, text=True,
                                 timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise CcxError(f"ccx ran longer than {timeout_s:g} s on {folder / job}.inp; use a coarser 3D mesh (fewer "
                       "elements or layers) or raise the timeout") from None
    wall = time.perf_counter() - start
    (folder / f"{job}.log").write_text(process.stdout + process.stderr, encoding="utf-8")
    error = next((line.strip() for line in (process.stdout + process.stderr).splitlines() if "*ERROR" in line), None)
    if process.returncode != 0 or error:
        raise CcxError(f"ccx failed on {folder / job}.inp ({error or f'exit code {process.returncode}'}); read "
                       f"{folder / job}.log, and lower the load or stiffen the tissues if it did not converge")
    displacement = _last_displacements(folder / f"{job}.dat", n_nodes)
    increments = len(re.findall(r"^\s*increment\s+\d+\s+attempt", process.stdout, flags=re.M))
    iterations = len(re.findall(r"^\s*iteration\s+\d+", process.stdout, flags=re.M))
    return CcxRun(displacement, wall, increments, iterations, folder)


def _last_displacements(path: Path, n_nodes: int) -> np.ndarray:
    """The last 'displacements (vx,vy,vz)' block of a .dat file, as (n_nodes, 3) in node-id order."""
    if not path.is_file():
        raise CcxError(f"ccx wrote no {path.name} in {path.parent}; read its log there")
    text = path.read_text(encoding="utf-8", errors="replace")
    start = text.rfind("displacements (vx,vy,vz)")
    if start < 0:
        raise CcxError(f"{path} holds no displacement block: ccx stopped before the first converged increment; read "
                       "its log, and lower the load or stiffen the tissues")
    body = text[text.index("\n", start) + 1:]
    rows = []
    for line in body.splitlines():
        parts = line.split()
        if not parts:
            if rows:
                break
            continue
        try:
            rows.append((int(parts[0]), float(parts[1]), float(parts[2]), float(parts[3])))
        except (ValueError, IndexError):
            break
    table = np.array(rows)
    if len(table) != n_nodes or not np.array_equal(table[:, 0].astype(int), np.arange(1, n_nodes + 1)):
        raise CcxError(f"{path} lists {len(table)} nodes where the deck has {n_nodes}; the run is incomplete, read "
                       "its log")
    return table[:, 1:]
