"""Find DICOM files under a folder and read the headers needed to group them.

Only headers are read here (``stop_before_pixels=True``); pixel data are decoded
later, one slice at a time, by :mod:`imaging.volume`, which reads uncompressed
little-endian frames straight from the file offset recorded here. Every image
frame becomes one private :class:`_Frame` record (a classic single-frame file
gives one record, an Enhanced CT multi-frame file one per frame, with its
per-frame functional groups resolved and the shared groups as fallback). Files
that carry no image (ECG waveforms, structured reports, ...) become
:class:`_Other` records so that ``list_series`` can show them. Element values
are converted by :mod:`imaging.dicom_values`; each file's header is read and its
Pixel Data checked against the file's length by :mod:`imaging.dicom_file`.

Nothing identifying a patient is copied out of the datasets.
"""

from __future__ import annotations

import logging
import os
import stat
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hrcore.output import study_folder
from imaging.dicom_file import _read_header
from imaging.dicom_values import (
    _as_float,
    _as_floats,
    _as_int,
    _date,
    _dt_to_seconds,
    _first,
    _get,
    _private_value,
    _seq_item,
    _str,
    _tm_to_seconds,
    _upper_values,
    on_study_clock,
)

logger = logging.getLogger(__name__)

_DICOMDIR_SOP_CLASS = "1.2.840.10008.1.3.10"

GE_ACQU_CREATOR = "GEMS_ACQU_01"
GE_MID_SCAN_TIME = (0x0019, 0x24)  # (0019,xx24) *Mid Scan Time*, s since scan origin
GE_CARDIAC_CREATOR = "GEMS_CT_CARDIAC_001"
GE_RPEAK_TIMESTAMPS = (0x0049, 0x0C)  # (0049,xx0C) *RpeakTimeStamps*, ms, VR FD 1-n


@dataclass(frozen=True)
class _Frame:
    """One image frame as read from a header (no pixels)."""

    path: str
    frame: int | None  # 0-based frame number for multi-frame files, else None
    n_frames_in_file: int
    sop_instance_uid: str
    sop_class_uid: str
    transfer_syntax_uid: str
    series_instance_uid: str
    study_instance_uid: str
    frame_of_reference_uid: str
    series_number: int | None
    description: str
    modality: str
    manufacturer: str
    model_name: str
    image_type: tuple[str, ...]
    instance_number: int | None
    ipp: tuple[float, float, float] | None
    iop: tuple[float, ...] | None
    pixel_spacing: tuple[float, float] | None
    slice_thickness_mm: float | None
    gantry_tilt_deg: float | None
    rows: int
    columns: int
    samples_per_pixel: int
    bits_allocated: int
    bits_stored: int
    pixel_representation: int
    slope: float | None
    intercept: float | None
    acquisition_time_s: float | None
    mid_scan_time_s: float | None
    trigger_time_ms: float | None
    nominal_interval_ms: float | None
    heart_rate_bpm: float | None
    nominal_cardiac_percent: float | None
    temporal_position: int | None
    acquisition_number: int | None
    rpeak_timestamps_ms: tuple[float, ...] | None = field(default=None, repr=False)
    # file offset and length of a native little-endian (7FE0,0010) value, else None
    pixel_offset: int | None = field(default=None, repr=False, compare=False)
    pixel_length: int | None = field(default=None, repr=False, compare=False)
    # (0018,9037) Cardiac Synchronization Technique (NONE, PROSPECTIVE, ...), upper case; None if absent
    cardiac_sync_technique: str | None = None
    # (0028,0120) Pixel Padding Value and (0028,0121) Pixel Padding Range Limit, stored values; None if absent
    padding_value: int | None = None
    padding_limit: int | None = None

    @property
    def is_localizer(self) -> bool:
        return "LOCALIZER" in self.image_type


@dataclass(frozen=True)
class _Other:
    """A DICOM file without an image frame (waveform, SR, ...)."""

    path: str
    series_instance_uid: str
    study_instance_uid: str
    series_number: int | None
    description: str
    modality: str
    sop_class_uid: str


@dataclass(frozen=True)
class _Scan:
    """What discovery found under a path."""

    frames: tuple[_Frame, ...]
    others: tuple[_Other, ...]
    n_files: int
    skipped_non_dicom: tuple[str, ...]
    skipped_dicomdir: tuple[str, ...]
    skipped_broken: tuple[tuple[str, str], ...]  # (file, reason)


# --------------------------------------------------------------------- values


# Fast element values. pydicom converts an element's raw bytes on first access
# (DSfloat, IS, UID, ... with validation), some 20 us each, which made up most of
# the header scan. For the few plain kinds read here the raw bytes are parsed
# directly, but only when the result is certainly the one pydicom would give
# (printable ASCII text without a value delimiter, finite numbers, the expected
# VR or implicit VR, one binary value); anything else is converted by pydicom as
# before, so odd files behave exactly as they used to. pydicom's validation
# warnings about such values are not emitted; when a caller asked pydicom to
# raise on invalid values (``reading_validation_mode = RAISE``) everything goes
# through pydicom.


# ------------------------------------------------------------------ headers


#: largest plausible |coordinate| of (0020,0032) *Image Position (Patient)*, mm.
MAX_POSITION_MM = 1e5
#: largest plausible (0028,0030) *Pixel Spacing*, mm.
MAX_SPACING_MM = 1e3


class _BadGeometry(ValueError):
    """A header whose geometry is not numbers a scanner writes (NaN, inf, 1e30)."""


def _floats_or_none(values):
    try:
        return [float(v) for v in values]
    except (TypeError, ValueError):
        return None


def _two_orthonormal(a: np.ndarray) -> bool:
    """Image Orientation (Patient): a row and a column direction, each of unit length, at right angles
    (all zeros made every slice's position along the normal 0: "repeated slice positions")."""
    if a.size != 6:
        return abs(a).max() <= 1.0 + 1e-3  # a wrong count is the caller's to report
    row, col = a[:3], a[3:]
    return abs(np.linalg.norm(row) - 1.0) <= 0.01 and abs(np.linalg.norm(col) - 1.0) <= 0.01 and abs(row @ col) <= 0.01


def _geometry_problem(ipp, iop, spacing) -> str | None:
    """Why a frame's geometry cannot be used, or None (absent values are left to the caller)."""
    checks = (
        ("(0020,0032) Image Position (Patient)", ipp, lambda a: abs(a).max() <= MAX_POSITION_MM, "mm"),
        ("(0020,0037) Image Orientation (Patient)", iop, _two_orthonormal, ""),
        ("(0028,0030) Pixel Spacing", spacing, lambda a: (a > 0).all() and a.max() <= MAX_SPACING_MM, "mm"),
    )
    for name, value, plausible, unit in checks:
        if value is None:
            continue
        numbers = _floats_or_none(value)
        if numbers is None:
            return f"{name} is not numeric: {' / '.join(str(v) for v in value)[:60]}"
        arr = np.asarray(numbers, dtype=float)
        if arr.size and (not np.all(np.isfinite(arr)) or not plausible(arr)):
            shown = ", ".join(f"{v:g}" for v in arr)
            return f"{name} is ({shown}){' ' + unit if unit else ''}, not a plausible value; fix or remove the file"
    return None


def _meta_str(meta, keyword: str) -> str:
    """A file meta element as text (:func:`_str`), "" when the file has no meta."""
    return _str(meta, keyword) if meta is not None else ""


def _frames_from_dataset(ds, path: str, native: tuple[int, int] | None = None) -> list[_Frame]:
    """One _Frame per image frame of `ds` (header only).

    `native`: file offset and length of the native little-endian Pixel Data value.
    """
    meta = getattr(ds, "file_meta", None)
    ts = str(_get(meta, "TransferSyntaxUID", "")) if meta is not None else ""
    if not ts:
        implicit, little = ds.original_encoding
        ts = "1.2.840.10008.1.2" if implicit else "1.2.840.10008.1.2.1"
    n_frames = _as_int(_get(ds, "NumberOfFrames")) or 1
    shared = _seq_item(ds, "SharedFunctionalGroupsSequence")
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    is_enhanced = per_frame is not None or shared is not None
    rpeaks = _as_floats(
        _private_value(ds, GE_RPEAK_TIMESTAMPS[0], GE_CARDIAC_CREATOR, GE_RPEAK_TIMESTAMPS[1])
    )
    mid_scan = _as_float(
        _private_value(ds, GE_MID_SCAN_TIME[0], GE_ACQU_CREATOR, GE_MID_SCAN_TIME[1])
    )
    study_day = _date(_get(ds, "StudyDate"))
    top_dt = _get(ds, "AcquisitionDateTime")
    top_time = on_study_clock(_dt_to_seconds(top_dt), _date(top_dt), study_day)
    if top_time is None:
        top_time = on_study_clock(
            _tm_to_seconds(_get(ds, "AcquisitionTime")), _date(_get(ds, "AcquisitionDate")), study_day
        )
    if top_time is None:
        top_time = on_study_clock(
            _tm_to_seconds(_get(ds, "ContentTime")), _date(_get(ds, "ContentDate")), study_day
        )
    common = dict(
        path=path,
        n_frames_in_file=n_frames,
        # anonymisers may blank the dataset's UIDs and leave the file meta's
        sop_instance_uid=_str(ds, "SOPInstanceUID") or _meta_str(meta, "MediaStorageSOPInstanceUID"),
        sop_class_uid=_str(ds, "SOPClassUID") or _meta_str(meta, "MediaStorageSOPClassUID"),
        transfer_syntax_uid=ts,
        series_instance_uid=_str(ds, "SeriesInstanceUID"),
        study_instance_uid=_str(ds, "StudyInstanceUID"),
        frame_of_reference_uid=_str(ds, "FrameOfReferenceUID"),
        series_number=_as_int(_get(ds, "SeriesNumber")),
        description=_str(ds, "SeriesDescription"),
        modality=_str(ds, "Modality"),
        manufacturer=_str(ds, "Manufacturer"),
        model_name=_str(ds, "ManufacturerModelName"),
        instance_number=_as_int(_get(ds, "InstanceNumber")),
        gantry_tilt_deg=_as_float(_get(ds, "GantryDetectorTilt")),
        rows=int(_get(ds, "Rows", 0) or 0),
        columns=int(_get(ds, "Columns", 0) or 0),
        samples_per_pixel=int(_get(ds, "SamplesPerPixel", 1) or 1),
        bits_allocated=int(_get(ds, "BitsAllocated", 16) or 16),
        bits_stored=int(_get(ds, "BitsStored", _get(ds, "BitsAllocated", 16)) or 16),
        pixel_representation=int(_get(ds, "PixelRepresentation", 0) or 0),
        padding_value=_as_int(_get(ds, "PixelPaddingValue")),
        padding_limit=_as_int(_get(ds, "PixelPaddingRangeLimit")),
        mid_scan_time_s=mid_scan,
        rpeak_timestamps_ms=rpeaks,
        pixel_offset=None if native is None else native[0],
        pixel_length=None if native is None else native[1],
    )
    top_type = _upper_values(_get(ds, "ImageType"))
    frames = []
    for f in range(n_frames):
        pf = per_frame[f] if per_frame is not None and f < len(per_frame) else None
        groups = (pf, shared) if is_enhanced else ()

        def grp(keyword, _groups=groups):
            for g in _groups:
                item = _seq_item(g, keyword)
                if item is not None:
                    return item
            return None

        plane_pos = grp("PlanePositionSequence")
        plane_ori = grp("PlaneOrientationSequence")
        measures = grp("PixelMeasuresSequence")
        transform = grp("PixelValueTransformationSequence")
        content = grp("FrameContentSequence")
        cardiac = grp("CardiacSynchronizationSequence")
        frame_type_item = grp("CTImageFrameTypeSequence")
        ipp = _first("ImagePositionPatient", plane_pos, ds)
        iop = _first("ImageOrientationPatient", plane_ori, ds)
        spacing = _first("PixelSpacing", measures, ds)
        frame_type = _first("FrameType", frame_type_item)
        image_type = top_type + _upper_values(frame_type)
        frame_dt = _first("FrameAcquisitionDateTime", content)
        t = on_study_clock(_dt_to_seconds(frame_dt), _date(frame_dt), study_day)
        trigger = _as_float(_first("TriggerTime", cardiac, ds))
        if trigger is None:
            trigger = _as_float(_first("NominalCardiacTriggerDelayTime", cardiac))
        interval = _as_float(_first("NominalInterval", cardiac, ds))
        if interval is None:
            interval = _as_float(_first("RRIntervalTimeNominal", cardiac))
        problem = _geometry_problem(ipp, iop, spacing)
        if problem:
            raise _BadGeometry(problem + (f" (frame {f + 1})" if n_frames > 1 else ""))
        frames.append(
            _Frame(
                frame=f if (n_frames > 1 or is_enhanced) else None,
                image_type=image_type,
                ipp=tuple(float(v) for v in ipp) if ipp is not None and len(ipp) == 3 else None,
                iop=tuple(float(v) for v in iop) if iop is not None and len(iop) == 6 else None,
                pixel_spacing=(
                    (float(spacing[0]), float(spacing[1]))
                    if spacing is not None and len(spacing) == 2
                    else None
                ),
                slice_thickness_mm=_as_float(_first("SliceThickness", measures, ds)),
                slope=_as_float(_first("RescaleSlope", transform, ds)),
                intercept=_as_float(_first("RescaleIntercept", transform, ds)),
                acquisition_time_s=t if t is not None else top_time,
                trigger_time_ms=trigger,
                nominal_interval_ms=interval,
                heart_rate_bpm=_as_float(_first("HeartRate", cardiac, ds)),
                nominal_cardiac_percent=_as_float(
                    _first("NominalPercentageOfCardiacPhase", cardiac, ds)
                ),
                cardiac_sync_technique=(" ".join(_upper_values(_first("CardiacSynchronizationTechnique", ds)))
                                        .strip() or None),
                temporal_position=_as_int(
                    _first("TemporalPositionIndex", content)
                    if content is not None
                    else _get(ds, "TemporalPositionIdentifier")
                ),
                acquisition_number=_as_int(
                    _first("FrameAcquisitionNumber", content)
                    if content is not None
                    else _get(ds, "AcquisitionNumber")
                ),
                **common,
            )
        )
    return frames


def _iter_files(root: Path, unreadable: list) -> Iterable[str]:
    """The files under ``root``, sorted; folders that cannot be listed go to ``unreadable`` with the reason."""
    if root.is_file():
        yield str(root)
        return

    def cannot_list(exc: OSError) -> None:  # os.walk passes over such a folder without a word otherwise
        unreadable.append((exc.filename or str(root), f"folder that cannot be opened ({exc.strerror or exc})"))

    for dirpath, dirnames, filenames in os.walk(root, onerror=cannot_list):
        dirnames.sort()
        for name in sorted(filenames):
            yield os.path.join(dirpath, name)


def _scan(path: str | os.PathLike, *, progress: bool = False) -> _Scan:
    """Read the headers of every file under `path` (recursively, any file names).

    DICOMDIR files are skipped; non-DICOM files are counted; DICOM files whose
    header or pixel data are cut short are skipped and reported with a reason.
    """
    root = Path(path)
    if not root.exists():
        raise FileNotFoundError(f"study path {str(root)!r} does not exist")
    root = study_folder(root)  # a DICOMDIR file: the files beside it
    broken: list[tuple[str, str]] = []
    files = list(_iter_files(root, broken))
    frames: list[_Frame] = []
    others: list[_Other] = []
    non_dicom: list[str] = []
    dicomdir: list[str] = []
    iterator = files
    if progress:
        from tqdm import tqdm

        iterator = tqdm(files, desc="reading headers", unit="file", leave=False)
    # pydicom's warnings about a file's values ("Invalid value for VR IS") name no file: caught, and said once
    # per message, in their own category, with the file(s) they came from; a developer's warning
    # (DeprecationWarning, FutureWarning) goes on as it was, under the caller's filters
    said: dict[tuple[type, str], list[str]] = {}  # (category, message): the files that raised it
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for name in iterator:
            seen = len(caught)
            _scan_file(name, frames, others, non_dicom, dicomdir, broken)
            for w in caught[seen:]:
                said.setdefault((w.category, f"{w.message}"), []).append(name)
    for (category, message), names in said.items():
        if issubclass(category, (DeprecationWarning, PendingDeprecationWarning, FutureWarning)):
            warnings.warn(message, category, stacklevel=2)
            continue
        more = f" and {len(names) - 1} other file(s)" if len(names) > 1 else ""
        warnings.warn(f"{names[0]}{more}: {message}", category, stacklevel=3)
    return _Scan(
        frames=tuple(frames),
        others=tuple(others),
        n_files=len(files),
        skipped_non_dicom=tuple(non_dicom),
        skipped_dicomdir=tuple(dicomdir),
        skipped_broken=tuple(broken),
    )


def _scan_file(name: str, frames, others, non_dicom, dicomdir, broken) -> None:
    """Read one file's header into the list it belongs to."""
    if os.path.basename(name).upper() == "DICOMDIR":
        dicomdir.append(name)
        return
    try:
        if not stat.S_ISREG(os.stat(name).st_mode):  # a named pipe would block open()
            broken.append((name, "not a regular file (named pipe, socket or device)"))
            return
        ds, why, native = _read_header(name)
    except OSError as exc:
        broken.append((name, f"cannot open ({exc.strerror or exc})"))
        return
    if ds is None:
        (non_dicom.append(name) if why == "not-dicom" else broken.append((name, why)))
        return
    meta = getattr(ds, "file_meta", None)
    sop_class = _str(ds, "SOPClassUID") or _meta_str(meta, "MediaStorageSOPClassUID")
    if sop_class == _DICOMDIR_SOP_CLASS or "DirectoryRecordSequence" in ds:
        dicomdir.append(name)
        return
    has_image = int(_get(ds, "Rows", 0) or 0) > 0 and int(_get(ds, "Columns", 0) or 0) > 0
    if not has_image:
        others.append(
            _Other(
                path=name,
                series_instance_uid=_str(ds, "SeriesInstanceUID"),
                study_instance_uid=_str(ds, "StudyInstanceUID"),
                series_number=_as_int(_get(ds, "SeriesNumber")),
                description=_str(ds, "SeriesDescription"),
                modality=_str(ds, "Modality"),
                sop_class_uid=sop_class,
            )
        )
        return
    try:
        frames.extend(_frames_from_dataset(ds, name, native))
    except _BadGeometry as exc:
        broken.append((name, str(exc)))
    except Exception as exc:  # noqa: BLE001 - malformed functional groups etc.
        broken.append((name, f"malformed header ({type(exc).__name__}: {exc})"))
