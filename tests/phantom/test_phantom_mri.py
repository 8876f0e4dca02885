"""The second phantom (orchestrator.phantom.mri): its anatomy, its T1 grey levels, features that move with the
material while bias and noise stay with the scanner, and cases made from it that calfit can measure."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from orchestrator.core.frame import pixel_centres_mm
from orchestrator.imaging.segment import dice
from orchestrator.measure.measurements import read_window_table
from orchestrator.phantom import (
    COMPARTMENTS,
    LANDMARK_NAMES,
    CalfPhantom,
    LegGeometry,
    LegShape,
    MRIPhantom,
    as_displacement_fn,
    loaded_labels,
    make_loaded_image,
    render_unloaded,
    write_case,
)
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.stages import run_measure

PIXEL_MM = 0.6


@pytest.fixture(scope="module")
def phantom():
    # 3 x 3 samples of 0.2 mm per pixel instead of the default 5 x 5: the same anatomy, rendered faster
    return MRIPhantom.at_resolution(PIXEL_MM, supersampling=3)


@pytest.fixture(scope="module")
def noiseless(phantom):
    return render_unloaded(phantom, noise_seed=None)


def _polygon_area(points: np.ndarray) -> float:
    x, y = points.T
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_a_calf_with_a_small_fibula_on_its_lateral_side():
    geometry = LegGeometry()
    outlines = geometry.boundaries()
    skin = outlines["skin"]
    assert 105.0 < np.ptp(skin[:, 0]) < 125.0 and 95.0 < np.ptp(skin[:, 1]) < 115.0
    assert 320.0 < np.sum(np.hypot(*np.diff(np.vstack([skin, skin[:1]]), axis=0).T)) < 380.0
    fibula_width = max(np.ptp(outlines["fibula"], axis=0))
    assert 8.0 < fibula_width < 12.0 < max(np.ptp(outlines["tibia"], axis=0))
    # radiological view from the feet: a right leg's fibula (lateral) is on the image's left, a left leg's on its right
    centre_x = geometry.shape.centre_mm[0]
    assert np.mean(outlines["fibula"][:, 0]) < centre_x < np.mean(LegGeometry(LegShape(side="left")).boundaries()["fibula"][:, 0])
    marks = geometry.landmarks()
    assert tuple(marks) == LANDMARK_NAMES
    assert abs(geometry.fascia.radial_excess(*marks.pop("max_pressure"))) < 1e-9    # on the fat/muscle interface
    x, y = np.array(list(marks.values())).T
    assert list(geometry.labels_at(x, y)) == [1, 2, 1, 1]   # hypodermis, between the deep veins, two veins in fat


@pytest.mark.parametrize("pixel_mm", [0.3, 0.36, 0.45, 0.6])
def test_labels_are_exact_at_every_pixel_size(pixel_mm):
    """The label image and the analytic outlines describe the same regions (areas within 0.5 %)."""
    phantom = MRIPhantom.at_resolution(pixel_mm)
    labels = phantom.labels()
    polygons = phantom.geometry.boundaries(2880)
    bone = _polygon_area(polygons["tibia"]) + _polygon_area(polygons["fibula"])
    expected = {1: _polygon_area(polygons["skin"]) - _polygon_area(polygons["fascia"]),
                2: _polygon_area(polygons["fascia"]) - bone, 3: bone}
    for label, area in expected.items():
        assert np.sum(labels == label) * pixel_mm ** 2 == pytest.approx(area, rel=0.005)


def test_four_compartments_of_calf_proportions(phantom):
    labels = phantom.labels(compartments=True)
    np.testing.assert_array_equal(labels >= 4, phantom.labels() == 2)
    area = {name: np.sum(labels == 4 + index) * PIXEL_MM ** 2 for index, name in enumerate(COMPARTMENTS)}
    assert min(area.values()) > 300.0
    assert area["superficial_posterior"] > max(area["anterior"], area["lateral"], area["deep_posterior"]) * 2
    for index in range(len(COMPARTMENTS)):    # each compartment is one piece
        assert ndimage.label(labels == 4 + index)[1] == 1


def test_grey_levels_follow_the_labels(phantom, noiseless):
    """T1: fat bright, muscle intermediate, background black; bones a black cortex around bright marrow."""
    labels = phantom.labels()
    median = {label: np.median(noiseless[labels == label]) for label in (0, 1, 2, 3)}
    assert median[0] == 0.0
    assert 0.75 < median[1] < 0.95 and 0.33 < median[2] < 0.47
    bone = noiseless[labels == 3]
    assert np.mean(bone < 0.15) > 0.1 and np.mean(bone > 0.6) > 0.3


def test_the_fibula_is_seen_at_06_mm(phantom, noiseless):
    """Only about 17 pixels across, the fibula still shows its bright marrow inside a dark cortex all around."""
    geometry = phantom.geometry
    centre = np.array(geometry.frame.to_image(geometry.fibula.centre))
    angles = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
    radii = np.linspace(0.0, 9.0, 61)
    points = centre + radii[:, None, None] * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    profiles = ndimage.map_coordinates(noiseless, [points[..., 1] / PIXEL_MM - 0.5, points[..., 0] / PIXEL_MM - 0.5],
                                       order=1)
    assert profiles[0, 0] > 0.6                                   # marrow
    assert np.all(profiles.min(axis=0) < 0.25)                    # the cortex, in every direction
    assert np.all(profiles[-1] > 0.25)                            # muscle beyond it


def test_a_translation_of_the_tissue_shifts_the_image(phantom, noiseless):
    """Everything drawn is attached to the material: moving the tissue by whole pixels gives the unloaded image
    shifted, exactly once the scanner's coil bias is divided out; with noise, up to the noise."""
    shift = (3, 2)   # pixels along x, y
    dy, dx = phantom.pixel_size_mm

    def translation(x, y):
        return np.full_like(x, shift[0] * dx), np.full_like(y, shift[1] * dy)

    bias = phantom.coil_bias(*pixel_centres_mm(phantom.image_shape, phantom.pixel_size_mm))
    moved = make_loaded_image(phantom, translation, noise_seed=None)
    before, after = (noiseless / bias)[:-shift[1], :-shift[0]], (moved / bias)[shift[1]:, shift[0]:]
    assert np.max(np.abs(after - before)) < 1e-9
    assert np.max(np.abs(moved[shift[1]:, shift[0]:] - noiseless[:-shift[1], :-shift[0]])) > 1e-4   # the bias did not move
    noisy = make_loaded_image(phantom, translation, noise_seed=5)
    inside = ndimage.binary_erosion(phantom.labels() > 0, iterations=3)[:-shift[1], :-shift[0]]
    residual = noisy[shift[1]:, shift[0]:][inside] - noiseless[:-shift[1], :-shift[0]][inside]
    assert np.std(residual) == pytest.approx(phantom.contrast.noise_sigma, rel=0.1)


def test_rician_noise_in_the_background(phantom):
    image = render_unloaded(phantom, noise_seed=3)
    background = image[~ndimage.binary_dilation(phantom.labels() > 0, iterations=3)]
    assert background.min() >= 0.0
    assert background.mean() == pytest.approx(phantom.contrast.noise_sigma * np.sqrt(np.pi / 2), rel=0.05)


def test_unlike_the_first_phantom(phantom, noiseless):
    """Another outline, fat layer and bones, and another picture inside the leg."""
    first = CalfPhantom(image_shape=phantom.image_shape, pixel_size_mm=phantom.pixel_size_mm)
    ours, theirs = phantom.labels(), first.labels()
    skin = phantom.geometry.boundaries()["skin"]
    assert np.max(np.min(np.hypot(*(skin[:, None, :] - first.geometry.boundaries()["skin"][None]).T), axis=0)) > 2.0
    assert dice(ours == 1, theirs == 1) < 0.9 and dice(ours == 3, theirs == 3) < 0.3
    both = (ours > 0) & (theirs > 0)
    assert np.corrcoef(noiseless[both], render_unloaded(first, noise_seed=None)[both])[0, 1] < 0.8


def test_the_seed_draws_another_leg(phantom):
    """Same seed, same leg to the bit; another seed moves the outline by millimetres and redraws the septa."""
    again, other = LegGeometry(LegShape(seed=0)), LegGeometry(LegShape(seed=1))
    moved = np.abs(other.boundaries()["skin"] - phantom.geometry.boundaries()["skin"])
    assert 0.5 < np.max(moved) < 6.0
    x, y = np.meshgrid(np.linspace(60.0, 90.0, 300), np.linspace(118.0, 128.0, 100))   # back of the leg: fat
    patch = phantom.intensity_at(x, y, 0.1)
    np.testing.assert_array_equal(patch, MRIPhantom(geometry=again).intensity_at(x, y, 0.1))
    assert np.mean(np.abs(patch - MRIPhantom(geometry=other).intensity_at(x, y, 0.1))) > 0.05


def test_write_case_with_the_default_compression(phantom, tmp_path):
    """write_case takes the second phantom unchanged: bone-clamped compression of its own bones, truth.json."""
    case_folder, truth_folder = write_case(tmp_path / "leg", phantom, labels="truth")
    truth = json.loads((truth_folder / "truth.json").read_text())
    assert truth["renderer"] == "mri" and truth["shape"]["seed"] == 0 and truth["supersampling"] == 3
    field = np.load(truth_folder / "displacement_mm.npy")
    after = loaded_labels(phantom, as_displacement_fn(field, phantom.pixel_size_mm))
    before = phantom.labels()
    assert np.sum(after > 0) / np.sum(before > 0) == pytest.approx(0.975 ** 2, abs=0.01)
    assert np.sum(after == 3) == pytest.approx(np.sum(before == 3), rel=0.01)     # the bones are clamped
    assert (case_folder / "loaded.png").is_file()


def test_a_case_made_by_the_engine_is_measured(tmp_path):
    """make_phantom_case meshes the phantom's exact labels, solves the engine and renders with the second phantom;
    calfit measure then tracks its displacements from the images alone."""
    phantom = MRIPhantom.at_resolution(PIXEL_MM, supersampling=3)
    case, truth = make_phantom_case(tmp_path / "case", tmp_path / "truth", phantom=phantom, n_elements=2000,
                                    points_spacing_mm=None)
    assert json.loads((truth / "truth.json").read_text())["renderer"] == "mri"
    summary = run_measure(case, tmp_path / "run", window_px=64)
    windows = read_window_table(tmp_path / "run")
    kept = np.array([status == "kept" for status in windows.status])
    assert summary["kept"] == kept.sum() >= 10
    true_u = as_displacement_fn(np.load(truth / "displacement_mm.npy"), phantom.pixel_size_mm)
    error = np.hypot(*(windows.displacement_mm[kept] - np.stack(true_u(*windows.position_mm[kept].T), axis=1)).T)
    assert np.median(error) < 0.1     # a tenth of a millimetre, where the garment moves the tissue up to 1.5 mm
