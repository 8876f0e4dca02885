"""What an FE evaluation is scored on: the two misfits of the papers and the landmark pressures.

- `ContourMismatchObjective`: the contour mismatch of Avril et al. (sec. 2.2.5),
  M(theta) = sum_k d_k^2, d_k the distance from each fat or muscle contour pixel of the
  warped image I(x) = I1(x + u(x; theta)) (sec. 2.1.2) to the nearest contour pixel of the
  same tissue in I0 (mm^2; `orchestrator.imaging.mismatch`). u on the pixels is the FE
  interpolation of the nodal field (`forward.MeshInterpolator`).
- `DisplacementResidualObjective`: the displacement residual of Bouten and Drapier (eq. 2),
  F(theta) = 1/(2N) sum_i |u_e(P_i) - u_s(P_i; theta)|^2 over N measured points P_i (DIC
  window centres or points.csv), with the residual vector r = (u_s - u_e) / sigma for
  Levenberg-Marquardt (sigma = 1 mm when the points carry none, so that then F = r.r / (2N)).
- `LandmarkPressure`: the hydrostatic pressure -tr(sigma)/3 (kPa) at the five landmarks of
  Avril et al. (sec. 3.2, Table 3), interpolated from the engine's nodal-averaged field.

Each objective is built once in the main process and shipped once to every worker; `outputs`
turns an engine result into a small JSON-able dict stored in the evaluation log, and
`fingerprint` (part of the cache key) changes whenever the data it compares with change.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .decks import KPA_PER_MPA, text_sha256
from .forward import MeshInterpolator, field_on_pixels
from .imaging.mismatch import ContourMismatch, MismatchResult


def _array_sha(*arrays) -> str:
    return text_sha256("".join(text_sha256(np.ascontiguousarray(a).tobytes().hex()) for a in arrays))[:16]


class ContourMismatchObjective:
    """M(theta) of Avril et al. sec. 2.2.5 for one mesh and one pair of label maps."""

    name = "contour_mismatch"
    needs_vtu = False

    def __init__(self, mesh, labels_unloaded: np.ndarray, labels_loaded: np.ndarray, pixel_size_mm):
        self.shape = tuple(np.shape(labels_unloaded))
        self.pixel_size_mm = tuple(float(v) for v in pixel_size_mm)
        self.mismatch = ContourMismatch(labels_unloaded, labels_loaded, self.pixel_size_mm)
        self.weights = MeshInterpolator(mesh).pixel_weights(self.shape, self.pixel_size_mm)
        self.fingerprint = f"M:{_array_sha(labels_unloaded, labels_loaded)}"

    def displacement(self, nodal_u: np.ndarray) -> np.ndarray:
        return field_on_pixels(self.weights, nodal_u, self.shape)

    def evaluate(self, nodal_u: np.ndarray) -> MismatchResult:
        return self.mismatch(self.displacement(nodal_u))

    def outputs(self, nodal_u: np.ndarray, outdir: Path) -> dict:
        result = self.evaluate(nodal_u)
        return {"cost": result.value_mm2, "per_tissue_mm2": result.per_tissue_mm2}


class DisplacementResidualObjective:
    """F(theta) of Bouten and Drapier eq. 2 at measured points, and its residual vector."""

    name = "displacement_residual"
    needs_vtu = False

    def __init__(self, mesh, positions_mm: np.ndarray, measured_mm: np.ndarray, sigma_mm: np.ndarray | None = None):
        self.positions_mm = np.asarray(positions_mm, float).reshape(-1, 2)
        self.measured_mm = np.asarray(measured_mm, float).reshape(-1, 2)
        if len(self.positions_mm) == 0 or self.positions_mm.shape != self.measured_mm.shape:
            raise ValueError("the displacement residual needs as many measured displacements as points, at least one")
        self.sigma_mm = np.ones(len(self.positions_mm)) if sigma_mm is None else np.asarray(sigma_mm, float).ravel()
        self.weights = MeshInterpolator(mesh).weights(self.positions_mm)
        self.fingerprint = f"F:{_array_sha(self.positions_mm, self.measured_mm, self.sigma_mm)}"

    def residuals(self, nodal_u: np.ndarray) -> np.ndarray:
        simulated = self.weights @ np.asarray(nodal_u, float)
        return ((simulated - self.measured_mm) / self.sigma_mm[:, None]).ravel()

    def cost(self, nodal_u: np.ndarray) -> float:
        simulated = self.weights @ np.asarray(nodal_u, float)
        return float(np.sum((simulated - self.measured_mm) ** 2) / (2 * len(self.measured_mm)))

    def outputs(self, nodal_u: np.ndarray, outdir: Path) -> dict:
        """Cost and residuals; with the engine's sensitivities (a deck with *SENSITIVITY), also
        dr/d(engine parameter) = W du/dtheta / sigma per engine parameter name."""
        from .results import EngineResults

        out = {"cost": self.cost(nodal_u), "residuals": self.residuals(nodal_u).tolist()}
        sensitivities = EngineResults(Path(outdir)).sensitivities()
        if sensitivities:
            out["sensitivity"] = {name: ((self.weights @ du) / self.sigma_mm[:, None]).ravel().tolist()
                                  for name, du in sensitivities.items()}
        return out


class LandmarkPressure:
    """Hydrostatic pressure (kPa) at named positions, from the VTU's nodal `pressure` (-tr sigma / 3)."""

    name = "landmark_pressure"
    needs_vtu = True

    def __init__(self, mesh, landmarks_mm: dict[str, tuple[float, float]]):
        if not landmarks_mm:
            raise ValueError("no landmarks given: add a [landmarks] table to case.toml")
        self.names = list(landmarks_mm)
        self.positions_mm = np.array([landmarks_mm[name] for name in self.names], float)
        self.weights = MeshInterpolator(mesh).weights(self.positions_mm)
        self.fingerprint = f"P:{_array_sha(self.positions_mm)}:{','.join(self.names)}"

    def outputs(self, nodal_u: np.ndarray, outdir: Path) -> dict:
        from .results import EngineResults

        pressure = EngineResults(Path(outdir)).point_field("pressure") * KPA_PER_MPA
        values = self.weights @ pressure
        return {"cost": float(np.max(values)), "pressure_kPa": dict(zip(self.names, map(float, values)))}


class Combined:
    """Several objectives in one evaluation; the cost is that of the first."""

    def __init__(self, *parts):
        self.parts = parts
        self.name = "+".join(p.name for p in parts)
        self.needs_vtu = any(p.needs_vtu for p in parts)
        self.fingerprint = "+".join(p.fingerprint for p in parts)

    def outputs(self, nodal_u: np.ndarray, outdir: Path) -> dict:
        merged: dict = {}
        for part in reversed(self.parts):
            merged.update(part.outputs(nodal_u, outdir))
        return merged
