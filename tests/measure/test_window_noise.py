"""The predicted covariance of windows across the skin against noise draws.

A window's Gauss-Newton matrix is built from the noisy reference, whose gradient noise looks like texture, so the
measurement takes the expected noise part away (`dic.denoised_hessian`). Beside the skin half the window is air,
whose Rician noise has 0.43 of the tissue's variance: taking the tissue's noise away everywhere removed too much
from the direction along the skin, where the weak texture of the tissue is all the window has, and over-predicted
that direction's variance (empirical / predicted 0.64 on the scene below, 0.60 with three windows per row). The
subtraction weighted by each pixel's share of the noise gives 0.91.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from orchestrator.measure.dic import correlate

SIZE = 192
SIGMA = 0.02
DRAWS = 50
SHIFT_PX = (0.3, 0.4)
MAX_UNCERTAINTY_PX = 0.25   # windows less certain than this are rejected by `calfit measure` (`measure`)


def _scene(texture: np.ndarray, shift_rows: float, shift_cols: float) -> np.ndarray:
    """Weak texture of the tissue right of a wavy skin edge, air on the left; moved by a sub-pixel shift."""
    rows, cols = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    rows, cols = rows - shift_rows, cols - shift_cols
    tissue = ndimage.map_coordinates(texture, [rows, cols], order=3, mode="nearest")
    return tissue * 0.5 * (1.0 + np.tanh((cols - 96.0 + 6.0 * np.sin(rows / 30.0)) / 0.8))


def test_windows_half_in_air_predict_their_noise_along_the_skin():
    rng = np.random.default_rng(0)
    texture = 0.6 + 0.05 * ndimage.gaussian_filter(rng.standard_normal((SIZE, SIZE)), 1.5) / 0.19
    reference, loaded = _scene(texture, 0.0, 0.0), _scene(texture, *SHIFT_PX)
    centres = np.array([(row, col) for row in range(40, 160, 20) for col in (93, 99)])
    displacements, covariances = [], []
    for _ in range(DRAWS):
        noisy = [np.hypot(image + SIGMA * rng.standard_normal(image.shape), SIGMA * rng.standard_normal(image.shape))
                 for image in (reference, loaded)]
        result = correlate(noisy[0], noisy[1], centres, (1.0, 1.0), window_px=32, noise_sigma=(SIGMA, SIGMA))
        displacements.append(result.displacement_px)
        covariances.append(result.covariance_mm2)   # pixels of 1 mm: px^2
    displacements, predicted = np.array(displacements), np.nanmean(np.array(covariances), axis=0)
    measured = np.all(np.isfinite(predicted.reshape(len(centres), -1)), axis=1)
    measured[measured] = np.sqrt(np.linalg.eigvalsh(predicted[measured])[:, 1]) <= MAX_UNCERTAINTY_PX
    assert measured.sum() >= 6, measured.sum()
    weak, strong = [], []
    for k in np.flatnonzero(measured):
        empirical = np.cov(displacements[:, k].T)
        values, vectors = np.linalg.eigh(predicted[k])
        strong.append(vectors[:, 0] @ empirical @ vectors[:, 0] / values[0])
        weak.append(vectors[:, 1] @ empirical @ vectors[:, 1] / values[1])
    # one window's variance ratio over 50 draws scatters by about 0.2; the mean of 6-8 windows by about 0.08
    assert 0.78 <= np.mean(weak) <= 1.25, weak
    assert 0.78 <= np.mean(strong) <= 1.25, strong
    # the sub-pixel shift is found, within 4 standard errors of the draws' mean: the scene moves by SHIFT_PX (rows,
    # columns), the windows report (x, y)
    found = displacements[:, measured]
    error = np.abs(found.mean(axis=0) - np.array(SHIFT_PX[::-1]))
    assert np.all(error <= 4.0 * found.std(axis=0) / np.sqrt(DRAWS)), error


def test_a_window_under_the_calibrated_noise_is_told_apart_from_its_textured_neighbours():
    """`windows.textured` says which windows' texture rises above a noise level: the same weak-textured window
    passes at half the images' noise and fails at four times it, while a well-textured one passes both;
    `measure.measure_dic` rejects and counts the first kind instead of failing the whole measurement with it."""
    from orchestrator.measure.windows import WindowOperators, textured

    rng = np.random.default_rng(3)
    image = np.full((SIZE, SIZE), 0.6)
    image[:, SIZE // 2:] += 0.2 * ndimage.gaussian_filter(rng.standard_normal((SIZE, SIZE // 2)), 1.5) / 0.19
    image[:, :SIZE // 2] += 0.0035 * ndimage.gaussian_filter(rng.standard_normal((SIZE, SIZE // 2)), 1.5) / 0.19
    noisy = image + SIGMA * rng.standard_normal(image.shape)
    centres = np.array([(96, 40), (96, 150)])
    assert textured(noisy, centres, 32, 0.5 * SIGMA).tolist() == [True, True]
    assert textured(noisy, centres, 32, 4 * SIGMA).tolist() == [False, True]
    with pytest.raises(ValueError, match="less texture than noise"):
        WindowOperators(noisy, centres, 32, (1.0, 1.0), 4 * SIGMA)
    assert len(WindowOperators(noisy, centres[1:], 32, (1.0, 1.0), 4 * SIGMA)) == 1
