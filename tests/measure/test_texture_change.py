"""The loaded texture that is not the unloaded texture moved (`orchestrator.measure.texture_change`): found where it
is and only there, and sent through the windows as their operators say."""

import numpy as np
import pytest
from scipy import ndimage

from orchestrator.measure.prefilter import Prefilter
from orchestrator.measure.texture_change import (
    LAG_PX,
    Change,
    autocovariance,
    covariance_factor,
    high_pass,
    measure_change,
    valid_autocovariance,
    window_covariance,
)
from orchestrator.measure.windows import WindowOperators

SHAPE = (160, 200)
NOISE = 0.01
WINDOW = 32
SHIFT = (0.37, -0.61)   # rows, columns: the loaded image shows the reference moved by this


def _texture(seed: int, correlation_px: float = 1.5) -> np.ndarray:
    values = ndimage.gaussian_filter(np.random.default_rng(seed).normal(size=SHAPE), correlation_px)
    return values / values.std()


def _labels() -> np.ndarray:
    labels = np.full(SHAPE, 2, np.uint8)   # muscle on the right
    labels[:, : SHAPE[1] // 2] = 1         # fat on the left
    return labels


def _moved_by_shift(indices: np.ndarray) -> np.ndarray:
    return np.asarray(indices, float) + np.array(SHIFT)


def _through_shift(loaded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the loaded image shows I0's pixels (moved by SHIFT) and the loaded image sampled there."""
    rows, cols = np.indices(SHAPE, dtype=float)
    where = _moved_by_shift(np.column_stack([rows.ravel(), cols.ravel()])).T
    return where, ndimage.map_coordinates(loaded, where, order=3, mode="constant", cval=np.nan).reshape(SHAPE)


def _images(changed_fat: float, seed: int = 1, change=None):
    """I0 a smooth texture; I1 the same texture moved by SHIFT (then `change`d, when given), plus, in the fat, a
    texture of I1's own of standard deviation changed_fat; both with white noise."""
    reference = 0.5 + 0.1 * _texture(seed)
    rows, cols = np.indices(SHAPE, dtype=float)
    moved = ndimage.map_coordinates(reference, [rows - SHIFT[0], cols - SHIFT[1]], order=3, mode="nearest")
    if change is not None:
        moved = change(moved)
    own = changed_fat * _texture(seed + 100) * (_labels() == 1)
    rng = np.random.default_rng(seed + 200)
    return (reference + rng.normal(0, NOISE, SHAPE), moved + own + rng.normal(0, NOISE, SHAPE), own)


def test_a_texture_moved_intact_adds_nothing():
    unloaded, loaded, _ = _images(0.0)
    changes, found = measure_change(unloaded, loaded, _labels(), *_through_shift(loaded), (NOISE, NOISE), WINDOW)
    assert changes == {}
    assert [change.significant for change in found] == [False, False]
    for change in found:   # the noise, simulated through the same warp and filters, is what the residual holds
        assert change.residual_variance == pytest.approx(change.noise_variance, rel=0.1)


def test_a_texture_of_the_loaded_image_s_own_is_found_in_its_tissue_at_its_size():
    unloaded, loaded, own = _images(NOISE)
    changes, found = measure_change(unloaded, loaded, _labels(), *_through_shift(loaded), (NOISE, NOISE), WINDOW)
    fat, muscle = found
    assert fat.significant and not muscle.significant
    assert list(changes) == ["fat"]
    # what the change is, through the same high pass, in the same (eroded) fat: the local fit on I0's texture takes a
    # part of a texture this like I0's, and the patches' displacements give it back
    inner = ndimage.binary_erosion(_labels() == 1, iterations=3)
    expected = np.var(high_pass(own, WINDOW / np.sqrt(12.0))[inner & (np.arange(SHAPE[1]) < SHAPE[1] // 2 - 12)])
    assert fat.excess_variance < expected
    assert changes["fat"].autocovariance[LAG_PX, LAG_PX] == pytest.approx(expected, rel=0.2)


def test_a_change_of_the_texture_s_contrast_and_sharpness_moves_nothing_and_adds_nothing():
    """The loaded fat 30 % less contrasted and blurred by 0.6 px more (another slice profile, a filter): every
    feature keeps its centroid, so no window is moved by it."""
    fat = _labels() == 1

    def contrast_and_sharpness(image):
        mean = image[fat].mean()
        return np.where(fat, mean + 0.7 * (ndimage.gaussian_filter(image, 0.6) - mean), image)

    unloaded, changed, _ = _images(0.0, change=contrast_and_sharpness)
    changes, found = measure_change(unloaded, changed, _labels(), *_through_shift(changed), (NOISE, NOISE), WINDOW)
    assert changes == {}
    assert not found[0].significant


def test_the_autocovariance_made_valid_keeps_a_valid_one_and_makes_any_other_positive():
    kernel = np.outer(np.hanning(7), np.hanning(7))
    white = np.random.default_rng(3).normal(size=(400, 400))
    valid = autocovariance(ndimage.convolve(white, kernel, mode="wrap"), np.ones((400, 400), bool))
    assert valid_autocovariance(valid) == pytest.approx(valid, abs=0.05 * valid[LAG_PX, LAG_PX])
    rough = np.random.default_rng(4).normal(size=(2 * LAG_PX + 1, 2 * LAG_PX + 1))
    made = valid_autocovariance(rough)
    spectrum = np.real(np.fft.fft2(np.roll(np.pad(made, (0, 6 * LAG_PX)), (-LAG_PX, -LAG_PX), axis=(0, 1))))
    assert spectrum.min() > -1e-9 * np.abs(spectrum).max()


def test_the_windows_covariance_is_the_scatter_of_their_operators_on_errors_of_that_autocovariance():
    """Errors e = h * white with h a 5 x 5 kernel have the autocovariance h * h; sent through each window's B they
    scatter as window_covariance predicts."""
    reference = 0.5 + 0.1 * _texture(7)
    labels = _labels()
    centres = np.array([[48, 48], [48, 64], [80, 56], [80, 140], [112, 150], [64, 120]])
    operators = WindowOperators(reference, centres, WINDOW, (0.4, 0.4), NOISE, prefilter=Prefilter(1.0))
    kernel = np.outer(np.hanning(7)[1:-1], np.hanning(7)[1:-1]) * 0.01
    change = np.zeros((2 * LAG_PX + 1, 2 * LAG_PX + 1))
    padded = np.zeros_like(change)
    padded[LAG_PX - 2:LAG_PX + 3, LAG_PX - 2:LAG_PX + 3] = kernel
    change = ndimage.correlate(padded, kernel, mode="constant")
    assert change[LAG_PX, LAG_PX] == pytest.approx(np.sum(kernel ** 2))
    uniform = Change(change, np.ones(SHAPE))
    predicted = window_covariance(operators, labels, {"fat": uniform, "muscle": uniform})
    rng = np.random.default_rng(8)
    draws = []
    for _ in range(600):
        error = ndimage.convolve(rng.normal(size=SHAPE), kernel, mode="constant")
        flat = error.ravel()
        draws.append(np.concatenate([(b @ flat[pixels]) * operators.to_mm for pixels, b in
                                     zip(operators.noise_pixels, operators.B)]))
    empirical = np.cov(np.array(draws).T)
    assert np.diagonal(empirical) == pytest.approx(np.diagonal(predicted), rel=0.15)
    # windows 0 and 1 overlap: their covariance is held too
    assert empirical[0, 2] == pytest.approx(predicted[0, 2], abs=0.15 * np.sqrt(predicted[0, 0] * predicted[2, 2]))
    factor = covariance_factor(predicted)
    assert factor @ factor.T == pytest.approx(predicted, abs=1e-9 * np.abs(predicted).max())
