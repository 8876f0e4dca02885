"""The five landmarks placed from a segmentation (`model.landmarks`) against the positions calfit's phantom gives them
from its exact geometry, on legs of other sizes, at two pixel sizes and mirrored (a right leg); a segmentation
without bones is refused in one sentence."""

import numpy as np
import pytest

from orchestrator.core.tissues import BONE, FAT, MUSCLE
from orchestrator.model.landmarks import LANDMARK_NAMES, LandmarkError, placed_landmarks
from orchestrator.model.regions import LegFrame
from orchestrator.phantom.geometry import LANDMARK_NAMES as PHANTOM_NAMES
from orchestrator.phantom.geometry import CalfGeometry, CalfShape

SIDE_MM = 151.2


def _labels(geometry: CalfGeometry, pixel_mm: float) -> np.ndarray:
    centres = (np.arange(int(SIDE_MM / pixel_mm)) + 0.5) * pixel_mm
    x, y = np.meshgrid(centres, centres)
    return geometry.labels_at(x, y)


@pytest.mark.parametrize("pixel_mm", [0.36, 0.6])
@pytest.mark.parametrize("shape", [{}, {"half_width_mm": 50.0, "fat_back_mm": 16.0},
                                   {"half_depth_mm": 46.0, "fat_side_mm": 5.0}])
def test_placed_landmarks_lie_where_the_phantom_puts_them(pixel_mm, shape):
    geometry = CalfGeometry(CalfShape(**shape))
    labels = _labels(geometry, pixel_mm)
    placed = placed_landmarks(LegFrame.from_labels(labels, (pixel_mm, pixel_mm)))
    assert tuple(placed) == LANDMARK_NAMES == PHANTOM_NAMES
    truth = geometry.landmarks()
    error = {name: float(np.hypot(*(np.asarray(placed[name]) - truth[name]))) for name in LANDMARK_NAMES}
    # the fat's middle and the fascia to a pixel and a half; the veins to their own diameter (3.2 mm)
    assert max(error["hypodermis_tibia"], error["max_pressure"]) < 2.0, error
    assert max(error["deep_veins"], error["great_saphenous"], error["small_saphenous"]) < 3.2, error
    tissue = {name: labels[int(y / pixel_mm), int(x / pixel_mm)] for name, (x, y) in placed.items()}
    assert tissue["hypodermis_tibia"] == tissue["great_saphenous"] == tissue["small_saphenous"] == FAT
    assert tissue["deep_veins"] == MUSCLE


def test_a_mirrored_leg_gets_mirrored_landmarks():
    # a right leg is the left one mirrored: the great saphenous vein goes to the other side of the tibia
    geometry, pixel_mm = CalfGeometry(CalfShape()), 0.6
    labels = _labels(geometry, pixel_mm)
    left = placed_landmarks(LegFrame.from_labels(labels, (pixel_mm, pixel_mm)))
    right = placed_landmarks(LegFrame.from_labels(labels[:, ::-1], (pixel_mm, pixel_mm)))
    width = labels.shape[1] * pixel_mm
    for name in LANDMARK_NAMES:
        assert np.hypot(right[name][0] - (width - left[name][0]), right[name][1] - left[name][1]) < 1.0, name


def test_a_segmentation_without_bones_is_refused():
    geometry, pixel_mm = CalfGeometry(CalfShape()), 0.6
    labels = _labels(geometry, pixel_mm)
    labels[labels == BONE] = MUSCLE
    with pytest.raises(LandmarkError, match="no bone"):
        placed_landmarks(LegFrame.from_labels(labels, (pixel_mm, pixel_mm)))
