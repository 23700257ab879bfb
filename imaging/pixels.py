"""Pixel data of one planned image stack to a HU array.

:mod:`imaging.volume` plans where every acquired slice goes (the geometry);
here each slice is decoded (uncompressed little-endian frames straight from the
file offset found by :mod:`imaging.discover`, anything else through a pydicom
plugin), rescaled to HU (int16 when every slice allows it, else float32) and,
for irregular stacks, interpolated onto the planned grid.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pydicom
from pydicom.errors import InvalidDicomError

from .dicom_file import DEFLATED_UID
from .discover import _Frame
from hrcore.errors import HeartregError
from .volume import OUTSIDE_HU, SeriesError, _files_text, _Plan


_INT16 = np.iinfo(np.int16)
_NATIVE_LITTLE_ENDIAN = {"1.2.840.10008.1.2", "1.2.840.10008.1.2.1"}


# Transfer syntaxes whose pydicom "pylibjpeg" plugin needs the GPL pylibjpeg-libjpeg:
# heartreg never decodes these through it.
_GPL_LIBJPEG_SYNTAXES = {
    "1.2.840.10008.1.2.4.50",
    "1.2.840.10008.1.2.4.51",
    "1.2.840.10008.1.2.4.57",
    "1.2.840.10008.1.2.4.70",
    "1.2.840.10008.1.2.4.80",
    "1.2.840.10008.1.2.4.81",
}


_INSTALL_HINT = {
    "1.2.840.10008.1.2.4.50": "pillow",
    "1.2.840.10008.1.2.4.51": "python-gdcm",
    "1.2.840.10008.1.2.4.57": "python-gdcm",
    "1.2.840.10008.1.2.4.70": "python-gdcm",
    "1.2.840.10008.1.2.4.80": "pyjpegls (or python-gdcm)",
    "1.2.840.10008.1.2.4.81": "pyjpegls (or python-gdcm)",
    "1.2.840.10008.1.2.4.90": "pylibjpeg-openjpeg",
    "1.2.840.10008.1.2.4.91": "pylibjpeg-openjpeg",
    "1.2.840.10008.1.2.4.201": "pylibjpeg-openjpeg",
    "1.2.840.10008.1.2.4.202": "pylibjpeg-openjpeg",
    "1.2.840.10008.1.2.4.203": "pylibjpeg-openjpeg",
    "1.2.840.10008.1.2.5": "pylibjpeg-rle",
}


class PixelDataError(HeartregError, ValueError):
    """A file's pixel data cannot be read (truncated or corrupt)."""


class DecoderUnavailableError(HeartregError, RuntimeError):
    """No installed pixel-data decoder handles a file's transfer syntax."""


#: (0002,0010) JPEG Extended (process 2 & 4): 8- or 12-bit samples.
_JPEG_EXTENDED = "1.2.840.10008.1.2.4.51"


def _choose_plugin(ts: str, path: str, bits_stored: int = 8) -> str:
    """The pydicom decoding plugin to use for `ts` ('' = pydicom's choice).

    `bits_stored` is the file's (0028,0101) Bits Stored: pydicom's gdcm and pillow
    plugins refuse JPEG Extended beyond 8 bits, which leaves a 12-bit file (older CT
    exports) to the GPL libjpeg alone; without this its refusal read as a corrupt file.
    """
    from pydicom.pixels import get_decoder

    try:
        decoder = get_decoder(ts)
    except NotImplementedError:
        raise DecoderUnavailableError(
            f"{path}: transfer syntax {ts} is not supported by pydicom; convert the "
            "study to an uncompressed syntax (e.g. `gdcmconv --raw`)"
        ) from None
    if not decoder.is_encapsulated:
        return ""
    plugins = list(decoder.available_plugins)
    if ts in _GPL_LIBJPEG_SYNTAXES:
        plugins = [p for p in plugins if p != "pylibjpeg"]
    if ts == _JPEG_EXTENDED and bits_stored > 8:
        raise DecoderUnavailableError(
            f"{path}: transfer syntax {ts} ({decoder.UID.name}) with {bits_stored}-bit samples: no installable "
            "decoder heartreg uses reads it (pillow and python-gdcm decode 8-bit JPEG Extended only; "
            "pylibjpeg-libjpeg is GPL); convert the study to an uncompressed syntax first, e.g. with dcmtk's "
            "`dcmdjpeg` or GDCM's `gdcmconv --raw`"
        )
    if not plugins:
        hint = _INSTALL_HINT.get(ts, "a pydicom pixel-data plugin for it")
        raise DecoderUnavailableError(
            f"{path}: no decoder for transfer syntax {ts} ({decoder.UID.name}); "
            f"install {hint} (e.g. `pip install {hint.split(' ')[0]}`); "
            "heartreg does not use the GPL pylibjpeg-libjpeg"
        )
    return "" if plugins == list(decoder.available_plugins) else plugins[0]


def _native_dtype(frame: _Frame) -> np.dtype | None:
    """Dtype of the stored values when `frame` can be read straight from its file.

    That is uncompressed little-endian grey-level data of 8, 16 or 32 bits whose
    (7FE0,0010) value, found at discovery, holds every frame of the file; anything
    else is left to pydicom.
    """
    if (
        frame.pixel_offset is None
        or frame.transfer_syntax_uid not in _NATIVE_LITTLE_ENDIAN
        or frame.samples_per_pixel != 1
        or frame.bits_allocated not in (8, 16, 32)
        or not 1 <= frame.bits_stored <= frame.bits_allocated
    ):
        return None
    kind = "i" if frame.pixel_representation == 1 else "u"
    dtype = np.dtype(f"<{kind}{frame.bits_allocated // 8}")
    frame_bytes = frame.rows * frame.columns * dtype.itemsize
    if frame.pixel_length < frame.n_frames_in_file * frame_bytes:
        return None
    return dtype


def _read_native(frame: _Frame, dtype: np.dtype, out: np.ndarray | None = None) -> np.ndarray:
    """Stored values of one frame read from the file, (rows, cols) of `dtype`.

    Gives what pydicom's native decoder gives (including its shift correction of
    unused high bits when BitsStored < BitsAllocated), into `out` when given (a
    C-contiguous (rows, cols) array of `dtype`).
    """
    arr = np.empty((frame.rows, frame.columns), dtype) if out is None else out
    offset = frame.pixel_offset + (frame.frame or 0) * arr.nbytes
    try:
        with open(frame.path, "rb") as fp:
            fp.seek(offset)
            n_read = fp.readinto(memoryview(arr).cast("B"))
    except OSError as exc:
        raise PixelDataError(
            f"{frame.path}: cannot read pixel data ({exc.strerror or exc})"
        ) from exc
    if n_read != arr.nbytes:
        raise PixelDataError(
            f"{frame.path}: pixel data end after {n_read} of {arr.nbytes} bytes; the file "
            "may be truncated or corrupt: remove it or re-export the series"
        )
    shift = frame.bits_allocated - frame.bits_stored
    if shift:
        np.left_shift(arr, shift, out=arr)
        np.right_shift(arr, shift, out=arr)
    return arr


def _decode(frame: _Frame, plugin: str) -> np.ndarray:
    """Stored values of one frame, (rows, cols).

    Native little-endian data are read straight from the file (`_read_native`);
    everything else is decoded by pydicom.
    """
    from pydicom.pixels import pixel_array

    dtype = _native_dtype(frame)
    if dtype is not None:
        return _read_native(frame, dtype)

    kwargs = {"index": frame.frame} if frame.frame is not None else {}
    if plugin:
        kwargs["decoding_plugin"] = plugin
    try:
        if frame.transfer_syntax_uid == DEFLATED_UID:
            # pydicom's file-path decoder does not inflate: read (and inflate) the dataset
            ds = pydicom.dcmread(frame.path)
            arr = ds.pixel_array if frame.frame is None else pixel_array(ds, index=frame.frame)
            return _checked_shape(arr, frame)
        try:
            arr = pixel_array(frame.path, **kwargs)
        except (InvalidDicomError, AttributeError):
            # no preamble / file meta: pydicom needs the syntax found at discovery
            arr = pixel_array(frame.path, transfer_syntax_uid=frame.transfer_syntax_uid, **kwargs)
    except Exception as exc:  # noqa: BLE001 - decoders raise all kinds
        raise PixelDataError(
            f"{frame.path}: cannot decode pixel data ({type(exc).__name__}: {exc}); "
            "the file may be truncated or corrupt: remove it or re-export the series"
        ) from exc
    return _checked_shape(arr, frame)


def _checked_shape(arr: np.ndarray, frame: _Frame) -> np.ndarray:
    if arr.shape != (frame.rows, frame.columns):
        raise PixelDataError(
            f"{frame.path}: decoded frame has shape {arr.shape}, expected "
            f"({frame.rows}, {frame.columns}) grey levels"
        )
    return arr


#: Largest rescale slope and intercept (magnitude) taken for HU: a CT's are about 1 and -1024.
MAX_RESCALE_SLOPE = 1.0e4
MAX_RESCALE_INTERCEPT = 1.0e6


def _rescale(frame: _Frame) -> tuple[float, float]:
    slope = 1.0 if frame.slope is None else frame.slope
    intercept = 0.0 if frame.intercept is None else frame.intercept
    # a slope beyond MAX_RESCALE maps the smallest step of 16-bit data past any tissue's HU (and a Python int
    # that large overflowed numpy's arithmetic: a traceback for a slope of 1e30)
    if (slope == 0 or not np.isfinite(slope) or not np.isfinite(intercept)
            or abs(slope) > MAX_RESCALE_SLOPE or abs(intercept) > MAX_RESCALE_INTERCEPT):
        raise PixelDataError(
            f"{frame.path}: (0028,1053) Rescale Slope {slope!r} / (0028,1052) Rescale Intercept "
            f"{intercept!r} cannot map stored values to HU; the file is corrupt"
        )
    return slope, intercept


def _int16_possible(frames) -> bool:
    for f in frames:
        s, b = _rescale(f)
        if s != round(s) or b != round(b):
            return False
    return True


def _padding_range(frame: _Frame) -> tuple[int, int] | None:
    """Stored values of (0028,0120) *Pixel Padding Value* to (0028,0121) *Pixel Padding Range Limit*, or None.
    A value written with the other sign (-2000 in unsigned data: 63536) is taken modulo 2**BitsStored."""
    if frame.padding_value is None:
        return None
    size = 1 << frame.bits_stored

    def wrap(v: int) -> int:
        v %= size
        return v - size if frame.pixel_representation == 1 and v >= size // 2 else v

    ends = [wrap(frame.padding_value), wrap(frame.padding_limit if frame.padding_limit is not None else frame.padding_value)]
    return min(ends), max(ends)


def _padding(stored: np.ndarray, frame: _Frame) -> np.ndarray | None:
    """Where `stored` holds padding (see `_padding_range`), or None."""
    if (ends := _padding_range(frame)) is None:
        return None
    mask = (stored >= ends[0]) & (stored <= ends[1])
    return mask if mask.any() else None


def _padding_as_air(hu: np.ndarray, stored: np.ndarray, frame: _Frame) -> np.ndarray:
    """`hu` (rescaled from `stored`) with its padding at most OUTSIDE_HU, in place."""
    if (pad := _padding(stored, frame)) is not None:
        hu[pad] = np.minimum(hu[pad], OUTSIDE_HU)
    return hu


def _slice_hu_int(arr: np.ndarray, frame: _Frame) -> np.ndarray | None:
    """HU as int16 when it fits, else None; padding at most OUTSIDE_HU."""
    s, b = _rescale(frame)
    hu = _padding_as_air(arr.astype(np.int32, copy=False) * int(round(s)) + int(round(b)), arr, frame)
    if hu.size and (hu.min() < _INT16.min or hu.max() > _INT16.max):
        return None
    return hu.astype(np.int16)


def _wrap16(value: int) -> np.int16:
    """`value` modulo 2**16, as int16."""
    return np.int16((value + 32768) % 65536 - 32768)


def _read_hu_int16_into(dst: np.ndarray, frame: _Frame) -> bool:
    """Read a 16-bit native frame straight into the int16 slice `dst`, as HU.

    Returns False, `dst` then holding nothing useful, when the frame is not
    16-bit native data (see `_native_dtype`) or its rescaled values do not fit
    int16. Integer slope and intercept only (see `_int16_possible`): the rescale
    is done in place modulo 2**16, which is exact since the result fits int16.
    """
    dtype = _native_dtype(frame)
    if dtype is None or dtype.itemsize != 2:
        return False
    stored = _read_native(frame, dtype, out=dst.view(dtype))
    pad = _padding(stored, frame)
    values = stored if pad is None else stored[~pad]
    s, b = _rescale(frame)
    s, b = int(round(s)), int(round(b))
    ends = (s * int(values.min()) + b, s * int(values.max()) + b) if values.size else (0, 0)
    padded = None if pad is None else np.minimum(stored[pad].astype(np.int64) * s + b, int(OUTSIDE_HU))
    if min(ends) < _INT16.min or max(ends) > _INT16.max or (padded is not None and padded.min() < _INT16.min):
        return False
    if s != 1:
        np.multiply(dst, _wrap16(s), out=dst)
    if b != 0:
        np.add(dst, _wrap16(b), out=dst)
    if pad is not None:
        dst[pad] = padded
    return True


def _slice_hu_float(arr: np.ndarray, frame: _Frame) -> np.ndarray:
    s, b = _rescale(frame)
    return _padding_as_air(arr.astype(np.float32) * np.float32(s) + np.float32(b), arr, frame)


def _series_rescale(frames):
    """Frames lacking RescaleSlope or RescaleIntercept take the rest of the series' own, where it has one.

    One image of a series without them was read with slope 1, intercept 0: 1024 HU too bright beside its
    neighbours (session 15's DICOM sweep).  Where the others share no one value, or every image lacks them,
    the stored values are taken as HU (slope 1, intercept 0), as before.  Returns (frames, note or "").
    """
    lacking = [f for f in frames if f.slope is None or f.intercept is None]
    if not lacking:
        return frames, ""
    names = _files_text([f.path for f in lacking], 2, names=True)
    given = {(f.slope, f.intercept) for f in frames if f.slope is not None and f.intercept is not None}
    if len(given) == 1:
        slope, intercept = given.pop()
        frames = tuple(f if f.slope is not None and f.intercept is not None
                       else dataclasses.replace(f, slope=slope, intercept=intercept) for f in frames)
        return frames, (f"{len(lacking)} image(s) lack RescaleSlope/RescaleIntercept ({names}): the series' other "
                        f"images' slope {slope:g} and intercept {intercept:g} taken")
    return frames, (f"{len(lacking)} image(s) lack RescaleSlope/RescaleIntercept ({names}): slope 1 and "
                    "intercept 0 assumed where missing (stored values taken as HU)")


def _assemble(plan: _Plan, *, progress: bool = False) -> tuple[np.ndarray, tuple[str, ...]]:
    """Decode and place every slice; returns (hu, notes).

    The output array is allocated once and filled one slice at a time; resampling
    keeps at most two decoded input slices alive. Uncompressed little-endian
    16-bit slices are read from their files straight into the output and rescaled
    in place; other data go through pydicom (see `_decode`).
    """
    frames = plan.frames
    rows, cols = frames[0].rows, frames[0].columns
    odd = [f.path for f in frames if (f.rows, f.columns) != (rows, cols)]
    if odd:
        raise SeriesError(f"images differ in size from {rows}x{cols}: {_files_text(odd)}")
    colour = [f.path for f in frames if f.samples_per_pixel != 1]
    if colour:
        raise SeriesError(f"images are not grey-level (SamplesPerPixel != 1): {_files_text(colour)}")
    plugins = {}
    for f in frames:
        if f.transfer_syntax_uid not in plugins:
            plugins[f.transfer_syntax_uid] = _choose_plugin(f.transfer_syntax_uid, f.path, f.bits_stored)
    notes: list[str] = []
    frames, rescale_note = _series_rescale(frames)
    if rescale_note:
        notes.append(rescale_note)
        plan = dataclasses.replace(plan, frames=frames)
    if padded := sorted({f.padding_value for f in frames if (ends := _padding_range(f)) is not None
                         and max(_rescale(f)[0] * v + _rescale(f)[1] for v in ends) > OUTSIDE_HU}):
        notes.append(f"pixels at (0028,0120) Pixel Padding Value {', '.join(map(str, padded))} (outside the "
                     f"reconstructed field of view) taken as at most {OUTSIDE_HU:g} (air)")
    resampling = plan.resample_k or plan.resample_plane
    use_int16 = not resampling and _int16_possible(frames)
    out = np.empty((plan.n_out, *(plan.grid_shape or (rows, cols))), dtype=np.int16 if use_int16 else np.float32)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=plan.n_out, desc="reading slices", unit="slice", leave=False)

    if not resampling:
        for k, f in enumerate(frames):
            if out.dtype == np.int16 and _read_hu_int16_into(out[k], f):
                pass  # read and rescaled in place, the common case
            elif out.dtype == np.int16:
                arr = _decode(f, plugins[f.transfer_syntax_uid])
                hu = _slice_hu_int(arr, f)
                if hu is None:
                    notes.append(
                        f"values of {os.path.basename(f.path)} exceed int16 after rescale; volume stored as float32"
                    )
                    out = out.astype(np.float32)
                    out[k] = _slice_hu_float(arr, f)
                else:
                    out[k] = hu
            else:
                out[k] = _slice_hu_float(_decode(f, plugins[f.transfer_syntax_uid]), f)
            if bar is not None:
                bar.update()
    else:
        _resample_into(out, plan, plugins, bar)
        notes.append("resampled volume stored as float32")
    if bar is not None:
        bar.close()
    return out, tuple(notes)


def _onto_grid(hu: np.ndarray, dj: float, di: float, grid_shape) -> np.ndarray:
    """One slice (rows, cols) on the widened grid: grid pixel (j, i) is the slice's
    own pixel (j - dj, i - di), linearly interpolated.  The slice is extended by its
    edge values for one pixel, so a grid pixel within one pixel of an acquired one
    keeps acquired values; farther out it is OUTSIDE_HU."""
    from scipy import ndimage

    rows, cols = hu.shape
    canvas = np.pad(hu.astype(np.float32), ((1, grid_shape[0] - rows + 1), (1, grid_shape[1] - cols + 1)), mode="edge")
    moved = ndimage.shift(canvas, (dj, di), order=1, mode="nearest", prefilter=False)[1:-1, 1:-1]
    j = np.arange(grid_shape[0]) - dj
    i = np.arange(grid_shape[1]) - di
    inside = ((j >= -1) & (j <= rows))[:, None] & ((i >= -1) & (i <= cols))[None, :]
    moved[~inside] = OUTSIDE_HU
    return moved


def _resample_into(out, plan: _Plan, plugins, bar) -> None:
    frames, pos = plan.frames, plan.positions_mm
    m = plan.spacing_mm[2]
    cache: dict[int, np.ndarray] = {}

    def slice_at(idx: int) -> np.ndarray:
        if idx not in cache:
            f = frames[idx]
            hu = _slice_hu_float(_decode(f, plugins[f.transfer_syntax_uid]), f)
            dj, di = plan.shifts_px[idx]
            if plan.resample_plane:
                hu = _onto_grid(hu, dj, di, plan.grid_shape)
            for old in [key for key in cache if key < idx - 1]:
                del cache[old]
            cache[idx] = hu
        return cache[idx]

    below = 0
    for k in range(plan.n_out):
        t = pos[0] + k * m
        while below + 1 < len(frames) and pos[below + 1] <= t + 1e-6:
            below += 1
        if below + 1 >= len(frames) or abs(t - pos[below]) <= 1e-6:
            out[k] = slice_at(below)
        else:
            w = (t - pos[below]) / (pos[below + 1] - pos[below])
            a = slice_at(below)
            b = slice_at(below + 1)
            out[k] = (1.0 - w) * a + w * b
        if bar is not None:
            bar.update()
