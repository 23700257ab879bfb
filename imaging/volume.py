"""The `Volume` result and the assembly of one image stack into it.

Geometry (DICOM PS3.3 C.7.6.2.1.1): with ``r = IOP[:3]`` (direction of increasing
column index i), ``c = IOP[3:]`` (increasing row index j) and the slice normal
``n = r x c``, a pixel (i, j) of a slice lies at
``IPP + i * PixelSpacing[1] * r + j * PixelSpacing[0] * c``. Slices are ordered by
``IPP . n`` (never by file name or InstanceNumber), so k grows along ``n`` and
``T_patient_from_voxel`` is right-handed.

Irregular stacks are resampled, never silently stacked:

- uneven spacing or missing slices: linear interpolation along the normal onto a
  regular grid at the median spacing, from the first to the last slice position.
  Gaps wider than ``MAX_GAP_FACTOR`` x the median are refused (`SeriesError`).
- sheared stacks (gantry tilt, or slices shifted in-plane): every slice is shifted
  in-plane by linear interpolation onto the grid of the first slice, so the result
  is orthogonal; voxels that fall outside an acquired slice get ``OUTSIDE_HU``.
- resampled volumes are float32; `Volume.slices` keeps describing the acquired
  images, with their voxel coordinate `SliceInfo.k` in the resampled grid.

Pass ``resample=False`` to `imaging.load_study` to refuse irregular stacks instead.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pydicom
from pydicom.errors import InvalidDicomError

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points

from .discover import DEFLATED_UID, _Frame

logger = logging.getLogger(__name__)

#: Gaps wider than this many median spacings are refused rather than interpolated.
MAX_GAP_FACTOR = 3.0
#: Deviation from the median spacing (mm) tolerated as rounding in IPP.
GAP_TOL_MM = 0.02
#: Relative deviation from the median spacing tolerated as rounding.
GAP_TOL_REL = 0.01
#: In-plane slice offsets below this (mm) are treated as rounding, not shear.
SHEAR_TOL_MM = 0.02
#: Value given to resampled voxels that fall outside every acquired slice (air).
OUTSIDE_HU = -1024.0
#: Orthonormality tolerance for ImageOrientationPatient.
ORIENTATION_TOL = 1e-3

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


class SeriesError(HeartregError, ValueError):
    """A series cannot be turned into a volume (geometry, selection, content)."""


class PixelDataError(HeartregError, ValueError):
    """A file's pixel data cannot be read (truncated or corrupt)."""


class DecoderUnavailableError(HeartregError, RuntimeError):
    """No installed pixel-data decoder handles a file's transfer syntax."""


@dataclass(frozen=True)
class SliceInfo:
    """One acquired image of the volume, in ascending position along the normal.

    Attributes
    ----------
    index : int
        Rank of the image in ascending ``position_mm``.
    file : str
        Path of the file holding the image.
    frame : int or None
        0-based frame number in a multi-frame file, else None.
    instance_number : int or None
        (0020,0013) *Instance Number* (informative only, never used for order).
    position_mm : float
        ``ImagePositionPatient . normal``, mm.
    k : float
        Voxel coordinate of this image along k in `Volume.hu` (equal to `index`
        unless the stack was resampled).
    sop_instance_uid : str
    acquisition_time_s : float or None
        Seconds after midnight: (0008,002A) *Acquisition DateTime*, else (0008,0032)
        *Acquisition Time*, else (0008,0033) *Content Time*; for enhanced CT the
        per-frame (0018,9074) *Frame Acquisition DateTime*.
    mid_scan_time_s : float or None
        GE (0019,xx24) *Mid Scan Time* (block ``GEMS_ACQU_01``), s since scan origin.
    trigger_time_ms, nominal_interval_ms, heart_rate_bpm, nominal_cardiac_percent
        (0018,1060) *Trigger Time*, (0018,1062) *Nominal Interval*, (0018,1088)
        *Heart Rate*, (0020,9241) *Nominal Percentage of Cardiac Phase* (classic or
        from the per-frame *Cardiac Synchronization Sequence*).
    """

    index: int
    file: str
    frame: int | None
    instance_number: int | None
    position_mm: float
    k: float
    sop_instance_uid: str
    acquisition_time_s: float | None
    mid_scan_time_s: float | None
    trigger_time_ms: float | None
    nominal_interval_ms: float | None
    heart_rate_bpm: float | None
    nominal_cardiac_percent: float | None


@dataclass(frozen=True)
class SeriesInfo:
    """Identity of the source series, without patient-identifying data.

    ``subset`` names how a series was split (e.g. ``"NominalPercentageOfCardiacPhase=70"``),
    empty when the series was used whole. ``rpeak_timestamps_ms`` is GE (0049,xx0C)
    *RpeakTimeStamps* (block ``GEMS_CT_CARDIAC_001``), ms since the scan origin, or None.
    """

    series_instance_uid: str
    study_instance_uid: str
    frame_of_reference_uid: str
    series_number: int | None
    description: str
    modality: str
    manufacturer: str
    model_name: str
    n_files: int
    subset: str
    rpeak_timestamps_ms: tuple[float, ...] | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class Volume:
    """An image volume in patient coordinates.

    Attributes
    ----------
    hu : (n_slices, n_rows, n_cols) int16 or float32, read-only
        Modality-LUT values (HU for CT), indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64, read-only
        Maps homogeneous ``(i, j, k, 1)`` to LPS mm.
    spacing_mm : (3,) float64, read-only
        Voxel size along i, j, k.
    slices : tuple of SliceInfo
        The acquired images, ascending along the normal.
    series : SeriesInfo
    notes : tuple of str
        Everything worth knowing about how the volume was made.
    source_path : str
    resampled : bool
        True when `hu` was interpolated (see the module docstring).
    waveform_files : tuple of str
        Waveform instances (e.g. the ECG recorded during the scan) of the same
        study found beside the images; used as an R-peak source.
    """

    hu: np.ndarray = field(repr=False)
    T_patient_from_voxel: np.ndarray
    spacing_mm: np.ndarray
    slices: tuple[SliceInfo, ...] = field(repr=False)
    series: SeriesInfo
    notes: tuple[str, ...]
    source_path: str
    resampled: bool = False
    waveform_files: tuple[str, ...] = ()

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(n_slices, n_rows, n_cols)``."""
        return tuple(self.hu.shape)

    def voxel_to_patient(self, ijk) -> np.ndarray:
        """Map voxel coordinates to patient LPS mm.

        Parameters
        ----------
        ijk : (n, 3) or (3,) float
            Voxel coordinates in (i, j, k) order (column, row, slice); note that
            ``hu`` is indexed ``[k, j, i]``.

        Returns
        -------
        (n, 3) or (3,) float64, mm
        """
        pts = np.asarray(ijk, dtype=np.float64)
        if pts.shape[-1:] != (3,) or pts.ndim > 2:
            raise ValueError(f"ijk must have shape (n, 3) or (3,), got {pts.shape}")
        return apply_to_points(self.T_patient_from_voxel, pts)

    def patient_to_voxel(self, xyz) -> np.ndarray:
        """Inverse of `voxel_to_patient`: LPS mm (n, 3) or (3,) -> (i, j, k) float64."""
        pts = np.asarray(xyz, dtype=np.float64)
        if pts.shape[-1:] != (3,) or pts.ndim > 2:
            raise ValueError(f"xyz must have shape (n, 3) or (3,), got {pts.shape}")
        return apply_to_points(np.linalg.inv(self.T_patient_from_voxel), pts)


# ------------------------------------------------------------------ geometry


def _files_text(paths, limit: int = 4) -> str:
    paths = list(dict.fromkeys(paths))
    shown = ", ".join(paths[:limit])
    return shown + (f" and {len(paths) - limit} more" if len(paths) > limit else "")


@dataclass(frozen=True)
class _Plan:
    frames: tuple[_Frame, ...]  # ascending along the normal
    positions_mm: np.ndarray  # (n,)
    shifts_px: np.ndarray  # (n, 2) in-plane (dj, di) offsets of each slice vs. the first
    T_patient_from_voxel: np.ndarray
    spacing_mm: np.ndarray
    n_out: int
    resample_k: bool
    resample_plane: bool
    notes: tuple[str, ...]
    grid_shape: tuple[int, int] | None = None  # (rows, cols) of the output; None: the slices'


def _unit_axes(frames: list[_Frame], label: str):
    missing = [f.path for f in frames if f.ipp is None or f.iop is None or f.pixel_spacing is None]
    if missing:
        raise SeriesError(
            f"series {label}: {len(missing)} image(s) lack ImagePositionPatient, "
            f"ImageOrientationPatient or PixelSpacing ({_files_text(missing)}); "
            "they cannot be placed in patient space"
        )
    iop = np.asarray(frames[0].iop, dtype=np.float64)
    r, c = iop[:3], iop[3:]
    if (
        abs(np.linalg.norm(r) - 1) > ORIENTATION_TOL
        or abs(np.linalg.norm(c) - 1) > ORIENTATION_TOL
        or abs(r @ c) > ORIENTATION_TOL
    ):
        raise SeriesError(
            f"series {label}: ImageOrientationPatient {tuple(iop)} is not two orthonormal "
            f"vectors (file {frames[0].path})"
        )
    r = r / np.linalg.norm(r)
    c = c - (c @ r) * r
    c = c / np.linalg.norm(c)
    return r, c, np.cross(r, c)


def _plan_geometry(frames: list[_Frame], *, label: str, resample: bool = True) -> _Plan:
    """Order one orientation-consistent stack and decide how to grid it."""
    r, c, n = _unit_axes(frames, label)
    spacings = {f.pixel_spacing for f in frames}
    if len(spacings) > 1:
        raise SeriesError(
            f"series {label}: PixelSpacing differs between images {sorted(spacings)}; "
            "pass series=... to choose a consistent one"
        )
    dr, dc = frames[0].pixel_spacing  # row spacing (between rows), column spacing
    ipp = np.array([f.ipp for f in frames], dtype=np.float64)
    pos = ipp @ n
    order = np.argsort(pos, kind="stable")
    frames = [frames[i] for i in order]
    ipp, pos = ipp[order], pos[order]
    notes: list[str] = []
    nf = len(frames)

    if nf == 1:
        thick = frames[0].slice_thickness_mm
        m = thick if thick and thick > 0 else 1.0
        notes.append(
            "single image: slice spacing set to "
            + (f"SliceThickness {m:g} mm" if thick else "1 mm (no SliceThickness)")
        )
        gaps = np.zeros(0)
    else:
        gaps = np.diff(pos)
        dup = np.flatnonzero(gaps < GAP_TOL_MM)
        if dup.size:
            files = [frames[i].path for i in dup] + [frames[i + 1].path for i in dup]
            raise SeriesError(
                f"series {label}: {dup.size} pair(s) of images share a position "
                f"(e.g. {pos[dup[0]]:.3f} mm): {_files_text(files)}; "
                "see list_series() and pass series=..."
            )
        m = float(np.median(gaps))
    resample_k = False
    if nf > 2:
        worst = int(np.argmax(np.abs(gaps - m)))
        if np.abs(gaps[worst] - m) > max(GAP_TOL_MM, GAP_TOL_REL * m):
            wide = np.flatnonzero(gaps > MAX_GAP_FACTOR * m)
            if wide.size:
                w = int(wide[0])
                raise SeriesError(
                    f"series {label}: gap of {gaps[w]:.3f} mm between positions "
                    f"{pos[w]:.3f} and {pos[w + 1]:.3f} mm (files {frames[w].path}, "
                    f"{frames[w + 1].path}) exceeds {MAX_GAP_FACTOR:g} x the median spacing "
                    f"{m:.3f} mm; too much is missing to interpolate. Check the export is "
                    "complete, or pass series=... for another series"
                )
            resample_k = True
            n_missing = int(np.sum(np.round(gaps / m) - 1).clip(0))
            what = (
                f"{n_missing} missing slice(s)"
                if n_missing and np.allclose(gaps / m, np.round(gaps / m), atol=0.05)
                else "uneven slice spacing"
            )
            notes.append(
                f"{what}: gaps from {gaps.min():.3f} to {gaps.max():.3f} mm (median "
                f"{m:.3f} mm, largest between {frames[worst].path} and "
                f"{frames[worst + 1].path}); resampled linearly along the slice normal "
                f"onto a regular grid at {m:.3f} mm"
            )
        else:
            m = float((pos[-1] - pos[0]) / (nf - 1))
    elif nf == 2:
        m = float(pos[1] - pos[0])

    # In-plane offset of each slice's origin from the first slice's, along r and c.
    d = (ipp - ipp[0]) - np.outer(pos - pos[0], n)
    d_i_mm, d_j_mm = d @ r, d @ c
    shear_mm = np.hypot(d_i_mm, d_j_mm)
    resample_plane = bool(nf > 1 and shear_mm.max() > SHEAR_TOL_MM)
    if resample_plane:
        span = pos[-1] - pos[0]
        tilt = np.degrees(np.arctan2(shear_mm[-1], span)) if span > 0 else 0.0
        gantry = frames[0].gantry_tilt_deg
        worst = int(np.argmax(shear_mm))
        notes.append(
            f"sheared stack (gantry tilt or shifted slices): ImagePositionPatient steps are "
            f"not along the slice normal; in-plane offsets up to {shear_mm.max():.3f} mm "
            f"(file {frames[worst].path}), about {tilt:.2f} deg"
            + (f", GantryDetectorTilt {gantry:g} deg" if gantry else "")
            + "; each slice resampled in-plane (linear) onto an orthogonal grid widened to "
            "the bounding box of every slice's pixels (no acquired pixel dropped; GRID), voxels "
            f"outside the acquired slice set to {OUTSIDE_HU:g}"
        )
    if (resample_k or resample_plane) and not resample:
        raise SeriesError(
            f"series {label} is not a regular orthogonal stack: {notes[-1]}. "
            "Pass resample=True to interpolate it"
        )

    thick = frames[0].slice_thickness_mm
    if nf > 1 and thick and abs(thick - m) > 0.1 * m:
        notes.append(
            f"SliceThickness {thick:g} mm differs from the slice spacing {m:.3f} mm ("
            + ("slices overlap" if thick > m else "gaps between slices")
            + ")"
        )
    n_out = int(np.floor((pos[-1] - pos[0]) / m + 1e-6)) + 1 if nf > 1 else 1
    T = np.eye(4)
    T[:3, 0] = r * dc
    T[:3, 1] = c * dr
    T[:3, 2] = n * m
    T[:3, 3] = ipp[0]
    shifts = np.column_stack([d_j_mm / dr, d_i_mm / dc])
    grid_shape = None
    if resample_plane:
        # widen the first slice's grid to hold every slice's pixels: slice pixel
        # (j, i) lands on grid (j + dj, i + di)
        rows, cols = frames[0].rows, frames[0].columns
        lo = np.ceil(np.maximum(0.0, -shifts.min(axis=0)) - 1e-6).astype(int)
        hi = np.ceil(np.maximum(0.0, shifts.max(axis=0)) - 1e-6).astype(int)
        shifts = shifts + lo
        T[:3, 3] = ipp[0] - lo[1] * dc * r - lo[0] * dr * c
        grid_shape = (int(rows + lo[0] + hi[0]), int(cols + lo[1] + hi[1]))
        notes = [n.replace(
            "GRID",
            f"{grid_shape[0]} x {grid_shape[1]} pixels at the slices' spacing, the first slice's grid "
            f"extended by {lo[0]} / {hi[0]} rows and {lo[1]} / {hi[1]} columns",
        ) for n in notes]
    return _Plan(
        frames=tuple(frames),
        positions_mm=pos,
        shifts_px=shifts,
        T_patient_from_voxel=T,
        spacing_mm=np.array([dc, dr, m], dtype=np.float64),
        n_out=n_out,
        resample_k=resample_k,
        resample_plane=resample_plane,
        notes=tuple(notes),
        grid_shape=grid_shape,
    )


# -------------------------------------------------------------------- pixels


def _choose_plugin(ts: str, path: str) -> str:
    """The pydicom decoding plugin to use for `ts` ('' = pydicom's choice)."""
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


def _rescale(frame: _Frame) -> tuple[float, float]:
    slope = 1.0 if frame.slope is None else frame.slope
    intercept = 0.0 if frame.intercept is None else frame.intercept
    if slope == 0 or not np.isfinite(slope) or not np.isfinite(intercept):
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


def _slice_hu_int(arr: np.ndarray, frame: _Frame) -> np.ndarray | None:
    """HU as int16 when it fits, else None."""
    s, b = _rescale(frame)
    hu = arr.astype(np.int32, copy=False) * int(round(s)) + int(round(b))
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
    s, b = _rescale(frame)
    s, b = int(round(s)), int(round(b))
    lo, hi = int(stored.min()), int(stored.max())
    ends = (s * lo + b, s * hi + b)
    if min(ends) < _INT16.min or max(ends) > _INT16.max:
        return False
    if s != 1:
        np.multiply(dst, _wrap16(s), out=dst)
    if b != 0:
        np.add(dst, _wrap16(b), out=dst)
    return True


def _slice_hu_float(arr: np.ndarray, frame: _Frame) -> np.ndarray:
    s, b = _rescale(frame)
    return arr.astype(np.float32) * np.float32(s) + np.float32(b)


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
            plugins[f.transfer_syntax_uid] = _choose_plugin(f.transfer_syntax_uid, f.path)
    notes: list[str] = []
    no_rescale = [f.path for f in frames if f.slope is None or f.intercept is None]
    if no_rescale:
        notes.append(
            f"{len(no_rescale)} image(s) lack RescaleSlope/RescaleIntercept "
            f"({_files_text(no_rescale, 2)}): assumed slope 1, intercept 0 (stored values "
            "taken as HU)"
        )
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
                        f"values of {f.path} exceed int16 after rescale; volume stored as float32"
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
