"""One DICOM file's header, checked before its file offsets are trusted.

:func:`_read_header` reads a header without the pixels (``stop_before_pixels``)
and walks the (7FE0,0010) Pixel Data element's header and, for encapsulated
data, its item headers, so that a truncated file is named at discovery rather
than failing half-way through a volume; for native little-endian data it keeps
the value's file offset, from which :mod:`imaging.volume` reads frames
directly.  Files without the 128-byte preamble are parsed only when they start
like a DICOM data set.
"""

from __future__ import annotations

import os
import struct

import pydicom
from pydicom.errors import InvalidDicomError

_PIXEL_DATA_TAG = (0x7FE0, 0x0010)
_ITEM_TAG = (0xFFFE, 0xE000)
_SEQ_DELIM_TAG = (0xFFFE, 0xE0DD)


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
