"""Read what calfit-fe wrote into an output folder (formats: solver_cpp/README.md).

summary.json (status, increments, Newton residual histories, timings), the nodal
displacement table step-N.u.npy (node id, X, Y, u_x, u_y) and, on demand, the VTU of a
step through meshio (stress, pressure, J and material per element). The hydrostatic
pressure that the first paper maps (Avril et al. sec. 3.2, Fig. 5) is the VTU's
`pressure` = -tr(sigma)/3, per node (nodal average) or per element, in MPa.

With `*SENSITIVITY` in the deck, summary.json lists the requested parameters
(`sensitivities`: index, name, value, file, max_abs_du) and each has its table
step-N.du-K.npy (node id, X, Y, du_x/dtheta, du_y/dtheta) for the last step N; with
PRESSURE=YES the last step's VTU holds the cell fields `dp/d<name>`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..core.errors import ResultsError

# what an evaluation of a deck came to (runner, progress), as its record in the run folder's log says
OK, NOT_CONVERGED, BAD_DECK, ENGINE_FAILED, TIMEOUT = "ok", "not_converged", "bad_deck", "engine_failed", "timeout"
FAILED_STATUSES = (NOT_CONVERGED, BAD_DECK, ENGINE_FAILED, TIMEOUT)


def sensitivity_name(line: str) -> str:
    """The engine's name for the column of a plain `*SENSITIVITY` line as calfit writes it: its fields joined by
    colons ("SHAPE, SKIN, A2" -> "SHAPE:SKIN:A2"; solver_cpp/README.md, Sensitivities)."""
    return ":".join(field.strip() for field in line.split(","))


@dataclass
class EngineResults:
    outdir: Path
    # each step's VTU parsed once: a reader of several fields (garment_state reads six) does not parse it again
    _meshes: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @cached_property
    def summary(self) -> dict:
        path = self.outdir / "summary.json"
        if not path.is_file():
            raise ResultsError(f"{path} does not exist: the engine wrote no results there")
        return json.loads(path.read_text())

    @property
    def n_steps(self) -> int:
        return len(self.summary["steps"])

    def table(self, step: int | None = None) -> np.ndarray:
        """(n_nodes, 5) array: node id, X, Y, u_x, u_y at the end of `step` (default: last)."""
        step = self.n_steps if step is None else step
        path = self.outdir / f"step-{step}.u.npy"
        if not path.is_file():
            raise ResultsError(f"{path} does not exist (the run has {self.n_steps} step(s))")
        return np.load(path)

    def displacement(self, step: int | None = None) -> np.ndarray:
        return self.table(step)[:, 3:5]

    def mesh(self, step: int | None = None):
        import meshio

        step = self.n_steps if step is None else step
        if step not in self._meshes:
            self._meshes[step] = meshio.read(self.outdir / f"step-{step}.vtu")
        return self._meshes[step]

    def point_field(self, name: str, step: int | None = None) -> np.ndarray:
        """A point-data array of the step's VTU (e.g. "pressure", MPa), in deck node order."""
        mesh = self.mesh(step)
        if name not in mesh.point_data:
            raise ResultsError(f"{self.outdir}: the VTU has no point field {name!r} (it has {sorted(mesh.point_data)})")
        return np.asarray(mesh.point_data[name], float).squeeze()

    def cell_field(self, name: str, step: int | None = None) -> np.ndarray:
        """A cell-data array of the step's VTU (e.g. "pressure", "J", "material_id"), in deck element order."""
        mesh = self.mesh(step)
        if name not in mesh.cell_data:
            raise ResultsError(f"{self.outdir}: the VTU has no cell field {name!r} (it has {sorted(mesh.cell_data)})")
        return np.asarray(mesh.cell_data[name][0], float).squeeze()

    @property
    def sensitivity_parameters(self) -> list[dict]:
        """The summary's `sensitivities` entries (index, name, value, file, max_abs_du), deck order."""
        return list(self.summary.get("sensitivities", []))

    def sensitivities(self) -> dict[str, np.ndarray]:
        """du/dtheta of each *SENSITIVITY parameter: name (e.g. "MATERIAL:MUSCLE:C10") ->
        (n_nodes, 2) array in deck node order, parameters in deck order; {} without *SENSITIVITY."""
        out: dict[str, np.ndarray] = {}
        for entry in self.sensitivity_parameters:
            path = self.outdir / entry["file"]
            if not path.is_file():
                raise ResultsError(f"{path} does not exist: summary.json lists it for {entry['name']}")
            out[entry["name"]] = np.load(path)[:, 3:5]
        return out

    def pressure_sensitivities(self) -> dict[str, np.ndarray]:
        """d(pressure)/dtheta per element (*SENSITIVITY, PRESSURE=YES): name -> (n_elements,)
        array of d(-tr sigma / 3)/dtheta in deck element order, from the last step's VTU."""
        names = [entry["name"] for entry in self.sensitivity_parameters]
        if not names:
            return {}
        mesh = self.mesh()
        missing = [n for n in names if f"dp/d{n}" not in mesh.cell_data]
        if missing:
            raise ResultsError(f"{self.outdir}: no pressure sensitivities for {missing} (ask with *SENSITIVITY, PRESSURE=YES)")
        return {n: np.asarray(mesh.cell_data[f"dp/d{n}"][0], float).squeeze() for n in names}

    @property
    def total_newton_iterations(self) -> int:
        return sum(int(step["newton_iterations"]) for step in self.summary["steps"])

    def residual_histories(self) -> list[list[float]]:
        return [inc["residual_norms"] for s in self.summary["steps"] for inc in s["increments"]]
