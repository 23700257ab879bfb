"""From any CT study folder to a `Volume`: `list_series` and `load_study`.

Files are found recursively whatever their names (:mod:`imaging.discover`), grouped
by (0020,000E) *Series Instance UID* and split further when a series mixes
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
from collections import defaultdict
from dataclasses import dataclass, field, replace

import numpy as np

from hrcore.errors import HeartregError

from .discover import _Frame, _Other, _Scan, _scan
from .volume import (
    SeriesError,
    SeriesInfo,
    SliceInfo,
    Volume,
    _assemble,
    _files_text,
    _plan_geometry,
)

logger = logging.getLogger(__name__)

#: Slice positions closer than this (mm) are the same position.
SAME_POSITION_MM = 0.01
#: A stack is called axial/coronal/sagittal when its normal is this close to an axis.
AXIS_COS = np.cos(np.radians(10.0))

_LOADABLE = ("volume", "slice", "localizer")
_SPLIT_KEYS = (
    ("nominal_cardiac_percent", "NominalPercentageOfCardiacPhase"),
    ("trigger_time_ms", "TriggerTime"),
    ("temporal_position", "TemporalPosition"),
    ("acquisition_number", "AcquisitionNumber"),
)


class StudyError(HeartregError, ValueError):
    """A study path holds nothing that can be loaded."""


class StudyWarning(UserWarning):
    """Something in a study was skipped or altered; details are in ``Volume.notes``."""


@dataclass(frozen=True)
class SeriesSummary:
    """One loadable (or listed) group of images, as `list_series` shows it.

    ``kind`` is ``"volume"`` (a stack of 2+ images), ``"slice"`` (one image),
    ``"localizer"``, ``"non-image"`` (e.g. an ECG waveform or report) or
    ``"unusable"``; ``reason`` says why a group is not a volume or how it was split.
    ``uid`` is the Series Instance UID; a series split into several groups has the
    same ``uid`` in each, with ``subset`` telling them apart: select those by index.
    """

    index: int
    uid: str
    description: str
    modality: str
    n_slices: int
    orientation: str
    kind: str
    reason: str
    series_number: int | None
    subset: str
    n_files: int
    files: tuple[str, ...] = field(repr=False)


@dataclass(frozen=True)
class _Group:
    summary: SeriesSummary
    frames: tuple[_Frame, ...]


# ----------------------------------------------------------------- grouping


def _normal(iop) -> np.ndarray:
    v = np.asarray(iop, dtype=np.float64)
    n = np.cross(v[:3], v[3:])
    norm = np.linalg.norm(n)
    return n / norm if norm > 0 else n


def _orientation_label(iop) -> str:
    if iop is None:
        return ""
    n = np.abs(_normal(iop))
    axis = int(np.argmax(n))
    if n[axis] < AXIS_COS:
        return "oblique"
    return ("sagittal", "coronal", "axial")[axis]


def _cluster_orientation(frames: list[_Frame]) -> list[list[_Frame]]:
    clusters: list[tuple[np.ndarray | None, list[_Frame]]] = []
    for f in frames:
        key = None if f.iop is None else np.asarray(f.iop)
        for ref, members in clusters:
            if (ref is None and key is None) or (
                ref is not None and key is not None and np.max(np.abs(ref - key)) < 1e-4
            ):
                members.append(f)
                break
        else:
            clusters.append((key, [f]))
    return [members for _, members in clusters]


def _has_duplicates(frames: list[_Frame]) -> bool:
    if frames[0].iop is None or any(f.ipp is None for f in frames):
        return False
    n = _normal(frames[0].iop)
    pos = np.sort(np.array([f.ipp for f in frames]) @ n)
    return bool(np.any(np.diff(pos) < SAME_POSITION_MM))


def _split_duplicates(frames: list[_Frame]) -> tuple[list[tuple[str, list[_Frame]]], str]:
    """Split a stack with repeated positions; returns ([(subset, frames)], reason)."""
    for attr, label in _SPLIT_KEYS:
        values = [getattr(f, attr) for f in frames]
        if any(v is None for v in values) or len(set(values)) < 2:
            continue
        parts: dict = defaultdict(list)
        for f, v in zip(frames, values):
            parts[v].append(f)
        if not any(_has_duplicates(p) for p in parts.values()):
            return (
                [(f"{label}={v:g}", parts[v]) for v in sorted(parts)],
                f"series repeats slice positions; split by {label}",
            )
    return [("", frames)], ""


#: Below this share of images at a repeated position, the repeats are strays
#: (a resent or duplicated file), not a multi-phase series to split.
STRAY_REPEAT_SHARE = 0.25


def _drop_stray_duplicates(frames: list[_Frame]) -> tuple[list[_Frame], list[tuple[str, str]]]:
    """Drop the few images that repeat another's position, keeping the first by
    InstanceNumber; returns (kept, [(dropped file, kept file)]).  Nothing is
    dropped when many images repeat (a multi-phase series: split it instead)."""
    n = _normal(frames[0].iop)
    pos = np.round(np.array([f.ipp for f in frames]) @ n / SAME_POSITION_MM).astype(np.int64)
    _, inverse, counts = np.unique(pos, return_inverse=True, return_counts=True)
    if np.mean(counts[inverse] > 1) >= STRAY_REPEAT_SHARE:
        return frames, []
    order = sorted(range(len(frames)), key=lambda i: (frames[i].instance_number is None, frames[i].instance_number or 0, frames[i].path))
    first: dict[int, int] = {}
    dropped = []
    for i in order:
        key = int(pos[i])
        if key in first:
            dropped.append((frames[i].path, frames[first[key]].path))
        else:
            first[key] = i
    kept = [frames[i] for i in sorted(first.values())]
    return kept, dropped


def _dedupe(frames: list[_Frame]) -> tuple[list[_Frame], list[str]]:
    seen: dict[tuple[str, int | None], _Frame] = {}
    dropped = []
    for f in frames:
        key = (f.sop_instance_uid, f.frame)
        if f.sop_instance_uid and key in seen:
            dropped.append(f.path)
            continue
        seen[key] = f
    return list(seen.values()), dropped


def _summarise(
    frames: list[_Frame], subset: str, reason: str, kind: str | None = None
) -> tuple[SeriesSummary, tuple[_Frame, ...]]:
    first = frames[0]
    files = tuple(dict.fromkeys(f.path for f in frames))
    if kind is None:
        if first.is_localizer:
            kind, reason = "localizer", reason or "ImageType says LOCALIZER"
        elif first.iop is None or any(f.ipp is None or f.pixel_spacing is None for f in frames):
            kind = "unusable"
            reason = reason or "no ImagePositionPatient/ImageOrientationPatient/PixelSpacing"
        elif _has_duplicates(frames):
            kind = "unusable"
            reason = (
                "repeated slice positions that no attribute separates "
                f"({_files_text(files, 3)})"
            )
        else:
            kind = "volume" if len(frames) > 1 else "slice"
    summary = SeriesSummary(
        index=-1,
        uid=first.series_instance_uid,
        description=first.description,
        modality=first.modality,
        n_slices=len(frames),
        orientation=_orientation_label(first.iop),
        kind=kind,
        reason=reason,
        series_number=first.series_number,
        subset=subset,
        n_files=len(files),
        files=files,
    )
    return summary, tuple(frames)


def _group(found: _Scan) -> tuple[list[_Group], list[str]]:
    """All groups, in a deterministic order, and notes about de-duplication."""
    notes: list[str] = []
    by_uid: dict[str, list[_Frame]] = defaultdict(list)
    for f in found.frames:
        by_uid[f.series_instance_uid].append(f)
    raw: list[tuple[SeriesSummary, tuple[_Frame, ...]]] = []
    for uid, frames in by_uid.items():
        frames, dropped = _dedupe(frames)
        if dropped:
            notes.append(
                f"series {uid}: {len(dropped)} duplicate image(s) (same SOPInstanceUID) "
                f"ignored: {_files_text(dropped)}"
            )
        subsets: dict[tuple, list[_Frame]] = defaultdict(list)
        for f in frames:
            subsets[(f.is_localizer, f.rows, f.columns)].append(f)
        for (_, rows, cols), members in subsets.items():
            for cluster in _cluster_orientation(members):
                if cluster[0].is_localizer or not _has_duplicates(cluster):
                    raw.append(_summarise(cluster, "", ""))
                    continue
                cluster, repeated = _drop_stray_duplicates(cluster)
                if repeated:
                    message = (
                        f"series {uid}: {len(repeated)} image(s) repeat the position of another and "
                        f"were ignored: " + "; ".join(f"{a} repeats {b}" for a, b in repeated[:4])
                    )
                    notes.append(message)
                    warnings.warn(message, StudyWarning, stacklevel=3)
                    raw.append(_summarise(cluster, "", ""))
                    continue
                parts, reason = _split_duplicates(cluster)
                for subset, part in parts:
                    raw.append(_summarise(part, subset, reason))
    others: dict[str, list[_Other]] = defaultdict(list)
    for o in found.others:
        others[o.series_instance_uid].append(o)
    for uid, members in others.items():
        first = members[0]
        files = tuple(o.path for o in members)
        raw.append(
            (
                SeriesSummary(
                    index=-1,
                    uid=uid,
                    description=first.description,
                    modality=first.modality,
                    n_slices=0,
                    orientation="",
                    kind="non-image",
                    reason=f"no image (SOP Class {first.sop_class_uid})",
                    series_number=first.series_number,
                    subset="",
                    n_files=len(files),
                    files=files,
                ),
                (),
            )
        )
    kind_rank = {"volume": 0, "slice": 1, "localizer": 2, "unusable": 3, "non-image": 4}
    raw.sort(
        key=lambda sf: (
            sf[0].series_number if sf[0].series_number is not None else 1 << 30,
            sf[0].uid,
            kind_rank[sf[0].kind],
            sf[0].orientation,
            sf[0].subset,
            sf[0].files[:1],
        )
    )
    groups = [
        _Group(summary=replace(s, index=i), frames=frames) for i, (s, frames) in enumerate(raw)
    ]
    return groups, notes


def _scan_notes(found: _Scan) -> list[str]:
    notes = []
    if found.skipped_non_dicom:
        notes.append(f"{len(found.skipped_non_dicom)} non-DICOM file(s) ignored")
    if found.skipped_dicomdir:
        notes.append(f"DICOMDIR ignored: {_files_text(found.skipped_dicomdir)}")
    for path, why in found.skipped_broken:
        notes.append(f"skipped unreadable DICOM file {path}: {why}")
    return notes


def _warn_broken(found: _Scan) -> None:
    if found.skipped_broken:
        listing = "; ".join(f"{p}: {why}" for p, why in found.skipped_broken[:5])
        more = len(found.skipped_broken) - 5
        warnings.warn(
            f"skipped {len(found.skipped_broken)} DICOM file(s) that cannot be read: {listing}"
            + (f"; and {more} more" if more > 0 else ""),
            StudyWarning,
            stacklevel=3,
        )


def _scan_groups(path, progress: bool):
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    found = _scan(path, progress=progress)
    _warn_broken(found)
    groups, notes = _group(found)
    if not groups:
        detail = (
            f"{found.n_files} file(s) examined: {len(found.skipped_non_dicom)} not DICOM, "
            f"{len(found.skipped_broken)} unreadable, {len(found.skipped_dicomdir)} DICOMDIR"
        )
        raise StudyError(
            f"no DICOM images found under {os.fspath(path)!r} ({detail}); point to the folder "
            "that holds the study's DICOM files"
        )
    return found, groups, _scan_notes(found) + notes


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
    """
    _, groups, _ = _scan_groups(path, progress)
    return tuple(g.summary for g in groups)


def _choices(groups: list[_Group]) -> str:
    lines = []
    for g in groups:
        s = g.summary
        lines.append(
            f"[{s.index}] {s.uid} #{s.series_number} {s.description!r} {s.modality} "
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
    if all(f.trigger_time_ms is not None and (f.nominal_interval_ms or f.heart_rate_bpm) for f in frames):
        return "TriggerTime"
    if all(f.nominal_cardiac_percent is not None for f in frames):
        return "NominalPercentageOfCardiacPhase"
    return ""


def _select(groups: list[_Group], series, *, prefer_gated: bool = False, ecg_studies=frozenset()) -> tuple[_Group, str]:
    loadable = [g for g in groups if g.summary.kind in _LOADABLE]
    if series is None:
        ranked = [g for g in loadable if g.summary.modality == "CT" and g.summary.kind == "volume"]
        if not ranked:
            ranked = [g for g in loadable if g.summary.modality == "CT" and g.summary.kind == "slice"]
        if not ranked:
            raise SeriesError(
                "no CT image stack found automatically; choose one with series=<index or "
                "SeriesInstanceUID> among: " + _choices(groups)
            )
        gating = {id(g): _gating(g, ecg_studies) for g in ranked} if prefer_gated else {}
        ranked.sort(
            key=lambda g: (
                prefer_gated and not gating[id(g)],
                g.summary.orientation != "axial",
                -g.summary.n_slices,
                g.summary.index,
            )
        )
        best = ranked[0].summary
        why = (
            f"chose series [{best.index}] {best.uid} ({best.description!r}"
            + (f", {best.subset}" if best.subset else "")
            + f"): {best.orientation} CT, {best.n_slices} image(s)"
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
            warnings.warn(
                f"{len(rivals) + 1} CT series are equally good candidates ([{best.index}]"
                + "".join(f", [{r.index}]" for r in rivals)
                + f"); used [{best.index}] {best.uid}: choose with --series (see --list-series)",
                StudyWarning,
                stacklevel=3,
            )
        if len(ranked) > 1:
            why += (
                f"; {len(ranked) - 1} other CT candidate(s) "
                + ", ".join(
                    f"[{g.summary.index}] {g.summary.orientation} {g.summary.n_slices}"
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
        matches = [g for g in groups if g.summary.uid == series.strip()]
    if not matches:
        raise SeriesError(f"series {series!r} not found; the study holds: " + _choices(groups))
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
    return chosen, f"series [{chosen.summary.index}] {chosen.summary.uid} chosen by the caller"


def load_study(
    path, *, series=None, progress: bool = False, resample: bool = True, prefer_gated: bool = False
) -> Volume:
    """Load one image stack of a DICOM study as a `Volume`.

    Parameters
    ----------
    path : str or os.PathLike
        A study folder (searched recursively, any file names) or a single file.
    series : int, str, SeriesSummary or None
        Index from `list_series`, or a Series Instance UID. None picks the axial CT
        stack with the most slices (not a localizer) and says why in ``notes``.
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
        The requested series is unknown, or its geometry cannot be handled.
    imaging.volume.DecoderUnavailableError
        A compressed transfer syntax has no installed decoder (names the package).
    imaging.volume.PixelDataError
        A file's pixel data cannot be decoded.
    """
    if not isinstance(progress, (bool, np.bool_)):
        raise TypeError(f"progress must be a bool, got {type(progress).__name__}")
    found, groups, notes = _scan_groups(path, progress)
    ecg_studies = {
        o.study_instance_uid for o in found.others if o.sop_class_uid.startswith("1.2.840.10008.5.1.4.1.1.9.1.")
    }
    group, why = _select(groups, series, prefer_gated=prefer_gated, ecg_studies=ecg_studies)
    notes.append(why)
    summary = group.summary
    label = f"[{summary.index}] {summary.uid}" + (f" ({summary.subset})" if summary.subset else "")
    if summary.reason and summary.subset:
        notes.append(summary.reason)
    plan = _plan_geometry(list(group.frames), label=label, resample=resample)
    notes.extend(plan.notes)
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
            instance_number=f.instance_number,
            position_mm=float(p),
            k=float((p - pos0) / m) if (plan.resample_k or len(plan.frames) == 1) else float(idx),
            sop_instance_uid=f.sop_instance_uid,
            acquisition_time_s=f.acquisition_time_s,
            mid_scan_time_s=f.mid_scan_time_s,
            trigger_time_ms=f.trigger_time_ms,
            nominal_interval_ms=f.nominal_interval_ms,
            heart_rate_bpm=f.heart_rate_bpm,
            nominal_cardiac_percent=f.nominal_cardiac_percent,
        )
        for idx, (f, p) in enumerate(zip(plan.frames, plan.positions_mm))
    )
    first = plan.frames[0]
    rpeaks = next((f.rpeak_timestamps_ms for f in plan.frames if f.rpeak_timestamps_ms), None)
    info = SeriesInfo(
        series_instance_uid=first.series_instance_uid,
        study_instance_uid=first.study_instance_uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        series_number=first.series_number,
        description=first.description,
        modality=first.modality,
        manufacturer=first.manufacturer,
        model_name=first.model_name,
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
    )
