"""The two slices must show what the model assumes (`imaging.field_checks`, run by `prepare_run` before it
writes anything): the leg inside the field of view, and a garment that compresses it. Phantom cases with the
analytic bone-clamped compression (2.5 % radial strain: the leg loses about 5 % of its area). Float slices with
NaN (as a reslicing leaves them) are read with the NaN outside the leg as background, and refused with the
place named where the NaN touch the leg."""

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest

from orchestrator.core.errors import ImagingError
from orchestrator.imaging.field_checks import (
    MAX_GROWTH,
    MISSING_MARGIN_MM,
    check_compression,
    check_leg_in_view,
)
from orchestrator.imaging.segment import segment_t1
from orchestrator.phantom import CalfPhantom, write_case
from orchestrator.run.setup import prepare_run


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


def test_labels_with_holes_and_islands_mesh_the_leg_alone(compressed_case, tmp_path):
    """A hand segmentation with a pinhole of background in the muscle, a speck of muscle in the fat and a fleck of
    fat in the air outside the leg: the specks are dropped, the mesh covers the leg and nothing else."""
    case = _copy(compressed_case, tmp_path, "speckled")
    unloaded = iio.imread(case / "unloaded.png")
    labels = segment_t1(unloaded.astype(float), CalfPhantom().pixel_size_mm)
    clean = labels.copy()
    rows, cols = np.nonzero(labels == 2)
    r, c = rows[len(rows) // 2], cols[len(cols) // 2]
    labels[r:r + 2, c:c + 2] = 0                      # hole in the muscle
    rows, cols = np.nonzero(labels == 1)
    labels[rows[0] + 1, cols[0]] = 2                  # island of muscle in the fat
    labels[3:5, 3:5] = 1                              # island of fat in the air
    iio.imwrite(case / "labels.png", labels)
    setup = prepare_run(case, tmp_path / "run", n_elements=1000, order=2)
    corners = setup.mesh.nodes[setup.mesh.elements[:, :3]]
    area = _mesh_area(setup.mesh)
    pixel = CalfPhantom().pixel_size_mm
    soft = np.isin(clean, (1, 2)).sum() * pixel[0] * pixel[1]
    assert abs(area / soft - 1.0) < 0.02                # the soft tissue of the clean segmentation, within 2 %
    assert corners[:, :, 0].min() > 10.0 and corners[:, :, 1].min() > 10.0    # nothing meshed at the fleck


def _mesh_area(mesh) -> float:
    corners = mesh.nodes[mesh.elements[:, :3]]
    edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    return 0.5 * float(np.abs(edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0]).sum())


def _as_float_nifti(case, edit):
    """Replace the case's PNG slices by float32 NIfTI files, each edited by edit(pixels, name)."""
    import nibabel

    affine = np.diag([*CalfPhantom().pixel_size_mm, 1.0, 1.0])
    for name in ("unloaded", "loaded"):
        pixels = iio.imread(case / f"{name}.png").astype(np.float32)
        edit(pixels, name)
        (case / f"{name}.png").unlink()
        nibabel.save(nibabel.Nifti1Image(pixels[:, :, None], affine), case / f"{name}.nii.gz")


def test_float_slices_with_nan_outside_the_leg_are_read_as_background(compressed_case, tmp_path):
    """NaN in the corners and along the top rows (a reslicing's empty wedge): counted, announced, and the leg
    segmented and meshed as from the clean slices."""
    case = _copy(compressed_case, tmp_path, "nan-outside")

    def blank_corners(pixels, name):
        pixels[:6, :] = np.nan
        for rows in (slice(0, 25), slice(-25, None)):
            for cols in (slice(0, 25), slice(-25, None)):
                pixels[rows, cols] = np.nan
    _as_float_nifti(case, blank_corners)
    setup = prepare_run(case, tmp_path / "run", n_elements=1000, order=2)
    clean = prepare_run(compressed_case, tmp_path / "clean", n_elements=1000, order=2)
    shape = setup.case.shape
    expected = 6 * shape[1] + 2 * 25 * 25 + 2 * 19 * 25
    share = expected / (shape[0] * shape[1])
    assert setup.missing_fraction == {"unloaded.nii.gz": share, "loaded.nii.gz": share}
    assert f"unloaded.nii.gz: no value (NaN) in {100 * share:.1f} % of the slice, all outside the leg" in setup.setup_lines()[0]
    differ = np.count_nonzero(setup.labels_unloaded != clean.labels_unloaded)
    print(f"{differ} of {np.count_nonzero(clean.labels_unloaded)} leg pixels labelled otherwise")
    assert differ <= 0.001 * np.count_nonzero(clean.labels_unloaded)
    assert abs(_mesh_area(setup.mesh) / _mesh_area(clean.mesh) - 1.0) < 0.002


def test_nan_in_the_leg_is_refused_with_its_place(compressed_case, tmp_path):
    case = _copy(compressed_case, tmp_path, "nan-inside")
    pixel = CalfPhantom().pixel_size_mm
    labels = segment_t1(iio.imread(case / "loaded.png").astype(float), pixel)
    rows, cols = np.nonzero(labels == 2)
    r, c = rows[len(rows) // 2], cols[len(cols) // 2]

    def hole_in_loaded(pixels, name):
        if name == "loaded":
            pixels[r - 2:r + 3, c - 2:c + 3] = np.nan
    _as_float_nifti(case, hole_in_loaded)
    where = rf"\({c * pixel[1]:.1f}, {r * pixel[0]:.1f}\) mm"
    with pytest.raises(ImagingError, match=rf"loaded.nii.gz has 25 pixels with no value \(NaN\) in the leg or "
                                           rf"within {MISSING_MARGIN_MM:g} mm of its skin, around \(x, y\) = {where}"):
        prepare_run(case, tmp_path / "run", n_elements=1000, order=2)
    assert not (tmp_path / "run").exists()
