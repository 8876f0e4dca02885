"""Case folders of the k-space phantom: what a user brings, and the truth kept apart.

`make_kspace_case` solves the 3D leg (`mechanics3d`, CalculiX), images one slice in two sessions as a scanner does
(`acquisition`) and writes:

- the case folder, what a user brings (docs/design.md, "The case folder"): case.toml ([case] name and pixel_size_mm,
  which is omitted for DICOM since the files carry it; [garment] tension_N_per_mm and tension_rel_uncertainty;
  [landmarks] of the leg at the slice's height), unloaded.png and loaded.png (16-bit, fat ~ intensity_scale) or
  unloaded.dcm and loaded.dcm with their geometry tags; no labels and no points unless asked;
- the truth folder (default the sibling `<case>.truth`): truth.json (the leg, its appearance, the scanner, the
  motion, the slice and its profile, the seeds, the mechanics and its timings), displacement_mm.npy (2, H, W): the
  in-plane displacement (mm, image frame) of the material under each pixel centre of I0 at the slice's centre
  height, relative to the bones (clamped), uz_mm.npy (H, W) its axial part, labels_unloaded.png (the exact labels
  at the slice's centre height), clean_unloaded.npy and clean_loaded.npy (noise-free magnitude images, fat ~ 1),
  coil.npy (the coil's complex sensitivity at the pixel centres), and parameters.json in the layout of
  `study.make_phantom_case` ("parameters_kPa" keyed C10_fat, C10_muscle, Kv_fat, Kv_muscle; "tension_N_per_mm";
  "effects" in the catalog's terms where it has them; "laws"; "engine_mesh"; ...).

`write_kspace_volume_case` images a stack of slices instead (every slice with the same profile) and writes two DICOM
series (unloaded/ and loaded/) with case.toml's [study] table as `phantom.volume.write_volume_case` writes it, the
truth per studied height (displacement_<h>mm.npy, uz_<h>mm.npy, labels_<h>mm.png) and the true motion, both as the
leg's `LegMotion` and as the patient-frame `imaging.volume.RigidMotion3D` that `imaging.align3d` estimates.

Both folders are staged in temporary siblings and renamed into place only when complete.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ...case._formats import write_png16
from ...case.folder import (
    DEFAULT_TENSION_REL_UNCERTAINTY,
    DisplacementPoints,
    write_case_folder,
)
from ...core.files import staged_folders
from ...core.frame import pixel_centres_mm
from ..mri.anatomy import LegShape
from .acquisition import (
    AcquiredImage,
    DisplacementGrid,
    LegMotion,
    Scanner,
    grid_heights,
    material_points,
)
from .appearance3d import Appearance3D, KspaceContrast
from .leg3d import Leg3D, LegAlongHeight
from .mechanics3d import (
    DEFAULT_SECTION_ELEMENTS,
    FINE_SECTION_ELEMENTS,
    LEG_PARAMETERS,
    HiddenEffects3D,
    Layering,
    LegSolution3D,
    leg_mesh_3d,
    solve_leg3d,
)

PARAMETERS_FILE = "parameters.json"      # the name `study.make_phantom_case` gives it
LEG_MARGIN_MM = 3.0                       # the skin stays this far inside the field of view in both sessions
FINE_LAYERING = Layering(fine_mm=4.0, coarse_mm=16.0, growth=1.4)
TABLE2_CENTRAL_KPA = (4.5, 11.2, 106.0, 69.5)


@dataclass
class KspacePhantom:
    """The 3D leg, its appearance and the scanner that images it; `image` makes one session's image of a slice."""

    leg: Leg3D = field(default_factory=Leg3D)
    appearance: Appearance3D | None = None
    scanner: Scanner = field(default_factory=Scanner)

    def __post_init__(self):
        if self.appearance is None:
            self.appearance = Appearance3D(self.leg)
        elif self.appearance.leg is not self.leg:
            raise ValueError("the appearance must be drawn on the phantom's own leg; build it as Appearance3D(leg)")

    def signals(self, motion: LegMotion | None = None, displacement=None):
        """signals(x, y, z, sample_mm) of one session: the unloaded leg (no motion, no displacement), or the
        leg moved by `motion` and deformed by `displacement` (callable (x, y, z) -> (3, ...), e.g. a
        `DisplacementGrid`)."""
        if motion is None and displacement is None:
            return self.appearance.signals
        motion = motion if motion is not None else LegMotion(centre_mm=(0.0, 0.0, 0.0))
        if motion.centre_mm is None:
            raise ValueError("a session's motion needs its centre (LegMotion.about((x, y, z)))")
        deformation = displacement if displacement is not None else (lambda x, y, z: np.zeros((3,) + np.shape(x)))

        def loaded(x, y, z, sample_mm):
            X = material_points(np.stack([x, y, z]), motion, deformation, self.appearance.in_air)
            return self.appearance.signals(X[0], X[1], X[2], sample_mm)

        return loaded

    def image(self, height_mm: float, noise_seed: int | None, motion: LegMotion | None = None,
              displacement=None) -> AcquiredImage:
        return self.scanner.acquire(self.signals(motion, displacement), height_mm, noise_seed)

    def check_in_view(self, heights_mm: Sequence[float], motion: LegMotion) -> None:
        """ValueError when the skin comes within LEG_MARGIN_MM of the field of view's edge in either session."""
        width, height = self.scanner.extent_mm
        offsets, _ = self.scanner.subplanes()
        for z in heights_mm:
            for offset in (offsets[0], 0.0, offsets[-1]):
                skin = self.leg.skin_polygon(z + offset, 360)
                points = np.vstack([skin.T, np.full(len(skin), z + offset)])
                for session, where in (("unloaded", points), ("loaded", motion.apply(points))):
                    x, y = where[0], where[1]
                    if (x.min() < LEG_MARGIN_MM or y.min() < LEG_MARGIN_MM or x.max() > width - LEG_MARGIN_MM
                            or y.max() > height - LEG_MARGIN_MM):
                        raise ValueError(f"the leg at {z + offset:g} mm comes within {LEG_MARGIN_MM} mm of the field "
                                         f"of view's edge in the {session} session; enlarge the matrix or the pixels, "
                                         "or centre the leg (LegShape.centre_mm)")

    def description(self) -> dict:
        return {"renderer": "kspace3d", "leg": self.leg.description(), "appearance": self.appearance.description(),
                "scanner": self.scanner.description()}


def build_phantom(*, pixel_size_mm=0.4, image_shape=(384, 384), chemical_shift_px: float = 1.4, readout: str = "x",
                  slice_thickness_mm: float = 4.0, noise_sigma: float = 0.026, vendor_filter: str | None = None,
                  oversampling: int = 3, intensity_scale: float = 20000.0, shape: LegShape | None = None,
                  along: LegAlongHeight | None = None, appearance_seed: int = 0, contrast: KspaceContrast | None = None,
                  coil_seed: int = 0) -> KspacePhantom:
    """A `KspacePhantom` with the leg centred in the field of view unless `shape` places it."""
    pixel = _pixel_pair(pixel_size_mm)
    scanner = Scanner(tuple(int(n) for n in image_shape), pixel, oversampling, slice_thickness_mm,
                      chemical_shift_px=chemical_shift_px, readout=readout, noise_sigma=noise_sigma,
                      vendor_filter=vendor_filter, coil_seed=coil_seed, intensity_scale=intensity_scale)
    width, height = scanner.extent_mm
    leg = Leg3D(shape or LegShape(centre_mm=(width / 2.0, height / 2.0)), along or LegAlongHeight())
    return KspacePhantom(leg, Appearance3D(leg, contrast or KspaceContrast(), appearance_seed), scanner)


def solve_truth(phantom: KspacePhantom, theta_kPa, tension_N_per_mm: float, *, heights_mm: Sequence[float],
                motion: LegMotion, effects: HiddenEffects3D, garment_law: str = "unloaded", fine: bool = False,
                n_section_elements: int | None = None, layering: Layering | None = None,
                segment_mm: tuple[float, float] = (0.0, 140.0)) -> LegSolution3D:
    """The 3D truth of a case: the segment meshed finely around every height the two sessions' slabs see."""
    scanner = phantom.scanner
    low, high = grid_heights(scanner, heights_mm, motion, margin_mm=1.0)
    lo0, hi0 = grid_heights(scanner, heights_mm, LegMotion(centre_mm=motion.centre_mm), margin_mm=1.0)
    low, high = min(low, lo0), max(high, hi0)
    base = layering or (FINE_LAYERING if fine else Layering())
    base = dataclasses.replace(base, bottom_mm=segment_mm[0], top_mm=segment_mm[1])
    mesh = leg_mesh_3d(phantom.leg, scanner.extent_mm, focus_mm=[low, high], band_mm=0.0, layering=base,
                       n_elements=n_section_elements or (FINE_SECTION_ELEMENTS if fine else DEFAULT_SECTION_ELEMENTS),
                       compartments=effects.stiffer_compartment is not None)
    return solve_leg3d(mesh, theta_kPa, tension_N_per_mm, garment_law=garment_law, effects=effects)


def make_kspace_case(folder, truth_folder=None, *, theta_kPa: Sequence[float] = TABLE2_CENTRAL_KPA,
                     tension_N_per_mm: float = 0.16, effects: dict | None = None, motion: LegMotion | None = None,
                     garment_law: str = "unloaded", noise_seeds: tuple[int, int] = (0, 1),
                     slice_height_mm: float = 70.0, pixel_size_mm=0.4, image_shape=(384, 384),
                     chemical_shift_px: float = 1.4, readout: str = "x", slice_thickness_mm: float = 4.0,
                     noise_sigma: float = 0.026, vendor_filter: str | None = None, oversampling: int = 3,
                     dicom: bool = False, labels: str | None = None, points_spacing_mm: float | None = None,
                     points_sigma_mm: float = 0.02, fine: bool = False, n_section_elements: int | None = None,
                     shape: LegShape | None = None, along: LegAlongHeight | None = None, appearance_seed: int = 0,
                     name: str = "kspace-calf", tension_rel_uncertainty: float = DEFAULT_TENSION_REL_UNCERTAINTY,
                     phantom: KspacePhantom | None = None, solution: LegSolution3D | None = None,
                     overwrite: bool = False) -> tuple[Path, Path]:
    """Write one slice's case folder and its truth folder (module text). Returns (case folder, truth folder).

    theta_kPa: (C10_fat, C10_muscle, Kv_fat, Kv_muscle); effects: hidden effects of the truth
    (`mechanics3d.HiddenEffects3D.from_dict`: drainage, tension_profile, stiffer_muscle, bone_motion); motion: the
    leg's rigid motion between the sessions (`acquisition.LegMotion`, about the leg centre at the slice's height
    unless its centre is given); labels: None, "truth" (exact labels at the slice's centre height) or
    "compartments" (the muscle compartments as labels 4-7); points_spacing_mm: write points.csv, the true
    displacement on a grid of that spacing plus Gaussian noise of points_sigma_mm. phantom and solution: a
    phantom and a solved truth to reuse (the solution must have been solved for this slice and motion)."""
    started = time.perf_counter()
    folder, truth_folder = _targets(folder, truth_folder, overwrite)
    if labels not in (None, "truth", "compartments"):
        raise ValueError("labels must be None, 'truth' or 'compartments'")
    phantom = phantom or build_phantom(pixel_size_mm=pixel_size_mm, image_shape=image_shape,
                                       chemical_shift_px=chemical_shift_px, readout=readout,
                                       slice_thickness_mm=slice_thickness_mm, noise_sigma=noise_sigma,
                                       vendor_filter=vendor_filter, oversampling=oversampling, shape=shape, along=along,
                                       appearance_seed=appearance_seed)
    scanner, leg = phantom.scanner, phantom.leg
    motion = _centred(motion, leg, slice_height_mm)
    phantom.check_in_view([slice_height_mm], motion)
    hidden = HiddenEffects3D.from_dict(effects)
    if solution is None:
        solution = solve_truth(phantom, theta_kPa, tension_N_per_mm, heights_mm=[slice_height_mm], motion=motion,
                               effects=hidden, garment_law=garment_law, fine=fine,
                               n_section_elements=n_section_elements)
    elif solution.mesh.leg is not leg:
        raise ValueError("the solution was solved on another leg; pass the phantom it was solved for")
    solved = time.perf_counter()
    grid = _displacement_grid(phantom, solution, [slice_height_mm], motion)
    unloaded = phantom.image(slice_height_mm, noise_seeds[0])
    loaded = phantom.image(slice_height_mm, noise_seeds[1], motion, grid)
    rendered = time.perf_counter()

    field_3d = solution.slice_field(slice_height_mm, scanner.image_shape, scanner.pixel_size_mm)
    x, y = pixel_centres_mm(scanner.image_shape, scanner.pixel_size_mm)
    true_labels = leg.labels_at(x, y, np.full(x.shape, slice_height_mm))
    case_labels = {None: None, "truth": true_labels,
                   "compartments": leg.labels_at(x, y, np.full(x.shape, slice_height_mm), compartments=True)}[labels]
    points = _grid_points(field_3d[:2], true_labels, scanner, points_spacing_mm, points_sigma_mm, noise_seeds[1]) \
        if points_spacing_mm else None
    landmarks = leg.landmarks_at(slice_height_mm)
    record = {"case_folder": str(folder), **phantom.description(), "slice_height_mm": float(slice_height_mm),
              "noise_seeds": list(map(int, noise_seeds)), "motion": motion.as_dict(),
              "patient_motion": motion.patient_motion(scanner.pixel_size_mm).as_dict(),
              "mechanics": solution.description(), "landmarks": landmarks, "labels_in_case": labels,
              "format": "dicom" if dicom else "png", "files": _image_names(dicom),
              "displacement_file": "displacement_mm.npy", "uz_file": "uz_mm.npy",
              "conventions": CONVENTIONS,
              "timing_s": {"solve": round(solved - started, 2), "render": round(rendered - solved, 2)}}
    parameters = _parameters(solution, hidden)

    with staged_folders(truth_folder) as (staging,):
        _write_json(staging / "truth.json", record)
        _write_json(staging / PARAMETERS_FILE, parameters)
        np.save(staging / "displacement_mm.npy", np.ascontiguousarray(field_3d[:2]))
        np.save(staging / "uz_mm.npy", np.ascontiguousarray(field_3d[2]))
        write_png16(staging / "labels_unloaded.png", true_labels.astype(np.uint8))
        np.save(staging / "clean_unloaded.npy", np.abs(unloaded.clean))
        np.save(staging / "clean_loaded.npy", np.abs(loaded.clean))
        np.save(staging / "coil.npy", scanner.coil(x, y, slice_height_mm))
        images = (scanner.stored(unloaded.magnitude), scanner.stored(loaded.magnitude))
        if dicom:
            _write_dicom_case(folder, name, images, scanner, slice_height_mm, tension_N_per_mm,
                              tension_rel_uncertainty, landmarks, case_labels, points, overwrite)
        else:
            write_case_folder(folder, name=name, unloaded=images[0], loaded=images[1],
                              pixel_size_mm=scanner.pixel_size_mm, tension_N_per_mm=tension_N_per_mm,
                              tension_rel_uncertainty=tension_rel_uncertainty, labels=case_labels, points=points,
                              landmarks=landmarks, overwrite=overwrite)
    return folder, truth_folder


def write_kspace_volume_case(folder, truth_folder=None, *, heights_mm: Sequence[float] | None = None,
                             studied: Sequence[float] | None = None,
                             theta_kPa: Sequence[float] = TABLE2_CENTRAL_KPA, tension_N_per_mm: float = 0.16,
                             effects: dict | None = None, motion: LegMotion | None = None,
                             garment_law: str = "unloaded", noise_seed: int = 0, pixel_size_mm=0.4,
                             image_shape=(384, 384), chemical_shift_px: float = 1.4, readout: str = "x",
                             slice_thickness_mm: float = 4.0, noise_sigma: float = 0.026,
                             vendor_filter: str | None = None, oversampling: int = 3, fine: bool = False,
                             n_section_elements: int | None = None, shape: LegShape | None = None,
                             along: LegAlongHeight | None = None, appearance_seed: int = 0,
                             name: str = "kspace-leg", tension_rel_uncertainty: float = DEFAULT_TENSION_REL_UNCERTAINTY,
                             phantom: KspacePhantom | None = None, overwrite: bool = False) -> tuple[Path, Path]:
    """Write a volume case (unloaded/ and loaded/ DICOM series, case.toml with [study]) and its truth folder
    (module text). heights_mm: the slices' heights, evenly spaced (default 16 slices 3 mm apart about the reference
    height); studied: the heights identified (default all but the first two and the last two); motion: the leg's
    rigid motion (default: a 3 mm axial slide towards the knee with a turn of 2 degrees, a tilt of 1 degree and a
    shift of 1.5 mm, about the leg centre at the middle height); slice k's noise seeds are 10000 noise_seed + k
    (unloaded) and 10000 noise_seed + 5000 + k (loaded)."""
    from ..volume import COMPRESSION_POINTS, HeightProfile, _case_toml, height_tag

    started = time.perf_counter()
    folder, truth_folder = _targets(folder, truth_folder, overwrite)
    phantom = phantom or build_phantom(pixel_size_mm=pixel_size_mm, image_shape=image_shape,
                                       chemical_shift_px=chemical_shift_px, readout=readout,
                                       slice_thickness_mm=slice_thickness_mm, noise_sigma=noise_sigma,
                                       vendor_filter=vendor_filter, oversampling=oversampling, shape=shape, along=along,
                                       appearance_seed=appearance_seed)
    scanner, leg = phantom.scanner, phantom.leg
    z_ref = leg.along.reference_height_mm
    heights = np.asarray(heights_mm if heights_mm is not None else z_ref + 3.0 * (np.arange(16) - 7.5), float)
    if len(heights) < 3 or not np.allclose(np.diff(heights), heights[1] - heights[0]) or heights[1] <= heights[0]:
        raise ValueError(f"the volume's heights must be at least three, increasing and evenly spaced: {list(heights)}")
    studied = [float(h) for h in (heights[2:-2] if studied is None else studied)]
    if not studied or any(not np.isclose(heights, h).any() for h in studied):
        raise ValueError(f"the studied heights {studied} must be some of the volume's heights {list(heights)}")
    middle = float(0.5 * (heights[0] + heights[-1]))
    motion = _centred(motion if motion is not None else DEFAULT_VOLUME_MOTION, leg, middle)
    phantom.check_in_view(list(heights), motion)
    hidden = HiddenEffects3D.from_dict(effects)
    solution = solve_truth(phantom, theta_kPa, tension_N_per_mm, heights_mm=list(heights), motion=motion,
                           effects=hidden, garment_law=garment_law, fine=fine, n_section_elements=n_section_elements)
    solved = time.perf_counter()
    grid = _displacement_grid(phantom, solution, list(heights), motion)
    seeds = {"unloaded": [10000 * noise_seed + k for k in range(len(heights))],
             "loaded": [10000 * noise_seed + 5000 + k for k in range(len(heights))]}
    unloaded = [scanner.stored(phantom.image(h, s).magnitude) for h, s in zip(heights, seeds["unloaded"])]
    loaded = [scanner.stored(phantom.image(h, s, motion, grid).magnitude) for h, s in zip(heights, seeds["loaded"])]
    rendered = time.perf_counter()

    x, y = pixel_centres_mm(scanner.image_shape, scanner.pixel_size_mm)
    slices = []
    fields = {}
    for k, height in enumerate(heights):
        entry = {"height_mm": float(height), "studied": any(np.isclose(height, h) for h in studied),
                 "noise_seeds": {role: seeds[role][k] for role in seeds}, "landmarks": leg.landmarks_at(float(height))}
        if entry["studied"]:
            tag = height_tag(float(height))
            entry.update(displacement_file=f"displacement_{tag}mm.npy", uz_file=f"uz_{tag}mm.npy",
                         labels_file=f"labels_{tag}mm.png")
            fields[k] = solution.slice_field(float(height), scanner.image_shape, scanner.pixel_size_mm)
            entry["max_displacement_mm"] = float(np.abs(fields[k][:2]).max())
        slices.append(entry)
    record = {"case_folder": str(folder), **phantom.description(), "heights_mm": heights.tolist(),
              "studied_heights_mm": studied, "slice_spacing_mm": float(heights[1] - heights[0]),
              "noise_seed": noise_seed, "motion": motion.as_dict(),
              "patient_motion": motion.patient_motion(scanner.pixel_size_mm).as_dict(),
              "mechanics": solution.description(), "slices": slices, "conventions": CONVENTIONS,
              "timing_s": {"solve": round(solved - started, 2), "render": round(rendered - solved, 2)}}
    parameters = _parameters(solution, hidden)
    named = _compression_heights(studied, z_ref)
    tension = HeightProfile((float(heights[0]), float(heights[-1])), (float(tension_N_per_mm), float(tension_N_per_mm)))
    case_toml = _case_toml(name, scanner.pixel_size_mm, tension, tension_rel_uncertainty, studied,
                           {key: named[key] for key in COMPRESSION_POINTS},
                           [(float(h), leg.landmarks_at(float(h))) for h in heights])

    with staged_folders(truth_folder, folder) as (truth_staging, case_staging):
        from .dicom import new_identities, write_dicom_slice

        _write_json(truth_staging / "truth.json", record)
        _write_json(truth_staging / PARAMETERS_FILE, parameters)
        for k, entry in enumerate(slices):
            if entry["studied"]:
                np.save(truth_staging / entry["displacement_file"], np.ascontiguousarray(fields[k][:2]))
                np.save(truth_staging / entry["uz_file"], np.ascontiguousarray(fields[k][2]))
                write_png16(truth_staging / entry["labels_file"],
                            leg.labels_at(x, y, np.full(x.shape, entry["height_mm"])).astype(np.uint8))
        spacing = float(heights[1] - heights[0])
        for identity, role, stack in zip(new_identities(("unloaded", "loaded"), name), ("unloaded", "loaded"),
                                         (unloaded, loaded)):
            (case_staging / role).mkdir()
            for k, (height, image) in enumerate(zip(heights, stack)):
                write_dicom_slice(case_staging / role / f"IM{k + 1:04d}.dcm", image,
                                  pixel_size_mm=scanner.pixel_size_mm,
                                  height_mm=float(height), slice_thickness_mm=scanner.slice_thickness_mm,
                                  identity=identity, instance=k + 1, spacing_mm=spacing,
                                  chemical_shift_px=scanner.chemical_shift_px, readout=scanner.readout)
        (case_staging / "case.toml").write_text(case_toml, encoding="utf-8")
    return folder, truth_folder


# Between the two sessions of a volume: 3 mm along the leg towards the knee, a turn and a tilt, a shift across.
DEFAULT_VOLUME_MOTION = LegMotion(turn_deg=2.0, tilt_deg=1.0, tilt_axis_deg=30.0, shift_mm=(1.5, -1.0), slide_mm=3.0)

CONVENTIONS = {
    "frame": "image frame of I0: mm from the top-left pixel corner, x to the right (columns), y downwards (rows); "
             "z = height along the leg (towards the knee), the slices' normal; DICOM patient frame = image frame "
             "less half a pixel in x and y, patient z = z",
    "motion": "a bone-fixed point p0 (session 0, scanner x, y, z mm) is at p1 = c + R (p0 - c) + t in session 1, "
              "R = Rz(turn_deg) Raxis(tilt_deg about the in-plane axis at tilt_axis_deg), angles about +z in the "
              "image frame's numbers (a positive turn is clockwise on screen), t = (shift_mm, slide_mm); the "
              "scanner's slices stay in place",
    "displacement": "u of the material under each pixel centre of I0 at the slice's centre height, relative to the "
                    "bones (clamped): the garment's deformation only, no rigid motion; ux, uy image frame, uz along +z",
    "truth_units": "kPa (decks: MPa = kPa/1000, mm, N; NEO HOOKE with D1 = 1/Kv)",
    "noise": "complex Gaussian in k-space, sigma = noise_sigma x the fat signal per channel in the image after the "
             "vendor filter; magnitude image: Rician",
    "coil": "complex sensitivity fixed to the scanner, magnitude 1 +- coil_amplitude over the leg, a smooth phase",
    "intensity_scale": "stored value of a fat signal of 1 (before the coil and the noise)",
    "tension_profile": "T(theta) = T (1 + a cos(theta - theta0)), theta = atan2(y - cy, x - cx) in the image frame "
                       "about the leg centre at the face's height (calfit-fe's angle: a1 = a cos theta0, "
                       "b1 = a sin theta0)",
}


def _targets(folder, truth_folder, overwrite: bool) -> tuple[Path, Path]:
    folder = Path(folder)
    truth_folder = Path(truth_folder) if truth_folder is not None else folder.with_name(folder.name + ".truth")
    for target in (folder, truth_folder):
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} already exists; choose another folder or pass overwrite=True")
    return folder, truth_folder


def _pixel_pair(pixel_size_mm) -> tuple[float, float]:
    values = np.broadcast_to(np.asarray(pixel_size_mm, float), (2,))
    if np.any(values <= 0):
        raise ValueError(f"pixel_size_mm must be positive, got {pixel_size_mm}")
    return float(values[0]), float(values[1])


def _centred(motion: LegMotion | None, leg: Leg3D, height_mm: float) -> LegMotion:
    """The motion about its own centre, or about the leg centre at that height when it has none."""
    motion = motion or LegMotion()
    if motion.centre_mm is not None:
        return motion
    cx, cy = leg.centre_mm(height_mm)
    return motion.about((float(cx), float(cy), float(height_mm)))


def _displacement_grid(phantom: KspacePhantom, solution: LegSolution3D, heights_mm, motion: LegMotion):
    """The truth on a grid of half a pixel over the heights the loaded session's slabs see."""
    scanner = phantom.scanner
    return DisplacementGrid.sample(solution.at, scanner.extent_mm, grid_heights(scanner, heights_mm, motion),
                                   0.5 * min(scanner.pixel_size_mm))


def _parameters(solution: LegSolution3D, hidden: HiddenEffects3D) -> dict:
    """parameters.json in `study.make_phantom_case`'s layout."""
    law = {"law": "neo_hooke", "terms": None, "incompressible": False, "fixed": {}}
    return {"parameters_kPa": dict(zip(LEG_PARAMETERS, map(float, solution.theta_kPa))),
            "tension_N_per_mm": float(solution.tension_N_per_mm), "laws": {"fat": law, "muscle": law},
            "effects": hidden.catalog_form(), "deck_edited": False, "garment": "laplace", "friction_mu": 0.0,
            "garment_law": solution.garment_law, "solver": "ccx (CalculiX 2.20), 3D",
            "engine_mesh": {"elements": int(len(solution.mesh.elements)), "type": "C3D15"},
            "max_displacement_mm": float(np.abs(solution.displacement_mm).max())}


def _image_names(dicom: bool) -> list[str]:
    return ["unloaded.dcm", "loaded.dcm"] if dicom else ["unloaded.png", "loaded.png"]


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def _grid_points(field_mm, labels, scanner: Scanner, spacing_mm: float, sigma_mm: float,
                 seed: int) -> DisplacementPoints:
    """The true displacement at grid points in fat and muscle, plus Gaussian noise of sigma_mm."""
    x, y = pixel_centres_mm(scanner.image_shape, scanner.pixel_size_mm)
    step = max(1, int(round(spacing_mm / scanner.pixel_size_mm[0])))
    grid = np.zeros(labels.shape, bool)
    grid[::step, ::step] = True
    keep = grid & ((labels == 1) | (labels == 2))
    noise = np.random.default_rng(seed + 1000).normal(0.0, sigma_mm, (int(keep.sum()), 2))
    return DisplacementPoints(np.column_stack([x[keep], y[keep]]),
                              np.column_stack([field_mm[0][keep], field_mm[1][keep]]) + noise,
                              np.full(int(keep.sum()), sigma_mm))


def _write_dicom_case(folder: Path, name: str, images, scanner: Scanner, height_mm: float, tension: float,
                      rel: float, landmarks: dict, labels, points, overwrite: bool) -> None:
    """The case folder with one DICOM file per image: case.toml without pixel_size_mm (the files carry it)."""
    from ...case.folder import _write_points
    from .dicom import new_identities, write_dicom_slice

    if folder.exists() and not overwrite:
        raise FileExistsError(f"{folder} already exists; choose another folder or pass overwrite=True")
    with staged_folders(folder) as (staging,):
        for identity, role, image in zip(new_identities(("unloaded", "loaded"), name), ("unloaded", "loaded"), images):
            write_dicom_slice(staging / f"{role}.dcm", image, pixel_size_mm=scanner.pixel_size_mm, height_mm=height_mm,
                              slice_thickness_mm=scanner.slice_thickness_mm, identity=identity,
                              chemical_shift_px=scanner.chemical_shift_px, readout=scanner.readout)
        lines = ["[case]", f"name = {json.dumps(name)}", "", "[garment]", f"tension_N_per_mm = {float(tension)!r}",
                 f"tension_rel_uncertainty = {float(rel)!r}", "",
                 "[landmarks]  # mm, image frame of the unloaded image (x right, y down)"]
        lines += [f"{key} = [{float(x)!r}, {float(y)!r}]" for key, (x, y) in landmarks.items()]
        (staging / "case.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")
        if labels is not None:
            write_png16(staging / "labels.png", np.asarray(labels).astype(np.uint8))
        if points is not None:
            _write_points(staging / "points.csv", points)


def _compression_heights(studied: Sequence[float], widest_mm: float) -> dict[str, float]:
    """B the lowest studied height, C the nearest to the calf's largest girth (the reference section), B1 a third
    of the way from B to C, D the highest (RAL-GZ 387's measuring points, as `phantom.volume` names them)."""
    heights = np.asarray(sorted(studied), float)

    def nearest(height: float) -> float:
        return float(heights[np.argmin(np.abs(heights - height))])

    lowest, widest = float(heights[0]), nearest(widest_mm)
    return {"B": lowest, "B1": nearest(lowest + (widest - lowest) / 3.0), "C": widest, "D": float(heights[-1])}
