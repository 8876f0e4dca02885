"""3D volumes of the calf: a DICOM series of many slices or a 3D NIfTI, and the rigid motion between two sessions.

A `Volume` holds the voxels as (rows, columns, slices) and the affine that maps a continuous index
(row, column, slice) to the patient frame in mm. Its slices are ordered by increasing position along the slice
normal; that position is the slice's *height* in a study (`[study] heights_mm`), the same number as
`[images] slice_position_mm` of a single-slice case.

Each slice of the unloaded volume is a 2D image whose frame is the one of every case (`imaging.frame`):
x = (column + 0.5) * column spacing, y = (row + 0.5) * row spacing, in mm. `slice_points_mm` gives the patient
points of those pixels; `index_of_points` the continuous voxel index of patient points.

`RigidMotion3D` maps a point of the unloaded session (patient mm) to the point of the loaded session where the
same bone point is: p -> R (p - centre) + centre + translation, R given by a rotation vector in degrees (axis
times angle). It is the 3D counterpart of `imaging.frame.RigidMotion`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Volume:
    """Voxels (rows, columns, slices) and the affine (row, column, slice, 1) -> patient mm; slices in increasing
    position along the normal."""

    voxels: np.ndarray
    affine: np.ndarray
    source: Path = field(default=Path("."))

    def __post_init__(self):
        if np.ndim(self.voxels) != 3:
            raise ValueError(f"a volume's voxels are (rows, columns, slices), not an array of shape {np.shape(self.voxels)}")
        if np.shape(self.affine) != (4, 4):
            raise ValueError("a volume's affine is a 4x4 matrix")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.voxels.shape)

    @property
    def pixel_size_mm(self) -> tuple[float, float]:
        """(row spacing, column spacing) of a slice, mm: the `pixel_size_mm` of its 2D case."""
        return float(np.linalg.norm(self.affine[:3, 0])), float(np.linalg.norm(self.affine[:3, 1]))

    @property
    def normal(self) -> np.ndarray:
        """Unit normal of the slices, pointing towards increasing slice index."""
        row_direction, column_direction = self.affine[:3, 0], self.affine[:3, 1]
        normal = np.cross(row_direction, column_direction)
        normal /= np.linalg.norm(normal)
        return normal if np.dot(normal, self.affine[:3, 2]) >= 0 else -normal

    @property
    def slice_positions_mm(self) -> np.ndarray:
        """Position of each slice along the normal (its height), mm, increasing."""
        corners = self.affine[:3, 3][None, :] + np.arange(self.shape[2])[:, None] * self.affine[:3, 2][None, :]
        return corners @ self.normal

    @property
    def slice_spacing_mm(self) -> float:
        return float(abs(np.dot(self.affine[:3, 2], self.normal)))

    def slice_image(self, k: int) -> np.ndarray:
        return np.asarray(self.voxels[:, :, k], dtype=float)

    def slice_points_mm(self, k: int) -> np.ndarray:
        """Patient points (3, rows, columns) of the pixel centres of slice k."""
        rows, columns = np.indices(self.shape[:2], dtype=float)
        index = np.stack([rows, columns, np.full_like(rows, float(k)), np.ones_like(rows)])
        return np.tensordot(self.affine[:3], index, axes=1)

    def index_of_points(self, points_mm: np.ndarray) -> np.ndarray:
        """Continuous (row, column, slice) index (3, ...) of patient points (3, ...)."""
        inverse = np.linalg.inv(self.affine)
        points = np.asarray(points_mm, float)
        return np.tensordot(inverse[:3, :3], points, axes=1) + inverse[:3, 3].reshape((3,) + (1,) * (points.ndim - 1))


@dataclass(frozen=True)
class RigidMotion3D:
    """p -> R (p - centre_mm) + centre_mm + translation_mm (patient mm); R = exp(rotation_vector_deg in radians)."""

    rotation_vector_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    translation_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def rotation(self) -> np.ndarray:
        return Rotation.from_rotvec(np.deg2rad(np.asarray(self.rotation_vector_deg, float))).as_matrix()

    @property
    def angle_deg(self) -> float:
        return float(np.linalg.norm(self.rotation_vector_deg))

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        """Map patient points (3, ...) of the unloaded session to the loaded session."""
        points = np.asarray(points_mm, float)
        shape = (3,) + (1,) * (points.ndim - 1)
        centre = np.asarray(self.centre_mm, float).reshape(shape)
        return (np.tensordot(self.rotation, points - centre, axes=1) + centre
                + np.asarray(self.translation_mm, float).reshape(shape))

    def inverse(self) -> "RigidMotion3D":
        rotation = self.rotation.T
        translation = -rotation @ np.asarray(self.translation_mm, float)
        vector = np.rad2deg(Rotation.from_matrix(rotation).as_rotvec())
        return RigidMotion3D(tuple(map(float, vector)), tuple(map(float, translation)), tuple(map(float, self.centre_mm)))

    def as_dict(self) -> dict:
        return {"rotation_vector_deg": list(map(float, self.rotation_vector_deg)),
                "translation_mm": list(map(float, self.translation_mm)), "centre_mm": list(map(float, self.centre_mm))}

    @classmethod
    def from_dict(cls, values: dict) -> "RigidMotion3D":
        return cls(tuple(values["rotation_vector_deg"]), tuple(values["translation_mm"]), tuple(values["centre_mm"]))


def volume_affine(pixel_size_mm: tuple[float, float], slice_spacing_mm: float,
                  origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The affine of an axial volume whose slice frame is the case frame: a column step along +x, a row step along
    +y, a slice step along +z (the height); origin_mm is the patient point of voxel (0, 0, 0)'s centre."""
    dy, dx = pixel_size_mm
    affine = np.eye(4)
    affine[:3, 0] = (0.0, dy, 0.0)
    affine[:3, 1] = (dx, 0.0, 0.0)
    affine[:3, 2] = (0.0, 0.0, slice_spacing_mm)
    affine[:3, 3] = origin_mm
    return affine


def write_nifti_volume(path: str | Path, voxels: np.ndarray, affine: np.ndarray) -> Path:
    """Write voxels (rows, columns, slices) as a 3D NIfTI with that affine (axis 0 = rows, as `read_volume`
    reads it), float32. The file is written whole under a temporary name and renamed."""
    import nibabel

    path = Path(path)
    staging = path.with_name(f".{path.name}.partial{''.join(path.suffixes)}")
    nibabel.save(nibabel.Nifti1Image(np.asarray(voxels, np.float32), np.asarray(affine, float)), staging)
    staging.replace(path)
    return path
