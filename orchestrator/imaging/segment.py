"""Segmentation of a T1-weighted calf slice into background, fat, muscle and bone, and the checks that say where
a label map is doubtful.

The first paper segments the T1 slice into tibia, fibula, fat and muscle
(section 2.1.1); the second thresholds fat first, as it is bright in T1
(section 3.2). Here, on the image smoothed by a Gaussian of `smoothing_mm` (lengths in mm, so that
a finer matrix of the same leg segments the same):

1. three-class Otsu thresholds (`skimage.filters.threshold_multiotsu`) split
   dark (air, cortex, flowing blood, fascia), intermediate (muscle, skin) and
   bright (fat, fatty marrow) grey levels;
2. the leg is the largest non-dark component, closed by a disk of `skin_closing_mm` (3 mm) and its holes filled:
   a superficial vein lies under the skin but is as dark as the air, and where it touches the skin's edge it cut a
   notch into the outline (another program's control case, a 3.6 mm vein: Laplace's law pressed the notch's
   curvature, and the fit ended at 4.8 x the floor against 1.0 x with that program's own labels). The saphenous
   veins are 3-5 mm across, and the closing fills notches up to 6 mm wide; the calf's outline has no concavity
   that tight, and a garment bridges one anyway;
3. bones (`find_bones`) are cortex plus marrow, whatever the marrow's grey level: on the image smoothed less
   (`bone_smoothing_mm`: a Gaussian of 0.36 mm lifts the middle of a 1 mm cortex above the dark threshold at
   0.6 mm pixels, and its ring opens), a region of the leg enclosed by the dark mask is marrow when its rim is a
   cortex: at least `min_cortex_mm` (0.5 mm) and a tenth of the region's radius thick along 80 % of its length,
   measured on a grid of 0.1 mm interpolated from the image, so that the test does not depend on the pixel (a
   1 mm cortex at 0.6 mm pixels is 0.6-0.7 mm thick at the threshold). Septa and fascia that close a loop around
   a compartment are too thin for its size, even as black as cortex. The dark mask with that marrow is opened by
   a disk of `bone_opening_mm` (1 mm: it drops the fascia, septa and vessels stuck to a bone, not the bone, a
   solid region at least 8 mm across), and its pieces of plausible area (`min_bone_area_mm2` to
   `max_bone_area_mm2`) are the bones. A marrow as dark as the cortex is part of the dark mask itself;
4. muscle (`find_muscle`) is what lies beyond the bright fat. The subcutaneous fat is crossed by fibrous septa,
   thin dark lines (0.3-0.6 mm) from the skin to the deep fascia, itself a dark line along the muscle, and the
   muscle holds streaks of fat, thin bright lines, some of which run out to the fascia: neither is the interface.
   Bright is told from the rest on the image smoothed as little as for the bones (`bone_smoothing_mm`, less than
   a septum is wide: at `smoothing_mm` septa 1 mm apart merged into a grey patch that passed for muscle, and a
   streak merged with the fat across the fascia). The non-bright leg is opened, together with the bones (which
   keep the thin muscle between a bone and the fascia), by a disk of `skin_opening_mm`: the skin ring and the
   septa, thinner than the disk, come off the muscle. The muscle is the largest piece of what is left deeper than
   `min_muscle_depth_mm` under the leg's outline (the skin covers the muscle: where the fat under it is too thin
   and septate to show bright, as over the tibia at 0.6 mm pixels, skin, septa and muscle are one non-bright
   piece), holes (veins, streaks) filled. Then every soft-tissue pixel takes the tissue that fills most of the
   soft tissue in the disk of `interface_disk_mm` around it: a line crossing the interface narrower than about
   pi/4 of that radius (a septum, a cluster of septa, a streak with the notch the opening cut round it where it
   meets the fascia) joins the tissue it crosses into, while a smooth interface stays where it is. (On the second
   phantom at 0.36 mm, septa grown back into the muscle put the meshed interface 0.5 mm outside the true one on
   average, RMS 0.9 mm with spikes up to 4 mm; now +0.05 mm, RMS 0.1 mm, at most 0.6 mm);
5. fat is the rest of the leg: skin, septa and superficial veins count as fat, as in
   the first paper's model (section 2.2.4).

The label boundary is a threshold, off the image's edge by a fraction of a pixel; the mesh
(`meshing.labels.EdgeMap`) puts the fat/muscle interface where the bright fat ends on the image itself.

Labels: 0 background, 1 fat, 2 muscle, 3 bone.

`segmentation_checks` reads any label map (this segmentation or a user's labels.png) and returns a
`SegmentationWarning` for each place it is unsure of: an island of one tissue inside another (fat inside the
muscle, muscle inside the fat, fat inside a bone: a lost marrow) of at least `min_island_mm2`, and a bone count
other than the calf's two (tibia and fibula), each with its place in mm (image frame) and a sentence saying it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage, signal
from skimage import filters, morphology

from ..core.errors import ImagingError
from ..core.tissues import BACKGROUND, BONE, FAT, FIRST_COMPARTMENT, MUSCLE

TISSUE_NAMES = {BACKGROUND: "background", FAT: "fat", MUSCLE: "muscle", BONE: "bone"}
CALF_BONES = ("tibia", "fibula")
RIM_GRID_MM = 0.1          # the grid on which a rim's thickness is measured
RIM_THICK_SHARE = 0.8      # share of a marrow's rim that must be cortex-thick (a partial-volumed pixel may not be)
CORTEX_TO_MARROW_RADIUS = 0.1   # a long bone's cortex is several tenths of its marrow's radius, septa round a compartment a few hundredths


def largest_component(mask: np.ndarray) -> np.ndarray:
    labelled, count = ndimage.label(mask)
    if count == 0:
        return np.zeros_like(mask, dtype=bool)
    sizes = np.bincount(labelled.ravel())
    sizes[0] = 0
    return labelled == int(np.argmax(sizes))


def segment_t1(image: np.ndarray, pixel_size_mm: tuple[float, float], *, smoothing_mm: float = 0.36,
               bone_smoothing_mm: float = 0.2, skin_opening_mm: float = 0.8, min_muscle_depth_mm: float = 1.5,
               interface_disk_mm: float = 3.0, min_bone_area_mm2: float = 40.0,
               max_vein_hole_mm2: float = 30.0, skin_closing_mm: float = 3.0,
               fat_shift_mm: float = 0.0) -> np.ndarray:
    """Label map (uint8) of a T1 slice: 0 background, 1 fat (with skin), 2 muscle, 3 bone. fat_shift_mm: the size of
    the fat's chemical shift on the image (`chemical_shift`), by which a fatty marrow's edge moves against its
    cortex's outer one: the cortex looks that much thinner on one side (`find_bones`)."""
    image = np.asarray(image, dtype=float)
    pixel_area = pixel_size_mm[0] * pixel_size_mm[1]
    # lengths in mm, not pixels: a 2048-pixel slice of the same leg has the same anatomy and the same noise per pixel
    scale_px = smoothing_mm / min(pixel_size_mm)
    smooth = ndimage.gaussian_filter(image, scale_px)
    try:
        dark_level, bright_level = filters.threshold_multiotsu(smooth, classes=3)
    except ValueError:   # scikit-image's text speaks of bins: say what the image lacks
        raise ImagingError("no leg found in the image: it holds too few grey levels for three classes (background, "
                           "soft tissue, bone); give the MRI slice itself, not a blank or binary image") from None

    leg = _bridge_notches(ndimage.binary_fill_holes(largest_component(smooth > dark_level)), skin_closing_mm,
                          pixel_size_mm)
    if leg.sum() * pixel_area < 100.0:
        raise ImagingError("no leg found in the image: it has no large region brighter than the background")

    sharp = ndimage.gaussian_filter(image, bone_smoothing_mm / min(pixel_size_mm))
    bone = find_bones(sharp, leg, dark_level, pixel_size_mm, min_bone_area_mm2=min_bone_area_mm2,
                      fat_shift_mm=fat_shift_mm)
    if not bone.any():
        raise ImagingError(f"no bone found: no dark ring inside the leg encloses {min_bone_area_mm2} mm^2")

    muscle = find_muscle(leg & (sharp > bright_level), leg, bone, pixel_size_mm, skin_opening_mm=skin_opening_mm,
                         min_depth_mm=min_muscle_depth_mm, interface_disk_mm=interface_disk_mm,
                         max_hole_mm2=max_vein_hole_mm2)

    labels = np.zeros(image.shape, dtype=np.uint8)
    labels[leg] = FAT
    labels[muscle] = MUSCLE
    labels[bone] = BONE
    return labels


def find_muscle(bright: np.ndarray, leg: np.ndarray, bone: np.ndarray, pixel_size_mm, *, skin_opening_mm: float = 0.8,
                min_depth_mm: float = 1.5, interface_disk_mm: float = 3.0, max_hole_mm2: float = 30.0) -> np.ndarray:
    """Mask of the muscle in the leg: what lies beyond the bright fat (`bright`: fat, fatty marrow, streaks of fat),
    with the septa on the fat's side and the streaks on the muscle's (see the module text, step 4)."""
    max_hole = max(1, int(max_hole_mm2 / (pixel_size_mm[0] * pixel_size_mm[1])))
    not_bright = leg & ~bright & ~bone
    muscle = _opening_mm(not_bright | bone, skin_opening_mm, pixel_size_mm) & not_bright
    muscle &= ndimage.distance_transform_edt(leg, sampling=pixel_size_mm) > min_depth_mm
    muscle = morphology.remove_small_holes(largest_component(muscle) | bone, max_size=max_hole) & ~bone
    soft = leg & ~bone
    muscle = largest_component(_majority(muscle, soft, interface_disk_mm, pixel_size_mm))
    return morphology.remove_small_holes(muscle | bone, max_size=max_hole) & ~bone


def _majority(mask: np.ndarray, within: np.ndarray, radius_mm: float, pixel_size_mm) -> np.ndarray:
    """Pixels of `within` where `mask` covers more than half of `within` in the disk of radius_mm around them."""
    half_rows, half_cols = (int(np.ceil(radius_mm / size)) for size in pixel_size_mm)
    rows, cols = np.mgrid[-half_rows:half_rows + 1, -half_cols:half_cols + 1]
    disk = (np.hypot(rows * pixel_size_mm[0], cols * pixel_size_mm[1]) <= radius_mm).astype(float)
    # pixel counts: whole numbers once the transform's round-off is rounded away, so that a tie is a tie
    covered = np.rint(signal.fftconvolve((mask & within).astype(float), disk, mode="same"))
    total = np.rint(signal.fftconvolve(within.astype(float), disk, mode="same"))
    return within & (2.0 * covered > total)


def find_bones(image: np.ndarray, leg: np.ndarray, dark_level: float, pixel_size_mm, *, min_cortex_mm: float = 0.5,
               bone_opening_mm: float = 1.0, min_bone_area_mm2: float = 40.0,
               max_bone_area_mm2: float = 1500.0, fat_shift_mm: float = 0.0) -> np.ndarray:
    """Mask of the bones in the leg: the dark mask (image <= dark_level) with the regions it encloses whose rim is
    a cortex (see the module text), opened by a disk of bone_opening_mm, pieces of min_bone_area_mm2 to
    max_bone_area_mm2 (15 cm^2: over twice a tibia's cross-section in the calf). fat_shift_mm: the fat's chemical
    shift, by which a fatty marrow moves against its cortex: the cortex a bone's size asks for is that much thinner
    (never under min_cortex_mm). On the third phantom (1.4 px of 0.4 mm) the tibia's cortex fell under a tenth of
    its marrow's radius along a quarter of its rim, and its marrow was read as an island of fat."""
    pixel_area = pixel_size_mm[0] * pixel_size_mm[1]
    # no opening before the holes are filled: at 0.6 mm a 1.2 mm cortex is a ring two pixels wide, which an
    # opening by the smallest disk (one pixel) erases, and the fibula's marrow then became an island of fat
    dark = leg & (image <= dark_level)
    enclosed, _ = ndimage.label(ndimage.binary_fill_holes(dark) & ~dark)
    marrow = np.zeros_like(dark)
    for index, piece in enumerate(ndimage.find_objects(enclosed), start=1):
        region = enclosed[piece] == index
        area = region.sum() * pixel_area
        if area > max_bone_area_mm2:
            continue
        cortex_mm = max(min_cortex_mm, CORTEX_TO_MARROW_RADIUS * np.sqrt(area / np.pi) - abs(fat_shift_mm))
        # a speck smaller than the cortex is thick has no rim to measure: noise inside a dark region, kept with it
        if area < np.pi * min_cortex_mm ** 2 or _thick_rim_share(
                image, dark_level, enclosed, index, piece, pixel_size_mm, cortex_mm) >= RIM_THICK_SHARE:
            marrow[piece] |= region
    solid = _opening_mm(dark | marrow, bone_opening_mm, pixel_size_mm)
    pieces, _ = ndimage.label(solid)
    areas = np.bincount(pieces.ravel()) * pixel_area
    plausible = (areas >= min_bone_area_mm2) & (areas <= max_bone_area_mm2)
    plausible[0] = False
    return plausible[pieces]


def _bridge_notches(leg: np.ndarray, radius_mm: float, pixel_size_mm) -> np.ndarray:
    """The leg with every notch narrower than 2 radius_mm in its outline filled (a closing), and the outline across
    it straight: the closing alone leaves a concave arc of radius_mm there (0.6 mm deep across a 3.6 mm vein), whose
    curvature Laplace's law turns into a pull. Within radius_mm of each filled notch the leg takes its convex hull,
    the chord between the notch's lips, 0.03 mm inside a calf's outline of 55 mm radius over 3.6 mm."""
    closed = _closing_mm(leg, radius_mm, pixel_size_mm)
    notches, _ = ndimage.label(closed & ~leg)
    margin = int(np.ceil(2.0 * radius_mm / min(pixel_size_mm))) + 1
    for index, box in enumerate(ndimage.find_objects(notches), start=1):
        rows = slice(max(box[0].start - margin, 0), min(box[0].stop + margin, leg.shape[0]))
        cols = slice(max(box[1].start - margin, 0), min(box[1].stop + margin, leg.shape[1]))
        near = ndimage.distance_transform_edt(notches[rows, cols] != index, sampling=pixel_size_mm) <= radius_mm
        closed[rows, cols] |= morphology.convex_hull_image(closed[rows, cols]) & near
    return closed


def _closing_mm(mask: np.ndarray, radius_mm: float, pixel_size_mm) -> np.ndarray:
    """Closing by a Euclidean disk of radius_mm, holes filled; the image is padded so that a leg touching its border
    is not closed against it."""
    if radius_mm <= 0:
        return mask
    pad = int(np.ceil(radius_mm / min(pixel_size_mm))) + 1
    padded = np.pad(mask, pad)
    grown = ndimage.distance_transform_edt(~padded, sampling=pixel_size_mm) <= radius_mm
    closed = ~(ndimage.distance_transform_edt(grown, sampling=pixel_size_mm) <= radius_mm)
    return ndimage.binary_fill_holes(closed | padded)[pad:-pad, pad:-pad]


def _opening_mm(mask: np.ndarray, radius_mm: float, pixel_size_mm) -> np.ndarray:
    """Opening by a Euclidean disk of radius_mm (through distance transforms: the radius need not be whole pixels)."""
    core = ndimage.distance_transform_edt(mask, sampling=pixel_size_mm) > radius_mm
    if not core.any():
        return core
    return ndimage.distance_transform_edt(~core, sampling=pixel_size_mm) <= radius_mm


def _thick_rim_share(image: np.ndarray, dark_level: float, regions: np.ndarray, index: int,
                     piece: tuple[slice, slice], pixel_size_mm, thickness_mm: float) -> float:
    """Share of the dark rim around region `index` of the labelled `regions` (`piece` its bounding box) that is at
    least thickness_mm thick, measured on a grid of RIM_GRID_MM interpolated (bilinearly) from the image, where the
    partial-volumed edge of a cortex lands between pixels instead of on one of them."""
    margin = int(np.ceil(2 * thickness_mm / min(pixel_size_mm))) + 2
    window = tuple(slice(max(s.start - margin, 0), min(s.stop + margin, n)) for s, n in zip(piece, image.shape))
    factor = max(1, int(np.ceil(max(pixel_size_mm) / RIM_GRID_MM)))
    fine_pixel = (pixel_size_mm[0] / factor, pixel_size_mm[1] / factor)
    fine = ndimage.zoom(image[window], factor, order=1, grid_mode=True, mode="nearest")
    dark = fine <= dark_level
    # the region grown by one pixel: its edge on the fine grid may lie up to a pixel from its edge on the image's
    grown = ndimage.binary_dilation(regions[window] == index, structure=np.ones((3, 3)))
    inside = np.kron(grown, np.ones((factor, factor), bool))
    inside &= ~dark
    rim = dark & ndimage.binary_dilation(inside)
    if not rim.any():
        return 0.0
    return float(_opening_mm(dark, thickness_mm / 2, fine_pixel)[rim].mean())


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice overlap 2|A n B| / (|A| + |B|) of two masks."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    total = a.sum() + b.sum()
    return 1.0 if total == 0 else 2.0 * np.logical_and(a, b).sum() / total


# ----------------------------------------------------------------- checks


@dataclass(frozen=True)
class SegmentationWarning:
    """A place where a label map is doubtful: kind ("island" or "bone_count"), the place (x, y) in mm in the image
    frame, the area concerned (mm^2), a sentence that says it, and a few words for a figure."""

    kind: str
    position_mm: tuple[float, float]
    area_mm2: float
    message: str
    short: str

    def as_dict(self) -> dict:
        info = asdict(self)
        info["position_mm"] = [round(float(v), 2) for v in self.position_mm]
        info["area_mm2"] = round(float(self.area_mm2), 1)
        return info

    @classmethod
    def from_dict(cls, info: dict) -> "SegmentationWarning":
        return cls(info["kind"], tuple(info["position_mm"]), float(info["area_mm2"]), info["message"], info["short"])


def tissue_map(labels: np.ndarray) -> np.ndarray:
    """The label map with the muscle compartments (>= 4) as muscle."""
    labels = np.asarray(labels)
    return np.where(labels >= FIRST_COMPARTMENT, MUSCLE, labels).astype(np.uint8)


def segmentation_checks(labels: np.ndarray, pixel_size_mm, *, min_island_mm2: float = 25.0,
                        bones: tuple[str, ...] = CALF_BONES) -> list[SegmentationWarning]:
    """What is doubtful in a label map (0 background, 1 fat, 2 muscle, 3 bone, >= 4 compartments): islands of fat or
    muscle of at least min_island_mm2 (25 mm^2: about an element of a 400-element mesh of a calf) inside another
    tissue, and a bone count other than len(bones). Islands come largest first, then the bone count."""
    tissues = tissue_map(labels)
    pixel_area = pixel_size_mm[0] * pixel_size_mm[1]
    warnings = []
    for tissue in (FAT, MUSCLE):
        warnings += _islands(tissues, tissue, pixel_size_mm, min_island_mm2)
    warnings.sort(key=lambda w: -w.area_mm2)
    pieces, count = ndimage.label(tissues == BONE, structure=np.ones((3, 3)))
    if count != len(bones):
        found = sorted(((_place(pieces == k, pixel_size_mm), float((pieces == k).sum() * pixel_area))
                        for k in range(1, count + 1)), key=lambda item: -item[1])
        expected = f"a calf slice has {len(bones)} ({' and '.join(bones)})"
        listing = ", ".join(f"{area:.0f} mm2 at {_at(place)}" for place, area in found)
        if count > len(bones):
            place, area = found[-1]   # the smallest is the likeliest to be something else
            message = f"{count} bones where {expected}: {listing} mm"
            short = f"{count} bones, {len(bones)} expected"
        elif count:
            place = tuple(np.mean([p for p, _ in found], axis=0))
            area = sum(a for _, a in found)
            message = (f"{count} bone{'s' if count > 1 else ''} where {expected}: {listing} mm; one is missing "
                       "(its marrow read as another tissue) or two are joined")
            short = f"{count} bone{'s' if count > 1 else ''}, {len(bones)} expected"
        else:
            place, area = _place(tissues > BACKGROUND, pixel_size_mm), 0.0
            message, short = f"no bone where {expected}", f"no bone, {len(bones)} expected"
        warnings.append(SegmentationWarning("bone_count", place, area, message, short))
    return warnings


def _islands(tissues: np.ndarray, tissue: int, pixel_size_mm, min_area_mm2: float) -> list[SegmentationWarning]:
    """Pieces of `tissue` cut off from its main body and enclosed by another tissue: for fat, the pieces that do not
    reach the outside of the leg (the subcutaneous fat and the skin do); for muscle, all but the largest piece."""
    pixel_area = pixel_size_mm[0] * pixel_size_mm[1]
    pieces, count = ndimage.label(tissues == tissue, structure=np.ones((3, 3)))
    if count == 0:
        return []
    sizes = np.bincount(pieces.ravel())
    if tissue == FAT:
        outside = ndimage.binary_dilation(tissues == BACKGROUND, border_value=1)
        main = set(np.unique(pieces[outside]))
    else:
        main = {int(np.argmax(sizes[1:])) + 1}
    found = []
    for index, piece in enumerate(ndimage.find_objects(pieces), start=1):
        area = sizes[index] * pixel_area
        if index in main or area < min_area_mm2:
            continue
        window = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in piece)
        island = pieces[window] == index
        around = tissues[window][ndimage.binary_dilation(island, structure=np.ones((3, 3))) & ~island]
        host = int(np.bincount(around, minlength=BONE + 1).argmax())
        offset = (window[0].start, window[1].start)
        place = _place(island, pixel_size_mm, offset)
        name, host_name = TISSUE_NAMES[tissue], TISSUE_NAMES[host]
        found.append(SegmentationWarning(
            "island", place, area, f"an island of {name} of {area:.0f} mm2 inside the {host_name} at {_at(place)} mm",
            f"{name} in {host_name}, {area:.0f} mm2"))
    return found


def _place(mask: np.ndarray, pixel_size_mm, offset: tuple[int, int] = (0, 0)) -> tuple[float, float]:
    """(x, y) mm of a region: its centroid, or its pixel nearest the centroid when the centroid falls outside it (a
    crescent), so that a marker drawn there lands on the region."""
    rows, cols = np.nonzero(mask)
    row, col = rows.mean(), cols.mean()
    if not mask[int(round(row)), int(round(col))]:
        nearest = np.argmin((rows - row) ** 2 + (cols - col) ** 2)
        row, col = rows[nearest], cols[nearest]
    dy, dx = pixel_size_mm
    return float((col + offset[1] + 0.5) * dx), float((row + offset[0] + 0.5) * dy)


def _at(place: tuple[float, float]) -> str:
    return f"({place[0]:.1f}, {place[1]:.1f})"
