"""The windows' second-order (quadratic) shape function (orchestrator/measure/shape.py) against analytic fields.

- The shape's map matrices: a quadratic map with no second-order terms is the affine map; the lifted matrix moves
  the monomials (dx, dy, 1) exactly as the map moves the point, and undoes itself.
- The observation operator of a quadratic window reads a quadratic field exactly at its centre; an affine window
  reads the curvature's mean over the window too.
- On speckle deformed by a field that bends inside the windows, over several noise draws: the quadratic windows'
  errors against the true field match their predicted covariance (chi^2/n near 1) where the affine windows' are
  biased many times beyond theirs; without the bend, both hold.
- `calfit measure` with quadratic windows: the run folder keeps the shape, and its measurements observe through it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from orchestrator.measure.dic import correlate, grid_centres
from orchestrator.measure.shape import AFFINE, QUADRATIC, WindowShape, lift
from orchestrator.measure.windows import WindowOperators
from orchestrator.phantom import CalfPhantom, write_case
from orchestrator.run.setup import load_run
from orchestrator.run.stages import run_measure

WINDOW_PX = 32
CENTRE_PX = 80.0


def test_the_quadratic_map_holds_the_affine_one_and_moves_the_monomials_as_it_moves_the_point():
    rng = np.random.default_rng(3)
    affine_p = rng.normal(scale=0.05, size=6)
    quadratic_p = np.zeros(12)
    quadratic_p[[0, 1, 2, 6, 7, 8]] = affine_p
    np.testing.assert_allclose(QUADRATIC.matrix(quadratic_p)[-3:, -3:], AFFINE.matrix(affine_p), atol=1e-15)
    p = rng.normal(scale=0.02, size=12)
    dx, dy = rng.normal(scale=10.0, size=(2, 50))
    moved = QUADRATIC.matrix(p) @ QUADRATIC.monomials(dx, dy)
    basis = QUADRATIC.basis(dx, dy)
    np.testing.assert_allclose(moved[3], dx + p[:6] @ basis, rtol=1e-12)
    np.testing.assert_allclose(moved[4], dy + p[6:] @ basis, rtol=1e-12)
    np.testing.assert_allclose(moved[5], 1.0)
    # a translation composes exactly: lift(W) lift(T)^-1 with T the same translation leaves no displacement
    shift = QUADRATIC.translated((0.7, -0.4))
    np.testing.assert_allclose((shift @ np.linalg.inv(shift))[-3:-1], lift(np.eye(6)[3:5])[-3:-1], atol=1e-14)
    with pytest.raises(ValueError, match="order 1 .affine. or 2 .quadratic."):
        WindowShape(3)
    with pytest.raises(ValueError, match="'affine' or 'quadratic'"):
        WindowShape.named("cubic")


def _speckle(shape, seed, sigma_px=2.0):
    rng = np.random.default_rng(seed)
    grains = ndimage.gaussian_filter(rng.normal(size=(shape[0] + 40, shape[1] + 40)), sigma_px)
    return 1000.0 + 400.0 * grains / grains.std()


def _bend(curvature):
    """u(x), v(x) in px: a translation and a field that bends with `curvature` per px about the image centre."""
    def field(x, y):
        return (0.3 + curvature * (x - CENTRE_PX) ** 2,
                -0.2 + curvature * (x - CENTRE_PX) * (y - CENTRE_PX) + 0.5 * curvature * (y - CENTRE_PX) ** 2)
    return field


def _pair(field, seed, noise, shape=(160, 160)):
    """I0 and I1 with I1(x + u(x)) = I0(x), the speckle's spline sampled at the inverse map (solved by fixed point)."""
    base = _speckle(shape, seed)
    rows, cols = np.indices(shape, dtype=float)
    x, y = cols.copy(), rows.copy()
    for _ in range(30):
        u, v = field(x, y)
        x, y = cols - u, rows - v
    loaded = ndimage.map_coordinates(ndimage.spline_filter(base, order=3), [y + 20, x + 20], order=3,
                                     prefilter=False, mode="nearest")
    rng = np.random.default_rng(seed + 100)
    return (base[20:20 + shape[0], 20:20 + shape[1]] + noise * rng.normal(size=shape),
            loaded + noise * rng.normal(size=shape))


def test_a_quadratic_windows_operator_reads_a_quadratic_field_at_its_centre():
    reference, _ = _pair(_bend(0.0), seed=1, noise=0.0)
    centres = grid_centres(reference.shape, WINDOW_PX, 24)
    rows, cols = np.indices(reference.shape, dtype=float)
    curvature = 4e-4
    # px = mm here, and the operators read the field's array at the pixel centres, (index + 0.5) mm; an even window's
    # centre lies at index c - 0.5 of its centre pixel c, so at c mm
    field = np.stack(_bend(curvature)(cols + 0.5, rows + 0.5))
    at_centre = np.stack(_bend(curvature)(centres[:, 1].astype(float), centres[:, 0].astype(float)), axis=1)
    seen = {shape.name: WindowOperators(reference, centres, WINDOW_PX, (1.0, 1.0), 5.0,
                                        window_shape=shape).observe(field) for shape in (AFFINE, QUADRATIC)}
    np.testing.assert_allclose(seen["quadratic"], at_centre, atol=1e-9)
    # the affine window reads the bend's mean over its square, about curvature (w^2 - 1) / 12 in u
    assert np.median(seen["affine"][:, 0] - at_centre[:, 0]) == pytest.approx(curvature * (WINDOW_PX ** 2 - 1) / 12,
                                                                            rel=0.3)


@pytest.mark.parametrize("curvature", [0.0, 5e-4])
def test_quadratic_windows_err_as_predicted_where_the_field_bends_inside_them(curvature):
    noise = 20.0
    chi2 = {"affine": [], "quadratic": []}
    for seed in range(6):
        reference, deformed = _pair(_bend(curvature), seed, noise)
        centres = grid_centres(reference.shape, WINDOW_PX, 16)
        inside = np.all((centres > 40) & (centres < 120), axis=1)
        for shape in (AFFINE, QUADRATIC):
            result = correlate(reference, deformed, centres[inside], (1.0, 1.0), window_px=WINDOW_PX, shape=shape,
                               noise_sigma=(noise, noise))
            centre = result.centre_rc
            error = result.displacement_px - np.stack(_bend(curvature)(centre[:, 1], centre[:, 0]), axis=1)
            variance = np.stack([result.covariance_mm2[:, 0, 0], result.covariance_mm2[:, 1, 1]], axis=1)
            chi2[shape.name].append(error ** 2 / variance)
    quadratic, affine = (float(np.mean(chi2[name])) for name in ("quadratic", "affine"))
    assert 0.7 < quadratic < 1.4   # 300 values: chi^2/n has a standard error of about 0.1
    if curvature == 0.0:
        assert 0.7 < affine < 1.4
    else:
        assert affine > 10.0


def test_calfit_measure_takes_the_quadratic_shape_and_the_run_folder_keeps_it(tmp_path):
    """`calfit measure --window-shape quadratic`: measurements.json says so, and the run folder's measurements (what
    `calfit identify` fits) observe a field through quadratic windows' operators, which read a quadratic field at
    the windows' centres."""
    phantom = CalfPhantom()
    case, _ = write_case(tmp_path / "case", phantom, labels=None)
    summary = run_measure(case, tmp_path / "run", window_shape="quadratic")
    assert summary["window_shape"] == "quadratic"
    measured = load_run(tmp_path / "run").measurements("dic")
    assert measured.operators.window_shape == QUADRATIC
    shape = phantom.image_shape
    rows, cols = np.indices(shape, dtype=float)
    dy, dx = phantom.pixel_size_mm
    x, y = (cols + 0.5) * dx, (rows + 0.5) * dy
    curvature = 2e-4   # per mm
    field = np.stack([curvature * (x - 70.0) ** 2, curvature * (x - 70.0) * (y - 80.0)])
    seen = measured.operators.observe(field)
    px, py = measured.position_mm[:, 0], measured.position_mm[:, 1]
    at_centres = np.stack([curvature * (px - 70.0) ** 2, curvature * (px - 70.0) * (py - 80.0)], axis=1)
    assert np.max(np.abs(seen - at_centres)) < 1e-6
