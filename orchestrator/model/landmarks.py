"""The five named positions of the first paper (Avril et al. sec. 3.2, Table 3), placed from I0's segmentation when
case.toml names none: a user with images and no landmarks still gets the pressures a garment designer reads.

The leg's frame (`regions.LegFrame`) gives its centre, the ray to the tibia (the first bone) and the side of the
fibula (lateral). The tibia lies anteromedial: the anterior midline is TIBIA_MEDIAL_OF_ANTERIOR_DEG lateral of the
tibia's ray (the first paper's leg, Fig. 2, as calfit's phantom draws it). Along a ray from the centre the labels are
read outwards; the fat is the last run of fat before the skin and the fascia its inner edge. The landmarks are then:
- hypodermis_tibia: the middle of the fat on the ray through the tibia (the thin fat over the tibia's face);
- max_pressure: the fascia on the posterior midline, where the first paper found the largest pressure (the
  gastrocnemius under the thickest fat);
- small_saphenous: the middle of the fat on the posterior midline (the vein runs in the posterior midline's fat);
- great_saphenous: the middle of the fat on the ray GREAT_SAPHENOUS_FROM_TIBIA_DEG medial of the tibia's (the vein
  runs in the medial fat, behind the tibia's medial border);
- deep_veins: the posterior tibial veins on tibialis posterior: from the tibia's centroid along the normal of the
  tibia-fibula line (towards the back) to the bone's surface, then DEEP_VEINS_BEHIND_TIBIA_MM further, and
  DEEP_VEINS_TOWARDS_FIBULA_MM towards the fibula. With one bone, on the ray from the tibia through the centre.
These are anatomical conventions, not measurements: the veins themselves are not segmented, so a vein's landmark is
where that vein usually runs, to within its own diameter's few millimetres, and every output that uses them says
they were placed (case.toml's [landmarks] table puts them where the user wants).
"""

from __future__ import annotations

import numpy as np

from ..core.tissues import BONE, FAT
from .regions import LegFrame, bone_centroids

LANDMARK_NAMES = ("hypodermis_tibia", "deep_veins", "max_pressure", "great_saphenous", "small_saphenous")
TIBIA_MEDIAL_OF_ANTERIOR_DEG = 30.0     # the tibia's ray, medial of the anterior midline
GREAT_SAPHENOUS_FROM_TIBIA_DEG = 75.0   # the vein's ray, medial of the tibia's (105 deg from the anterior midline)
DEEP_VEINS_BEHIND_TIBIA_MM = 5.0        # tibialis posterior's thickness between the tibia and the veins
DEEP_VEINS_TOWARDS_FIBULA_MM = 5.0      # the veins lie behind the tibia's lateral half, towards the membrane


class LandmarkError(ValueError):
    """The segmentation does not show what a landmark is placed by (a bone, the fat on a ray)."""


def _labels_along(frame: LegFrame, origin_mm: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(positions (n, 2) mm, labels (n,)) every quarter pixel from origin along direction, to the image's edge."""
    step = 0.25 * min(frame.pixel_size_mm)
    dy, dx = frame.pixel_size_mm
    extent = np.hypot(frame.labels.shape[0] * dy, frame.labels.shape[1] * dx)
    positions = origin_mm + np.arange(0.0, extent, step)[:, None] * direction
    inside = ((positions[:, 0] >= 0) & (positions[:, 0] < frame.labels.shape[1] * dx)
              & (positions[:, 1] >= 0) & (positions[:, 1] < frame.labels.shape[0] * dy))
    positions = positions[inside]
    rows = (positions[:, 1] / dy).astype(int)
    cols = (positions[:, 0] / dx).astype(int)
    return positions, frame.labels[rows, cols]


def _unit(display_deg: float) -> np.ndarray:
    """The image-frame direction (x right, y down) of a display angle (counter-clockwise on the screen)."""
    a = np.radians(display_deg)
    return np.array([np.cos(a), -np.sin(a)])


def _outer_fat(frame: LegFrame, display_deg: float, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(the fascia, the middle of the fat) on the ray from the leg's centre at display_deg: the last run of fat
    before the skin (label 0 after it)."""
    positions, labels = _labels_along(frame, frame.centre_mm, _unit(display_deg))
    leg = np.nonzero(labels > 0)[0]
    if not leg.size:
        raise LandmarkError(f"the ray of {name} meets no leg in the segmentation")
    last = leg[-1]
    first = last
    while first > 0 and labels[first - 1] == FAT:
        first -= 1
    if labels[last] != FAT or first == last:
        raise LandmarkError(f"the segmentation shows no fat under the skin on the ray of {name} "
                            f"({display_deg:.0f} deg on the display)")
    return positions[first], 0.5 * (positions[first] + positions[last])


def _behind_the_tibia(frame: LegFrame, tibia: np.ndarray, fibula: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(the unit normal of the tibia-fibula line on the leg centre's side, the unit vector from the tibia to the
    fibula); with no fibula, the ray from the tibia through the centre and no shift along."""
    towards_centre = frame.centre_mm - tibia
    if fibula is None:
        return towards_centre / np.linalg.norm(towards_centre), np.zeros(2)
    along = (np.asarray(fibula, float) - tibia) / np.linalg.norm(np.asarray(fibula, float) - tibia)
    normal = np.array([-along[1], along[0]])
    return (normal if normal @ towards_centre >= 0 else -normal), along


def placed_landmarks(frame: LegFrame) -> dict[str, tuple[float, float]]:
    """The five landmarks (mm, image frame of I0) from the segmentation (module text). LandmarkError when the
    segmentation holds no bone, or no fat on a landmark's ray."""
    bones = bone_centroids(frame.labels, frame.pixel_size_mm)
    if frame.anterior_deg is None or not bones:
        raise LandmarkError("the segmentation holds no bone, so the landmarks cannot be placed: add a [landmarks] "
                            "table to case.toml")
    tibia_ray = frame.anterior_deg
    lateral = frame.lateral_sense   # +1: lateral is counter-clockwise of the tibia's ray on the display
    back = (tibia_ray + lateral * TIBIA_MEDIAL_OF_ANTERIOR_DEG + 180.0) % 360.0
    medial = (tibia_ray - lateral * GREAT_SAPHENOUS_FROM_TIBIA_DEG) % 360.0
    _, hypodermis = _outer_fat(frame, tibia_ray, "hypodermis_tibia")
    fascia_back, small_saphenous = _outer_fat(frame, back, "small_saphenous")
    _, great_saphenous = _outer_fat(frame, medial, "great_saphenous")
    tibia = np.asarray(bones[0][0], float)
    behind, along = _behind_the_tibia(frame, tibia, bones[1][0] if len(bones) > 1 else None)
    positions, labels = _labels_along(frame, tibia, behind)
    outside = np.nonzero(labels != BONE)[0]
    if not outside.size:
        raise LandmarkError("the tibia's back surface is not found in the segmentation: add a [landmarks] table")
    deep = positions[outside[0]] + DEEP_VEINS_BEHIND_TIBIA_MM * behind + DEEP_VEINS_TOWARDS_FIBULA_MM * along
    points = {"hypodermis_tibia": hypodermis, "deep_veins": deep, "max_pressure": fascia_back,
              "great_saphenous": great_saphenous, "small_saphenous": small_saphenous}
    return {name: (float(points[name][0]), float(points[name][1])) for name in LANDMARK_NAMES}
