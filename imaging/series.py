"""From any CT study folder to a `Volume`: `list_series` and `load_study`.

Files are found recursively whatever their names (:mod:`imaging.discover`), grouped
(:mod:`imaging.grouping`) by (0020,000E) *Series Instance UID* and split further when a series mixes
orientations, image sizes, localizers (``LOCALIZER`` in *Image Type* / *Frame Type*)
or repeats slice positions (several cardiac phases in one series: split by the first
of *Nominal Percentage of Cardiac Phase*, *Trigger Time*, *Temporal Position*,
*Acquisition Number* that separates them). Images identical by SOP Instance UID
(copies of one file) are kept once.

Without ``series=``, `load_study` takes the axial CT stack with the most slices
(never a localizer) and says why in ``Volume.notes``. Geometry and resampling rules
are in :mod:`imaging.volume`.
"""

from __future__ import annotations

import logging
import os
import warnings

import numpy as np

from hrcore.redact import pseudonym_uid

from .grouping import _LOADABLE, SeriesSummary, StudyWarning, _Group, _scan_groups
from .nominal import percent_not_gated, trigger_not_gated
from .pixels import _assemble, _choose_plugin, _decode, _slice_hu_float
from .volume import SeriesError, SeriesInfo, SliceInfo, Volume, _files_text, _plan_geometry, check_memory

logger = logging.getLogger(__name__)

#: What a `SliceInfo` and the `SeriesInfo` copy unchanged from the frames' headers.
_SLICE_FROM_FRAME = (
    "instance_number", "sop_instance_uid", "acquisition_time_s", "mid_scan_time_s", "trigger_time_ms",
    "nominal_interval_ms", "heart_rate_bpm", "nominal_cardiac_percent", "cardiac_sync_technique",
)  # fmt: skip
_SERIES_FROM_FRAME = (
    "series_instance_uid", "study_instance_uid", "frame_of_reference_uid", "series_number", "description",
    "modality", "manufacturer", "model_name",
)  # fmt: skip


# ------------------------------------------------------------------- public


def list_series(path, *, progress: bool = False) -> tuple[SeriesSummary, ...]:
    """List every image group (and non-image series) found under `path`.

    Parameters
    ----------
    path : str or os.PathLike
        A study folder (searched recursively) or a single DICOM file.
    progress : bool
        Show a progress bar on stderr while reading headers.

    Returns
    -------
    tuple of SeriesSummary
        In a stable order; ``index`` is what ``load_study(series=index)`` takes.

    Examples
    --------
    The repository's sample study holds a gated CT series and its ECG:

    >>> from imaging import list_series
    >>> [(s.index, s.kind, s.n_slices) for s in list_series("sample_dicom/ct")]
    [(0, 'volume', 72), (1, 'non-image', 0)]
    """
    _, groups, _ = _scan_groups(path, progress)
    return tuple(g.summary for g in groups)


def _choices(groups: list[_Group]) -> str:
    """The series in one line, without their free-text descriptions: ``heartreg batch`` writes error lines
    into its records, and a description can name the patient (``--list-series`` shows them)."""
    lines = []
    for g in groups:
        s = g.summary
        lines.append(
            f"[{s.index}] {s.uid} #{s.series_number} {s.modality} "
            f"{s.kind} {s.orientation} {s.n_slices} image(s)"
            + (f" {s.subset}" if s.subset else "")
            + (f" ({s.reason})" if s.reason and s.kind != "volume" else "")
        )
    return "; ".join(lines)  # one line: the CLI prints one line per error


def _gating(group: _Group, ecg_studies: set) -> str:
    """What could time the cardiac phase of every image of ``group`` ('' if nothing)."""
    frames = group.frames
    if any(f.rpeak_timestamps_ms for f in frames) and all(f.mid_scan_time_s is not None for f in frames):
        return "GE RpeakTimeStamps"
    if frames and frames[0].study_instance_uid in ecg_studies and all(
        f.acquisition_time_s is not None for f in frames
    ):
        return "the study's ECG waveform"
    if all(f.trigger_time_ms is not None and (f.nominal_interval_ms or f.heart_rate_bpm) for f in frames) and (
        not trigger_not_gated(frames)
    ):
        return "TriggerTime"
    if all(f.nominal_cardiac_percent is not None for f in frames) and not percent_not_gated(frames):
        return "NominalPercentageOfCardiacPhase"
    return ""


def _one_scan(groups: list[_Group]) -> bool:
    """Whether the series are reconstructions of one scan: the same cardiac phase and the same slice positions
    (several phases of a gated study are told apart by their phase, not by their images' texture)."""
    def signature(g):  # its slices' positions (any orientation: not their height alone), to 0.1 mm
        return g.summary.cardiac, frozenset(tuple(np.round(f.ipp, 1)) for f in g.frames if f.ipp is not None)

    return len({signature(g) for g in groups}) == 1


def _texture_hu(group: _Group) -> float | None:
    """How far neighbouring voxels of soft tissue (-100 to 300 HU) differ in the series' middle image, median HU.

    Two reconstructions of one scan alike in size differ by their kernel: a soft-tissue one (a few HU between
    neighbours) or a lung or bone one (tens: sharp and noisy), which the segmentation of soft tissue and
    contrast blood reads worse (a lung kernel's copy of the real CT, taken on a tie by its lower index: the
    model 1.3 % smaller, other notes).  None where the image cannot be read or holds too little soft tissue.
    """
    frames = sorted(group.frames, key=lambda f: f.ipp or (0.0, 0.0, 0.0))  # the middle of the stack, not of the disk
    frame = frames[len(frames) // 2]
    try:
        hu = _slice_hu_float(_decode(frame, _choose_plugin(frame.transfer_syntax_uid, frame.path, frame.bits_stored)),
                             frame)
    except Exception:  # noqa: BLE001 - the load itself says what is wrong with the file
        return None
    soft = (hu > -100) & (hu < 300)
    pairs = soft[:, 1:] & soft[:, :-1]
    if np.count_nonzero(pairs) < 100:
        return None
    return float(np.median(np.abs(np.diff(hu, axis=1))[pairs]))


def _select(groups: list[_Group], series, *, prefer_gated: bool = False, ecg_studies=frozenset(),
            unreadable=()) -> tuple[_Group, str]:
    loadable = [g for g in groups if g.summary.kind in _LOADABLE]
    if series is None:
        ranked = [g for g in loadable if g.summary.modality == "CT" and g.summary.kind == "volume"]
        if not ranked:
            ranked = [g for g in loadable if g.summary.modality == "CT" and g.summary.kind == "slice"]
        broken = (f"{len(unreadable)} DICOM file(s) cannot be read, e.g. {unreadable[0][0]}: {unreadable[0][1]}"
                  if unreadable else "")
        if not loadable and broken:  # the images are there, but none could be read: say why, not --series
            raise SeriesError(f"no CT image stack: {broken}")
        if not ranked and len(groups) == 1 and groups[0].summary.kind == "unusable":  # nothing else to choose
            raise SeriesError(f"no CT image stack in {_files_text(groups[0].summary.files, 2)}: {groups[0].summary.reason}")
        if not ranked:
            raise SeriesError(
                "no CT image stack found automatically" + (f" ({broken})" if broken else "")
                + "; choose one with --series INDEX or UID (series= in Python) among: " + _choices(groups)
            )
        gating = {id(g): _gating(g, ecg_studies) for g in ranked} if prefer_gated else {}

        def rank(g):
            return prefer_gated and not gating[id(g)], g.summary.orientation != "axial", -g.summary.n_slices

        ranked.sort(key=lambda g: (*rank(g), g.summary.index))
        tied = [g for g in ranked if rank(g) == rank(ranked[0])]
        texture = {id(g): _texture_hu(g) for g in tied} if len(tied) > 1 and _one_scan(tied) else {}
        if texture:  # as good by their size: the smoother reconstruction (a soft-tissue kernel, not a lung one)
            tied.sort(key=lambda g: (texture[id(g)] is None, texture[id(g)] or 0.0, g.summary.index))
            ranked = tied + ranked[len(tied):]
        best = ranked[0].summary
        why = (
            # not its description: free text that can name the patient (the listing shows it)
            f"chose series [{best.index}] {best.uid}"
            + (f" ({best.subset})" if best.subset else "")
            + f": {best.orientation} CT, {best.n_slices} image(s)"
        )
        if prefer_gated:
            g0 = gating[id(ranked[0])]
            why += f", cardiac gating from {g0}" if g0 else ", no cardiac gating in any CT series"
            bigger = [
                g.summary for g in ranked[1:]
                if not gating[id(g)] and g.summary.n_slices > best.n_slices and g0
            ]
            if bigger:
                why += (
                    "; preferred to the larger series without cardiac gating "
                    + ", ".join(f"[{b.index}] ({b.n_slices} image(s))" for b in bigger[:3])
                )
        rivals = [
            g.summary for g in ranked[1:]
            if g.summary.orientation == best.orientation and g.summary.n_slices == best.n_slices
        ]
        if rivals:
            smoother = ""
            if texture and texture[id(ranked[0])] is not None:
                smoother = (", the smoothest (neighbouring voxels in soft tissue differ by a median "
                            + ", ".join(f"{texture[id(g)]:.0f} HU in [{g.summary.index}]" for g in tied
                                        if texture[id(g)] is not None) + ": a softer reconstruction kernel)")
            warnings.warn(
                f"{len(rivals) + 1} CT series are equally good candidates ([{best.index}]"
                + "".join(f", [{r.index}]" for r in rivals)
                + f"); used [{best.index}] {best.uid}{smoother}: choose with --series (see --list-series)",
                StudyWarning,
                stacklevel=3,
            )
        apart = [g.summary for g in groups if g.summary.uid == best.uid and g.summary.index != best.index
                 and g.summary.kind != "localizer"]
        if apart:  # the same series split (another orientation, size or acquisition): its other images unused
            warnings.warn(
                f"series [{best.index}] {best.uid} is used without {sum(a.n_files for a in apart)} of its own "
                "image(s) that do not stack with it: " + ", ".join(
                    f"[{a.index}] {a.orientation or a.kind} {a.n_files} file(s)" + (f" {a.cardiac}" if a.cardiac else "")
                    for a in apart[:4])
                + "; choose another part with --series (see --list-series)", StudyWarning, stacklevel=3)
        if len(ranked) > 1:
            why += (
                f"; {len(ranked) - 1} other CT candidate(s) "
                + ", ".join(
                    f"[{g.summary.index}] {g.summary.orientation} {g.summary.n_slices}"
                    + (f" {g.summary.cardiac}" if g.summary.cardiac else "")
                    for g in ranked[1:6]
                )
                + " (pass series=... / --series to choose)"
            )
        skipped = [g.summary for g in groups if g.summary.kind == "localizer"]
        if skipped:
            why += f"; localizer(s) ignored: {', '.join(f'[{s.index}]' for s in skipped)}"
        return ranked[0], why
    if isinstance(series, SeriesSummary):
        series = series.index
    if isinstance(series, (bool, np.bool_)) or not isinstance(series, (int, np.integer, str)):
        raise TypeError(
            f"series must be an index (int), a SeriesInstanceUID (str) or a SeriesSummary, "
            f"got {type(series).__name__}"
        )
    if isinstance(series, (int, np.integer)):
        matches = [g for g in groups if g.summary.index == int(series)]
    else:
        # the UID, or its pseudonym: what the commands print in its place (hrcore.redact)
        matches = [g for g in groups if series.strip() in (g.summary.uid, pseudonym_uid(g.summary.uid))]
    if not matches:
        # a UID given is not echoed: the line prints pseudonyms in place of UIDs, and its own would read as another
        missing = f"series {series!r} not found" if isinstance(series, (int, np.integer)) else "no series has the UID given"
        raise SeriesError(f"{missing}; the study holds: " + _choices(groups))
    if len(matches) > 1:
        usable = [g for g in matches if g.summary.kind in _LOADABLE]
        if len(usable) == 1:
            matches = usable
        else:
            raise SeriesError(
                f"series {series!r} was split into {len(matches)} groups; pass series=<index> (--series) "
                "for one of: " + _choices(matches)
            )
    chosen = matches[0]
    if chosen.summary.kind not in _LOADABLE:
        raise SeriesError(
            f"series [{chosen.summary.index}] {chosen.summary.uid} cannot be loaded as a "
            f"volume: {chosen.summary.reason}. Choose another among: " + _choices(groups)
        )
    if chosen.summary.modality != "CT":  # the caller's choice, but no Hounsfield units: say so
        warnings.warn(
            f"series [{chosen.summary.index}] {chosen.summary.uid} is {chosen.summary.modality or 'of no modality'}, "
            "not CT: its values are not Hounsfield units, which the heart's segmentation reads",
            StudyWarning,
            stacklevel=3,
        )
    return chosen, f"series [{chosen.summary.index}] {chosen.summary.uid} chosen by the caller"


def load_study(
    path, *, series=None, progress: bool = False, resample: bool = True, prefer_gated: bool = False,
    memory_factor: float = 1.0,
) -> Volume:
    """Load one image stack of a DICOM study as a `Volume`.

    Parameters
    ----------
    path : str or os.PathLike
        A study folder (searched recursively, any file names) or a single file.
    series : int, str, SeriesSummary or None
        Index from `list_series`, or a Series Instance UID (or its pseudonym,
        :func:`hrcore.redact.pseudonym_uid`, which the commands print in its place).
        None picks the axial CT stack with the most slices (not a localizer) and
        says why in ``notes``.
    progress : bool
        Progress bars on stderr.
    resample : bool
        Resample uneven, gapped or sheared stacks onto a regular orthogonal grid
        (default, said in ``notes``); False refuses them with `SeriesError`.
    prefer_gated : bool
        With ``series=None``: prefer a CT stack whose cardiac phase can be timed
        (GE R-peak stamps, the study's ECG waveform, TriggerTime, nominal phase)
        over a larger one that cannot (for the commands that need a phase); the
        note says which was taken and which were passed over.
    memory_factor : float
        The caller's peak memory in multiples of the volume's bytes as int16
        (``heartreg model``: :data:`modeling.options.MODEL_MEMORY_FACTOR`); a
        series needing more than the memory available is refused with a
        `SeriesError` before any pixel is read (1: the volume alone).

    Returns
    -------
    Volume

    Raises
    ------
    FileNotFoundError
        `path` does not exist.
    StudyError
        Nothing under `path` is a DICOM image.
    SeriesError
        The requested series is unknown, or its geometry cannot be handled, or it
        needs more memory than is available.
    imaging.pixels.DecoderUnavailableError
        A compressed transfer syntax has no installed decoder (names the package).
    imaging.pixels.PixelDataError
        A file's pixel data cannot be decoded.

    Examples
    --------
    >>> from imaging import load_study
    >>> volume = load_study("sample_dicom/ct")
    >>> volume.hu.shape, volume.spacing_mm.tolist()  # [k, j, i] voxels; mm along i, j, k
    ((72, 128, 128), [1.95, 1.95, 2.5])
    >>> len(volume.waveform_files)  # the ECG recorded with it
    1
    """
    if not isinstance(progress, (bool, np.bool_)):
        raise TypeError(f"progress must be a bool, got {type(progress).__name__}")
    found, groups, notes = _scan_groups(path, progress)
    ecg_studies = {
        o.study_instance_uid for o in found.others if o.sop_class_uid.startswith("1.2.840.10008.5.1.4.1.1.9.1.")
    }
    group, why = _select(groups, series, prefer_gated=prefer_gated, ecg_studies=ecg_studies,
                         unreadable=found.skipped_broken)
    notes.append(why)
    summary = group.summary
    label = f"[{summary.index}] {summary.uid}" + (f" ({summary.subset})" if summary.subset else "")
    if summary.reason and summary.subset:
        notes.append(summary.reason)
    plan = _plan_geometry(list(group.frames), label=label, resample=resample)
    notes.extend(plan.notes)
    rows, cols = plan.grid_shape or (plan.frames[0].rows, plan.frames[0].columns)
    check_memory((cols, rows, plan.n_out), memory_factor, f"series {label}",
                 float32=bool(plan.resample_k or plan.resample_plane))  # stored as float32 (_assemble)
    hu, pixel_notes = _assemble(plan, progress=progress)
    notes.extend(pixel_notes)
    if plan.resample_k or plan.resample_plane or any("RescaleSlope" in n for n in pixel_notes):
        warnings.warn(
            f"series {label}: " + "; ".join(plan.notes + pixel_notes), StudyWarning, stacklevel=2
        )
    hu.flags.writeable = False
    T = plan.T_patient_from_voxel
    T.flags.writeable = False
    spacing = plan.spacing_mm
    spacing.flags.writeable = False
    m = spacing[2]
    pos0 = plan.positions_mm[0]
    slices = tuple(
        SliceInfo(
            index=idx,
            file=f.path,
            frame=f.frame,
            position_mm=float(p),
            k=float((p - pos0) / m) if (plan.resample_k or len(plan.frames) == 1) else float(idx),
            **{name: getattr(f, name) for name in _SLICE_FROM_FRAME},
        )
        for idx, (f, p) in enumerate(zip(plan.frames, plan.positions_mm))
    )
    first = plan.frames[0]
    rpeaks = next((f.rpeak_timestamps_ms for f in plan.frames if f.rpeak_timestamps_ms), None)
    info = SeriesInfo(
        **{name: getattr(first, name) for name in _SERIES_FROM_FRAME},
        n_files=summary.n_files,
        subset=summary.subset,
        rpeak_timestamps_ms=rpeaks,
    )
    for note in notes:
        logger.info(note)
    return Volume(
        hu=hu,
        T_patient_from_voxel=T,
        spacing_mm=spacing,
        slices=slices,
        series=info,
        notes=tuple(notes),
        source_path=os.fspath(path),
        resampled=bool(plan.resample_k or plan.resample_plane),
        waveform_files=tuple(
            o.path
            for o in found.others
            if o.study_instance_uid == info.study_instance_uid
            and o.sop_class_uid.startswith("1.2.840.10008.5.1.4.1.1.9.1.")
        ),
        selection=why,
    )
