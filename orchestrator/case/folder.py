"""Read and write a case folder (docs/design.md, "The case folder"; every key: docs/case-folder.md).

A case is ``case.toml`` + the unloaded image I0 + the loaded image I1, with an
optional label map of I0 (0 background, 1 fat with skin, 2 muscle, 3 bone,
labels >= 4 are muscle compartments) and optional measured displacements
``points.csv`` (x_mm,y_mm,ux_mm,uy_mm[,sigma_mm], image frame of I0, tissue
relative to bones). Images may be PNG/TIFF, ``.npy``, DICOM or NIfTI; the unloaded and loaded
images may also be folders ``unloaded/`` and ``loaded/`` holding a DICOM series each, the slice chosen by the
optional [images] table of case.toml (`dicom_series`). More loaded images of the same slice under other garment
tensions (the second paper's socks of 20 and 40 mmHg) are named by [[garment.levels]] tables, each with its image,
its tension and optionally its points (`GarmentLevel`); they are fitted jointly with the first (`levels`).

Reading checks everything before returning and raises one `CaseError` (one
sentence: file, what is wrong, the fix) at the first problem; it never writes.
case.toml is read through its declared schema (`schema.CaseToml`: keys, units,
ranges); what needs the images is checked here: a landmark inside the image, a
level's file, a header's pixel spacing, and a label map whose labels all mean a tissue (0-3, or a muscle
compartment 4-31 of at least MIN_COMPARTMENT_MM2).
Writing goes to a temporary sibling folder renamed into place at the end, so a
case folder is either complete or absent.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomllib

from ..core.errors import CaseError, MaterialError
from ..core.files import staged_folders
from ..core.materials import ELEMENTS, TissueLaw
from ..core.tissues import (
    BACKGROUND,
    BONE,
    FAT,
    FIRST_COMPARTMENT,
    LAST_COMPARTMENT,
    MUSCLE,
)
from .acquisition import LARMOR_MHZ_PER_T, PHASE_ENCODING_OF_READOUT, Acquisition
from ._formats import IMAGE_SUFFIXES, SliceFile, file_suffix, read_slice, write_png16
from .dicom_series import PIXEL_SIZE_RTOL, read_image_pair
from .schema import (
    PIXEL_SIZE_RANGE_MM,
    PIXEL_SIZE_TEXT,
    CaseToml,
    GarmentLevelTable,
    ModelTable,
    TissueTable,
    keys_of,
    parse,
)

POINTS_COLUMNS = ("x_mm", "y_mm", "ux_mm", "uy_mm")
DEFAULT_TENSION_REL_UNCERTAINTY = 0.10

_TOML_SCHEMA = keys_of(CaseToml)   # {table: its keys}, as docs/case-folder.md lists them
MIN_COMPARTMENT_MM2 = 50.0   # a labelled muscle compartment's least area (`imaging.compartments` keeps 150 mm^2)


@dataclass(frozen=True)
class ModelChoice:
    """The [model] table of case.toml: the element (None: the run's default, CPE6 for displacement data, CPE3 for
    contours), the garment (Laplace's law, or the second paper's explicit band with penalty contact), the
    band's Coulomb friction coefficient and the law of each tissue with a [model.<tissue>] table
    (`materials.TissueLaw` by tissue name; the others keep the first paper's law)."""

    element: str | None = None
    garment: str = "laplace"
    friction: float = 0.0
    tissues: dict = field(default_factory=dict)

    @property
    def order(self) -> int | None:
        return ELEMENTS[self.element] if self.element else None

    @property
    def hybrid(self) -> bool:
        return self.element == "CPE6H"


@dataclass(frozen=True)
class DisplacementPoints:
    """Measured displacements at points: positions and displacements in mm (N, 2), sigma in mm (N,) or None."""

    position_mm: np.ndarray
    displacement_mm: np.ndarray
    sigma_mm: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.position_mm)


@dataclass(frozen=True)
class GarmentLevel:
    """One more loaded image of the slice, under another garment tension: a [[garment.levels]] table of case.toml.
    number: the garment level it is (2, 3, ...: level 1 is loaded.* under the [garment] tension); path: its image
    file (in the case folder; when writing a case, the file name to write); points: its points file read, if any;
    missing: its pixels without a value (NaN), None when every pixel has one."""

    number: int
    image: np.ndarray
    tension_N_per_mm: float
    path: Path
    points: DisplacementPoints | None = None
    points_path: Path | None = None
    missing: np.ndarray | None = None


@dataclass(frozen=True)
class Case:
    """A validated case folder. Images are float64 (H, W); pixel_size_mm is (row, column)."""

    folder: Path
    name: str
    pixel_size_mm: tuple[float, float]
    unloaded: np.ndarray
    loaded: np.ndarray
    tension_N_per_mm: float
    tension_rel_uncertainty: float
    model: ModelChoice = ModelChoice()
    labels: np.ndarray | None = None
    points: DisplacementPoints | None = None
    landmarks: dict[str, tuple[float, float]] = field(default_factory=dict)
    files: dict[str, Path] = field(default_factory=dict)
    missing: dict[str, np.ndarray] = field(default_factory=dict)   # "unloaded"/"loaded": pixels with no value
    block_factor: int = 1     # pixels of the files per pixel side of these arrays (`resolution.working_resolution`)
    levels: tuple[GarmentLevel, ...] = ()   # more loaded images under other tensions ([[garment.levels]])
    acquisition: Acquisition | None = None  # what the images' DICOM header says of the sequence (`acquisition`)

    @property
    def tensions(self) -> tuple[float, ...]:
        """The garment tension of every level (N/mm), the first level's ([garment]) first."""
        return (self.tension_N_per_mm,) + tuple(level.tension_N_per_mm for level in self.levels)

    @property
    def shape(self) -> tuple[int, int]:
        return self.unloaded.shape

    @property
    def extent_mm(self) -> tuple[float, float]:
        """(width along x, height along y) of the image in mm."""
        return self.shape[1] * self.pixel_size_mm[1], self.shape[0] * self.pixel_size_mm[0]


# --------------------------------------------------------------------- reading


def read_case(folder: str | os.PathLike) -> Case:
    """Read and validate a case folder; raise CaseError naming the file and the fix."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaseError(folder, "is not a folder", "give the path of a case folder holding case.toml and the two images")
    toml_path = folder / "case.toml"
    settings = _read_toml(toml_path)
    images = settings.images.model_dump(exclude_none=True) if settings.images is not None else None
    unloaded, loaded = read_image_pair(toml_path, images, _find_file(folder, "unloaded", required=True),
                                       _find_file(folder, "loaded", required=True))
    if loaded.pixels.shape != unloaded.pixels.shape:
        raise CaseError(loaded.path, f"is {_dims(loaded.pixels)} pixels but {unloaded.path.name} is {_dims(unloaded.pixels)}",
                        "export both slices with the same matrix size and field of view")
    level_tables = settings.garment.levels
    level_slices = [_level_slice(toml_path, folder, number, entry, (unloaded, loaded))
                    for number, entry in enumerate(level_tables, start=2)]
    pixel_size = _pixel_size(toml_path, settings.case.pixel_size_mm, (unloaded, loaded, *level_slices))
    shape = unloaded.pixels.shape
    extent = (shape[1] * pixel_size[1], shape[0] * pixel_size[0])

    labels_path = _find_file(folder, "labels", required=False)
    labels = _read_labels(labels_path, shape, unloaded.path.name, pixel_size) if labels_path else None
    points_path = folder / "points.csv"
    points = _read_points(points_path, extent) if points_path.exists() else None
    garment = settings.garment
    landmarks = _landmarks(toml_path, settings.landmarks, extent)
    name = settings.case.name if settings.case.name is not None else folder.name
    model = model_choice(toml_path, settings.model)
    levels = tuple(_garment_level(toml_path, folder, number, entry, image, extent)
                   for number, (entry, image) in enumerate(zip(level_tables, level_slices), start=2))

    files = {"toml": toml_path, "unloaded": unloaded.path, "loaded": loaded.path}
    if labels_path:
        files["labels"] = labels_path
    if points is not None:
        files["points"] = points_path
    for role, image in (("unloaded", unloaded), ("loaded", loaded)):
        if image.series_file is not None:
            files[f"{role}_slice"] = image.series_file    # the file of the slice chosen in a DICOM series
    return Case(folder=folder, name=name, pixel_size_mm=pixel_size,
                unloaded=unloaded.pixels.astype(float), loaded=loaded.pixels.astype(float),
                tension_N_per_mm=garment.tension_N_per_mm,
                tension_rel_uncertainty=(DEFAULT_TENSION_REL_UNCERTAINTY if garment.tension_rel_uncertainty is None
                                         else garment.tension_rel_uncertainty),
                model=model, labels=labels, points=points, landmarks=landmarks, files=files,
                missing={role: image.missing for role, image in (("unloaded", unloaded), ("loaded", loaded))
                         if image.missing is not None}, levels=levels,
                acquisition=_acquisition(settings.acquisition, (unloaded, loaded), pixel_size))


def _acquisition(table, slices: tuple[SliceFile, ...], pixel_size: tuple[float, float]) -> Acquisition | None:
    """The sequence's parameters: the images' DICOM header's, else case.toml's [acquisition] (`acquisition`)."""
    for image in slices:
        if image.acquisition is not None and image.acquisition.fat_shift_px is not None:
            return image.acquisition
    if table is None:
        return next((image.acquisition for image in slices if image.acquisition is not None), None)
    frequency = (table.imaging_frequency_MHz if table.imaging_frequency_MHz is not None
                 else LARMOR_MHZ_PER_T * table.field_strength_T)
    phase = PHASE_ENCODING_OF_READOUT.get(table.readout)
    return Acquisition(frequency, table.pixel_bandwidth_Hz, phase, tuple(pixel_size), "case.toml's [acquisition]")


def _level_file(path: Path, folder: Path, index: int, entry: GarmentLevelTable, key: str, what: str) -> Path:
    """The file a [[garment.levels]] key names, in the case folder."""
    name = getattr(entry, key)
    target = folder / name
    if target.resolve().parent != folder.resolve():
        raise CaseError(path, f"[[garment.levels]] number {index} {key} = {name!r} is not a file of the case folder",
                        "put the file in the case folder beside case.toml and give its name alone")
    if not target.is_file():
        raise CaseError(target, f"is missing ({key} of [[garment.levels]] number {index} in case.toml)",
                        f"put that level's {what} in the case folder under this name, or correct {key} in case.toml")
    return target


def _level_slice(path: Path, folder: Path, number: int, entry: GarmentLevelTable,
                 pair: tuple[SliceFile, SliceFile]) -> SliceFile:
    """The loaded image of the garment level `number` (2, 3, ...), checked against the first level's pair."""
    index = number - 1
    target = _level_file(path, folder, index, entry, "image", "loaded slice")
    unloaded, loaded = pair
    for other, role in ((unloaded, "the unloaded image"), (loaded, "the first level's loaded image")):
        if target.resolve() == other.path.resolve():
            raise CaseError(path, f"[[garment.levels]] number {index} image names {other.path.name}, {role}",
                            "give each garment level its own loaded slice")
    image = read_slice(target)
    if image.pixels.shape != unloaded.pixels.shape:
        raise CaseError(target, f"is {_dims(image.pixels)} pixels but {unloaded.path.name} is {_dims(unloaded.pixels)}",
                        "export every slice of the case with the same matrix size and field of view")
    return image


def _garment_level(path: Path, folder: Path, number: int, entry: GarmentLevelTable, image: SliceFile,
                   extent: tuple[float, float]) -> GarmentLevel:
    index = number - 1
    points_path = (_level_file(path, folder, index, entry, "points", "points (points.csv format)")
                   if entry.points is not None else None)
    points = _read_points(points_path, extent) if points_path is not None else None
    return GarmentLevel(number, image.pixels.astype(float), float(entry.tension_N_per_mm), image.path, points,
                        points_path, image.missing)


def _dims(pixels: np.ndarray) -> str:
    return f"{pixels.shape[0]}x{pixels.shape[1]}"


def _read_toml(path: Path) -> CaseToml:
    """case.toml read and validated against its schema (`schema.CaseToml`)."""
    if not path.is_file():
        raise CaseError(path, "is missing", "create it with a [case] table (name, pixel_size_mm) and a [garment] table")
    try:
        text = path.read_text(encoding="utf-8")
        settings = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CaseError(path, f"is not valid TOML ({exc})", "fix the syntax (tables in [brackets], key = value)") from exc
    if "study" in settings:
        raise CaseError(path, "is a volume case ([study]: slices to cut at several heights), not one slice",
                        f"run `calfit study {path.parent} --out STUDY_DIR`, which cuts it into slice cases")
    return parse(path, text, settings)


def read_model_choice(folder: str | os.PathLike) -> ModelChoice:
    """The [model] table of a case folder's case.toml alone (no image read; the whole file is checked)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaseError(folder, "is not a folder", "give the path of a case folder holding case.toml and the two images")
    toml_path = folder / "case.toml"
    return model_choice(toml_path, _read_toml(toml_path).model)


def model_choice(path: Path, table: ModelTable) -> ModelChoice:
    """The [model] table (validated by `schema.ModelTable`) as a ModelChoice, each tissue's law made."""
    tissues = {tissue: _tissue_law(path, tissue, entry) for tissue, entry in table.tissues.items()}
    return ModelChoice(table.element, table.garment, float(table.friction), tissues)


def _tissue_law(path: Path, tissue: str, table: TissueTable) -> TissueLaw:
    """[model.<tissue>] as a TissueLaw (docs/case-folder.md, "The model")."""
    try:
        return TissueLaw(table.law, table.terms, table.incompressible, fixed=dict(table.fixed),
                         bounds={name: tuple(pair) for name, pair in table.bounds.items()}, start=dict(table.start))
    except MaterialError as error:
        raise CaseError(path, f"[model.{tissue}]: {error}", "name only the law's constants (C10, C01, C20, C30, Kv), "
                        "in kPa") from None


def _find_file(folder: Path, stem: str, required: bool) -> Path | None:
    """The image file `stem`.<suffix>, or, for the unloaded and loaded images, a DICOM series folder `stem`/."""
    series_allowed = stem in ("unloaded", "loaded")
    found = sorted(p for p in folder.iterdir()
                   if (p.is_file() and file_suffix(p) in IMAGE_SUFFIXES and p.name.lower() == stem + file_suffix(p))
                   or (series_allowed and p.is_dir() and p.name.lower() == stem))
    if len(found) > 1:
        raise CaseError(found[1], f"competes with {found[0].name} as the {stem} image", "keep only one of them in the folder")
    if not found and required:
        raise CaseError(folder / f"{stem}.png", "is missing",
                        f"put the {stem} slice in the case folder as {stem}.png (or .tif, .npy, .dcm, .nii), "
                        f"or its DICOM series in a folder {stem}/")
    return found[0] if found else None


def _pixel_size(toml_path: Path, declared, slices: tuple[SliceFile, ...]) -> tuple[float, float]:
    """The pixel size: case.toml's (its range checked by the schema), else the headers', which must agree."""
    declared = (float(declared[0]), float(declared[1])) if declared is not None else None
    headers = [(s.path, s.header_pixel_size_mm) for s in slices if s.header_pixel_size_mm is not None]
    low, high = PIXEL_SIZE_RANGE_MM
    for path, spacing in headers:
        if not all(math.isfinite(v) and v > 0 for v in spacing):
            raise CaseError(path, f"has an invalid pixel spacing {spacing} in its header", "fix the header or re-export the slice")
        reference = declared if declared is not None else headers[0][1]
        if not np.allclose(spacing, reference, rtol=PIXEL_SIZE_RTOL, atol=0):
            source = f"case.toml says {list(reference)}" if declared is not None else f"{headers[0][0].name} says {list(reference)}"
            raise CaseError(path, f"header gives a pixel spacing of {[round(v, 6) for v in spacing]} mm but {source}",
                            "correct pixel_size_mm in case.toml or use slices from the same acquisition")
        if declared is None and not all(low <= v <= high for v in spacing):
            raise CaseError(path, f"header gives a pixel spacing of {[round(v, 6) for v in spacing]} mm, not "
                            f"{PIXEL_SIZE_TEXT}", "fix the header, or give pixel_size_mm = [row_mm, column_mm] "
                            "under [case] in case.toml")
    if declared is not None:
        return declared
    if headers:
        return headers[0][1]
    raise CaseError(toml_path, "[case] pixel_size_mm is missing and the images carry no spacing",
                    "add pixel_size_mm = [row_mm, column_mm] under [case]")


_LABELS_MEANING = (f"labels are 0 background, 1 fat, 2 muscle, 3 bone and {FIRST_COMPARTMENT} to {LAST_COMPARTMENT} "
                   "muscle compartments")


def _read_labels(path: Path, shape: tuple[int, int], image_name: str, pixel_size_mm) -> np.ndarray:
    labels = read_slice(path).pixels
    if labels.shape != shape:
        raise CaseError(path, f"is {_dims(labels)} pixels but {image_name} is {shape[0]}x{shape[1]}",
                        f"export the label map of {image_name} itself, at its {shape[0]}x{shape[1]} pixels, or remove "
                        f"labels.png (calfit then segments {image_name})")
    if not np.all(labels == np.round(labels)) or labels.min() < 0:
        raise CaseError(path, "holds values that are not non-negative integers",
                        "store labels 0 background, 1 fat, 2 muscle, 3 bone (4 and up for compartments)")
    labels = labels.astype(np.int32)
    for value in np.unique(labels[labels > LAST_COMPARTMENT]):
        mask_note = " (255 is what a binary mask stores for its foreground)" if value == 255 else ""
        raise CaseError(path, f"holds label {value} {_where_label(labels, value, pixel_size_mm)}, which means no "
                        f"tissue: {_LABELS_MEANING}{mask_note}",
                        "relabel those pixels with the tissue they show, or 0 outside the leg")
    area = float(np.prod(pixel_size_mm))
    for value, count in zip(*np.unique(labels[labels >= FIRST_COMPARTMENT], return_counts=True)):
        if count * area < MIN_COMPARTMENT_MM2:
            raise CaseError(path, f"holds label {value} {_where_label(labels, value, pixel_size_mm)}, too small for a "
                            f"muscle compartment (at least {MIN_COMPARTMENT_MM2:g} mm^2: a calf's are some hundreds)",
                            "relabel those pixels with the tissue they show (2 for muscle), or give the whole "
                            "compartment that label")
    tissues = {"fat (label 1)": labels == FAT, "muscle (label 2 or compartments >= 4)": (labels == MUSCLE) | (labels >= FIRST_COMPARTMENT),
               "bone (label 3)": labels == BONE}
    for tissue, mask in tissues.items():
        if not mask.any():
            raise CaseError(path, f"has no {tissue} pixels", "segment the slice again so that fat, muscle and bone are all labelled")
    return labels


def _where_label(labels: np.ndarray, value: int, pixel_size_mm) -> str:
    """Where a label lies, in words: its pixels, area, and whether inside the leg or outside it (at the border)."""
    from scipy import ndimage

    mask = labels == value
    rows, cols = np.nonzero(mask)
    dy, dx = pixel_size_mm
    around = ndimage.binary_dilation(mask) & ~mask
    inside = around.any() and np.mean(labels[around] > BACKGROUND) > 0.5
    place = f"inside the leg around x {cols.mean() * dx:.1f}, y {rows.mean() * dy:.1f} mm" if inside else \
        f"outside the leg, rows {rows.min()}-{rows.max()}, columns {cols.min()}-{cols.max()}"
    return f"in {len(rows)} pixels ({len(rows) * dx * dy:.0f} mm^2, {place})"


def _read_points(path: Path, extent: tuple[float, float]) -> DisplacementPoints:
    fix = f"write a header {','.join(POINTS_COLUMNS)}[,sigma_mm] and one point per line in mm"
    try:
        with path.open(newline="", encoding="utf-8") as stream:
            rows = [row for row in csv.reader(stream) if any(cell.strip() for cell in row)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise CaseError(path, f"cannot be read as CSV ({exc})", fix) from exc
    if not rows:
        raise CaseError(path, "is empty", fix + " (or delete the file)")
    header = tuple(cell.strip() for cell in rows[0])
    if header not in (POINTS_COLUMNS, POINTS_COLUMNS + ("sigma_mm",)):
        raise CaseError(path, f"has the header {','.join(header)}", fix)
    if len(rows) == 1:
        raise CaseError(path, "has a header but no points", fix + " (or delete the file)")
    values = np.empty((len(rows) - 1, len(header)))
    for index, row in enumerate(rows[1:]):
        line = index + 2
        if len(row) != len(header):
            raise CaseError(path, f"line {line} has {len(row)} fields instead of {len(header)}", fix)
        for column, cell in enumerate(row):
            try:
                values[index, column] = float(cell)
            except ValueError:
                raise CaseError(path, f"line {line}: '{cell.strip()}' is not a number", fix) from None
    where_bad = ~np.isfinite(values).all(axis=1)
    if where_bad.any():
        raise CaseError(path, f"line {int(np.argmax(where_bad)) + 2} holds a NaN or infinite value", "give finite numbers")
    outside = (values[:, 0] < 0) | (values[:, 0] > extent[0]) | (values[:, 1] < 0) | (values[:, 1] > extent[1])
    if outside.any():
        raise CaseError(path, f"line {int(np.argmax(outside)) + 2} lies outside the image ({extent[0]:.1f} x {extent[1]:.1f} mm)",
                        "give positions in mm from the top-left corner of the unloaded image")
    sigma = None
    if len(header) == 5:
        sigma = values[:, 4]
        if (sigma <= 0).any():
            raise CaseError(path, f"line {int(np.argmax(sigma <= 0)) + 2} has sigma_mm <= 0", "give positive uncertainties in mm")
    return DisplacementPoints(values[:, :2].copy(), values[:, 2:4].copy(), sigma)


def _landmarks(path: Path, table: dict, extent: tuple[float, float]) -> dict[str, tuple[float, float]]:
    """The [landmarks] (pairs of numbers, by the schema), each inside the image."""
    landmarks = {}
    for name, (x, y) in table.items():
        if not (0 <= x <= extent[0] and 0 <= y <= extent[1]):
            raise CaseError(path, f"landmark '{name}' at ({x}, {y}) mm lies outside the image ({extent[0]:.1f} x {extent[1]:.1f} mm)",
                            "give landmarks in mm from the top-left corner of the unloaded image (x right, y down)")
        landmarks[name] = (float(x), float(y))
    return landmarks


# --------------------------------------------------------------------- writing


def to_uint16(images: list[np.ndarray], full_scale: int = 60000) -> tuple[list[np.ndarray], float]:
    """Scale float images by one common factor to uint16 (so their grey levels stay comparable)."""
    peak = max(float(np.max(image)) for image in images)
    scale = full_scale / peak if peak > 0 else 1.0
    return [np.clip(np.round(image * scale), 0, 65535).astype(np.uint16) for image in images], scale


def write_case_folder(folder: str | os.PathLike, *, name: str, unloaded: np.ndarray, loaded: np.ndarray,
                      pixel_size_mm: tuple[float, float], tension_N_per_mm: float,
                      tension_rel_uncertainty: float = DEFAULT_TENSION_REL_UNCERTAINTY,
                      labels: np.ndarray | None = None, points: DisplacementPoints | None = None,
                      landmarks: dict[str, tuple[float, float]] | None = None, levels: tuple[GarmentLevel, ...] = (),
                      images_as: str = "png", model_toml: str = "", overwrite: bool = False,
                      acquisition: Acquisition | None = None) -> Path:
    """Write a complete case folder atomically (temporary sibling, then rename). Returns the folder.

    images_as "png": float images are scaled by one common factor to 16-bit PNG; uint8/uint16 images are written
    as they are. "npy": the two images are written as they are (float, NaN kept: a slice resampled from a volume
    has no value outside the other session's field of view). model_toml: the text of [model] tables, appended to
    case.toml as it is (the model a volume case gives all its slices).
    levels: more loaded images under other tensions, each written as its `path` (a .png file name) with its
    [[garment.levels]] table, and its points as `points_path` (a file name) when it has points.
    acquisition: the sequence's parameters of the images (a slice of a DICOM series), written as the [acquisition]
    table when they give the chemical shift's size.
    """
    folder = Path(folder)
    if folder.exists() and not overwrite:
        raise FileExistsError(f"{folder} already exists; choose another folder or pass overwrite=True")
    if unloaded.shape != loaded.shape or (labels is not None and labels.shape != unloaded.shape):
        raise ValueError("unloaded, loaded and labels must have the same shape")
    level_images = [np.asarray(level.image) for level in levels]
    if any(image.shape != unloaded.shape for image in level_images):
        raise ValueError("every garment level's image must have the shape of the unloaded image")
    if any(Path(level.path).suffix.lower() != ".png" or Path(level.path).name != str(level.path) for level in levels):
        raise ValueError("a garment level is written as a .png file name of the case folder")
    if images_as not in ("png", "npy") or (images_as == "npy" and levels):
        raise ValueError("images_as is 'png', or 'npy' for a case without garment levels")
    images = [unloaded, loaded, *level_images]
    if images_as == "npy" or (unloaded.dtype in (np.uint8, np.uint16) and all(image.dtype == unloaded.dtype for image in images)):
        pngs = images
    else:   # one common scale, so that every level's grey levels compare with I0's
        pngs, _ = to_uint16([np.asarray(image, float) for image in images])
    with staged_folders(folder) as (staging,):
        text = _case_toml(name, pixel_size_mm, tension_N_per_mm, tension_rel_uncertainty, landmarks or {}, levels)
        if acquisition is not None and acquisition.fat_shift_px is not None:
            text += _acquisition_toml(acquisition)
        (staging / "case.toml").write_text(text + ("\n" + model_toml.strip() + "\n" if model_toml.strip() else ""),
                                           encoding="utf-8")
        for role, image in (("unloaded", pngs[0]), ("loaded", pngs[1])):
            if images_as == "npy":
                np.save(staging / f"{role}.npy", np.asarray(image))
            else:
                write_png16(staging / f"{role}.png", image)
        for level, png in zip(levels, pngs[2:]):
            write_png16(staging / Path(level.path).name, png)
            if level.points is not None:
                _write_points(staging / Path(level.points_path).name, level.points)
        if labels is not None:
            write_png16(staging / "labels.png", np.asarray(labels).astype(np.uint8))
        if points is not None:
            _write_points(staging / "points.csv", points)
    return folder


def _case_toml(name, pixel_size_mm, tension, rel, landmarks, levels=()) -> str:
    lines = ["[case]", f"name = {_toml_string(name)}",
             f"pixel_size_mm = [{float(pixel_size_mm[0])!r}, {float(pixel_size_mm[1])!r}]  # row, column", "",
             "[garment]", f"tension_N_per_mm = {float(tension)!r}", f"tension_rel_uncertainty = {float(rel)!r}"]
    for level in levels:
        lines += ["", "[[garment.levels]]  # one more loaded image of the slice, under another garment tension",
                  f"image = {_toml_string(Path(level.path).name)}", f"tension_N_per_mm = {float(level.tension_N_per_mm)!r}"]
        if level.points is not None:
            lines.append(f"points = {_toml_string(Path(level.points_path).name)}")
    if landmarks:
        lines += ["", "[landmarks]  # mm, image frame of the unloaded image (x right, y down)"]
        lines += [f"{key} = [{float(x)!r}, {float(y)!r}]" for key, (x, y) in landmarks.items()]
    return "\n".join(lines) + "\n"


def _acquisition_toml(acquisition: Acquisition) -> str:
    lines = ["", "[acquisition]  # the sequence's parameters: the size of the fat's chemical shift",
             f"pixel_bandwidth_Hz = {float(acquisition.pixel_bandwidth_Hz)!r}",
             f"imaging_frequency_MHz = {float(acquisition.imaging_frequency_MHz)!r}"]
    if acquisition.readout_axis is not None:
        lines.append(f"readout = {_toml_string(acquisition.readout_axis)}")
    return "\n".join(lines) + "\n"


def _toml_string(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _write_points(path: Path, points: DisplacementPoints) -> None:
    header = list(POINTS_COLUMNS) + (["sigma_mm"] if points.sigma_mm is not None else [])
    columns = [points.position_mm, points.displacement_mm] + ([points.sigma_mm[:, None]] if points.sigma_mm is not None else [])
    with path.open("w", newline="", encoding="utf-8") as stream:
        writer = csv.writer(stream)
        writer.writerow(header)
        for row in np.hstack(columns):
            writer.writerow([repr(float(v)) for v in row])
