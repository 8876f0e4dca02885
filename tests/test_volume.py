"""Volumes of a volume study (orchestrator/imaging/volume.py: read_volume): NIfTI files and DICOM series folders."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from dicom_files import new_dataset, put_grey_image

from orchestrator.imaging.errors import CaseError
from orchestrator.imaging.volume import read_volume, write_nifti_volume

# ----------------------------------------------------------------- NIfTI


def _oblique(angle_deg: float = 20.0) -> np.ndarray:
    """Rotation about (1, 2, 3): no axis of the voxel grid along a patient axis."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.deg2rad(angle_deg) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)).as_matrix()


@pytest.mark.parametrize("slice_axis_sign", [1.0, -1.0])
def test_nifti_round_trip_keeps_voxels_pixel_size_and_positions(tmp_path, slice_axis_sign):
    rotation = _oblique()
    affine = np.eye(4)
    affine[:3, :3] = rotation @ np.diag([0.55, 0.7, 3.5 * slice_axis_sign])   # rows, columns, slices: non-square
    affine[:3, 3] = (-40.0, 12.5, 101.0)
    voxels = np.random.default_rng(4).normal(300.0, 50.0, (20, 24, 5))
    voxels[3, 7, 2] = np.nan
    path = write_nifti_volume(tmp_path / "unloaded.nii.gz", voxels, affine)

    volume = read_volume(path)

    assert volume.shape == (20, 24, 5) and volume.source == path
    np.testing.assert_array_equal(volume.voxels, voxels.astype(np.float32))       # NaN where it was, and only there
    np.testing.assert_allclose(volume.affine, affine, rtol=1e-6, atol=1e-5)        # stored as float32 in the header
    np.testing.assert_allclose(volume.pixel_size_mm, (0.55, 0.7), rtol=1e-6)
    np.testing.assert_allclose(volume.slice_spacing_mm, 3.5, rtol=1e-6)
    normal = slice_axis_sign * rotation[:, 2]    # towards increasing slice index, whichever way rows x columns points
    np.testing.assert_allclose(volume.normal, normal, atol=1e-6)
    np.testing.assert_allclose(volume.slice_positions_mm, affine[:3, 3] @ normal + 3.5 * np.arange(5), atol=1e-4)
    np.testing.assert_allclose(volume.slice_points_mm(4)[:, 19, 0], affine[:3] @ [19, 0, 4, 1], atol=1e-4)


@pytest.mark.parametrize("shape, problem", [((20, 24), "not a 3D volume"), ((20, 24, 3, 2), "not a 3D volume"),
                                            ((20, 24, 1), "a single slice")])
def test_nifti_that_is_not_a_volume_is_refused(tmp_path, shape, problem):
    import nibabel

    path = tmp_path / "loaded.nii"
    nibabel.save(nibabel.Nifti1Image(np.ones(shape, np.float32), np.eye(4)), path)
    with pytest.raises(CaseError, match=problem) as raised:
        read_volume(path)
    assert raised.value.file == path


def test_without_the_medical_extra_a_case_error_says_what_to_install(tmp_path, monkeypatch):
    path = write_nifti_volume(tmp_path / "unloaded.nii", np.ones((16, 16, 3)), np.eye(4))
    folder = tmp_path / "loaded"
    folder.mkdir()
    monkeypatch.setitem(sys.modules, "nibabel", None)     # import nibabel now raises ImportError
    monkeypatch.setitem(sys.modules, "pydicom", None)
    for source, module in ((path, "nibabel"), (folder, "pydicom")):
        with pytest.raises(CaseError, match=rf"without {module}, which is not installed; install the medical extra: "
                                            r"pip install 'calfit\[medical\]'"):
            read_volume(source)


# ----------------------------------------------------------------- DICOM series

DICOM_SHAPE = (18, 22)              # rows != columns, so that a transpose is seen
DICOM_SPACING = (0.5, 0.6)          # row, column spacing: non-square, so that a swap is seen
DICOM_CORNER = (-30.0, 12.0)        # x, y of the first pixel's centre
DICOM_RESCALE = (2.0, -10.0)


def _write_series(folder, heights_mm, *, overrides=None, shifts=None) -> list[np.ndarray]:
    """An axial series (rows along +y, columns along +x) of one file per slice, file names shuffled against the
    heights and InstanceNumbers running against them; returns the rescaled pixels in order of height.
    overrides: {slice index: DICOM keywords to delete}; shifts: {slice index: x shift of its corner, mm}."""
    from pydicom.uid import generate_uid

    folder.mkdir()
    series_uid = generate_uid()
    names = np.random.default_rng(5).permutation(len(heights_mm))
    expected = []
    for index, height in enumerate(heights_mm):
        stored = (np.random.default_rng(index).integers(0, 500, DICOM_SHAPE) + 1000 * (index + 1)).astype(np.uint16)
        dataset = new_dataset()
        put_grey_image(dataset, stored, [str(v) for v in DICOM_SPACING], rescale=tuple(map(str, DICOM_RESCALE)))
        dataset.Modality, dataset.PatientID, dataset.SeriesInstanceUID = "MR", "CALF-01", series_uid
        dataset.InstanceNumber = len(heights_mm) - index
        dataset.SliceThickness = "3"
        dataset.ImageOrientationPatient = ["1", "0", "0", "0", "1", "0"]
        shift = (shifts or {}).get(index, 0.0)
        dataset.ImagePositionPatient = [str(DICOM_CORNER[0] + shift), str(DICOM_CORNER[1]), str(height)]
        for keyword in (overrides or {}).get(index, ()):
            delattr(dataset, keyword)
        dataset.save_as(folder / f"IM_{names[index] + 1:04d}", enforce_file_format=True)
        expected.append(stored * DICOM_RESCALE[0] + DICOM_RESCALE[1])
    return expected


def test_dicom_series_reads_in_order_of_position_with_its_spacing_and_rescale(tmp_path):
    heights = (-12.0, -8.0, -4.0, 0.0, 4.0, 8.0)
    expected = _write_series(tmp_path / "unloaded", heights)

    volume = read_volume(tmp_path / "unloaded")

    assert volume.shape == (*DICOM_SHAPE, len(heights)) and volume.source == tmp_path / "unloaded"
    for k, pixels in enumerate(expected):
        np.testing.assert_array_equal(volume.slice_image(k), pixels)
    assert volume.pixel_size_mm == pytest.approx(DICOM_SPACING)
    assert volume.slice_spacing_mm == pytest.approx(4.0)
    np.testing.assert_allclose(volume.normal, (0, 0, 1))
    np.testing.assert_allclose(volume.slice_positions_mm, heights)
    # pixel (row 2, column 5) of the slice at -8 mm: 5 columns along +x, 2 rows along +y from the first pixel
    point = (DICOM_CORNER[0] + 5 * DICOM_SPACING[1], DICOM_CORNER[1] + 2 * DICOM_SPACING[0], -8.0)
    np.testing.assert_allclose(volume.slice_points_mm(1)[:, 2, 5], point)
    np.testing.assert_allclose(volume.index_of_points(np.array(point)), (2, 5, 1), atol=1e-12)


@pytest.mark.parametrize("heights, changes, problem", [
    ((0.0, 4.0, 8.0, 14.0, 18.0), {}, r"uneven slice gaps, 4\.00 to 6\.00 mm .*6\.00 mm between IM_\d+ at 8 mm and "
                                      r"IM_\d+ at 14 mm, against a median gap of 4\.00 mm"),
    ((5.0,), {}, "is a series of 1 slice at 5 mm along the slice normal, not a volume"),
    ((0.0, 4.0, 8.0), {"overrides": {i: ("ImagePositionPatient", "ImageOrientationPatient") for i in range(3)}},
     "without ImagePositionPatient, ordered by InstanceNumber .* cannot be placed in space"),
    ((0.0, 4.0, 8.0, 12.0), {"shifts": {1: 1.5}}, r"shifted in their plane \(IM_\d+ lies 1\.50 mm off the line"),
])
def test_dicom_series_that_is_not_an_even_stack_is_refused(tmp_path, heights, changes, problem):
    folder = tmp_path / "loaded"
    _write_series(folder, heights, **changes)
    with pytest.raises(CaseError, match=problem) as raised:
        read_volume(folder)
    assert raised.value.file == folder and str(raised.value).startswith(f"{folder}: ")
