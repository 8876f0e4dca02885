"""From a case folder to a run folder, and phantom cases made by the engine.

`prepare_run` does once what every later command of a run needs (docs/design.md, "The data flow"): read the case,
segment I0 if the case has no labels, align the loaded image on the bones (rigid motion, Bouten and Drapier
sec. 3.1), segment the aligned loaded image, check that the leg lies inside both images and that the garment
compressed it (`imaging.field_checks`), cut the muscle into compartments at the septa seen in I0 when the
labels hold none (`imaging.compartments`, drawn in RUN_DIR/compartments.png for the user to check; each muscle
element takes the compartment under its centroid, `assign_compartments`, and they share the muscle's constants
until the `compartments` effect separates them), mesh the labels of I0 with their
interfaces moved onto the edges of I0 (`meshing.tissue_curves`), and store the labels, the motion and the
mesh in RUN_DIR/setup.npz + setup.json (written to temporary names, then renamed). `load_run` gives them back
with the model and the objectives, so that `calfit identify`, `montecarlo`, `pressures` and `report` all see
the same mesh. A case with more garment levels ([[garment.levels]]: loaded images of the slice under other tensions)
has each level's image aligned on the bones and checked as the first level's is, stored beside it
(setup.npz level_<k>_aligned, setup.json "levels"), measured with the same windows, and fitted jointly
(`levels`: `fit_model`, `displacement_objective`).

`make_phantom_case` writes a phantom case whose loaded image is made by the engine: the
phantom's exact geometry (its labels sampled 4 times finer than the image) is meshed finely
(T6, 2,000 elements by default: not the mesh of the fit, so no inverse crime), the leg model is solved at the chosen parameters, its displacement
is interpolated on the pixels and the phantom renders the loaded image by inverse warping
(`orchestrator.phantom.write_case`); the true parameters go to the truth folder only.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy import ndimage

from ..case.folder import Case, read_case
from ..case.resolution import coarsen_image, working_resolution
from ..core.errors import RunFolderError
from ..core.files import read_json, write_json
from ..core.frame import RigidMotion
from ..core.materials import law_notes
from ..core.tissues import MUSCLE
from ..engine.runner import write_mesh_include
from ..fit.geometry_uncertainty import level_file as geometry_level_file
from ..fit.geometry_uncertainty import read_columns as read_geometry_columns
from ..fit.geometry_uncertainty import read_covariance as read_geometry_covariance
from ..fit.objectives import (
    ContourMismatchObjective,
    DisplacementResidualObjective,
    LandmarkPressure,
)
from ..imaging.align import align_on_bones, resample_rigid
from ..imaging.chemical_shift import FatShift, fat_shift
from ..imaging.compartments import (
    FIRST_COMPARTMENT,
    compartment_areas_mm2,
    find_compartments,
)
from ..imaging.field_checks import (
    check_compression,
    check_grey_levels,
    check_leg_in_view,
    check_missing_pixels,
)
from ..imaging.segment import SegmentationWarning, segment_t1, segmentation_checks
from ..measure.measurements import (
    Measurements,
    dic_measurements,
    points_measurements,
    read_window_table,
)
from ..measure.measurements import level_files as measure_level_files
from ..meshing import (
    Mesh,
    TissueCurves,
    fat_muscle_normals,
    mesh_tissue_curves,
    tissue_curves,
    with_fat_moved_back,
)
from ..meshing.curves import ERROR_BAND
from ..meshing.labels import SHORTEST_SKIN_SHAPE_MM, interface_shift
from ..model.forward import LegModel
from ..model.landmarks import LandmarkError, placed_landmarks
from ..model.regions import LegFrame
from .setup_figures import compartments_figure
from .timings import stage

SETUP_ARRAYS = "setup.npz"
COMPARTMENTS_FIGURE = "compartments.png"
SETUP_JSON = "setup.json"
PARAMETERS_FILE = "parameters.json"
DATA_SOURCES = ("auto", "dic", "points")


def _mesh_arrays(mesh: Mesh) -> dict[str, np.ndarray]:
    arrays = {"nodes": mesh.nodes, "elements": mesh.elements, "element_regions": mesh.element_regions,
              "skin_faces": mesh.skin_faces, "skin_loop": mesh.skin_loop}
    arrays.update({f"set_{name}": np.asarray(ids) for name, ids in mesh.node_sets.items()})
    return arrays


def _mesh_from_arrays(arrays) -> Mesh:
    sets = {key[4:]: arrays[key] for key in arrays.files if key.startswith("set_")}
    return Mesh(arrays["nodes"], arrays["elements"], arrays["element_regions"], sets, arrays["skin_faces"],
                arrays["skin_loop"])


@dataclass
class RunSetup:
    """Everything a run needs, rebuilt identically by every command."""

    run_dir: Path
    case: Case
    labels_unloaded: np.ndarray
    labels_loaded: np.ndarray
    loaded_aligned: np.ndarray
    motion: RigidMotion
    mesh: Mesh
    model: LegModel
    compartments: dict = field(default_factory=lambda: {"source": "none"})   # setup.json "compartments"
    missing_fraction: dict = field(default_factory=dict)    # setup.json "missing_fraction": image name -> share
    level_motions: tuple = ()     # the bones' rigid motion of each more garment level's image (case.levels order)
    levels_aligned: tuple = ()    # each more garment level's image aligned on the bones of I0
    segmentation_warnings: dict = field(default_factory=dict)   # label map -> [SegmentationWarning], setup.json
    skin_outline: dict = field(default_factory=dict)   # setup.json "skin_outline": the skin's cut-off and error
    chemical_shift: dict | None = None   # setup.json "chemical_shift" (`imaging.chemical_shift.FatShift.as_dict`)
    # the DIC measurements of each garment level as `calfit measure` stored them, rebuilt once (their windows'
    # operators and covariance take about a second); the geometry's part is read again at every call
    _measured: dict = field(default_factory=dict, repr=False, compare=False)
    _tissue_curves: TissueCurves | None = field(default=None, repr=False, compare=False)   # `tissue_curves`
    _compartment_labels: np.ndarray | None = field(default=None, repr=False, compare=False)   # `compartment_labels`
    # the leg meshed again (`mesh_again`, `shifted_mesh`), once a mesh: the skin's uncertainty at every pass and at
    # every refit of a diagnosis, and the discretization check, use the same meshes (and so the same observations
    # of them, which `measure.Measurements.observation` keeps by mesh)
    _meshes: dict = field(default_factory=dict, repr=False, compare=False)
    _meshes_lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def tissue_curves(self) -> TissueCurves:
        """The interfaces of the unloaded labels snapped onto I0's edges, as the run's mesh was made from them
        (`meshing.tissue_curves`, made once; the skin cut where the run's was, `skin_outline`, a run folder written
        before that was stored having been cut at SHORTEST_SKIN_SHAPE_MM; the fat/muscle interface moved back by the
        chemical shift the setup found, `chemical_shift`): the discretization check and the skin's uncertainty mesh
        them again."""
        if self._tissue_curves is None:
            curves = tissue_curves(self.labels_unloaded, self.case.pixel_size_mm, image=self.case.unloaded,
                                   skin_cutoff_mm=self.skin_cutoff_mm)
            if self.fat_shift_mm is not None:
                curves = with_fat_moved_back(curves, self.fat_shift_mm)
            self._tissue_curves = curves
        return self._tissue_curves

    def compartment_labels(self) -> np.ndarray | None:
        """The muscle compartments the setup found at the septa of I0 (`imaging.compartments`, found once), None
        where the labels gave them or none were found."""
        if self.compartments.get("source") != "image":
            return None
        if self._compartment_labels is None:
            self._compartment_labels = find_compartments(self.case.unloaded, self.labels_unloaded,
                                                         self.case.pixel_size_mm).labels
        return self._compartment_labels

    def _made_once(self, key, make):
        """make() the first time key is asked for, in whichever thread asks first; the others wait for it."""
        with self._meshes_lock:
            made = self._meshes.get(key)
            if made is None:
                made = self._meshes[key] = Future()
                mine = True
            else:
                mine = False
        if mine:
            try:
                made.set_result(make())
            except BaseException as error:
                with self._meshes_lock:
                    del self._meshes[key]   # asked again, made again
                made.set_exception(error)
        return made.result()

    def mesh_again(self, n_elements: int, interface_offsets=None) -> Mesh:
        """The run's leg meshed again from its curves with n_elements (and interface_offsets: `mesh_tissue_curves`),
        its muscle cut into the compartments the setup found in I0 as the setup cut the run's mesh: the
        discretization check's finer mesh and the skin's shifted ones, which a model with the compartments effect
        needs. Without interface_offsets, made once (`_meshes`)."""
        if interface_offsets is None:
            return self._made_once(("mesh", int(n_elements)), lambda: self._meshed_again(n_elements, None))
        return self._meshed_again(n_elements, interface_offsets)

    def shifted_mesh(self, interface: str, distance_mm: float) -> Mesh:
        """The run's leg meshed again with one interface moved uniformly by distance_mm (`meshing.interface_shift`:
        the skin outwards, the fascia into the muscle), as many elements as the run's mesh; made once."""
        return self._made_once(("shifted", interface, float(distance_mm)), lambda: self._meshed_again(
            len(self.mesh.elements), interface_shift(self.labels_unloaded, self.case.pixel_size_mm, interface,
                                                     distance_mm)))

    def _meshed_again(self, n_elements: int, interface_offsets) -> Mesh:
        mesh = mesh_tissue_curves(self.tissue_curves(), n_elements=n_elements, order=self.mesh.order,
                                  interface_offsets=interface_offsets)
        found = self.compartment_labels()
        return mesh if found is None else assign_compartments(mesh, found, self.case.pixel_size_mm)

    @property
    def fat_shift_mm(self) -> tuple[float, float] | None:
        """The fat's chemical shift (x, y) mm the setup found on I0 and took (`imaging.chemical_shift`), None."""
        info = self.chemical_shift
        return tuple(info["shift_mm"]) if info is not None and info["significant"] else None

    @property
    def skin_cutoff_mm(self) -> float:
        """The wavelength the run's skin was low-passed at (`meshing.labels`)."""
        return float(self.skin_outline.get("cutoff_mm", SHORTEST_SKIN_SHAPE_MM))

    @property
    def skin_mode_variance_mm2(self) -> float | None:
        """The skin's error per Fourier coefficient as its own spectrum measured it (`meshing.curves.outline_error`),
        None where it could not."""
        return self.skin_outline.get("mode_variance_mm2")

    def setup_lines(self) -> list[str]:
        """What the user should know of how the images were read: the slice taken from a DICOM series, averaged
        over blocks of pixels, pixels with no value given the background's grey level, and the muscle
        compartments, found in I0 (and where to check them) or given by the labels, and where a segmentation (or
        labels.png) is unsure (`imaging.segment.segmentation_checks`)."""
        case, lines = self.case, []
        for role in ("unloaded", "loaded"):
            if f"{role}_slice" in case.files:
                lines.append(f"{case.files[role].name}: DICOM series, slice {case.files[f'{role}_slice'].name} used")
        if case.block_factor > 1:
            k, (rows, cols), (dy, dx) = case.block_factor, case.shape, case.pixel_size_mm
            lines.append(f"{case.files['unloaded'].name} and {case.files['loaded'].name}: pixels of {dy / k:.3f} x "
                         f"{dx / k:.3f} mm worked at {dy:.3f} x {dx:.3f} mm ({rows}x{cols} pixels, means of {k}x{k} "
                         "blocks), the pixel the DIC windows and the segmentation are made for")
        lines += [f"{name}: no value (NaN) in {100 * share:.1f} % of the slice, all outside the leg, read as background"
                  for name, share in self.missing_fraction.items()]
        if self.model.garment == "explicit":
            lines.append(f"garment: the explicit band of {self.case.tension_N_per_mm:g} N/mm, penalty contact"
                         + (f" with friction {self.model.friction_mu:g}: the engine carries the sensitivities "
                            "along the loading path (the constants, a volume change, the out-of-plane stretch); "
                            "Levenberg-Marquardt differences runs for any other parameter (one per parameter and "
                            "iteration)"
                            if self.model.friction_mu > 0 else ", frictionless"))
        lines += [note for tissue, law in self.model.tissue_laws.items() for note in law_notes(tissue, law)]
        if self.case.levels:
            lines.append("garment levels fitted jointly: " + ", ".join(
                f"{path.name} at {tension:g} N/mm" for path, tension in
                zip([self.case.files["loaded"]] + [level.path for level in self.case.levels], self.case.tensions)))
        info = self.compartments
        count = len(info.get("areas_mm2", {}))
        if info["source"] == "image":
            lines.append(f"muscle compartments: {count} found at the septa of I0, check them in "
                         f"{self.run_dir / info['figure']}")
        elif info["source"] == "labels":
            lines.append(f"muscle compartments: {count} from the labels")
        lines += [f"{source} unsure: {warning.message}" for source, warnings in self.segmentation_warnings.items()
                  for warning in warnings]
        if self.chemical_shift is not None:
            lines.append(FatShift.from_dict(self.chemical_shift).sentence(self.case.pixel_size_mm))
        if self.skin_mode_variance_mm2 is not None:
            band = "-".join(f"{factor * SHORTEST_SKIN_SHAPE_MM:g}" for factor in ERROR_BAND)
            lines.append(f"skin: low-passed at {self.skin_cutoff_mm:.1f} mm, the shortest wavelength at which its "
                         f"outline stands out of its own error ({np.sqrt(2.0 * self.skin_mode_variance_mm2):.4f} mm "
                         f"per Fourier mode, measured at {band} mm)")
        return lines

    def solve(self, theta: Sequence[float], folder: Path, model: LegModel | None = None):
        """Solve the run's model (or `model`) once at theta in `folder`, keeping the engine's outputs (the VTU of
        each step: stresses, pressure); returns its `EngineResults`. RuntimeError when it does not converge."""
        from ..engine.results import EngineResults
        from ..engine.runner import run_engine

        model = model if model is not None else self.model
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        write_mesh_include(model, folder)
        deck = folder / "deck.inp"
        deck.write_text(model.deck(theta))
        outcome = run_engine(deck, folder / "out", threads=1, timeout_s=300)
        if not outcome.converged:
            raise RuntimeError(f"the engine did not converge at {list(theta)} (see {outcome.outdir})")
        return EngineResults(outcome.outdir)

    def model_with(self, effects: Sequence[str] = (), sensitivities: bool = False) -> LegModel:
        """The run's leg model with these catalog effects fitted too; with `sensitivities` its decks ask the engine
        for du/dtheta (Levenberg-Marquardt and the diagnosis then need no finite-difference runs)."""
        from ..model.effects import parse_effects

        return case_model(self.mesh, self.case, effects=parse_effects(list(effects)), engine_sensitivities=sensitivities)

    def fit_model(self, effects: Sequence[str] = (), sensitivities: bool = False):
        """The model the displacements are fitted with: `model_with`, under every garment level of the case at once
        when it has more than one (`at_every_level`)."""
        return self.at_every_level(self.model_with(effects, sensitivities))

    def at_every_level(self, model: LegModel):
        """The model under every garment level of the case at once (`levels.LevelsModel`), or the model itself
        when the case has one level."""
        from ..fit.levels import LevelsModel

        return LevelsModel(model, self.case.tensions) if self.case.levels else model

    def frame(self) -> LegFrame:
        """Leg centre, anatomical orientation and skin distance of I0: how residual regions are named."""
        return LegFrame.from_labels(self.labels_unloaded, self.case.pixel_size_mm)

    def mismatch_objective(self) -> ContourMismatchObjective:
        return ContourMismatchObjective(self.mesh, self.labels_unloaded, self.labels_loaded, self.case.pixel_size_mm)

    def data_source(self, data: str = "auto") -> str:
        """"points" or "dic": auto takes points.csv when the case has one, otherwise the images (DIC)."""
        if data not in DATA_SOURCES:
            raise ValueError(f"the measured data are one of {', '.join(DATA_SOURCES)}, not {data!r}")
        if data == "auto":
            return "points" if self.case.points is not None else "dic"
        if data == "points" and self.case.points is None:
            raise RunFolderError(f"{self.case.folder} has no points.csv: measure the displacements from the images "
                                 "(--data dic, the default without points.csv)")
        return data

    def measurements(self, data: str = "auto", level: int = 1, with_geometry: bool = True) -> Measurements:
        """The measured displacements of garment level `level` (1: loaded.*, 2, 3, ...: the [[garment.levels]]) the
        fit compares the model with: points.csv (or the level's points file), or the DIC windows that
        `calfit measure` stored in the run folder, with the model's geometry uncertainty when the identification
        has estimated it (`geometry_uncertainty`) and `with_geometry`."""
        if self.data_source(data) == "points":
            if level == 1:
                return points_measurements(self.case.points)
            extra = self.case.levels[level - 2]
            if extra.points is None:
                raise RunFolderError(f"{self.case.files['toml']}: the garment level of {extra.path.name} has no points "
                                     f"while the fit uses points.csv: add points = \"<file>\" to its [[garment.levels]] "
                                     "table, or measure every level from the images (--data dic)")
            return points_measurements(extra.points)
        files = measure_level_files(level)
        table = read_window_table(self.run_dir, level)
        summary_path = self.run_dir / files["summary"]
        if table is None or not summary_path.is_file():
            raise RunFolderError(f"{self.run_dir} holds no DIC measurements{'' if level == 1 else f' of garment level {level}'}:"
                                 f" run `calfit measure CASE_DIR --out {self.run_dir}` first")
        summary = read_json(summary_path, "calfit measure")
        stamp = tuple((self.run_dir / files[key]).stat().st_mtime_ns for key in ("arrays", "summary"))
        if self._measured.get(level, (None,))[0] != stamp:
            # measurements made before the prefilter and the edges' error model were neither prefiltered nor had one
            motion = self.motion if level == 1 else self.level_motions[level - 2]
            self._measured[level] = (stamp, dic_measurements(
                self.case.unloaded, table, summary["window_px"], self.case.pixel_size_mm, summary["noise_sigma"][0],
                summary.get("prefilter_px", 0.0), summary.get("edge_variance_px2", 0.0), self.labels_unloaded,
                summary.get("outline_margin_px"), fat_shift_mm=summary.get("fat_shift_mm"), motion=motion,
                window_shape=summary.get("window_shape", "affine")))   # measured before the shape was a choice
        measured = self._measured[level][1]
        geometry = read_geometry_covariance(self.run_dir, 2 * len(measured), level) if with_geometry else None
        if geometry is None:
            return measured
        covariance, info = geometry
        description = f"skin uncertain by {info['skin_sigma_mm']:.3f} mm RMS at wavelengths over {info['cutoff_mm']:g} mm"
        if not self.case.levels:
            return measured.with_model_covariance(covariance, description)
        # several garment levels: one skin error moves every level's prediction, so the joint fit needs the columns
        # that make each level's C_geo (`levels.JointDisplacementObjective`)
        columns = read_geometry_columns(self.run_dir, 2 * len(measured), level)
        if columns is None:
            raise RunFolderError(f"{self.run_dir / geometry_level_file(level)} holds the skin's uncertainty of garment "
                                 f"level {level} alone (written before the levels' common skin error was kept): rerun "
                                 f"`calfit identify {self.case.folder} --out {self.run_dir}` to estimate it for the "
                                 "levels together")
        return measured.with_model_covariance(covariance, description, *columns)

    def level_measurements(self, data: str = "auto", with_geometry: bool = True) -> list[Measurements]:
        """The measurements of every garment level, the first level's first (`measurements`)."""
        return [self.measurements(data, level, with_geometry) for level in range(1, len(self.case.tensions) + 1)]

    def objective_of(self, measured: Sequence[Measurements]):
        """The displacement residual of these measurements, one per garment level: a
        `DisplacementResidualObjective` for one, their `levels.JointDisplacementObjective` for several."""
        from ..fit.levels import JointDisplacementObjective
        from ..measure.measurements import reference_noise_covariance

        with stage("weights"):   # C^-1/2 of each level's covariance (`core.linalg.symmetric_roots`)
            parts = [DisplacementResidualObjective(self.mesh, m) for m in measured]
        if len(parts) == 1:
            return parts[0]
        # the levels' DIC windows are the same windows of I0: its noise is in every level's errors
        between = {(k, l): reference_noise_covariance(measured[k], measured[l])
                   for k in range(len(measured)) for l in range(k + 1, len(measured))}
        return JointDisplacementObjective(parts, between)

    def displacement_objective(self, data: str = "auto"):
        """The displacement residual of the run's measurements, of every garment level (`objective_of`)."""
        return self.objective_of(self.level_measurements(data))

    def landmarks(self) -> tuple[dict[str, tuple[float, float]], str]:
        """(the named positions where pressures are read, where they come from): case.toml's [landmarks], or, when
        it names none, the first paper's five placed from I0's segmentation (`model.landmarks`, "segmentation")."""
        if self.case.landmarks:
            return dict(self.case.landmarks), "case.toml"
        try:
            return placed_landmarks(self.frame()), "segmentation"
        except LandmarkError as error:
            raise RunFolderError(f"{self.case.folder / 'case.toml'} has no [landmarks] table and {error}: add the "
                                 "positions (mm, image frame of I0) where pressures are wanted") from None

    def pressure_objective(self) -> LandmarkPressure:
        return LandmarkPressure(self.mesh, self.landmarks()[0])


def prepare_run(case_dir: str | Path, run_dir: str | Path, *, n_elements: int = 400, order: int = 1,
                align: bool = True, compartments: bool = True) -> RunSetup:
    """Read, segment, align and mesh a case; store the result in run_dir (see the module text)."""
    with stage("segmentation"):
        case, segmented = _segmented_case(case_dir, align)
    with stage("meshing"):
        return _meshed_run(case_dir, run_dir, case, *segmented, n_elements=n_elements, order=order,
                           compartments=compartments)


def _segmented_case(case_dir, align: bool):
    """The case read, its images checked, segmented and aligned on the bones (`prepare_run`'s first half)."""
    case = working_case(case_dir)
    unloaded_name, loaded_name = case.files["unloaded"].name, case.files["loaded"].name
    for image, name in ((case.unloaded, unloaded_name), (case.loaded, loaded_name),
                        *((level.image, level.path.name) for level in case.levels)):
        check_grey_levels(image, name)
    # the fat's chemical shift, first on a segmentation that knows none: a fatty marrow it moves against its
    # cortex may be missed there, so the images are segmented again knowing its size (`segment_t1`)
    unshifted = segment_t1(case.unloaded, case.pixel_size_mm) if case.labels is None else None
    first_labels = case.labels if case.labels is not None else unshifted
    first_curves = tissue_curves(first_labels, case.pixel_size_mm, image=case.unloaded)
    first = fat_shift(case.unloaded, *fat_muscle_normals(first_curves), case.pixel_size_mm, case.acquisition)
    shift_size = float(np.hypot(*first.shift_mm)) if first is not None and first.significant else 0.0
    # segment_t1 without a shift is the first segmentation again: not made twice
    segmented_unloaded = (unshifted if unshifted is not None and shift_size == 0.0
                          else segment_t1(case.unloaded, case.pixel_size_mm, fat_shift_mm=shift_size))
    labels_unloaded = case.labels if case.labels is not None else segmented_unloaded
    segmented_loaded = segment_t1(case.loaded, case.pixel_size_mm, fat_shift_mm=shift_size)
    missing_fraction = {}
    labels_name = case.files["labels"].name if case.labels is not None else unloaded_name
    for role, name, labels in (("unloaded", unloaded_name, labels_unloaded), ("loaded", loaded_name, segmented_loaded)):
        check_leg_in_view(labels, case.pixel_size_mm, labels_name if role == "unloaded" else name)
        if check_missing_pixels(case.missing.get(role), labels > 0, case.pixel_size_mm, name):
            missing_fraction[name] = float(case.missing[role].mean())
    motion = (align_on_bones(case.unloaded, case.loaded, case.pixel_size_mm, labels_unloaded=labels_unloaded,
                             fat_shift_mm=shift_size) if align else RigidMotion())
    loaded_aligned = resample_rigid(case.loaded, motion, case.pixel_size_mm) if align else case.loaded
    labels_loaded = segment_t1(loaded_aligned, case.pixel_size_mm, fat_shift_mm=shift_size)
    area_change = check_compression(segmented_unloaded > 0, labels_loaded > 0, unloaded_name, loaded_name)
    # labels.png is meshed as given; what is doubtful in it, or in the segmentations, is said, not corrected
    unloaded_source = case.files["labels"].name if case.labels is not None else f"segmentation of {unloaded_name}"
    segmentation_warnings = {source: [w.as_dict() for w in segmentation_checks(labels, case.pixel_size_mm)]
                             for source, labels in ((unloaded_source, labels_unloaded),
                                                    (f"segmentation of {loaded_name} aligned on the bones", labels_loaded))}
    prepared_levels = [_prepare_level(case, level, labels_unloaded, segmented_unloaded, align, shift_size)
                       for level in case.levels]
    for level, (_, _, _, share) in zip(case.levels, prepared_levels):
        if share is not None:
            missing_fraction[level.path.name] = share
    return case, (labels_unloaded, labels_loaded, loaded_aligned, motion, missing_fraction, segmentation_warnings,
                  prepared_levels, area_change, (first_labels, first_curves, first))


def _meshed_run(case_dir, run_dir, case: Case, labels_unloaded, labels_loaded, loaded_aligned, motion,
                missing_fraction, segmentation_warnings, prepared_levels, area_change, first, *, n_elements: int,
                order: int, compartments: bool) -> RunSetup:
    """The segmented case meshed and stored in run_dir (`prepare_run`'s second half)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    compartment_info = {"source": "labels" if labels_unloaded.max() >= FIRST_COMPARTMENT else "none"}
    first_labels, curves, shift = first   # the interfaces and the chemical shift the segmentation found
    if not np.array_equal(labels_unloaded, first_labels):   # segmented again, knowing the shift: found again
        curves = tissue_curves(labels_unloaded, case.pixel_size_mm, image=case.unloaded)
        shift = fat_shift(case.unloaded, *fat_muscle_normals(curves), case.pixel_size_mm, case.acquisition)
    if shift is not None and shift.significant:
        curves = with_fat_moved_back(curves, shift.shift_mm)
    mesh = mesh_tissue_curves(curves, n_elements=n_elements, order=order)
    compartment_labels = labels_unloaded
    if compartments and compartment_info["source"] == "none":
        found = find_compartments(case.unloaded, labels_unloaded, case.pixel_size_mm)
        compartments_figure(run_dir / COMPARTMENTS_FIGURE, case.unloaded, case.pixel_size_mm, found)
        if found.count >= 2:
            compartment_labels = found.labels
            mesh = assign_compartments(mesh, found.labels, case.pixel_size_mm)
            compartment_info = {"source": "image", "figure": COMPARTMENTS_FIGURE}
    compartment_info["areas_mm2"] = {str(k): round(v, 1)
                                      for k, v in compartment_areas_mm2(compartment_labels, case.pixel_size_mm).items()}
    temporary = run_dir / f".{SETUP_ARRAYS}.tmp.npz"
    np.savez_compressed(temporary, labels_unloaded=labels_unloaded, labels_loaded=labels_loaded,
                        loaded_aligned=loaded_aligned, **_mesh_arrays(mesh),
                        **{f"level_{level.number}_aligned": aligned
                           for level, (aligned, _, _, _) in zip(case.levels, prepared_levels)})
    temporary.replace(run_dir / SETUP_ARRAYS)
    chemical_shift = None if shift is None else shift.as_dict(case.pixel_size_mm)
    skin_outline = {"cutoff_mm": curves.skin_cutoff_mm,
                    "mode_variance_mm2": None if curves.skin_error is None else curves.skin_error.mode_variance_mm2}
    write_json(run_dir / SETUP_JSON, {"case_dir": str(Path(case_dir).resolve()), "n_elements": len(mesh.elements),
                                      "order": order, "compartments": compartment_info, "skin_outline": skin_outline,
                                      "chemical_shift": chemical_shift,
                                      "missing_fraction": missing_fraction, "segmentation_warnings": segmentation_warnings,
                                      **({"levels": [info for _, _, info, _ in prepared_levels]} if case.levels else {}),
                                      "leg_area_change": area_change, "rigid_motion": {"angle_deg": motion.angle_deg,
                                                                       "translation_mm": list(motion.translation_mm),
                                                                       "centre_mm": list(motion.centre_mm)}})
    setup = load_run(run_dir)
    setup._tissue_curves = curves   # the same labels and I0 as load_run reads back: not snapped again
    if compartment_info["source"] == "image":   # found at the septa of I0 just now: not searched again
        setup._compartment_labels = compartment_labels
    return setup


def working_case(case_dir: str | Path) -> Case:
    """The case read and put at its working resolution (`imaging.resolution`), its garment levels' images too."""
    case = working_resolution(read_case(case_dir))
    factor = case.block_factor
    if factor == 1 or not case.levels:
        return case
    return replace(case, levels=tuple(
        replace(level, image=coarsen_image(level.image, factor),
                missing=None if level.missing is None else coarsen_image(level.missing.astype(float), factor) > 0)
        for level in case.levels))


def _prepare_level(case: Case, level, labels_unloaded: np.ndarray, segmented_unloaded: np.ndarray, align: bool,
                   fat_shift_mm: float = 0.0):
    """A more garment level's image checked and aligned on the bones as the first level's: (aligned image, motion,
    its setup.json entry, its share of pixels without a value or None)."""
    name = level.path.name
    labels = segment_t1(level.image, case.pixel_size_mm, fat_shift_mm=fat_shift_mm)
    check_leg_in_view(labels, case.pixel_size_mm, name)
    share = (float(level.missing.mean())
             if check_missing_pixels(level.missing, labels > 0, case.pixel_size_mm, name) else None)
    motion = (align_on_bones(case.unloaded, level.image, case.pixel_size_mm, labels_unloaded=labels_unloaded,
                             fat_shift_mm=fat_shift_mm) if align else RigidMotion())
    aligned = resample_rigid(level.image, motion, case.pixel_size_mm) if align else level.image
    area_change = check_compression(segmented_unloaded > 0,
                                    segment_t1(aligned, case.pixel_size_mm, fat_shift_mm=fat_shift_mm) > 0,
                                    case.files["unloaded"].name, name)
    info = {"level": level.number, "image": name, "tension_N_per_mm": level.tension_N_per_mm,
            "leg_area_change": area_change,
            "rigid_motion": {"angle_deg": motion.angle_deg, "translation_mm": list(motion.translation_mm),
                             "centre_mm": list(motion.centre_mm)}}
    return aligned, motion, info, share


def assign_compartments(mesh: Mesh, compartment_labels: np.ndarray, pixel_size_mm) -> Mesh:
    """The mesh with each muscle element in the compartment (label >= 4) under its centroid, or the nearest one.
    The mesh itself is not cut at the septa: septa meshed as interfaces take elements from the skin (at 1,000
    CPE6 its edges grew from 2.1 to 2.8 mm), which inflated the skin's share of the error budget threefold,
    while a stiffness that changes from one element to the next across a septum is what the compartments
    effect needs."""
    inside = compartment_labels >= FIRST_COMPARTMENT
    _, (rows_near, cols_near) = ndimage.distance_transform_edt(~inside, return_indices=True)
    nearest = compartment_labels[rows_near, cols_near]
    centroids = mesh.nodes[mesh.elements[:, :3]].mean(axis=1)
    rows = np.clip((centroids[:, 1] / pixel_size_mm[0]).astype(int), 0, nearest.shape[0] - 1)
    cols = np.clip((centroids[:, 0] / pixel_size_mm[1]).astype(int), 0, nearest.shape[1] - 1)
    regions = mesh.element_regions.copy()
    muscle = regions == MUSCLE
    regions[muscle] = nearest[rows[muscle], cols[muscle]]
    return replace(mesh, element_regions=regions)


def case_model(mesh: Mesh, case: Case, **options) -> LegModel:
    """The leg model the case's [model] table asks for (garment, friction, u/p elements, the tissues' laws) on
    mesh."""
    choice = case.model
    return LegModel(mesh, case.tension_N_per_mm, garment=choice.garment, friction_mu=choice.friction,
                    hybrid=choice.hybrid, tissues=dict(choice.tissues), **options)


def load_run(run_dir: str | Path) -> RunSetup:
    run_dir = Path(run_dir)
    info = read_json(run_dir / SETUP_JSON, "calfit identify CASE_DIR --out RUN_DIR")
    case = working_case(info["case_dir"])
    stored_levels = info.get("levels", [])
    if [entry["image"] for entry in stored_levels] != [level.path.name for level in case.levels]:
        raise RunFolderError(f"{run_dir} was prepared for the garment levels {[e['image'] for e in stored_levels]} "
                             f"and {case.files['toml']} now names {[level.path.name for level in case.levels]}: give "
                             "--out another folder for this case")
    with np.load(run_dir / SETUP_ARRAYS) as arrays:
        mesh = _mesh_from_arrays(arrays)
        labels_unloaded, labels_loaded = arrays["labels_unloaded"], arrays["labels_loaded"]
        loaded_aligned = arrays["loaded_aligned"]
        levels_aligned = tuple(arrays[f"level_{entry['level']}_aligned"] for entry in stored_levels)
    level_motions = tuple(RigidMotion(entry["rigid_motion"]["angle_deg"], tuple(entry["rigid_motion"]["translation_mm"]),
                                      tuple(entry["rigid_motion"]["centre_mm"])) for entry in stored_levels)
    motion = RigidMotion(info["rigid_motion"]["angle_deg"], tuple(info["rigid_motion"]["translation_mm"]),
                         tuple(info["rigid_motion"]["centre_mm"]))
    segmentation_warnings = {source: [SegmentationWarning.from_dict(w) for w in warnings]
                             for source, warnings in info.get("segmentation_warnings", {}).items()}
    return RunSetup(run_dir, case, labels_unloaded, labels_loaded, loaded_aligned, motion, mesh,
                    case_model(mesh, case), info.get("compartments", {"source": "none"}),
                    info.get("missing_fraction", {}), level_motions, levels_aligned, segmentation_warnings,
                    skin_outline=info.get("skin_outline", {}), chemical_shift=info.get("chemical_shift"))


