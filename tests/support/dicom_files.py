"""DICOM files for the tests, written with pydicom as a scanner writes them (explicit VR little endian, with the
file meta information): a dataset of a given storage class, and a grey 16-bit image in it."""

from __future__ import annotations

import numpy as np


def new_dataset(storage_class: str | None = None):
    """An empty dataset of `storage_class` (default: MR image storage) with its file meta information."""
    import pydicom
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = storage_class or MRImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    dataset = pydicom.Dataset()
    dataset.file_meta = meta
    return dataset


def put_grey_image(dataset, stored: np.ndarray, spacing_mm, rescale=("1", "0")) -> None:
    """Make the dataset an image: 16-bit unsigned grey pixels, PixelSpacing (row, column mm) and the rescale
    slope and intercept (decimal strings)."""
    dataset.SOPClassUID = dataset.file_meta.MediaStorageSOPClassUID
    dataset.SOPInstanceUID = dataset.file_meta.MediaStorageSOPInstanceUID
    dataset.Rows, dataset.Columns = stored.shape
    dataset.SamplesPerPixel = 1
    dataset.PhotometricInterpretation = "MONOCHROME2"
    dataset.BitsAllocated, dataset.BitsStored, dataset.HighBit, dataset.PixelRepresentation = 16, 16, 15, 0
    dataset.PixelSpacing = [str(spacing_mm[0]), str(spacing_mm[1])]
    dataset.RescaleSlope, dataset.RescaleIntercept = rescale
    dataset.PixelData = np.asarray(stored, np.uint16).tobytes()
