"""The DIC windows' compiled loops (correlation_cpp/, `orchestrator._correlation`) against the Python loops they
replace, which stay the reference (`dic.correlate(..., compiled=False)`).

On the phantom's images, through everything a window can meet in `calfit measure` (the bones' rigid motion, a prior
field from a first pass, pixel sets that leave out the outline, windows whose search area leaves the image and windows
that do not fit in it), the two give the same displacements to 1e-6 px, the same confidences and the same error model
(covariances, intensity variances, the edges' part, the residuals' sums): the compiled loops return each window's
start, warp and error terms, which the Python loops compute in their own way (numpy, scipy's filters). Then inputs
that must be refused with one sentence or rejected window by window, never crash: tiny images, NaN pixels, centres
far outside, arrays of the wrong shape or type.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from orchestrator.core.frame import RigidMotion
from orchestrator.measure.dic import compiled_windows, correlate, grid_centres, spline_gradient
from orchestrator.measure.measurements import window_pixel_masks
from orchestrator.measure.shape import WindowShape
from orchestrator.phantom import CalfPhantom, make_loaded_image, render_unloaded

TOLERANCE_PX = 1e-6


def _bent(x, y):
    """A sub-pixel field that bends inside a window (mm)."""
    return 0.047 + 0.05 * np.sin(x / 20.0), -0.033 + 0.03 * np.cos(y / 15.0)


@pytest.fixture(scope="module")
def images():
    if compiled_windows() is None:
        pytest.fail("orchestrator._correlation is not built: pip install -e . builds it (correlation_cpp/)")
    phantom = CalfPhantom()
    return phantom, render_unloaded(phantom, noise_seed=0), make_loaded_image(phantom, _bent, noise_seed=5)


def _assert_same(reference, compiled):
    """The two results agree: displacements to TOLERANCE_PX, the rest to rounding (relative 1e-6)."""
    d_ref, d_cmp = reference.displacement_px, compiled.displacement_px
    assert np.array_equal(np.isnan(d_ref), np.isnan(d_cmp))
    found = ~np.isnan(d_ref)
    assert np.max(np.abs(d_ref[found] - d_cmp[found]), initial=0.0) <= TOLERANCE_PX
    assert np.max(np.abs(reference.confidence - compiled.confidence), initial=0.0) <= TOLERANCE_PX
    for name in ("covariance_mm2", "uncertainty_px", "anisotropy", "intensity_variance", "edge_covariance_mm2",
                 "gradient"):
        a, b = np.asarray(getattr(reference, name)), np.asarray(getattr(compiled, name))
        assert np.array_equal(np.isfinite(a), np.isfinite(b)), name
        finite = np.isfinite(a)
        scale = max(float(np.max(np.abs(a[finite]), initial=0.0)), 1e-300)
        assert np.max(np.abs(a[finite] - b[finite]), initial=0.0) <= 1e-6 * scale, name
    for mine, theirs in zip(reference.edge_residuals, compiled.edge_residuals):
        assert mine.count == theirs.count
        for name in ("z", "zz", "y", "yz"):
            assert getattr(mine, name) == pytest.approx(getattr(theirs, name), rel=1e-6, abs=1e-12), name


@pytest.mark.parametrize("window, shape", [(16, "affine"), (32, "affine"), (32, "quadratic")])
def test_the_compiled_windows_match_the_python_loops_on_the_phantom(images, window, shape):
    phantom, unloaded, loaded = images
    labels = phantom.labels()
    centres = grid_centres(unloaded.shape, window, window // 2, mask=labels > 0)[::2]
    # windows whose search area leaves the image, one at the very edge, and two that do not fit
    height, width = unloaded.shape
    edge = np.array([(window // 2, window // 2), (height - window // 2, width // 2), (window // 2 - 1, 40),
                     (height // 2, width + 3 * window)])
    centres = np.concatenate([centres, edge])
    masks = window_pixel_masks(labels, centres[:-1], window, margin_px=5) + [None]   # (the last is off the labels)
    assert any(mask is not None for mask in masks)
    dy, dx = phantom.pixel_size_mm
    prior = RigidMotion(0.4, (0.06, -0.04), (0.5 * width * dx, 0.5 * height * dy))
    rows, cols = np.indices(unloaded.shape, dtype=float)
    field = np.stack(_bent(cols * dx, rows * dy)) * 0.8
    for options in (dict(), dict(prior=prior, prior_field_mm=field, pixel_masks=masks)):
        options["shape"] = WindowShape.named(shape)
        reference = correlate(unloaded, loaded, centres, phantom.pixel_size_mm, window_px=window, compiled=False,
                              **options)
        compiled = correlate(unloaded, loaded, centres, phantom.pixel_size_mm, window_px=window, compiled=True,
                             **options)
        assert np.isfinite(reference.displacement_px[:-2]).all(axis=1).mean() > 0.9
        assert np.isnan(compiled.displacement_px[-2:]).all() and np.all(compiled.confidence[-2:] == 0.0)
        _assert_same(reference, compiled)


def test_threads_and_worker_processes_give_the_windows_of_one(images):
    phantom, unloaded, loaded = images
    centres = grid_centres(unloaded.shape, 16, 8, mask=phantom.labels() > 0)[::3]
    one = correlate(unloaded, loaded, centres, phantom.pixel_size_mm, window_px=16, compiled=True)
    two = correlate(unloaded, loaded, centres, phantom.pixel_size_mm, window_px=16, compiled=True, workers=2)
    np.testing.assert_array_equal(one.displacement_px, two.displacement_px)
    np.testing.assert_array_equal(one.covariance_mm2, two.covariance_mm2)


def test_the_environment_chooses_the_python_loops(images, monkeypatch):
    phantom, unloaded, loaded = images
    centres = np.array([(210, 210)])
    calls = []
    module = compiled_windows()

    class Spy:
        def __getattr__(self, name):
            if name == "match_windows":
                calls.append(name)
            return getattr(module, name)

    monkeypatch.setattr("orchestrator.measure.dic.compiled_windows", lambda: Spy())
    monkeypatch.setenv("CALFIT_DIC_COMPILED", "0")
    correlate(unloaded, loaded, centres, phantom.pixel_size_mm)
    assert calls == []
    monkeypatch.delenv("CALFIT_DIC_COMPILED")
    correlate(unloaded, loaded, centres, phantom.pixel_size_mm)
    assert calls == ["match_windows"]


def test_bad_images_are_refused_in_one_sentence_and_bad_windows_rejected():
    rng = np.random.default_rng(7)
    texture = 100.0 + 20.0 * ndimage.gaussian_filter(rng.standard_normal((48, 48)), 1.5)
    shifted = ndimage.shift(texture, (0.3, -0.2), order=3, mode="nearest")
    noise = (0.5, 0.5)
    with_nan = shifted.copy()
    with_nan[10, 11] = np.nan
    with pytest.raises(ValueError, match="1 NaN or infinite pixels"):
        correlate(texture, with_nan, [(24, 24)], (1.0, 1.0), noise_sigma=noise)
    with pytest.raises(ValueError, match="same shape"):
        correlate(texture, shifted[:-1], [(24, 24)], (1.0, 1.0), noise_sigma=noise)
    with pytest.raises(ValueError, match="prior field"):
        correlate(texture, shifted, [(24, 24)], (1.0, 1.0), noise_sigma=noise, prior_field_mm=np.zeros((2, 5, 5)))
    bad_field = np.zeros((2, 48, 48))
    bad_field[1, 3, 3] = np.inf
    with pytest.raises(ValueError, match="prior field"):
        correlate(texture, shifted, [(24, 24)], (1.0, 1.0), noise_sigma=noise, prior_field_mm=bad_field)
    with pytest.raises(ValueError, match="pixel mask holds 9 pixels"):
        correlate(texture, shifted, [(24, 24)], (1.0, 1.0), noise_sigma=noise, pixel_masks=[np.ones((3, 3), bool)])
    # centres at, beyond and far beyond the border, in images smaller than a window, and a flat image: rejected
    centres = [(24, 24), (8, 8), (7, 24), (24, 41), (-10**9, 5), (5, 10**12)]
    for compiled in (False, True):
        result = correlate(texture, shifted, centres, (1.0, 1.0), noise_sigma=noise, compiled=compiled)
        assert np.isfinite(result.displacement_px[:2]).all()
        assert np.isnan(result.displacement_px[2:]).all() and np.all(result.confidence[2:] == 0.0)
        for shape in ((1, 1), (3, 40), (17, 17)):
            tiny = correlate(np.ones(shape) + np.arange(shape[1]), np.ones(shape), [(0, 0), (shape[0] // 2, 1)],
                             (1.0, 1.0), noise_sigma=noise, compiled=compiled)
            assert np.isnan(tiny.displacement_px).all()
        flat = correlate(np.full((48, 48), 3.0), shifted, [(24, 24)], (1.0, 1.0), noise_sigma=noise, compiled=compiled)
        assert np.isnan(flat.displacement_px).all()


def test_the_compiled_module_refuses_arrays_that_do_not_fit():
    module = compiled_windows()
    if module is None:
        pytest.fail("orchestrator._correlation is not built")
    image = 100.0 + 20.0 * ndimage.gaussian_filter(np.random.default_rng(1).standard_normal((40, 40)), 1.5)
    grad_rows, grad_cols = np.gradient(image)
    good = dict(reference=image, spline=ndimage.spline_filter(image, order=3), grad_rows=grad_rows,
                grad_cols=grad_cols, to_deformed=np.eye(3), prior=None,
                centres=np.array([[20, 20]], dtype=np.int64), used=np.ones((1, 256), bool), window_px=16,
                search_px=64, iterations=20, tolerance_px=1e-4, tolerance_gradient=1e-5, threads=2)
    assert module.match_windows(**good)["status"].tolist() == [module.MATCHED]
    wrong = [dict(spline=image[:, :-1]), dict(to_deformed=np.eye(2)), dict(prior=np.zeros((2, 40, 39))),
             dict(used=np.ones((1, 255), bool)), dict(used=np.ones((2, 256), bool)), dict(window_px=0),
             dict(search_px=8), dict(threads=0), dict(iterations=-1), dict(reference=np.zeros((0, 40))),
             dict(centres=np.array([[20, 20, 1]], dtype=np.int64))]
    for change in wrong:
        with pytest.raises(ValueError):
            module.match_windows(**{**good, **change})
    with pytest.raises(TypeError):   # not an image at all
        module.match_windows(**{**good, "reference": "an image"})
    # NaN in the images or the prior reaching the compiled loops directly: the window is rejected, not read
    holed = image.copy()
    holed[20, 20] = np.nan
    assert module.match_windows(**{**good, "reference": holed})["status"].tolist() == [module.NOT_FINITE]
    assert module.match_windows(**{**good, "spline": holed})["status"].tolist() == [module.NOT_FINITE]
    assert module.match_windows(**{**good, "prior": np.stack([holed, image])})["status"].tolist() == [module.NOT_FINITE]
    # the spline's gradient: scipy's central difference, taken again in C++
    for mine, scipys in zip(spline_gradient(image, module=module), spline_gradient(image)):
        np.testing.assert_allclose(mine, scipys, rtol=0, atol=1e-9 * np.max(np.abs(scipys)))
    for step in (0.0, -1e-3, np.nan):
        with pytest.raises(ValueError):
            module.spline_gradient(image, step)
    with pytest.raises(ValueError):
        module.spline_gradient(np.zeros((0, 3)), 1e-3)
    # random centres and pixel sets, some far outside: every window gets a status
    rng = np.random.default_rng(2)
    centres = rng.integers(-100, 140, size=(200, 2)).astype(np.int64)
    used = rng.random((200, 256)) < 0.7
    status = module.match_windows(**{**good, "centres": centres, "used": used})["status"]
    inside = np.all((centres >= 8) & (centres <= 32), axis=1)
    assert set(status[~inside].tolist()) == {module.OUTSIDE}
    assert set(status[inside].tolist()) <= {module.MATCHED, module.REFINEMENT_FAILED}
