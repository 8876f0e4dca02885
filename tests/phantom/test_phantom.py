"""The phantom calf: anatomy, T1 contrast, texture moving with the tissue, inverse warping, case writing."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from scipy import ndimage

from orchestrator.case.folder import read_case
from orchestrator.core.frame import RigidMotion, displacement_on_grid, pixel_centres_mm
from orchestrator.phantom import (
    COMPARTMENTS,
    LANDMARK_NAMES,
    CalfGeometry,
    CalfPhantom,
    CalfShape,
    T1Contrast,
    Tissue,
    as_displacement_fn,
    loaded_labels,
    make_loaded_image,
    material_points,
    render_unloaded,
    write_case,
)


@pytest.fixture(scope="module")
def phantom_model():
    return CalfPhantom()


@pytest.fixture(scope="module")
def phantom_noiseless(phantom_model):
    return render_unloaded(phantom_model, noise_seed=None)


def _polygon_area(points: np.ndarray) -> float:
    x, y = points.T
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_calf_size_matches_a_calf_at_its_largest_perimeter(phantom_model):
    skin = phantom_model.geometry.boundaries()["skin"]
    width = skin[:, 0].max() - skin[:, 0].min()
    assert 110.0 <= width <= 120.0
    assert phantom_model.image_shape == (420, 420) and phantom_model.pixel_size_mm == (0.36, 0.36)
    perimeter = np.sum(np.hypot(*np.diff(np.vstack([skin, skin[:1]]), axis=0).T))
    assert 320.0 < perimeter < 380.0


def test_fat_is_thin_over_the_tibia_and_thick_at_the_back(phantom_model):
    geometry = phantom_model.geometry
    over_tibia = geometry.fat_thickness(np.deg2rad(geometry.shape.tibia_angle_deg))
    back = geometry.fat_thickness(np.pi / 2)
    assert over_tibia < 3.5 and back > 10.0
    # The tibia is nearest to the skin on the anteromedial side: the hypodermis landmark lies between them, in fat.
    x, y = geometry.landmarks()["hypodermis_tibia"]
    assert geometry.tissue_at(x, y) == Tissue.FAT
    assert -geometry.skin.radial_excess(x, y) < 3.5


def test_landmarks_sit_in_their_tissues(phantom_model):
    geometry = phantom_model.geometry
    marks = geometry.landmarks()
    assert tuple(marks) == LANDMARK_NAMES
    assert geometry.tissue_at(*marks["great_saphenous"]) == Tissue.SUPERFICIAL_VEIN
    assert geometry.tissue_at(*marks["small_saphenous"]) == Tissue.SUPERFICIAL_VEIN
    assert geometry.labels_at(*marks["deep_veins"]) == 2                    # between the paired deep veins, in muscle
    x, y = marks["max_pressure"]
    assert abs(geometry.fascia.radial_excess(x, y)) < 1e-9                   # on the fat/muscle interface
    assert y > geometry.shape.centre_mm[1]                                   # at the back
    assert marks["great_saphenous"][0] < geometry.shape.centre_mm[0]         # medial (left)


def test_label_map_regions_match_the_polygons(phantom_model):
    """The label image and the analytic polygons describe the same regions (areas within 1 %)."""
    labels = phantom_model.labels()
    pixel_area = np.prod(phantom_model.pixel_size_mm)
    polygons = phantom_model.geometry.boundaries()
    bone = _polygon_area(polygons["tibia"]) + _polygon_area(polygons["fibula"])
    muscle = _polygon_area(polygons["fascia"]) - bone
    fat = _polygon_area(polygons["skin"]) - _polygon_area(polygons["fascia"])
    for label, area in ((1, fat), (2, muscle), (3, bone)):
        assert np.sum(labels == label) * pixel_area == pytest.approx(area, rel=0.01)
    assert set(np.unique(labels)) == {0, 1, 2, 3}


def test_compartment_labels(phantom_model):
    labels = phantom_model.labels(compartments=True)
    basic = phantom_model.labels()
    assert set(np.unique(labels)) == {0, 1, 3} | {4 + i for i in range(len(COMPARTMENTS))}
    np.testing.assert_array_equal(labels >= 4, basic == 2)
    fibula_row = int(phantom_model.geometry.fibula.centre[1] / 0.36)
    skin_right = int(max(phantom_model.geometry.boundaries()["fascia"][:, 0]) / 0.36) - 3
    assert labels[fibula_row, skin_right] == 4 + COMPARTMENTS.index("lateral")


def test_parts_that_would_overlap_are_refused():
    with pytest.raises(ValueError, match="fibula"):
        CalfGeometry(CalfShape(fibula_offset_mm=(-10.0, -20.0)))
    with pytest.raises(ValueError, match="saphenous"):
        CalfGeometry(CalfShape(saphenous_radius_mm=4.0))


def test_t1_contrast(phantom_model, phantom_noiseless):
    """Fat bright, muscle intermediate, cortex dark, marrow bright (first paper, section 2.1.1)."""
    x, y = pixel_centres_mm(phantom_model.image_shape, phantom_model.pixel_size_mm)
    tissue = phantom_model.geometry.tissue_at(x, y)
    median = {t: np.median(phantom_noiseless[tissue == t]) for t in (Tissue.FAT, Tissue.MUSCLE, Tissue.CORTEX, Tissue.MARROW)}
    assert median[Tissue.FAT] > 2 * median[Tissue.MUSCLE] > 4 * median[Tissue.CORTEX]
    assert median[Tissue.MARROW] > 2 * median[Tissue.MUSCLE]


def test_rician_noise_in_the_background():
    """Background noise is the magnitude of complex Gaussian noise: mean sigma sqrt(pi/2)."""
    phantom = CalfPhantom(contrast=T1Contrast(noise_sigma=0.02), image_shape=(200, 200), supersampling=1)
    image = render_unloaded(phantom, noise_seed=3)
    background = image[~ndimage.binary_dilation(phantom.labels() > 0, iterations=10)]   # away from the edge ringing
    assert background.min() >= 0
    assert background.mean() == pytest.approx(0.02 * np.sqrt(np.pi / 2), rel=0.05)


def test_texture_moves_with_the_tissue(phantom_model, phantom_noiseless):
    """A whole-pixel translation of the tissue gives the same image shifted (only the scanner-fixed bias differs)."""
    step = phantom_model.pixel_size_mm[1]
    moved = make_loaded_image(phantom_model, lambda x, y: (np.full_like(x, 3 * step), np.zeros_like(y)), noise_seed=None)
    difference = moved[:, 3:] - phantom_noiseless[:, :-3]
    assert np.max(np.abs(difference)) < 0.005      # bias change over 1 mm; textures are 0.08 to 0.18 of the signal
    assert np.std(phantom_noiseless[phantom_model.labels() == 2]) > 0.03


def test_inverse_warping_solves_x_equals_X_plus_u():
    def u(x, y):
        return 0.05 * np.sin(y / 7.0) * 3.0, -0.04 * (x - 50.0)

    x = np.linspace(10, 90, 50)
    y = np.linspace(90, 20, 50)
    X, Y = material_points(x, y, u)
    ux, uy = u(X, Y)
    np.testing.assert_allclose(X + ux, x, atol=1e-5)
    np.testing.assert_allclose(Y + uy, y, atol=1e-5)
    motion = RigidMotion(4.0, (2.0, -1.0), (50.0, 50.0))
    X, Y = material_points(*motion.apply(x, y), u, motion)
    ux, uy = u(X, Y)
    np.testing.assert_allclose(X + ux, x, atol=1e-5)


def test_folding_displacement_is_refused():
    with pytest.raises(ValueError, match="inverted"):
        material_points(np.array([1.0, 2.0]), np.array([1.0, 1.0]), lambda x, y: (-1.5 * x, 0.0 * y))


def test_radial_shrink_shrinks_the_loaded_leg_by_the_expected_area(phantom_model):
    """u = -e (X - c): every area scales by (1 - e)^2 in the loaded image."""
    strain = 0.03
    cx, cy = phantom_model.geometry.shape.centre_mm

    def shrink(x, y):
        return -strain * (x - cx), -strain * (y - cy)

    before = phantom_model.labels()
    after = loaded_labels(phantom_model, shrink)
    for label in (1, 2, 3):
        assert np.sum(after == label) / np.sum(before == label) == pytest.approx((1 - strain) ** 2, rel=0.01)


def test_grid_displacement_equals_the_callable(phantom_model):
    cx, cy = phantom_model.geometry.shape.centre_mm

    def field(x, y):
        return 0.01 * (x - cx), -0.02 * (y - cy)

    grid = displacement_on_grid(field, phantom_model.image_shape, phantom_model.pixel_size_mm)
    from_grid = as_displacement_fn(grid, phantom_model.pixel_size_mm)
    x, y = np.array([30.3, 70.7, 101.1]), np.array([40.2, 75.5, 120.9])
    np.testing.assert_allclose(from_grid(x, y), field(x, y), atol=1e-9)   # bilinear is exact for a linear field


def test_write_case_keeps_the_truth_apart(tmp_path):
    phantom = CalfPhantom(image_shape=(300, 300), pixel_size_mm=(0.5, 0.5), supersampling=1)
    motion = RigidMotion(1.5, (0.8, -0.4), (75.0, 75.0))
    case_folder, truth_folder = write_case(tmp_path / "leg", phantom, rigid=motion, points_spacing_mm=15.0)
    assert sorted(os.listdir(tmp_path)) == ["leg", "leg.truth"]
    assert sorted(os.listdir(case_folder)) == ["case.toml", "labels.png", "loaded.png", "points.csv", "unloaded.png"]
    case = read_case(case_folder)
    assert case.pixel_size_mm == (0.5, 0.5) and set(case.landmarks) == set(LANDMARK_NAMES)
    assert len(case.points) > 20
    truth = json.loads((truth_folder / "truth.json").read_text())
    assert truth["rigid_motion"]["angle_deg"] == 1.5
    field = np.load(truth_folder / "displacement_mm.npy")
    assert field.shape == (2, 300, 300) and 0.5 < np.abs(field).max() < 3.0
    with pytest.raises(FileExistsError):
        write_case(tmp_path / "leg", phantom)
    assert sorted(os.listdir(tmp_path)) == ["leg", "leg.truth"]
