"""Case folder reading and writing (docs/design.md, "The case folder").

A good folder reads back what was written, in every image format; every bad
folder of the table raises one CaseError, a single sentence naming the file,
and leaves the folder untouched.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from dicom_files import new_dataset, put_grey_image

from orchestrator.case.folder import DisplacementPoints, read_case, write_case_folder
from orchestrator.core.errors import CaseError

SHAPE = (48, 64)
PIXEL = (0.5, 0.4)


def _images(seed: int = 0):
    rng = np.random.default_rng(seed)
    unloaded = rng.integers(100, 60000, SHAPE).astype(np.uint16)
    loaded = rng.integers(100, 60000, SHAPE).astype(np.uint16)
    labels = np.zeros(SHAPE, np.uint8)
    labels[8:40, 8:56] = 1
    labels[14:34, 14:50] = 2
    labels[20:26, 20:28] = 3
    return unloaded, loaded, labels


@pytest.fixture
def good_case(tmp_path):
    unloaded, loaded, labels = _images()
    points = DisplacementPoints(np.array([[10.0, 8.0], [20.5, 12.25]]), np.array([[0.1, -0.2], [0.0, 0.3]]), np.array([0.05, 0.07]))
    return write_case_folder(tmp_path / "case", name="volunteer-01", unloaded=unloaded, loaded=loaded, pixel_size_mm=PIXEL,
                             tension_N_per_mm=0.16, labels=labels, points=points,
                             landmarks={"hypodermis_tibia": (5.0, 6.0), "deep_veins": (12.0, 10.0)})


def test_good_case_reads_back_what_was_written(good_case):
    unloaded, loaded, labels = _images()
    case = read_case(good_case)
    assert case.name == "volunteer-01"
    assert case.pixel_size_mm == PIXEL
    assert case.shape == SHAPE
    assert case.extent_mm == pytest.approx((SHAPE[1] * PIXEL[1], SHAPE[0] * PIXEL[0]))
    np.testing.assert_array_equal(case.unloaded, unloaded)
    np.testing.assert_array_equal(case.loaded, loaded)
    np.testing.assert_array_equal(case.labels, labels)
    np.testing.assert_allclose(case.points.position_mm, [[10.0, 8.0], [20.5, 12.25]])
    np.testing.assert_allclose(case.points.displacement_mm, [[0.1, -0.2], [0.0, 0.3]])
    np.testing.assert_allclose(case.points.sigma_mm, [0.05, 0.07])
    assert case.landmarks == {"hypodermis_tibia": (5.0, 6.0), "deep_veins": (12.0, 10.0)}
    assert case.tension_N_per_mm == 0.16 and case.tension_rel_uncertainty == 0.10


def test_writer_refuses_to_overwrite_and_leaves_no_staging(good_case):
    before = sorted(os.listdir(good_case.parent))
    unloaded, loaded, _ = _images(1)
    with pytest.raises(FileExistsError):
        write_case_folder(good_case, name="x", unloaded=unloaded, loaded=loaded, pixel_size_mm=PIXEL, tension_N_per_mm=0.1)
    assert sorted(os.listdir(good_case.parent)) == before
    np.testing.assert_array_equal(read_case(good_case).loaded, _images()[1])


def test_writer_failure_leaves_nothing(tmp_path):
    unloaded, loaded, _ = _images()
    with pytest.raises(ValueError):
        write_case_folder(tmp_path / "case", name="x", unloaded=unloaded, loaded=loaded[:, :10], pixel_size_mm=PIXEL,
                          tension_N_per_mm=0.1)
    assert os.listdir(tmp_path) == []


def _replace_images(folder, suffix_writer):
    """Swap unloaded.png/loaded.png for files written by suffix_writer(path_stem, pixels)."""
    case = read_case(folder)
    for stem, pixels in (("unloaded", case.unloaded), ("loaded", case.loaded)):
        (folder / f"{stem}.png").unlink()
        suffix_writer(folder / stem, pixels)


def _write_dicom(stem, pixels, spacing=(0.5, 0.4)):
    dataset = new_dataset()
    put_grey_image(dataset, pixels, spacing, rescale=("2", "-10"))
    dataset.save_as(f"{stem}.dcm", enforce_file_format=True)


def _write_nifti(stem, pixels, zooms=(0.5, 0.4), slices=1):
    import nibabel

    volume = np.repeat(np.asarray(pixels, np.float32)[:, :, None], slices, axis=2)
    nibabel.save(nibabel.Nifti1Image(volume, np.diag([zooms[0], zooms[1], 5.0, 1.0])), f"{stem}.nii.gz")


def _write_tiff(stem, pixels):
    import tifffile

    tifffile.imwrite(f"{stem}.tif", np.asarray(pixels, np.uint16))


@pytest.mark.parametrize("writer, expected", [
    (_write_tiff, lambda p: p),
    (lambda stem, p: np.save(f"{stem}.npy", p.astype(np.float32)), lambda p: p),
    (_write_dicom, lambda p: 2 * p - 10),
    (_write_nifti, lambda p: p),
])
def test_every_image_format_reads(good_case, writer, expected):
    original = read_case(good_case)
    _replace_images(good_case, writer)
    case = read_case(good_case)
    np.testing.assert_allclose(case.unloaded, expected(original.unloaded))
    np.testing.assert_allclose(case.loaded, expected(original.loaded))
    assert case.pixel_size_mm == pytest.approx(PIXEL)


def test_dicom_spacing_is_used_when_case_toml_has_none(good_case):
    _replace_images(good_case, lambda stem, p: _write_dicom(stem, p, spacing=(0.7, 0.6)))
    toml = good_case / "case.toml"
    toml.write_text("\n".join(l for l in toml.read_text().splitlines() if not l.startswith("pixel_size_mm")) + "\n")
    assert read_case(good_case).pixel_size_mm == pytest.approx((0.7, 0.6))


# Each entry: (what is broken, how to break the good folder, the file the message must name).
def _edit_toml(old, new):
    def edit(folder):
        path = folder / "case.toml"
        text = path.read_text()
        assert old in text
        path.write_text(text.replace(old, new))
    return edit


def _write(name, content):
    def edit(folder):
        (folder / name).write_bytes(content if isinstance(content, bytes) else content.encode())
    return edit


def _png(name, pixels):
    def edit(folder):
        from skimage import io

        io.imsave(folder / name, pixels, check_contrast=False)
    return edit


def _labels_without(label):
    labels = _images()[2].copy()
    labels[labels == label] = 1 if label != 1 else 2
    return labels


BAD_CASES = [
    ("missing case.toml", lambda f: (f / "case.toml").unlink(), "case.toml"),
    ("toml syntax error", _write("case.toml", "[case\nname = 'x'\n"), "case.toml"),
    ("pixel size missing", _edit_toml("pixel_size_mm = [0.5, 0.4]  # row, column", ""), "case.toml"),
    ("pixel size negative", _edit_toml("[0.5, 0.4]", "[0.5, -0.4]"), "case.toml"),
    ("unknown key (typo)", _edit_toml("pixel_size_mm", "pixel_size"), "case.toml"),
    ("garment tension missing", _edit_toml("tension_N_per_mm = 0.16", ""), "case.toml"),
    ("landmark outside the image", _edit_toml("[5.0, 6.0]", "[500.0, 6.0]"), "case.toml"),
    ("loaded image missing", lambda f: (f / "loaded.png").unlink(), "loaded.png"),
    ("unreadable image", _write("loaded.png", b"\x89PNG\r\n\x1a\nthis is not a png"), "loaded.png"),
    ("shapes differ", _png("loaded.png", np.ones((40, 64), np.uint16)), "loaded.png"),
    ("colour image", _png("unloaded.png", np.dstack([np.full(SHAPE, 9, np.uint8), np.zeros(SHAPE, np.uint8),
                                                     np.zeros(SHAPE, np.uint8)])), "unloaded.png"),
    ("two unloaded images", lambda f: np.save(f / "unloaded.npy", np.ones(SHAPE)), "unloaded"),
    ("NaN pixels", lambda f: ((f / "unloaded.png").unlink(), np.save(f / "unloaded.npy", np.full(SHAPE, np.nan))), "unloaded.npy"),
    ("labels do not match the image", _png("labels.png", np.ones((20, 20), np.uint8)), "labels.png"),
    ("labels without muscle", _png("labels.png", _labels_without(2)), "labels.png"),
    ("labels without bone", _png("labels.png", _labels_without(3)), "labels.png"),
    ("points.csv bad header", _write("points.csv", "x,y,ux,uy\n1,2,3,4\n"), "points.csv"),
    ("points.csv not a number", _write("points.csv", "x_mm,y_mm,ux_mm,uy_mm\n1,2,abc,4\n"), "points.csv"),
    ("points.csv outside the image", _write("points.csv", "x_mm,y_mm,ux_mm,uy_mm\n1,2000,0,0\n"), "points.csv"),
    ("points.csv zero sigma", _write("points.csv", "x_mm,y_mm,ux_mm,uy_mm,sigma_mm\n1,2,0,0,0\n"), "points.csv"),
    ("DICOM spacing contradicts case.toml",
     lambda f: _replace_images(f, lambda stem, p: _write_dicom(stem, p, spacing=(0.9, 0.9))), "unloaded.dcm"),
    ("NIfTI holds several slices",
     lambda f: ((f / "loaded.png").unlink(), _write_nifti(f / "loaded", _images()[1], slices=3)), "loaded.nii.gz"),
]


def _snapshot(folder):
    return {p.name: (p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("kind, breaker, named_file", BAD_CASES, ids=[case[0] for case in BAD_CASES])
def test_bad_case_gives_one_clear_error_and_writes_nothing(good_case, kind, breaker, named_file):
    breaker(good_case)
    before = _snapshot(good_case)
    with pytest.raises(CaseError) as raised:
        read_case(good_case)
    message = str(raised.value)
    assert named_file in message, message
    assert "\n" not in message and message.endswith(".") and message.count("; ") >= 1, message
    assert _snapshot(good_case) == before
    assert sorted(p.name for p in good_case.parent.iterdir()) == ["case"]


def test_bad_case_table_covers_at_least_ten_kinds():
    assert len({named for _, _, named in BAD_CASES}) >= 8 and len(BAD_CASES) >= 10


def test_not_a_folder_is_a_case_error(tmp_path):
    with pytest.raises(CaseError, match="not a folder"):
        read_case(tmp_path / "nowhere")


def test_points_without_sigma_and_default_uncertainty(good_case):
    (good_case / "points.csv").write_text("x_mm,y_mm,ux_mm,uy_mm\n1.5,2.5,0.1,0.2\n")
    case = read_case(good_case)
    assert case.points.sigma_mm is None and len(case.points) == 1
