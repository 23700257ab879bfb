"""The `Volume` result and the geometry plan of one image stack (pixels: `imaging.pixels`).

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
import os
from dataclasses import dataclass, field

import numpy as np

from .discover import _Frame
from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points

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
#: PixelSpacing values of one series differing by at most this share of their value are one spacing:
#: DICOM DS values hold 16 characters, and exporters round them differently (1.5 beside 1.500001).
PIXEL_SPACING_TOL_REL = 1e-4
#: Orthonormality tolerance for ImageOrientationPatient.
ORIENTATION_TOL = 1e-3



class SeriesError(HeartregError, ValueError):
    """A series cannot be turned into a volume (geometry, selection, content)."""


def check_memory(shape_ijk, factor: float, what: str, *, float32: bool = False) -> None:
    """Refuse, in one line, a volume whose reading and processing need more memory than there is.

    Said before the slow work: Linux overcommits, so the volume's array is
    allocated whatever its size and the process is killed (no message, nothing
    written) once reading its slices has filled the memory, minutes later.

    Parameters
    ----------
    shape_ijk : (3,) int
        Columns, rows and slices.
    factor : float
        The caller's peak memory in multiples of the volume's bytes as int16 (1: the volume alone).
    what : str
        The volume, for the message (``series [0] 2.25...``, ``NIfTI file ct.nii.gz``).
    float32 : bool
        Held as float32 (a resampled series): at least twice the int16 bytes.

    Raises
    ------
    SeriesError
        More than the memory available (:func:`hrcore.memory.available_memory_bytes`; nothing is refused
        where that cannot be told).
    """
    from hrcore.memory import available_memory_bytes

    cols, rows, n = (int(v) for v in shape_ijk)
    int16_bytes = 2 * cols * rows * n
    need = max(factor * int16_bytes, 2 * int16_bytes if float32 else int16_bytes)
    free = available_memory_bytes()
    if free is None or need <= free:
        return
    gb = 2.0**30
    share = "" if factor == 1 else f" ({factor:g}x its {int16_bytes / gb:.3g} GB as int16)"
    raise SeriesError(
        f"{what}: {cols} x {rows} x {n} voxels need about {need / gb:.3g} GB of memory{share}, "
        f"and {free / gb:.3g} GB is available; free memory, or give a reconstruction with fewer voxels "
        "(thicker slices, a smaller matrix, or a field of view cropped to the heart)"
    )


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
    cardiac_sync_technique : str or None
        (0018,9037) *Cardiac Synchronization Technique* (``NONE``, ``PROSPECTIVE``,
        ``RETROSPECTIVE``, ...), upper case; None when absent.
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
    cardiac_sync_technique: str | None = None


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
    selection : str
        How the series was chosen among the study's (its place in the listing,
        the other candidates; ``''`` for a volume file): it names series by
        their UIDs, as the terminal does.
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
    selection: str = ""

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


def _files_text(paths, limit: int = 4, *, names: bool = False) -> str:
    """Up to ``limit`` of ``paths``, then how many more; ``names``: the file names
    alone, for notes that go into outputs (a study's subfolders can be named
    after the patient)."""
    paths = list(dict.fromkeys(os.path.basename(p) if names else p for p in paths))
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
    spacings = np.array([f.pixel_spacing for f in frames], dtype=np.float64)
    if np.any(np.ptp(spacings, axis=0) > PIXEL_SPACING_TOL_REL * spacings.max(axis=0)):
        raise SeriesError(
            f"series {label}: PixelSpacing differs between images {sorted({f.pixel_spacing for f in frames})} "
            f"by more than {PIXEL_SPACING_TOL_REL:g} of its value; pass series=... (--series) to choose a "
            "consistent one"
        )
    # row spacing (between rows), column spacing: the median of values that differ by rounding at most
    dr, dc = (float(v) for v in np.median(spacings, axis=0))
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
                "see list_series() (--list-series) and pass series=... (--series)"
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
                    "complete, or pass series=... (--series) for another series"
                )
            resample_k = True
            n_missing = int(np.sum(np.round(gaps / m) - 1).clip(0))
            what = (
                f"{n_missing} missing slice(s)"
                if n_missing and np.allclose(gaps / m, np.round(gaps / m), atol=0.05)
                else "uneven slice spacing"
            )
            # a note is printed as a warning: the files by name, as the grouping's notes (a study's
            # folders can be named after the patient), not by path
            notes.append(
                f"{what}: gaps from {gaps.min():.3f} to {gaps.max():.3f} mm (median "
                f"{m:.3f} mm, largest between {os.path.basename(frames[worst].path)} and "
                f"{os.path.basename(frames[worst + 1].path)}); resampled linearly along the slice normal "
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
            f"(file {os.path.basename(frames[worst].path)}), about {tilt:.2f} deg"
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
