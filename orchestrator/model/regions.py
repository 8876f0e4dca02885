"""Where a place in the leg is, in the words a clinician reads: tissue, sector around the leg, depth under the skin.

The frame comes from the segmentation of I0 alone. The leg centre is the centroid of the leg (fat, muscle and
bone). Angles are read on the image as displayed (x to the right, y downwards), counter-clockwise from the +x
axis about that centre, so that 90 deg is the top of the picture. Each sector is named after the anatomical
direction nearest its middle: anterior is the direction from the leg centre to the tibia (the largest bone,
under the thin anterior skin), lateral the side of the fibula (the second bone), posterior and medial their
opposites; with one bone only, the sides are named "image left/right". Depth is the distance to the skin
(the edge of the leg) in mm.

Example: "fat, posterior sector 240-270 deg, 0-5 mm under the skin".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..core.tissues import tissue_of_label
from ..imaging.align import bone_centroids
from ..imaging.mismatch import FIRST_COMPARTMENT

SECTORS = 12                   # 30-degree sectors
DEPTH_BANDS_MM = (0.0, 5.0, 10.0, 20.0, 40.0, np.inf)
DEEP_COMPARTMENT_MM = 15.0
DIRECTIONS = ("anterior", "anterolateral", "lateral", "posterolateral", "posterior", "posteromedial", "medial",
              "anteromedial")
QUARTERS = ("anterior", "lateral", "posterior", "medial")
IMAGE_SIDES = ("image right", "image top", "image left", "image bottom")   # the quarters' names without bones


@dataclass
class LegFrame:
    """Centre, anatomical orientation and skin-distance map of one leg slice (module text)."""

    labels: np.ndarray
    pixel_size_mm: tuple[float, float]
    centre_mm: np.ndarray
    anterior_deg: float | None       # display angle of the anterior direction; None without bones
    lateral_sense: int               # +1: lateral is counter-clockwise from anterior on the display, -1 clockwise
    skin_distance_mm: np.ndarray

    @classmethod
    def from_labels(cls, labels: np.ndarray, pixel_size_mm) -> "LegFrame":
        labels = np.asarray(labels)
        leg = labels > 0
        if not leg.any():
            raise ValueError("the segmentation holds no leg")
        dy, dx = pixel_size_mm
        rows, cols = np.nonzero(leg)
        centre = np.array([(cols.mean() + 0.5) * dx, (rows.mean() + 0.5) * dy])
        bones = bone_centroids(labels, pixel_size_mm)
        anterior, sense = None, 1
        if bones:
            anterior = display_angle_deg(bones[0][0][None, :], centre)[0]
            if len(bones) > 1:
                lateral = display_angle_deg(bones[1][0][None, :], centre)[0]
                sense = 1 if (lateral - anterior) % 360.0 < 180.0 else -1
        distance = ndimage.distance_transform_edt(np.pad(leg, 1), sampling=pixel_size_mm)[1:-1, 1:-1]
        return cls(labels, (float(dy), float(dx)), centre, anterior, sense, distance)

    def _pixels(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dy, dx = self.pixel_size_mm
        points = np.asarray(points_mm, float).reshape(-1, 2)
        rows = np.clip((points[:, 1] / dy).astype(int), 0, self.labels.shape[0] - 1)
        cols = np.clip((points[:, 0] / dx).astype(int), 0, self.labels.shape[1] - 1)
        return rows, cols

    def tissues(self, points_mm: np.ndarray) -> list[str]:
        rows, cols = self._pixels(points_mm)
        return [tissue_of_label(int(v)) for v in self.labels[rows, cols]]

    def depth_mm(self, points_mm: np.ndarray) -> np.ndarray:
        rows, cols = self._pixels(points_mm)
        return self.skin_distance_mm[rows, cols]

    def angles_deg(self, points_mm: np.ndarray) -> np.ndarray:
        return display_angle_deg(points_mm, self.centre_mm)

    def direction(self, angle_deg: float) -> str:
        """Anatomical name of the direction at a display angle."""
        return self._nearest(angle_deg, DIRECTIONS)

    def quarter(self, angle_deg: float) -> str:
        """Anatomical name of the quarter of the leg (90 degrees about anterior, lateral, posterior or medial) that
        holds a display angle."""
        return self._nearest(angle_deg, QUARTERS)

    def _nearest(self, angle_deg: float, names: tuple[str, ...]) -> str:
        """The one of `names`, evenly spaced around the leg from anterior towards lateral, nearest a display angle;
        without bones, the image's sides."""
        if self.anterior_deg is None:
            return IMAGE_SIDES[int(((angle_deg + 45.0) % 360.0) // 90.0)]
        width = 360.0 / len(names)
        relative = ((angle_deg - self.anterior_deg) * self.lateral_sense) % 360.0
        return names[int(((relative + width / 2.0) % 360.0) // width)]

    def sector_label(self, sector: int) -> str:
        width = 360.0 / SECTORS
        low = sector * width
        return f"{self.direction(low + width / 2)} sector {low:.0f}-{low + width:.0f} deg"

    def sectors(self, points_mm: np.ndarray) -> np.ndarray:
        return np.minimum((self.angles_deg(points_mm) / (360.0 / SECTORS)).astype(int), SECTORS - 1)


def compartment_names(labels: np.ndarray, pixel_size_mm) -> dict[int, str]:
    """A name per muscle compartment (label >= 4) a reader can find on the image: its number, the direction of its
    centroid from the leg centre ("deep" when it lies more than DEEP_COMPARTMENT_MM under the skin everywhere: the
    direction of a compartment between the bones says little), its depth range and its area, e.g.
    "compartment 2: posterior, 12-48 mm under the skin, 38.4 cm2"."""
    frame = LegFrame.from_labels(labels, pixel_size_mm)
    dy, dx = frame.pixel_size_mm
    names = {}
    for number, label in enumerate(sorted(int(v) for v in np.unique(labels[labels >= FIRST_COMPARTMENT])), start=1):
        rows, cols = np.nonzero(labels == label)
        centroid = np.array([[(cols.mean() + 0.5) * dx, (rows.mean() + 0.5) * dy]])
        depth = frame.skin_distance_mm[rows, cols]
        where = "deep" if depth.min() > DEEP_COMPARTMENT_MM else frame.direction(frame.angles_deg(centroid)[0])
        names[label] = (f"compartment {number}: {where}, "
                        f"{depth.min():.0f}-{depth.max():.0f} mm under the skin, {len(rows) * dx * dy / 100.0:.1f} cm2")
    return names


def display_angle_deg(points_mm: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
    """Counter-clockwise angle on the displayed image (y down) from +x, in [0, 360)."""
    offset = np.asarray(points_mm, float).reshape(-1, 2) - np.asarray(centre_mm, float)
    return np.degrees(np.arctan2(-offset[:, 1], offset[:, 0])) % 360.0


def depth_band(depth_mm: float) -> str:
    for low, high in zip(DEPTH_BANDS_MM[:-1], DEPTH_BANDS_MM[1:]):
        if depth_mm < high:
            return f"{low:.0f}-{high:.0f} mm under the skin" if np.isfinite(high) else f"over {low:.0f} mm under the skin"
    return f"over {DEPTH_BANDS_MM[-2]:.0f} mm under the skin"
