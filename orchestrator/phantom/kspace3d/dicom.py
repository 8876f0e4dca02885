"""DICOM files of the k-space phantom's images, with the geometry a scanner writes (pydicom, explicit VR little
endian, file meta information).

One file per slice: MR image storage, 16-bit unsigned grey pixels, PixelSpacing (row, column mm),
ImageOrientationPatient (1, 0, 0, 0, 1, 0: rows along +x, columns along +y, an axial slice), ImagePositionPatient
of the first pixel's centre, SliceThickness, SliceLocation, and for a series the SpacingBetweenSlices, one
SeriesInstanceUID and a FrameOfReferenceUID shared by the two sessions' series (the same scanner frame). The
patient frame is the image frame less half a pixel (as `phantom.volume` places a volume's voxels): the pixel of
row i and column j, at ((j + 1/2) dx, (i + 1/2) dy) in the image frame, is at (j dx, i dy, z) in the patient frame.
The sequence's parameters (field strength, pixel bandwidth from the chemical shift, the phase encoding across the
readout) are written as a 1.5 T T1 TSE would have them (`case.acquisition` reads them back).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...case.acquisition import FAT_WATER_PPM, LARMOR_MHZ_PER_T, PHASE_ENCODING_OF_READOUT


@dataclass(frozen=True)
class SeriesIdentity:
    """The UIDs and names shared by the files of a series (and, for the frame of reference, by both sessions)."""

    study_uid: str
    series_uid: str
    frame_uid: str
    series_number: int
    description: str
    patient_id: str = "CALFIT-KSPACE"


def new_identities(descriptions: tuple[str, ...], patient_id: str) -> list[SeriesIdentity]:
    """One identity per series, all of one study and one frame of reference."""
    from pydicom.uid import generate_uid

    study, frame = generate_uid(), generate_uid()
    return [SeriesIdentity(study, generate_uid(), frame, number + 1, description, patient_id)
            for number, description in enumerate(descriptions)]


def write_dicom_slice(path: Path, stored: np.ndarray, *, pixel_size_mm: tuple[float, float], height_mm: float,
                      slice_thickness_mm: float, identity: SeriesIdentity, instance: int = 1,
                      spacing_mm: float | None = None, field_strength_T: float = 1.5,
                      chemical_shift_px: float = 1.4, readout: str = "x") -> Path:
    """Write one slice (uint16 pixels) with its geometry tags (module text)."""
    import pydicom
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage, generate_uid

    if stored.dtype != np.uint16:
        raise ValueError(f"a DICOM slice is written from uint16 pixels, not {stored.dtype}")
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = MRImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = pydicom.Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = MRImageStorage, meta.MediaStorageSOPInstanceUID
    ds.Modality, ds.PatientID, ds.PatientName = "MR", identity.patient_id, identity.patient_id
    ds.StudyInstanceUID, ds.SeriesInstanceUID = identity.study_uid, identity.series_uid
    ds.FrameOfReferenceUID = identity.frame_uid
    ds.SeriesNumber, ds.InstanceNumber = identity.series_number, int(instance)
    ds.SeriesDescription = identity.description
    ds.Rows, ds.Columns = stored.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelSpacing = [f"{pixel_size_mm[0]:.6g}", f"{pixel_size_mm[1]:.6g}"]
    ds.ImageOrientationPatient = ["1", "0", "0", "0", "1", "0"]
    ds.ImagePositionPatient = ["0", "0", f"{height_mm:.6g}"]
    ds.SliceLocation = f"{height_mm:.6g}"
    ds.SliceThickness = f"{slice_thickness_mm:.6g}"
    if spacing_mm is not None:
        ds.SpacingBetweenSlices = f"{spacing_mm:.6g}"
    ds.RescaleSlope, ds.RescaleIntercept = "1", "0"
    frequency = LARMOR_MHZ_PER_T * field_strength_T
    ds.MagneticFieldStrength = f"{field_strength_T:g}"
    ds.ImagingFrequency = f"{frequency:.4f}"
    ds.PixelBandwidth = f"{FAT_WATER_PPM * frequency / chemical_shift_px:.2f}"   # Hz per pixel: the fat's shift
    ds.InPlanePhaseEncodingDirection = PHASE_ENCODING_OF_READOUT[readout]
    ds.ScanningSequence, ds.SequenceVariant, ds.MRAcquisitionType = "SE", "SK", "2D"
    ds.RepetitionTime, ds.EchoTime, ds.EchoTrainLength = "550", "12", 3
    ds.PixelData = np.ascontiguousarray(stored).tobytes()
    path = Path(path)
    ds.save_as(path, enforce_file_format=True)
    return path
