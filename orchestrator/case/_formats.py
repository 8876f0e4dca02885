"""Image file formats of a case folder: read one 2D slice and its pixel spacing.

PNG and TIFF (8 or 16 bit, grey), NumPy ``.npy``, DICOM (``PixelSpacing`` and
the rescale slope/intercept from the header, via pydicom) and NIfTI (``zooms``
from the header, via nibabel; array axis 0 is taken as rows, axis 1 as
columns, as nibabel stores it, with no reorientation). Every failure is a
`CaseError` naming the file and the fix. A folder holding a DICOM series is read
by `dicom_series`, one slice of it through `read_dicom_file`.

Float images (NIfTI, .npy, float TIFF) may hold NaN where the scanner or a
reslicing left no value, usually outside the field of view. Those pixels are
given the darkest grey level of the slice (background, in an MRI) and their mask
is kept, so that the run can refuse them where they would be read as tissue
(`field_checks.check_missing_pixels`). A slice missing more than half of its
pixels is refused here.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import CaseError
from .acquisition import Acquisition, acquisition_of

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".dcm", ".nii", ".nii.gz")
_GREY_FIX = "save it as a single-channel (greyscale) 8 or 16-bit image"
MAX_MISSING_FRACTION = 0.5


@dataclass(frozen=True)
class SliceFile:
    """One 2D image read from a file, with the pixel spacing its header gives (None if none) and the mask of the
    pixels that had no value (NaN or infinite; None when every pixel has one). A slice of a DICOM series
    (`dicom_series`) has the series folder as its path and the file it was read from as series_file."""

    path: Path
    pixels: np.ndarray
    header_pixel_size_mm: tuple[float, float] | None
    missing: np.ndarray | None = None
    series_file: Path | None = None
    acquisition: Acquisition | None = None   # DICOM: the sequence's parameters (`acquisition`), None for others


def file_suffix(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def read_slice(path: Path) -> SliceFile:
    """Read a 2D slice; raise CaseError on anything unreadable or not 2D."""
    suffix = file_suffix(path)
    readers = {".png": _read_png, ".tif": _read_tiff, ".tiff": _read_tiff, ".npy": _read_npy,
               ".dcm": _read_dicom, ".nii": _read_nifti, ".nii.gz": _read_nifti}
    if suffix not in readers:
        raise CaseError(path, f"the format '{suffix}' is not supported", "use PNG, TIFF, .npy, DICOM (.dcm) or NIfTI (.nii/.nii.gz)")
    _check_not_empty(path)
    return _checked_slice(path, *readers[suffix](path))


def read_dicom_file(path: Path) -> SliceFile:
    """Read a 2D DICOM slice whatever its file name (a scanner's series files often have no suffix)."""
    _check_not_empty(path)
    return _checked_slice(path, *_read_dicom(path))


def _check_not_empty(path: Path) -> None:
    if path.is_file() and path.stat().st_size == 0:
        raise CaseError(path, "is empty (0 bytes)", "copy the slice again from where it was exported (this copy was "
                        "cut short or never written)")


def _checked_slice(path: Path, pixels, spacing, acquisition: Acquisition | None = None) -> SliceFile:
    pixels = _as_2d(path, pixels)
    if not np.issubdtype(pixels.dtype, np.number) or np.issubdtype(pixels.dtype, np.complexfloating):
        raise CaseError(path, f"holds {pixels.dtype} values, not real numbers", _GREY_FIX)
    if min(pixels.shape) < 16:
        raise CaseError(path, f"is only {pixels.shape[0]}x{pixels.shape[1]} pixels", "give the full slice")
    missing = ~np.isfinite(pixels)
    if not missing.any():
        return SliceFile(path, pixels, spacing, acquisition=acquisition)
    if missing.mean() > MAX_MISSING_FRACTION:
        raise CaseError(path, f"has no value (NaN or infinite) in {100 * missing.mean():.0f} % of its pixels",
                        "export the slice from the scanner's series itself, not a masked or resliced copy")
    filled = pixels.astype(float)
    filled[missing] = filled[~missing].min()
    return SliceFile(path, filled, spacing, missing, acquisition=acquisition)


def _as_2d(path: Path, pixels: np.ndarray) -> np.ndarray:
    pixels = np.asarray(pixels)
    if pixels.ndim == 3 and pixels.shape[-1] in (3, 4) and file_suffix(path) in (".png", ".tif", ".tiff"):
        rgb = pixels[..., :3]
        if pixels.shape[-1] == 4 and np.any(pixels[..., 3] != pixels[..., 3].max()):
            raise CaseError(path, "has a transparent alpha channel", _GREY_FIX)
        if np.any(rgb != rgb[..., :1]):
            raise CaseError(path, "is a colour image", _GREY_FIX)
        pixels = rgb[..., 0]
    squeezed = np.squeeze(pixels) if pixels.ndim > 2 else pixels
    if squeezed.ndim != 2:
        raise CaseError(path, f"holds an array of shape {pixels.shape}, not one 2D slice",
                        "extract the single slice at the largest calf perimeter and save it alone")
    return squeezed


# how each format's files begin: a file that does not is another format (or none), one that does but fails is damaged
_SIGNATURES = {"PNG": ((0, b"\x89PNG\r\n\x1a\n"),), "TIFF": ((0, b"II*\x00"), (0, b"MM\x00*"), (0, b"II+\x00"),
                                                              (0, b"MM\x00+")),
               "NumPy .npy": ((0, b"\x93NUMPY"),), "DICOM": ((128, b"DICM"),)}
_LIBRARY_ADVICE = re.compile(r"[^.]*\bforce\s*=\s*True\b[^.]*\.?|[^.]*\bbackend\b[^.]*\.?", re.I)


def _failed(path: Path, kind: str, exc: Exception) -> CaseError:
    """The CaseError of a file its reader could not read: not that format at all, or a damaged file of it (then
    with the reader's reason, its advice to the programmer left out)."""
    signatures = _SIGNATURES.get(kind, ())
    try:
        with path.open("rb") as stream:
            head = stream.read(256)
    except OSError as error:
        return CaseError(path, f"cannot be opened ({error.strerror or error})", "check the file's permissions")
    if signatures and not any(head[offset:offset + len(magic)] == magic for offset, magic in signatures):
        begins = "a DICOM file's 'DICM' after its 128-byte preamble" if kind == "DICOM" else f"a {kind} file's signature"
        return CaseError(path, f"cannot be read as {kind}: it is not a {kind} file (it does not begin with {begins})",
                         f"give the file the suffix of the format it is in, or export the slice again as {kind}")
    reason = _LIBRARY_ADVICE.sub("", str(exc)).strip().rstrip(".").splitlines()
    detail = f" ({reason[0].strip()})" if reason and reason[0].strip() else ""
    return CaseError(path, f"cannot be read as {kind}: the file is damaged{detail}",
                     f"copy or export the slice again as {kind}")


def _read_png(path: Path):
    from skimage import io

    try:
        pixels = io.imread(path)
    except Exception as exc:  # any decoder failure is a bad file
        raise _failed(path, "PNG", exc) from exc
    return pixels, None


def _read_tiff(path: Path):
    import tifffile

    try:
        pixels = tifffile.imread(path)
    except Exception as exc:
        raise _failed(path, "TIFF", exc) from exc
    return pixels, None


def _read_npy(path: Path):
    try:
        pixels = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise _failed(path, "NumPy .npy", exc) from exc
    return pixels, None


def _read_dicom(path: Path):
    import pydicom

    try:
        dataset = pydicom.dcmread(path)
        pixels = dataset.pixel_array.astype(float)
    except Exception as exc:
        raise _failed(path, "DICOM", exc) from exc
    pixels = pixels * float(getattr(dataset, "RescaleSlope", 1.0)) + float(getattr(dataset, "RescaleIntercept", 0.0))
    spacing = getattr(dataset, "PixelSpacing", None)
    header = (float(spacing[0]), float(spacing[1])) if spacing is not None and len(spacing) == 2 else None
    return pixels, header, acquisition_of(dataset)


def _read_nifti(path: Path):
    import nibabel

    try:
        volume = nibabel.load(path)
        pixels = np.asarray(volume.dataobj, dtype=float)
        zooms = volume.header.get_zooms()
    except Exception as exc:
        raise _failed(path, "NIfTI", exc) from exc
    header = (float(zooms[0]), float(zooms[1])) if len(zooms) >= 2 else None
    return pixels, header


def write_png16(path: Path, pixels: np.ndarray) -> None:
    """Write a uint16 or uint8 greyscale PNG, bit-exact."""
    from skimage import io

    if pixels.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"PNG pixels must be uint8 or uint16, got {pixels.dtype}")
    io.imsave(path, pixels, check_contrast=False)
