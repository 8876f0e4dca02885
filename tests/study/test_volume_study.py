"""A volume case's case.toml (orchestrator/study/volume_cases.py): heights, the tension along the leg, landmark lines,
the [model] tables passed to every slice, and the errors that name the fix."""

from __future__ import annotations

import numpy as np
import pytest
import tomllib

from orchestrator.case.folder import read_case
from orchestrator.core.errors import CaseError
from orchestrator.study.volume_cases import (
    _chosen_slices,
    is_volume_case,
    read_volume_case,
)

TOML = """\
[case]
name = "leg 7"

[garment]
tension_N_per_mm = { heights_mm = [300.0, 196.0], values = [0.14, 0.20] }
tension_rel_uncertainty = 0.08

[study]
heights_mm = [212.0, 204.0]
compression_heights_mm = { B = 204.0, C = 284.0 }

[landmarks]
deep_veins = [[54.0, 61.0, 196.0], [50.0, 65.0, 300.0]]
tibia_crest = [40.0, 20.0, 212.5]

[model]
element = "CPE6"
[model.fat]
law = "neo_hooke"
"""


def _volume_case(folder, text=TOML, volumes=("unloaded.nii.gz", "loaded.nii.gz")):
    folder.mkdir(exist_ok=True)
    (folder / "case.toml").write_text(text)
    for name in volumes:
        (folder / name).write_bytes(b"")
    return folder


def test_reads_heights_tension_profile_and_landmark_lines(tmp_path):
    case = read_volume_case(_volume_case(tmp_path / "leg"))
    assert is_volume_case(case.folder)
    assert case.name == "leg 7" and case.heights_mm == (204.0, 212.0)
    assert case.tension_at(196.0) == pytest.approx(0.20) and case.tension_at(248.0) == pytest.approx(0.17)
    assert case.tension_rel_uncertainty == 0.08
    with pytest.raises(CaseError, match="extend its heights_mm"):
        case.tension_at(310.0)
    at_248 = case.landmarks_at(248.0, half_spacing_mm=4.0)
    assert at_248 == {"deep_veins": pytest.approx((52.0, 63.0))}
    assert set(case.landmarks_at(212.0, half_spacing_mm=4.0)) == {"deep_veins", "tibia_crest"}
    model = tomllib.loads(case.model_toml)["model"]
    assert model == {"element": "CPE6", "fat": {"law": "neo_hooke"}}
    assert case.compression_heights_mm == {"B": 204.0, "C": 284.0}


def test_a_volume_case_given_to_identify_points_to_study(tmp_path):
    folder = _volume_case(tmp_path / "leg")
    with pytest.raises(CaseError, match="calfit study"):
        read_case(folder)


@pytest.mark.parametrize("change, message", [
    ("heights_mm = [212.0, 204.0]", "one of heights_mm and every_mm"),
    ("tension_N_per_mm = { heights_mm = [300.0, 196.0], values = [0.14, 0.20] }", "tension_N_per_mm"),
    ('deep_veins = [[54.0, 61.0, 196.0], [50.0, 65.0, 300.0]]', "landmark 'deep_veins'"),
    ('element = "CPE6"', "element"),
])
def test_errors_name_the_key_and_the_fix(tmp_path, change, message):
    replacement = {"heights_mm = [212.0, 204.0]": "",
                   "tension_N_per_mm = { heights_mm = [300.0, 196.0], values = [0.14, 0.20] }":
                       "tension_N_per_mm = { heights_mm = [300.0], values = [0.14] }",
                   'deep_veins = [[54.0, 61.0, 196.0], [50.0, 65.0, 300.0]]': 'deep_veins = [[54.0, 61.0]]',
                   'element = "CPE6"': 'element = "Q4"'}[change]
    folder = _volume_case(tmp_path / "leg", TOML.replace(change, replacement))
    with pytest.raises(CaseError, match=message) as error:
        read_volume_case(folder)
    assert "case.toml" in str(error.value)


def test_a_missing_volume_names_both_forms(tmp_path):
    folder = _volume_case(tmp_path / "leg", volumes=("unloaded.nii.gz",))
    with pytest.raises(CaseError, match=r"loaded/ \(a DICOM series\) or loaded.nii.gz"):
        read_volume_case(folder)


def test_sessions_in_two_formats_are_refused(tmp_path):
    folder = _volume_case(tmp_path / "leg", volumes=("unloaded.nii.gz",))
    (folder / "loaded").mkdir()
    with pytest.raises(CaseError, match="two formats"):
        read_volume_case(folder)


def test_heights_snap_to_the_nearest_slice_within_half_a_spacing(tmp_path):
    case = read_volume_case(_volume_case(tmp_path / "leg"))
    positions = np.arange(196.0, 301.0, 8.0)
    assert _chosen_slices(case, positions, 8.0) == [1, 2]
    off = read_volume_case(_volume_case(tmp_path / "off", TOML.replace("[212.0, 204.0]", "[212.0, 320.0]")))
    with pytest.raises(CaseError, match="no unloaded slice within half a spacing"):
        _chosen_slices(off, positions, 8.0)
    every = read_volume_case(_volume_case(tmp_path / "every", TOML.replace("heights_mm = [212.0, 204.0]",
                                                                           "every_mm = 16.0")))
    assert _chosen_slices(every, positions, 8.0) == [0, 2, 4, 6, 8, 10, 12]
    fine = read_volume_case(_volume_case(tmp_path / "fine", TOML.replace("heights_mm = [212.0, 204.0]",
                                                                         "every_mm = 4.0")))
    with pytest.raises(CaseError, match="finer than the slices"):
        _chosen_slices(fine, positions, 8.0)


def test_a_volume_is_cut_into_slice_cases_that_see_the_same_tissue(tmp_path):
    """Two sessions of the analytic leg of test_volume (the loaded one moved in 3D) cut at two heights: each slice
    case reads as a case, with its tension, its landmarks, the model, and a loaded slice whose bones superpose the
    unloaded ones; a second run reuses the slices, and other heights in the same folder are refused."""
    from test_volume import TRUTH, _render

    from orchestrator.case.volume import RigidMotion3D, write_nifti_volume
    from orchestrator.core.errors import RunFolderError
    from orchestrator.core.tissues import BONE
    from orchestrator.imaging.segment import segment_t1
    from orchestrator.study.volume_cases import slice_volume_case

    unloaded, loaded = _render(seed=0), _render(TRUTH, seed=1)
    heights = unloaded.slice_positions_mm[[4, 6]]
    folder = tmp_path / "leg"
    text = (TOML.replace("heights_mm = [212.0, 204.0]", f"heights_mm = [{heights[0]}, {heights[1]}]")
            .replace("[300.0, 196.0]", "[0.0, 44.0]")
            .replace("[[54.0, 61.0, 196.0], [50.0, 65.0, 300.0]]", "[[40.0, 50.0, 0.0], [44.0, 50.0, 44.0]]"))
    _volume_case(folder, text, volumes=())
    write_nifti_volume(folder / "unloaded.nii.gz", unloaded.voxels, unloaded.affine)
    write_nifti_volume(folder / "loaded.nii.gz", loaded.voxels, loaded.affine)
    lines = []
    slices, record = slice_volume_case(folder, tmp_path / "study", lines.append)
    assert [s.slice_index for s in slices] == [4, 6]
    probes = unloaded.slice_points_mm(5)[:, ::30, ::30].reshape(3, -1)
    found = RigidMotion3D.from_dict(record["motion"]).apply(probes)
    assert np.abs(found - TRUTH.apply(probes)).max() < 0.3
    for piece in slices:
        case = read_case(piece.folder)
        expected = np.interp(piece.height_mm, [0.0, 44.0], [0.14, 0.20])
        assert case.tension_N_per_mm == pytest.approx(expected)
        assert case.landmarks["deep_veins"] == pytest.approx((40.0 + piece.height_mm / 11.0, 50.0))
        assert case.model.element == "CPE6"
        bones = segment_t1(case.unloaded, case.pixel_size_mm) == BONE
        finite = np.isfinite(case.loaded)
        correlation = np.corrcoef(case.unloaded[bones & finite], case.loaded[bones & finite])[0, 1]
        assert correlation > 0.9, correlation
    again, _ = slice_volume_case(folder, tmp_path / "study", lines.append)
    assert [s.folder for s in again] == [s.folder for s in slices] and "reused" in lines[-1]
    (folder / "case.toml").write_text(text.replace(f"{heights[1]}]", f"{unloaded.slice_positions_mm[11]}]"))
    with pytest.raises(RunFolderError, match="other heights"):
        slice_volume_case(folder, tmp_path / "study")
    # the top slice: the leg slid 5 mm up between the sessions, so the loaded volume does not reach it
    lines.clear()
    slices, record = slice_volume_case(folder, tmp_path / "study-top", lines.append)
    assert [s.slice_index for s in slices] == [4] and record["left_out"][0]["height_mm"] == pytest.approx(44.0)
    assert any("left out" in line for line in lines)
    again, _ = slice_volume_case(folder, tmp_path / "study-top")
    assert [s.slice_index for s in again] == [4]


def test_the_skin_shift_between_slices_is_measured_in_pixels():
    """A leg whose outline grows by 1.5 px from one slice to the next (the analytic leg of test_volume, its
    radius scaled along the leg): the shift read from the segmented slices is that, within a third of a pixel."""
    from test_volume import _leg

    from orchestrator.case.volume import Volume, volume_affine
    from orchestrator.study.volume_cases import skin_shift_px

    pixel, spacing = 0.8, 4.0
    affine = volume_affine((pixel, pixel), spacing)
    grid = Volume(np.zeros((120, 120, 5)), affine)
    slices = []
    for k in range(5):
        x, y, z = grid.slice_points_mm(k)
        centre = np.array([48.0, 50.0])[:, None, None]
        scale = 1.0 + 1.5 * pixel * (k - 2) / 40.0     # the leg's radius is about 40 mm
        points = np.stack([x, y]) - centre
        slices.append(_leg(*(centre + points / scale), np.full_like(z, 22.0)))
    volume = Volume(np.stack(slices, axis=2), affine)
    assert skin_shift_px(volume, 2) == pytest.approx(1.5, abs=0.33)
