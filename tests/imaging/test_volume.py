"""Volumes of a volume study (orchestrator/case/volume.py: read_volume) and their rigid alignment on the bones
(orchestrator/imaging/align3d.py).

The alignment is checked on a phantom leg drawn analytically in patient mm: an elliptic outline with a layer of
bright fat, muscle, and two bone rods (a dark cortex round a bright marrow) whose cross-sections swell, turn and run
obliquely with height, so that the slide along the leg is determined; fat, muscle and marrow carry a smooth random
texture, and the magnitude image has Rician noise. Each voxel averages the phantom over its slice's thickness (3 mm
of the 4 mm spacing). The loaded volume is drawn by sampling the phantom at the inverse motion of its own voxel
points, not by resampling the unloaded volume, so the interpolation of the alignment meets data it did not make.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from dicom_files import new_dataset, put_grey_image
from scipy import ndimage
from scipy.special import erf

from orchestrator.case.volume import (
    RigidMotion3D,
    Volume,
    read_volume,
    volume_affine,
    write_nifti_volume,
)
from orchestrator.core.errors import CaseError, ImagingError
from orchestrator.core.tissues import BONE
from orchestrator.imaging.align3d import align_volumes_on_bones, resample_on_slice
from orchestrator.imaging.segment import segment_t1

# ----------------------------------------------------------------- the phantom leg

SHAPE = (120, 120, 12)
PIXEL_MM = (0.8, 0.8)
SPACING_MM = 4.0
THICKNESS_MM = 3.0
EDGE_MM = 0.35                  # blur of every edge (Gaussian sigma): a pixel's partial volume
GREY = {"fat": 1000.0, "muscle": 420.0, "cortex": 60.0, "marrow": 850.0}
NOISE = 15.0                    # Rician: SNR 28 in the muscle
LEG_CENTRE_MM = (48.0, 50.0, 22.0)
TRUTH = RigidMotion3D((1.0, -1.5, 4.0), (3.0, -2.0, 5.0), LEG_CENTRE_MM)


def _inside(u, v, a, b):
    """Smooth indicator of the ellipse (u/a)^2 + (v/b)^2 < 1 (signed distance approximated by its mean radius)."""
    rho = np.sqrt((u / a) ** 2 + (v / b) ** 2)
    return 0.5 * (1 + erf((1 - rho) * (a + b) / 2 / (np.sqrt(2) * EDGE_MM)))


def _texture(x, y, z):
    """Smooth random texture of unit RMS: six plane waves of 6-20 mm wavelength, the same in both sessions."""
    rng = np.random.default_rng(3)
    total = 0.0
    for _ in range(6):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        wavenumber = 2 * np.pi / rng.uniform(6.0, 20.0)
        total = total + np.cos(wavenumber * (direction[0] * x + direction[1] * y + direction[2] * z)
                               + rng.uniform(0, 2 * np.pi))
    return total / np.sqrt(3.0)


def _leg(x, y, z, bones: bool = True):
    """Grey level of the phantom at patient points (mm): x along columns, y along rows, z the height."""
    texture = 1 + 0.05 * _texture(x, y, z)
    height = z - LEG_CENTRE_MM[2]
    a, b = 37.0 + 1.5 * np.sin(z / 20), 34.0 - 1.0 * np.cos(z / 17)
    leg = _inside(x - 48.0, y - 50.0, a, b)
    muscle = _inside(x - 48.5, y - 50.5, a - 6.5, b - 5.5)
    # tibia: elliptic, swelling and turning with height, inclined; fibula: round, thinning, inclined the other way
    angle = 0.4 + 0.012 * height
    tx, ty = x - (42.0 + 0.06 * height), y - (36.0 + 0.03 * height)
    u, v = np.cos(angle) * tx + np.sin(angle) * ty, -np.sin(angle) * tx + np.cos(angle) * ty
    ta, tb = 11.0 + 1.8 * np.sin(z / 12), 8.5 + 0.8 * np.cos(z / 9)
    tibia, tibia_marrow = _inside(u, v, ta, tb), _inside(u, v, ta - 2.5, tb - 2.5)
    fx, fy, radius = x - (64.0 - 0.08 * height), y - (58.0 + 0.04 * height), 5.6 + 0.9 * np.sin(z / 8)
    fibula, fibula_marrow = _inside(fx, fy, radius, radius), _inside(fx, fy, radius - 1.6, radius - 1.6)
    bone = (tibia + fibula) * bones
    marrow = (tibia * tibia_marrow + fibula * fibula_marrow) / np.maximum(tibia + fibula, 1e-9)
    bone_grey = GREY["cortex"] * (1 - marrow) + GREY["marrow"] * texture * marrow
    deep = GREY["muscle"] * texture * (1 - bone) + bone * bone_grey
    return leg * (GREY["fat"] * texture * (1 - muscle) + muscle * deep)


def _render(motion: RigidMotion3D | None = None, *, seed: int, shape=SHAPE, bones: bool = True) -> Volume:
    """The phantom moved by `motion` (the loaded session), seen by an axial volume: each voxel is the phantom at
    motion.inverse() of its points, averaged over the slice thickness, with Rician noise."""
    affine = volume_affine(PIXEL_MM, SPACING_MM, (PIXEL_MM[1] / 2, PIXEL_MM[0] / 2, 0.0))
    grid = Volume(np.zeros(shape), affine)
    points = np.stack([grid.slice_points_mm(k) for k in range(shape[2])], axis=-1)
    back = (motion or RigidMotion3D()).inverse()
    depths = ((np.arange(4) + 0.5) / 4 - 0.5) * THICKNESS_MM
    signal = np.mean([_leg(*back.apply(points + (grid.normal * depth)[:, None, None, None]), bones=bones)
                      for depth in depths], axis=0)
    rng = np.random.default_rng(seed)
    return Volume(np.hypot(signal + rng.normal(0, NOISE, shape), rng.normal(0, NOISE, shape)), affine)


@pytest.fixture(scope="module")
def sessions():
    """(unloaded, loaded, alignment): the phantom and the phantom moved by TRUTH, aligned once for the module."""
    unloaded, loaded = _render(seed=0), _render(TRUTH, seed=1)
    return unloaded, loaded, align_volumes_on_bones(unloaded, loaded)


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


# ----------------------------------------------------------------- sampling through slices


@pytest.mark.parametrize("through_plane", ["linear", "keys"])
def test_resampling_is_cubic_in_plane_and_between_slices_as_asked_and_nan_outside(through_plane):
    """Voxels 0.3 row^2 - 2 column + 5 slice^2: a cubic spline gives the in-plane quadratic exactly (away from the
    edges); between slices Keys' cubic convolution gives slice^2 exactly, and linear interpolation its chord, which
    is also what Keys falls back to between the last two slices (no slice beyond to take part)."""
    rows, columns, slices = np.indices((40, 44, 6), dtype=float)
    loaded = Volume(0.3 * rows ** 2 - 2 * columns + 5 * slices ** 2, volume_affine((0.5, 0.5), 3.0))
    unloaded = Volume(np.zeros((40, 44, 6)), volume_affine((0.5, 0.5), 3.0))
    # up by half a slice and 0.3 pixels along the rows: slice k of the unloaded volume falls at k + 0.5 of the loaded
    shift = RigidMotion3D(translation_mm=(0.0, 0.15, 1.5))
    row, column = np.indices((40, 44), dtype=float)
    interior = (slice(10, 30), slice(10, 34))
    for k in (2, 4):
        resampled = resample_on_slice(loaded, unloaded, k, shift, through_plane)
        along = 5 * (k ** 2 + (k + 1) ** 2) / 2 if through_plane == "linear" or k == 4 else 5 * (k + 0.5) ** 2
        np.testing.assert_allclose(resampled[interior], (0.3 * (row + 0.3) ** 2 - 2 * column + along)[interior],
                                   atol=1e-6)
        assert not np.isnan(resampled).any()      # row 39.3 lies in the last row's pixel, which ends at 39.5

    # beyond the matrix's edge: 0.6 of a column to the right, the last column falls at 43.6, outside
    off = np.isnan(resample_on_slice(loaded, unloaded, 2, RigidMotion3D(translation_mm=(0.3, 0.0, 0.0))))
    assert off[:, -1].all() and off.sum() == 40

    # at the last slice, the last slice; beyond it, nothing (another tissue plane)
    last = resample_on_slice(loaded, unloaded, 4, RigidMotion3D(translation_mm=(0.0, 0.0, 3.0)))
    np.testing.assert_allclose(last, loaded.slice_image(5), atol=1e-9)
    assert np.isnan(resample_on_slice(loaded, unloaded, 5, RigidMotion3D(translation_mm=(0.0, 0.0, 0.3)))).all()

    # a NaN voxel spoils the samples whose interpolation uses it, and no other
    holed = loaded.voxels.copy()
    holed[20, 20, 3] = np.nan
    spoiled = np.isnan(resample_on_slice(Volume(holed, loaded.affine), unloaded, 2, shift))
    assert spoiled[19, 20] and spoiled[20, 20] and spoiled.sum() == 2     # rows 19.3 and 20.3, column 20


# ----------------------------------------------------------------- alignment on the bones


def test_known_motion_is_recovered(sessions):
    """Measured: rotation vector within 0.04 degree and the bone centre within 0.03 mm, slide included (seeds 0
    and 1; 0.1 mm of slide over five other motions of up to 10 mm of slide)."""
    _, _, alignment = sessions
    assert alignment.bones_per_slice_unloaded == (2,) * 12 and alignment.bones_per_slice_loaded == (2,) * 12
    centre = np.array(alignment.motion.centre_mm)
    error_rotation = np.array(alignment.motion.rotation_vector_deg) - TRUTH.rotation_vector_deg
    error_centre = alignment.motion.apply(centre) - TRUTH.apply(centre)
    assert abs(error_rotation[2]) < 0.3                     # the turn about the leg (the slices are axial)
    assert np.hypot(*error_rotation[:2]) < 0.5              # the tilt
    assert np.hypot(*error_centre[:2]) < 0.3                # in the plane
    assert abs(error_centre[2]) < 1.5                       # the slide
    assert alignment.slide_mm == pytest.approx(error_centre[2] + (TRUTH.apply(centre) - centre)[2])
    assert alignment.centroid_rms_mm < 0.2 and alignment.correlation > 0.99
    # the refinement did the work the bones' lines and the slide scan began
    start_error = np.array(alignment.start.rotation_vector_deg) - TRUTH.rotation_vector_deg
    assert np.linalg.norm(error_rotation) < np.linalg.norm(start_error)


def test_resampled_slice_superposes_the_bones_and_is_nan_beyond_the_loaded_slab(sessions):
    unloaded, loaded, alignment = sessions
    k = 5
    resampled = resample_on_slice(loaded, unloaded, k, alignment.motion)
    labels = segment_t1(unloaded.slice_image(k), PIXEL_MM)
    bones = ndimage.binary_dilation(labels == BONE, iterations=1)

    def correlation(image):
        a, b = unloaded.slice_image(k)[bones], image[bones]
        return float(np.corrcoef(a, b)[0, 1])

    assert not np.isnan(resampled[labels > 0]).any()      # only the corners of the field left the loaded matrix
    assert correlation(resampled) > 0.95                     # measured 0.997
    assert correlation(loaded.slice_image(k)) < 0.3          # the same slice unaligned (0.07): the bones have moved

    # slid up 5 mm, the top two slices fall beyond the loaded slab (the lower one but for a corner, by the tilt)
    for k in range(SHAPE[2]):
        index = loaded.index_of_points(alignment.motion.apply(unloaded.slice_points_mm(k)))
        # outside the loaded voxels' extent: more than half a pixel beyond the edge centres, or beyond the end slices
        margins = (0.5, 0.5, 0.0)
        beyond = np.any([(index[axis] < -margins[axis]) | (index[axis] > SHAPE[axis] - 1 + margins[axis])
                         for axis in range(3)], axis=0)
        np.testing.assert_array_equal(np.isnan(resample_on_slice(loaded, unloaded, k, alignment.motion)), beyond)
    assert np.isnan(resample_on_slice(loaded, unloaded, 11, alignment.motion)).all()
    lost = {k: np.isnan(resample_on_slice(loaded, unloaded, k, alignment.motion))[
        segment_t1(unloaded.slice_image(k), PIXEL_MM) > 0].mean() for k in (9, 10)}
    assert lost[9] == 0.0 and 0.5 < lost[10] < 1.0          # slice 10 lies 0.25 of a slice beyond the loaded slab,
    #                                                          but for the corner that the tilt brings back in (97 %)


def test_volumes_without_bones_raise_imaging_error():
    boneless = _render(seed=2, shape=(120, 120, 3), bones=False)
    with pytest.raises(ImagingError, match="no bone found in any of the 3 slices of the unloaded volume"):
        align_volumes_on_bones(boneless, boneless)
