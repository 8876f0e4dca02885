"""How the images were drawn: boundaries point-sampled S x S times per pixel, and the error it makes in the windows.

A renderer that sets each pixel to the mean of S x S point samples of the tissue (each sample wholly in one tissue:
no anti-aliasing of the samples) draws a boundary's pixel with a coverage of k / S^2, not the share of the pixel the
tissue covers. Where it puts the boundary is then off by an amount that depends on where the boundary crosses the
pixel, and is the same wherever a boundary crosses alike. Along an oblique boundary the crossing changes from pixel to
pixel and the errors average out over a window, as `prefilter`'s edge term has them. Where a boundary runs along the
pixel grid (or its diagonal) its pixels cross alike for tens of pixels: their errors add up over a window, which takes
them for motion, and its residual, on which `prefilter` calibrates s_edge^2, does not show them. On the other
program's calf cases (a 3 x 3 renderer) that error, computed from their true meshes, is what held the fat more than
5 mm under the skin at chi^2/n 1.26 against the true field (0.92 without it; docs/validation/error-model.md,
`benchmarks/error_budget.py --sampling`). A scanner does not draw so (its image is band-limited by the k-space it
acquires), nor do renderers that anti-alias their samples (calfit's two phantoms); only point-sampled renders do.

Detection (`detect_point_sampling`). The coverage of each pixel the leg's outline crosses is read from its grey level
between the levels either side of it along the normal (air outside, LEVEL_DEPTH_PX away; the tissue inside), and a
point-sampled image puts those coverages on the comb k / S^2. The Rayleigh test of the phases 2 pi S^2 c over the
coverages within [1.5 / S^2, 1 - 1.5 / S^2] (a whole number of the comb's periods, so a uniform spread of coverages
has no power there; the first and last steps are left out, where the flat ends of a band-limited edge's profile and
the air's Rician bias pile coverages up: calfit's first phantom reached n R^2 = 9.4 at 9 cycles with them, one case in
six, and 0.4-2.7 without), pooled over both images' outlines, gives p = exp(-n R^2), R the mean resultant length of
the n phases; the images are taken as point-sampled by the S of the smallest p when p < DETECTION_ALPHA / the number
of S tried. Only the S from MIN_SAMPLES to MAX_SAMPLES whose steps 1 / S^2 stand RESOLVED times above the coverages'
scatter (about COVERAGE_NOISE_GAIN sigma / step, sigma the images' noise, step the outline's grey-level step) are
tried: a finer comb drowns in the noise, and a spread of coverages that is merely not smooth would pass for one (the
image's own segmentation of an anti-aliased bright outline: n R^2 up to 10 at 25-36 cycles, 4-10 beside them). S = 2
is not tried: the grey levels across a band-limited edge spread smoothly but unevenly over the coverages, with as much
power at 4 cycles as a weak comb (calfit's first phantom: n R^2 = 8 there). Finer sampling than MAX_SAMPLES draws the
boundaries within 1 / (MAX_SAMPLES sqrt(12)) px. Measured: the other program's four cases S = 3 at p = 6e-13 to 7e-20
(both images); calfit's two phantoms, and its second drawn anti-aliased with a bright skin, none; its second
point-sampled (`MRIPhantom(anti_aliased=False)`) S = 3 with a bright skin (p = 3e-13), none with its grey skin, whose
steps of 1/9 are under three times the scatter (tests/measure/test_drawing.py, docs/validation/error-model.md).

The windows' error (`drawn_boundaries_factor`). The boundaries are the labels' contours (the leg's outline and the
muscle's boundary, leaving out the bones, which do not move), smoothed along their arc over ALONG_ARC_PX so that the
labels' own staircase does not make them straighter than the tissue, with outward normals and the grey-level step
across each. In each image a pixel within REACH_PX of a boundary is drawn with S x S samples and exactly (`covered`, the
share of the pixel inside), from its signed distance to the boundary along the normal (the boundary is straight
within a pixel); the difference times the step is the drawing's error of intensity. The loaded image's boundaries are
the reference's moved by the measured field and the bones' motion, and its error is pulled back onto the reference's
pixels; a window's error is then B~ (dI0 - dI1 o phi) (`windows`; IC-GN composes the inverse of its step). Where the
leg sits on the pixel grid is not known to a fraction of a pixel, so the scene is moved by a random sub-pixel shift in
both images, `draws` times: the columns of F (2N, draws) are those errors over sqrt(draws), and F F^T is added to the
windows' covariance (its mean over the shifts is zero: S x S samples of a randomly placed pixel cover it exactly on
average).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage import measure

from ..core.tissues import BONE, MUSCLE
from ..imaging.mismatch import tissue_mask
from .dic import estimate_noise_sigma

MIN_SAMPLES, MAX_SAMPLES = 3, 6   # point samples per pixel side tested for (module text)
DETECTION_ALPHA = 1e-4     # the comb test's level, over all the S tried
RESOLVED = 3.0             # a comb is told only where its steps are this many times the coverages' scatter
END_STEPS = 1.5            # the coverages within this many steps of 0 and 1 are left out of the test (module text)
COVERAGE_NOISE_GAIN = 1.2  # that scatter over sigma / step (module text)
REACH_PX = 2.5             # pixels this close to a boundary can be crossed by it
CONTOUR_STEP_PX = 0.1      # spacing of the boundaries' points
CONTOUR_SMOOTHING_PX = 1.5  # the labels' indicator smoothed this much before its 0.5 contour is taken
ALONG_ARC_PX = 6.0         # then smoothed along the arc: longer than the labels' flat runs where the outline runs
#                            along the grid (sqrt(2 R) ~ 15 px at R = 40 mm), short enough that it sags by
#                            ALONG_ARC_PX^2 / 2R <= 0.2 px
BONE_MARGIN_PX = 3         # boundary points this close to a bone are left out (the bones do not move)
LEVEL_DEPTH_PX = (2.5, 3.5)  # where the grey levels either side of an outline pixel are read, along its normal
MIN_BOUNDARY_PX = 20.0     # shorter contours (specks of a label) are not boundaries


@dataclass(frozen=True)
class Boundary:
    """A boundary between two tissues in the reference: points (M, 2) (row, column) every CONTOUR_STEP_PX, their
    outward normals, the grey-level step across it (inside less outside) and which points are drawn (not at a bone)."""

    points: np.ndarray
    normals: np.ndarray
    step: float
    drawn: np.ndarray
    outline: bool = False   # the leg's outline (against air), not a boundary inside it

    def moved(self, to_loaded) -> "Boundary":
        """The same boundary in the loaded image: to_loaded maps (M, 2) reference indices to loaded ones."""
        points = to_loaded(self.points)
        normals = _normals(points)
        normals *= np.sign(np.sum(normals * self.normals, axis=1, keepdims=True))
        return Boundary(points, normals, self.step, self.drawn, self.outline)


@dataclass(frozen=True)
class PointSampling:
    """The comb test's verdict (module text): samples per pixel side, its p-value, the coverages it read."""

    samples: int
    p_value: float
    pixels: int


def _normals(points: np.ndarray) -> np.ndarray:
    tangent = np.gradient(points, axis=0)
    normals = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def boundaries(labels: np.ndarray, reference: np.ndarray) -> list[Boundary]:
    """The leg's outline and the muscle's boundary in the reference (module text)."""
    labels = np.asarray(labels)
    reference = np.asarray(reference, float)
    near_bone = ndimage.binary_dilation(labels == BONE, iterations=BONE_MARGIN_PX)
    out = []
    for outline, region in ((True, labels > 0), (False, tissue_mask(labels, MUSCLE))):
        if not region.any() or region.all():
            continue
        inside = ndimage.binary_erosion(region, iterations=1) & ~ndimage.binary_erosion(region, iterations=4)
        outside = ~ndimage.binary_dilation(region, iterations=1) & ndimage.binary_dilation(region, iterations=4)
        inside, outside = inside & ~near_bone, outside & ~near_bone
        if not inside.any() or not outside.any():
            continue
        step = float(np.median(reference[inside]) - np.median(reference[outside]))
        smooth = ndimage.gaussian_filter(region.astype(float), CONTOUR_SMOOTHING_PX)
        grad_rows, grad_cols = np.gradient(smooth)
        for contour in measure.find_contours(smooth, 0.5):
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(contour, axis=0), axis=1))])
            if arc[-1] < MIN_BOUNDARY_PX:
                continue
            along = np.arange(0.0, arc[-1], CONTOUR_STEP_PX)
            points = np.stack([np.interp(along, arc, contour[:, 0]), np.interp(along, arc, contour[:, 1])], axis=1)
            closed = bool(np.allclose(contour[0], contour[-1]))
            points = ndimage.gaussian_filter1d(points, ALONG_ARC_PX / CONTOUR_STEP_PX, axis=0,
                                               mode="wrap" if closed else "nearest")
            normals = _normals(points)
            # outward: down the smoothed indicator
            downhill = -(ndimage.map_coordinates(grad_rows, points.T, order=1) * normals[:, 0]
                         + ndimage.map_coordinates(grad_cols, points.T, order=1) * normals[:, 1])
            normals *= np.sign(np.sum(downhill)) or 1.0
            index = np.clip(np.round(points).astype(int), 0, np.array(labels.shape) - 1)
            out.append(Boundary(points, normals, step, ~near_bone[index[:, 0], index[:, 1]], outline))
    return out


def _sample_offsets(samples: int) -> np.ndarray:
    """(samples^2, 2) the point samples' offsets from a pixel's centre (rows, columns), on a regular lattice."""
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    rows, cols = np.meshgrid(offsets, offsets, indexing="ij")
    return np.stack([rows.ravel(), cols.ravel()], axis=1)


@dataclass(frozen=True)
class Crossing:
    """The pixels near a boundary (K, 2), their signed distances to it along its normal (pixels; the boundary is
    straight within a pixel, so a shift s of the scene makes them distance - normals . s) and the normals there."""

    pixels: np.ndarray
    distance: np.ndarray
    normals: np.ndarray
    step: float


def crossings(shape, drawn: list[Boundary], reach_px: float = REACH_PX + 1.0) -> list[Crossing]:
    """Each boundary's pixels within reach_px of its drawn points (module text)."""
    out = []
    for boundary in drawn:
        points = boundary.points[boundary.drawn]
        if len(points) == 0:
            continue
        on = np.zeros(shape, bool)
        index = np.round(points).astype(int)
        within = np.all((index >= 0) & (index < np.array(shape)), axis=1)
        on[index[within, 0], index[within, 1]] = True
        candidates = np.argwhere(ndimage.binary_dilation(on, np.ones((3, 3), bool), iterations=int(np.ceil(reach_px))))
        distance, nearest = cKDTree(points).query(candidates.astype(float), distance_upper_bound=reach_px)
        near = np.isfinite(distance)
        pixels, nearest = candidates[near], nearest[near]
        normals = boundary.normals[boundary.drawn][nearest]
        out.append(Crossing(pixels, np.einsum("ij,ij->i", pixels - points[nearest], normals), normals,
                            boundary.step))
    return out


def covered(distance: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The exact share of a pixel on the inside of a straight boundary at signed distance `distance` from its centre
    (positive outside) with unit normals (K, 2): P(a X + b Y < -distance) for X, Y uniform over the pixel, whose
    density is a trapezoid on [-(|a| + |b|) / 2, (|a| + |b|) / 2] with its flat top over [-||a| - |b|| / 2, ...]."""
    u, v = np.abs(normals[:, 0]), np.abs(normals[:, 1])
    wide, narrow = np.maximum(u, v), np.minimum(u, v)
    t = -np.asarray(distance, float)
    outer, inner = 0.5 * (wide + narrow), 0.5 * (wide - narrow)
    ramp = np.maximum(2.0 * wide * narrow, 1e-300)
    rising = np.clip(t + outer, 0.0, outer - inner) ** 2 / ramp
    flat = np.clip(t + inner, 0.0, 2.0 * inner) / wide
    falling = (outer - inner) ** 2 / ramp - np.clip(outer - t, 0.0, outer - inner) ** 2 / ramp
    share = np.where(narrow * wide > 1e-9, rising + flat + falling, np.clip(t / wide + 0.5, 0.0, 1.0))
    return np.clip(share, 0.0, 1.0)


def drawing_error(shape, crossed: list[Crossing], samples: int, shift=(0.0, 0.0)) -> np.ndarray:
    """The error of intensity of an image whose boundaries (`crossings`, moved by shift, pixels) are drawn with
    samples x samples point samples per pixel, less their exact coverage (module text)."""
    error = np.zeros(shape)
    offsets = _sample_offsets(samples)
    shift = np.asarray(shift, float)
    for crossing in crossed:
        distance = crossing.distance - crossing.normals @ shift
        near = np.abs(distance) < REACH_PX
        distance, normals, pixels = distance[near], crossing.normals[near], crossing.pixels[near]
        sampled = np.mean(distance[:, None] + normals @ offsets.T < 0.0, axis=1)
        np.add.at(error, (pixels[:, 0], pixels[:, 1]), crossing.step * (sampled - covered(distance, normals)))
    return error


def outline_coverages(image: np.ndarray, outline: Boundary) -> np.ndarray:
    """The coverage of each pixel the outline crosses, from its grey level between the levels read either side of
    it along the normal (module text)."""
    image = np.asarray(image, float)
    found = crossings(image.shape, [outline])
    if not found:
        return np.zeros(0)
    crossed = np.abs(found[0].distance) < 0.5 * np.sqrt(2.0)
    pixels, normals = found[0].pixels[crossed].astype(float), found[0].normals[crossed]

    def level(sign):
        return np.mean([ndimage.map_coordinates(image, (pixels + sign * depth * normals).T, order=1)
                        for depth in LEVEL_DEPTH_PX], axis=0)

    inside, outside = level(-1.0), level(+1.0)
    values = image[pixels[:, 0].astype(int), pixels[:, 1].astype(int)]
    step = inside - outside
    usable = np.abs(step) > 0.25 * abs(outline.step)
    return (values[usable] - outside[usable]) / step[usable]


def detect_point_sampling(reference: np.ndarray, labels: np.ndarray, loaded: np.ndarray | None = None,
                          to_loaded=None, noise_sigma: float | None = None,
                          drawn: list[Boundary] | None = None) -> PointSampling | None:
    """Whether the images' outline is point-sampled, and how finely (module text); None when the test finds no
    comb. The loaded image's outline (the reference's moved by to_loaded, `Boundary.moved`) adds its coverages.
    noise_sigma: the images' raw noise (default: the reference's own estimate in the leg), which sets the finest
    comb that can be told (module text); drawn: `boundaries(labels, reference)` when the caller has them."""
    drawn = boundaries(labels, reference) if drawn is None else drawn
    outlines = [boundary for boundary in drawn if boundary.outline]
    if not outlines:
        return None
    outline = max(outlines, key=lambda boundary: len(boundary.points))
    coverage = outline_coverages(reference, outline)
    if loaded is not None and to_loaded is not None:
        coverage = np.concatenate([coverage, outline_coverages(loaded, outline.moved(to_loaded))])
    sigma = estimate_noise_sigma(reference, np.asarray(labels) > 0) if noise_sigma is None else float(noise_sigma)
    # a coverage read from three noisy grey levels (the pixel's, and the two levels' means of two) scatters by about
    # 1.2 sigma / step: a comb whose steps are not RESOLVED times that apart cannot be told from a smooth spread
    scatter = COVERAGE_NOISE_GAIN * sigma / max(abs(outline.step), 1e-300)
    finest = int(np.floor(np.sqrt(1.0 / (RESOLVED * scatter)))) if scatter > 0 else MAX_SAMPLES
    tried = range(MIN_SAMPLES, min(MAX_SAMPLES, finest) + 1)
    if len(tried) == 0:
        return None
    best = None
    for samples in tried:
        period = samples * samples
        within = coverage[(coverage > END_STEPS / period) & (coverage < 1.0 - END_STEPS / period)]
        if len(within) < 50:
            continue
        resultant = abs(np.mean(np.exp(2j * np.pi * period * within)))
        p_value = float(np.exp(-len(within) * resultant ** 2))
        if best is None or p_value < best.p_value:
            best = PointSampling(samples, p_value, len(within))
    if best is None or best.p_value >= DETECTION_ALPHA / len(tried):
        return None
    return best


def drawn_boundaries_factor(drawn: list[Boundary], shape, samples: int, to_loaded, operators, to_mm, draws: int,
                            seed: int = 0) -> np.ndarray:
    """(2N, draws) F with F F^T the covariance (mm^2) of the windows' error from the reference's boundaries
    (`boundaries`) point-sampled samples x samples times per pixel in both images of `shape` (module text).
    to_loaded maps (M, 2) reference indices (rows, columns) to the loaded image's; operators: the windows'
    `WindowOperators`; to_mm: (2,) mm per pixel along x and y."""
    reference_crossings = crossings(shape, drawn)
    loaded_crossings = crossings(shape, [boundary.moved(to_loaded) for boundary in drawn])
    grid = np.indices(shape, dtype=float).reshape(2, -1).T
    rng = np.random.default_rng(seed)
    columns = []
    for _ in range(draws):
        shift = rng.uniform(-0.5, 0.5, 2)
        reference_error = drawing_error(shape, reference_crossings, samples, shift)
        loaded_error = drawing_error(shape, loaded_crossings, samples, shift)
        # the scene moved by shift in both images: reference pixel y shows what the unshifted one shows at y - shift
        back = (to_loaded(grid - shift) + shift).T
        difference = (reference_error - ndimage.map_coordinates(loaded_error, back, order=1, mode="constant")
                      .reshape(shape)).ravel()
        columns.append(np.concatenate([(B @ difference[pixels]) * to_mm
                                       for B, pixels in zip(operators.B, operators.noise_pixels)]))
    return np.array(columns).T / np.sqrt(draws)
