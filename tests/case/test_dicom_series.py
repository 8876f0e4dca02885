"""DICOM series as case images (orchestrator/case/dicom_series.py).

Series are written as a scanner exports them: one file per slice, file names shuffled against the positions,
some with a .dcm suffix and some with none, a DICOMDIR and a text file beside them, InstanceNumbers running
against the positions (feet first), and an oblique orientation, so that a reader ordering by name, by
InstanceNumber or by the z of ImagePositionPatient picks the wrong slice. Every slice has its own grey levels,
so the wrong pick fails the comparison.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from dicom_files import new_dataset, put_grey_image

from orchestrator.case.folder import PIXEL_SIZE_RTOL, read_case
from orchestrator.core.errors import CaseError

SHAPE = (48, 64)
SPACING = (0.42, 0.40)         # row, column: non-square, so a swap is seen
POSITIONS = (-7.5, -2.5, 2.5, 7.5)
SLICE_GAP = 5.0
RESCALE = {"unloaded": (2.0, -10.0), "loaded": (0.5, 100.0)}


def _rotation(axis, angle_deg: float) -> np.ndarray:
    """Rotation matrix about an axis (Rodrigues)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = math.radians(angle_deg)
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


# Columns: row direction, column direction, normal. Oblique, with the normal pointing down (z component -0.45),
# so that the z of ImagePositionPatient decreases along the normal and is not the position along it.
OBLIQUE = _rotation((1.0, 0.3, 0.2), 120.0)


def _stored_pixels(role: str, index: int, shape=SHAPE) -> np.ndarray:
    """Grey levels of one slice as stored: distinct for every state and slice."""
    rng = np.random.default_rng(100 * (role == "loaded") + index)
    return (rng.integers(0, 800, shape) + 1000 * (index + 1) + 20000 * (role == "loaded")).astype(np.uint16)


def _ds(value: float) -> str:
    return f"{value:.10g}"[:16]


def _write_slice(path, stored, *, position_mm, rotation, spacing, rescale, instance, patient_id, series_uid,
                 overrides=None):
    dataset = new_dataset()
    put_grey_image(dataset, stored, [_ds(v) for v in spacing], rescale=(_ds(rescale[0]), _ds(rescale[1])))
    dataset.Modality = "MR"
    dataset.PatientID = patient_id
    dataset.SeriesInstanceUID = series_uid
    dataset.InstanceNumber = instance
    dataset.SliceThickness = "4"
    origin = rotation @ np.array([-40.0, -30.0, position_mm])   # in-plane offset, then along the normal
    dataset.ImagePositionPatient = [_ds(v) for v in origin]
    dataset.ImageOrientationPatient = [_ds(v) for v in np.concatenate([rotation[:, 0], rotation[:, 1]])]
    for keyword, value in (overrides or {}).items():
        if value is None:
            delattr(dataset, keyword)
        else:
            setattr(dataset, keyword, value)
    dataset.save_as(path, enforce_file_format=True)


def _write_dicomdir(path):
    """A DICOM file with no image, as the DICOMDIR a scanner writes beside the slices."""
    from pydicom.uid import MediaStorageDirectoryStorage

    dataset = new_dataset(MediaStorageDirectoryStorage)
    dataset.FileSetID = "CALF"
    dataset.save_as(path, enforce_file_format=True)


def _write_series(folder, role, *, images=None, positions=POSITIONS, rotation=OBLIQUE, spacing=SPACING,
                  shape=SHAPE, patient_id="CALF-01", overrides=None, seed=0):
    """Write a series, one file per slice in shuffled names; return the pixels expected of each slice (rescaled),
    in the order of increasing position. overrides: {slice index: {DICOM keyword: value or None to delete}}."""
    from pydicom.uid import generate_uid

    folder.mkdir()
    images = images if images is not None else [_stored_pixels(role, i, shape) for i in range(len(positions))]
    slope, intercept = RESCALE[role]
    series_uid = generate_uid()
    names = np.random.default_rng(seed + 7).permutation(len(positions))
    for index, (stored, position) in enumerate(zip(images, positions)):
        name = f"IM_{names[index] + 1:04d}" + (".dcm" if names[index] % 2 else "")
        _write_slice(folder / name, stored, position_mm=position, rotation=rotation, spacing=spacing,
                     rescale=(slope, intercept), instance=len(positions) - index, patient_id=patient_id,
                     series_uid=series_uid, overrides=(overrides or {}).get(index))
    _write_dicomdir(folder / "DICOMDIR")
    (folder / "README.txt").write_text("exported by the scanner\n")
    return [stored.astype(float) * slope + intercept for stored in images]


def _write_toml(folder, images="slice_index = 2", pixel_size=None):
    lines = ['[case]', 'name = "series"']
    if pixel_size is not None:
        lines.append(f"pixel_size_mm = [{pixel_size[0]}, {pixel_size[1]}]")
    lines += ["[garment]", "tension_N_per_mm = 0.16"]
    if images is not None:
        lines += ["[images]", images]
    (folder / "case.toml").write_text("\n".join(lines) + "\n")


def _series_case(tmp_path, images="slice_index = 2", pixel_size=None, unloaded=None, loaded=None):
    """A case of two series; unloaded/loaded: keyword arguments of _write_series. Returns (folder, expected)."""
    folder = tmp_path / "case"
    folder.mkdir()
    _write_toml(folder, images, pixel_size)
    expected = {role: _write_series(folder / role, role, **(kwargs or {}), seed=seed)
                for role, kwargs, seed in (("unloaded", unloaded, 0), ("loaded", loaded, 1))}
    return folder, expected


# --------------------------------------------------------------------------- good series


def test_slice_chosen_by_index_in_order_of_position(tmp_path):
    folder, expected = _series_case(tmp_path, "slice_index = 2")
    case = read_case(folder)
    np.testing.assert_array_equal(case.unloaded, expected["unloaded"][2])
    np.testing.assert_array_equal(case.loaded, expected["loaded"][2])
    assert case.pixel_size_mm == pytest.approx(SPACING)
    assert case.shape == SHAPE
    assert case.files["unloaded"] == folder / "unloaded" and case.files["loaded"] == folder / "loaded"
    import pydicom
    chosen = pydicom.dcmread(case.files["unloaded_slice"])
    assert case.files["unloaded_slice"].parent == folder / "unloaded" and int(chosen.InstanceNumber) == 2


@pytest.mark.parametrize("position_mm, index", [(-3.4, 1), (9.9, 3), (-9.9, 0), (5.1, 3), (4.9, 2)])
def test_slice_chosen_by_position_is_the_nearest(tmp_path, position_mm, index):
    folder, expected = _series_case(tmp_path, f"slice_position_mm = {position_mm}")
    case = read_case(folder)
    np.testing.assert_array_equal(case.unloaded, expected["unloaded"][index])
    np.testing.assert_array_equal(case.loaded, expected["loaded"][index])


def test_small_tilt_and_another_patient_position_are_accepted(tmp_path):
    tilted = _rotation(OBLIQUE[:, 0], 0.5) @ OBLIQUE
    folder, expected = _series_case(tmp_path, "slice_position_mm = 2.0", loaded={"rotation": tilted,
                                                                                 "positions": (-4.0, 1.0, 6.0)})
    case = read_case(folder)
    np.testing.assert_array_equal(case.unloaded, expected["unloaded"][2])
    np.testing.assert_array_equal(case.loaded, expected["loaded"][1])


def test_single_slice_series_needs_no_key_and_header_spacing_is_checked_against_case_toml(tmp_path):
    folder = tmp_path / "case"
    folder.mkdir()
    expected = {role: _write_series(folder / role, role, positions=(1.0,)) for role in ("unloaded", "loaded")}
    _write_toml(folder, images=None, pixel_size=SPACING)
    case = read_case(folder)
    np.testing.assert_array_equal(case.unloaded, expected["unloaded"][0])
    assert case.pixel_size_mm == pytest.approx(SPACING)
    _write_toml(folder, images=None, pixel_size=SPACING[::-1])
    with pytest.raises(CaseError, match=r"unloaded: header gives a pixel spacing of \[0\.42, 0\.4\] mm but case\.toml"):
        read_case(folder)


def test_single_slice_series_gives_its_slice_whatever_the_index_and_is_checked_by_position(tmp_path):
    folder, expected = _series_case(tmp_path, "slice_index = 2", unloaded={"positions": (2.5,)})
    case = read_case(folder)
    np.testing.assert_array_equal(case.unloaded, expected["unloaded"][0])
    np.testing.assert_array_equal(case.loaded, expected["loaded"][2])
    _write_toml(folder, "slice_index = 0")   # the loaded slice at -7.5 mm, 10 mm from the unloaded one
    with pytest.raises(CaseError, match=r"slice 0 at -7\.5 mm .* slice 0 of the unloaded series .* at 2\.5 mm"):
        read_case(folder)


def test_instance_number_orders_a_series_without_positions(tmp_path):
    no_position = {i: {"ImagePositionPatient": None, "ImageOrientationPatient": None} for i in range(4)}
    folder, expected = _series_case(tmp_path, None, unloaded={"overrides": no_position},
                                    loaded={"overrides": no_position})
    with pytest.raises(CaseError, match="ordered by InstanceNumber") as raised:
        read_case(folder)
    assert "slice_index" in str(raised.value)
    _write_toml(folder, "slice_index = 0")
    # InstanceNumbers run against the positions (4 for the first slice written, 1 for the last).
    np.testing.assert_array_equal(read_case(folder).unloaded, expected["unloaded"][3])
    _write_toml(folder, "slice_position_mm = 2.5")
    with pytest.raises(CaseError, match="without ImagePositionPatient"):
        read_case(folder)


def test_one_series_beside_a_single_file(tmp_path):
    folder = tmp_path / "case"
    folder.mkdir()
    expected = _write_series(folder / "unloaded", "unloaded")
    np.save(folder / "loaded.npy", np.ones(SHAPE))
    _write_toml(folder, "slice_position_mm = -7", pixel_size=SPACING)
    case = read_case(folder)
    np.testing.assert_array_equal(case.unloaded, expected[0])
    assert case.files["loaded"] == folder / "loaded.npy" and "loaded_slice" not in case.files


def test_pixel_size_tolerance_is_the_case_tolerance():
    from orchestrator.case import dicom_series

    assert dicom_series.PIXEL_SIZE_RTOL == PIXEL_SIZE_RTOL == 0.01


# --------------------------------------------------------------------------- refused


def _snapshot(folder):
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(folder.rglob("*"))}


def _resized(shape):
    return {"Rows": shape[0], "Columns": shape[1], "PixelData": np.zeros(shape, np.uint16).tobytes()}


def _plain_files(tmp_path):
    folder = tmp_path / "case"
    folder.mkdir()
    for role in ("unloaded", "loaded"):
        np.save(folder / f"{role}.npy", _stored_pixels(role, 0).astype(float))
    _write_toml(folder, "slice_index = 0", pixel_size=SPACING)
    return folder


def _only_non_images(tmp_path):
    folder, _ = _series_case(tmp_path)
    for path in (folder / "loaded").iterdir():
        if path.name.startswith("IM_"):
            path.unlink()
    return folder


def _truncated_chosen_slice(tmp_path):
    import pydicom

    folder, _ = _series_case(tmp_path, "slice_index = 1")
    chosen = next(p for p in (folder / "unloaded").glob("IM_*") if int(pydicom.dcmread(p).InstanceNumber) == 3)
    chosen.write_bytes(chosen.read_bytes()[:-1000])
    return folder


def _with_competing_png(tmp_path):
    folder, _ = _series_case(tmp_path)
    np.save(folder / "unloaded.npy", np.ones(SHAPE))
    return folder


BOTH = ("case/unloaded", "case/loaded")
# (what is wrong, how to make the case, texts the message must hold)
REFUSED = [
    ("several slices and no key", lambda t: _series_case(t, None)[0],
     ("case/unloaded", "4 slices", "-7.5 to 7.5 mm", "slice_position_mm")),
    ("position far from every slice", lambda t: _series_case(t, "slice_position_mm = 11")[0],
     ("case.toml", "beyond its last slice, at 7.5 mm", "half its slice spacing of 5.00 mm")),
    ("index out of range", lambda t: _series_case(t, "slice_index = 4")[0], ("case.toml", "from 0 to 3")),
    ("both keys", lambda t: _series_case(t, "slice_index = 1\nslice_position_mm = 2.5")[0], ("case.toml", "only one")),
    ("unknown key", lambda t: _series_case(t, "slice = 1")[0], ("case.toml", "slice_index, slice_position_mm")),
    ("negative index", lambda t: _series_case(t, "slice_index = -1")[0], ("case.toml", "non-negative")),
    ("keys with single files", _plain_files, ("case.toml", "single slices", "remove the [images] table")),
    ("matrix size differs", lambda t: _series_case(t, loaded={"shape": (48, 60)})[0], BOTH + ("48x60", "48x64")),
    ("pixel spacing differs", lambda t: _series_case(t, loaded={"spacing": (0.44, 0.40)})[0],
     BOTH + ("0.44 x 0.4", "0.42 x 0.4")),
    ("orientation differs", lambda t: _series_case(t, loaded={"rotation": _rotation(OBLIQUE[:, 1], 3.0) @ OBLIQUE})[0],
     BOTH + ("tilted by 3.0 degrees",)),
    ("chosen slices apart", lambda t: _series_case(t, loaded={"positions": tuple(p + 3.0 for p in POSITIONS)})[0],
     BOTH + ("at 5.5 mm", "at 2.5 mm", "3.00 mm", "slice_position_mm")),
    ("series at other positions", lambda t: _series_case(t, "slice_position_mm = -0.05",
                                                         loaded={"positions": (-2.6, 2.4, 7.4)})[0],
     BOTH + ("at -2.5 mm", "at 2.4 mm", "same slice positions")),
    ("another patient", lambda t: _series_case(t, loaded={"patient_id": "CALF-02"})[0], BOTH + ("CALF-02", "CALF-01")),
    ("slices of two matrix sizes", lambda t: _series_case(t, unloaded={"overrides": {2: _resized((40, 64))}})[0],
     ("case/unloaded", "40x64 pixels", "one series only")),
    ("slices of two pixel spacings", lambda t: _series_case(t, loaded={"overrides": {1: {"PixelSpacing": ["0.5", "0.4"]}}})[0],
     ("case/loaded", "PixelSpacing")),
    ("slices of two orientations",
     lambda t: _series_case(t, loaded={"overrides": {3: {"ImageOrientationPatient": ["1", "0", "0", "0", "1", "0"]}}})[0],
     ("case/loaded", "two orientations")),
    ("slices of two series", lambda t: _series_case(t, loaded={"overrides": {2: {"SeriesInstanceUID": "1.2.826.0.1.9"}}})[0],
     ("case/loaded", "2 series", "1.2.826.0.1.9")),
    ("position in some slices only", lambda t: _series_case(t, unloaded={"overrides": {1: {"ImagePositionPatient": None}}})[0],
     ("case/unloaded/IM_", "has no ImagePositionPatient", "3 other slices")),
    ("multi-frame file", lambda t: _series_case(t, unloaded={"overrides": {0: {"NumberOfFrames": 4}}})[0],
     ("case/unloaded/IM_", "4 frames", "one file per slice")),
    ("two slices at one position", lambda t: _series_case(t, unloaded={"positions": (-5.0, 0.0, 0.0, 5.0)})[0],
     ("case/unloaded", "two slices at 0 mm", "one slice per position")),
    ("position in a gap of the series",
     lambda t: _series_case(t, "slice_position_mm = 2.5", unloaded={"positions": (-7.5, -2.5, 7.5, 12.5)})[0],
     ("case.toml", "between its slices at -2.5 and 7.5 mm")),
    ("chosen slice truncated", _truncated_chosen_slice, ("case/unloaded/IM_", "cannot be read as DICOM")),
    ("no image in the series folder", _only_non_images, ("case/loaded", "no DICOM image among its 2 files")),
    ("series folder beside a file", _with_competing_png, ("unloaded", "competes")),
]


@pytest.mark.parametrize("kind, make, texts", REFUSED, ids=[r[0] for r in REFUSED])
def test_refused_with_one_sentence_and_nothing_written(tmp_path, kind, make, texts):
    folder = make(tmp_path)
    before = _snapshot(tmp_path)
    with pytest.raises(CaseError) as raised:
        read_case(folder)
    message = str(raised.value)
    for text in texts:
        assert text in message, f"{text!r} not in {message!r}"
    assert "\n" not in message and message.endswith(".") and "; " in message, message
    assert _snapshot(tmp_path) == before


# --------------------------------------------------------------------------- the pipeline's start


def test_prepare_run_from_dicom_series_of_the_phantom(tmp_path):
    """The phantom's two slices, each in the middle of a 3-slice series whose other slices hold no leg."""
    import imageio.v3 as iio

    from orchestrator.phantom import write_case
    from orchestrator.run.setup import prepare_run

    png_case, _ = write_case(tmp_path / "png", labels=None)
    folder = tmp_path / "series"
    folder.mkdir()
    legs = {}
    for role in ("unloaded", "loaded"):
        legs[role] = iio.imread(png_case / f"{role}.png")
        background = [np.random.default_rng(seed).integers(0, 300, legs[role].shape).astype(np.uint16) for seed in (1, 2)]
        _write_series(folder / role, role, images=[background[0], legs[role], background[1]], positions=(-40.0, -35.0, -30.0),
                      spacing=(0.36, 0.36), shape=legs[role].shape)
    toml = [line for line in (png_case / "case.toml").read_text().splitlines() if not line.startswith("pixel_size_mm")]
    (folder / "case.toml").write_text("\n".join(toml) + "\n[images]\nslice_position_mm = -34.2\n")

    setup = prepare_run(folder, tmp_path / "run", n_elements=400, order=1)
    slope, intercept = RESCALE["unloaded"]
    np.testing.assert_array_equal(setup.case.unloaded, legs["unloaded"] * slope + intercept)
    assert setup.case.pixel_size_mm == pytest.approx((0.36, 0.36))
    assert len(setup.mesh.elements) > 100 and (tmp_path / "run" / "setup.json").is_file()
    chosen = setup.case.files["unloaded_slice"].name
    assert f"unloaded: DICOM series, slice {chosen} used" in setup.setup_lines()
