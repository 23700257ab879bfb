"""DICOM datasets of the phantom's gated CT study (pydicom).

Two kinds of instance, written by :func:`heartreg.phantom.ct.write_ct_study`:

- CT Image Storage, one per slice, emulating a GE LightSpeed VCT prospectively
  gated ("step-and-shoot") cardiac series: geometry tags, sub-second
  (0008,0032) *AcquisitionTime* / (0008,0033) *ContentTime*, (0018,1060)
  *Trigger Time*, and the GE private tags of docs/CONTRACTS.md:
  (0019,xx24) *Mid Scan Time* in block ``GEMS_ACQU_01`` (DS, s since the scan
  origin) and (0049,xx0C) *RpeakTimeStamps* in block ``GEMS_CT_CARDIAC_001``
  (FD, VM 1-n, ms since the scan origin).
- General ECG Waveform Storage, one lead II channel, int16 samples with
  (003A,0210) *Channel Sensitivity* in mV per count, so that
  ``ds.waveform_array(0)`` returns mV.

Stored pixel values are signed 16 bit (PixelRepresentation 1) with
RescaleSlope 1 and RescaleIntercept -1024: ``HU = stored - 1024``.

Nothing here identifies a person: PatientName ``PHANTOM^HEARTREG``, PatientID
``PHANTOM-<seed>``, no birth date, a fixed synthetic date (20000101).  No
wall-clock time is used anywhere; UIDs are derived from the seed.
"""

from __future__ import annotations

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

__all__ = [
    "CT_IMAGE_STORAGE",
    "ECG_WAVEFORM_STORAGE",
    "STUDY_DATE",
    "RESCALE_INTERCEPT",
    "GE_ACQU_CREATOR",
    "GE_CARDIAC_CREATOR",
    "derive_uid",
    "format_tm",
    "format_ds",
    "ct_slice_dataset",
    "ecg_dataset",
]

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
ECG_WAVEFORM_STORAGE = "1.2.840.10008.5.1.4.1.1.9.1.2"
STUDY_DATE = "20000101"
RESCALE_INTERCEPT = -1024.0
GE_ACQU_CREATOR = "GEMS_ACQU_01"
GE_CARDIAC_CREATOR = "GEMS_CT_CARDIAC_001"
#: mV per stored ECG count
ECG_SENSITIVITY_MV = 0.001


def derive_uid(*parts) -> str:
    """A UID under pydicom's root derived (SHA-512) from ``parts`` only."""
    return str(generate_uid(entropy_srcs=[str(p) for p in parts]))


def format_tm(seconds_after_midnight: float) -> str:
    """DICOM TM 'HHMMSS.ffffff' of a time in seconds after midnight (microseconds)."""
    us = int(round(float(seconds_after_midnight) * 1e6))
    if not 0 <= us < 86400 * 10**6:
        raise ValueError(f"time must be within one day (0..86400 s), got {seconds_after_midnight}")
    s, frac = divmod(us, 10**6)
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h:02d}{m:02d}{sec:02d}.{frac:06d}"


def format_ds(value: float, decimals: int = 6) -> str:
    """DICOM DS text of ``value`` rounded to ``decimals`` (at most 16 characters)."""
    text = f"{float(value):.{decimals}f}".rstrip("0").rstrip(".")
    if text in ("-0", ""):
        text = "0"
    if len(text) > 16:
        raise ValueError(f"{value} does not fit a DICOM DS (16 characters) with {decimals} decimals")
    return text


def _file_meta(sop_class: str, sop_instance: str) -> FileMetaDataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_instance
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    return meta


def _patient_study(ds: Dataset, *, seed: int, study_uid: str, origin_s: float) -> None:
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.PatientName = "PHANTOM^HEARTREG"
    ds.PatientID = f"PHANTOM-{seed}"
    ds.PatientSex = "O"
    ds.StudyInstanceUID = study_uid
    ds.StudyDate = STUDY_DATE
    ds.StudyTime = format_tm(origin_s)
    ds.StudyID = "1"
    ds.AccessionNumber = ""
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = "heartreg phantom gated cardiac CT"
    ds.Manufacturer = "GE MEDICAL SYSTEMS"
    ds.ManufacturerModelName = "LightSpeed VCT"
    ds.InstitutionName = "heartreg synthetic phantom"
    ds.StationName = "PHANTOM"
    ds.SoftwareVersions = "heartreg-phantom"


def ct_slice_dataset(
    hu: np.ndarray,
    *,
    seed: int,
    study_uid: str,
    series_uid: str,
    frame_uid: str,
    sop_uid: str,
    instance_number: int,
    acquisition_number: int,
    position_mm,
    pixel_mm: float,
    slice_mm: float,
    origin_s: float,
    time_s: float,
    trigger_ms: float,
    r_peaks_ms,
    nominal_interval_ms: float,
) -> Dataset:
    """One CT Image Storage dataset (with file meta) of an axial slice.

    Parameters
    ----------
    hu : (n_rows, n_cols) float, HU
        The slice; rounded and stored as int16 ``HU + 1024``.
    position_mm : (3,) float, mm
        (0020,0032) *Image Position (Patient)*: centre of the first pixel, LPS.
    origin_s, time_s : float, s after midnight
        The scan origin and this slice's mid-scan time (both microsecond-rounded).
    trigger_ms : float
        (0018,1060) *Trigger Time*: ms from the triggering R-peak to the trigger.
    r_peaks_ms : (n,) float, ms since the scan origin
        Every R-peak covering the scan (GE *RpeakTimeStamps*).
    """
    hu = np.asarray(hu)
    stored = np.clip(np.round(hu.astype(np.float64) - RESCALE_INTERCEPT), -32768, 32767).astype("<i2")
    ds = Dataset()
    ds.file_meta = _file_meta(CT_IMAGE_STORAGE, sop_uid)
    _patient_study(ds, seed=seed, study_uid=study_uid, origin_s=origin_s)
    ds.SOPClassUID = CT_IMAGE_STORAGE
    ds.SOPInstanceUID = sop_uid
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
    ds.Modality = "CT"
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = 2
    ds.SeriesDate = STUDY_DATE
    ds.SeriesTime = format_tm(origin_s)
    ds.SeriesDescription = "Cardiac 0.7 prospective gated"
    ds.BodyPartExamined = "CHEST"
    ds.PatientPosition = "HFS"
    ds.FrameOfReferenceUID = frame_uid
    ds.PositionReferenceIndicator = ""
    ds.AcquisitionDate = STUDY_DATE
    ds.ContentDate = STUDY_DATE
    ds.AcquisitionTime = format_tm(time_s)
    ds.ContentTime = format_tm(time_s)
    ds.InstanceNumber = int(instance_number)
    ds.AcquisitionNumber = int(acquisition_number)
    # CT image / acquisition
    ds.KVP = "120"
    ds.ScanOptions = "CARDIAC"
    ds.DataCollectionDiameter = "500"
    ds.ReconstructionDiameter = format_ds(pixel_mm * hu.shape[1], 4)
    ds.GantryDetectorTilt = "0"
    ds.RotationDirection = "CW"
    ds.XRayTubeCurrent = 500
    ds.ConvolutionKernel = "STANDARD"
    # cardiac synchronisation
    ds.CardiacSynchronizationTechnique = "PROSPECTIVE"
    ds.CardiacSignalSource = "ECG"
    ds.BeatRejectionFlag = "N"
    ds.TriggerTime = format_ds(trigger_ms, 3)
    ds.NominalInterval = int(round(nominal_interval_ms))
    ds.HeartRate = int(round(60000.0 / nominal_interval_ms))
    # image plane
    ds.ImageOrientationPatient = ["1", "0", "0", "0", "1", "0"]
    ds.ImagePositionPatient = [format_ds(v, 4) for v in position_mm]
    ds.SliceLocation = format_ds(position_mm[2], 4)
    ds.PixelSpacing = [format_ds(pixel_mm, 6), format_ds(pixel_mm, 6)]
    ds.SliceThickness = format_ds(slice_mm, 6)
    ds.SpacingBetweenSlices = format_ds(slice_mm, 6)
    # image pixel
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = int(hu.shape[0]), int(hu.shape[1])
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 1
    ds.RescaleIntercept = format_ds(RESCALE_INTERCEPT)
    ds.RescaleSlope = "1"
    ds.RescaleType = "HU"
    ds.WindowCenter = "40"
    ds.WindowWidth = "400"
    # GE private clocks
    acqu = ds.private_block(0x0019, GE_ACQU_CREATOR, create=True)
    acqu.add_new(0x24, "DS", format_ds(time_s - origin_s, 6))
    cardiac = ds.private_block(0x0049, GE_CARDIAC_CREATOR, create=True)
    cardiac.add_new(0x0C, "FD", [float(v) for v in r_peaks_ms])
    ds.PixelData = stored.tobytes()
    return ds


def _code(value: str, scheme: str, meaning: str) -> Dataset:
    item = Dataset()
    item.CodeValue = value
    item.CodingSchemeDesignator = scheme
    item.CodeMeaning = meaning
    return item


def ecg_dataset(
    ecg_mv: np.ndarray,
    *,
    seed: int,
    study_uid: str,
    series_uid: str,
    sop_uid: str,
    origin_s: float,
    start_offset_ms: float,
    rate_hz: float,
) -> Dataset:
    """General ECG Waveform Storage dataset (with file meta): one lead-II channel.

    Sample n is at ``AcquisitionDateTime + start_offset_ms / 1000 + n / rate_hz``
    with (0008,002A) *AcquisitionDateTime* the scan origin.

    Parameters
    ----------
    ecg_mv : (n,) float, mV
        Stored as int16 counts of :data:`ECG_SENSITIVITY_MV`.
    """
    ecg_mv = np.asarray(ecg_mv, dtype=float)
    counts = np.clip(np.round(ecg_mv / ECG_SENSITIVITY_MV), -32768, 32767).astype("<i2")
    ds = Dataset()
    ds.file_meta = _file_meta(ECG_WAVEFORM_STORAGE, sop_uid)
    _patient_study(ds, seed=seed, study_uid=study_uid, origin_s=origin_s)
    ds.SOPClassUID = ECG_WAVEFORM_STORAGE
    ds.SOPInstanceUID = sop_uid
    ds.Modality = "ECG"
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = 900
    ds.SeriesDescription = "ECG during gated CT"
    ds.InstanceNumber = 1
    ds.ContentDate = STUDY_DATE
    ds.ContentTime = format_tm(origin_s)
    ds.AcquisitionDateTime = STUDY_DATE + format_tm(origin_s)
    ds.AcquisitionContextSequence = Sequence()

    channel = Dataset()
    channel.ChannelLabel = "II"
    channel.ChannelStatus = "OK"
    channel.ChannelSourceSequence = Sequence([_code("2:2", "MDC", "Lead II")])
    channel.ChannelSensitivity = format_ds(ECG_SENSITIVITY_MV, 6)
    channel.ChannelSensitivityUnitsSequence = Sequence([_code("mV", "UCUM", "millivolt")])
    channel.ChannelSensitivityCorrectionFactor = "1"
    channel.ChannelBaseline = "0"
    channel.ChannelSampleSkew = "0"
    channel.WaveformBitsStored = 16
    channel.FilterLowFrequency = "0.05"
    channel.FilterHighFrequency = "150"

    group = Dataset()
    group.MultiplexGroupTimeOffset = format_ds(start_offset_ms, 3)
    group.WaveformOriginality = "ORIGINAL"
    group.NumberOfWaveformChannels = 1
    group.NumberOfWaveformSamples = int(counts.size)
    group.SamplingFrequency = format_ds(rate_hz, 3)
    group.MultiplexGroupLabel = "ECG"
    group.ChannelDefinitionSequence = Sequence([channel])
    group.WaveformBitsAllocated = 16
    group.WaveformSampleInterpretation = "SS"
    group.WaveformData = counts.tobytes()
    ds.WaveformSequence = Sequence([group])
    return ds
