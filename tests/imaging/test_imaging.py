"""Imaging room on the phantom calf: segmentation, bone alignment, warping, contour mismatch, DIC.

The phantom images are band-limited, noisy, biased renderings made by inverse
warping (orchestrator.phantom), not by the interpolation tested here.
Measured values at the time of writing are quoted in comments.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from orchestrator.core.frame import RigidMotion, displacement_on_grid
from orchestrator.imaging.align import align_on_bones, kabsch_2d, resample_rigid
from orchestrator.imaging.mismatch import ContourMismatch, contour_pixels
from orchestrator.imaging.segment import dice, segment_t1
from orchestrator.imaging.warp import warp_image, warp_labels
from orchestrator.measure.dic import correlate, grid_centres, roi_centres
from orchestrator.phantom import (
    CalfPhantom,
    T1Contrast,
    bone_clamped_compression,
    loaded_labels,
    make_loaded_image,
    render_unloaded,
)

PIXEL = 0.36


@pytest.fixture(scope="module")
def imaging_phantom():
    return CalfPhantom()


@pytest.fixture(scope="module")
def imaging_compression(imaging_phantom):
    return bone_clamped_compression(imaging_phantom.geometry)


@pytest.fixture(scope="module")
def imaging_unloaded(imaging_phantom):
    return render_unloaded(imaging_phantom, noise_seed=10)


@pytest.fixture(scope="module")
def imaging_loaded(imaging_phantom, imaging_compression):
    return make_loaded_image(imaging_phantom, imaging_compression, noise_seed=11)


# ----------------------------------------------------------------- warping


def test_warp_with_zero_displacement_is_identity():
    image = np.random.default_rng(0).random((30, 40))
    np.testing.assert_allclose(warp_image(image, np.zeros((2, 30, 40)), (0.5, 0.5)), image)


def test_warp_samples_the_loaded_image_at_x_plus_u():
    """I(x) = I1(x + u): a whole-pixel u gives a shifted image, a half-pixel u the mean of two neighbours."""
    image = np.random.default_rng(1).random((30, 40))
    pixel = (0.5, 0.25)
    shifted = warp_image(image, lambda x, y: (np.full_like(x, 2 * pixel[1]), np.full_like(y, -3 * pixel[0])), pixel)
    np.testing.assert_allclose(shifted[3:, :-2], image[:-3, 2:])
    half = warp_image(image, np.stack([np.full((30, 40), 0.5 * pixel[1]), np.zeros((30, 40))]), pixel)
    np.testing.assert_allclose(half[:, :-1], 0.5 * (image[:, :-1] + image[:, 1:]))


def test_warp_undoes_the_phantom_deformation(imaging_phantom, imaging_compression):
    """Warping the noiseless loaded phantom by the true u gives back the unloaded phantom (section 2.1.2)."""
    unloaded = render_unloaded(imaging_phantom, noise_seed=None)
    loaded = make_loaded_image(imaging_phantom, imaging_compression, noise_seed=None)
    warped = warp_image(loaded, imaging_compression, imaging_phantom.pixel_size_mm)
    leg = imaging_phantom.labels() > 0
    before = np.sqrt(np.mean((loaded - unloaded)[leg] ** 2))
    after = np.sqrt(np.mean((warped - unloaded)[leg] ** 2))
    assert after < 0.25 * before   # measured: rms 0.22 -> 0.016 (fat = 1)


def test_warp_labels_is_nearest_neighbour():
    labels = np.zeros((10, 10), np.uint8)
    labels[2:5, 2:5] = 2
    moved = warp_labels(labels, lambda x, y: (np.full_like(x, 1.0), np.zeros_like(y)), (1.0, 1.0))
    np.testing.assert_array_equal(moved[:, :-1], labels[:, 1:])


# ----------------------------------------------------------------- segmentation


def test_segmentation_dice_on_the_phantom(imaging_phantom, imaging_unloaded, imaging_loaded, imaging_compression):
    """Dice >= 0.95 for fat and muscle (measured: fat 0.984, muscle 0.997, bone 0.99) on both images."""
    for image, truth in ((imaging_unloaded, imaging_phantom.labels()),
                         (imaging_loaded, loaded_labels(imaging_phantom, imaging_compression))):
        labels = segment_t1(image, imaging_phantom.pixel_size_mm)
        assert set(np.unique(labels)) == {0, 1, 2, 3}
        assert dice(labels == 1, truth == 1) >= 0.95
        assert dice(labels == 2, truth == 2) >= 0.95
        assert dice(labels == 3, truth == 3) >= 0.95


def test_segmentation_without_bone_is_an_imaging_error():
    from orchestrator.core.errors import ImagingError

    image = np.zeros((120, 120))
    image[20:100, 20:100] = 0.4
    image[30:90, 30:90] = 1.0
    with pytest.raises(ImagingError, match="no bone"):
        segment_t1(image + np.random.default_rng(0).normal(0, 0.01, image.shape), (0.36, 0.36))


# ----------------------------------------------------------------- alignment


def test_kabsch_recovers_a_rotation_and_translation():
    source = np.array([[0.0, 0.0], [40.0, 10.0], [5.0, 30.0]])
    motion = RigidMotion(7.0, (1.5, -2.0), (0.0, 0.0))
    target = np.stack(motion.apply(source[:, 0], source[:, 1]), axis=1)
    angle, translation = kabsch_2d(source, target)
    assert angle == pytest.approx(7.0, abs=1e-9)
    np.testing.assert_allclose(translation, [1.5, -2.0], atol=1e-9)


def test_rigid_motion_inverse_and_change_of_centre():
    motion = RigidMotion(12.0, (3.0, -1.0), (50.0, 40.0))
    x, y = np.array([0.0, 10.0, 75.0]), np.array([5.0, 80.0, 20.0])
    np.testing.assert_allclose(motion.inverse().apply(*motion.apply(x, y)), (x, y), atol=1e-12)
    np.testing.assert_allclose(motion.about((0.0, 0.0)).apply(x, y), motion.apply(x, y), atol=1e-12)


def test_alignment_recovers_a_known_rigid_motion(imaging_phantom, imaging_unloaded, imaging_compression):
    """Within 0.1 degree and 0.1 pixel on the bones (measured: 0.006 degree, 0.015 pixel), with the soft tissue deformed."""
    centre = (imaging_phantom.extent_mm[0] / 2, imaging_phantom.extent_mm[1] / 2)
    true_motion = RigidMotion(2.5, (1.3, -0.9), centre)
    loaded = make_loaded_image(imaging_phantom, imaging_compression, rigid=true_motion, noise_seed=12)
    found = align_on_bones(imaging_unloaded, loaded, imaging_phantom.pixel_size_mm)
    assert abs(found.angle_deg - true_motion.angle_deg) < 0.1
    geometry = imaging_phantom.geometry
    bone_points = np.concatenate([geometry.tibia.polygon(90), geometry.fibula.polygon(90)])
    error_mm = np.hypot(*np.subtract(found.apply(*bone_points.T), true_motion.apply(*bone_points.T)))
    assert np.max(error_mm) / PIXEL < 0.1
    # The aligned loaded image sits on the unloaded one at the bones.
    aligned = resample_rigid(loaded, found, imaging_phantom.pixel_size_mm)
    bones = imaging_phantom.labels() == 3
    assert np.abs(aligned - imaging_unloaded)[bones].mean() < 0.3 * np.abs(loaded - imaging_unloaded)[bones].mean()


# ----------------------------------------------------------------- contour mismatch


def test_contour_pixels_of_a_square():
    region = np.zeros((8, 8), bool)
    region[2:6, 2:6] = True
    contour = contour_pixels(region)
    assert contour.sum() == 12 and not contour[3:5, 3:5].any()


def test_mismatch_is_zero_for_identical_labels_and_signed_by_overshoot():
    labels = np.zeros((60, 60), np.uint8)
    labels[10:50, 10:50] = 1
    labels[20:40, 20:40] = 2
    mismatch = ContourMismatch(labels, None, (0.5, 0.5))
    assert mismatch.compare(labels).value_mm2 == 0.0
    grown = labels.copy()
    grown[8:52, 8:52] = np.where(grown[8:52, 8:52] == 0, 1, grown[8:52, 8:52])   # fat grows outwards by 2 pixels
    result = mismatch.compare(grown)
    outer = result.signed_distance_mm[8, 8:52]
    np.testing.assert_allclose(outer[2:-2], 1.0)   # 2 pixels of 0.5 mm, outside I0's fat: positive
    assert result.per_tissue_mm2["muscle"] == 0.0
    assert result.value_mm2 == pytest.approx(np.nansum(result.distance_mm ** 2))
    shrunk = labels.copy()
    shrunk[20:40, 20:40] = 1
    shrunk[22:38, 22:38] = 2
    inner = mismatch.compare(shrunk).signed_distance_mm
    np.testing.assert_allclose(inner[22, 24:36], -1.0)   # muscle contour falls 2 pixels short, inside I0's muscle
    np.testing.assert_allclose(inner[21, 24:36], 1.0)    # fat contour 2 pixels beyond I0's fat, in I0's muscle


def test_true_displacement_brings_the_mismatch_to_the_noise_floor(imaging_phantom, imaging_unloaded, imaging_loaded,
                                                                  imaging_compression):
    """Section 2.2.5 on a phantom pair. The floor is M for a loaded image that is the unloaded leg moved by a known
    sub-pixel translation, undone exactly: noise plus pixel discretisation, no deformation.
    Measured: M(true u) 41 mm^2, floor 49 mm^2, M(u = 0) 3245 mm^2."""
    pixel = imaging_phantom.pixel_size_mm
    labels_unloaded = segment_t1(imaging_unloaded, pixel)
    mismatch = ContourMismatch(labels_unloaded, segment_t1(imaging_loaded, pixel), pixel)
    field = displacement_on_grid(imaging_compression, imaging_unloaded.shape, pixel)
    at_truth = mismatch(field)
    at_zero = mismatch(np.zeros_like(field))

    def shift(x, y):
        return np.full_like(x, 0.47), np.full_like(y, -0.21)

    shifted = make_loaded_image(imaging_phantom, shift, noise_seed=14)
    floor = ContourMismatch(labels_unloaded, segment_t1(shifted, pixel), pixel)(shift)
    assert at_truth.value_mm2 < 1.5 * floor.value_mm2
    assert at_zero.value_mm2 > 20 * at_truth.value_mm2
    assert at_truth.rms_mm < 0.5 * PIXEL
    # Maps: d_k on the contours only, and |signed| = d_k.
    on_contour = np.isfinite(at_zero.distance_mm)
    assert on_contour.sum() == at_zero.contour_pixel_count
    np.testing.assert_allclose(np.abs(at_zero.signed_distance_mm[on_contour]), at_zero.distance_mm[on_contour])
    # Without the displacement, the compressed loaded leg falls short of I0: negative signed distances dominate.
    assert np.nanmean(at_zero.signed_distance_mm) < 0


# ----------------------------------------------------------------- DIC


def smooth_field(x, y):
    """A smooth field of about 1-2 pixels with strains of about 2 %."""
    return 0.5 * np.sin(2 * np.pi * y / 120.0) + 0.3, 0.5 * np.cos(2 * np.pi * x / 140.0) - 0.2


@pytest.fixture(scope="module")
def imaging_dic_pair():
    """A quiet phantom (noise sigma 0.005) to test the correlation itself rather than the noise."""
    phantom = CalfPhantom(contrast=T1Contrast(noise_sigma=0.005))
    return phantom, render_unloaded(phantom, noise_seed=20), make_loaded_image(phantom, smooth_field, noise_seed=21)


def _errors_px(result):
    ux, uy = smooth_field(result.position_mm[:, 0], result.position_mm[:, 1])
    return np.hypot(result.displacement_mm[:, 0] - ux, result.displacement_mm[:, 1] - uy) / PIXEL


def test_dic_16_pixel_windows_within_a_tenth_of_a_pixel_where_texture_exists(imaging_dic_pair):
    """Windows wholly inside the leg. Measured: 408 of 452 reliable, largest error 0.07 pixel (0.06 without noise)."""
    phantom, unloaded, loaded = imaging_dic_pair
    inside = ndimage.binary_erosion(phantom.labels() > 0, iterations=9)
    centres = grid_centres(unloaded.shape, 16, 12, mask=inside)
    result = correlate(unloaded, loaded, centres, phantom.pixel_size_mm, window_px=16)
    reliable = result.reliable()
    assert reliable.sum() > 0.75 * len(centres)
    assert np.max(_errors_px(result)[reliable]) < 0.1
    assert result.search_px == 64
    points = result.to_points()   # the rows of a points.csv
    assert len(points) == reliable.sum()
    np.testing.assert_allclose(points.sigma_mm, result.uncertainty_px[reliable] * PIXEL)


def test_dic_confidence_is_low_without_texture(imaging_dic_pair):
    """Windows wholly in the air around the leg (noise only) have a low ZNCC; windows in the tissue a high one."""
    phantom, unloaded, loaded = imaging_dic_pair
    labels = phantom.labels()
    air = ~ndimage.binary_dilation(labels > 0, iterations=12)
    tissue = ndimage.binary_erosion(labels > 0, iterations=12)
    air_centres = grid_centres(unloaded.shape, 16, 24, mask=air)
    tissue_centres = grid_centres(unloaded.shape, 16, 24, mask=tissue)
    in_air = correlate(unloaded, loaded, air_centres, phantom.pixel_size_mm, window_px=16)
    in_tissue = correlate(unloaded, loaded, tissue_centres, phantom.pixel_size_mm, window_px=16)
    assert np.median(in_air.confidence) < 0.5 and np.max(in_air.confidence) < 0.8
    assert np.min(in_tissue.confidence) > 0.9
    assert not in_air.reliable().any()


def test_dic_with_realistic_noise_and_64_pixel_windows(imaging_phantom, imaging_unloaded):
    """Default noise (sigma 0.015): 16x16 windows are noise-limited (measured rms 0.06 px, largest 0.18 px, over the
    243 reliable of 282 windows);
    64x64 windows average it out but feel the curvature of the field (measured largest error 0.13 px)."""
    loaded = make_loaded_image(imaging_phantom, smooth_field, noise_seed=22)
    labels = imaging_phantom.labels()
    small = correlate(imaging_unloaded, loaded, grid_centres(loaded.shape, 16, 16, mask=labels > 0),
                      imaging_phantom.pixel_size_mm, window_px=16)
    errors = _errors_px(small)[small.reliable()]
    assert np.sqrt(np.mean(errors ** 2)) < 0.08
    large = correlate(imaging_unloaded, loaded, grid_centres(loaded.shape, 64, 32, mask=labels > 0),
                      imaging_phantom.pixel_size_mm, window_px=64)
    assert large.search_px == 256
    assert np.max(_errors_px(large)[large.reliable()]) < 0.25


def test_roi_windows_sit_on_skin_fascia_and_vessels(imaging_phantom):
    labels = imaging_phantom.labels()
    landmarks = imaging_phantom.geometry.landmarks()
    vessels = [landmarks["great_saphenous"], landmarks["small_saphenous"], landmarks["deep_veins"]]
    centres = roi_centres(labels, imaging_phantom.pixel_size_mm, spacing_mm=5.0, vessels_mm=vessels)
    # About one window every 5 mm along a ~330 mm skin and a ~300 mm fascia, plus the vessels (the paper used ~160).
    assert 100 < len(centres) < 160
    values = labels[centres[:, 0], centres[:, 1]]
    assert np.all(values > 0)
    rows, cols = centres[-3:].T
    np.testing.assert_allclose((cols + 0.5) * PIXEL, [v[0] for v in vessels], atol=PIXEL)
    np.testing.assert_allclose((rows + 0.5) * PIXEL, [v[1] for v in vessels], atol=PIXEL)
