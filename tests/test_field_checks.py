"""The two slices must show what the model assumes (`imaging.field_checks`, run by `prepare_run` before it
writes anything): the leg inside the field of view, and a garment that compresses it. Phantom cases with the
analytic bone-clamped compression (2.5 % radial strain: the leg loses about 5 % of its area)."""

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest

from orchestrator.imaging.errors import ImagingError
from orchestrator.imaging.field_checks import MAX_GROWTH, check_compression, check_leg_in_view
from orchestrator.imaging.segment import segment_t1
from orchestrator.phantom import CalfPhantom, write_case
from orchestrator.study import prepare_run


@pytest.fixture(scope="module")
def compressed_case(tmp_path_factory):
    case, _ = write_case(tmp_path_factory.mktemp("checks") / "case", labels=None)
    return case


def _copy(case, tmp_path, name):
    target = tmp_path / name
    shutil.copytree(case, target)
    return target


def test_a_case_that_shows_a_compression_passes(compressed_case, tmp_path):
    setup = prepare_run(compressed_case, tmp_path / "run", n_elements=1000, order=2)
    change = json.loads(setup.run_dir.joinpath("setup.json").read_text())["leg_area_change"]
    assert -0.07 < change < -0.03     # a 2.5 % radial shrink outside the bones: about 5 % of the area


def test_swapped_images_are_named_and_nothing_is_written(compressed_case, tmp_path):
    case = _copy(compressed_case, tmp_path, "swapped")
    unloaded, loaded = (case / "unloaded.png").read_bytes(), (case / "loaded.png").read_bytes()
    (case / "unloaded.png").write_bytes(loaded)
    (case / "loaded.png").write_bytes(unloaded)
    with pytest.raises(ImagingError, match=r"loaded.png \(with the garment\) is [4-6]\.\d % larger .* swapped"):
        prepare_run(case, tmp_path / "run", n_elements=1000, order=2)
    assert not (tmp_path / "run").exists()


def test_a_leg_cut_by_the_field_of_view_is_refused(compressed_case, tmp_path):
    case = _copy(compressed_case, tmp_path, "cut")
    for name in ("unloaded", "loaded"):
        iio.imwrite(case / f"{name}.png", iio.imread(case / f"{name}.png")[:, 60:])
    with pytest.raises(ImagingError, match=r"unloaded.png touches the image border \(\d+\.\d mm along the left edge\)"):
        prepare_run(case, tmp_path / "run", n_elements=1000, order=2)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("seeds", [(0, 1), (5, 6), (11, 12)])
def test_segmentation_jitter_without_a_garment_stays_under_the_growth_bound(seeds):
    """The same slice twice with independent noise: the area change is jitter, well inside MAX_GROWTH."""
    from orchestrator.phantom.render import render_unloaded

    phantom = CalfPhantom()
    first, second = (segment_t1(render_unloaded(phantom, noise_seed=s), phantom.pixel_size_mm) > 0 for s in seeds)
    assert abs(check_compression(first, second, "a", "b")) < MAX_GROWTH / 2
    check_leg_in_view(first.astype(np.uint8), phantom.pixel_size_mm, "a")
