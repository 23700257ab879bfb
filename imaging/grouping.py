"""Frames of a scanned folder grouped into series a user can choose from.

Frames are grouped by SeriesInstanceUID, then split where one UID holds several
stacks: by orientation (clusters of slice normals), by acquisition keys
(``_SPLIT_KEYS``, e.g. one stack per nominal cardiac phase) and by repeated
positions; stray repeated slices are dropped and exact duplicates removed. Each
group is summarised as a :class:`SeriesSummary` for ``list_series``.
"""

from __future__ import annotations

import os
import warnings
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError

from .discover import _Frame, _Other, _Scan, _scan
from .files import is_analyze_header
from .volume import _files_text


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


@dataclass(frozen=True)
class SeriesSummary:
    """One loadable (or listed) group of images, as `list_series` shows it.

    ``kind`` is ``"volume"`` (a stack of 2+ images), ``"slice"`` (one image),
    ``"localizer"``, ``"non-image"`` (e.g. an ECG waveform or report) or
    ``"unusable"``; ``reason`` says why a group is not a volume or how it was split.
    ``uid`` is the Series Instance UID; a series split into several groups has the
    same ``uid`` in each, with ``subset`` telling them apart: select those by index.
    ``cardiac`` is the images' cardiac phase tag when they share one value
    (``"phase 70 %"`` from *Nominal Percentage of Cardiac Phase*, else
    ``"TriggerTime 560 ms"``, or its range), "" without one: the phases of a
    multi-phase series told apart in ``--list-series``.
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
    cardiac: str = ""


def _cardiac_label(frames) -> str:
    """The frames' cardiac phase tag (SeriesSummary.cardiac)."""
    pct = {f.nominal_cardiac_percent for f in frames}
    if None not in pct and len(pct) == 1:
        return f"phase {pct.pop():g} %"
    trigger = [f.trigger_time_ms for f in frames]
    if frames and None not in trigger:
        lo, hi = min(trigger), max(trigger)
        return f"TriggerTime {lo:g} ms" if lo == hi else f"TriggerTime {lo:g}-{hi:g} ms"
    return ""


@dataclass(frozen=True)
class _Group:
    summary: SeriesSummary
    frames: tuple[_Frame, ...]


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


def _repeat_text(path: str, first: str) -> str:
    """``NAME repeats OTHER`` by file names (a study's folders can be named after the patient); two copies of one
    name (two exports merged) are told apart by saying so ('ct0030.dcm repeats ct0030.dcm' read as a mistake)."""
    name, other = os.path.basename(path), os.path.basename(first)
    return f"{name} repeats " + ("the file of that name in another folder" if name == other else other)


#: Below this share of images at a repeated position, the repeats are strays
#: (a resent or duplicated file), not a multi-phase series to split.
STRAY_REPEAT_SHARE = 0.25


def _drop_stray_duplicates(frames: list[_Frame]) -> tuple[list[_Frame], list[tuple[str, str]]]:
    """Drop the few images that repeat another's position, keeping the first by
    InstanceNumber; returns (kept, [(dropped file, kept file)]).  Nothing is
    dropped when many images repeat (a multi-phase series: split it instead),
    unless each repeat is the same image again (every attribute read, and the pixel
    data's length, but its file and SOPInstanceUID: a series exported twice over
    with new SOPInstanceUIDs)."""
    n = _normal(frames[0].iop)
    pos = np.round(np.array([f.ipp for f in frames]) @ n / SAME_POSITION_MM).astype(np.int64)
    _, inverse, counts = np.unique(pos, return_inverse=True, return_counts=True)
    again = {}
    for f, key in zip(frames, inverse):
        again.setdefault(int(key), set()).add((replace(f, path="", sop_instance_uid=""), f.pixel_length))
    if np.mean(counts[inverse] > 1) >= STRAY_REPEAT_SHARE and any(len(v) > 1 for v in again.values()):
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
    """Drop repeats of an image (same SOPInstanceUID and frame); images without a
    SOPInstanceUID (blanked by an anonymiser) are all kept."""
    seen: set[tuple[str, int | None]] = set()
    kept, dropped = [], []
    for f in frames:
        key = (f.sop_instance_uid, f.frame)
        if f.sop_instance_uid and key in seen:
            dropped.append(f.path)
            continue
        seen.add(key)
        kept.append(f)
    return kept, dropped


def _missing_geometry(f: _Frame) -> tuple[str, ...]:
    """The attributes placing an image in the patient frame that it lacks."""
    return tuple(name for name, value in (("ImagePositionPatient", f.ipp), ("ImageOrientationPatient", f.iop),
                                          ("PixelSpacing", f.pixel_spacing)) if value is None)


def _missing_geometry_text(frames) -> str:
    """What the frames lack of :func:`_missing_geometry`, each attribute once: ``"A/B"``."""
    return "/".join(dict.fromkeys(t for f in frames for t in _missing_geometry(f)))


def _classic_multiframe(frames) -> bool:
    """Frames of one multi-frame file without per-frame positions (CT Image Storage with NumberOfFrames > 1)."""
    return (len({f.path for f in frames}) == 1 and frames[0].n_frames_in_file > 1
            and frames[0].sop_class_uid != "1.2.840.10008.5.1.4.1.1.2.1")  # not Enhanced CT


def _summarise(
    frames: list[_Frame], subset: str, reason: str, kind: str | None = None
) -> tuple[SeriesSummary, tuple[_Frame, ...]]:
    first = frames[0]
    files = tuple(dict.fromkeys(f.path for f in frames))
    if kind is None:
        if first.is_localizer:
            kind, reason = "localizer", reason or "ImageType says LOCALIZER"
        elif any(_missing_geometry(f) for f in frames):
            kind = "unusable"
            reason = reason or "no " + _missing_geometry_text(frames)
        elif _has_duplicates(frames) and _classic_multiframe(frames):
            kind = "unusable"
            reason = (f"a classic multi-frame CT image ({first.n_frames_in_file} frames in one file, one "
                      "ImagePositionPatient for them all): its frames cannot be placed; export the series as "
                      "single-frame CT images or as Enhanced CT")
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
        cardiac=_cardiac_label(frames),
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
                f"ignored: {_files_text(dropped, names=True)}"
            )
        unplaced = [f for f in frames if not f.is_localizer and _missing_geometry(f)]
        if unplaced and len(unplaced) < len(frames):  # the rest can still be a volume: leave these out, by name
            message = (
                f"series {uid}: {len(unplaced)} image(s) without "
                f"{_missing_geometry_text(unplaced)} left out: "
                f"{_files_text([f.path for f in unplaced], 4, names=True)}"
            )
            notes.append(message)
            warnings.warn(message, StudyWarning, stacklevel=3)
            raw.append(_summarise(unplaced, "", message.split(": ", 1)[1]))
            left_out = {id(f) for f in unplaced}
            frames = [f for f in frames if id(f) not in left_out]
        subsets: dict[tuple, list[_Frame]] = defaultdict(list)
        for f in frames:
            subsets[(f.is_localizer, f.rows, f.columns)].append(f)
        images = {key: members for key, members in subsets.items() if not key[0]}
        if len(images) > 1:  # a few images of another size among a stack: say which, not only the gap they leave
            main_key = max(images, key=lambda key: len(images[key]))
            odd = [f for key, members in images.items() if key != main_key for f in members]
            if len(odd) <= max(2, 0.1 * len(images[main_key])):
                message = (
                    f"series {uid}: {len(odd)} image(s) of another size than its {main_key[1]}x{main_key[2]} "
                    f"left out of its stack: {_files_text([f.path for f in odd], 4, names=True)}"
                )
                notes.append(message)
                warnings.warn(message, StudyWarning, stacklevel=3)
        for (_, rows, cols), members in subsets.items():
            for cluster in _cluster_orientation(members):
                if cluster[0].is_localizer or not _has_duplicates(cluster):
                    raw.append(_summarise(cluster, "", ""))
                    continue
                cluster, repeated = _drop_stray_duplicates(cluster)
                if repeated:
                    message = (
                        f"series {uid}: {len(repeated)} image(s) repeat the position of another and "
                        f"were ignored: "
                        + "; ".join(_repeat_text(a, b) for a, b in repeated[:4])
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
        notes.append(f"DICOMDIR ignored: {_files_text(found.skipped_dicomdir, names=True)}")
    for path, why in found.skipped_broken:  # a folder not named at all: the name filter knows files only
        notes.append(f"skipped a {why}" if why.startswith("folder") else
                     f"skipped unreadable DICOM file {os.path.basename(path)}: {why}")
    return notes


def _warn_broken(found: _Scan) -> None:
    if found.skipped_broken:
        listing = "; ".join(f"{p}: {why}" for p, why in found.skipped_broken[:5])
        more = len(found.skipped_broken) - 5
        warnings.warn(
            f"skipped {len(found.skipped_broken)} DICOM file(s) or folder(s) that cannot be read: {listing}"
            + (f"; and {more} more" if more > 0 else ""),
            StudyWarning,
            stacklevel=3,
        )


def _image_pair(path) -> str:
    """What a ``.hdr``/``.img`` file is (an Analyze 7.5 or NIfTI-1 pair, by its header's 348 bytes), '' otherwise."""
    p = Path(path)
    if not p.is_file() or p.suffix.lower() not in (".hdr", ".img"):
        return ""
    try:
        head = p.with_suffix(".hdr" if p.suffix.islower() else ".HDR").read_bytes()[:348]
    except OSError:
        return ""
    if not is_analyze_header(head):
        return ""
    return "a NIfTI-1 image pair (.hdr/.img)" if head[344:347] == b"ni1" else "an Analyze 7.5 image (.hdr/.img pair)"


def _scan_groups(path, progress: bool):
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    found = _scan(path, progress=progress)
    _warn_broken(found)
    groups, notes = _group(found)
    if not groups and found.skipped_broken:  # DICOM files there, none readable: why, for one of them
        path_, why = found.skipped_broken[0]
        raise StudyError(f"no readable DICOM image under {os.fspath(path)!r}: {len(found.skipped_broken)} "
                         f"DICOM file(s) cannot be read, e.g. {path_}: {why}")
    if not groups:
        detail = (
            f"{found.n_files} file(s) examined: {len(found.skipped_non_dicom)} not DICOM, "
            f"{len(found.skipped_broken)} unreadable file(s) or folder(s), {len(found.skipped_dicomdir)} DICOMDIR"
        )
        if pair := _image_pair(path):
            raise StudyError(f"{os.fspath(path)!r} is {pair}, not DICOM: convert it to NIfTI (.nii.gz, e.g. with "
                             "nibabel or 3D Slicer) and give that file, or give the DICOM study's folder")
        raise StudyError(
            f"no DICOM images found under {os.fspath(path)!r} ({detail}); point to the folder "
            "that holds the study's DICOM files"
        )
    return found, groups, _scan_notes(found) + notes


class StudyError(HeartregError, ValueError):
    """A study path holds nothing that can be loaded."""


class StudyWarning(UserWarning):
    """Something in a study was skipped or altered; details are in ``Volume.notes``."""
