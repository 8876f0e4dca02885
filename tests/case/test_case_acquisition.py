"""The sequence's parameters that set the fat's chemical shift (`case.acquisition`): read from a DICOM header as a
scanner writes it, or from case.toml's [acquisition] for images without one, and refused with the fix when half
given."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.case.folder import read_case
from orchestrator.case.acquisition import FAT_WATER_PPM, LARMOR_MHZ_PER_T, acquisition_of
from orchestrator.core.errors import CaseError
from orchestrator.phantom.kspace3d.dicom import new_identities, write_dicom_slice

pydicom = pytest.importorskip("pydicom")


def _slice(path, readout="x", shift_px=1.4):
    identity = new_identities(("unloaded",), "P")[0]
    image = (np.indices((40, 40)).sum(axis=0) * 20).astype(np.uint16)
    return write_dicom_slice(path, image, pixel_size_mm=(0.4, 0.5), height_mm=70.0, slice_thickness_mm=4.0,
                             identity=identity, chemical_shift_px=shift_px, readout=readout)


@pytest.mark.parametrize("readout, spacing", [("x", 0.5), ("y", 0.4)])
def test_the_header_gives_the_shift_s_size_and_the_readout(tmp_path, readout, spacing):
    dataset = pydicom.dcmread(_slice(tmp_path / "a.dcm", readout, 1.7))
    acquisition = acquisition_of(dataset)
    assert acquisition.readout_axis == readout
    # 3.5 ppm of 63.87 MHz over the bandwidth the file holds (written to two decimals)
    expected = FAT_WATER_PPM * 1.5 * LARMOR_MHZ_PER_T / float(dataset.PixelBandwidth)
    assert acquisition.fat_shift_px == pytest.approx(expected) and acquisition.fat_shift_px == pytest.approx(1.7, 1e-3)
    assert acquisition.fat_shift_mm == pytest.approx(expected * spacing)


def test_a_header_without_the_sequence_s_tags_gives_no_size(tmp_path):
    dataset = pydicom.dcmread(_slice(tmp_path / "a.dcm"))
    for tag in ("PixelBandwidth", "ImagingFrequency", "MagneticFieldStrength"):
        del dataset[tag]
    assert acquisition_of(dataset) is None
    dataset = pydicom.dcmread(_slice(tmp_path / "a.dcm"))
    del dataset["ImagingFrequency"]           # the field strength stands in for the frequency
    assert acquisition_of(dataset).fat_shift_px == pytest.approx(1.4, 1e-3)
    dataset.PixelBandwidth = "0"              # not a bandwidth: no size
    assert acquisition_of(dataset).fat_shift_px is None


def _png_case(folder, acquisition_toml: str):
    from orchestrator.case.folder import write_case_folder

    rng = np.random.default_rng(0)
    image = rng.uniform(100, 200, (64, 64))
    write_case_folder(folder, name="c", unloaded=image, loaded=image, pixel_size_mm=(0.4, 0.4),
                      tension_N_per_mm=0.16)
    with open(folder / "case.toml", "a") as toml:
        toml.write(acquisition_toml)
    return folder


def test_case_toml_gives_it_for_images_without_a_header(tmp_path):
    case = read_case(_png_case(tmp_path / "c", '\n[acquisition]\npixel_bandwidth_Hz = 160.0\nfield_strength_T = 1.5\n'
                                                'readout = "y"\n'))
    assert case.acquisition.readout_axis == "y"
    assert case.acquisition.fat_shift_px == pytest.approx(FAT_WATER_PPM * 1.5 * LARMOR_MHZ_PER_T / 160.0)
    assert case.acquisition.fat_shift_mm == pytest.approx(case.acquisition.fat_shift_px * 0.4)
    assert "from case.toml's [acquisition]" in case.acquisition.sentence()
    assert read_case(_png_case(tmp_path / "d", "")).acquisition is None


def test_a_bandwidth_without_a_frequency_is_refused_with_the_fix(tmp_path):
    folder = _png_case(tmp_path / "c", "\n[acquisition]\npixel_bandwidth_Hz = 160.0\n")
    with pytest.raises(CaseError) as refused:
        read_case(folder)
    message = str(refused.value)
    assert "case.toml" in message and "[acquisition]" in message and "field_strength_T" in message


def test_a_dicom_case_carries_its_header_s_acquisition(tmp_path):
    folder = tmp_path / "case"
    folder.mkdir()
    _slice(folder / "unloaded.dcm")
    _slice(folder / "loaded.dcm")
    (folder / "case.toml").write_text("[garment]\ntension_N_per_mm = 0.16\n")
    case = read_case(folder)
    assert case.acquisition.readout_axis == "x" and case.acquisition.fat_shift_px == pytest.approx(1.4, 1e-3)


def test_a_slice_case_cut_from_a_series_keeps_its_acquisition(tmp_path):
    """A volume study writes each slice case's images as arrays: the series' header goes into its [acquisition]."""
    from orchestrator.case.folder import write_case_folder

    header = acquisition_of(pydicom.dcmread(_slice(tmp_path / "a.dcm", "y", 1.6)))
    image = np.random.default_rng(1).uniform(100, 200, (64, 64))
    folder = write_case_folder(tmp_path / "slice", name="s", unloaded=image, loaded=image, pixel_size_mm=(0.4, 0.5),
                               tension_N_per_mm=0.16, images_as="npy", acquisition=header)
    again = read_case(folder).acquisition
    assert again.readout_axis == "y" and again.fat_shift_px == pytest.approx(header.fat_shift_px)
    assert again.fat_shift_mm == pytest.approx(header.fat_shift_mm)
