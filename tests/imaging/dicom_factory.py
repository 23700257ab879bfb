"""Write tiny, valid CT DICOM series for the imaging tests.

Every pixel holds ``pattern_hu(p) = round(x + 2y + 3z)`` of its own LPS position p,
so a loaded volume can be checked voxel by voxel through its affine. Geometry
follows DICOM: pixel (j, i) of a slice lies at ``IPP + i*dc*r + j*dr*c`` with
``r = IOP[:3]``, ``c = IOP[3:]``, ``PixelSpacing = (dr, dc)``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence as DicomSequence
from pydicom.uid import (
    CTImageStorage,
    EnhancedCTImageStorage,
    ExplicitVRLittleEndian,
    generate_uid,
)

AXIAL = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)
CORONAL = (1.0, 0.0, 0.0, 0.0, 0.0, -1.0)
PATIENT_NAME = "Secret^Patient"
PATIENT_ID = "PID-424242"
SCAN_ORIGIN_S = 10 * 3600 + 15 * 60  # 10:15:00 on the AcquisitionTime clock
SLICE_DT_S = 0.25


def pattern_hu(points) -> np.ndarray:
    """The analytic image: round(x + 2y + 3z) of LPS points (..., 3)."""
    p = np.asarray(points, dtype=np.float64)
    return np.round(p[..., 0] + 2.0 * p[..., 1] + 3.0 * p[..., 2])


def _ds(values, decimals=6):
    return [float(round(float(v), decimals)) for v in values]


def slice_positions(n_slices, *, origin=(-16.0, -16.0, -20.0), iop=AXIAL, spacing_mm=2.0,
                    shear_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(n, 3) IPPs of a stack: origin + k*spacing*normal + k*shear."""
    v = np.asarray(iop, dtype=np.float64)
    n = np.cross(v[:3], v[3:])
    k = np.arange(n_slices)[:, None]
    return np.asarray(origin) + k * spacing_mm * n + k * np.asarray(shear_mm)


def slice_pixels(ipp, iop, rows, cols, pixel_spacing) -> np.ndarray:
    """(rows, cols, 3) LPS positions of the pixels of one slice."""
    v = np.asarray(iop, dtype=np.float64)
    dr, dc = pixel_spacing
    j, i = np.mgrid[0:rows, 0:cols]
    return (np.asarray(ipp)[None, None, :] + i[..., None] * dc * v[:3]
            + j[..., None] * dr * v[3:])


def _base(sop_class, *, series_uid, study_uid, for_uid, series_number, description,
          modality="CT") -> Dataset:
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = sop_class
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = generate_uid()
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.PatientName = PATIENT_NAME
    ds.PatientID = PATIENT_ID
    ds.PatientBirthDate = "19700101"
    ds.StudyInstanceUID = study_uid
    ds.SeriesInstanceUID = series_uid
    ds.FrameOfReferenceUID = for_uid
    ds.SeriesNumber = series_number
    ds.SeriesDescription = description
    ds.Modality = modality
    ds.Manufacturer = "GE MEDICAL SYSTEMS"
    ds.ManufacturerModelName = "LightSpeed VCT"
    ds.StudyDate = "20240101"
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    return ds


def _tm(seconds: float) -> str:
    hh = int(seconds // 3600)
    mm = int(seconds % 3600 // 60)
    ss = seconds - hh * 3600 - mm * 60
    return f"{hh:02d}{mm:02d}{ss:09.6f}"


def write_ct_series(
    folder,
    *,
    n_slices: int = 20,
    rows: int = 32,
    cols: int = 32,
    pixel_spacing=(1.0, 1.0),
    iop=AXIAL,
    positions: Sequence | None = None,
    spacing_mm: float = 2.0,
    origin=(-16.0, -16.0, -20.0),
    shear_mm=(0.0, 0.0, 0.0),
    skip: Sequence[int] = (),
    names: str = "ordered",
    seed: int = 0,
    reverse_instance: bool = False,
    series_uid: str | None = None,
    study_uid: str | None = None,
    for_uid: str | None = None,
    series_number: int = 2,
    description: str = "Cardiac 0.625 mm",
    image_type=("ORIGINAL", "PRIMARY", "AXIAL"),
    rescale: tuple[float, float] | None = (1.0, -1024.0),
    transfer_syntax: str = ExplicitVRLittleEndian,
    slice_thickness: float | None = None,
    ge_private: str | None = "DS",
    extra: Callable[[Dataset, int], None] | None = None,
) -> list[Path]:
    """Write a single-frame CT series; returns the files in slice order.

    ``names``: "ordered" (slice_000.dcm ...), "shuffled" (random names in random
    sub-folders, seeded). ``ge_private``: "DS" writes GE Mid Scan Time / RpeakTimeStamps
    with their real VRs, "UN" as raw bytes, None not at all. ``rescale=None`` omits
    RescaleSlope/Intercept and stores HU directly as signed values.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    series_uid = series_uid or generate_uid()
    study_uid = study_uid or generate_uid()
    for_uid = for_uid or generate_uid()
    iop = tuple(_ds(iop))
    if positions is None:
        positions = slice_positions(n_slices, origin=origin, iop=iop, spacing_mm=spacing_mm,
                                    shear_mm=shear_mm)
    positions = [tuple(_ds(p)) for p in positions]
    n_total = len(positions)
    rpeaks = tuple(float(v) for v in np.arange(-1000.0, 12000.0, 850.0))
    written = []
    for k, ipp in enumerate(positions):
        if k in skip:
            continue
        ds = _base(CTImageStorage, series_uid=series_uid, study_uid=study_uid,
                   for_uid=for_uid, series_number=series_number, description=description)
        ds.ImageType = list(image_type)
        ds.InstanceNumber = (n_total - k) if reverse_instance else (k + 1)
        ds.ImagePositionPatient = list(ipp)
        ds.ImageOrientationPatient = list(iop)
        ds.PixelSpacing = list(pixel_spacing)
        ds.SliceThickness = spacing_mm if slice_thickness is None else slice_thickness
        ds.Rows, ds.Columns = rows, cols
        mid_scan = 0.5 + k * SLICE_DT_S
        ds.AcquisitionTime = _tm(SCAN_ORIGIN_S + mid_scan)
        ds.ContentTime = _tm(SCAN_ORIGIN_S + 100.0)
        hu = pattern_hu(slice_pixels(ipp, iop, rows, cols, pixel_spacing))
        if rescale is None:
            ds.PixelRepresentation = 1
            stored = hu.astype(np.int16)
        else:
            slope, intercept = rescale
            ds.RescaleSlope = slope
            ds.RescaleIntercept = intercept
            ds.RescaleType = "HU"
            ds.PixelRepresentation = 0
            stored = np.round((hu - intercept) / slope).astype(np.uint16)
        ds.PixelData = stored.tobytes()
        if ge_private:
            acq = ds.private_block(0x0019, "GEMS_ACQU_01", create=True)
            card = ds.private_block(0x0049, "GEMS_CT_CARDIAC_001", create=True)
            if ge_private == "DS":
                acq.add_new(0x24, "DS", f"{mid_scan:.6f}")
                card.add_new(0x0C, "FD", list(rpeaks))
            else:
                acq.add_new(0x24, "UN", f"{mid_scan:.6f}".encode("ascii"))
                card.add_new(0x0C, "UN", np.asarray(rpeaks, "<f8").tobytes())
        if extra is not None:
            extra(ds, k)
        if transfer_syntax != ExplicitVRLittleEndian:
            ds.compress(transfer_syntax)
        if names == "shuffled":
            sub = folder / f"d{rng.integers(0, 3)}"
            sub.mkdir(exist_ok=True)
            path = sub / f"{rng.integers(0, 1 << 40):x}"
        else:
            path = folder / f"slice_{k:03d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        written.append(path)
    return written


def write_enhanced_ct(
    path,
    *,
    n_slices: int = 20,
    rows: int = 32,
    cols: int = 32,
    pixel_spacing=(1.0, 1.0),
    iop=AXIAL,
    spacing_mm: float = 2.0,
    origin=(-16.0, -16.0, -20.0),
    rescale=(1.0, -1024.0),
    frame_order: Sequence[int] | None = None,
    cardiac_percent: float = 70.0,
    series_uid: str | None = None,
) -> Path:
    """Write one Enhanced CT multi-frame file with the same content as write_ct_series.

    Orientation, pixel measures and rescale go in the shared functional groups; plane
    position, frame content (FrameAcquisitionDateTime) and cardiac synchronisation
    per frame. ``frame_order`` permutes the frames in the file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iop = tuple(_ds(iop))
    positions = [tuple(_ds(p)) for p in slice_positions(
        n_slices, origin=origin, iop=iop, spacing_mm=spacing_mm)]
    order = list(range(n_slices)) if frame_order is None else list(frame_order)
    ds = _base(EnhancedCTImageStorage, series_uid=series_uid or generate_uid(),
               study_uid=generate_uid(), for_uid=generate_uid(), series_number=3,
               description="Enhanced cardiac")
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL", "NONE"]
    ds.InstanceNumber = 1
    ds.Rows, ds.Columns = rows, cols
    ds.NumberOfFrames = n_slices
    ds.PixelRepresentation = 0
    ds.AcquisitionDateTime = "20240101" + _tm(SCAN_ORIGIN_S)
    shared = Dataset()
    measures = Dataset()
    measures.PixelSpacing = list(pixel_spacing)
    measures.SliceThickness = spacing_mm
    orient = Dataset()
    orient.ImageOrientationPatient = list(iop)
    transform = Dataset()
    transform.RescaleSlope, transform.RescaleIntercept = rescale
    transform.RescaleType = "HU"
    shared.PixelMeasuresSequence = DicomSequence([measures])
    shared.PlaneOrientationSequence = DicomSequence([orient])
    shared.PixelValueTransformationSequence = DicomSequence([transform])
    ds.SharedFunctionalGroupsSequence = DicomSequence([shared])
    per_frame, pixels = [], []
    for k in order:
        item = Dataset()
        pos = Dataset()
        pos.ImagePositionPatient = list(positions[k])
        content = Dataset()
        content.FrameAcquisitionDateTime = "20240101" + _tm(SCAN_ORIGIN_S + 0.5 + k * SLICE_DT_S)
        content.FrameAcquisitionNumber = 1
        cardiac = Dataset()
        cardiac.NominalPercentageOfCardiacPhase = cardiac_percent
        cardiac.NominalCardiacTriggerDelayTime = 600.0
        cardiac.RRIntervalTimeNominal = 850.0
        item.PlanePositionSequence = DicomSequence([pos])
        item.FrameContentSequence = DicomSequence([content])
        item.CardiacSynchronizationSequence = DicomSequence([cardiac])
        per_frame.append(item)
        hu = pattern_hu(slice_pixels(positions[k], iop, rows, cols, pixel_spacing))
        pixels.append(np.round((hu - rescale[1]) / rescale[0]).astype(np.uint16))
    ds.PerFrameFunctionalGroupsSequence = DicomSequence(per_frame)
    ds.PixelData = np.stack(pixels).tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path


def truncate(path, n_bytes: int) -> None:
    """Cut the last `n_bytes` off a file."""
    data = Path(path).read_bytes()
    Path(path).write_bytes(data[: len(data) - n_bytes])


def recompress(path, transfer_syntax) -> None:
    """Re-encode a file in place with another transfer syntax."""
    ds = pydicom.dcmread(path)
    ds = copy.deepcopy(ds)
    ds.compress(transfer_syntax)
    ds.save_as(path, enforce_file_format=True)
