"""Rigid alignment of the loaded image on the unloaded one, on the bones.

Between the two acquisitions the leg moves rigidly in the scanner; the second
paper removes this motion "by performing a rotation and a translation, so
that the surface centre of the bones coincide in both images" (section 3.1).
We do the same in two steps:

1. bone centroids: the bones of each image are segmented (`segment_t1`),
   matched by size, and the rigid motion that best superposes their area
   centroids is found by the Kabsch/Procrustes solution (two or more bones
   fix the rotation; with one bone the rotation starts at zero);
2. refinement: the rotation and translation are then adjusted to minimise
   the squared difference of the normalised grey levels of I0 and I1 over
   the bones and a thin rim around them (bones are rigid and clamped, first
   paper section 2.2.2, so this region moves only with the scanner motion),
   with cubic-spline interpolation of I1 and scipy's least_squares.

The result is a `RigidMotion` M with I1(M(x)) ~ I0(x) at the bones; M maps
a point of the unloaded frame to where the same bone point is in the loaded
image. `resample_rigid` makes the aligned loaded image I1(M(x)).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, optimize
from skimage import morphology

from ..core.errors import ImagingError
from ..core.frame import RigidMotion, mm_to_index, pixel_centres_mm
from ..core.tissues import BONE
from .segment import segment_t1


def bone_centroids(labels: np.ndarray, pixel_size_mm) -> list[tuple[np.ndarray, float]]:
    """(centroid (x, y) mm, area mm^2) of each bone component, largest first."""
    components, count = ndimage.label(labels == BONE)
    if count == 0:
        return []
    dy, dx = pixel_size_mm
    found = []
    for index in range(1, count + 1):
        rows, cols = np.nonzero(components == index)
        found.append((np.array([(cols.mean() + 0.5) * dx, (rows.mean() + 0.5) * dy]), rows.size * dx * dy))
    return sorted(found, key=lambda item: -item[1])


def kabsch_2d(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation angle (deg) and translation t so that R source_i + t best matches target_i (least squares)."""
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    if len(source) < 2:
        return 0.0, target_mean - source_mean
    a, b = source - source_mean, target - target_mean
    angle = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return float(np.degrees(angle)), target_mean - rotation @ source_mean


def align_on_bones(unloaded: np.ndarray, loaded: np.ndarray, pixel_size_mm, *, labels_unloaded: np.ndarray | None = None,
                   labels_loaded: np.ndarray | None = None, rim_mm: float = 0.7, centre_mm=None,
                   fat_shift_mm: float = 0.0) -> RigidMotion:
    """The rigid motion M (about `centre_mm`, default the image centre) with I1(M(x)) ~ I0(x) on the bones; the
    images segmented here knowing the size of the fat's chemical shift (`segment.segment_t1`)."""
    shape = unloaded.shape
    dy, dx = pixel_size_mm
    centre = np.asarray(centre_mm if centre_mm is not None else (shape[1] * dx / 2, shape[0] * dy / 2), float)
    labels_unloaded = (segment_t1(unloaded, pixel_size_mm, fat_shift_mm=fat_shift_mm) if labels_unloaded is None
                       else labels_unloaded)
    labels_loaded = segment_t1(loaded, pixel_size_mm, fat_shift_mm=fat_shift_mm) if labels_loaded is None else labels_loaded
    bones0, bones1 = bone_centroids(labels_unloaded, pixel_size_mm), bone_centroids(labels_loaded, pixel_size_mm)
    matched = min(len(bones0), len(bones1))
    if matched == 0:
        raise ImagingError("no bone found in one of the images, so the rigid motion cannot be estimated")
    source = np.array([c for c, _ in bones0[:matched]])
    target = np.array([c for c, _ in bones1[:matched]])
    angle, translation = kabsch_2d(source, target)
    start = RigidMotion(angle, (float(translation[0]), float(translation[1])), (0.0, 0.0)).about(tuple(centre))

    rim = morphology.disk(max(1, int(round(rim_mm / min(pixel_size_mm)))))
    region = ndimage.binary_dilation(labels_unloaded == BONE, structure=rim)
    x_all, y_all = pixel_centres_mm(shape, pixel_size_mm)
    x, y = x_all[region], y_all[region]
    reference = _normalised(np.asarray(unloaded, float)[region])
    coefficients = ndimage.spline_filter(np.asarray(loaded, float), order=3)

    def residual(parameters):
        motion = RigidMotion(parameters[0], (parameters[1], parameters[2]), tuple(centre))
        rows, cols = mm_to_index(*motion.apply(x, y), pixel_size_mm)
        moved = ndimage.map_coordinates(coefficients, np.stack([rows, cols]), order=3, prefilter=False, mode="nearest")
        return _normalised(moved) - reference

    fit = optimize.least_squares(residual, [start.angle_deg, *start.translation_mm], x_scale=[0.1, dx / 10, dy / 10],
                                 diff_step=1e-4, xtol=1e-10, ftol=1e-12)
    return RigidMotion(float(fit.x[0]), (float(fit.x[1]), float(fit.x[2])), (float(centre[0]), float(centre[1])))


def resample_rigid(image: np.ndarray, motion: RigidMotion, pixel_size_mm, *, order: int = 1, cval: float = 0.0) -> np.ndarray:
    """The image seen in the unloaded frame: out(x) = image(M(x)). Use order=0 for label maps."""
    x, y = pixel_centres_mm(image.shape, pixel_size_mm)
    rows, cols = mm_to_index(*motion.apply(x, y), pixel_size_mm)
    return ndimage.map_coordinates(image, np.stack([rows, cols]), order=order, mode="constant", cval=cval)


def _normalised(values: np.ndarray) -> np.ndarray:
    return (values - values.mean()) / (values.std() + 1e-12)
