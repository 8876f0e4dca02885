"""Rigid alignment of the loaded volume on the unloaded one, on the bones, and the loaded volume seen on a slice of
the unloaded one.

Between the two sessions of a volume study the leg moves rigidly in the scanner: it slides along its axis by
several mm, turns about it by a few degrees, tilts by a degree or two and shifts in the plane. As in the 2D case
(`align`, after Bouten and Drapier sec. 3.1: "a rotation and a translation, so that the surface centre of the bones
coincide in both images"), the motion is found on the bones, which are rigid and clamped to the muscle, in the same
two steps, plus one for what the bones' centroids cannot say:

1. bone axes: every slice of both volumes is segmented (`segment_t1`, label 3), twice when the fat's chemical
   shift is given (knowing it and not: each found bones the other missed), the bone of either kept; the tibia is
   a component of at least TIBIA_AREA_SHARE of the largest bone of both volumes, the fibula the largest smaller
   one clear of the tibia's line (by size, as in 2D: a tibia's cross-section is several times a fibula's; not
   simply the largest and the second of each slice, since a slice where only a piece of the tibia is found
   would pass that piece for the tibia). A line is fitted to
   each bone's per-slice centroids (patient mm) in each volume. The rotation is the one that best superposes, by
   the Kabsch (Wahba) solution, three directions: the tibia's line, the fibula's line, and the tibia-to-fibula
   offset across them at the middle height; the translation superposes the lines' points at that height. This
   takes the tilt and the turn about the leg from every slice at once, which the other way the design allowed (the
   centroid of all bone voxels plus the 2D alignment of the middle slice) cannot: one slice says nothing of the
   tilt. Directions rather than points paired at equal heights, because the tilt itself moves the two bones to
   different heights (0.4 mm up and 0.6 mm down on the test phantom), and points paired at equal heights denied
   the tilt about the line between the bones (0.5 degree left in the start). With one bone only, the rotation is
   the least one that takes its line onto the other's (no turn about the leg, as `align` starts with one bone).
2. the slide: the centroids do not fix it. Bones are nearly prisms, so their centroid lines are the same lines
   whatever the slide, and both slabs' centroids sit at their own middle height. The slide is started by a scan
   of the grey-level cost of step 3 along the slice normal, every `slide_step_mm` within `max_slide_mm` of step 1's
   solution, the other five parameters held. Step 1 is then made again with the loaded lines met that much
   higher (an inclined bone's course over the slide had passed for a turn: 1 degree of the test's 4), and the
   slide scanned again near there, finer.
3. refinement: the six parameters (rotation vector and translation in the unloaded slice frame, about the unloaded
   bones' centre) are adjusted by scipy's least_squares to match the normalised grey levels of the unloaded volume
   over its bones and a thin rim around them (`rim_mm`, as in 2D) with the loaded volume sampled at
   ``motion.apply(points)``. The grey levels are normalised slice by slice of the unloaded volume (mean 0, std 1),
   so that a coil's fall-off along the leg does not weigh as a mismatch.

What is weakly determined: the slide. A bone's shaft is nearly a prism, so the cost varies little along the leg,
and the slices, 2-10 mm apart, are interpolated linearly between them. The slide is determined by two things only:
the change of the bones' cross-sections with height (the tibia's flare, the fibula thinning) and the bones'
inclination to the slice normal, which differs between the tibia and the fibula (a slide then moves their
cross-sections apart in the plane). Two parallel prisms along the normal would leave it free, and the result
would be the scan's guess. On the test phantom (cross-sections changing by 1-2 mm over its 44 mm slab, bones
inclined 4 and 5 degrees): within 0.1 mm; with the changes of shape removed, 0.14 mm, from the inclinations alone,
while the scan had started 2.3 mm off. The optimisation is kept robust to it by the scan of step 2 (a gradient
step from a slide of zero may stall in the flat cost), and by `x_scale`: the slide's scale is a tenth of a slice
spacing where the others' is a tenth of a pixel or 0.1 degree, so that a trust-region step along the slide is
not held to a pixel's length. The points that take part are those that fall inside the loaded slab (between its
first and last slice, not in the half spacing beyond) at the current estimate; they are chosen before each
least_squares run and kept during it, so that the cost is continuous, and chosen again after it until they no
longer change.

The slide's bias: the loaded volume is interpolated between its slices and the unloaded one was sampled at its
voxels. Interpolation averages the noise of two slices (at half a spacing its variance is half), so a cost as flat
as the slide's fell by more where the loaded samples lay between slices than where they lay on them, and the slide
was pulled towards half a spacing: on the k-space phantom (3 mm slices, 4 mm thick, the leg slid 3 mm and tilted
1.5 degrees) 2.50 mm at the leg's centre against 3.00 true, with a jackknife error of 0.1 mm. The unloaded bones are
therefore taken at HEIGHTS_PER_SLICE heights between each slice and the next, the unloaded volume interpolated
there as the loaded one is; over those heights the noise the two interpolations leave no longer depends on the
slide (its share varies by 3 / (4 N^2) of itself, 8 % at N = 3, 50 % at N = 1), and the slide came to 2.98 mm.

The slide of what: the motion is a rotation and a translation, and when the leg tilts, every point slides along
the leg by a different amount: the translation along the normal plus the tilt times the point's distance from the
tilt's axis (1.5 degrees over the 30 mm between the bones' centre and the leg's: 0.8 mm). `slide_mm` is the
bones' centre's, the point the motion is written about; `slide_at` gives any point's, and `calfit study` reports
the leg's centre of each studied slice (`study.volume_cases.leg_slide`), which is what the loaded slice of a
tapering leg shows higher or lower. `slide_sd_at` is the delete-one-slice jackknife of the refinement: the
refinement made again from the estimate without each unloaded slice's points, the spread of the refits times
(n - 1) / n. It holds the noise and the texture of each slice, not a bias common to all.

Sampling through slices (`_SliceStack`, used by both the alignment and `resample_on_slice`): cubic B-spline
within a slice, where pixels are 0.3-0.8 mm apart and a cubic follows the edges, and linear between two slices,
2-10 mm apart, where a cubic through a bone's end or an interface crossing the slice would overshoot. NaN voxels
are filled for the spline by their nearest valid voxel in the slice, and a sample is NaN where a NaN voxel takes
part in its linear interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize
from scipy.spatial.transform import Rotation
from skimage import morphology

from ..case.volume import RigidMotion3D, Volume
from ..core.errors import ImagingError
from ..core.frame import mm_to_index
from ..core.tissues import BONE
from .align import bone_centroids
from .segment import segment_t1

MIN_POINTS_PER_SLICE = 20    # an unloaded slice with fewer bone and rim points takes no part (its std is noise)
MIN_OVERLAP = 0.5            # share of the bone and rim points that must fall inside the loaded slab
INSIDE_MARGIN_PIXELS = 2     # points within two pixels of the loaded matrix's edge take no part (cubic support)
MAX_POINT_SETS = 4           # least_squares runs, each with the points inside at the previous estimate
LINE_OUTLIER_MM = 3.0        # a per-slice centroid farther than this from its bone's line is left out of the fit
HEIGHTS_PER_SLICE = 3        # the unloaded bones sampled at this many heights per slice spacing (the slide's bias)
TIBIA_AREA_SHARE = 0.6       # a component of at least this share of the largest bone's area is the tibia


@dataclass(frozen=True)
class VolumeAlignment:
    """The rigid motion between the sessions found on the bones, and how well it superposes them.

    motion: maps a patient point of the unloaded session to where the same bone point is in the loaded session,
    about the centre of the unloaded bones. start: the estimate from the bone axes and the slide scan, before the
    grey-level refinement. rotation_deg and translation_mm: the motion's rotation vector and translation (of the bone
    centre) in the unloaded slice frame (column direction, row direction, slice normal). centroid_rms_mm: RMS
    in-plane distance between each unloaded bone centroid moved by the motion and the loaded bone's centroid at the
    same height (interpolated between its slices), over the slices and bones where both are found. correlation:
    normalised correlation of the grey levels over the bones and rim at the estimate, the mean over the unloaded
    slices weighted by their points (1 for a perfect match).
    bones_per_slice_*: bone components found in each slice. points, slices_used: unloaded voxels and slices that
    took part in the refinement.
    """

    motion: RigidMotion3D
    start: RigidMotion3D
    rotation_deg: tuple[float, float, float]
    translation_mm: tuple[float, float, float]
    centroid_rms_mm: float
    correlation: float
    bones_per_slice_unloaded: tuple[int, ...]
    bones_per_slice_loaded: tuple[int, ...]
    points: int
    slices_used: int
    jackknife: tuple[RigidMotion3D, ...] = ()
    fat_shift_mm: float = 0.0

    def slide_at(self, points_mm) -> np.ndarray:
        """How far the motion moves patient points (3, ...) of the unloaded session along the slice normal (mm):
        the slide of the leg there. A tilted leg slides by different amounts across the slice, by the tilt times
        the distance from the tilt's axis (module text, "The slide of what")."""
        return _along_normal(self.motion, points_mm, self.normal)

    def slide_sd_at(self, points_mm) -> np.ndarray:
        """The standard error of `slide_at`: the delete-one-slice jackknife of the refinement (module text); NaN
        without one."""
        if len(self.jackknife) < 3:
            return np.full(np.shape(points_mm)[1:], np.nan)
        values = np.stack([_along_normal(motion, points_mm, self.normal) for motion in self.jackknife])
        n = len(values)
        return np.sqrt((n - 1) / n * np.sum((values - values.mean(axis=0)) ** 2, axis=0))

    @property
    def normal(self) -> np.ndarray:
        return np.asarray(self.normal_vector, float)

    normal_vector: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @property
    def turn_deg(self) -> float:
        """Rotation about the slice normal (the leg's axis in an axial series)."""
        return self.rotation_deg[2]

    @property
    def tilt_deg(self) -> float:
        """Rotation about an axis in the slice plane."""
        return float(np.hypot(self.rotation_deg[0], self.rotation_deg[1]))

    @property
    def in_plane_translation_mm(self) -> tuple[float, float]:
        return self.translation_mm[0], self.translation_mm[1]

    @property
    def slide_mm(self) -> float:
        """Translation of the bone centre along the slice normal: the weakly determined one (module text). Not the
        slide of the leg's centre when the leg tilts: `slide_at`."""
        return self.translation_mm[2]


def _along_normal(motion: RigidMotion3D, points_mm, normal: np.ndarray) -> np.ndarray:
    points = np.asarray(points_mm, float)
    return np.tensordot(normal, motion.apply(points) - points, axes=1)


# ----------------------------------------------------------------- sampling through slices


class _SliceStack:
    """A volume sampled at continuous (row, column, slice) indices: cubic B-spline within a slice, linear between
    two slices (module text). Each slice's spline coefficients are made when first needed, so that resampling one
    slice of a long series filters only the two slices it falls between."""

    def __init__(self, voxels: np.ndarray):
        self._voxels = voxels
        self.rows, self.columns, self.count = voxels.shape
        self._planes: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}

    def _plane(self, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Spline coefficients of slice k, and its mask of NaN voxels as floats (None when it has none)."""
        if k not in self._planes:
            values = np.array(self._voxels[:, :, k], dtype=float)
            missing = ~np.isfinite(values)
            if missing.all():
                values[:] = 0.0
            elif missing.any():
                # the nearest valid voxel, not a constant: a constant would ring through the spline into valid pixels
                nearest = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
                values = values[tuple(nearest)]
            coefficients = ndimage.spline_filter(values, order=3, mode="mirror")
            self._planes[k] = coefficients, (missing.astype(float) if missing.any() else None)
        return self._planes[k]

    def sample(self, index: np.ndarray, *, nan_outside: bool, through_plane: str = "linear",
               beyond_slices: float = 0.5) -> np.ndarray:
        """Values at continuous indices (3, ...). nan_outside: NaN beyond the matrix (more than half a pixel from
        its edge pixels' centres), beyond the first or last slice by more than `beyond_slices` of a slice, and where
        a NaN voxel takes part; otherwise the edge values continue outside, so that a cost stays continuous. through_plane:
        "linear" between the two slices around the point, or "keys", the cubic convolution of Keys (IEEE Trans.
        ASSP 29, 1981, a = -1/2) over four slices, exact for a quadratic course along the leg."""
        shape = np.shape(index)[1:]
        rows, columns, slices = (np.ravel(np.asarray(c, float)) for c in index)
        rows_in = np.clip(rows, -0.5, self.rows - 0.5)
        columns_in = np.clip(columns, -0.5, self.columns - 0.5)
        lower = np.clip(np.floor(slices), 0, max(self.count - 2, 0)).astype(int)
        weight = np.clip(slices - lower, 0.0, 1.0) if self.count > 1 else np.zeros_like(slices)
        values = np.zeros(rows.size)
        missing = np.zeros(rows.size)
        for k in np.unique(lower):
            at = np.flatnonzero(lower == k)
            coordinates = np.stack([rows_in[at], columns_in[at]])
            for plane, share in _through_plane_weights(int(k), weight[at], self.count, through_plane):
                used = share != 0.0
                if not used.any():
                    continue
                coefficients, plane_missing = self._plane(int(plane))
                values[at[used]] += share[used] * ndimage.map_coordinates(
                    coefficients, coordinates[:, used], order=3, prefilter=False, mode="mirror")
                if nan_outside and plane_missing is not None:
                    missing[at[used]] += np.abs(share[used]) * ndimage.map_coordinates(
                        plane_missing, coordinates[:, used], order=1, mode="nearest")
        if nan_outside:
            outside = ((rows != rows_in) | (columns != columns_in) | (slices < -beyond_slices)
                       | (slices > self.count - 1 + beyond_slices) | (missing > 0.0))
            values[outside] = np.nan
        return values.reshape(shape)


def _through_plane_weights(k: int, t: np.ndarray, count: int, kind: str) -> list[tuple[int, np.ndarray]]:
    """(slice, weight) pairs of points at fraction t between slices k and k + 1 (module text). With "keys" the
    four slices k - 1 .. k + 2 take part; between the first two slices or the last two, where one of them is
    missing, linear (Keys' boundary condition extrapolates a slice, 3 s_0 - 3 s_1 + s_2: exact for a quadratic, but
    on an image it multiplies the noise by 4.4 and repeats every edge three times; a study's slice there measured
    3.3 x its noise floor against 1.2 beside it)."""
    if kind not in ("linear", "keys"):
        raise ValueError(f"through_plane is 'linear' or 'keys', not {kind!r}")
    if kind == "linear" or k < 1 or k + 2 > count - 1:
        return [(k, 1.0 - t), (min(k + 1, count - 1), t)]
    return [(k + offset, _keys_kernel(distance)) for offset, distance in ((-1, 1.0 + t), (0, t), (1, 1.0 - t), (2, 2.0 - t))]


def _keys_kernel(distance: np.ndarray, a: float = -0.5) -> np.ndarray:
    s = np.abs(distance)
    near = ((a + 2.0) * s - (a + 3.0)) * s * s + 1.0
    far = ((a * s - 5.0 * a) * s + 8.0 * a) * s - 4.0 * a
    return np.where(s < 1.0, near, np.where(s < 2.0, far, 0.0))


def resample_on_slice(loaded: Volume, unloaded: Volume, k: int, motion: RigidMotion3D,
                      through_plane: str = "keys") -> np.ndarray:
    """The loaded volume seen on the pixels of the unloaded volume's slice k: loaded(motion.apply(point)) at each
    pixel's patient point, cubic in-plane and, by default, Keys' cubic convolution between slices, NaN where the
    point falls outside the loaded volume (outside its matrix, or beyond its first or last slice) or on a NaN
    voxel. Shape: the unloaded slice's. Beyond the last slice nothing stands in for the tissue: the last slice is
    another tissue plane (a study's slice that took it up to half a spacing beyond measured 3.3 x its floor).

    Why not linear between slices, as the alignment samples: the skin's course along the leg is curved (the calf's
    girth has a maximum), and a linear blend of two slices 8 mm apart puts the skin on the chord, inside the leg. On
    the 3D phantom leg, against the loaded slice rendered at the plane itself, the DIC saw the fat 0.026 mm inside
    with linear and 0.017 mm with Keys (the noise of a window: 0.011 mm); the error falls as the spacing squared."""
    if not 0 <= k < unloaded.shape[2]:
        raise IndexError(f"slice {k} of a volume of {unloaded.shape[2]} slices")
    index = loaded.index_of_points(motion.apply(unloaded.slice_points_mm(k)))
    return _SliceStack(loaded.voxels).sample(index, nan_outside=True, through_plane=through_plane, beyond_slices=0.0)


# ----------------------------------------------------------------- bones of a volume


@dataclass(frozen=True)
class _VolumeBones:
    """The bones found in each slice of a volume: the bone mask (rows, columns, slices) and, per slice, the
    (centroid (3,) patient mm, area mm^2) of each component, largest first."""

    mask: np.ndarray
    centroids: tuple[tuple[tuple[np.ndarray, float], ...], ...]

    @property
    def counts(self) -> tuple[int, ...]:
        return tuple(len(found) for found in self.centroids)


def _find_bones(volume: Volume, role: str, fat_shift_mm: float = 0.0) -> _VolumeBones:
    """Segment every slice (`segment_t1`) and keep the bone that either of two segmentations finds: one that knows
    the fat's chemical shift on the images (a fatty marrow moved against its cortex leaves the cortex thin on one
    side, and a segmentation that knows no shift misses that bone) and one that knows none (module text, step 1:
    on the k-space phantom at 0.6 mm pixels the first found the tibia in 10 of 12 slices and the fibula in none,
    the second the fibula alone in 7). A slice where neither finds a leg or a bone has none (the slab may run past
    the bones' ends, or out of the leg)."""
    mask = np.zeros(volume.shape, dtype=bool)
    per_slice = []
    shifts = (0.0,) if not fat_shift_mm else (0.0, float(fat_shift_mm))
    for k in range(volume.shape[2]):
        image = volume.slice_image(k)
        finite = np.isfinite(image)
        found: list = []
        if finite.any() and np.ptp(image[finite]) > 0:
            image = np.where(finite, image, image[finite].min())   # no value: background, as `_formats` reads it
            for shift in shifts:
                try:
                    mask[:, :, k] |= segment_t1(image, volume.pixel_size_mm, fat_shift_mm=shift) == BONE
                except ImagingError:
                    pass
            labels = np.where(mask[:, :, k], BONE, 0)
            for (x, y), area in bone_centroids(labels, volume.pixel_size_mm):
                row, column = mm_to_index(x, y, volume.pixel_size_mm)
                found.append((volume.affine[:3] @ np.array([row, column, k, 1.0]), area))
        per_slice.append(tuple(found))
    bones = _VolumeBones(mask, tuple(per_slice))
    if not mask.any():
        raise ImagingError(f"no bone found in any of the {volume.shape[2]} slices of the {role} volume "
                           f"({volume.source}), so the rigid motion between the sessions cannot be estimated")
    return bones


def _bone_lines(bones: _VolumeBones, normal: np.ndarray,
                tibia_area_mm2: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point, unit direction towards +normal) of the line through each bone's per-slice centroids (module text,
    step 1): the tibia's through the components of at least TIBIA_AREA_SHARE of `tibia_area_mm2` (the largest
    bone of both volumes), the fibula's through the largest smaller component of each slice that lies clear of
    the tibia (beyond its radius and LINE_OUTLIER_MM of its line). Not the largest and the second of each slice:
    where a segmentation finds a piece of the tibia only (its cortex, thickened on one side by the chemical
    shift), or no tibia, that piece would pass for the tibia, or the fibula for it, and the line through half such
    slices tilted 7 degrees. A bone found in fewer than two slices, or running across the slices, has no line."""
    if tibia_area_mm2 is None:
        tibia_area_mm2 = max((area for found in bones.centroids for _, area in found), default=0.0)
    threshold = TIBIA_AREA_SHARE * tibia_area_mm2
    lines = []
    tibia = np.array([found[0][0] for found in bones.centroids if found and found[0][1] >= threshold])
    line = _robust_line(tibia)
    if line is None:
        return lines
    lines.append(line)
    radius = np.sqrt(tibia_area_mm2 / np.pi)
    fibula = []
    for found in bones.centroids:
        clear = [centroid for centroid, area in found if area < threshold
                 and _distance_to_line(centroid[None, :], *line)[0] > radius + LINE_OUTLIER_MM]
        if clear:
            fibula.append(clear[0])
    line = _robust_line(np.array(fibula))
    if line is not None:
        lines.append(line)
    return [(point, direction if np.dot(direction, normal) >= 0 else -direction) for point, direction in lines
            if abs(np.dot(direction, normal)) >= 0.5]   # over 60 degrees from the normal: not a long bone cut across


def _robust_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The line through points, fitted again without those farther than LINE_OUTLIER_MM from it (another piece
    taken for this bone: a vessel, a fragment); None for fewer than two points."""
    if len(points) < 2:
        return None
    line = _fit_line(points)
    near = _distance_to_line(points, *line) <= LINE_OUTLIER_MM
    if 2 <= near.sum() < len(points):
        line = _fit_line(points[near])
    return line


def _fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centre = points.mean(axis=0)
    return centre, np.linalg.svd(points - centre)[2][0]


def _distance_to_line(points: np.ndarray, point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    offsets = points - point
    return np.linalg.norm(offsets - np.outer(offsets @ direction, direction), axis=1)


def _at_height(point: np.ndarray, direction: np.ndarray, normal: np.ndarray, height: float) -> np.ndarray:
    """The point of a line at a height along the normal."""
    return point + direction * (height - point @ normal) / (direction @ normal)


def _rotation_of_directions(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rotation R with R source_i closest to target_i (rows of unit vectors, least squares: Wahba's problem,
    solved as Kabsch's by the SVD of their correlation, without a reflection)."""
    u, _, vt = np.linalg.svd(source.T @ target)
    reflection = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, reflection]) @ u.T


def _across(points: np.ndarray, lines) -> np.ndarray:
    """Unit vector from the first bone's point to the second's, across their mean direction."""
    axis = lines[0][1] + lines[1][1]
    axis /= np.linalg.norm(axis)
    offset = points[1] - points[0]
    offset -= np.dot(offset, axis) * axis
    return offset / np.linalg.norm(offset)


def _least_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a onto unit vector b."""
    axis = np.cross(a, b)
    angle = np.arctan2(np.linalg.norm(axis), np.dot(a, b))
    if np.linalg.norm(axis) < 1e-12:
        return np.eye(3)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


def _start_from_bone_axes(bones0: _VolumeBones, bones1: _VolumeBones, unloaded: Volume, centre: np.ndarray,
                          slide_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(rotation matrix, translation of the centre) from the bones' lines (module text, step 1), the loaded lines
    met slide_mm higher along the normal than the unloaded ones; without lines in both volumes, the translation
    of the centroid of all bone centroids and no rotation."""
    normal = unloaded.normal
    largest = max((area for bones in (bones0, bones1) for found in bones.centroids for _, area in found), default=0.0)
    lines0, lines1 = _bone_lines(bones0, normal, largest), _bone_lines(bones1, normal, largest)
    matched = min(len(lines0), len(lines1))
    if matched == 0:
        means = [np.mean([c for found in bones.centroids for c, _ in found], axis=0) for bones in (bones0, bones1)]
        return np.eye(3), means[1] - means[0]
    middle = float(np.mean(unloaded.slice_positions_mm))
    source = np.array([_at_height(*line, normal, middle) for line in lines0[:matched]])
    target = np.array([_at_height(*line, normal, middle + slide_mm) for line in lines1[:matched]])
    if matched == 1:
        rotation = _least_rotation(lines0[0][1], lines1[0][1])
    else:
        # directions, not points paired at equal heights, which deny the tilt about the line between the bones
        # (module text): the bones' lines give the tilt, the tibia-to-fibula offset across them the turn
        directions = [np.array([lines[0][1], lines[1][1], _across(points, lines)])
                      for points, lines in ((source, lines0), (target, lines1))]
        rotation = _rotation_of_directions(*directions)
    offset = target.mean(axis=0) - rotation @ source.mean(axis=0)
    # R p + offset written as R (p - centre) + centre + translation
    return rotation, rotation @ centre + offset - centre


# ----------------------------------------------------------------- the alignment


def _slice_frame(volume: Volume) -> np.ndarray:
    """Columns: unit column direction, the in-plane direction completing a right-handed frame (the row direction
    of an orthogonal grid), the slice normal."""
    along_columns = volume.affine[:3, 1] / np.linalg.norm(volume.affine[:3, 1])
    normal = volume.normal
    return np.column_stack([along_columns, np.cross(normal, along_columns), normal])


class _BoneCost:
    """The grey-level residual of step 3 over the unloaded bones and rim, for parameters (rotation vector deg,
    translation mm) in the unloaded slice frame about the bone centre."""

    def __init__(self, unloaded: Volume, loaded: Volume, bone_mask: np.ndarray, rim_mm: float,
                 heights_per_slice: int = HEIGHTS_PER_SLICE):
        self.frame = _slice_frame(unloaded)
        rim = morphology.disk(max(1, int(round(rim_mm / min(unloaded.pixel_size_mm)))))
        region = np.zeros_like(bone_mask)
        for k in range(bone_mask.shape[2]):
            if bone_mask[:, :, k].any():
                region[:, :, k] = ndimage.binary_dilation(bone_mask[:, :, k], structure=rim)
        region &= np.isfinite(unloaded.voxels)
        rows, columns, slices = np.nonzero(region)
        # each slice's region at heights_per_slice heights between it and the next (module text, "The slide's
        # bias"): the unloaded volume interpolated there as the loaded one is, so that the interpolation's
        # smoothing of the noise no longer favours a slide that puts the loaded samples between its slices
        count = bone_mask.shape[2]
        offsets = np.arange(heights_per_slice) / heights_per_slice
        index = [np.concatenate([rows] * len(offsets)), np.concatenate([columns] * len(offsets)),
                 np.concatenate([slices + offset for offset in offsets])]
        group = np.concatenate([slices * len(offsets) + n for n in range(len(offsets))])
        reference = _SliceStack(unloaded.voxels).sample(np.stack(index).astype(float), nan_outside=True)
        keep = np.isfinite(reference) & (index[2] <= count - 1)
        self.points = unloaded.affine[:3] @ np.stack([index[0][keep], index[1][keep], index[2][keep],
                                                       np.ones(np.count_nonzero(keep))])
        self.slice_of_point = np.concatenate([slices] * len(offsets))[keep]
        self.group_of_point = group[keep]
        self.slice_count = count
        self.group_count = count * len(offsets)
        self.reference = reference[keep]
        self.centre = unloaded.affine[:3] @ np.array([*np.mean(np.nonzero(bone_mask), axis=1), 1.0])
        self.loaded = loaded
        self.stack = _SliceStack(loaded.voxels)

    def motion(self, parameters: np.ndarray) -> RigidMotion3D:
        rotation_vector = self.frame @ np.asarray(parameters[:3], float)
        translation = self.frame @ np.asarray(parameters[3:], float)
        return RigidMotion3D(tuple(map(float, rotation_vector)), tuple(map(float, translation)),
                             tuple(map(float, self.centre)))

    def parameters(self, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
        rotation_vector = np.rad2deg(Rotation.from_matrix(rotation).as_rotvec())
        return np.concatenate([self.frame.T @ rotation_vector, self.frame.T @ translation])

    def _index(self, parameters: np.ndarray, selected: np.ndarray) -> np.ndarray:
        return self.loaded.index_of_points(self.motion(parameters).apply(self.points[:, selected]))

    def inside(self, parameters: np.ndarray) -> np.ndarray:
        """Mask of the points that take part at these parameters: inside the loaded slab and matrix (module text),
        on no NaN voxel, in unloaded slices that keep at least MIN_POINTS_PER_SLICE of them."""
        everything = np.ones(self.points.shape[1], dtype=bool)
        rows, columns, slices = self._index(parameters, everything)
        rows_count, columns_count, slice_count = self.loaded.shape
        margin = INSIDE_MARGIN_PIXELS
        inside = ((slices >= 0) & (slices <= slice_count - 1) & (rows >= margin) & (rows <= rows_count - 1 - margin)
                  & (columns >= margin) & (columns <= columns_count - 1 - margin))
        inside[inside] = np.isfinite(self.stack.sample(np.stack([rows, columns, slices])[:, inside], nan_outside=True))
        kept = np.bincount(self.group_of_point[inside], minlength=self.group_count)
        return inside & (kept[self.group_of_point] >= MIN_POINTS_PER_SLICE)

    def residual(self, parameters: np.ndarray, selected: np.ndarray) -> np.ndarray:
        moved = self.stack.sample(self._index(parameters, selected), nan_outside=False)
        groups = self.group_of_point[selected]
        return _normalised_by_group(moved, groups) - _normalised_by_group(self.reference[selected], groups)


def _normalised_by_group(values: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Values less their group's mean, over their group's standard deviation (groups: the unloaded slices)."""
    _, which = np.unique(groups, return_inverse=True)
    counts = np.bincount(which)
    mean = np.bincount(which, values) / counts
    centred = values - mean[which]
    std = np.sqrt(np.bincount(which, centred ** 2) / counts)
    return centred / (std[which] + 1e-12)


def align_volumes_on_bones(unloaded: Volume, loaded: Volume, *, rim_mm: float = 0.7, max_slide_mm: float = 15.0,
                           slide_step_mm: float = 1.0, fat_shift_mm: float = 0.0,
                           jackknife: bool = True) -> VolumeAlignment:
    """The rigid motion M of the bones between the sessions, with loaded(M(p)) ~ unloaded(p) on the unloaded
    bones (module text); ImagingError when no bone is found in a volume, or when no slide within max_slide_mm
    leaves half the bones inside the loaded slab. fat_shift_mm: the size of the fat's chemical shift on the
    images (`segment_t1`); jackknife: the refinement made again without each unloaded slice in turn, for the
    motion's standard error (`VolumeAlignment.slide_sd_at`)."""
    bones0 = _find_bones(unloaded, "unloaded", fat_shift_mm)
    bones1 = _find_bones(loaded, "loaded", fat_shift_mm)
    cost = _BoneCost(unloaded, loaded, bones0.mask, rim_mm)
    rotation, translation = _start_from_bone_axes(bones0, bones1, unloaded, cost.centre)
    parameters = _scan_slide(cost, cost.parameters(rotation, translation), max_slide_mm, slide_step_mm)
    # the lines met again at the heights the slide brings together, then the slide scanned again near there, finer
    rotation, translation = _start_from_bone_axes(bones0, bones1, unloaded, cost.centre, slide_mm=parameters[5])
    parameters = _scan_slide(cost, cost.parameters(rotation, translation), slide_step_mm, slide_step_mm / 4)
    start = cost.motion(parameters)

    dy, dx = unloaded.pixel_size_mm
    scale = [0.1, 0.1, 0.1, dx / 10, dy / 10, unloaded.slice_spacing_mm / 10]
    selected = cost.inside(parameters)
    for _ in range(MAX_POINT_SETS):
        fit = optimize.least_squares(cost.residual, parameters, args=(selected,), x_scale=scale, diff_step=1e-4,
                                     xtol=1e-8, ftol=1e-10, max_nfev=200)
        parameters = fit.x
        now_inside = cost.inside(parameters)
        if np.array_equal(now_inside, selected) or now_inside.sum() < MIN_OVERLAP * selected.size:
            break
        selected = now_inside

    motion = cost.motion(parameters)
    residual = cost.residual(parameters, selected)
    left_out = []
    if jackknife:
        for k in np.unique(cost.slice_of_point[selected]):
            fewer = selected & (cost.slice_of_point != k)
            fit = optimize.least_squares(cost.residual, parameters, args=(fewer,), x_scale=scale, diff_step=1e-4,
                                         xtol=1e-8, ftol=1e-10, max_nfev=200)
            left_out.append(cost.motion(fit.x))
    return VolumeAlignment(
        motion=motion, start=start, rotation_deg=tuple(map(float, parameters[:3])),
        translation_mm=tuple(map(float, parameters[3:])),
        centroid_rms_mm=_centroid_rms_mm(bones0, bones1, loaded, motion),
        correlation=float(1.0 - np.mean(residual ** 2) / 2.0),   # normalised values: |a - b|^2 = 2 (1 - r)
        bones_per_slice_unloaded=bones0.counts, bones_per_slice_loaded=bones1.counts,
        points=int(selected.sum()), slices_used=int(np.unique(cost.slice_of_point[selected]).size),
        jackknife=tuple(left_out), fat_shift_mm=float(fat_shift_mm),
        normal_vector=tuple(map(float, unloaded.normal)))


def _scan_slide(cost: _BoneCost, parameters: np.ndarray, max_slide_mm: float, step_mm: float) -> np.ndarray:
    """The parameters with the slide (the last) set to the best of a scan of the cost along the normal (module
    text, step 2)."""
    best, best_cost = None, np.inf
    for slide in parameters[5] + np.arange(-max_slide_mm, max_slide_mm + step_mm / 2, step_mm):
        trial = np.concatenate([parameters[:5], [slide]])
        selected = cost.inside(trial)
        if selected.sum() < MIN_OVERLAP * selected.size:
            continue
        mean_square = float(np.mean(cost.residual(trial, selected) ** 2))
        if mean_square < best_cost:
            best, best_cost = trial, mean_square
    if best is None:
        raise ImagingError(f"the bones of the unloaded volume fall outside the loaded one for every slide within "
                           f"{max_slide_mm:g} mm, so the two volumes do not cover the same part of the leg")
    return best


def _centroid_rms_mm(bones0: _VolumeBones, bones1: _VolumeBones, loaded: Volume, motion: RigidMotion3D) -> float:
    """RMS in-plane distance between the unloaded bone centroids moved by the motion and the loaded bones' centroids
    interpolated at the same height (bones matched by size in each slice); NaN when no pair is found."""
    normal = loaded.normal
    distances = []
    for found in bones0.centroids:
        for rank, (centroid, _) in enumerate(found[:2]):
            moved = motion.apply(centroid)
            height = float(loaded.index_of_points(moved)[2])
            lower = int(np.floor(height))
            if not 0 <= lower < loaded.shape[2] - 1:
                continue
            pair = bones1.centroids[lower], bones1.centroids[lower + 1]
            if min(len(pair[0]), len(pair[1])) <= rank:
                continue
            weight = height - lower
            target = (1 - weight) * pair[0][rank][0] + weight * pair[1][rank][0]
            offset = moved - target
            distances.append(np.linalg.norm(offset - np.dot(offset, normal) * normal))
    return float(np.sqrt(np.mean(np.square(distances)))) if distances else float("nan")
