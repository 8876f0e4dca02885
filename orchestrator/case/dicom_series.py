"""DICOM series in a case folder: ``unloaded/`` and ``loaded/`` as a scanner exports them.

What is accepted. In a case folder, ``unloaded`` and ``loaded`` may each be a folder instead of a single image
file, holding one DICOM series: one file per slice, named as the scanner names them (``IM_0001``,
``1.3.12.2...``, ``slice07.dcm``). A file is recognised by its content, the ``DICM`` prefix of a DICOM Part 10
file, not by its name. Files that are not DICOM (a ``README.txt``, ``.DS_Store``) and DICOM files holding no
image (a ``DICOMDIR``, a structured report) are skipped without a word; a folder left with no image is refused.
Sub-folders are not searched. Each file holds one 2D slice (an enhanced multi-frame file is refused), read as
the single-file reader of `_formats` reads a ``.dcm``: rescale slope and intercept applied, pixel spacing from
``PixelSpacing`` (row, column mm), so that case.toml's pixel_size_mm is optional and, when given, is checked
against the header as for a single file.

How the slices are ordered. By their position along the slice normal: ``ImagePositionPatient`` projected on
n = row x column direction cosines of ``ImageOrientationPatient``, in mm of the scanner's patient frame (for an
axial series of a patient lying head first, the LPS z, increasing towards the head; ``SliceLocation``, which the
console often shows, is not used: it is optional and its sign is the vendor's). The order of the files and their
``InstanceNumber`` do not matter, as a feet-first acquisition numbers its slices against the position.
Only when no slice carries a position (no ``ImagePositionPatient`` or ``ImageOrientationPatient`` in any file)
are the slices ordered by ``InstanceNumber``. That fallback is never silent in effect: a series of several
slices must then be chosen by ``slice_index``, and the error that asks for it says the order is the
InstanceNumber's; ``slice_position_mm`` is refused, and the position check between the two series is skipped,
as it cannot be made.

How the slice is chosen. The optional [images] table of case.toml, one key, for both series::

    slice_index = N         0-based, in the order of increasing position along the normal
    slice_position_mm = z   position along the normal (mm): the nearest slice, refused when farther than
                            half the slice spacing; the error names the positions on either side of z

The slice spacing is the median gap between the positions; for a series of one slice, its
``SpacingBetweenSlices``, else its ``SliceThickness`` (slice_position_mm is refused on a single slice that gives
neither). A series of several slices without a key is refused with its number of slices and range of positions.
A series of one slice needs no key and gives its slice whatever the key (slice_index counts in the series of
several slices; slice_position_mm is still checked against the single slice's position). When neither image
is a series, [images] is refused, as it would be ignored.

What is refused, each by one `CaseError` sentence naming the folder(s) and the fix, before any pixel is read:

- in one series: slices that differ in Rows/Columns, PixelSpacing or orientation (0.1 degree); slices of
  several series (SeriesInstanceUID); two slices at one position (several echoes, or a repeated acquisition);
  positions in some slices only; without positions, a missing or repeated InstanceNumber.
- between the two series: another matrix size; pixel spacings more than 1 % apart; normals more than 1 degree
  apart; different PatientID (when both give one); chosen slices farther apart along the normal than half the
  larger slice spacing of the two (the positions are compared as the scanner gives them, so both series must
  share one frame of reference, as two acquisitions of one session do).

When one image is a series and the other a single file, the single file is read as before and the two are
related only by the checks of `case.read_case` (matrix size, pixel spacing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..core.errors import CaseError
from ._formats import SliceFile, read_dicom_file, read_slice

PIXEL_SIZE_RTOL = 0.01                 # pixel spacings of the two images (and case.toml) may differ by 1 %
MAX_NORMAL_ANGLE_DEG = 1.0             # between the normals of the two series
SAME_ORIENTATION_IN_SERIES_DEG = 0.1   # direction cosines are stored as text of up to 16 characters
SAME_SPACING_IN_SERIES_RTOL = 1e-4    # one acquisition writes one PixelSpacing; this only absorbs its decimal text
SAME_POSITION_MM = 0.01                # two slices closer than this along the normal are at one position
IMAGES_KEYS = ("slice_index", "slice_position_mm")

_DICOM_PREFIX_OFFSET = 128             # a Part 10 file: 128-byte preamble, then b"DICM"
_DEFER_HEADER_BYTES = 4096             # read pixel data (and other large values) only for the chosen slice
_PIXEL_DATA_KEYWORDS = ("PixelData", "FloatPixelData", "DoubleFloatPixelData")
_REEXPORT = "export the series again from the scanner, one file per slice, with nothing else in the folder"


@dataclass(frozen=True)
class SliceChoice:
    """The [images] table of case.toml: at most one of index and position_mm is set."""

    index: int | None = None
    position_mm: float | None = None

    def describe(self) -> str:
        return f"slice_index = {self.index}" if self.index is not None else f"slice_position_mm = {self.position_mm:g}"


@dataclass(frozen=True)
class SeriesSlice:
    """The header of one slice file (nothing of its pixels is read)."""

    path: Path
    rows: int
    columns: int
    pixel_spacing_mm: tuple[float, float] | None
    directions: np.ndarray | None          # (2, 3) unit row and column direction cosines, patient frame
    position_patient_mm: np.ndarray | None  # (3,) ImagePositionPatient
    instance_number: int | None
    patient_id: str | None
    series_uid: str | None
    slice_gap_mm: float | None             # SpacingBetweenSlices, else SliceThickness

    @property
    def normal(self) -> np.ndarray | None:
        if self.directions is None:
            return None
        normal = np.cross(self.directions[0], self.directions[1])
        return normal / np.linalg.norm(normal)


@dataclass(frozen=True)
class DicomSeries:
    """A checked series: slices in increasing position along the normal (in InstanceNumber order when
    positions_mm is None)."""

    folder: Path
    slices: tuple[SeriesSlice, ...]
    positions_mm: np.ndarray | None
    spacing_mm: float | None

    @property
    def first(self) -> SeriesSlice:
        return self.slices[0]

    @property
    def shape(self) -> tuple[int, int]:
        return self.first.rows, self.first.columns

    def describe(self) -> str:
        """How many slices, where (for the messages)."""
        count = len(self.slices)
        if count == 1:
            where = (f"at {_mm(self.positions_mm[0])} mm along the slice normal" if self.positions_mm is not None
                     else "without ImagePositionPatient")
            return f"1 slice {where}"
        if self.positions_mm is None:
            numbers = [s.instance_number for s in self.slices]
            return (f"{count} slices without ImagePositionPatient, ordered by InstanceNumber "
                    f"({numbers[0]} to {numbers[-1]})")
        gaps = np.diff(self.positions_mm)
        if gaps.size and np.ptp(gaps) > 0.01 * self.spacing_mm:    # a slice missing, or a series of several stacks
            gap = f", {gaps.min():.2f} to {gaps.max():.2f} mm apart (slice spacing taken as the median, {self.spacing_mm:.2f} mm)"
        else:
            gap = f", {self.spacing_mm:.2f} mm apart" if self.spacing_mm is not None else ""
        return f"{count} slices at {_mm(self.positions_mm[0])} to {_mm(self.positions_mm[-1])} mm along the slice normal{gap}"


def _mm(value: float) -> str:
    """A position as the console shows it: at most two decimals, no trailing zeros, no "-0"."""
    return f"{round(float(value), 2) + 0.0:.2f}".rstrip("0").rstrip(".")


# ----------------------------------------------------------------- the pair of images of a case


def read_image_pair(toml_path: Path, images_table: dict | None, unloaded_path: Path,
                    loaded_path: Path) -> tuple[SliceFile, SliceFile]:
    """Read the unloaded and loaded images, each a single file or a DICOM series folder; choose the slice of
    a series by the [images] table (None when absent). A slice read from a series has the folder as its path
    and its own file as series_file."""
    choice = slice_choice(toml_path, images_table)
    paths = {"unloaded": unloaded_path, "loaded": loaded_path}
    if choice is not None and not any(path.is_dir() for path in paths.values()):
        raise CaseError(toml_path, f"[images] {choice.describe()} chooses a slice of a DICOM series but "
                        f"{unloaded_path.name} and {loaded_path.name} are single slices",
                        "remove the [images] table (it applies only to unloaded/ and loaded/ given as series folders)")
    series = {role: read_series(path) for role, path in paths.items() if path.is_dir()}
    chosen = {role: choose_slice(toml_path, one, choice) for role, one in series.items()}
    if len(series) == 2:
        check_same_acquisition(series["unloaded"], chosen["unloaded"], series["loaded"], chosen["loaded"], choice)
    images = []
    for role, path in paths.items():
        if role in series:
            slice_file = read_dicom_file(series[role].slices[chosen[role]].path)
            images.append(replace(slice_file, path=path, series_file=slice_file.path))
        else:
            images.append(read_slice(path))
    return images[0], images[1]


def slice_choice(toml_path: Path, table: dict | None) -> SliceChoice | None:
    """The [images] table as a SliceChoice (its keys, types and the one choice checked by `schema.ImagesTable`)."""
    if not table:
        return None
    if "slice_index" in table:
        return SliceChoice(index=int(table["slice_index"]))
    return SliceChoice(position_mm=float(table["slice_position_mm"]))


# ----------------------------------------------------------------- one series


def read_series(folder: Path) -> DicomSeries:
    """Read the headers of the DICOM images of a folder, check that they make one series, order them."""
    files = sorted(p for p in folder.iterdir() if p.is_file())
    slices = [header for header in (_read_header(path) for path in files) if header is not None]
    if not slices:
        subfolders = " (sub-folders are not searched)" if any(p.is_dir() for p in folder.iterdir()) else ""
        raise CaseError(folder, f"holds no DICOM image among its {len(files)} files{subfolders}",
                        "put the slice files of one DICOM series in it (DICOM Part 10 files, with the DICM prefix), "
                        "or replace the folder by a single image file")
    # Several series first: a localizer or a second acquisition left in the folder is the likely cause of the
    # differences `_check_alike` would report.
    uids = sorted({s.series_uid for s in slices if s.series_uid})
    if len(uids) > 1:
        raise CaseError(folder, f"holds slices of {len(uids)} series (SeriesInstanceUID {uids[0]} and {uids[1]})",
                        "keep the slices of one series only in the folder")
    _check_alike(folder, slices)
    with_position = [s for s in slices if s.position_patient_mm is not None and s.directions is not None]
    if with_position and len(with_position) < len(slices):
        lacking = next(s for s in slices if s.position_patient_mm is None or s.directions is None)
        raise CaseError(lacking.path, f"has no ImagePositionPatient or ImageOrientationPatient while "
                        f"{len(with_position)} other slices of {folder.name}/ have them", _REEXPORT)
    if with_position:
        normal = slices[0].normal
        positions = np.array([float(np.dot(s.position_patient_mm, normal)) for s in slices])
        order = np.argsort(positions, kind="stable")
        slices, positions = [slices[i] for i in order], positions[order]
        gaps = np.diff(positions)
        if gaps.size and gaps.min() < SAME_POSITION_MM:
            i = int(np.argmin(gaps))
            raise CaseError(folder, f"holds two slices at {_mm(positions[i])} mm along the normal "
                            f"({slices[i].path.name} and {slices[i + 1].path.name}: several echoes or a repeated acquisition?)",
                            "keep one slice per position (one echo, one acquisition) in the folder")
        spacing = float(np.median(gaps)) if gaps.size else slices[0].slice_gap_mm
        return DicomSeries(folder, tuple(slices), positions, spacing)
    if len(slices) > 1:
        # The fallback on InstanceNumber: documented in the module text; `choose_slice` says it in its errors.
        unnumbered = [s for s in slices if s.instance_number is None]
        if unnumbered:
            raise CaseError(unnumbered[0].path, "has neither ImagePositionPatient nor InstanceNumber, so the slices "
                            f"of {folder.name}/ cannot be ordered", _REEXPORT)
        slices = sorted(slices, key=lambda s: s.instance_number)
        numbers = [s.instance_number for s in slices]
        repeated = next((a for a, b in zip(numbers, numbers[1:]) if a == b), None)
        if repeated is not None:
            twins = [s.path.name for s in slices if s.instance_number == repeated]
            raise CaseError(folder, f"holds two slices with InstanceNumber {repeated} ({twins[0]} and {twins[1]}) "
                            "and no ImagePositionPatient to order them", "keep the slices of one series only in the folder")
    return DicomSeries(folder, tuple(slices), None, slices[0].slice_gap_mm if len(slices) == 1 else None)


def choose_slice(toml_path: Path, series: DicomSeries, choice: SliceChoice | None) -> int:
    """The index of the slice of the series that [images] asks for."""
    count = len(series.slices)
    if count > 1 and choice is None:
        if series.positions_mm is None:
            raise CaseError(series.folder, f"is a series of {series.describe()}, and case.toml does not say which to use",
                            f"add [images] slice_index = <0 to {count - 1}> to case.toml (the slice at the largest calf perimeter)")
        raise CaseError(series.folder, f"is a series of {series.describe()}, and case.toml does not say which to use",
                        "add [images] slice_position_mm = <position of the slice at the largest calf perimeter> to "
                        f"case.toml (or slice_index = <0 to {count - 1}>)")
    if choice is None:
        return 0
    if choice.index is not None:
        if count == 1:
            return 0    # one slice is the only choice; its position is checked against the other series'
        if choice.index >= count:
            raise CaseError(toml_path, f"[images] slice_index = {choice.index} but {series.folder.name}/ is a series of "
                            f"{series.describe()}", f"give slice_index from 0 to {count - 1}")
        return choice.index
    positions = series.positions_mm
    if positions is None:
        raise CaseError(toml_path, f"[images] slice_position_mm is given but {series.folder.name}/ is a series of "
                        f"{series.describe()}", "choose the slice with slice_index (0-based, in InstanceNumber order)")
    if series.spacing_mm is None:
        raise CaseError(toml_path, f"[images] slice_position_mm is given but the single slice of {series.folder.name}/ "
                        "gives no SliceThickness or SpacingBetweenSlices to check its position against",
                        "write slice_index = 0 instead")
    z = choice.position_mm
    nearest = int(np.argmin(np.abs(positions - z)))   # a tie goes to the lower position
    distance = abs(positions[nearest] - z)
    half = series.spacing_mm / 2
    if distance > half + 1e-6 * max(1.0, abs(z)):
        below, above = positions[positions <= z], positions[positions >= z]
        where = (f"between its slices at {_mm(below[-1])} and {_mm(above[0])} mm" if below.size and above.size else
                 f"beyond its last slice, at {_mm(below[-1])} mm" if below.size else f"before its first slice, at {_mm(above[0])} mm")
        raise CaseError(toml_path, f"[images] slice_position_mm = {z:g} lies in {series.folder.name}/ {where}, "
                        f"{distance:.2f} mm from the nearest, more than half its slice spacing of {series.spacing_mm:.2f} mm",
                        f"give a position within {half:.2f} mm of a slice: {series.folder.name}/ is a series of "
                        f"{series.describe()}")
    return nearest


# ----------------------------------------------------------------- the two series


def check_same_acquisition(unloaded: DicomSeries, unloaded_index: int, loaded: DicomSeries, loaded_index: int,
                           choice: SliceChoice | None) -> None:
    """Refuse two series that do not show the same slice of the same leg the same way (module text)."""
    ours, theirs = loaded.folder, f"the unloaded series {unloaded.folder}"
    if loaded.shape != unloaded.shape:
        raise CaseError(ours, f"is a series of {loaded.shape[0]}x{loaded.shape[1]} pixels but {theirs} is "
                        f"{unloaded.shape[0]}x{unloaded.shape[1]}", "acquire both series with the same matrix size and field of view")
    spacing_loaded, spacing_unloaded = loaded.first.pixel_spacing_mm, unloaded.first.pixel_spacing_mm
    if (spacing_loaded is not None and spacing_unloaded is not None
            and not np.allclose(spacing_loaded, spacing_unloaded, rtol=PIXEL_SIZE_RTOL, atol=0)):
        raise CaseError(ours, f"has pixels of {_pair(spacing_loaded)} mm (row x column) but {theirs} has "
                        f"{_pair(spacing_unloaded)} mm", "acquire both series with the same field of view and matrix size")
    normal_loaded, normal_unloaded = loaded.first.normal, unloaded.first.normal
    if normal_loaded is not None and normal_unloaded is not None:
        angle = _angle_deg(normal_loaded, normal_unloaded)
        if angle > MAX_NORMAL_ANGLE_DEG:
            raise CaseError(ours, f"has its slices tilted by {angle:.1f} degrees from those of {theirs}",
                            "acquire both series with the same slice orientation (copy the slice planning of the first)")
    patient_loaded, patient_unloaded = loaded.first.patient_id, unloaded.first.patient_id
    if patient_loaded and patient_unloaded and patient_loaded != patient_unloaded:
        raise CaseError(ours, f"belongs to PatientID '{patient_loaded}' but {theirs} to '{patient_unloaded}'",
                        "put the two series of the same leg in the case folder")
    if loaded.positions_mm is None or unloaded.positions_mm is None:
        return
    spacings = [s for s in (loaded.spacing_mm, unloaded.spacing_mm) if s is not None]
    if not spacings:
        return    # two single slices that give no thickness: nothing to measure the gap against
    at_loaded, at_unloaded = loaded.positions_mm[loaded_index], unloaded.positions_mm[unloaded_index]
    half = max(spacings) / 2
    if abs(at_loaded - at_unloaded) > half + 1e-6:
        fix = ("acquire both series at the same slice positions (same table position and slice planning)"
               if choice is not None and choice.position_mm is not None else
               "choose the slice with [images] slice_position_mm, which takes the nearest slice in each series")
        raise CaseError(ours, f"slice {loaded_index} at {_mm(at_loaded)} mm along the normal is {abs(at_loaded - at_unloaded):.2f} mm "
                        f"from slice {unloaded_index} of {theirs} at {_mm(at_unloaded)} mm, more than half a slice spacing "
                        f"({half:.2f} mm)", fix)


def _pair(values) -> str:
    return f"{values[0]:g} x {values[1]:g}"


# ----------------------------------------------------------------- headers


def _check_alike(folder: Path, slices: list[SeriesSlice]) -> None:
    """All slices of one series share matrix size, pixel spacing and orientation."""
    first = slices[0]
    for other in slices[1:]:
        names = first.path.name, other.path.name
        differs = None
        if (other.rows, other.columns) != (first.rows, first.columns):
            differs = f"of {first.rows}x{first.columns} pixels ({names[0]}) and {other.rows}x{other.columns} pixels ({names[1]})"
        elif (other.pixel_spacing_mm is None) != (first.pixel_spacing_mm is None) or (
                first.pixel_spacing_mm is not None
                and not np.allclose(other.pixel_spacing_mm, first.pixel_spacing_mm, rtol=SAME_SPACING_IN_SERIES_RTOL, atol=0)):
            differs = f"with a PixelSpacing of {_spacing(first)} ({names[0]}) and {_spacing(other)} ({names[1]})"
        elif (other.directions is None) != (first.directions is None) or (
                first.directions is not None and max(_angle_deg(a, b) for a, b in zip(first.directions, other.directions))
                > SAME_ORIENTATION_IN_SERIES_DEG):
            differs = f"of two orientations ({names[0]} and {names[1]} differ in ImageOrientationPatient)"
        if differs:
            raise CaseError(folder, f"mixes slices {differs}", "keep the slices of one series only in the folder")


def _spacing(header: SeriesSlice) -> str:
    return "none" if header.pixel_spacing_mm is None else f"{_pair(header.pixel_spacing_mm)} mm"


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def _is_dicom_file(path: Path) -> bool:
    try:
        with path.open("rb") as stream:
            stream.seek(_DICOM_PREFIX_OFFSET)
            return stream.read(4) == b"DICM"
    except OSError:
        return False


def _read_header(path: Path) -> SeriesSlice | None:
    """The header of a DICOM image file; None for a file that is not DICOM or holds no image."""
    import pydicom

    if not _is_dicom_file(path):
        return None
    try:
        dataset = pydicom.dcmread(path, defer_size=_DEFER_HEADER_BYTES)
    except Exception as exc:   # the DICM prefix says it is meant to be DICOM: a broken file is not skipped
        reason = str(exc).strip().splitlines()[0].rstrip(".") if str(exc).strip() else type(exc).__name__
        raise CaseError(path, f"cannot be read as DICOM ({reason})", _REEXPORT) from exc
    if not any(keyword in dataset for keyword in _PIXEL_DATA_KEYWORDS):
        return None
    frames = dataset.get("NumberOfFrames")
    if frames not in (None, "") and int(frames) > 1:
        raise CaseError(path, f"holds {int(frames)} frames (an enhanced multi-frame DICOM file)",
                        f"export the series as one file per slice (classic DICOM) or extract the slice as {path.parent.name}.dcm")
    rows, columns = dataset.get("Rows"), dataset.get("Columns")
    if not rows or not columns:
        raise CaseError(path, "holds pixel data without Rows and Columns", _REEXPORT)
    spacing = _numbers(dataset, "PixelSpacing", 2, path)
    orientation = _numbers(dataset, "ImageOrientationPatient", 6, path)
    directions = None
    if orientation is not None:
        directions = orientation.reshape(2, 3)
        norms = np.linalg.norm(directions, axis=1)
        if norms.min() < 0.5 or np.linalg.norm(np.cross(directions[0], directions[1])) < 0.5 * norms.prod():
            raise CaseError(path, f"has an ImageOrientationPatient {list(orientation)} that is not two directions",
                            _REEXPORT)
        directions = directions / norms[:, None]
    gap = next((float(v[0]) for key in ("SpacingBetweenSlices", "SliceThickness")
                if (v := _numbers(dataset, key, 1, path)) is not None and v[0] > 0), None)
    number = dataset.get("InstanceNumber")
    return SeriesSlice(path=path, rows=int(rows), columns=int(columns),
                       pixel_spacing_mm=(float(spacing[0]), float(spacing[1])) if spacing is not None else None,
                       directions=directions, position_patient_mm=_numbers(dataset, "ImagePositionPatient", 3, path),
                       instance_number=int(number) if number not in (None, "") else None,
                       patient_id=str(dataset.get("PatientID") or "").strip() or None,
                       series_uid=str(dataset.get("SeriesInstanceUID") or "").strip() or None,
                       slice_gap_mm=gap)


def _numbers(dataset, keyword: str, count: int, path: Path) -> np.ndarray | None:
    """A numeric header element of `count` values; None when absent or empty."""
    value = dataset.get(keyword)
    if value is None or value == "":
        return None
    values = [value] if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__") else list(value)
    try:
        numbers = np.array([float(v) for v in values])
    except (TypeError, ValueError):
        numbers = np.array([])
    if numbers.size != count or not np.all(np.isfinite(numbers)):
        raise CaseError(path, f"has an unreadable {keyword} {value!r} ({count} numbers expected)", _REEXPORT)
    return numbers
