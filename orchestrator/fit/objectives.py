"""What an FE evaluation is scored on: the two misfits of the papers and the landmark pressures.

- `ContourMismatchObjective`: the contour mismatch of Avril et al. (sec. 2.2.5),
  M(theta) = sum_k d_k^2, d_k the distance from each fat or muscle contour pixel of the
  warped image I(x) = I1(x + u(x; theta)) (sec. 2.1.2) to the nearest contour pixel of the
  same tissue in I0 (mm^2; `orchestrator.imaging.mismatch`). u on the pixels is the FE
  interpolation of the nodal field (`forward.MeshInterpolator`).
- `DisplacementResidualObjective`: the displacement residual of Bouten and Drapier (eq. 2), weighted
  by the measurements' covariance C (`measure.Measurements`: DIC windows or points.csv):
  r = P C^-1/2 (O u_s(theta) - u_e), with O what the measurement sees of the model (the FE
  interpolation at the points, or the DIC windows' observation operator), C^-1/2 the symmetric
  inverse square root (so that r_i stays attached to window i) and P the projection that removes
  the residual rigid motion of the bones between the two images when the measurement has it as a
  nuisance (DIC). The misfit F = s^2 r.r / n (mm^2, n = 2N values, s^2 the mean variance of one
  component) is eq. 2's F for points of equal sigma; its expectation for a correct model is the
  noise floor s^2 (n - p - k) / n (p fitted parameters, k nuisance ones).
- `LandmarkPressure`: the hydrostatic pressure -tr(sigma)/3 (kPa) at the five landmarks of
  Avril et al. (sec. 3.2, Table 3), interpolated from the engine's nodal-averaged field.

Each objective is built once in the main process and shipped once to every worker; `outputs`
turns an engine result into a small JSON-able dict stored in the evaluation log, and
`fingerprint` (part of the cache key) changes whenever the data it compares with change.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.linalg import symmetric_roots
from ..core.units import KPA_PER_MPA
from ..engine.decks import text_sha256
from ..imaging.mismatch import ContourMismatch, MismatchResult
from ..model.forward import MeshInterpolator, field_on_pixels


def leg_rows(nodal: np.ndarray, n_nodes: int) -> np.ndarray:
    """The rows of the mesh an objective was built on: its nodes come first in every deck (an explicit garment
    band's follow them), so a nodal array of the engine is cut to them."""
    return np.asarray(nodal, float)[:n_nodes]


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
        return field_on_pixels(self.weights, leg_rows(nodal_u, self.weights.shape[1]), self.shape)

    def evaluate(self, nodal_u: np.ndarray) -> MismatchResult:
        return self.mismatch(self.displacement(nodal_u))

    def outputs(self, nodal_u: np.ndarray, outdir: Path) -> dict:
        result = self.evaluate(nodal_u)
        return {"cost": result.value_mm2, "per_tissue_mm2": result.per_tissue_mm2}


class DisplacementResidualObjective:
    """F of Bouten and Drapier eq. 2, weighted by the measurements' covariance (module text), and its residual vector."""

    name = "displacement_residual"
    needs_vtu = False

    def __init__(self, mesh, measurements):
        self.positions_mm = np.asarray(measurements.position_mm, float)
        self.measured = np.asarray(measurements.displacement_mm, float).ravel()
        if len(self.positions_mm) == 0:
            raise ValueError("the displacement residual needs at least one measured displacement")
        self.source = measurements.source
        self.observation = measurements.observation(mesh)
        covariance = np.asarray(measurements.covariance_mm2, float)
        if np.count_nonzero(covariance - np.diag(np.diagonal(covariance))) == 0:
            sigma = np.sqrt(np.diagonal(covariance))
            self._whiten, self._colour = np.diag(1.0 / sigma), np.diag(sigma)
        else:
            self._whiten, self._colour = symmetric_roots(covariance, "the measurement covariance")
        self.nuisance_dof = 0
        self._nuisance = np.zeros((len(self.measured), 0))
        self.rigid_columns = np.zeros((len(self.measured), 0))   # unwhitened, for a joint fit of garment levels
        if measurements.rigid_nuisance:
            self.rigid_columns = measurements.rigid_columns(self.positions_mm.mean(axis=0))
            basis, _ = np.linalg.qr(self._whiten @ self.rigid_columns)
            self._nuisance, self.nuisance_dof = basis, basis.shape[1]
        self.reference_variance_mm2 = measurements.reference_variance_mm2
        # the model's geometry part of the covariance: "none", "columns" (its columns G and weights w are kept with
        # the measurement's own part, from which `levels.JointDisplacementObjective` forms the blocks between
        # garment levels) or "covariance" (added without them)
        self.geometry, self.geometry_columns, self.geometry_weights = "none", None, None
        self.measurement_covariance = None
        if measurements.measurement_covariance_mm2 is not None:
            self.geometry = "covariance"
        if measurements.model_columns_mm is not None:
            self.geometry = "columns"
            self.geometry_columns = np.asarray(measurements.model_columns_mm, float)
            self.geometry_weights = np.asarray(measurements.model_weights, float)
            self.measurement_covariance = np.asarray(measurements.measurement_covariance_mm2, float)
        self.fingerprint = (f"F:{measurements.source}:{_array_sha(self.positions_mm, self.measured, covariance)}:"
                            f"{_array_sha(self.observation.data, self.observation.indices)}")

    @classmethod
    def at_points(cls, mesh, positions_mm, measured_mm, sigma_mm=None) -> "DisplacementResidualObjective":
        """The residual at points (points.csv rows; sigma 1 mm when not given, so that F = r.r / (2N))."""
        from ..case.folder import DisplacementPoints
        from ..measure.measurements import points_measurements

        points = DisplacementPoints(np.asarray(positions_mm, float).reshape(-1, 2),
                                    np.asarray(measured_mm, float).reshape(-1, 2), sigma_mm)
        return cls(mesh, points_measurements(points))

    @property
    def n_residuals(self) -> int:
        return len(self.measured)

    def _project(self, whitened: np.ndarray) -> np.ndarray:
        return whitened - self._nuisance @ (self._nuisance.T @ whitened)

    def difference(self, nodal_u: np.ndarray) -> np.ndarray:
        """O u_s - u_e (mm, interleaved): what the model predicts of the measurements less what was measured."""
        simulated = self.observation @ leg_rows(nodal_u, self.observation.shape[1] // 2).ravel()
        return simulated - self.measured

    def weigh(self, values_mm: np.ndarray) -> np.ndarray:
        """P C^-1/2 of a vector of these measurements' values (mm): a residual vector."""
        return self._project(self._whiten @ values_mm)

    def residuals(self, nodal_u: np.ndarray) -> np.ndarray:
        return self.weigh(self.difference(nodal_u))

    def cost_of(self, residuals: np.ndarray) -> float:
        """F (mm^2) of a residual vector."""
        residuals = np.asarray(residuals, float)
        return float(self.reference_variance_mm2 * (residuals @ residuals) / len(residuals))

    def noise_floor(self, n_parameters: int) -> float:
        """Expected F of a correct model with n_parameters fitted to these measurements."""
        n = len(self.measured)
        return float(self.reference_variance_mm2 * (n - n_parameters - self.nuisance_dof) / n)

    def residual_mm(self, residuals: np.ndarray) -> np.ndarray:
        """(N, 2) u_model - u_measured in mm (the fitted residual rigid motion removed) of a residual vector."""
        return (self._colour @ np.asarray(residuals, float)).reshape(-1, 2)

    def outputs(self, nodal_u: np.ndarray, outdir: Path) -> dict:
        """Cost and residuals; with the engine's sensitivities (a deck with *SENSITIVITY), also
        dr/d(engine parameter) = P C^-1/2 O du/dtheta per engine parameter name."""
        r = self.residuals(nodal_u)
        out = {"cost": self.cost_of(r), "residuals": r.tolist()}
        observed = self.observed_sensitivities(outdir)
        if observed:
            out["sensitivity"] = {name: self.weigh(values).tolist() for name, values in observed.items()}
        return out

    def observed_sensitivities(self, outdir: Path) -> dict[str, np.ndarray]:
        """O du/dtheta (mm per unit, interleaved) per engine parameter name; empty when the deck asked for none."""
        from ..engine.results import EngineResults

        sensitivities = EngineResults(Path(outdir)).sensitivities()
        n_nodes = self.observation.shape[1] // 2
        return {name: self.observation @ leg_rows(du, n_nodes).ravel() for name, du in sensitivities.items()}


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
        from ..engine.results import EngineResults

        pressure = leg_rows(EngineResults(Path(outdir)).point_field("pressure"), self.weights.shape[1]) * KPA_PER_MPA
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
