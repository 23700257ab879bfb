"""Read one ECG lead, its clock and its annotated beats from a DICOM ECG waveform.

Supported: 12-lead ECG, General ECG and Ambulatory ECG Waveform Storage (and
any waveform instance whose (0008,0060) *Modality* is ECG).  Sample ``n`` of a
multiplex group is at (docs/CONTRACTS.md)::

    AcquisitionDateTime (0008,002A) + MultiplexGroupTimeOffset (0018,1068) / 1000
        + n / SamplingFrequency (003A,001A)

in seconds after midnight, the clock of (0008,0032) *Acquisition Time*.  When
*Acquisition DateTime* carries no time of day, (0008,0032) *Acquisition Time*
and then (0008,0033) *Content Time* are used instead, and the record says so in
``clock_source``.

Beats annotated in (0040,B020) *Waveform Annotation Sequence* are returned if
they are points named *Fiducial Point* (SCP-ECG 5.7.1-3, the QRS fiducial point
that ECG carts place at or next to the R maximum) or *R wave peak*.  Some carts
(e.g. Mortara) also annotate the fiducial point of the DERIVED median beat while
referencing the rhythm group; such a point, equal to a DERIVED group's
(0018,106E) *Trigger Sample Position* and within 200 ms of another annotated
beat, is dropped.
"""

from __future__ import annotations

import datetime
import os
import re
from dataclasses import dataclass, field

import numpy as np
import pydicom
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError

from hrcore.errors import HeartregError

__all__ = ["EcgRecord", "WaveformError", "read_ecg_waveform", "ECG_SOP_CLASSES"]

#: SOP classes of ECG waveforms: 12-lead, General, Ambulatory.
ECG_SOP_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.9.1.1": "12-lead ECG Waveform Storage",
    "1.2.840.10008.5.1.4.1.1.9.1.2": "General ECG Waveform Storage",
    "1.2.840.10008.5.1.4.1.1.9.1.3": "Ambulatory ECG Waveform Storage",
}
#: Codes of lead II: SCP-ECG, MDC (numeric and reference id).
_LEAD_II_CODES = {"5.6.3-9-2", "2:2", "MDC_ECG_LEAD_II"}
#: Concept names of annotated beats (lower case).
_BEAT_CONCEPTS = {"fiducial point", "r wave peak", "r-wave peak", "r peak", "qrs fiducial point"}
_BEAT_CODES = {"5.7.1-3"}
#: Scale from the channel sensitivity unit (UCUM) to mV.
_TO_MV = {"uV": 1e-3, "mV": 1.0, "V": 1e3, "nV": 1e-6}
#: Two annotated beats closer than this (s) cannot both be beats.
_MIN_RR_S = 0.2


class WaveformError(HeartregError, ValueError):
    """A DICOM file that is not a readable ECG waveform."""


@dataclass(frozen=True)
class EcgRecord:
    """One ECG lead read from a DICOM waveform.

    Attributes
    ----------
    signal_mv : (n,) float64, mV
        Samples of the chosen lead (sensitivity, correction and baseline applied).
    rate_hz : float, Hz
        (003A,001A) *Sampling Frequency*.
    start_time_s : float, s
        Time of sample 0 in seconds after midnight (AcquisitionTime clock).
    clock_source : str
        Which attributes gave ``start_time_s``.
    channel_label : str
        Label of the chosen lead (e.g. "Lead II").
    channel_index : int
        0-based index of the lead in its multiplex group.
    channel_labels : tuple of str
        Labels of all leads of the group.
    group_index : int
        0-based index of the multiplex group in (5400,0100) *Waveform Sequence*.
    annotated_r_peaks_s : (m,) float64, s
        Beats (QRS fiducial points / R-peaks) annotated in the file, on the same
        clock as ``start_time_s``; empty if the file has none.
    source : str
        File path, or "<Dataset>".
    notes : tuple of str
        Fallbacks taken while reading (clock, units), in words.
    """

    signal_mv: np.ndarray
    rate_hz: float
    start_time_s: float
    clock_source: str
    channel_label: str
    channel_index: int
    channel_labels: tuple[str, ...]
    group_index: int
    annotated_r_peaks_s: np.ndarray
    source: str
    notes: tuple[str, ...] = field(default=())

    @property
    def time_s(self) -> np.ndarray:
        """(n,) float64, s: time of each sample on the AcquisitionTime clock."""
        return self.start_time_s + np.arange(self.signal_mv.size) / self.rate_hz


def _tm_seconds(value) -> float | None:
    """Seconds after midnight of a DICOM TM (HHMMSS.FFFFFF, also HH:MM:SS)."""
    if value is None:
        return None
    if isinstance(value, datetime.time):
        return value.hour * 3600 + value.minute * 60 + value.second + value.microsecond * 1e-6
    text = str(value).strip().replace(":", "")
    m = re.fullmatch(r"(\d{2})(\d{2})?(\d{2})?(\.\d{1,6})?", text)
    if not m:
        return None
    hh, mm, ss, frac = m.groups()
    return int(hh) * 3600 + int(mm or 0) * 60 + int(ss or 0) + float(frac or 0.0)


def _dt_seconds(value) -> float | None:
    """Seconds after midnight of a DICOM DT, or None if it has no time of day."""
    if value is None:
        return None
    if isinstance(value, datetime.datetime):
        return _tm_seconds(value.time())
    text = re.split(r"[+-]", str(value).strip(), maxsplit=1)[0]
    if len(text) <= 8:
        return None
    return _tm_seconds(text[8:])


def _label(ch: Dataset, i: int) -> str:
    label = str(ch.get("ChannelLabel", "") or "").strip()
    if label:
        return label
    src = ch.get("ChannelSourceSequence")
    if src:
        meaning = str(src[0].get("CodeMeaning", "") or "").strip()
        if meaning:
            return meaning
    return f"channel {i}"


def _is_lead_ii(ch: Dataset, label: str) -> bool:
    src = ch.get("ChannelSourceSequence")
    if src and str(src[0].get("CodeValue", "")) in _LEAD_II_CODES:
        return True
    # "II", "Lead II", "ECG II", "ECG Lead II", "II (mV)": vendors label without a code as they like
    return re.fullmatch(r"(?:ecg[\s_-]*)?(?:lead[\s_-]*)?ii(?:\s*\(.*\))?", label.strip().lower()) is not None


def _to_mv(ch: Dataset, label: str, name: str) -> tuple[float, str | None]:
    units = ch.get("ChannelSensitivityUnitsSequence")
    if not units:
        return 1.0, f"{label}: no (003A,0211) Channel Sensitivity Units; values taken as mV"
    code = str(units[0].get("CodeValue", "")).strip()
    if code not in _TO_MV:
        raise WaveformError(
            f"{name}: lead {label!r} is in units {code!r}, not a voltage (uV, mV, V): "
            "choose an ECG lead with channel="
        )
    return _TO_MV[code], None


def _start_time(ds: Dataset, group: Dataset, name: str) -> tuple[float, str]:
    from imaging.dicom_values import _date, on_study_clock

    offset_s = float(group.get("MultiplexGroupTimeOffset", 0.0) or 0.0) / 1000.0
    study_day = _date(ds.get("StudyDate"))
    for keyword, parse, tag, day_keyword in (
        ("AcquisitionDateTime", _dt_seconds, "(0008,002A)", "AcquisitionDateTime"),
        ("AcquisitionTime", _tm_seconds, "(0008,0032)", "AcquisitionDate"),
        ("ContentTime", _tm_seconds, "(0008,0033)", "ContentDate"),
    ):
        t = on_study_clock(parse(ds.get(keyword)), _date(ds.get(day_keyword)), study_day)
        if t is not None:
            src = f"{tag} {keyword} + (0018,1068) MultiplexGroupTimeOffset"
            if keyword != "AcquisitionDateTime":
                src += " (fallback: no time of day in AcquisitionDateTime)"
            return t + offset_s, src
    raise WaveformError(
        f"{name}: no (0008,002A) Acquisition DateTime, (0008,0032) Acquisition Time or "
        "(0008,0033) Content Time: the waveform cannot be placed on the study clock"
    )


def _pick_group(ds: Dataset, group, name: str) -> int:
    seq = ds.WaveformSequence
    if group is not None:
        if not (isinstance(group, (int, np.integer)) and 0 <= int(group) < len(seq)):
            raise WaveformError(f"{name}: group must be an index in [0, {len(seq)}), got {group!r}")
        return int(group)
    for g, item in enumerate(seq):
        if str(item.get("WaveformOriginality", "")).upper() == "ORIGINAL":
            return g
    return 0


def _pick_channel(labels, defs, channel, name: str) -> int:
    if channel is None:
        for i, (ch, lab) in enumerate(zip(defs, labels)):
            if _is_lead_ii(ch, lab):
                return i
        return 0
    if isinstance(channel, (int, np.integer)) and not isinstance(channel, bool):
        if 0 <= int(channel) < len(labels):
            return int(channel)
        raise WaveformError(f"{name}: channel must be in [0, {len(labels)}), got {channel}")
    if isinstance(channel, str):
        want = channel.strip().lower()
        for i, lab in enumerate(labels):
            low = lab.lower()
            if want in (low, low.removeprefix("lead ").strip(), f"lead {low}"):
                return i
        raise WaveformError(f"{name}: no lead named {channel!r}; the leads are {list(labels)}")
    raise WaveformError(f"{name}: channel must be None, an index or a lead name, got {channel!r}")


def _annotated_beats(ds: Dataset, g: int, rate: float, n: int) -> np.ndarray:
    """Sample positions (0-based, float) of beats annotated for multiplex group ``g``."""
    triggers = {
        int(item.TriggerSamplePosition)
        for item in ds.WaveformSequence
        if "TriggerSamplePosition" in item
        and str(item.get("WaveformOriginality", "")).upper() == "DERIVED"
    }
    found: list[tuple[float, bool]] = []
    for ann in ds.get("WaveformAnnotationSequence", []):
        names = ann.get("ConceptNameCodeSequence")
        if not names:
            continue
        code, meaning = str(names[0].get("CodeValue", "")), str(names[0].get("CodeMeaning", ""))
        if code not in _BEAT_CODES and meaning.strip().lower() not in _BEAT_CONCEPTS:
            continue
        refs = ann.get("ReferencedWaveformChannels")
        if refs is not None:
            groups = set(np.atleast_1d(np.asarray(refs, dtype=int))[0::2].tolist())
            if groups and (g + 1) not in groups and 0 not in groups:
                continue  # annotates another multiplex group (numbered from 1)
        if "ReferencedSamplePositions" in ann:
            for p in np.atleast_1d(np.asarray(ann.ReferencedSamplePositions, dtype=float)):
                found.append((p - 1.0, int(p) in triggers))  # positions count from 1
        elif "ReferencedTimeOffsets" in ann:
            for o in np.atleast_1d(np.asarray(ann.ReferencedTimeOffsets, dtype=float)):
                found.append((o * rate, False))  # seconds from the group's first sample
    if not found:
        return np.zeros(0)
    pos = np.array([p for p, _ in found])
    is_trigger = np.array([t for _, t in found])
    keep = np.ones(pos.size, dtype=bool)
    for i in np.flatnonzero(is_trigger):
        others = np.delete(pos, i)
        if others.size and np.min(np.abs(others - pos[i])) < _MIN_RR_S * rate:
            keep[i] = False
    pos = pos[keep]
    pos = pos[(pos >= 0) & (pos <= n - 1)]
    return np.unique(pos)


def read_ecg_waveform(path_or_dataset, *, channel=None, group: int | None = None) -> EcgRecord:
    """Read one lead of a DICOM ECG waveform with its clock and annotated beats.

    Parameters
    ----------
    path_or_dataset : str, os.PathLike or pydicom.Dataset
        A 12-lead, General or Ambulatory ECG Waveform Storage instance.
    channel : int or str, optional
        0-based channel index or lead name ("II", "Lead II", "V5", ...).  Default:
        lead II if the group has it, else the first channel.
    group : int, optional
        0-based multiplex group in (5400,0100) *Waveform Sequence*.  Default: the
        first ORIGINAL group (the rhythm strip, not a median beat).

    Returns
    -------
    EcgRecord

    Raises
    ------
    WaveformError
        If the file is not DICOM, not an ECG waveform, has no waveform data, has
        no time, or the lead asked for does not exist.

    Examples
    --------
    >>> from imaging import load_study, read_ecg_waveform
    >>> ecg = read_ecg_waveform(load_study("sample_dicom/ct").waveform_files[0])
    >>> ecg.rate_hz, ecg.channel_label, ecg.signal_mv.shape
    (500.0, 'II', (6302,))
    """
    if isinstance(path_or_dataset, Dataset):
        ds, name = path_or_dataset, str(getattr(path_or_dataset, "filename", "") or "<Dataset>")
    elif isinstance(path_or_dataset, (str, os.PathLike)):
        name = os.fspath(path_or_dataset)
        try:
            ds = pydicom.dcmread(name)
        except InvalidDicomError:
            raise WaveformError(
                f"{name} is not a DICOM file (no DICM preamble); if it is, try "
                "pydicom.dcmread(path, force=True) and pass the dataset"
            ) from None
        except OSError as exc:
            raise WaveformError(f"{name} cannot be read: {exc}") from None
    else:
        raise WaveformError(
            f"path_or_dataset must be a path or a pydicom Dataset, got {type(path_or_dataset).__name__}"
        )

    sop = str(ds.get("SOPClassUID", ""))
    modality = str(ds.get("Modality", "")).upper()
    if sop not in ECG_SOP_CLASSES and modality != "ECG":
        what = getattr(ds.get("SOPClassUID"), "name", sop) or "unknown SOP class"
        raise WaveformError(
            f"{name} is not an ECG waveform ({what}, modality {modality or 'none'}): "
            "give a 12-lead, General or Ambulatory ECG Waveform Storage file"
        )
    if not ds.get("WaveformSequence"):
        raise WaveformError(f"{name} has no (5400,0100) Waveform Sequence: there is no ECG to read")

    g = _pick_group(ds, group, name)
    item = ds.WaveformSequence[g]
    defs = list(item.get("ChannelDefinitionSequence", []))
    if not defs or "WaveformData" not in item:
        raise WaveformError(f"{name}: multiplex group {g} has no channels or no (5400,1010) Waveform Data")
    labels = tuple(_label(ch, i) for i, ch in enumerate(defs))
    c = _pick_channel(labels, defs, channel, name)
    try:
        rate = float(item.SamplingFrequency)
    except (AttributeError, TypeError, ValueError):
        raise WaveformError(f"{name}: multiplex group {g} has no (003A,001A) Sampling Frequency") from None
    if not (np.isfinite(rate) and rate > 0):
        raise WaveformError(f"{name}: (003A,001A) Sampling Frequency is {rate}, not a positive rate")

    try:
        data = ds.waveform_array(g)
    except Exception as exc:  # pydicom raises several types for broken waveform data
        try:  # the commonest: data cut short
            need = int(item.NumberOfWaveformSamples) * int(item.NumberOfWaveformChannels) * int(
                item.WaveformBitsAllocated) // 8
            exc = f"it holds {len(item.WaveformData)} bytes where its header's samples and channels need {need}"
        except (AttributeError, TypeError, ValueError):
            pass
        raise WaveformError(f"{name}: waveform data of group {g} cannot be decoded: {exc}") from None
    notes: list[str] = []
    scale, note = _to_mv(defs[c], labels[c], name)
    if note:
        notes.append(note)
    sig = np.ascontiguousarray(data[:, c], dtype=np.float64) * scale
    start, clock = _start_time(ds, item, name)
    if "fallback" in clock:
        notes.append(f"clock from {clock}")
    beats = start + _annotated_beats(ds, g, rate, sig.size) / rate
    sig.setflags(write=False)
    beats.setflags(write=False)
    return EcgRecord(
        signal_mv=sig,
        rate_hz=rate,
        start_time_s=start,
        clock_source=clock,
        channel_label=labels[c],
        channel_index=c,
        channel_labels=labels,
        group_index=g,
        annotated_r_peaks_s=beats,
        source=name,
        notes=tuple(notes),
    )
