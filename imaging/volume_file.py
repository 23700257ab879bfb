"""A CT volume from one file: NIfTI (research data sets) or NRRD (3D Slicer).

NIfTI stores its affine in RAS (+x right, +y anterior, +z superior), NRRD names
its space (Slicer writes LPS); heartreg works in DICOM LPS, so the affine is
converted and the volume's notes say so.  The voxel axes are kept as on disk
(array ``[i, j, k]`` becomes ``hu[k, j, i]``), except that the k axis is
reversed when needed to make ``T_patient_from_voxel`` right-handed, as for a
DICOM stack.

Such a file has no slice clock and no ECG: the returned volume's slices have
no acquisition times, so its cardiac phase is unknown (see
:func:`imaging.compute_phase_report`, which refuses it with a ``GatingError``).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import warnings
from pathlib import Path

import numpy as np

from hrcore.geometry import apply_to_points
from hrcore.redact import pseudonym_uid
from imaging.nrrd import NrrdError, is_nrrd_path, read_nrrd, read_nrrd_header
from imaging.files import gzip_damage, is_analyze_header
from imaging.grouping import StudyWarning
from imaging.volume import OUTSIDE_HU, SeriesError, SeriesInfo, SliceInfo, Volume, check_memory

__all__ = ["nifti_lps_affine", "nifti_unit", "is_nifti_path", "is_nrrd_path", "is_volume_file", "read_nifti_volume", "read_nrrd_volume",
           "read_volume_file"]

_LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
#: Largest |cosine| between two voxel axes accepted as orthogonal.
ORTHOGONAL_TOL = 1e-3


def is_nifti_path(path) -> bool:
    """True when ``path`` names a NIfTI file (``.nii`` or ``.nii.gz``)."""
    return str(path).lower().endswith((".nii", ".nii.gz"))


def is_volume_file(path) -> bool:
    """True when ``path`` names a CT volume file heartreg reads (NIfTI or NRRD)."""
    return is_nifti_path(path) or is_nrrd_path(path)


def read_volume_file(path, memory_factor: float = 1.0) -> Volume:
    """Read a NIfTI or NRRD CT volume (by its name's ending) as an LPS :class:`imaging.Volume`.

    ``memory_factor``: the caller's peak memory in multiples of the volume's int16 bytes; a volume needing
    more than the memory available is refused from its header, before its voxels are read
    (:func:`imaging.volume.check_memory`, as ``load_study``).

    Examples
    --------
    >>> import tempfile
    >>> import nibabel as nib
    >>> import numpy as np
    >>> from imaging import read_volume_file
    >>> path = tempfile.mkdtemp() + "/ct.nii.gz"
    >>> nib.save(nib.Nifti1Image(np.full((4, 5, 6), -1000, np.int16), np.eye(4)), path)
    >>> read_volume_file(path).notes[0]
    'NIfTI input: affine taken as RAS (NIfTI convention) and converted to LPS; no slice clock'
    """
    if (shape := _stored_shape(path)) is not None:
        check_memory(shape, memory_factor, f"{'NRRD' if is_nrrd_path(path) else 'NIfTI'} file {path}")
    return read_nrrd_volume(path) if is_nrrd_path(path) else read_nifti_volume(path)


def _stored_shape(path) -> tuple[int, int, int] | None:
    """The volume's (columns, rows, slices) from its header alone; None where the header cannot tell (the
    reader then says what is wrong)."""
    try:
        if is_nrrd_path(path):  # the spatial axes last (a list axis first)
            sizes = [int(v) for v in read_nrrd_header(path)["sizes"].split()][-3:]
        else:  # the spatial axes first (x, y, z, then time or components)
            import nibabel as nib

            with _nibabel_fixes():  # said again, judged, by the reader
                sizes = [int(v) for v in nib.load(str(path)).shape][:3]  # the header only: the voxels load lazily
    except Exception:  # noqa: BLE001 - a bad file is refused by its reader, in its words
        return None
    return tuple(sizes) if len(sizes) == 3 else None


def _uid(digest: str, what: str) -> str:
    """A deterministic DICOM UID from the file's content (2.25 root, UUID-sized; the outputs' pseudonym rule)."""
    return pseudonym_uid(what + digest)


#: mm per unit of each NIfTI spatial unit code (``xyzt_units & 7``); 0 (unknown) is mm, as NIfTI practice.
NIFTI_MM_PER_UNIT = {0: (1.0, "unknown (taken as mm)"), 1: (1000.0, "metres"), 2: (1.0, "mm"), 3: (1e-3, "micrometres")}


def nifti_unit(img) -> tuple[float, str]:
    """mm per unit of a NIfTI image's spatial unit (``xyzt_units``) and the unit's name; (nan, why) when its code
    is none of NIfTI's four (nibabel raises a KeyError on such a header)."""
    code = int(img.header["xyzt_units"]) & 0x07
    if code not in NIFTI_MM_PER_UNIT:
        return float("nan"), (f"its spatial unit code (xyzt_units & 7) is {code}, none of NIfTI's (0 unknown, "
                              "1 metre, 2 mm, 3 micrometre): write the file with its unit")
    return NIFTI_MM_PER_UNIT[code]


def nifti_lps_affine(img) -> tuple[np.ndarray, str]:
    """The LPS affine of a nibabel NIfTI image, in mm, and why it cannot be trusted ('' when it can).

    The affine is scaled to mm by the header's spatial unit (``xyzt_units``:
    metres x 1000, micrometres x 0.001; unknown is mm); an unknown unit code is
    said instead.  nibabel's affine is the sform whenever ``sform_code`` is set;
    ITK, and so 3D Slicer, take the qform when both are set (unless the sform is
    scanner coordinates).  Where both are set and place the volume's corners more
    than half its smallest voxel apart, the file means two things and no choice
    is safe: that is said instead.
    """
    header = img.header
    mm, unit = nifti_unit(img)
    T = _LPS_FROM_RAS @ np.asarray(img.affine, dtype=np.float64)
    if not np.isfinite(mm):
        return T, unit
    T[:3, :] *= mm
    if int(header["sform_code"]) > 0 and int(header["qform_code"]) > 0:
        shape = np.asarray(img.shape[:3], float)
        corners = np.stack(np.meshgrid(*[[0.0, n - 1] for n in shape], indexing="ij"), -1).reshape(-1, 3)
        apart = mm * np.linalg.norm(apply_to_points(img.get_sform(), corners) - apply_to_points(img.get_qform(),
                                                                                                corners), axis=1).max()
        voxel = mm * float(np.min(header.get_zooms()[:3]))
        if apart > 0.5 * voxel:
            return T, (f"its sform and qform place the volume up to {apart:.1f} mm apart (sform_code "
                       f"{int(header['sform_code'])}, qform_code {int(header['qform_code'])}): nibabel reads the "
                       "sform, ITK and 3D Slicer the qform; write the file with one orientation (e.g. nibabel's "
                       "img.set_qform(img.get_sform()))")
    return T, ""


def nifti_misnamed(path) -> str:
    """Why a ``.nii.gz`` that is not gzip-compressed cannot be read as named ('' for any other file): an
    uncompressed NIfTI under a .gz name (nibabel says 'Not a gzipped file'), or no NIfTI at all."""
    if not str(path).lower().endswith(".gz"):
        return ""
    try:
        with open(path, "rb") as f:
            head = f.read(352)
    except OSError:
        return ""  # said by the reader
    if head[:2] == b"\x1f\x8b":
        return ""
    if is_analyze_header(head):
        return "is an uncompressed NIfTI file named .nii.gz (no gzip compression): rename it to .nii"
    return "is not gzip-compressed, as a .nii.gz must be, nor a NIfTI file: check what was exported"


def _check_is_file(path: Path, kind: str) -> None:
    """Refuse a missing volume file, or a folder named like one, in one line."""
    if path.is_dir():
        raise SeriesError(f"{path} is a folder named like a {kind} file: rename it if it holds a DICOM study")
    if not path.is_file():
        raise SeriesError(f"{kind} file {path} does not exist" if not path.exists() else
                          f"{kind} file {path} is not a regular file (a named pipe or device)")


def degenerate_affine(T) -> str:
    """Why a voxel -> patient affine places no voxels ('degenerate affine (voxel sizes ...)'), '' when it does:
    NaN or infinite entries, or an axis of no length."""
    spacing = np.linalg.norm(np.asarray(T, dtype=float)[:3, :3], axis=0)
    if np.any(spacing < 1e-6) or not np.all(np.isfinite(T)):
        return f"degenerate affine (voxel sizes {spacing.tolist()} mm)"
    return ""


def nifti_unoriented(img) -> bool:
    """Whether a NIfTI image has no orientation (qform_code and sform_code 0): nibabel then places it by guess."""
    return int(img.header["qform_code"]) == 0 and int(img.header["sform_code"]) == 0


def load_nifti(path):
    """``(image, voxels, header fixes)`` of a NIfTI file through nibabel, its repairs caught, not printed.

    nibabel mends some headers as it loads them and says so on stderr through
    its own logger (``pixdim[1,2,3] should be non-zero; setting 0 dims to
    1``): the fixes come back instead, for the caller to judge.  Raises
    whatever nibabel raises for a file it cannot read.

    Trailing axes of length one are dropped (``x, y, z, 1`` or ``x, y, z, 1, 1``:
    one time point, one component, as some tools write a 3-D volume).
    """
    import nibabel as nib

    with _nibabel_fixes() as fixes:
        img = nib.load(str(path))
        data = np.asarray(img.dataobj)
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    return img, data, fixes


@contextlib.contextmanager
def _nibabel_fixes():
    """The messages nibabel's logger gives within the block (its header repairs), as a list, not printed."""
    fixes = []

    class _Catch(logging.Handler):
        def emit(self, record):
            fixes.append(record.getMessage())

    logger = logging.getLogger("nibabel.global")
    kept = logger.handlers[:]
    logger.handlers[:] = [_Catch()]
    try:
        yield fixes
    finally:
        logger.handlers[:] = kept


def read_nifti_volume(path) -> Volume:
    """Read a 3-D NIfTI CT volume as an :class:`imaging.Volume` in LPS.

    Parameters
    ----------
    path : path
        ``.nii`` or ``.nii.gz`` file holding HU values (the scaling slope and
        intercept of the header are applied).

    Returns
    -------
    Volume
        ``hu`` int16 when the values are whole numbers in range, else float32;
        slices without any clock; ``series`` with UIDs derived from the file's
        content (the same file gives the same UIDs) and no patient data.

    Raises
    ------
    SeriesError
        Missing or unreadable file, not 3-D, or an affine with sheared or
        degenerate axes.

    Examples
    --------
    >>> import tempfile
    >>> import nibabel as nib
    >>> import numpy as np
    >>> from imaging import read_nifti_volume
    >>> path = tempfile.mkdtemp() + "/ct.nii.gz"
    >>> nib.save(nib.Nifti1Image(np.full((4, 5, 6), -1000, np.int16), np.diag([0.5, 0.5, 2.0, 1.0])), path)
    >>> volume = read_nifti_volume(path)
    >>> volume.hu.shape, volume.spacing_mm.tolist()
    ((6, 5, 4), [0.5, 0.5, 2.0])
    """
    path = Path(path)
    _check_is_file(path, "NIfTI")
    if misnamed := nifti_misnamed(path):
        raise SeriesError(f"NIfTI file {path} {misnamed}")
    damage = gzip_damage(path)
    if damage:
        raise SeriesError(f"NIfTI file {path} is damaged ({damage}): copy it again from its source")
    try:
        img, data, fixes = load_nifti(path)
    except Exception as exc:  # noqa: BLE001 - nibabel raises many types for bad files
        raise SeriesError(f"cannot read NIfTI file {path}: {exc}") from None
    unoriented = nifti_unoriented(img)
    if unoriented and any("pixdim" in fix for fix in fixes):  # its voxels would be 1 mm for want of any size
        raise SeriesError(f"NIfTI file {path} gives its voxels no size (pixdim 0) and no orientation (no qform or "
                          "sform): write the file with its voxel size and orientation")
    if data.ndim != 3:
        raise SeriesError(f"NIfTI file {path} must hold a 3-D volume, got shape {data.shape}")
    T, conflict = nifti_lps_affine(img)
    if conflict:
        raise SeriesError(f"NIfTI file {path}: {conflict}")
    note = "affine taken as RAS (NIfTI convention) and converted to LPS"
    if unoriented:
        # nibabel then gives the pixel sizes on a diagonal: the orientation is a guess
        note = ("no orientation in the header (qform_code and sform_code 0): the voxel axes placed as nibabel "
                "places an unoriented file (x flipped, centred on the volume), so left-right and front-back may "
                "be wrong")
        # not the file's name: batch writes warnings into its records, and a name can name the patient
        warnings.warn(f"NIfTI input: {note}; write the file with its orientation (an sform or qform)",
                      StudyWarning, stacklevel=2)
    mm, unit = nifti_unit(img)
    if mm != 1.0:
        note += f"; its {unit} (xyzt_units) scaled to mm"
    return _volume(data, T, path, "NIfTI", note)


def read_nrrd_volume(path) -> Volume:
    """Read a 3-D NRRD CT volume (3D Slicer's format) as an :class:`imaging.Volume` in LPS.

    Parameters
    ----------
    path : path
        ``.nrrd`` file with an attached header holding HU values.

    Returns and raises as :func:`read_nifti_volume` (a layered segmentation
    file is no CT volume: ``SeriesError``).

    Examples
    --------
    3D Slicer's sample chest CT, shipped with the ``slicerio`` package:

    >>> from pathlib import Path
    >>> import slicerio
    >>> from imaging import read_nrrd_volume
    >>> volume = read_nrrd_volume(Path(slicerio.__file__).parent / "data" / "CTChest4.nrrd")
    >>> volume.hu.shape, [round(float(s), 2) for s in volume.spacing_mm]
    ((34, 128, 128), [3.05, 3.05, 10.0])
    """
    path = Path(path)
    _check_is_file(path, "NRRD")
    try:
        data_kji, T, fields = read_nrrd(path)
    except NrrdError as exc:
        raise SeriesError(str(exc)) from None
    if data_kji.ndim != 3:
        raise SeriesError(f"NRRD file {path} holds {data_kji.shape[0]} layers (a segmentation?), not a CT volume")
    space = ("affine converted to LPS from the file's space" if "space" in fields
             else "no 'space' field: the axes taken as LPS, as 3D Slicer writes them")
    return _volume(np.transpose(data_kji, (2, 1, 0)), T, path, "NRRD", space)


def _volume(data, T, path: Path, kind: str, affine_note: str) -> Volume:
    """The :class:`Volume` of a file's voxels ``data[i, j, k]`` and LPS affine ``T``."""
    if problem := degenerate_affine(T):
        raise SeriesError(f"{kind} file {path}: {problem}")
    axes = T[:3, :3] / np.linalg.norm(T[:3, :3], axis=0)
    cosines = np.abs(axes.T @ axes - np.eye(3))
    if cosines.max() > ORTHOGONAL_TOL:
        raise SeriesError(
            f"{kind} file {path}: the voxel axes are not orthogonal (sheared affine); "
            "resample it to an orthogonal grid first"
        )
    notes = [f"{kind} input: {affine_note}; no slice clock"]
    hu = np.ascontiguousarray(np.transpose(data, (2, 1, 0)))  # [k, j, i]
    if np.linalg.det(T[:3, :3]) < 0:  # left-handed on disk: reverse k
        hu = np.ascontiguousarray(hu[::-1])
        flip = np.eye(4)
        flip[2, 2], flip[2, 3] = -1.0, hu.shape[0] - 1
        T = T @ flip
        notes.append(f"{kind} input: slice order reversed to make the voxel frame right-handed")
    if np.issubdtype(hu.dtype, np.floating) and not np.all(np.isfinite(hu)):
        bad = ~np.isfinite(hu)
        what = f"{int(bad.sum())} voxel(s) not a number (NaN or infinite) taken as air ({OUTSIDE_HU:g} HU)"
        notes.append(f"{kind} input: {what}")
        warnings.warn(f"{kind} input: {what}; check how the file was written", StudyWarning, stacklevel=3)
        hu = np.where(bad, np.float32(OUTSIDE_HU), hu)
    fits_int16 = (np.issubdtype(hu.dtype, np.integer) and hu.dtype.itemsize <= 2 and hu.dtype != np.uint16) or (
        np.all(np.isfinite(hu)) and np.array_equal(hu, np.round(hu)) and hu.min() >= -32768 and hu.max() <= 32767
    )
    hu = hu.astype(np.int16 if fits_int16 else np.float32, copy=False)
    hu.setflags(write=False)
    T.setflags(write=False)
    spacing = np.linalg.norm(T[:3, :3], axis=0)
    spacing.setflags(write=False)

    # the volume's identity: every voxel (a CT edited anywhere is another series; ~0.1 s per 150 MB), its grid, its place
    digest = hashlib.sha256(memoryview(hu).cast("B"))
    digest.update(np.asarray(hu.shape).tobytes() + hu.dtype.str.encode() + T.tobytes())
    digest = digest.hexdigest()
    normal = T[:3, 2] / spacing[2]
    slices = tuple(
        SliceInfo(
            index=k, file=str(path), frame=k, instance_number=None,
            position_mm=float(apply_to_points(T, [0.0, 0.0, k]) @ normal),
            k=float(k), sop_instance_uid="", acquisition_time_s=None, mid_scan_time_s=None,
            trigger_time_ms=None, nominal_interval_ms=None, heart_rate_bpm=None,
            nominal_cardiac_percent=None,
        )
        for k in range(hu.shape[0])
    )
    series = SeriesInfo(
        series_instance_uid=_uid(digest, "series"),
        study_instance_uid=_uid(digest, "study"),
        frame_of_reference_uid=_uid(digest, "frame"),
        series_number=None,
        description="",
        modality="CT",
        manufacturer="",
        model_name="",
        n_files=1,
        subset="",
    )
    return Volume(
        hu=hu, T_patient_from_voxel=T, spacing_mm=spacing, slices=slices, series=series,
        notes=tuple(notes), source_path=str(path),
    )
