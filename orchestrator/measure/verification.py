"""A measurement held against a known true field: is its error what its covariance says?

The fit's floor, its intervals and every verdict of the diagnosis rest on the measurement's error model. Where
the truth is known (a phantom, a case made by another program with its true field), the measured displacements
less what the windows see of the true field (`Measurements.observation`), with the residual rigid motion of the
bones removed as the fit removes it (generalised least squares on the three nuisance columns), are whitened by the
predicted covariance: chi^2/n near 1 says the error model holds. It is reported per band of tissue, because the
errors of an image are not the same everywhere: the fat within 5 mm of the skin (windows on the skin's edge and
across a thin layer), the other fat, and the muscle.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..core.linalg import symmetric_roots
from ..model.forward import MeshInterpolator, field_on_pixels

SKIN_BAND_MM = 5.0
BANDS = ("fat within 5 mm of the skin", "other fat", "muscle")


@dataclass(frozen=True)
class BandError:
    """The error of one band's measurements against the truth."""

    band: str
    count: int                 # windows or points
    rms_error_mm: float        # RMS of the error components
    median_sigma_mm: float     # median predicted standard deviation of a component
    chi2_per_value: float      # e^T C^-1 e / n over the band's values, C the band's block of the covariance

    def line(self) -> str:
        return (f"{self.band:<28s} {self.count:4d}  RMS {self.rms_error_mm:.4f} mm  predicted sigma "
                f"{self.median_sigma_mm:.4f} mm  chi2/n {self.chi2_per_value:.2f}")


def band_masks(measurements, frame) -> dict[str, np.ndarray]:
    """The measured places of each band (`BANDS`), by the tissue of I0 under them and their depth under the skin."""
    tissue = np.array(frame.tissues(measurements.position_mm))
    depth = frame.depth_mm(measurements.position_mm)
    fat = tissue == "fat"
    return {BANDS[0]: fat & (depth < SKIN_BAND_MM), BANDS[1]: fat & (depth >= SKIN_BAND_MM),
            BANDS[2]: tissue == "muscle"}


def errors_against(measurements, mesh_or_observation, true_nodal_or_field) -> np.ndarray:
    """(2N,) measured less what the measurement sees of the truth, interleaved, before the rigid motion is removed.
    The truth is a nodal field on a mesh (`mesh_or_observation` the mesh) or a (2, H, W) field on the pixels of I0
    (`mesh_or_observation` None: DIC windows only)."""
    measured = np.asarray(measurements.displacement_mm, float).ravel()
    if mesh_or_observation is None:
        return measured - measurements.sees(true_nodal_or_field).ravel()
    return measured - measurements.observation(mesh_or_observation) @ np.asarray(true_nodal_or_field, float).ravel()


def without_rigid_motion(measurements, errors: np.ndarray, whiten: np.ndarray) -> np.ndarray:
    """(2N,) the errors less the bones' residual rigid motion, fitted by generalised least squares as the fit removes
    it (module text; `whiten` the inverse square root of the measurements' covariance); unchanged for measurements
    without that nuisance (points)."""
    errors = np.asarray(errors, float)
    if not measurements.rigid_nuisance:
        return errors.copy()
    columns = measurements.rigid_columns(measurements.position_mm.mean(axis=0))
    motion, *_ = np.linalg.lstsq(whiten @ columns, whiten @ errors, rcond=None)
    return errors - columns @ motion


def band_errors(measurements, errors: np.ndarray, frame) -> tuple[list[BandError], float]:
    """Per band and overall (chi^2/n over every value, full covariance) once the bones' residual rigid motion is
    removed by generalised least squares (module text)."""
    covariance = np.asarray(measurements.covariance_mm2, float)
    whiten, _ = symmetric_roots(covariance, "the measurement covariance")
    errors = without_rigid_motion(measurements, errors, whiten)
    whitened = whiten @ errors
    rows = []
    for band, mask in band_masks(measurements, frame).items():
        values = np.repeat(mask, 2)
        if not values.any():
            rows.append(BandError(band, 0, float("nan"), float("nan"), float("nan")))
            continue
        block = covariance[np.ix_(values, values)]
        band_errors_mm = errors[values]
        rows.append(BandError(band, int(mask.sum()), float(np.sqrt(np.mean(band_errors_mm ** 2))),
                              float(np.median(np.sqrt(np.diagonal(block)))),
                              float(band_errors_mm @ np.linalg.solve(block, band_errors_mm) / band_errors_mm.size)))
    return rows, float(whitened @ whitened / whitened.size)


def field_from_truth_file(path: str | Path, shape: tuple[int, int], pixel_size_mm) -> np.ndarray:
    """(2, H, W) true in-plane displacement on the pixels of I0 from another program's truth file: a mesh and its
    nodal field (`field_from_mesh_file`) or the field on I0's pixels itself, u_inplane_mm (H, W, 2), NaN outside
    the leg (a 3D leg imaged through k-space: the material under each pixel centre), which is extended outwards
    from the nearest pixel of the leg (a window on the skin sees the skin's edge, which moves with the skin)."""
    with np.load(path) as truth:
        if "u_inplane_mm" not in truth.files:
            return field_from_mesh_file(path, shape, pixel_size_mm)
        field = np.asarray(truth["u_inplane_mm"], float)
    if field.shape[:2] != tuple(shape):
        raise ValueError(f"{path}: its field is {field.shape[:2]} pixels where I0 is {tuple(shape)}")
    inside = np.all(np.isfinite(field), axis=2)
    rows, cols = ndimage.distance_transform_edt(~inside, return_distances=False, return_indices=True)
    field = field[rows, cols]
    return np.stack([field[..., 0], field[..., 1]])


def field_from_mesh_file(path: str | Path, shape: tuple[int, int], pixel_size_mm) -> np.ndarray:
    """(2, H, W) true displacement on the pixels of I0 from a file holding a mesh and its nodal field: nodes_mm
    (N, 2), cells (E, 3 or 6; CPE6 in CalculiX order), u_mm (N, 2), as the foreign cases' truth/<case>.npz."""
    from ..meshing.mesh import Mesh

    with np.load(path) as truth:
        mesh = Mesh(truth["nodes_mm"], truth["cells"], np.ones(len(truth["cells"]), int))
        nodal = truth["u_mm"]
    return field_on_pixels(MeshInterpolator(mesh).pixel_weights(shape, pixel_size_mm), nodal, shape)
