"""A volume case cut into slice cases, the first step of `calfit study VOLUME_CASE --out DIR`.

A volume case is a case folder whose unloaded and loaded images are each a 3D volume (a DICOM series folder
`unloaded/`, `loaded/`, or `unloaded.nii[.gz]`, `loaded.nii[.gz]`), with a [study] table in case.toml:

    [study]
    heights_mm = [204.0, 212.0]         # slice positions along the normal to study (or every_mm = 8.0)
    compression_heights_mm = { B = 204.0, B1 = 236.0, C = 284.0, D = 300.0 }   # optional, named in the report

    [garment]
    tension_N_per_mm = { heights_mm = [196.0, 300.0], values = [0.20, 0.14] }  # or one number for all heights

    [landmarks]
    deep_veins = [[54.3, 61.2, 196.0], [54.0, 60.9, 300.0]]   # a line along the leg: x, y (slice frame), height

A height is the position along the slices' normal (`imaging.volume.Volume.slice_positions_mm`), the number that
`[images] slice_position_mm` gives for a single slice. Cutting, in `slice_volume_case`:
1. both volumes are read and the loaded one is aligned rigidly on the bones in 3D (`imaging.align3d`): between
   the sessions the leg slides along its axis, turns and tilts;
2. each height takes the unloaded slice nearest it (within half a slice spacing; an unloaded slice is never
   resampled, so I0 keeps its texture), and the loaded volume is resampled on that slice's pixels through the
   motion (`align3d.resample_on_slice`, Keys' cubic convolution between slices): the two images of the slice case
   see the same tissue;
3. the skin's shift between neighbouring unloaded slices is measured (`skin_shift_px`): beyond a pixel the
   resampled loaded slice blends two outlines, and the slice is flagged too_coarse; a height that the loaded
   volume does not hold (the leg slid along its axis) is left out, with a warning;
4. the slice case gets the tension at its height (linear in the table; a height outside the table is refused),
   the landmarks at its height (each line interpolated linearly; a single point [x, y, z] belongs to the slice
   within half a spacing of z) and the volume case's [model] tables, and is written, whole or not at all, to
   DIR/slices/<name>-z<height>mm/ (`imaging.case.write_case_folder`, images as .npy with NaN where the loaded
   session has no voxel).
DIR/slices.json records the slices, their heights, the motion and the named heights; it is written last, so a
study stopped while cutting cuts again, and one stopped later reuses the slices.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tomllib

from ..case.folder import (
    DEFAULT_TENSION_REL_UNCERTAINTY,
    model_choice,
    write_case_folder,
)
from ..case.schema import TensionProfile, VolumeCaseToml, parse
from ..core.errors import CaseError, RunFolderError
from ..core.files import read_json, write_json

SLICES_JSON = "slices.json"
SLICES_FOLDER = "slices"
PIXEL_SIZE_RTOL = 0.01
MAX_SKIN_SHIFT_PX = 1.0   # beyond this shift of the skin between slices, a resampled loaded slice is flagged


@dataclass(frozen=True)
class VolumeCase:
    """What case.toml of a volume case says (module text), checked; the volumes are read by `slice_volume_case`."""

    folder: Path
    name: str
    unloaded: Path
    loaded: Path
    pixel_size_mm: tuple[float, float] | None
    heights_mm: tuple[float, ...] | None      # None: every_mm
    every_mm: float | None
    compression_heights_mm: dict[str, float]
    tension_heights_mm: tuple[float, ...]      # one entry: the same tension at every height
    tension_values: tuple[float, ...]
    tension_rel_uncertainty: float
    landmarks: dict[str, np.ndarray]           # name -> (n, 3) points x, y, height, by increasing height
    model_toml: str

    def tension_at(self, height_mm: float) -> float:
        """The garment tension at a height (linear between the table's heights)."""
        if len(self.tension_values) == 1:
            return self.tension_values[0]
        low, high = self.tension_heights_mm[0], self.tension_heights_mm[-1]
        if not low - 1e-6 <= height_mm <= high + 1e-6:
            raise CaseError(self.folder / "case.toml", f"[garment] tension_N_per_mm gives the tension from {low:g} to "
                            f"{high:g} mm, not at the slice at {height_mm:g} mm",
                            "extend its heights_mm and values to every studied height")
        return float(np.interp(height_mm, self.tension_heights_mm, self.tension_values))

    def landmarks_at(self, height_mm: float, half_spacing_mm: float) -> dict[str, tuple[float, float]]:
        """The landmarks of the slice at this height: each line interpolated in it, each point within half a slice
        spacing of it; the others are not in this slice."""
        found = {}
        for name, points in self.landmarks.items():
            heights = points[:, 2]
            if heights[0] - half_spacing_mm <= height_mm <= heights[-1] + half_spacing_mm:
                x = float(np.interp(height_mm, heights, points[:, 0]))
                y = float(np.interp(height_mm, heights, points[:, 1]))
                found[name] = (x, y)
        return found


@dataclass(frozen=True)
class SliceCase:
    """A slice case cut from a volume case."""

    folder: Path
    height_mm: float
    slice_index: int
    tension_N_per_mm: float

    def as_dict(self) -> dict:
        return {"folder": self.folder.name, "height_mm": self.height_mm, "slice_index": self.slice_index,
                "tension_N_per_mm": self.tension_N_per_mm}


def is_volume_case(folder: str | Path) -> bool:
    """A folder whose case.toml has a [study] table."""
    path = Path(folder) / "case.toml"
    if not path.is_file():
        return False
    try:
        return "study" in tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError):
        return False


def read_volume_case(folder: str | Path) -> VolumeCase:
    """Read and check case.toml of a volume case (`case.schema.VolumeCaseToml`) and find its two volumes; CaseError
    naming the file and the fix."""
    folder = Path(folder)
    path = folder / "case.toml"
    text = path.read_text(encoding="utf-8")
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CaseError(path, f"is not valid TOML ({exc})", "fix the syntax (tables in [brackets], key = value)") from exc
    settings = parse(path, text, raw, VolumeCaseToml)
    study = settings.study
    heights = tuple(sorted(study.heights_mm)) if study.heights_mm is not None else None
    tension = settings.garment.tension_N_per_mm
    if isinstance(tension, TensionProfile):
        order = np.argsort(tension.heights_mm)
        tension_heights = tuple(float(tension.heights_mm[i]) for i in order)
        tension_values = tuple(float(tension.values[i]) for i in order)
    else:
        tension_heights, tension_values = (math.nan,), (float(tension),)
    rel = settings.garment.tension_rel_uncertainty
    pixel_size = settings.case.pixel_size_mm
    model_choice(path, settings.model)   # each tissue's law made once here: a wrong constant stops the study now
    unloaded, loaded = _volume_path(folder, "unloaded"), _volume_path(folder, "loaded")
    if unloaded.is_dir() != loaded.is_dir():
        # A DICOM affine is in the patient's LPS frame, a NIfTI one usually in RAS: mixed, the two sessions' frames
        # would differ by a half turn that the alignment on the bones would have to find.
        raise CaseError(folder, f"holds the sessions in two formats ({unloaded.name} and {loaded.name})",
                        "export both as DICOM series or both as NIfTI volumes")
    return VolumeCase(folder=folder, name=settings.case.name or folder.name, unloaded=unloaded, loaded=loaded,
                      pixel_size_mm=tuple(map(float, pixel_size)) if pixel_size else None,
                      heights_mm=heights, every_mm=float(study.every_mm) if study.every_mm is not None else None,
                      compression_heights_mm={str(k): float(v) for k, v in study.compression_heights_mm.items()},
                      tension_heights_mm=tension_heights, tension_values=tension_values,
                      tension_rel_uncertainty=DEFAULT_TENSION_REL_UNCERTAINTY if rel is None else float(rel),
                      landmarks=_landmark_lines(path, settings.landmarks), model_toml=_model_tables(text))


def slice_volume_case(folder: str | Path, out: str | Path, report=None) -> tuple[list[SliceCase], dict]:
    """Cut the volume case into slice cases under out/slices (module text); returns them, by height, and the record
    written to out/slices.json. A record already there is reused when it was cut at the same heights."""
    from ..case.volume import read_volume
    from ..imaging.align3d import align_volumes_on_bones, resample_on_slice

    say = report or (lambda line: None)
    case = read_volume_case(folder)
    out = Path(out)
    record_path = out / SLICES_JSON
    unloaded = read_volume(case.unloaded)
    positions = unloaded.slice_positions_mm
    chosen = _chosen_slices(case, positions, unloaded.slice_spacing_mm)
    slices = [SliceCase(out / SLICES_FOLDER / _slice_name(case.name, positions[k]), float(positions[k]), int(k),
                        case.tension_at(float(positions[k]))) for k in chosen]
    if record_path.is_file():
        record = read_json(record_path, "calfit study")
        if record.get("requested") == [piece.folder.name for piece in slices]:
            kept = {entry["folder"] for entry in record["slices"]}
            slices = [piece for piece in slices if piece.folder.name in kept]
            say(f"{len(slices)} slices cut before, reused from {out / SLICES_FOLDER}")
            return slices, record
        raise RunFolderError(f"{out} holds slices cut at other heights ({record_path}); give the study another --out")
    _check_pixel_size(case, unloaded)
    loaded = read_volume(case.loaded)
    if loaded.shape[:2] != unloaded.shape[:2] or not np.allclose(loaded.pixel_size_mm, unloaded.pixel_size_mm,
                                                                rtol=PIXEL_SIZE_RTOL):
        raise CaseError(case.loaded, f"has {loaded.shape[0]}x{loaded.shape[1]} pixels of {_pair(loaded.pixel_size_mm)} mm "
                        f"but {case.unloaded.name} has {unloaded.shape[0]}x{unloaded.shape[1]} of "
                        f"{_pair(unloaded.pixel_size_mm)} mm", "acquire both sessions with the same matrix and field of view")
    say(f"volumes: {unloaded.shape[2]} unloaded slices at {positions[0]:.1f}-{positions[-1]:.1f} mm every "
        f"{unloaded.slice_spacing_mm:.2g} mm, {loaded.shape[2]} loaded; aligning the loaded volume on the bones")
    fat_shift_mm = volume_fat_shift_mm(unloaded)
    alignment = align_volumes_on_bones(unloaded, loaded, fat_shift_mm=fat_shift_mm)
    motion = alignment.motion
    masks: dict[int, np.ndarray] = {}
    slide = leg_slide(unloaded, alignment, [piece.slice_index for piece in slices], masks)
    say(f"the leg moved between the sessions: turned {alignment.turn_deg:.2f} deg, tilted {alignment.tilt_deg:.2f} deg, "
        f"slid {slide['slide_mm']:+.2f} ± {slide['slide_sd_mm']:.2f} mm along the leg (at the leg's centre, "
        f"{slide['height_mm']:.1f} mm)")
    shifts = {piece.slice_index: skin_shift_px(unloaded, piece.slice_index, masks) for piece in slices}
    coarse = [piece for piece in slices if shifts[piece.slice_index] > MAX_SKIN_SHIFT_PX]
    if coarse:
        say(f"warning: the skin moves by {max(shifts.values()):.1f} px between neighbouring slices (more than "
            f"{MAX_SKIN_SHIFT_PX:g} px at {', '.join(f'{p.height_mm:.0f}' for p in coarse)} mm): the loaded slices "
            "resampled there, between slices that show different outlines, carry edge errors above the DIC's noise; "
            f"acquire slices closer than {unloaded.slice_spacing_mm:.3g} mm")
    half = 0.5 * unloaded.slice_spacing_mm
    requested, left_out = [piece.folder.name for piece in slices], []
    for piece in list(slices):   # a slice left by a run stopped before slices.json is cut again, whole (overwrite)
        loaded_slice = resample_on_slice(loaded, unloaded, piece.slice_index, motion)
        unseen = float(np.mean(~np.isfinite(loaded_slice[leg_mask(unloaded, piece.slice_index, masks)])))
        if unseen > 0.0:
            # the leg slid along its axis between the sessions: the loaded volume does not reach this height
            say(f"warning: the slice at {piece.height_mm:.1f} mm is left out: the loaded volume does not hold "
                f"{100 * unseen:.0f} % of its leg (the leg slid {alignment.slide_mm:+.1f} mm between the sessions)")
            left_out.append({"height_mm": piece.height_mm, "leg_without_loaded_voxel": unseen})
            slices.remove(piece)
            continue
        write_case_folder(piece.folder, name=piece.folder.name, unloaded=unloaded.slice_image(piece.slice_index),
                          loaded=loaded_slice, pixel_size_mm=unloaded.pixel_size_mm,
                          tension_N_per_mm=piece.tension_N_per_mm, tension_rel_uncertainty=case.tension_rel_uncertainty,
                          landmarks=case.landmarks_at(piece.height_mm, half), images_as="npy",
                          model_toml=case.model_toml, overwrite=True, acquisition=unloaded.acquisition)
    if not slices:
        raise CaseError(case.loaded, "does not hold the leg at any studied height once aligned on the bones",
                        "study heights that both sessions imaged")
    per_slice = {entry["slice_index"]: entry for entry in slide["slices"]}
    record = {"volume_case": str(case.folder.resolve()), "name": case.name,
              "slices": [{**piece.as_dict(), "skin_shift_px": shifts[piece.slice_index],
                          "too_coarse": shifts[piece.slice_index] > MAX_SKIN_SHIFT_PX,
                          "slide_mm": per_slice[piece.slice_index]["slide_mm"],
                          "slide_sd_mm": per_slice[piece.slice_index]["slide_sd_mm"],
                          "leg_centre_mm": per_slice[piece.slice_index]["leg_centre_mm"]} for piece in slices],
              "slide": {key: value for key, value in slide.items() if key != "slices"},
              "max_skin_shift_px": MAX_SKIN_SHIFT_PX, "requested": requested, "left_out": left_out,
              "slice_spacing_mm": unloaded.slice_spacing_mm, "pixel_size_mm": list(unloaded.pixel_size_mm),
              "compression_heights_mm": case.compression_heights_mm,
              "tension_rel_uncertainty": case.tension_rel_uncertainty,
              "motion": motion.as_dict(), "alignment": _alignment_record(alignment)}
    write_json(record_path, record)
    say(f"cut {len(slices)} slices into {out / SLICES_FOLDER}")
    return slices, record


def volume_fat_shift_mm(volume) -> float:
    """The size of the fat's chemical shift on the volume's images (mm; 0 when not significant), read as a slice
    case's is (across the fat/muscle interface snapped to the image's edges, `imaging.chemical_shift.fat_shift`, the
    size the series' DICOM header gives when it does) on the slice nearest the middle that segments: the bones' segmentation
    needs it (`align3d._find_bones`)."""
    from ..core.errors import ImagingError
    from ..imaging.chemical_shift import fat_shift
    from ..imaging.segment import segment_t1
    from ..meshing import fat_muscle_normals, tissue_curves

    count = volume.shape[2]
    for k in sorted(range(count), key=lambda n: abs(n - (count - 1) / 2)):
        image = volume.slice_image(k)
        if not np.isfinite(image).all():
            continue
        try:
            curves = tissue_curves(segment_t1(image, volume.pixel_size_mm), volume.pixel_size_mm, image=image)
            found = fat_shift(image, *fat_muscle_normals(curves), volume.pixel_size_mm, volume.acquisition)
        except ImagingError:
            continue
        return float(np.hypot(*found.shift_mm)) if found is not None and found.significant else 0.0
    return 0.0


def leg_slide(volume, alignment, studied: list[int], masks: dict | None = None) -> dict:
    """How far the leg slid along itself between the sessions, as the 3D alignment found it: the motion's
    displacement along the slices' normal at the leg's centre (the centroid of the unloaded slice's leg), with
    its standard error (`align3d.VolumeAlignment.slide_sd_at`), at the middle studied slice and at each studied
    slice. Not the alignment's own translation, which is the bones' centre's: when the leg tilts, every point
    slides by a different amount, by the tilt times its distance from the tilt's axis, and the bones lie 20-40 mm
    from the leg's centre (docs/method/studies.md, "The slide along the leg")."""
    entries = []
    for k in studied:
        leg = leg_mask(volume, k, masks)
        rows, columns = np.nonzero(leg)
        centre = volume.affine[:3] @ np.array([rows.mean(), columns.mean(), k, 1.0])
        entries.append({"slice_index": int(k), "height_mm": float(volume.slice_positions_mm[k]),
                        "leg_centre_mm": centre.tolist(), "slide_mm": float(alignment.slide_at(centre)),
                        "slide_sd_mm": float(alignment.slide_sd_at(centre))})
    middle = entries[len(entries) // 2]
    bones = np.asarray(alignment.motion.centre_mm, float)
    return {"slide_mm": middle["slide_mm"], "slide_sd_mm": middle["slide_sd_mm"], "height_mm": middle["height_mm"],
            "at": "the leg's centre (centroid of the unloaded slice's leg) at the middle studied slice",
            "bones_centre_slide_mm": float(alignment.slide_at(bones)),
            "bones_centre_slide_sd_mm": float(alignment.slide_sd_at(bones)),
            "tilt_deg": float(alignment.tilt_deg), "jackknife_refits": len(alignment.jackknife),
            "fat_shift_mm": float(alignment.fat_shift_mm), "slices": entries}


def skin_shift_px(volume, k: int, masks: dict | None = None) -> float:
    """How far the skin of slice k lies from its neighbours' (pixels, the mean over its outline, the larger of the
    two neighbours): what a loaded slice resampled between slices there blends. The loaded volume is resampled
    between its slices (`align3d.resample_on_slice`); where the outline moves by more than a pixel from one slice to
    the next, the blend is no longer one edge but two, and the DIC sees an error that grows with the shift (on the 3D
    phantom leg with 8 mm slices: misfit 1.35 x the floor at 0.3 px, 1.8 at 1.1 px, 3.4 at 3.8 px)."""
    from scipy import ndimage

    def outline(index: int) -> np.ndarray:
        leg = leg_mask(volume, index, masks)
        return leg & ~ndimage.binary_erosion(leg)

    here = outline(k)
    distances = [ndimage.distance_transform_edt(~outline(n))[here].mean()
                 for n in (k - 1, k + 1) if 0 <= n < volume.shape[2]]
    return float(max(distances)) if distances else 0.0


def leg_mask(volume, k: int, masks: dict | None = None) -> np.ndarray:
    """The leg (every tissue) of slice k, segmented (`imaging.segment.segment_t1`); kept in `masks` when given."""
    from ..core.errors import ImagingError
    from ..imaging.segment import segment_t1

    masks = {} if masks is None else masks
    if k not in masks:
        image = volume.slice_image(k)
        try:
            masks[k] = segment_t1(image, volume.pixel_size_mm) > 0
        except ImagingError:   # no bone found in this slice: its leg is still the leg (`leg_outline`)
            masks[k] = leg_outline(image, volume.pixel_size_mm)
    return masks[k]


def leg_outline(image: np.ndarray, pixel_size_mm, smoothing_mm: float = 0.36) -> np.ndarray:
    """The leg of a slice whose bones `segment_t1` does not find (a slice past the bones' ends, or a thin cortex
    it misses): the largest region brighter than the darkest of three Otsu classes, holes filled, as
    `segment_t1` takes it before its bones."""
    from scipy import ndimage
    from skimage import filters

    from ..imaging.segment import largest_component

    finite = np.isfinite(image)
    values = np.where(finite, image, np.nanmin(image) if finite.any() else 0.0)
    smooth = ndimage.gaussian_filter(values, smoothing_mm / min(pixel_size_mm))
    dark, _ = filters.threshold_multiotsu(smooth, classes=3)
    return ndimage.binary_fill_holes(largest_component(smooth > dark))


def _chosen_slices(case: VolumeCase, positions: np.ndarray, spacing: float) -> list[int]:
    """The unloaded slice of each studied height (module text)."""
    path = case.folder / "case.toml"
    if case.every_mm is not None:
        if case.every_mm < spacing * (1 - 1e-6):
            raise CaseError(path, f"[study] every_mm = {case.every_mm:g} is finer than the slices ({spacing:.3g} mm apart)",
                            f"give every_mm >= {spacing:.3g}")
        wanted = np.arange(positions[0], positions[-1] + 1e-6, case.every_mm)
    else:
        wanted = np.asarray(case.heights_mm)
    chosen = []
    for height in wanted:
        k = int(np.argmin(np.abs(positions - height)))
        if abs(positions[k] - height) > 0.5 * spacing + 1e-6:
            raise CaseError(path, f"[study] height {height:g} mm has no unloaded slice within half a spacing "
                            f"(slices at {positions[0]:.1f}-{positions[-1]:.1f} mm every {spacing:.3g} mm)",
                            "choose heights inside the unloaded volume")
        if k in chosen:
            raise CaseError(path, f"[study] heights {height:g} mm and another fall on the same slice at "
                            f"{positions[k]:.1f} mm", f"give heights at least {spacing:.3g} mm apart")
        chosen.append(k)
    return chosen


def _slice_name(name: str, height_mm: float) -> str:
    return f"{re.sub(r'[^A-Za-z0-9_.-]+', '-', name)}-z{height_mm:.1f}mm"


def _volume_path(folder: Path, role: str) -> Path:
    for candidate in (folder / role, folder / f"{role}.nii.gz", folder / f"{role}.nii"):
        if candidate.exists():
            return candidate
    raise CaseError(folder, f"has no {role} volume",
                    f"put the {role} session in {role}/ (a DICOM series) or {role}.nii.gz (a 3D NIfTI)")


def _landmark_lines(path: Path, table: dict) -> dict[str, np.ndarray]:
    """The [landmarks] of a volume case (points [x, y, height] or lines of them, by the schema), by height."""
    lines = {}
    for name, value in table.items():
        points = [value] if not isinstance(value[0], list) else value
        array = np.array(points, float)
        array = array[np.argsort(array[:, 2])]
        if np.any(np.diff(array[:, 2]) <= 0):
            raise CaseError(path, f"landmark '{name}' has two points at one height", "keep one point per height")
        lines[name] = array
    return lines


def _model_tables(text: str) -> str:
    """The lines of case.toml's [model] and [model.<tissue>] tables, as they are (they go to every slice case)."""
    kept, inside = [], False
    for line in text.splitlines():
        header = re.match(r"\s*\[\[?\s*([A-Za-z0-9_.\"-]+)\s*\]\]?", line)
        if header:
            inside = header.group(1).split(".")[0] == "model"
        if inside:
            kept.append(line)
    return "\n".join(kept)


def _check_pixel_size(case: VolumeCase, unloaded) -> None:
    if case.pixel_size_mm is not None and not np.allclose(case.pixel_size_mm, unloaded.pixel_size_mm, rtol=PIXEL_SIZE_RTOL):
        raise CaseError(case.folder / "case.toml", f"[case] pixel_size_mm = {list(case.pixel_size_mm)} disagrees with "
                        f"the {_pair(unloaded.pixel_size_mm)} mm of {case.unloaded.name}'s header",
                        "remove pixel_size_mm (the header's is used) or correct it")


def _alignment_record(alignment) -> dict:
    values = {}
    for key, value in vars(alignment).items():
        if key in ("motion", "jackknife"):
            continue
        if isinstance(value, (int, float, str, bool)) or value is None:
            values[key] = value
        elif isinstance(value, (list, tuple, np.ndarray)):
            values[key] = np.asarray(value).tolist()
    return values


def _pair(values) -> str:
    return f"{float(values[0]):.3g} x {float(values[1]):.3g}"


