"""Find DICOM files under a folder and read the headers needed to group them.

Only headers are read here (``stop_before_pixels=True``); pixel data are decoded
later, one slice at a time, by :mod:`imaging.volume`, which reads uncompressed
little-endian frames straight from the file offset recorded here. Every image
frame becomes one private :class:`_Frame` record (a classic single-frame file
gives one record, an Enhanced CT multi-frame file one per frame, with its
per-frame functional groups resolved and the shared groups as fallback). Files
that carry no image (ECG waveforms, structured reports, ...) become
:class:`_Other` records so that ``list_series`` can show them.

Nothing identifying a patient is copied out of the datasets.
"""

from __future__ import annotations

import datetime

import logging
import os
import stat
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataelem import RawDataElement
from pydicom.datadict import dictionary_VR, tag_for_keyword
from pydicom.errors import InvalidDicomError
from pydicom.tag import Tag

logger = logging.getLogger(__name__)

_DICOMDIR_SOP_CLASS = "1.2.840.10008.1.3.10"
_PIXEL_DATA_TAG = (0x7FE0, 0x0010)
_ITEM_TAG = (0xFFFE, 0xE000)
_SEQ_DELIM_TAG = (0xFFFE, 0xE0DD)

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


def _as_float(value) -> float | None:
    """Decode a numeric DICOM value robustly: DS/IS/FD, multi-valued, or UN bytes."""
    if value is None:
        return None
    if isinstance(value, (bytes, bytearray)):
        raw = bytes(value)
        text = raw.replace(b"\x00", b" ").strip()
        try:
            return float(text.decode("ascii").split("\\")[0])
        except (UnicodeDecodeError, ValueError):
            pass
        if len(raw) == 8:
            return float(struct.unpack("<d", raw)[0])
        if len(raw) == 4:
            return float(struct.unpack("<f", raw)[0])
        return None
    if isinstance(value, (list, tuple, pydicom.multival.MultiValue)):
        return _as_float(value[0]) if len(value) else None
    if isinstance(value, str) and not value.strip():
        return None
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if np.isfinite(out) else None


def _plausible_times(arr: np.ndarray, *, allow_nan: bool = False) -> bool:
    """Finite (or NaN, with ``allow_nan``: a scanner's missing stamp), below 1e9
    and non-decreasing over the finite values."""
    if np.isinf(arr).any() or (not allow_nan and np.isnan(arr).any()):
        return False
    fin = arr[np.isfinite(arr)]
    return bool(arr.size and np.all(np.abs(fin) < 1e9) and np.all(np.diff(fin) >= 0))


def _as_floats(value) -> tuple[float, ...] | None:
    """Decode a multi-valued float (FD 1-n) of time stamps, also from UN bytes.

    Bytes are read as little-endian float64 (GE writes FD); if that gives no
    finite, non-decreasing series, as float32, then as backslash-separated text.
    """
    if value is None:
        return None
    if isinstance(value, (bytes, bytearray)):
        raw = bytes(value)
        for dtype, width in (("<f8", 8), ("<f4", 4)):
            if raw and len(raw) % width == 0:
                arr = np.frombuffer(raw, dtype=dtype)
                if _plausible_times(arr, allow_nan=width == 8):  # NaN stamps are kept, and reported
                    return tuple(float(v) for v in arr)
        try:
            text = raw.replace(b"\x00", b" ").decode("ascii").strip()
            return tuple(float(v) for v in text.split("\\") if v.strip())
        except (UnicodeDecodeError, ValueError):
            return None
    if isinstance(value, (list, tuple, pydicom.multival.MultiValue)):
        # a NaN stamp stays NaN (imaging.phase reports it); anything else unreadable drops the tag
        out = [float(v) if isinstance(v, (float, int)) and not np.isinf(v) else _as_float(v) for v in value]
        return None if any(v is None for v in out) else tuple(out)
    if isinstance(value, float) and np.isnan(value):
        return (value,)
    single = _as_float(value)
    return None if single is None else (single,)


def _as_int(value) -> int | None:
    f = _as_float(value)
    return None if f is None else int(round(f))


def _tm_to_seconds(value) -> float | None:
    """DICOM TM ('HHMMSS.FFFFFF', also 'HH:MM:SS' of old files) -> seconds after midnight."""
    if value is None:
        return None
    text = str(value).strip().replace(":", "")
    if not text:
        return None
    try:
        hh = int(text[0:2])
        mm = int(text[2:4]) if len(text) >= 4 else 0
        ss = float(text[4:]) if len(text) > 4 else 0.0
    except ValueError:
        return None
    return hh * 3600.0 + mm * 60.0 + ss


def _date(value) -> datetime.date | None:
    """The calendar day of a DICOM DA ('YYYYMMDD') or DT ('YYYYMMDD...'), else None."""
    if value is None:
        return None
    if isinstance(value, datetime.date):  # also a datetime
        return datetime.date(value.year, value.month, value.day)
    text = str(value).strip()
    if len(text) < 8 or not text[:8].isdigit():
        return None
    try:
        return datetime.date(int(text[0:4]), int(text[4:6]), int(text[6:8]))
    except ValueError:
        return None


def on_study_clock(time_s: float | None, day, study_day) -> float | None:
    """Seconds after midnight of ``day`` -> seconds after midnight of the study's
    day ((0008,0020) *Study Date*): a scan that crosses midnight keeps counting
    (00:00:07 of the next day is 86 407 s).  Without both dates the time is
    returned as it is."""
    if time_s is None or day is None or study_day is None:
        return time_s
    return time_s + 86400.0 * (day - study_day).days


def _dt_to_seconds(value) -> float | None:
    """DICOM DT ('YYYYMMDDHHMMSS.FFFFFF&ZZXX') -> seconds after midnight (offset ignored)."""
    if value is None:
        return None
    text = str(value).strip()
    if len(text) <= 8:
        return None
    time_part = text[8:]
    for sign in "+-":
        if sign in time_part:
            time_part = time_part.split(sign)[0]
    return _tm_to_seconds(time_part)


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

_PYDICOM = object()  # "let pydicom convert this element"


def _ascii(raw: bytes) -> str | None:
    """`raw` as text without trailing padding, when it is printable ASCII."""
    try:
        text = raw.decode("ascii").rstrip(" \x00")
    except UnicodeDecodeError:
        return None
    return text if text.isprintable() else None


def _parse_text(raw: bytes, little: bool):
    text = _ascii(raw)
    return _PYDICOM if text is None or "\\" in text else text


def _parse_strings(raw: bytes, little: bool):
    text = _ascii(raw)
    if text is None:
        return _PYDICOM
    parts = text.split("\\")
    return parts[0] if len(parts) == 1 else parts


def _parse_ds(raw: bytes, little: bool, *, multi: bool = False):
    text = _ascii(raw)
    if text is None:
        return _PYDICOM
    parts = text.strip().split("\\")
    if multi != (len(parts) > 1):
        return _PYDICOM
    try:
        out = [float(v) for v in parts if v.strip()]
    except ValueError:
        return _PYDICOM
    if len(out) != len(parts) or not all(np.isfinite(out)):
        return _PYDICOM
    return out if multi else out[0]


def _parse_ds_multi(raw: bytes, little: bool):
    return _parse_ds(raw, little, multi=True)


def _parse_is(raw: bytes, little: bool):
    text = _ascii(raw)
    if text is None or "\\" in text:
        return _PYDICOM
    try:
        return int(text)
    except ValueError:
        pass
    try:
        out = float(text)
    except ValueError:
        return _PYDICOM
    return int(out) if np.isfinite(out) and out.is_integer() else _PYDICOM


def _binary(code: str, *, single: bool = True):
    size = struct.calcsize(code)

    def parse(raw: bytes, little: bool):
        n, rest = divmod(len(raw), size)
        if rest or n == 0 or (single and n != 1):
            return _PYDICOM
        values = struct.unpack(("<" if little else ">") + str(n) + code, raw)
        return values[0] if n == 1 else list(values)

    return parse


_PARSERS = {
    "UI": _parse_text, "LO": _parse_text, "SH": _parse_text, "CS": _parse_text,
    "TM": _parse_text, "DT": _parse_text, "DS": _parse_ds, "IS": _parse_is,
    "US": _binary("H"), "UL": _binary("I"),
    "FL": _binary("f", single=False), "FD": _binary("d", single=False),
}
_MULTI_VALUED = {  # keywords read as several values
    "ImageType": _parse_strings, "FrameType": _parse_strings,
    "ImagePositionPatient": _parse_ds_multi, "ImageOrientationPatient": _parse_ds_multi,
    "PixelSpacing": _parse_ds_multi,
}


@lru_cache(maxsize=None)
def _fast_spec(keyword: str):
    """(tag, VR, parser) for a keyword read through `_get`."""
    tag = Tag(tag_for_keyword(keyword))
    vr = dictionary_VR(tag)
    return tag, vr, _MULTI_VALUED.get(keyword) or _PARSERS.get(vr)


def _raw_value(elem, vr: str, parse):
    """Parsed value of a raw element, or _PYDICOM."""
    if (
        parse is None
        or not isinstance(elem, RawDataElement)
        or pydicom.config.settings.reading_validation_mode == pydicom.config.RAISE
        or (elem.VR is not None and elem.VR != vr)
        or not elem.value
    ):
        return _PYDICOM
    return parse(elem.value, elem.is_little_endian)


def _get(ds, keyword: str, default=None):
    """``ds.get(keyword, default)``, parsed from the raw bytes where that gives the same value."""
    tag, vr, parse = _fast_spec(keyword)
    elem = ds.get_item(tag)
    if elem is None:
        return default
    value = _raw_value(elem, vr, parse)
    return ds.get(keyword) if value is _PYDICOM else value


def _private_creator_element(ds, group: int, creator: str) -> int | None:
    """Element number (0x10-0xFF) of the private block `creator` in `group`.

    Same rule as pydicom's ``Dataset.private_block``: the first creator element,
    in tag order, whose value equals `creator`.
    """
    block_tags = (t for t in ds.keys() if t >> 16 == group and 0x10 <= t & 0xFFFF <= 0xFF)
    for tag in sorted(block_tags):
        value = _raw_value(ds.get_item(tag), "LO", _parse_text)
        if value is _PYDICOM:
            value = ds[tag].value
        if value == creator:
            return tag & 0xFF
    return None


def _private_value(ds, group: int, creator: str, offset: int):
    """Value of a private element, or None when its block or element is absent.

    Elements read as UN (explicit VR UN, or implicit VR) come back as raw bytes:
    pydicom would otherwise apply its private dictionary's VR, which for
    (0049,xx0C) *RpeakTimeStamps* says FL where GE writes FD.
    """
    block = _private_creator_element(ds, group, creator)
    if block is None:
        return None
    tag = Tag((group << 16) | (block << 8) | offset)
    elem = ds.get_item(tag)
    if elem is None:
        return None
    if isinstance(elem, RawDataElement):
        if elem.VR in (None, "UN"):
            return None if elem.value is None else bytes(elem.value)
        value = _raw_value(elem, elem.VR, _PARSERS.get(elem.VR))
        return ds[tag].value if value is _PYDICOM else value
    return elem.value


def _seq_item(container, keyword):
    """First item of the sequence `keyword` in `container`, or None."""
    if container is None:
        return None
    seq = container.get(keyword)
    if seq is None or len(seq) == 0:
        return None
    return seq[0]


def _first(keyword, *items):
    """The first present, non-empty value of `keyword` among datasets `items`."""
    for item in items:
        if item is None:
            continue
        value = _get(item, keyword)
        if value is not None and value != "":
            return value
    return None


def _str(ds, keyword) -> str:
    value = _get(ds, keyword)
    return "" if value is None else str(value).strip()


# ------------------------------------------------------------------ headers


def _check_pixel_extent(fp, ds, size: int) -> tuple[str | None, tuple[int, int] | None]:
    """Check that the pixel data fit in the file; find native little-endian data.

    `fp` stands right before (7FE0,0010) after ``dcmread(stop_before_pixels=True)``.
    Native data: the element's length must fit. Encapsulated data: the item headers
    are walked (seeking over the fragments) up to the sequence delimiter.

    Returns ``(reason, native)``: `reason` says why the pixel data run past the end
    of the file (else None); `native` is the file offset and length of a
    defined-length, little-endian (7FE0,0010) value (else None), which lets
    :mod:`imaging.volume` read uncompressed frames straight from the file.
    """
    start = fp.tell()
    if start >= size:
        return None, None  # no pixel data element at all (header-only file)
    implicit, little = ds.original_encoding
    end = "<" if little is not False else ">"
    head = fp.read(8)
    if len(head) < 8:
        return "file ends inside the (7FE0,0010) Pixel Data header", None
    group, elem = struct.unpack(end + "HH", head[:4])
    if (group, elem) != _PIXEL_DATA_TAG:
        return None, None  # something else (e.g. float pixel data); leave it to the decoder
    if implicit:
        (length,) = struct.unpack(end + "I", head[4:8])
    else:
        vr = head[4:6]
        if vr in (b"OB", b"OW", b"OF", b"OD", b"OL", b"UN", b"OV", b"SQ", b"UT"):
            more = fp.read(4)
            if len(more) < 4:
                return "file ends inside the (7FE0,0010) Pixel Data header", None
            (length,) = struct.unpack(end + "I", more)
        else:
            (length,) = struct.unpack(end + "H", head[6:8])
    if length != 0xFFFFFFFF:
        if fp.tell() + length > size:
            return (
                f"Pixel Data holds {size - fp.tell()} of {length} bytes "
                "(file truncated)"
            ), None
        return None, ((fp.tell(), length) if little is True else None)
    while True:
        item = fp.read(8)
        if len(item) < 8:
            return "file ends before the end of the encapsulated Pixel Data (truncated)", None
        group, elem, item_len = struct.unpack(end + "HHI", item)
        if (group, elem) == _SEQ_DELIM_TAG:
            return None, None
        if (group, elem) != _ITEM_TAG:
            return f"unexpected tag ({group:04X},{elem:04X}) inside encapsulated Pixel Data", None
        if fp.tell() + item_len > size:
            return "a Pixel Data fragment runs past the end of the file (truncated)", None
        fp.seek(item_len, os.SEEK_CUR)


def _looks_like_bare_dicom(head: bytes) -> bool:
    """Whether a file without the preamble starts like a DICOM data set.

    Such files (e.g. old ACR-NEMA style exports) start with an element of group
    (0002) or (0008) in little-endian order; anything else (zeros, text, another
    format) is not parsed at all.
    """
    if len(head) < 8:
        return False
    group, _ = struct.unpack("<HH", head[:4])
    return group in (0x0002, 0x0008)

#: (0002,0010) Deflated Explicit VR Little Endian: the whole dataset is zlib-deflated.
DEFLATED_UID = "1.2.840.10008.1.2.1.99"


def _read_header(path: str):
    """Read one file's header.

    Returns ``(dataset, None, native)`` (`native` as from `_check_pixel_extent`) or
    ``(None, reason/kind, None)``.
    """
    size = os.path.getsize(path)
    with open(path, "rb") as fp:
        try:
            ds = pydicom.dcmread(fp, stop_before_pixels=True)
        except InvalidDicomError:
            # Files without the 128-byte preamble: accept only if they look like images.
            fp.seek(0)
            if not _looks_like_bare_dicom(fp.read(8)):
                return None, "not-dicom", None  # cheap: never parse megabytes of zeros or text
            fp.seek(0)
            try:
                ds = pydicom.dcmread(fp, stop_before_pixels=True, force=True)
            except Exception:  # noqa: BLE001 - anything unreadable is "not DICOM"
                return None, "not-dicom", None
            if "SOPInstanceUID" not in ds or "SeriesInstanceUID" not in ds:
                return None, "not-dicom", None
        except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds here
            return None, f"unreadable header ({type(exc).__name__}: {exc})", None
        if getattr(ds, "file_meta", None) is not None and ds.file_meta.get("TransferSyntaxUID") == DEFLATED_UID:
            return ds, None, None  # the dataset was inflated in memory: no file offsets to check
        try:
            reason, native = _check_pixel_extent(fp, ds, size)
        except Exception as exc:  # noqa: BLE001
            reason = f"unreadable Pixel Data ({type(exc).__name__}: {exc})"
    if reason is not None:
        return None, reason, None
    return ds, None, native


def _upper_values(value) -> tuple[str, ...]:
    """A code string's values, upper case; a single value (a str) stays whole."""
    if value is None:
        return ()
    if isinstance(value, (str, bytes)):
        value = [value.decode("ascii", "replace") if isinstance(value, bytes) else value]
    return tuple(str(v).upper() for v in value)


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


def _geometry_problem(ipp, iop, spacing) -> str | None:
    """Why a frame's geometry cannot be used, or None (absent values are left to the caller)."""
    checks = (
        ("(0020,0032) Image Position (Patient)", ipp, lambda a: abs(a).max() <= MAX_POSITION_MM, "mm"),
        ("(0020,0037) Image Orientation (Patient)", iop, lambda a: abs(a).max() <= 1.0 + 1e-3, ""),
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
        sop_instance_uid=_str(ds, "SOPInstanceUID"),
        sop_class_uid=_str(ds, "SOPClassUID"),
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


def _iter_files(root: Path) -> Iterable[str]:
    if root.is_file():
        yield str(root)
        return
    for dirpath, dirnames, filenames in os.walk(root):
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
    files = list(_iter_files(root))
    frames: list[_Frame] = []
    others: list[_Other] = []
    non_dicom: list[str] = []
    dicomdir: list[str] = []
    broken: list[tuple[str, str]] = []
    iterator = files
    if progress:
        from tqdm import tqdm

        iterator = tqdm(files, desc="reading headers", unit="file", leave=False)
    for name in iterator:
        if os.path.basename(name).upper() == "DICOMDIR":
            dicomdir.append(name)
            continue
        try:
            if not stat.S_ISREG(os.stat(name).st_mode):  # a named pipe would block open()
                broken.append((name, "not a regular file (named pipe, socket or device)"))
                continue
            ds, why, native = _read_header(name)
        except OSError as exc:
            broken.append((name, f"cannot open ({exc.strerror or exc})"))
            continue
        if ds is None:
            (non_dicom.append(name) if why == "not-dicom" else broken.append((name, why)))
            continue
        meta = getattr(ds, "file_meta", None)
        sop_class = _str(ds, "SOPClassUID") or (
            str(_get(meta, "MediaStorageSOPClassUID", "")) if meta is not None else ""
        )
        if sop_class == _DICOMDIR_SOP_CLASS or "DirectoryRecordSequence" in ds:
            dicomdir.append(name)
            continue
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
            continue
        try:
            frames.extend(_frames_from_dataset(ds, name, native))
        except _BadGeometry as exc:
            broken.append((name, str(exc)))
        except Exception as exc:  # noqa: BLE001 - malformed functional groups etc.
            broken.append((name, f"malformed header ({type(exc).__name__}: {exc})"))
    return _Scan(
        frames=tuple(frames),
        others=tuple(others),
        n_files=len(files),
        skipped_non_dicom=tuple(non_dicom),
        skipped_dicomdir=tuple(dicomdir),
        skipped_broken=tuple(broken),
    )
