"""Typed values out of DICOM headers: times and dates, numbers, private tags.

:mod:`imaging.discover` reads every header of a study; most of its time goes into
converting element values. The fast path here parses the raw bytes of the few
value representations a CT header uses (DS, IS, TM, DA, DT, strings, binary
numbers) without building pydicom's value objects, and falls back to pydicom for
anything else. Times come out in seconds on one study clock.
"""

from __future__ import annotations

import datetime
import struct
from functools import lru_cache

import numpy as np
import pydicom
from pydicom.datadict import dictionary_VR, tag_for_keyword
from pydicom.dataelem import RawDataElement
from pydicom.tag import Tag


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


def _upper_values(value) -> tuple[str, ...]:
    """A code string's values, upper case; a single value (a str) stays whole."""
    if value is None:
        return ()
    if isinstance(value, (str, bytes)):
        value = [value.decode("ascii", "replace") if isinstance(value, bytes) else value]
    return tuple(str(v).upper() for v in value)
