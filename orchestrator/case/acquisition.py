"""What an MR image's DICOM header says of its acquisition: the size and axis of the fat's chemical shift.

Fat and water precess at frequencies FAT_WATER_PPM apart (the main methylene resonance of fat lies 3.4-3.5 ppm from
water; Hamilton et al. 2011, NMR Biomed 24:784, Table 1). Along the readout, frequency encodes position at the
pixel bandwidth (Hz per pixel), so an image shows the fat's signal displaced along the readout by

    delta = FAT_WATER_PPM x 1e-6 x f0 / BW   pixels,

f0 the imaging frequency (ImagingFrequency, MHz; else the proton's Larmor frequency at MagneticFieldStrength) and BW
the PixelBandwidth (Hz per pixel): 1.4 pixels at 1.5 T and 160 Hz per pixel. The readout is the in-plane axis that
is not phase encoded (InPlanePhaseEncodingDirection: COL, phase encoded along the columns, reads out along the rows,
x; ROW reads out along y). The sign, which way along the readout the fat moves, depends on the readout gradient's
polarity, which no standard tag holds: the image tells it (`imaging.chemical_shift`). Every scanner writes these
tags; an anonymiser or a conversion to PNG may drop them, and then the size too is read from the image.
"""

from __future__ import annotations

from dataclasses import dataclass

FAT_WATER_PPM = 3.5
LARMOR_MHZ_PER_T = 42.577   # the proton's gyromagnetic ratio over 2 pi
READOUT_OF_PHASE_ENCODING = {"COL": "x", "ROW": "y"}
PHASE_ENCODING_OF_READOUT = {axis: phase for phase, axis in READOUT_OF_PHASE_ENCODING.items()}


@dataclass(frozen=True)
class Acquisition:
    """The header's sequence parameters that set the fat's chemical shift (module text); None where a tag is
    missing. pixel_size_mm: (row, column) as the file's PixelSpacing gives it."""

    imaging_frequency_MHz: float | None
    pixel_bandwidth_Hz: float | None
    phase_encoding: str | None
    pixel_size_mm: tuple[float, float] | None
    given_by: str = "the DICOM header"   # or "case.toml's [acquisition]"

    @property
    def fat_shift_px(self) -> float | None:
        """delta of the module text, pixels along the readout; None without a bandwidth and a frequency."""
        if not self.pixel_bandwidth_Hz or not self.imaging_frequency_MHz:
            return None
        return FAT_WATER_PPM * self.imaging_frequency_MHz / self.pixel_bandwidth_Hz

    @property
    def readout_axis(self) -> str | None:
        """'x' or 'y', the image axis the readout runs along; None when the header does not say."""
        return READOUT_OF_PHASE_ENCODING.get(self.phase_encoding or "")

    @property
    def fat_shift_mm(self) -> float | None:
        """delta in mm of the file's pixels along the readout (the mean of the two spacings when the readout is not
        given): a size that survives `resolution.working_resolution`'s coarsening."""
        shift = self.fat_shift_px
        if shift is None or self.pixel_size_mm is None:
            return None
        row_mm, column_mm = self.pixel_size_mm
        spacing = {"x": column_mm, "y": row_mm}.get(self.readout_axis or "", 0.5 * (row_mm + column_mm))
        return shift * spacing

    def sentence(self) -> str:
        """The header's numbers, as the setup lines quote them."""
        axis = f" along {self.readout_axis}" if self.readout_axis else ", readout axis not given"
        return (f"{self.fat_shift_px:.2f} px{axis} from {self.given_by} (a pixel bandwidth of "
                f"{self.pixel_bandwidth_Hz:g} Hz/px at {self.imaging_frequency_MHz:.4g} MHz, fat {FAT_WATER_PPM:g} ppm "
                "from water)")


def acquisition_of(dataset) -> Acquisition | None:
    """The Acquisition a pydicom dataset's header gives; None when it gives neither a bandwidth nor a frequency (a
    tag that is there but not a positive number counts as missing: the size is then read from the image)."""
    bandwidth = _positive(dataset, "PixelBandwidth")
    frequency = _positive(dataset, "ImagingFrequency")
    if frequency is None:
        field = _positive(dataset, "MagneticFieldStrength")
        frequency = None if field is None else LARMOR_MHZ_PER_T * field
    if bandwidth is None and frequency is None:
        return None
    phase = str(dataset.get("InPlanePhaseEncodingDirection", "") or "").strip().upper() or None
    spacing = dataset.get("PixelSpacing")
    try:
        size = (float(spacing[0]), float(spacing[1])) if spacing is not None and len(spacing) == 2 else None
    except (TypeError, ValueError):
        size = None
    return Acquisition(frequency, bandwidth, phase if phase in READOUT_OF_PHASE_ENCODING else None, size)


def _positive(dataset, keyword: str) -> float | None:
    value = dataset.get(keyword)
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if number > 0 else None
