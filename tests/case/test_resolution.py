"""Slices finer than the DIC windows and the segmentation are made for are worked over blocks of pixels
(`imaging.resolution`): the image frame in mm is kept, and a 1024x1024 slice of the phantom calf (0.148 mm
pixels) is measured over 2x2 blocks with almost every window kept and displacements as accurate as on a
clinical matrix."""

import numpy as np
import pytest

from orchestrator.case.resolution import block_factor, coarsen_image, coarsen_labels
from orchestrator.core.frame import pixel_centres_mm
from orchestrator.measure.measurements import read_window_table
from orchestrator.phantom import CalfPhantom, write_case
from orchestrator.phantom.render import bone_clamped_compression
from orchestrator.run.setup import load_run
from orchestrator.run.stages import run_measure

FIELD_OF_VIEW_MM = 151.2


@pytest.mark.parametrize("pixel_mm, factor", [(0.5, 1), (0.36, 1), (0.18, 1), (0.1476, 2), (0.12, 2), (0.0738, 3)])
def test_block_factor_brings_the_pixel_to_at_least_0_18_mm(pixel_mm, factor):
    assert block_factor((pixel_mm, pixel_mm)) == factor


def test_blocks_keep_the_image_frame():
    """An off-centre disk, 1001 pixels of 0.05 mm, over 3x3 blocks: its centroid in mm moves by less than a
    hundredth of a block, its area by less than 0.5 %."""
    shape, pixel = (1001, 1001), (0.05, 0.05)
    x, y = pixel_centres_mm(shape, pixel)
    disk = ((x - 21.3) ** 2 + (y - 27.9) ** 2 < 12.0 ** 2).astype(float)
    coarse_image, coarse_labels = coarsen_image(disk, 3), coarsen_labels(disk.astype(np.uint8), 3)
    cx, cy = pixel_centres_mm(coarse_image.shape, (0.15, 0.15))
    weight = coarse_image.sum()
    assert abs((cx * coarse_image).sum() / weight - 21.3) < 0.0015 and abs((cy * coarse_image).sum() / weight - 27.9) < 0.0015
    assert abs(coarse_labels.sum() * 0.15 ** 2 / (np.pi * 144.0) - 1.0) < 0.005


@pytest.mark.slow
def test_a_1024_matrix_is_measured_over_blocks_like_a_clinical_one(tmp_path):
    size = 1024
    pixel = FIELD_OF_VIEW_MM / size
    phantom = CalfPhantom(image_shape=(size, size), pixel_size_mm=(pixel, pixel), supersampling=1)
    case, _ = write_case(tmp_path / "case", phantom, labels=None)
    summary = run_measure(case, tmp_path / "run")
    setup = load_run(tmp_path / "run")
    assert setup.case.block_factor == 2 and setup.case.pixel_size_mm == (2 * pixel, 2 * pixel)
    assert "means of 2x2 blocks" in setup.setup_lines()[0]
    table = read_window_table(tmp_path / "run")
    kept = table.kept
    truth = bone_clamped_compression(phantom.geometry)
    position = table.position_mm[kept]
    error = np.linalg.norm(table.displacement_mm[kept] - np.stack(truth(position[:, 0], position[:, 1]), axis=1), axis=1)
    print(f"{summary['kept']} of {len(kept)} windows kept; error against the truth at their centres: median "
          f"{np.median(error):.4f} mm, 90th percentile {np.percentile(error, 90):.4f} mm")
    assert kept.mean() > 0.9                # natively (32 pixels = 4.7 mm) 85 % are kept
    assert np.median(error) < 0.025         # the clinical 420x420 matrix of the same calf: 0.014 mm
