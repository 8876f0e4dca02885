"""How the images were drawn (`orchestrator.measure.drawing`): a point-sampling renderer's boundaries, told from a
scanner's and from anti-aliased ones, and the error of intensity such a drawing makes."""

import numpy as np
import pytest

from orchestrator.core.tissues import FAT, MUSCLE
from orchestrator.measure.drawing import (
    Boundary,
    covered,
    crossings,
    detect_point_sampling,
    drawing_error,
)
from orchestrator.phantom.appearance import add_rician_noise

SHAPE = (220, 220)
CENTRE = (110.3, 109.6)
RADII = (80.0, 45.0)          # the leg's outline and the muscle's boundary (pixels)
LEVELS = (0.0, 0.85, 0.36)    # air, fat, muscle (the other program's cases' grey levels)


def test_a_straight_boundary_drawn_with_three_by_three_samples():
    """A boundary along the rows at row 10.3 (tissue below it, step 1): the pixels of row 10 cover 0.2 of
    tissue, and 3 x 3 samples at rows 10 - 1/3, 10, 10 + 1/3 put one row of three in it; moved up by 0.1 pixel the
    boundary covers 0.3, the samples still one third."""
    columns = np.arange(-5.0, 45.0, 0.1)
    boundary = Boundary(np.stack([np.full_like(columns, 10.3), columns], axis=1),
                        np.tile([-1.0, 0.0], (len(columns), 1)), 1.0, np.ones(len(columns), bool))
    crossed = crossings((20, 40), [boundary])
    error = drawing_error((20, 40), crossed, 3)
    assert error[10, 5:35] == pytest.approx(1.0 / 3.0 - 0.2, abs=1e-12)
    assert np.all(error[[8, 9, 11, 12], 5:35] == 0.0)
    moved = drawing_error((20, 40), crossed, 3, shift=(-0.1, 0.0))
    assert moved[10, 5:35] == pytest.approx(1.0 / 3.0 - 0.3, abs=1e-12)



@pytest.mark.parametrize("angle_deg", [0.0, 17.0, 45.0, 71.0])
def test_the_exact_coverage_of_a_pixel_by_a_straight_boundary(angle_deg):
    """`covered` against the share of 400 x 400 samples of the pixel inside the boundary (within 1 / 400)."""
    normal = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])
    distances = np.linspace(-0.8, 0.8, 33)
    offsets = (np.arange(400) + 0.5) / 400 - 0.5
    rows, cols = np.meshgrid(offsets, offsets, indexing="ij")
    counted = [np.mean(d + normal[0] * rows + normal[1] * cols < 0.0) for d in distances]
    assert covered(distances, np.tile(normal, (len(distances), 1))) == pytest.approx(counted, abs=2.5e-3)


def _disc_leg(samples: int | None, blur_px: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A leg of two discs (fat over muscle) and its labels; each pixel the mean of samples x samples point samples
    (None: 21 x 21, i.e. anti-aliased), optionally band-limited by a Gaussian of blur_px, with Rician noise."""
    from scipy import ndimage

    count = samples or 21
    offsets = (np.arange(count) + 0.5) / count - 0.5
    rows, cols = np.indices(SHAPE, dtype=float)
    image = np.zeros(SHAPE)
    for dr in offsets:
        for dc in offsets:
            radius = np.hypot(rows + dr - CENTRE[0], cols + dc - CENTRE[1])
            image += np.where(radius < RADII[1], LEVELS[2], np.where(radius < RADII[0], LEVELS[1], LEVELS[0]))
    image /= count * count
    if blur_px:
        image = ndimage.gaussian_filter(image, blur_px)
    radius = np.hypot(rows - CENTRE[0], cols - CENTRE[1])
    labels = np.where(radius < RADII[1], MUSCLE, np.where(radius < RADII[0], FAT, 0)).astype(np.uint8)
    return add_rician_noise(image, 0.02, np.random.default_rng(seed)), labels


@pytest.mark.parametrize("seed", [1, 2])
def test_point_sampled_outlines_are_told_from_anti_aliased_and_band_limited_ones(seed):
    drawn, labels = _disc_leg(3, seed=seed)
    verdict = detect_point_sampling(drawn, labels)
    assert verdict is not None and verdict.samples == 3 and verdict.p_value < 1e-6
    for other in (_disc_leg(None, seed=seed)[0], _disc_leg(None, blur_px=0.8, seed=seed)[0]):
        assert detect_point_sampling(other, labels) is None


@pytest.mark.slow
@pytest.mark.parametrize("anti_aliased", [False, True])
def test_calfits_second_renderer_point_sampled_is_found_and_anti_aliased_is_not(tmp_path, anti_aliased):
    """calfit's second renderer draws each of its 3 x 3 samples a pixel wholly in one tissue (anti_aliased False, a
    renderer's drawing; the skin as bright as fat, so that the steps of 1/9 rise above the noise) or with the share it
    covers (its default): `calfit measure` finds the first point-sampled, with 3 x 3 samples, and adds its drawing's
    error to the windows' covariance, and leaves the second as it is."""
    from orchestrator.core.files import read_json
    from orchestrator.core.frame import RigidMotion
    from orchestrator.measure.measurements import read_window_table
    from orchestrator.phantom import MRIPhantom
    from orchestrator.phantom.cases import make_phantom_case
    from orchestrator.phantom.mri.scanner import MRIContrast
    from orchestrator.phantom.truths import random_truth
    from orchestrator.run.stages import run_measure

    phantom = MRIPhantom.at_resolution(0.36, anti_aliased=anti_aliased, contrast=MRIContrast(skin=0.9))
    case, _ = make_phantom_case(tmp_path / "case", phantom=phantom, theta_kPa=random_truth(5), n_elements=3000,
                                labels=None, points_spacing_mm=None, noise_seeds=(11, 12),
                                rigid=RigidMotion(-1.0, (0.8, 0.5), (75.0, 75.0)))
    run_measure(case, tmp_path / "run")
    found = read_json(tmp_path / "run" / "measurements.json", "calfit measure")["point_sampling"]
    factor = read_window_table(tmp_path / "run").drawing_factor_mm
    if anti_aliased:
        assert found is None and factor is None
    else:
        assert found["samples_per_side"] == 3 and found["p_value"] < 1e-8
        assert factor is not None and 0.01 < found["share_of_variance"] < 0.5
