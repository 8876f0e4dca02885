"""Run calfit-fe (and CalculiX) on a deck in a scratch directory and read the results.

A small test helper, not the orchestrator's runner: subprocess with list arguments and
a timeout, never a shell. `run_engine` returns the exit code, stderr, the parsed
summary.json and the step-N.u.npy table (node id, X, Y, u_x, u_y); `run_ccx` runs
`ccx -i JOB` and parses the displacements of `*NODE PRINT ... U` from JOB.dat (the last
printed time), which is how the CalculiX cross-checks read CalculiX.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orchestrator.core.errors import ResultsError
from orchestrator.engine.locate import find_engine
from orchestrator.engine.results import EngineResults

ENGINE_TIMEOUT_S = 300.0


@dataclass
class EngineRun:
    returncode: int
    stdout: str
    stderr: str
    outdir: Path
    deck: Path
    summary: dict | None
    table: np.ndarray | None  # (n_nodes, 5): id, X, Y, u_x, u_y of the last step

    def u(self) -> np.ndarray:
        assert self.table is not None, f"no displacement table; exit {self.returncode}: {self.stderr}"
        return self.table[:, 3:5]

    def vtu(self, step: int = 1):
        return EngineResults(self.outdir).mesh(step)

    def residual_histories(self) -> list[list[float]]:
        return EngineResults(self.outdir).residual_histories() if self.summary else []


def run_engine(
    deck_text: str | None,
    workdir: Path,
    name: str = "job",
    *,
    deck_path: Path | None = None,
    extra_args: tuple[str, ...] = (),
    timeout: float = ENGINE_TIMEOUT_S,
) -> EngineRun:
    """Write deck_text to workdir/name.inp (or use deck_path) and run calfit-fe on it."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    if deck_path is None:
        deck_path = workdir / f"{name}.inp"
        deck_path.write_text(deck_text)
    outdir = workdir / f"{name}.out"
    cmd = [str(find_engine()), str(deck_path), "-o", str(outdir), "--quiet", *extra_args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=workdir)
    summary, table = None, None
    if (outdir / "summary.json").is_file():
        results = EngineResults(outdir)
        summary = results.summary
        try:
            table = results.table()
        except ResultsError:  # a run that failed before writing its first step
            table = None
    return EngineRun(proc.returncode, proc.stdout, proc.stderr, outdir, deck_path, summary, table)


# ----------------------------------------------------------------------------------------
# CalculiX
# ----------------------------------------------------------------------------------------

CCX = "ccx"
CCX_TIMEOUT_S = 1800.0


def ccx_available() -> bool:
    return shutil.which(CCX) is not None


def parse_ccx_dat(path: Path) -> dict[int, np.ndarray]:
    """Displacements of the last ' displacements (vx,vy,vz) ...' block of a ccx .dat file."""
    blocks: list[dict[int, np.ndarray]] = []
    current: dict[int, np.ndarray] | None = None
    for line in Path(path).read_text().splitlines():
        s = line.strip()
        if s.startswith("displacements"):
            current = {}
            blocks.append(current)
            continue
        if current is None or not s:
            continue
        parts = s.split()
        try:
            nid = int(parts[0])
            vals = np.array([float(v) for v in parts[1:4]])
        except ValueError:
            current = None
            continue
        current[nid] = vals
    if not blocks:
        raise RuntimeError(f"no displacement block in {path}")
    return blocks[-1]


NODE_TO_SURFACE_SIGMA_INF = 1e-8  # MPa


def node_to_surface(deck_text: str) -> str:
    """The deck with CalculiX's node-to-surface penalty contact instead of its face-to-face one. CalculiX's LINEAR
    law for it takes K, sigma_inf, c0 (here 1e-3 mm): it rounds the kink at zero clearance over sigma_inf pi / K
    and pulls open pairs with sigma_inf, so a tiny sigma_inf (1e-8 MPa) leaves the penalty pressure K d; calfit-fe
    reads the two and ignores them (no adhesion)."""
    deck_text = re.sub(r"TYPE=SURFACE TO SURFACE", "TYPE=NODE TO SURFACE", deck_text, flags=re.I)
    deck_text, count = re.subn(r"(\*SURFACE BEHAVIOR,\s*PRESSURE-OVERCLOSURE=LINEAR\s*\n)([^,\n]+)\n",
                               rf"\g<1>\g<2>, {NODE_TO_SURFACE_SIGMA_INF:g}, 1e-3\n", deck_text, flags=re.I)
    if count == 0:
        raise ValueError("no *SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR with K alone in the deck")
    return deck_text


def run_ccx(deck_text: str, workdir: Path, name: str = "ccxjob", timeout: float = CCX_TIMEOUT_S, threads: int = 1):
    """Run `ccx -i name` in workdir; returns (returncode, {node id: (ux, uy, uz)}, stdout)."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / f"{name}.inp").write_text(deck_text)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), CCX_NPROC_STIFFNESS=str(threads))
    proc = subprocess.run([CCX, "-i", name], capture_output=True, text=True, timeout=timeout, cwd=workdir, env=env)
    dat = workdir / f"{name}.dat"
    disp = parse_ccx_dat(dat) if dat.is_file() and proc.returncode == 0 else {}
    return proc.returncode, disp, proc.stdout


def ccx_displacement_array(disp: dict[int, np.ndarray], node_ids) -> np.ndarray:
    """(n, 2) in-plane displacements of the given node ids from a parse_ccx_dat dict."""
    return np.array([disp[int(i)][:2] for i in node_ids])
