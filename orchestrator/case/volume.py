"""3D volumes of the calf: a DICOM series of many slices or a 3D NIfTI, and the rigid motion between two sessions.

A `Volume` holds the voxels as (rows, columns, slices) and the affine that maps a continuous index
(row, column, slice) to the patient frame in mm. Its slices are ordered by increasing position along the slice
normal; that position is the slice's *height* in a study (`[study] heights_mm`), the same number as
`[images] slice_position_mm` of a single-slice case.

Each slice of the unloaded volume is a 2D image whose frame is the one of every case (`imaging.frame`):
x = (column + 0.5) * column spacing, y = (row + 0.5) * row spacing, in mm. `slice_points_mm` gives the patient
points of those pixels; `index_of_points` the continuous voxel index of patient points.

`read_volume` reads the volume of one session: a folder holding a DICOM series (the headers checked and ordered by
`dicom_series.read_series`) or a 3D NIfTI file, as `write_nifti_volume` writes it.

`RigidMotion3D` maps a point of the unloaded session (patient mm) to the point of the loaded session where the
same bone point is: p -> R (p - centre) + centre + translation, R given by a rotation vector in degrees (axis
times angle). It is the 3D counterpart of `imaging.frame.RigidMotion`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.errors import CaseError
from .acquisition import Acquisition


@dataclass(frozen=True)
class Volume:
    """Voxels (rows, columns, slices) and the affine (row, column, slice, 1) -> patient mm; slices in increasing
    position along the normal."""

    voxels: np.ndarray
    affine: np.ndarray
    source: Path = field(default=Path("."))
    acquisition: Acquisition | None = None   # a DICOM series' sequence parameters (`acquisition`), its first slice's

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


# ----------------------------------------------------------------- reading a volume

MAX_GAP_DEVIATION = 0.10        # a gap more than 10 % from the median: a slice missing, or two stacks in one folder
MAX_IN_PLANE_DRIFT_PIXELS = 0.5  # a slice's corner off the line of the others by more than this: not one stack
_MEDICAL_EXTRA = "install the medical extra: pip install 'calfit[medical]'"
_VOLUME_FIX = "give a folder holding one DICOM series (one file per slice) or a 3D NIfTI file (.nii or .nii.gz)"


def read_volume(path: Path) -> Volume:
    """Read the volume of one session: a folder holding a DICOM series, or a .nii/.nii.gz file of a 3D array.

    DICOM: the headers are checked and the slices ordered by `dicom_series.read_series` (by increasing position
    along the normal n = row x column direction cosines); each slice's pixels are rescaled by RescaleSlope and
    RescaleIntercept. The affine is built from ImageOrientationPatient (its first triplet, the row direction
    cosines, is the direction of increasing column; its second, the column direction cosines, that of increasing
    row), PixelSpacing (row spacing, column spacing), the ImagePositionPatient of the first slice and the slice
    step, the mean step between consecutive positions (last minus first over the count of gaps). Refused, each by a
    `CaseError` naming the folder: slices without positions, a single slice, gaps more than 10 % from their median,
    slices whose positions do not lie on one line (two stacks side by side).

    NIfTI: axis 0 = rows, axis 1 = columns, axis 2 = slices, as `write_nifti_volume` writes it; the file's affine is
    used as it is (nibabel's: the sform, else the qform), whichever way its slice axis points (`Volume.normal`
    points towards increasing slice index). A 2D or 4D array, or a single slice, is refused.

    NaN voxels (a reslicing's outside) are kept as NaN. pydicom and nibabel are the optional `medical` extra.
    """
    from ._formats import file_suffix

    path = Path(path)
    if path.is_dir():
        return _read_dicom_volume(path)
    if not path.exists():
        raise CaseError(path, "does not exist", _VOLUME_FIX)
    if file_suffix(path) in (".nii", ".nii.gz"):
        return _read_nifti_volume(path)
    raise CaseError(path, f"is a '{file_suffix(path) or path.name}' file, not a volume", _VOLUME_FIX)


def _import_medical(module: str, path: Path):
    """pydicom or nibabel, or a CaseError saying how to install them."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise CaseError(path, f"cannot be read without {module}, which is not installed", _MEDICAL_EXTRA) from None


def _read_dicom_volume(folder: Path) -> Volume:
    from ._formats import _read_dicom
    from .dicom_series import _mm, read_series

    _import_medical("pydicom", folder)
    series = read_series(folder)
    count = len(series.slices)
    if series.positions_mm is None:
        raise CaseError(folder, f"is a series of {series.describe()}, so its slices cannot be placed in space",
                        "export the series with its ImagePositionPatient and ImageOrientationPatient (every scanner "
                        "writes them; an anonymiser may have removed them)")
    if count < 2:
        raise CaseError(folder, f"is a series of {series.describe()}, not a volume",
                        "export every slice of the acquisition into the folder (a volume study needs several heights), "
                        "or make it a single-slice case")
    positions, spacing = series.positions_mm, series.spacing_mm
    gaps = np.diff(positions)
    worst = int(np.argmax(np.abs(gaps - spacing)))
    if abs(gaps[worst] - spacing) > MAX_GAP_DEVIATION * spacing:
        names = series.slices[worst].path.name, series.slices[worst + 1].path.name
        raise CaseError(folder, f"has uneven slice gaps, {gaps.min():.2f} to {gaps.max():.2f} mm along the normal: "
                        f"{gaps[worst]:.2f} mm between {names[0]} at {_mm(positions[worst])} mm and {names[1]} at "
                        f"{_mm(positions[worst + 1])} mm, against a median gap of {spacing:.2f} mm",
                        "export the whole acquisition, one stack of evenly spaced slices (a slice is missing, "
                        "or two stacks share the folder)")
    first = series.first
    if first.pixel_spacing_mm is None:
        raise CaseError(folder, "is a series without PixelSpacing, so its pixels have no size",
                        "export the series from the scanner again, with its PixelSpacing")
    row_spacing, column_spacing = first.pixel_spacing_mm
    corners = np.array([s.position_patient_mm for s in series.slices])
    step = (corners[-1] - corners[0]) / (count - 1)
    drift = corners - (corners[0] + np.arange(count)[:, None] * step)
    drift -= np.outer(drift @ first.normal, first.normal)        # along the normal, the gaps were checked above
    drift_mm = np.linalg.norm(drift, axis=1)
    if drift_mm.max() > MAX_IN_PLANE_DRIFT_PIXELS * min(row_spacing, column_spacing):
        offender = series.slices[int(np.argmax(drift_mm))].path.name
        raise CaseError(folder, f"has slices shifted in their plane ({offender} lies {drift_mm.max():.2f} mm off the "
                        "line through the others' ImagePositionPatient)",
                        "export one stack of slices, all with the same field of view")

    voxels = np.empty((first.rows, first.columns, count))
    acquisition = None
    for k, header in enumerate(series.slices):
        pixels, _, read = _read_dicom(header.path)      # rescale slope and intercept applied
        acquisition = acquisition if acquisition is not None else read
        pixels = np.squeeze(np.asarray(pixels, float))
        if pixels.shape != (first.rows, first.columns):
            raise CaseError(header.path, f"holds pixels of shape {pixels.shape} where its header says "
                            f"{first.rows}x{first.columns}",
                            "export the series from the scanner again, one grey slice per file")
        voxels[:, :, k] = pixels
    affine = np.eye(4)
    affine[:3, 0] = first.directions[1] * row_spacing       # one row down: along the column direction cosines
    affine[:3, 1] = first.directions[0] * column_spacing    # one column right: along the row direction cosines
    affine[:3, 2] = step
    affine[:3, 3] = corners[0]
    return Volume(voxels, affine, folder, acquisition)


def _read_nifti_volume(path: Path) -> Volume:
    from ._formats import _failed

    nibabel = _import_medical("nibabel", path)
    try:
        image = nibabel.load(path)
        voxels = np.asarray(image.dataobj, dtype=float)     # scl_slope and scl_inter applied
        affine = np.asarray(image.affine, dtype=float)
    except Exception as exc:   # any decoder failure is a bad file
        raise _failed(path, "NIfTI", exc) from exc
    if voxels.ndim != 3:
        raise CaseError(path, f"holds an array of shape {voxels.shape}, not a 3D volume (rows, columns, slices)",
                        "save the volume of one session as a 3D NIfTI (not a single slice, nor a 4D series)")
    if voxels.shape[2] < 2:
        raise CaseError(path, f"holds a single slice ({voxels.shape[0]}x{voxels.shape[1]}x1), not a volume",
                        "save every slice of the acquisition in the file (a volume study needs several heights), "
                        "or make it a single-slice case")
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise CaseError(path, "has an affine that does not place its voxels in space (singular or not finite)",
                        "save the file with the affine of its acquisition (the sform or qform of the converter)")
    return Volume(voxels, affine, path)
