"""Image-to-mesh: a conforming triangle mesh of the soft tissues from a label image.

Labels: 0 background, 1 fat (with skin), 2 muscle, 3 bone, >= 4 muscle compartments;
pixel size (row, column) in mm. Positions are in the image frame of docs/design.md: pixel
(i, j) covers [j dx, (j+1) dx] x [i dy, (i+1) dy], centre ((j + 0.5) dx, (i + 0.5) dy).

Method.
1. Clean-up: keep the largest connected leg (labels > 0), give enclosed background
   and components smaller than `min_component_pixels` the label of the nearest kept
   pixel, turn bone pixels that touch the background into fat (the skin covers the
   bones), and number the bone components by decreasing area (BONE1 the largest).
2. Interfaces: every pixel edge between two different regions is a boundary edge.
   Chains of such edges between junctions (pixel corners where three regions meet,
   or where the pair of regions changes) form the interface curves, whose vertices
   are the midpoints of the pixel edges: along a two-region interface this is
   exactly the sub-pixel contour that skimage.measure.find_contours draws at level
   0.5 on either region's mask, but each interface exists once, and at triple points
   the curves meet at the shared pixel corner (marching squares on each mask
   separately would leave a gap there). Curves are smoothed with a Gaussian of
   `smoothing_pixels` samples, junction end points fixed. With the image the labels
   come from, each interface is moved onto the image's edge (`EdgeMap`), the fat/muscle
   interface to where the bright fat ends.
   The skin (the closed interface with the background) is then low-pass filtered
   (`curves.lowpass_closed`, which does not shrink it), because the garment presses it
   by Laplace's law, p = T kappa, and curvature amplifies short wavelengths: a bump of
   0.02 mm over 6 mm of skin doubles the local pressure. The pixel staircase, the edge
   finder's own error and the segmentation's noise are such bumps; left in the skin
   they make the pressure near it depend on the mesh and on the segmentation. Where to
   cut is measured on the skin itself (`curves.outline_error`): wavelengths of 6-12 mm,
   about the shortest shape a calf's skin has (SHORTEST_SKIN_SHAPE_MM), hold its error
   alone, and the cut-off goes where its shape stands out of that error. A fixed cut-off
   at 8 mm left 0.002-0.004 mm of error in every Fourier mode from 8 to 48 mm (on the
   phantom calf, whose skin is known, and on calves another program made): 17-20 % RMS
   of error in the curvature, pressure bumps of a third of the pressure 6 mm apart, and
   0.03 mm of error in the displacements under the skin, twice what DIC resolves there.
   At the measured cut-off (55 mm on the phantom, 32 mm on those calves) the curvature's
   error is 0.1-0.6 %. A groove or a crest of a real calf stands out of the error and
   keeps its wavelengths. `skin_cutoff_mm` given as a number cuts there instead.
   An MR image shows the fat's signal displaced along the readout by the chemical shift (`imaging.chemical_shift`),
   while the water's tissues (muscle, skin) stay where they are: the edge where the bright fat ends is then off the
   fat/muscle interface by the projection of that displacement on its normal (+-0.6 mm on the sides of a calf at
   1.4 pixels of 0.41 mm). `with_fat_moved_back` moves the fat/muscle interfaces, snapped to that edge, back by
   it, the move fading to nothing over FAT_SHIFT_FADE_MM at the ends of an open interface, which meet interfaces
   of water (a bone's cortex, the skin) that do not move.
3. The curves go to triangulate.mesh_curves (resampling to the element size with
   area-preserving vertex placement, Triangle with minimum angle and maximum area,
   element-count targeting, node sets and skin surface).
Bones and background are holes. Sets: FAT, MUSCLE, COMPARTMENTk elements; BONE1..,
BONES, SKIN_NODES and tissue-interface node sets (e.g. FAT_MUSCLE); surface SKIN.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy import ndimage
from scipy.ndimage import gaussian_filter1d

from .curves import (
    Curve,
    OutlineError,
    SpacingRules,
    lowpass_closed,
    offset_points,
    outline_error,
    smooth_points,
    unit_normals,
)
from .mesh import Mesh
from .triangulate import BONE_KEY_OFFSET, is_tissue, mesh_curves

BONE_LABEL = 3
SHORTEST_SKIN_SHAPE_MM = 8.0   # a calf's skin has no real shape shorter (step 2 of the module text)
SNAP_PASSES = 8
FAT_SHIFT_FADE_MM = 2.0   # an open fat/muscle interface's move back fades to zero over this length at its ends


@dataclass(frozen=True)
class TissueCurves:
    """The interface curves of a label image (steps 1-2 of the module text: cleaned up, smoothed, snapped onto the
    image's edges, the skin low-passed), ready to mesh at any size or with its interfaces moved. Snapping is most of
    meshing's time, so a run that meshes the same labels again (the discretization check's finer mesh, the skin's
    uncertainty's shifted interfaces) computes them once."""

    regions: np.ndarray
    curves: tuple[Curve, ...]
    pixel_size: tuple[float, float]
    skin_cutoff_mm: float = SHORTEST_SKIN_SHAPE_MM   # the skin's low-pass cut-off wavelength
    skin_error: OutlineError | None = None           # what the skin's spectrum says of its error, measured there
    fat_shift_mm: tuple[float, float] = (0.0, 0.0)    # the fat's chemical shift its fat/muscle interfaces undo


def tissue_curves(labels: np.ndarray, pixel_size_mm: Sequence[float], smoothing_pixels: float = 1.0,
                  min_component_pixels: int = 20, skin_cutoff_mm: float | None = None,
                  image: np.ndarray | None = None) -> TissueCurves:
    """The interfaces of `labels`; with the `image` they were segmented from, moved to its edges (`EdgeMap`); the
    skin low-passed at `skin_cutoff_mm`, or where its own spectrum puts the cut-off (None, the module text)."""
    row_mm, col_mm = _pixel_size(pixel_size_mm)
    if image is not None and np.shape(image) != np.shape(labels):
        raise ValueError("the image and its labels must have the same shape")
    regions = region_image(labels, min_component_pixels)
    curves = interface_curves(regions, (row_mm, col_mm), smoothing_pixels)
    if image is not None:
        edges = EdgeMap(image, (row_mm, col_mm))
        # the skin is snapped where the leg's image last falls to the air, the fat/muscle interface where the
        # bright fat ends, any other interface where its gradient peaks
        sides = [skin_side(c, regions, (row_mm, col_mm)) or fat_side(c, regions, (row_mm, col_mm)) for c in curves]
        outer = [is_skin(c.sides) for c in curves]
        for _ in range(SNAP_PASSES):
            curves = [Curve(edges.snap(c.points, c.closed, smoothing_pixels, bright_side=side, outermost=last),
                            c.closed, c.sides)
                      if is_edge(c.sides) else c for c, side, last in zip(curves, sides, outer)]
    skins = [c for c in curves if c.closed and c.sides[0] == 0]
    error = outline_error(skins[0].points, SHORTEST_SKIN_SHAPE_MM) if len(skins) == 1 else None
    if skin_cutoff_mm is None:
        skin_cutoff_mm = error.cutoff_mm if error is not None else SHORTEST_SKIN_SHAPE_MM
    curves = [Curve(lowpass_closed(c.points, skin_cutoff_mm), True, c.sides) if any(c is skin for skin in skins) else c
              for c in curves]
    return TissueCurves(regions, tuple(curves), (row_mm, col_mm), float(skin_cutoff_mm), error)


def fat_muscle_normals(tissue: TissueCurves) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) points, (N, 2) unit normals from the muscle into the fat) along every fat/muscle interface of
    `tissue`: where `imaging.chemical_shift` reads the fat's displacement."""
    points, normals = [np.zeros((0, 2))], [np.zeros((0, 2))]
    for curve in tissue.curves:
        if is_fat_muscle(curve.sides):
            points.append(curve.points)
            normals.append(fat_side(curve, tissue.regions, tissue.pixel_size) * unit_normals(curve.points, curve.closed))
    return np.vstack(points), np.vstack(normals)


def with_fat_moved_back(tissue: TissueCurves, fat_shift_mm: Sequence[float]) -> TissueCurves:
    """`tissue` with its fat/muscle interfaces moved back by the fat's chemical shift (x, y) mm (module text,
    step 2; `fat_moved_back`)."""
    shift = np.asarray(fat_shift_mm, float).reshape(2)
    curves = tuple(fat_moved_back(c, shift) if is_fat_muscle(c.sides) else c for c in tissue.curves)
    return replace(tissue, curves=curves, fat_shift_mm=(float(shift[0]), float(shift[1])))


def is_fat_muscle(sides) -> bool:
    """Whether an interface lies between the fat and the muscle (or one of its compartments)."""
    low, high = sorted(int(v) for v in sides)
    return low == 1 and is_tissue(high) and high != 1


def fat_moved_back(curve: Curve, fat_shift_mm: np.ndarray) -> Curve:
    """The fat/muscle interface `curve`, found where the bright fat ends, moved back by the fat's displacement on the
    image (module text, step 2): translated by -fat_shift_mm, the move fading to zero over FAT_SHIFT_FADE_MM at the
    ends of an open curve (they meet interfaces that do not move)."""
    points = np.asarray(curve.points, float)
    weight = np.ones(len(points))
    if not curve.closed and len(points) > 1:
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        weight = np.clip(np.minimum(arc, arc[-1] - arc) / FAT_SHIFT_FADE_MM, 0.0, 1.0)
    return Curve(points - weight[:, None] * fat_shift_mm[None, :], curve.closed, curve.sides)


def mesh_tissue_curves(tissue: TissueCurves, n_elements: int = 400, order: int = 1, min_angle_deg: float = 25.0,
                       interface_offsets=None) -> Mesh:
    """Mesh `tissue`'s curves with about n_elements CPE3 (order 1) or CPE6 (order 2); interface_offsets(curve) ->
    normal moves (mm, one per point of the curve, positive to the left of its direction): a perturbed geometry."""
    curves = list(tissue.curves)
    if interface_offsets is not None:
        curves = [Curve(offset_points(c.points, c.closed, interface_offsets(c)), c.closed, c.sides) for c in curves]
    rules = SpacingRules(min_spacing=min(tissue.pixel_size))

    def classify(points: np.ndarray) -> np.ndarray:
        return _lookup(tissue.regions, tissue.pixel_size, points)

    return mesh_curves(curves, classify, n_elements, order=order, min_angle_deg=min_angle_deg, rules=rules)


def mesh_from_labels(
    labels: np.ndarray,
    pixel_size_mm: Sequence[float],
    n_elements: int = 400,
    order: int = 1,
    min_angle_deg: float = 25.0,
    smoothing_pixels: float = 1.0,
    min_component_pixels: int = 20,
    skin_cutoff_mm: float | None = None,
    image: np.ndarray | None = None,
    interface_offsets=None,
) -> Mesh:
    """Mesh the tissues of `labels` with about n_elements CPE3 (order 1) or CPE6 (order 2) (`tissue_curves`, then
    `mesh_tissue_curves`); with the `image` the labels were segmented from, the interfaces are moved to the image's
    edges (`EdgeMap`). interface_offsets(curve) -> normal moves (mm, one per point of the curve, positive to the left
    of its direction): a perturbed geometry.

    T6 mid-side nodes lie on the straight edges of the T3 mesh (also on the boundary).
    """
    tissue = tissue_curves(labels, pixel_size_mm, smoothing_pixels, min_component_pixels, skin_cutoff_mm, image)
    return mesh_tissue_curves(tissue, n_elements, order, min_angle_deg, interface_offsets)


def is_edge(sides) -> bool:
    """Whether an interface is a step of grey level, which `EdgeMap` finds: not the septum between two muscle
    compartments, a thin line whose middle is the boundary (the gradient peaks at either side of it)."""
    low, high = sorted(int(v) for v in sides)
    muscle = (2,) + tuple(range(4, BONE_KEY_OFFSET))
    return not (low in muscle and high in muscle)


def fat_side(curve: Curve, regions: np.ndarray, pixel_size: tuple[float, float]) -> int:
    """+1 (-1) when `curve` is an interface between fat and muscle (or a compartment) with the fat to the left
    (right) of its direction, 0 for any other interface."""
    low, high = sorted(int(v) for v in curve.sides)
    if low != 1 or not is_tissue(high) or high == 1:
        return 0
    probe = curve.points + 0.5 * min(pixel_size) * unit_normals(curve.points, curve.closed)
    return 1 if np.mean(_lookup(regions, pixel_size, probe) == 1) >= 0.5 else -1


def is_skin(sides) -> bool:
    """Whether an interface is the leg's outline (against the background)."""
    return min(int(v) for v in sides) == 0


def skin_side(curve: Curve, regions: np.ndarray, pixel_size: tuple[float, float]) -> int:
    """+1 (-1) when `curve` is the leg's outline with the leg to the left (right) of its direction, 0 otherwise."""
    if not is_skin(curve.sides):
        return 0
    probe = curve.points + 0.5 * min(pixel_size) * unit_normals(curve.points, curve.closed)
    return 1 if np.mean(_lookup(regions, pixel_size, probe) != 0) >= 0.5 else -1


class EdgeMap:
    """Sub-pixel edges of an image, to place the interface curves of its labels on them.

    A label boundary is a threshold of the grey levels: it sits wherever the threshold cuts the blurred edge,
    off the edge by a fraction of a pixel that depends on the two tissues' grey levels (on the phantom calf the
    segmented leg is 0.4 pixel too wide all round, its muscle 0.25 pixel too wide), which shifts the whole
    skin or interface by the same amount: a bias, not noise, and larger than what DIC resolves. The edge of a
    step blurred by a symmetric point-spread function is where the gradient magnitude peaks, whatever the two
    levels. `snap` moves every interior vertex of a curve along its normal to the sub-pixel maximum of the
    gradient magnitude (image smoothed over one pixel) within `max_move_pixels`, where that maximum stands out
    of the image noise, then smooths the curve again.

    The fat/muscle interface is where the bright fat ends (`snap` with `bright_side`), and what lies beside it is
    not a step. The deep fascia is a dark line on the muscle's side (0.5 mm): the image rises again beyond it, and
    the blurred rise pulls the gradient's peak into the fat (by 0.07 mm at 0.36 mm pixels and 0.15 mm at 0.6 mm on
    a box-blurred profile fat | 0.5 mm dark line | muscle of the phantoms' grey levels). The fat's septa are dark
    lines across the interface, whose sides are strong edges along it. So the edge is found as the peak of the
    image's fall along the normal from the fat's side (the directional derivative, which the septa's sides and the
    fascia's inner edge do not feed), then placed where the image crosses the half level between its brightest
    value within a pixel on the fat's side of that peak and its darkest within a pixel on the other side (on the
    same profile: 0.01 mm at 0.36 mm pixels, 0.07 mm at 0.6 mm, where the line no longer fills a pixel). Meshed
    from the phantoms' true labels, the interface moved from +0.12 to +0.06 mm (second phantom, 0.36 mm pixels;
    0.19 to 0.13 mm at 0.6 mm) and from +0.09 to +0.07 mm (first phantom), positive outside the muscle."""

    STEP = 0.25

    def __init__(self, image: np.ndarray, pixel_size: tuple[float, float], smoothing_px: float = 1.0,
                 max_move_pixels: float = 1.0, move_smoothing_samples: float = 10.0):
        self.pixel_size = pixel_size
        self.max_move = max_move_pixels
        self.move_smoothing_samples = move_smoothing_samples
        image = np.asarray(image, float)
        self.image, self.smoothing_px = image, smoothing_px
        self._directional = None
        self.gradient = ndimage.gaussian_gradient_magnitude(image, smoothing_px)
        noise = ndimage.gaussian_gradient_magnitude(image - ndimage.gaussian_filter(image, smoothing_px), smoothing_px)
        self.significant = 4.0 * float(np.median(noise))

    def snap(self, points: np.ndarray, closed: bool, sigma: float, bright_side: int = 0,
             outermost: bool = False) -> np.ndarray:
        """The curve moved onto the image's edge. bright_side: 0, the gradient magnitude's peak; +1 (-1), the end
        of a bright tissue lying to the left (right) of the curve (the class text). outermost: with bright_side,
        the last significant fall along the normal rather than the steepest (the skin, class text)."""
        if len(points) < 5:
            return points
        row_mm, col_mm = self.pixel_size
        normal = unit_normals(points, closed)
        if bright_side:
            normal = -bright_side * normal      # from the bright tissue into the dark one
        offsets = np.arange(-self.max_move - self.STEP, self.max_move + 1.5 * self.STEP, self.STEP)
        pixel = np.sqrt(row_mm * col_mm)
        samples = points[:, None, :] + offsets[None, :, None] * pixel * normal[:, None, :]   # (k, m, 2) mm
        rows, cols = samples[..., 1] / row_mm - 0.5, samples[..., 0] / col_mm - 0.5
        if bright_side:
            profile = self._fall(rows, cols, normal)
        else:
            profile = ndimage.map_coordinates(self.gradient, [rows.ravel(), cols.ravel()], order=3,
                                              mode="nearest").reshape(rows.shape)
        peak = np.argmax(profile, axis=1)
        index = np.arange(len(points))
        interior = (peak > 0) & (peak < len(offsets) - 1)
        left = profile[index, np.clip(peak - 1, 0, None)]
        right = profile[index, np.clip(peak + 1, None, len(offsets) - 1)]
        centre = profile[index, peak]
        curvature = left - 2 * centre + right
        refine = np.where(interior & (curvature < 0), 0.5 * (left - right) / np.where(curvature < 0, curvature, -1.0), 0.0)
        edge = offsets[peak] + refine * self.STEP
        found = interior & (centre >= self.significant)
        if bright_side and outermost:
            # the skin against the air: a stronger step of the tissues a pixel or two inside (the fat under a skin
            # darker than it, the fat's chemical shift into the skin) pulls the smoothed fall's peak inwards or
            # hides the skin's own, so the skin goes where the image crosses half its level, from where it is
            edge, found = np.zeros(len(points)), np.ones(len(points), bool)
        if bright_side:
            edge = self._half_level(points, normal, edge, found)
        move = np.clip(edge, -self.max_move, self.max_move)
        move[~found] = 0.0
        # the bias of a threshold is smooth along an interface, the peak of one noisy profile is not: the moves are
        # averaged along the curve, so that snapping corrects the one without adding the other as curvature
        move = gaussian_filter1d(move, self.move_smoothing_samples, mode="wrap" if closed else "nearest")
        if not closed:
            move[0] = move[-1] = 0.0
        moved = points + (move * pixel)[:, None] * normal
        return smooth_points(moved, closed, sigma)

    def _fall(self, rows: np.ndarray, cols: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """How fast the image (smoothed over smoothing_px) falls along `normal` (one per row of samples) at the
        samples (pixel coordinates), per pixel, as the gradient magnitude is."""
        row_mm, col_mm = self.pixel_size
        if self._directional is None:
            self._directional = tuple(ndimage.gaussian_filter(self.image, self.smoothing_px, order=order)
                                      for order in ((1, 0), (0, 1)))
        along_rows, along_cols = (ndimage.map_coordinates(d, [rows.ravel(), cols.ravel()], order=3,
                                                          mode="nearest").reshape(rows.shape)
                                  for d in self._directional)
        pixel = np.sqrt(row_mm * col_mm)
        return -pixel * (along_cols * normal[:, None, 0] / col_mm + along_rows * normal[:, None, 1] / row_mm)

    def _half_level(self, points: np.ndarray, normal: np.ndarray, edge: np.ndarray, found: np.ndarray,
                    step: float = 0.05) -> np.ndarray:
        """The edges (offsets along `normal`, pixels) moved to where the image crosses the half level between its
        brightest value within a pixel before the edge and its darkest within a pixel after it (the crossing next
        to the darkest value: a septum on the bright side is not the edge); unchanged where there is no such
        crossing."""
        row_mm, col_mm = self.pixel_size
        pixel = np.sqrt(row_mm * col_mm)
        offsets = np.arange(-1.0, 1.0 + 0.5 * step, step)
        middle = int(np.argmin(np.abs(offsets)))
        at = points[:, None, :] + (edge[:, None] + offsets[None, :])[..., None] * pixel * normal[:, None, :]
        rows, cols = at[..., 1] / row_mm - 0.5, at[..., 0] / col_mm - 0.5
        profile = ndimage.map_coordinates(self.image, [rows.ravel(), cols.ravel()], order=1,
                                          mode="nearest").reshape(rows.shape)
        placed = edge.copy()
        for k in np.flatnonzero(found):
            values = profile[k]
            bright = int(np.argmax(values[:middle + 1]))
            dark = middle + int(np.argmin(values[middle:]))
            level = 0.5 * (values[bright] + values[dark])
            last = bright + int(np.flatnonzero(values[bright:dark + 1] >= level)[-1])
            if last >= dark or values[last] <= values[last + 1]:
                continue
            placed[k] = edge[k] + offsets[last] + step * (values[last] - level) / (values[last] - values[last + 1])
        return placed


def interface_shift(labels: np.ndarray, pixel_size_mm: Sequence[float], interface: str, distance_mm: float,
                    min_component_pixels: int = 20):
    """interface_offsets for `mesh_from_labels` that move one interface uniformly: the "skin" outwards (the leg
    grows) or the "fascia" (fat against muscle) towards the muscle (the fat thickens), by distance_mm."""
    if interface not in ("skin", "fascia"):
        raise ValueError(f"the interface to shift is skin or fascia, not {interface!r}")
    pixel_size = _pixel_size(pixel_size_mm)
    regions = region_image(labels, min_component_pixels)

    def selected(sides) -> bool:
        low, high = sorted(sides)
        return low == 0 if interface == "skin" else (low == 1 and is_tissue(high) and high != 1)

    def offsets(curve):
        if not selected(curve.sides):
            return 0.0
        probe = curve.points + 0.5 * min(pixel_size) * unit_normals(curve.points, curve.closed)
        left = _lookup(regions, pixel_size, probe)
        towards = (left == 0) if interface == "skin" else (left != 1) & (left != 0)
        return distance_mm if np.mean(towards) >= 0.5 else -distance_mm

    return offsets


def _pixel_size(pixel_size_mm: Sequence[float]) -> tuple[float, float]:
    size = tuple(float(v) for v in np.ravel(pixel_size_mm))
    if len(size) != 2 or not all(np.isfinite(v) and v > 0 for v in size):
        raise ValueError(f"pixel size must be two positive numbers (row, column) in mm, not {pixel_size_mm!r}")
    return size  # type: ignore[return-value]


def region_image(labels: np.ndarray, min_component_pixels: int = 20) -> np.ndarray:
    """Cleaned region keys per pixel: 0 background, tissue labels, BONE_KEY_OFFSET + k for bone k."""
    labels = np.asarray(labels)
    integral = np.issubdtype(labels.dtype, np.integer) or (labels.size and np.all(labels == np.round(labels)))
    if labels.ndim != 2 or not integral:
        raise ValueError("labels must be a 2-D image of integer labels")
    if labels.min() < 0:
        raise ValueError("labels must be non-negative (0 background, 1 fat, 2 muscle, 3 bone, >= 4 compartments)")
    regions = labels.astype(np.int64)
    leg, count = ndimage.label(regions > 0)
    if count == 0:
        raise ValueError("the label image is empty: no fat, muscle or bone pixel")
    sizes = np.bincount(leg.ravel())
    sizes[0] = 0
    regions[leg != np.argmax(sizes)] = 0
    leg_mask = regions > 0
    enclosed = ndimage.binary_fill_holes(leg_mask) & ~leg_mask
    regions = _take_nearest(regions, enclosed)
    # The skin covers the bones: a bone pixel touching the background becomes fat.
    background = regions == 0
    touching = (regions == BONE_LABEL) & ndimage.binary_dilation(background)
    regions[touching] = 1
    for _ in range(3):
        small = np.zeros(regions.shape, dtype=bool)
        for value in np.unique(regions):
            if value == 0:
                continue
            components, n = ndimage.label(regions == value)
            component_sizes = np.bincount(components.ravel())
            tiny = np.flatnonzero(component_sizes < min_component_pixels)
            tiny = tiny[tiny > 0]
            if n and len(tiny):
                small |= np.isin(components, tiny)
        if not small.any():
            break
        regions = _take_nearest(regions, small)
    if not np.any([is_tissue(int(v)) for v in np.unique(regions)]):
        raise ValueError("the label image has no soft tissue (labels 1, 2 or >= 4) to mesh")
    bones, n_bones = ndimage.label(regions == BONE_LABEL)
    if n_bones:
        bone_sizes = np.bincount(bones.ravel())[1:]
        rank = np.empty(n_bones, dtype=np.int64)
        rank[np.argsort(-bone_sizes, kind="stable")] = np.arange(1, n_bones + 1)
        regions[bones > 0] = BONE_KEY_OFFSET + rank[bones[bones > 0] - 1]
    return regions


def _take_nearest(regions: np.ndarray, replace: np.ndarray) -> np.ndarray:
    """Give each pixel in `replace` the value of the nearest pixel not in `replace`."""
    if not replace.any():
        return regions
    _, (rows, cols) = ndimage.distance_transform_edt(replace, return_indices=True)
    out = regions.copy()
    out[replace] = regions[rows[replace], cols[replace]]
    return out


def _lookup(regions: np.ndarray, pixel_size: tuple[float, float], points: np.ndarray) -> np.ndarray:
    """Region key of the pixel containing each point (0 outside the image)."""
    rows = np.floor(points[:, 1] / pixel_size[0]).astype(np.int64)
    cols = np.floor(points[:, 0] / pixel_size[1]).astype(np.int64)
    inside = (rows >= 0) & (rows < regions.shape[0]) & (cols >= 0) & (cols < regions.shape[1])
    keys = np.zeros(len(points), dtype=np.int64)
    keys[inside] = regions[rows[inside], cols[inside]]
    return keys


def interface_curves(regions: np.ndarray, pixel_size: tuple[float, float], smoothing_pixels: float = 1.0) -> list[Curve]:
    """The interfaces of a region image that border at least one tissue, as smoothed curves (mm)."""
    padded = np.pad(regions, 1)
    width = padded.shape[1] + 1  # corners per row of the padded image

    # Pixel edges between different regions. Padded pixel (i, j) spans corners (i, j)..(i+1, j+1).
    rows, cols = np.nonzero(padded[1:, :] != padded[:-1, :])  # between (r, c) and (r + 1, c)
    horizontal = (
        np.column_stack([(rows + 1) * width + cols, (rows + 1) * width + cols + 1]),
        np.column_stack([padded[rows, cols], padded[rows + 1, cols]]),
    )
    rows, cols = np.nonzero(padded[:, 1:] != padded[:, :-1])  # between (r, c) and (r, c + 1)
    vertical = (
        np.column_stack([rows * width + cols + 1, (rows + 1) * width + cols + 1]),
        np.column_stack([padded[rows, cols], padded[rows, cols + 1]]),
    )
    corners = np.vstack([horizontal[0], vertical[0]])
    sides = np.sort(np.vstack([horizontal[1], vertical[1]]), axis=1)
    keep = np.array([is_tissue(int(a)) or is_tissue(int(b)) for a, b in sides]) if len(sides) else np.zeros(0, bool)
    corners, sides = corners[keep], sides[keep]
    pair_code = sides[:, 0] * (BONE_KEY_OFFSET * 2) + sides[:, 1]

    incident: dict[int, list[int]] = {}
    for edge, (a, b) in enumerate(corners.tolist()):
        incident.setdefault(a, []).append(edge)
        incident.setdefault(b, []).append(edge)
    junctions = {
        corner
        for corner, edges in incident.items()
        if len(edges) != 2 or pair_code[edges[0]] != pair_code[edges[1]]
    }

    def corner_position(corner: int) -> np.ndarray:
        i, j = divmod(corner, width)
        return np.array([(j - 1) * pixel_size[1], (i - 1) * pixel_size[0]])

    def edge_midpoint(edge: int) -> np.ndarray:
        return 0.5 * (corner_position(corners[edge, 0]) + corner_position(corners[edge, 1]))

    visited = np.zeros(len(corners), dtype=bool)
    curves: list[Curve] = []

    def walk(start_corner: int, first_edge: int) -> tuple[list[int], int]:
        chain, corner, edge = [], start_corner, first_edge
        while True:
            visited[edge] = True
            chain.append(edge)
            a, b = corners[edge]
            corner = b if a == corner else a
            if corner in junctions:
                return chain, corner
            following = [e for e in incident[corner] if e != edge]
            edge = following[0]
            if visited[edge]:
                return chain, corner

    for junction in sorted(junctions):
        for first in incident[junction]:
            if visited[first]:
                continue
            chain, end = walk(junction, first)
            points = np.vstack(
                [corner_position(junction)] + [edge_midpoint(e) for e in chain] + [corner_position(end)]
            )
            points = smooth_points(points, closed=False, sigma=smoothing_pixels)
            curves.append(Curve(points, False, (int(sides[first, 0]), int(sides[first, 1]))))
    for first in range(len(corners)):
        if visited[first]:
            continue
        chain, _ = walk(int(corners[first, 0]), first)
        points = np.vstack([edge_midpoint(e) for e in chain])
        points = smooth_points(points, closed=True, sigma=smoothing_pixels)
        curves.append(Curve(points, True, (int(sides[first, 0]), int(sides[first, 1]))))
    return curves
