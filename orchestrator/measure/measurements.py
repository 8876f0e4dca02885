"""Measured displacements, from the two images (DIC) or from points.csv: what the fit compares the model with.

Images first (docs/method/dic.md). A user brings two slices, not a table. `measure_dic` measures the displacement of
the tissue relative to the bones between them (Bouten and Drapier sec. 2.2 and 3.1):

1. windows of `window_px` (16, 32 or 64) on a grid inside the leg, every `step_px` (default half a window),
   plus windows on the regions of interest of sec. 3.1: along the skin and the fascia every `roi_spacing_mm`,
   and at the vessels named among the case's landmarks;
2. each window correlated with the bones' rigid motion composed into its warp (`imaging.dic`), so the
   displacement is relative to the bones, with its 2x2 covariance;
3. outliers rejected, each counted by reason, as OpenPIV validates: too little texture (a window whose texture and
   the images' noise allow a ZNCC under MIN_ATTAINABLE, `imaging.dic.attainable_confidence`), a low match (a ZNCC
   under `min_confidence` of what they allow: a weakly textured window matches at the low ZNCC its noise permits,
   and its covariance already says how little it knows, where a fixed ZNCC of 0.8 rejected the muscle of a T1
   image, 37 of 180 windows on the other program's k-space control, whose errors were as predicted: 0.73 of the
   variance over noise draws), a high predicted uncertainty (above `max_uncertainty_px`), and the normalised median
   test of Westerweel and Scarano (Exp. Fluids 39, 2005): with u_m the median of the 8 nearest accepted
   neighbours and r_m the median of their distances to u_m, a window whose |u - u_m| / (r_m + eps) exceeds
   `median_threshold` (2, eps = 0.1 px) in either component is an outlier;
4. the kept windows' full covariance, overlaps included (`imaging.windows`), with, for images that a renderer
   drew by point samples, the error of that drawing where boundaries run along the pixel grid, which no window's
   residual shows (`imaging.drawing`), the error that the loaded texture's own change makes (a thick slice the
   tissue slides through, the ringing of the deformed leg: `texture_change`, measured on the images through the
   kept windows' field, nothing where the texture moved intact), and the operator that observes a model's
   displacement field as the windows do (so the fit compares like with like).

Windows that respect the tissue (`respect_outline`, `window_pixel_masks`; `calfit measure --respect-outline`). A
grid window centred within half a window of the skin spans the leg's outline and the air beyond, and so measures
the skin's edge as well as the tissue at its centre. Where the outline differs between the two images by more than
the tissue's motion (a garment that shows in the loaded image; a sharp outline drawn afresh in each image, whose
staircase does not move with the tissue), that error reaches those windows. With respect_outline, a window centred
more than a margin inside the outline (the prefilter's radius + 1 pixel: the smoothing spreads the edge that far)
matches only the pixels at least that far inside; the windows on the outline keep it. Its operators and covariance
follow the same pixels. Measured (docs/validation/error-model.md), before calfit recognised their
point-sampled drawing (`imaging.drawing`): on the other program's four cases the deep fat's chi^2/n against the true
field falls from 1.26 to 1.18 (the skin band 0.97 -> 0.96), but the
parameters' standard errors grow by 3-38 % and the windows near the skin are less accurate (deep fat, radial: 0.026
-> 0.057 px RMS): the outline's edge is the most precise feature those windows see. So it is not the default; it is
the remedy for images whose outline does not follow the tissue (a garment visible in the loaded slice).

`Measurements` is the same object for points.csv (points, diagonal covariance from sigma_mm, the model
read at the points) and for DIC (windows, full covariance, the model observed through the windows, and three
nuisance degrees of freedom for the residual rigid motion between the two images' bones, which the fit
profiles out: the alignment is good to about 0.003 mm, a third of a 32-pixel window's noise, but common to
every window).

In a run folder: measurements.csv (every window tried, kept or why not, with its covariance), measurements.npz
(what rebuilds the Measurements), measurements.json (summary) and measurements.png (the vectors on the image).
A case with more garment levels ([[garment.levels]]) has the same four files for each more loaded image,
measurements-level-2.csv and so on (`level_files`): the same windows of I0, correlated with that image. The noise of
I0 is then in every level's errors, and `reference_noise_covariance` gives their covariance between two levels.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage, sparse
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from ..case.folder import DisplacementPoints
from ..core.files import write_json
from ..core.frame import RigidMotion, index_to_mm, mm_to_index, pixel_centres_mm
from ..core.tissues import FAT, MUSCLE
from ..imaging.chemical_shift import fat_signal
from ..imaging.coherence import coherence_sentence, texture_coherence
from ..imaging.mismatch import tissue_mask
from .dic import attainable_confidence, correlate, grid_centres, roi_centres
from .drawing import boundaries, detect_point_sampling, drawn_boundaries_factor
from .prefilter import PREFILTER_SIGMA_PX, Prefilter, fit_error_model
from .shape import SHAPE_ORDERS, WindowShape
from .texture_change import covariance_factor, measure_change, window_covariance
from .windows import WindowOperators, textured

WINDOW_CHOICES = (16, 32, 64)
DEFAULT_WINDOW_PX = 32
WINDOW_SHAPES = tuple(SHAPE_ORDERS)   # shape.WindowShape.named
DEFAULT_WINDOW_SHAPE = "affine"
MIN_CONFIDENCE = 0.8       # the share of the ZNCC its texture and noise allow a window must reach (`attainable_confidence`)
MIN_ATTAINABLE = 0.4       # a window whose texture allows less is not matched with confidence: a false peak of noise
#                            reaches 0.1-0.25 over the search (pure noise, 16-32 px windows, about 4,000 positions)
MAX_UNCERTAINTY_PX = 0.25
MEDIAN_THRESHOLD = 2.0
MEDIAN_EPSILON_PX = 0.1
MEDIAN_NEIGHBOURS = 8
RESIDUAL_ALPHA = 1e-3   # a window's residual beyond what the error model allows at this level raises its own noise
MAX_RESIDUAL_EXCESS = 5.0   # and beyond this many times the model the window is not trusted (a failed match)
PRIOR_SMOOTHING = 1e-3      # thin-plate smoothing of the first pass (it only has to bend the windows, not fit noise)
DRAWING_DRAWS = 64          # sub-pixel placements of the leg over which a point-sampled drawing's error is spread
#                             (`imaging.drawing`; 16 / 64 / 128 give the other program's bands within 0.05)
VESSEL_WORDS = ("vein", "saphenous", "artery", "vessel")
KINDS = ("grid", "skin", "fascia", "vessel")
KEPT = "kept"
FLAT = "less texture than the calibrated noise"
FILES = {"table": "measurements.csv", "arrays": "measurements.npz", "summary": "measurements.json",
         "figure": "measurements.png"}


def level_files(level: int = 1) -> dict[str, str]:
    """The measurement files of garment level `level`: FILES for the first (loaded.*), then
    measurements-level-<level>.* beside them."""
    if level == 1:
        return dict(FILES)
    return {role: name.replace("measurements.", f"measurements-level-{level}.") for role, name in FILES.items()}


@dataclass
class WindowTable:
    """Every window tried: where, what it found, and whether it is kept (status "kept") or why not."""

    centres_rc: np.ndarray        # (N, 2) integer centre pixels in I0
    kind: list[str]               # grid, skin, fascia or vessel
    position_mm: np.ndarray       # (N, 2)
    displacement_mm: np.ndarray   # (N, 2), relative to the bones
    covariance_mm2: np.ndarray    # (N, 2, 2)
    confidence: np.ndarray        # (N,) ZNCC
    intensity_variance: np.ndarray
    tissue: list[str]             # tissue of I0 under the centre
    status: list[str]
    prior_offset_mm: np.ndarray | None = None   # (N, 2) prior at the centre less what the window sees of it
    # (N,) the window's squared residual over what the calibrated error model predicts for it (`imaging.prefilter`:
    # 1 where the model holds, NaN where the window did not match)
    residual_over_model: np.ndarray | None = None
    # (2 K, D) for the K kept windows: F with F F^T the covariance (mm^2) of their error from boundaries that a
    # point-sampling renderer drew (`imaging.drawing`), None for images not drawn so
    drawing_factor_mm: np.ndarray | None = None
    # (2 K, D) for the K kept windows: F with F F^T the covariance (mm^2) of their error from the loaded texture that is
    # not the unloaded texture moved (`texture_change`), None where the images showed none
    texture_factor_mm: np.ndarray | None = None

    @property
    def kept(self) -> np.ndarray:
        return np.array([s == KEPT for s in self.status], bool)

    def counts(self) -> dict[str, int]:
        values, counts = np.unique(self.status, return_counts=True)
        return {str(v): int(c) for v, c in zip(values, counts)}


@dataclass
class Measurements:
    """Measured displacements and how to compare a model with them (module text).

    displacement (mm) and covariance (mm^2) are interleaved (u_x, u_y per window or point); `operators` is
    None for points (the model is read at the points), the windows' operators for DIC."""

    source: str
    position_mm: np.ndarray
    displacement_mm: np.ndarray
    covariance_mm2: np.ndarray
    operators: WindowOperators | None = None
    rigid_nuisance: bool = False
    description: str = ""
    kind: list[str] = field(default_factory=list)
    measurement_covariance_mm2: np.ndarray | None = None   # the measurement's part when a model part is added
    model_columns_mm: np.ndarray | None = None   # (2N, m) G: the model part is G diag(model_weights) G^T (levels)
    model_weights: np.ndarray | None = None      # (m,) the variances of the model part's modes
    reference_noise_sigma: float | None = None   # DIC: the noise of I0 (intensity), shared by every garment level
    fat_shift_mm: tuple[float, float] | None = None   # DIC: the fat's chemical shift the windows see (`windows`)
    # observation matrices already formed, by mesh (the same mesh is observed by every objective of a run)
    _observed: dict = field(default_factory=dict, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.position_mm)

    @property
    def reference_variance_mm2(self) -> float:
        """Mean variance of one displacement component: the unit of the misfit F and of its noise floor."""
        return float(np.trace(self.covariance_mm2) / self.covariance_mm2.shape[0])

    @property
    def measurement_share(self) -> float:
        """The share of the measurement noise (not the model's geometry) in the mean variance."""
        if self.measurement_covariance_mm2 is None:
            return 1.0
        return float(np.trace(self.measurement_covariance_mm2) / np.trace(self.covariance_mm2))

    def observer(self) -> "Observer":
        """What the measurement sees of a model (picklable, without the images)."""
        if self.operators is None:
            return Observer(self.position_mm, None)
        windows, positions = self.operators.observation(self.fat_shift_mm)
        return Observer(positions, windows)

    def sees(self, field_mm: np.ndarray) -> np.ndarray:
        """(N, 2) what the DIC windows measure of a (2, H, W) displacement field on the pixels of I0 (mm), the fat's
        chemical shift included (`imaging.windows`)."""
        if self.operators is None:
            raise ValueError("a field on the pixels is seen through DIC windows: these measurements are points")
        return self.operators.observe(field_mm, self.fat_shift_mm)

    def observation(self, mesh) -> sparse.csr_matrix:
        """Sparse (2N, 2M) map from the nodal displacement of `mesh` (interleaved) to what was measured."""
        # keyed by the objects themselves (held in the entry, so that their ids are not reused): `replace` shares
        # this cache between copies that keep the same places and windows
        key = (id(mesh), id(self.position_mm), id(self.operators))
        if key not in self._observed:
            self._observed[key] = (mesh, self.position_mm, self.operators, self.observer()(mesh))
        return self._observed[key][3]

    def with_model_covariance(self, covariance_mm2: np.ndarray, description: str, columns_mm: np.ndarray | None = None,
                              weights: np.ndarray | None = None) -> "Measurements":
        """The same measurements with the covariance of the model's own predictions added (geometry_uncertainty).
        columns_mm and weights, when given, are what makes it, covariance_mm2 = G diag(w) G^T: a case of several
        garment levels keeps them, so that the joint fit can form the covariance between the levels
        (`levels.JointDisplacementObjective`)."""
        if (columns_mm is None) != (weights is None):
            raise ValueError("the model covariance's columns and their weights come together")
        if columns_mm is not None:
            columns_mm, weights = np.asarray(columns_mm, float), np.asarray(weights, float).ravel()
            if columns_mm.shape != (len(self.covariance_mm2), len(weights)):
                raise ValueError(f"the model covariance's columns are {columns_mm.shape} for "
                                 f"{len(self.covariance_mm2)} measured values and {len(weights)} weights")
        return replace(self, covariance_mm2=self.covariance_mm2 + covariance_mm2,
                       description=f"{self.description}; {description}",
                       measurement_covariance_mm2=(self.covariance_mm2 if self.measurement_covariance_mm2 is None
                                                   else self.measurement_covariance_mm2),
                       model_columns_mm=columns_mm, model_weights=weights)

    def rigid_columns(self, centre_mm) -> np.ndarray:
        """(2N, 3) displacement of the measured places under a unit translation along x, y and a unit rotation
        (rad) about centre_mm: the residual rigid motion of the bones between the two images."""
        offset = self.position_mm - np.asarray(centre_mm, float)
        columns = np.zeros((2 * len(self), 3))
        columns[0::2, 0] = 1.0
        columns[1::2, 1] = 1.0
        columns[0::2, 2] = -offset[:, 1]
        columns[1::2, 2] = offset[:, 0]
        return columns


@dataclass(frozen=True)
class Observer:
    """The model seen at points (`windows` None: FE interpolation there) or through DIC windows (`windows` maps
    the displacement at the pixel centres `positions_mm`, interleaved, to what each window measures)."""

    positions_mm: np.ndarray
    windows: sparse.csr_matrix | None

    def __call__(self, mesh) -> sparse.csr_matrix:
        from ..model.forward import MeshInterpolator

        at_positions = sparse.kron(MeshInterpolator(mesh).weights(self.positions_mm), sparse.identity(2), format="csr")
        return at_positions if self.windows is None else (self.windows @ at_positions).tocsr()


def points_measurements(points: DisplacementPoints, sigma_default_mm: float = 1.0) -> Measurements:
    """points.csv as measurements: independent points, sigma_mm per point (1 mm when the file has none)."""
    sigma = (np.full(len(points), sigma_default_mm) if points.sigma_mm is None else np.asarray(points.sigma_mm, float))
    return Measurements("points.csv", np.asarray(points.position_mm, float), np.asarray(points.displacement_mm, float),
                        np.diag(np.repeat(sigma ** 2, 2)), None, False, f"{len(points)} points of points.csv",
                        ["point"] * len(points))


# --- DIC ----------------------------------------------------------------------------------------

def window_centres(labels: np.ndarray, pixel_size_mm, window_px: int, step_px: int, roi_spacing_mm: float,
                   vessels_mm) -> tuple[np.ndarray, list[str]]:
    """Grid windows whose centre is in fat or muscle, then vessel, skin and fascia windows (module text), each at
    least half a step (in rows or columns) from those before it."""
    leg = tissue_mask(labels, FAT) | tissue_mask(labels, MUSCLE)
    grid = grid_centres(labels.shape, window_px, step_px, mask=leg)
    skin = roi_centres(labels, pixel_size_mm, roi_spacing_mm, skin=True, fascia=False)
    fascia = roi_centres(labels, pixel_size_mm, roi_spacing_mm, skin=False, fascia=True)
    vessels = roi_centres(labels, pixel_size_mm, roi_spacing_mm, skin=False, fascia=False, vessels_mm=vessels_mm)
    parts = [(grid, "grid"), (vessels, "vessel"), (skin, "skin"), (fascia, "fascia")]
    centres, kinds = [], []
    for points, kind in parts:
        for point in points.reshape(-1, 2):
            # a window next to one already placed measures nearly the same pixels, with nearly the same error
            if not centres or np.min(np.max(np.abs(np.array(centres) - point), axis=1)) >= step_px / 2:
                centres.append(point)
                kinds.append(kind)
    return np.array(centres, dtype=int).reshape(-1, 2), kinds


def window_pixel_masks(labels: np.ndarray, centres_rc: np.ndarray, window_px: int, margin_px: int) -> list:
    """Per window, None (it matches its whole square) or the (window_px, window_px) pixels it matches: a window
    centred more than margin_px inside the leg's outline leaves out the pixels within margin_px of the outline and
    the air beyond (module text, windows that respect the tissue); windows on the outline keep it."""
    inside = ndimage.distance_transform_edt(np.asarray(labels) > 0) > margin_px
    masks = []
    for row, col in np.asarray(centres_rc, int).reshape(-1, 2):
        r0, c0 = row - window_px // 2, col - window_px // 2
        block = inside[max(r0, 0):r0 + window_px, max(c0, 0):c0 + window_px]
        masks.append(None if not inside[row, col] or block.shape != (window_px, window_px) or block.all()
                     else block.copy())
    return masks


def vessel_landmarks(landmarks: dict[str, tuple[float, float]]) -> list[tuple[float, float]]:
    """The landmarks that name a vessel (a vein, artery, saphenous...): DIC windows go there too."""
    return [tuple(xy) for name, xy in landmarks.items() if any(word in name.lower() for word in VESSEL_WORDS)]


def normalised_median_outliers(positions_mm: np.ndarray, displacement_px: np.ndarray, candidates: np.ndarray, *,
                               threshold: float = MEDIAN_THRESHOLD, epsilon_px: float = MEDIAN_EPSILON_PX,
                               neighbours: int = MEDIAN_NEIGHBOURS, radius_mm: float = np.inf) -> np.ndarray:
    """Westerweel and Scarano's normalised median test (module text) over the `candidates` windows, each against
    its nearest candidate neighbours within radius_mm; True where a window fails. Windows with fewer than 3
    neighbours cannot be tested and pass."""
    index = np.flatnonzero(candidates)
    outlier = np.zeros(len(positions_mm), bool)
    if len(index) < 4:
        return outlier
    tree = cKDTree(positions_mm[index])
    k = min(neighbours + 1, len(index))
    distance, nearest = tree.query(positions_mm[index], k=k)
    for row, i in enumerate(index):
        others = nearest[row][(nearest[row] != row) & np.isfinite(distance[row]) & (distance[row] <= radius_mm)]
        if len(others) < 3:
            continue
        values = displacement_px[index[others]]
        median = np.median(values, axis=0)
        spread = np.median(np.abs(values - median), axis=0)
        outlier[i] = bool(np.any(np.abs(displacement_px[i] - median) / (spread + epsilon_px) > threshold))
    return outlier


def measure_dic(unloaded: np.ndarray, loaded: np.ndarray, labels: np.ndarray, pixel_size_mm, motion: RigidMotion, *,
                landmarks: dict | None = None, window_px: int = DEFAULT_WINDOW_PX, step_px: int | None = None,
                roi_spacing_mm: float | None = None, min_confidence: float = MIN_CONFIDENCE,
                max_uncertainty_px: float = MAX_UNCERTAINTY_PX, prefilter_px: float = PREFILTER_SIGMA_PX,
                respect_outline: bool = False, workers: int = 1,
                fat_shift_mm=None, window_shape: str = DEFAULT_WINDOW_SHAPE) -> tuple[Measurements, WindowTable, dict]:
    """DIC between the two images (module text). Returns the kept windows as Measurements, every window tried,
    and a summary. respect_outline: windows inside the leg leave out its outline (`window_pixel_masks`); workers:
    local processes the windows are matched in (`imaging.dic.correlate`: the same matches as in one);
    fat_shift_mm: the fat's chemical shift (x, y) the setup found on I0 (`imaging.chemical_shift`), which the
    windows see as `imaging.windows` says, or None. window_shape: "affine" or "quadratic", the windows' shape
    function (`shape.WindowShape`)."""
    if window_px not in WINDOW_CHOICES:
        raise ValueError(f"the DIC window must be one of {WINDOW_CHOICES} pixels, not {window_px}")
    shape = WindowShape.named(window_shape)
    began = time.perf_counter()
    prefilter = Prefilter(prefilter_px)
    step_px = int(step_px or window_px // 2)
    pixel = float(min(pixel_size_mm))
    roi_spacing_mm = float(roi_spacing_mm or step_px * pixel)
    vessels = vessel_landmarks(landmarks or {})
    centres, kinds = window_centres(labels, pixel_size_mm, window_px, step_px, roi_spacing_mm, vessels)
    if len(centres) == 0:
        raise ValueError("the segmentation holds no fat or muscle where a DIC window could sit")
    # the outline's margin: the prefilter spreads the edge's error that far inside
    margin_px = prefilter.radius + 1 if respect_outline else None
    masks = window_pixel_masks(labels, centres, window_px, margin_px) if respect_outline else None
    first = correlate(unloaded, loaded, centres, pixel_size_mm, window_px=window_px, prior=motion, prefilter=prefilter,
                      pixel_masks=masks, workers=workers, shape=shape)
    attainable = attainable_confidence(unloaded, centres, window_px, first.noise_sigma, masks)
    trusted = _checks(first, min_confidence, max_uncertainty_px, step_px * pixel, attainable) == KEPT
    prior = prior_field(first.position_mm[trusted], first.displacement_mm[trusted], unloaded.shape, pixel_size_mm)
    result = correlate(unloaded, loaded, centres, pixel_size_mm, window_px=window_px, prior=motion,
                       prior_field_mm=prior, noise_sigma=first.noise_sigma, prefilter=prefilter, pixel_masks=masks,
                       workers=workers, shape=shape)
    # the error model calibrated on the residuals of the windows that matched (`prefilter`): the edges' error of
    # position, and the noise the images hold
    matched = np.isfinite(result.uncertainty_px) & (result.confidence >= min_confidence * attainable)
    edge_variance, residual_noise = fit_error_model([result.edge_residuals[k] for k in np.flatnonzero(matched)],
                                                    prefilter, RESIDUAL_ALPHA)
    excess = residual_excess(result, edge_variance, residual_noise, prefilter)
    result = result.calibrated(edge_variance, residual_noise, excess)
    status = _checks(result, min_confidence, max_uncertainty_px, step_px * pixel, attainable,
                     excess > MAX_RESIDUAL_EXCESS)
    # a window matched against the images' own noise estimate may hold less texture than the noise the residuals
    # calibrated: it is rejected and counted, not left to fail the operators of every other window
    candidates = np.flatnonzero(status == KEPT)
    flat = ~textured(unloaded, centres[candidates], window_px, result.noise_sigma[0], prefilter,
                     None if masks is None else [masks[k] for k in candidates], shape)
    status[candidates[flat]] = FLAT
    tissue_names = {0: "outside", FAT: "fat", MUSCLE: "muscle", 3: "bone"}
    tissue = [tissue_names.get(int(v), "muscle") for v in labels[centres[:, 0], centres[:, 1]]]
    kept = status == KEPT
    offset = np.full((len(centres), 2), np.nan)
    operators = None
    if kept.any():
        # what the windows see of the prior is not the prior at their centres: the data the model is compared with
        # are the displacements less that difference (measure_dic text)
        operators = WindowOperators(unloaded, centres[kept], window_px, pixel_size_mm, result.noise_sigma[0],
                                    prefilter=prefilter,
                                    pixel_masks=None if masks is None else [masks[k] for k in np.flatnonzero(kept)],
                                    fat_signal=None if fat_shift_mm is None else fat_signal(unloaded, labels),
                                    window_shape=shape)
        seen = operators.observe(prior)
        centre_values = np.stack([ndimage.map_coordinates(prior[c], result.centre_rc[kept].T, order=1, mode="nearest")
                                  for c in range(2)], axis=1)
        offset[kept] = centre_values - seen
    # does the loaded slice show the same tissue? (`imaging.coherence`: a slide along the leg between the sessions)
    through_kept = kept_field_warp(unloaded, loaded, pixel_size_mm, motion, result, status)
    coherence = [] if through_kept is None else slice_coherence(unloaded, through_kept[1], labels, result.noise_sigma)
    # boundaries drawn by point samples (a renderer's, not a scanner's) carry an error that the residuals cannot show
    to_loaded = loaded_index_map(prior, motion, pixel_size_mm)
    drawn = boundaries(labels, unloaded)
    point_sampling = detect_point_sampling(unloaded, labels, loaded, to_loaded,
                                           noise_sigma=float(np.sqrt(np.mean(np.square(first.noise_sigma)))),
                                           drawn=drawn)
    drawing_factor = None
    if point_sampling is not None and operators is not None:
        drawing_factor = drawn_boundaries_factor(drawn, unloaded.shape, point_sampling.samples, to_loaded, operators,
                                                 operators.to_mm, DRAWING_DRAWS)
    # the loaded texture that is not the unloaded texture moved (a thick slice the tissue slides through, the ringing
    # of the deformed leg): measured on the images through the kept windows' field
    texture_factor, texture = None, []
    if operators is not None and through_kept is not None:
        changes, texture = measure_change(unloaded, loaded, labels, *through_kept, result.noise_sigma, window_px,
                                          edge_variance)
        texture_factor = covariance_factor(window_covariance(operators, labels, changes))
    residual_over_model = np.array([window.residual_ratio(edge_variance, residual_noise)
                                    for window in result.edge_residuals])
    covariance = result.covariance_mm2.copy()
    for factor in (drawing_factor, texture_factor):
        if factor is not None:   # each kept window's own 2 x 2 block of F F^T
            per_window = factor.reshape(-1, 2, factor.shape[1])
            covariance[kept] += np.einsum("kad,kbd->kab", per_window, per_window)
    table = WindowTable(centres, kinds, result.position_mm, result.displacement_mm, covariance,
                        result.confidence, result.intensity_variance, tissue, [str(v) for v in status], offset,
                        residual_over_model, drawing_factor, texture_factor)
    measurements = dic_measurements(unloaded, table, window_px, pixel_size_mm, result.noise_sigma[0], prefilter_px,
                                    edge_variance, labels, operators=operators, fat_shift_mm=fat_shift_mm,
                                    motion=motion)
    summary = {"source": "dic", "window_px": window_px, "window_shape": shape.name, "step_px": step_px,
               "roi_spacing_mm": roi_spacing_mm,
               "prefilter_px": prefilter_px, "outline_margin_px": margin_px, "edge_variance_px2": edge_variance,
               "noise_scale": residual_noise,
               "windows_with_own_noise": int(np.sum((excess > 1.0) & kept)),
               "search_px": result.search_px, "windows": len(centres), "kept": int(table.kept.sum()),
               "status": table.counts(), "kinds": {k: int(sum(1 for x in kinds if x == k)) for k in KINDS},
               "noise_sigma": list(result.noise_sigma), "noise_sigma_estimated": list(first.noise_sigma),
               "median_sigma_mm": float(np.median(np.sqrt(np.diagonal(measurements.covariance_mm2)))),
               "rigid_motion": {"angle_deg": motion.angle_deg, "translation_mm": list(motion.translation_mm),
                                "centre_mm": list(motion.centre_mm)},
               "min_confidence": min_confidence, "max_uncertainty_px": max_uncertainty_px,
               "fat_shift_mm": None if fat_shift_mm is None else [float(v) for v in fat_shift_mm],
               "texture_coherence": [c.as_dict() for c in coherence],
               "through_plane_warning": coherence_sentence(coherence),
               "point_sampling": None if point_sampling is None else {
                   "samples_per_side": point_sampling.samples, "p_value": point_sampling.p_value,
                   "coverages": point_sampling.pixels, "draws": DRAWING_DRAWS,
                   "share_of_variance": (None if drawing_factor is None else
                                         float(np.sum(drawing_factor ** 2) / np.trace(measurements.covariance_mm2)))},
               "texture_change": {
                   "tissues": [change.as_dict() for change in texture],
                   "share_of_variance": (None if texture_factor is None else
                                         float(np.sum(texture_factor ** 2) / np.trace(measurements.covariance_mm2)))},
               "wall_time_s": time.perf_counter() - began}
    return measurements, table, summary


def residual_excess(result, edge_variance_px2: float, residual_noise: float, prefilter: Prefilter) -> np.ndarray:
    """(N,) each window's squared residual over what the calibrated error model predicts for it (`imaging.prefilter`:
    the edges' part and the typical noise ratio of the windows' residuals) where a chi^2 test at RESIDUAL_ALPHA on the
    window's independent values (its pixels over those one prefiltered value spreads over) finds it larger, 1
    elsewhere. A sliding interface, a vessel that fills, a texture aliased more than elsewhere shows here: the
    window's own noise is then taken that much larger (as the residual variance of a least-squares fit estimates
    it), and beyond MAX_RESIDUAL_EXCESS the match itself is in doubt."""
    excess = np.ones(len(result.confidence))
    if not np.isfinite(residual_noise) or residual_noise <= 0:
        return excess
    for k, window in enumerate(result.edge_residuals):
        if window.count == 0:
            continue
        if window.unpredicted(edge_variance_px2, residual_noise, prefilter, RESIDUAL_ALPHA):
            excess[k] = max(1.0, window.residual_ratio(edge_variance_px2, residual_noise))
    return excess


def _checks(result, min_confidence: float, max_uncertainty_px: float, step_mm: float, attainable: np.ndarray,
            unpredicted: np.ndarray | None = None) -> np.ndarray:
    """Status of every window: kept, or the first check it fails (module text). attainable: the ZNCC each window's
    texture and the images' noise allow (`imaging.dic.attainable_confidence`)."""
    status = np.full(len(result.confidence), KEPT, dtype=object)
    correlated = np.all(np.isfinite(result.displacement_px), axis=1)
    status[~correlated] = "not correlated (outside the image or no texture)"
    flat = correlated & (attainable < MIN_ATTAINABLE)
    status[flat] = f"too little texture (attainable ZNCC < {MIN_ATTAINABLE:g})"
    low = correlated & ~flat & (result.confidence < min_confidence * attainable)
    status[low] = f"low match (ZNCC < {min_confidence:g} of what its texture and noise allow)"
    uncertain = correlated & ~low & ~flat & ~(result.uncertainty_px <= max_uncertainty_px)
    status[uncertain] = f"uncertain (> {max_uncertainty_px:g} px)"
    if unpredicted is not None:
        status[(status == KEPT) & unpredicted] = f"residual over {MAX_RESIDUAL_EXCESS:g} x its error model"
    candidates = status == KEPT
    outliers = normalised_median_outliers(result.position_mm, result.displacement_px, candidates, radius_mm=3.0 * step_mm)
    status[outliers & candidates] = f"median test (> {MEDIAN_THRESHOLD:g})"
    return status


def kept_field_warp(unloaded: np.ndarray, loaded: np.ndarray, pixel_size_mm, motion: RigidMotion, result,
                    status: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the loaded image shows every pixel of I0 through the field the kept windows measured and the bones'
    motion ((2, H W) row and column indices), and I1 sampled there (cubic spline, NaN outside the image); None with
    too few kept windows for a field."""
    kept = status == KEPT
    if kept.sum() < 10:
        return None
    field = prior_field(result.position_mm[kept], result.displacement_mm[kept], unloaded.shape, pixel_size_mm)
    rows, cols = np.indices(unloaded.shape, dtype=float)
    where = loaded_index_map(field, motion, pixel_size_mm)(np.column_stack([rows.ravel(), cols.ravel()])).T
    warped = ndimage.map_coordinates(np.asarray(loaded, float), where, order=3, mode="constant",
                                     cval=np.nan).reshape(unloaded.shape)
    return where, warped


def slice_coherence(unloaded: np.ndarray, warped: np.ndarray, labels: np.ndarray, noise_sigma) -> list:
    """The fat's and the muscle's texture coherence between I0 and I1 sampled through the kept windows' field
    (`kept_field_warp`, `imaging.coherence`)."""
    values = []
    for name, label in (("fat", FAT), ("muscle", MUSCLE)):
        found = texture_coherence(unloaded, warped, tissue_mask(labels, label), noise_sigma, name)
        if found is not None:
            values.append(found)
    return values


def loaded_index_map(field_mm: np.ndarray, motion: RigidMotion, pixel_size_mm):
    """The map from reference indices (M, 2) (rows, columns) to where the loaded image shows them: moved by the
    displacement field (2, H, W) (mm, relative to the bones) and then by the bones' motion."""
    def to_loaded(indices: np.ndarray) -> np.ndarray:
        indices = np.asarray(indices, float)
        x, y = index_to_mm(indices[:, 0], indices[:, 1], pixel_size_mm)
        ux, uy = (ndimage.map_coordinates(field_mm[c], indices.T, order=1, mode="nearest") for c in range(2))
        rows, cols = mm_to_index(*motion.apply(x + ux, y + uy), pixel_size_mm)
        return np.stack([rows, cols], axis=1)

    return to_loaded


def prior_field(positions_mm: np.ndarray, displacement_mm: np.ndarray, shape, pixel_size_mm,
                smoothing: float = PRIOR_SMOOTHING) -> np.ndarray:
    """(2, H, W) thin-plate spline through the trusted first-pass displacements (mm), the prior by which the
    second pass deforms its windows (`imaging.dic`, window deformation)."""
    if len(positions_mm) < 10:
        raise ValueError(f"only {len(positions_mm)} DIC windows matched in the first pass: the images do not correlate; "
                         "check that both slices show the same level of the leg")
    spline = RBFInterpolator(positions_mm, displacement_mm, kernel="thin_plate_spline", smoothing=smoothing)
    x, y = pixel_centres_mm(shape, pixel_size_mm)
    values = np.concatenate([spline(np.column_stack([x.ravel()[k:k + 65536], y.ravel()[k:k + 65536]]))
                             for k in range(0, x.size, 65536)])
    return np.ascontiguousarray(values.T.reshape(2, *shape))


def dic_measurements(unloaded: np.ndarray, table: WindowTable, window_px: int, pixel_size_mm,
                     reference_noise_sigma: float, prefilter_px: float, edge_variance_px2: float,
                     labels: np.ndarray | None = None, outline_margin_px: int | None = None,
                     operators: WindowOperators | None = None, fat_shift_mm=None,
                     motion: RigidMotion | None = None, window_shape: str = DEFAULT_WINDOW_SHAPE) -> Measurements:
    """The kept windows of a table as Measurements (operators and covariance rebuilt from I0, prefiltered as the
    windows were correlated, over the pixels they matched (`window_pixel_masks` of labels, when the measurement
    left out the outline), with the error of the images' edges). operators: the kept windows' own, when the caller
    has built them already (`measure_dic`). fat_shift_mm: the fat's chemical shift (x, y), with the bones' `motion`
    between the images: the windows then see the fat where it lies on the image, and what they measure of its
    offset between the sessions, (R^T - I) delta, is taken out of the data (`imaging.windows`). window_shape: the
    shape function the windows were correlated with (`measure_dic`)."""
    kept = table.kept
    if kept.sum() < 10:
        raise ValueError(f"only {int(kept.sum())} DIC windows passed the checks ({table.counts()}); the images do "
                         "not correlate: check that both slices show the same level of the leg")
    shifted = fat_shift_mm is not None and labels is not None
    if operators is None:
        masks = (None if labels is None or outline_margin_px is None
                 else window_pixel_masks(labels, table.centres_rc[kept], window_px, outline_margin_px))
        operators = WindowOperators(unloaded, table.centres_rc[kept], window_px, pixel_size_mm, reference_noise_sigma,
                                    prefilter=Prefilter(prefilter_px), pixel_masks=masks,
                                    fat_signal=fat_signal(unloaded, labels) if shifted else None,
                                    window_shape=WindowShape.named(window_shape))
    covariance = operators.covariance(table.intensity_variance[kept], edge_variance_px2)
    for factor in (table.drawing_factor_mm, table.texture_factor_mm):
        if factor is not None:
            covariance += factor @ factor.T
    kinds = [k for k, keep in zip(table.kind, kept) if keep]
    offset = 0.0 if table.prior_offset_mm is None else table.prior_offset_mm[kept]
    if shifted:
        delta = np.asarray(fat_shift_mm, float)
        rotation = np.eye(2) if motion is None else motion.rotation
        offset = offset + operators.fat_offsets((rotation.T - np.eye(2)) @ delta)
    return Measurements("dic", table.position_mm[kept], table.displacement_mm[kept] - offset, covariance, operators, True,
                        f"DIC: {int(kept.sum())} windows of {window_px} px kept of {len(kept)}", kinds,
                        reference_noise_sigma=float(reference_noise_sigma),
                        fat_shift_mm=(float(fat_shift_mm[0]), float(fat_shift_mm[1])) if shifted else None)


def reference_noise_covariance(first: Measurements, second: Measurements) -> np.ndarray | None:
    """(2 N_1, 2 N_2) covariance (mm^2) between the errors of two DIC measurements made on the same reference I0
    (two garment levels: the same windows of I0, correlated with two loaded images). A window's error is the
    loaded image's noise less the reference's, both through B_i (`imaging.windows`); the reference's noise is one
    and the same in both, so Cov(u_i, u_j) = sigma_0^2 sum_{x in both} B_i(x) B_j(x)^T over the pixels of I0 that
    windows i and j share (half of each window's variance when I0 and I1 are equally noisy). None for points."""
    a, b = first.operators, second.operators
    if a is None or b is None or first.reference_noise_sigma is None or second.reference_noise_sigma is None:
        return None
    if (a.window_px != b.window_px or a.window_shape != b.window_shape or a.shape != b.shape
            or not np.allclose(a.to_mm, b.to_mm) or a.prefilter != b.prefilter):
        raise ValueError("two garment levels measured with other windows or on another reference image")
    variance = first.reference_noise_sigma * second.reference_noise_sigma
    to_mm = np.diag(a.to_mm)
    reach = a.window_px - 1 + 2 * a.prefilter.radius + 1e-9
    covariance = np.zeros((2 * len(a), 2 * len(b)))
    tree = cKDTree(b.centres)
    for i, centre in enumerate(a.centres):
        for j in tree.query_ball_point(centre, reach * np.sqrt(2)):
            if np.any(np.abs(centre - b.centres[j]) > reach):
                continue
            shared, in_i, in_j = np.intersect1d(a.noise_pixels[i], b.noise_pixels[j], assume_unique=True,
                                                return_indices=True)
            if shared.size:
                weight = variance * a.noise_ratio[shared]
                covariance[2 * i:2 * i + 2, 2 * j:2 * j + 2] = to_mm @ ((a.B[i][:, in_i] * weight) @ b.B[j][:, in_j].T) @ to_mm
    return covariance


# --- run folder ---------------------------------------------------------------------------------

def write_measurements(run_dir: Path, table: WindowTable, summary: dict, image: np.ndarray, pixel_size_mm,
                       level: int = 1) -> None:
    """The table, the arrays, the summary and the picture (of garment level `level`, `level_files`), each written
    to a temporary name then renamed."""
    from .figure import dic_vectors_figure

    run_dir = Path(run_dir)
    files = level_files(level)
    temporary = run_dir / f".{files['arrays']}.tmp.npz"
    residual_over_model = (np.full(len(table.status), np.nan) if table.residual_over_model is None
                           else table.residual_over_model)
    np.savez_compressed(temporary, centres_rc=table.centres_rc, kind=np.array(table.kind), position_mm=table.position_mm,
                        displacement_mm=table.displacement_mm, covariance_mm2=table.covariance_mm2,
                        confidence=table.confidence, intensity_variance=table.intensity_variance,
                        tissue=np.array(table.tissue), status=np.array(table.status),
                        prior_offset_mm=table.prior_offset_mm, residual_over_model=residual_over_model,
                        **{name: factor for name, factor in (("drawing_factor_mm", table.drawing_factor_mm),
                                                             ("texture_factor_mm", table.texture_factor_mm))
                           if factor is not None})
    temporary.replace(run_dir / files["arrays"])
    rows = ["x_mm,y_mm,ux_mm,uy_mm,var_x_mm2,var_y_mm2,cov_xy_mm2,confidence,residual_over_model,offset_x_mm,"
            "offset_y_mm,kind,tissue,status"]
    for k in range(len(table.status)):
        c = table.covariance_mm2[k]
        values = [*table.position_mm[k], *table.displacement_mm[k], c[0, 0], c[1, 1], c[0, 1], table.confidence[k],
                  residual_over_model[k], *table.prior_offset_mm[k]]
        rows.append(",".join(f"{v:.6g}" for v in values) + f",{table.kind[k]},{table.tissue[k]},{table.status[k]}")
    temporary = run_dir / f".{files['table']}.tmp"
    temporary.write_text("\n".join(rows) + "\n", encoding="utf-8")
    temporary.replace(run_dir / files["table"])
    dic_vectors_figure(run_dir / files["figure"], image, pixel_size_mm, table, summary)
    write_json(run_dir / files["summary"], summary)


def read_window_table(run_dir: Path, level: int = 1) -> WindowTable | None:
    """The windows of garment level `level` that `calfit measure` stored, None when it has not run."""
    path = Path(run_dir) / level_files(level)["arrays"]
    if not path.is_file():
        return None
    with np.load(path) as arrays:
        return WindowTable(arrays["centres_rc"], [str(v) for v in arrays["kind"]], arrays["position_mm"],
                           arrays["displacement_mm"], arrays["covariance_mm2"], arrays["confidence"],
                           arrays["intensity_variance"], [str(v) for v in arrays["tissue"]],
                           [str(v) for v in arrays["status"]], arrays["prior_offset_mm"],
                           arrays["residual_over_model"] if "residual_over_model" in arrays.files else None,
                           arrays["drawing_factor_mm"] if "drawing_factor_mm" in arrays.files else None,
                           arrays["texture_factor_mm"] if "texture_factor_mm" in arrays.files else None)

