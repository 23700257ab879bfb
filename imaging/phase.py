"""Cardiac phase of every CT slice and of the volume (paper section 2.2.2, Fig. 4).

A slice's cardiac phase is ``(t - R_k) / (R_{k+1} - R_k)`` for the R-peaks around
its acquisition time ``t``; the volume's phase phi_C* is the mean of the slice
phases (as the paper), reported beside their circular mean.

R-peak sources, in order of preference (DESIGN.md section 4):

1. a user's R-peak file (CSV, column ``time_s``, seconds after midnight on the
   (0008,0032) *AcquisitionTime* clock);
2. GE (0049,xx0C) *RpeakTimeStamps* (block ``GEMS_CT_CARDIAC_001``), in ms on the
   clock of GE (0019,xx24) *Mid Scan Time* (block ``GEMS_ACQU_01``);
3. a DICOM ECG waveform instance of the study, with QRS detection on it;
4. (0018,1060) *Trigger Time* over (0018,1062) *Nominal Interval* or the
   (0018,1088) *Heart Rate*;
5. (0020,9241) *Nominal Percentage of Cardiac Phase*.

Sources 4 and 5 (:mod:`imaging.nominal`) are not used when they carry no gating
information (a scan whose *Cardiac Synchronization Technique* is ``NONE``; trigger
times all 0 with no technique and no nominal RR interval): the phase is then
unknown, as for a CT without any timing.

The first source that can time every slice wins; the report names it and how
the clocks were aligned.
"""

from __future__ import annotations

import csv
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError
from imaging import nominal
from imaging.ecg import cardiac_phase, detect_r_peaks

__all__ = [
    "GatingError",
    "GatingWarning",
    "SlicePhase",
    "PhaseReport",
    "MOTION_FREE_WINDOW",
    "JUMP_THRESHOLD",
    "read_qrs_file",
    "compute_phase_report",
]

#: The diastolic window the paper relies on as nearly motion-free.
MOTION_FREE_WINDOW = (0.6, 0.8)
#: Consecutive slices whose phases differ by more than this (circularly) are a jump.
JUMP_THRESHOLD = 0.1
#: largest accepted R-peak file (a list of times: a few kB).
QRS_MAX_BYTES = 50_000_000
#: largest plausible R-peak time, s (seconds after midnight, a day or two).
QRS_MAX_ABS_S = 1e6


class GatingError(HeartregError, ValueError):
    """No usable cardiac gating information for the slices."""


class GatingWarning(UserWarning):
    """A gating source the user gave could not be used."""


@dataclass(frozen=True)
class SlicePhase:
    """Cardiac phase of one acquired slice.

    ``index`` counts the acquired images in order along the slice normal;
    ``volume_k`` is the image's (possibly fractional) slice index in the volume,
    which differs from ``index`` when the volume was resampled (a missing slice,
    uneven spacing).
    """

    index: int
    position_mm: float
    time_s: float
    cardiac_phase: float
    volume_k: float = float("nan")


@dataclass(frozen=True)
class PhaseReport:
    """Per-slice cardiac phases and the volume's phase.

    Attributes
    ----------
    slices : tuple of SlicePhase
        In volume order (sorted along the slice normal).
    volume_cardiac_phase : float
        phi_C*, the arithmetic mean of the slice phases (paper section 2.2.2).
    circular_mean_phase : float
        The circular mean, robust to phases that wrap past 1.
    source : str
        Which R-peak/gating source timed the slices.
    clock : str
        How slice times and R-peaks were put on one clock.
    r_peaks_s : (n,) float64
        The R-peaks used (on the slice clock), empty for nominal sources.
    jumps : tuple of int
        Indices i where slice i and i+1 differ by more than JUMP_THRESHOLD.
    fraction_in_window : float
        Share of slices with phase inside MOTION_FREE_WINDOW.
    notes : tuple of str
        Sources tried and skipped, and why.
    """

    slices: tuple[SlicePhase, ...]
    volume_cardiac_phase: float
    circular_mean_phase: float
    source: str
    clock: str
    r_peaks_s: np.ndarray
    jumps: tuple[int, ...]
    fraction_in_window: float
    notes: tuple[str, ...] = ()

    @property
    def phases(self) -> np.ndarray:
        return np.array([s.cardiac_phase for s in self.slices])

    @property
    def n_slices(self) -> int:
        return len(self.slices)

    def to_dict(self) -> dict:
        return {
            "volume_cardiac_phase": self.volume_cardiac_phase,
            "circular_mean_phase": self.circular_mean_phase,
            "source": self.source,
            "clock": self.clock,
            "n_slices": self.n_slices,
            "fraction_in_window": self.fraction_in_window,
            "motion_free_window": list(MOTION_FREE_WINDOW),
            "jumps": list(self.jumps),
            "jump_threshold": JUMP_THRESHOLD,
            "r_peaks_s": [float(t) for t in self.r_peaks_s],
            "notes": list(self.notes),
        }


def read_qrs_file(path) -> np.ndarray:
    """R-peak times from a CSV file with a ``time_s`` column (seconds after
    midnight on the AcquisitionTime clock).

    Returns
    -------
    (n,) float64, s, strictly increasing

    Examples
    --------
    >>> from imaging import read_qrs_file
    >>> read_qrs_file("sample_dicom/qrs.csv")[:2]  # s after midnight
    array([38331.025715, 38331.994804])
    """
    path = Path(path)
    if not path.exists():
        raise GatingError(f"QRS file {path} does not exist; give the R-peak times CSV (column time_s)")
    if not path.is_file():
        raise GatingError(f"QRS file {path} is not a regular file (a folder, named pipe or device)")
    if path.stat().st_size > QRS_MAX_BYTES:
        raise GatingError(
            f"QRS file {path} holds {path.stat().st_size / 1e6:.0f} MB; an R-peak list is a few kB: "
            "check that it is the right file"
        )
    try:
        # utf-8-sig: Excel's "CSV UTF-8" starts with a byte-order mark
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            if reader.fieldnames is None or "time_s" not in reader.fieldnames:
                found = ", ".join(reader.fieldnames or []) or "nothing"
                raise GatingError(
                    f"QRS file {path} needs a header with a 'time_s' column (found {found[:80]})"
                )
            values = []
            for row_number, row in enumerate(reader, start=2):
                if any(v.strip() for v in row.get(None) or ()):  # more values than the header names: "38330,986"
                    raise GatingError(f"QRS file {path}, line {row_number}: more values than the header's columns; "
                                      "a decimal comma? write seconds with a decimal point (38330.986)")
                try:
                    value = float(row["time_s"])
                except (TypeError, ValueError):
                    raise GatingError(
                        f"QRS file {path}, line {row_number}: time_s {str(row['time_s'])[:40]!r} is not a number"
                    ) from None
                if not np.isfinite(value) or abs(value) > QRS_MAX_ABS_S:
                    raise GatingError(
                        f"QRS file {path}, line {row_number}: time_s {value!r} is not a time in seconds "
                        "after midnight; fix or remove the row"
                    )
                values.append(value)
    except UnicodeDecodeError:
        raise GatingError(f"QRS file {path} is not a UTF-8 text CSV (column time_s)") from None
    except csv.Error as exc:
        raise GatingError(f"QRS file {path} is not a readable CSV ({exc}); one column time_s") from None
    except OSError as exc:
        raise GatingError(f"cannot read QRS file {path}: {exc.strerror or exc}") from None
    times = np.asarray(values, dtype=float)
    if len(times) < 2:
        raise GatingError(f"QRS file {path} holds {len(times)} R-peak(s); at least 2 are needed")
    if np.any(np.diff(times) <= 0):
        line = int(np.argmax(np.diff(times) <= 0)) + 3
        raise GatingError(f"QRS file {path}, line {line}: time_s must be strictly increasing")
    return times


def _circular_mean(phases: np.ndarray) -> float:
    angle = np.angle(np.mean(np.exp(2j * np.pi * phases)))
    return float(np.mod(angle / (2 * np.pi), 1.0))


def _report(volume, times_s, phases, source, clock, r_peaks, notes) -> PhaseReport:
    phases = np.asarray(phases, dtype=float)
    slices = tuple(
        SlicePhase(
            index=s.index,
            position_mm=float(s.position_mm),
            time_s=float(t) if t is not None and np.isfinite(t) else float("nan"),
            cardiac_phase=float(p),
            volume_k=float(getattr(s, "k", s.index)),
        )
        for s, t, p in zip(volume.slices, times_s, phases)
    )
    step = np.abs(np.diff(phases))
    step = np.minimum(step, 1.0 - step)
    lo, hi = MOTION_FREE_WINDOW
    return PhaseReport(
        slices=slices,
        volume_cardiac_phase=float(np.mean(phases)),
        circular_mean_phase=_circular_mean(phases),
        source=source,
        clock=clock,
        r_peaks_s=np.asarray(r_peaks, dtype=float),
        jumps=tuple(int(i) for i in np.flatnonzero(step > JUMP_THRESHOLD)),
        fraction_in_window=float(np.mean((phases >= lo) & (phases <= hi))),
        notes=tuple(notes),
    )


def _column(volume, name) -> np.ndarray:
    return np.array(
        [np.nan if getattr(s, name) is None else float(getattr(s, name)) for s in volume.slices]
    )


#: A slice in an R-R interval longer than this multiple of the median R-R lies where beats are missing
#: (a lead off or in noise under the scan, found no beat) or in a pause: its phase is warned about.
LONG_RR_RATIO = 1.8


def _from_r_peaks(times_s, r_peaks_s, what, notes):
    phases = cardiac_phase(times_s, r_peaks_s)
    bad = ~np.isfinite(phases)
    if bad.any():
        (t0, t1), r = (np.nanmin(times_s), np.nanmax(times_s)), r_peaks_s  # both: an ECG of another day shows
        return None, (f"{what}: {int(bad.sum())} slice time(s) fall outside the R-peaks (slices {t0:.3f}..{t1:.3f} s, "
                      f"R-peaks {r[0]:.3f}..{r[-1]:.3f} s" + ("; they do not overlap at all" if t1 < r[0] or t0 > r[-1]
                                                              else "") + "); not extrapolated")
    # the R-R interval each slice lies in (cardiac_phase checked the R-peaks increase and holds every slice)
    r = np.asarray(r_peaks_s, dtype=float)
    rr = np.diff(r)
    median = float(np.median(rr))
    held = rr[np.searchsorted(r, times_s, side="right") - 1]
    long = held > LONG_RR_RATIO * median
    if long.any():
        note = (f"{what}: {int(long.sum())} slice(s) lie in R-R intervals up to {held.max():.2f} s, "
                f"{held.max() / median:.1f} times the median {median:.2f} s: beats missing there (a lead off "
                "or in noise) or a pause; their phases are uncertain")
        notes.append(note)
        warnings.warn(note, GatingWarning, stacklevel=3)
    return phases, None


def _usable_stamps(r_s: np.ndarray, times_s: np.ndarray, notes: list):
    """GE stamps without their NaN values (when no slice needs a missing one), in order, each once.

    GE scanners may write the list twice over (the stamps, then the same again with the next beat:
    pydicom's ``dicomdirtests/98892001``).  Returns ``(r_peaks_s, None)`` or ``(None, why)``; a note
    counts what was left out.
    """
    what = "GE RpeakTimeStamps (0049,xx0C)"
    nan = ~np.isfinite(r_s)
    if nan.all():
        return None, f"{what}: all {nan.size} stamps are NaN; not used"
    if nan.any():
        notes.append(f"{what}: {int(nan.sum())} of {nan.size} stamps are NaN and were left out")
        index = np.flatnonzero(~nan)
        gaps = [(r_s[a], r_s[b]) for a, b in zip(index[:-1], index[1:]) if b > a + 1]
        inside = [t for t in times_s for lo, hi in gaps if lo <= t < hi]
        if inside:
            return None, (f"{what}: a NaN stamp lies among the slice times ({len(inside)} slice(s) between "
                          "the stamps around it); not used")
        r_s = r_s[~nan]
    if r_s.size >= 2 and np.all(np.diff(r_s) > 0):
        return r_s, None
    distinct = np.unique(r_s)
    if distinct.size < 2:
        return None, f"{what}: fewer than two distinct stamps ({r_s.size} given); not used"
    notes.append(f"{what}: {r_s.size} stamps out of order or repeated, {distinct.size} distinct ones used in order")
    return distinct, None


def _waveform_label(k: int, n: int) -> str:
    """An ECG waveform of the study named by its place, not its file: a file or folder name
    can name the patient (``--list-series`` lists the files)."""
    return "ECG waveform" if n == 1 else f"ECG waveform {k + 1} of {n}"


def _read_study_waveforms(volume, notes: list[str]) -> list[tuple[str, object]]:
    """The study's readable ECG waveforms as (label, record), each labelled by its place among all of them."""
    from imaging.waveform import WaveformError, read_ecg_waveform

    records = []
    files = list(getattr(volume, "waveform_files", ()))
    for k, path in enumerate(files):
        label = _waveform_label(k, len(files))
        try:
            records.append((label, read_ecg_waveform(path)))
        except WaveformError as exc:
            notes.append(f"{label} unreadable: " + _strip_paths(str(exc), path))
    return records


def _r_peaks_of_some_lead(record, label: str, notes: list[str]):
    """(R-peaks, label) of the record's lead, or of the first other lead of its group with QRS complexes
    when that one has none (lead II off in a 12-lead ECG whose other leads are good); (None, label) if no lead has."""
    from imaging.waveform import WaveformError, read_ecg_waveform

    try:
        return detect_r_peaks(record.signal_mv, record.rate_hz, start_s=record.start_time_s), label
    except ValueError as exc:
        notes.append(f"{label}: {exc}")
    if record.source == "<Dataset>":
        return None, label
    for k, lead in enumerate(record.channel_labels):
        if k == record.channel_index:
            continue
        try:
            other = read_ecg_waveform(record.source, channel=k, group=record.group_index)
            peaks = detect_r_peaks(other.signal_mv, other.rate_hz, start_s=other.start_time_s)
        except (ValueError, WaveformError):
            continue
        notes.append(f"{label}: lead {record.channel_label} has no usable QRS complexes, lead {lead} used")
        return peaks, f"{label} (lead {lead})"
    return None, label


def _strip_paths(text: str, path) -> str:
    """``text`` without ``path`` (as given or resolved): it becomes "the file"."""
    p = Path(path)
    for long in (str(p.resolve()), str(p)):
        text = text.replace(long, "the file")
    return text


def compute_phase_report(volume, *, qrs_s=None, qrs_label="QRS file", ecg_records=None) -> PhaseReport:
    """Cardiac phase of every slice of ``volume`` from the best available source.

    Every R-peak source the study holds is considered, in the order of the
    module docstring; this is what ``heartreg phases``, ``model`` and
    ``pipeline`` report.

    Parameters
    ----------
    volume : imaging.Volume
        Its ``slices`` carry the slice clocks and gating attributes; its
        ``series`` the GE R-peak time stamps, if any; its ``waveform_files`` the
        study's ECG waveform instances.
    qrs_s : (n,) float, s, optional
        R-peak times on the AcquisitionTime clock (a user's QRS file).
    qrs_label : str
        How to name the R-peak times in the report (e.g. the file name).
    ecg_records : sequence of imaging.waveform.EcgRecord, optional
        ECG waveform records to use instead of reading ``volume.waveform_files``
        (default: read them; an unreadable one is named in the notes).

    Raises
    ------
    GatingError
        When no source can time every slice; the message lists what was looked for.

    Examples
    --------
    The sample study's slices carry GE's R-peak time stamps:

    >>> from imaging import compute_phase_report, load_study
    >>> report = compute_phase_report(load_study("sample_dicom/ct"))
    >>> round(report.volume_cardiac_phase, 2), report.source
    (0.69, 'GE RpeakTimeStamps (0049,xx0C)')
    """
    notes: list[str] = []
    if ecg_records is None:
        labelled = _read_study_waveforms(volume, notes)
    else:
        labelled = [(_waveform_label(k, len(ecg_records)), r) for k, r in enumerate(ecg_records)]
    waveforms = bool(labelled or getattr(volume, "waveform_files", ()))  # read, or there and unreadable (noted)
    acq = _column(volume, "acquisition_time_s")
    has_acq = bool(np.all(np.isfinite(acq)))

    # 1. the user's R-peak file, on the AcquisitionTime clock
    if qrs_s is not None:
        r = np.asarray(qrs_s, dtype=float)
        if not has_acq:
            notes.append(f"{qrs_label}: slices lack AcquisitionTime/ContentTime, cannot align")
        else:
            phases, why = _from_r_peaks(acq, r, qrs_label, notes)
            if phases is not None:
                return _report(
                    volume, acq, phases, f"{qrs_label} (R-peak times)",
                    "slice AcquisitionTime and the R-peak file share the AcquisitionTime clock",
                    r, notes,
                )
            notes.append(why)
        warnings.warn(
            f"the R-peak times given ({qrs_label}) were not used: {notes[-1]}; falling back to the "
            "study's own gating information",
            GatingWarning,
            stacklevel=2,
        )

    # 2. GE RpeakTimeStamps on the Mid Scan Time clock
    rpeaks_ms = getattr(volume.series, "rpeak_timestamps_ms", None)
    mid = _column(volume, "mid_scan_time_s")
    if rpeaks_ms:
        if not np.all(np.isfinite(mid)):
            notes.append("GE RpeakTimeStamps present but some slices lack GE Mid Scan Time")
        else:
            r, why = _usable_stamps(np.asarray(rpeaks_ms, dtype=float) / 1000.0, mid, notes)
            phases = None
            if r is not None:
                phases, why = _from_r_peaks(mid, r, "GE RpeakTimeStamps", notes)
            if phases is not None:
                clock = "GE Mid Scan Time and RpeakTimeStamps share the scan's origin"
                times = mid
                if has_acq:
                    offset = acq - mid
                    spread_ms = 1000.0 * float(np.ptp(offset))
                    clock += (
                        f"; AcquisitionTime = origin + Mid Scan Time with origin "
                        f"{np.median(offset):.3f} s after midnight (spread {spread_ms:.1f} ms)"
                    )
                    times = mid + np.median(offset)
                    r = r + np.median(offset)
                return _report(volume, times, phases, "GE RpeakTimeStamps (0049,xx0C)", clock, r, notes)
            notes.append(why)
    else:
        notes.append("no GE RpeakTimeStamps (0049,xx0C)")

    # 3. an ECG waveform instance of the study, QRS detection on it
    for label, record in labelled:
        if not has_acq:
            notes.append(f"{label}: slices lack AcquisitionTime, cannot align")
            continue
        peaks, label = _r_peaks_of_some_lead(record, label, notes)
        if peaks is None:
            continue
        phases, why = _from_r_peaks(acq, peaks.times_s, label, notes)
        if phases is not None:
            return _report(
                volume, acq, phases, f"{label} (Pan-Tompkins QRS detection)",
                "waveform AcquisitionDateTime + MultiplexGroupTimeOffset on the AcquisitionTime clock",
                peaks.times_s, notes,
            )
        notes.append(why)
    if not waveforms:
        notes.append("no DICOM ECG waveform instance in the study")

    # 4. TriggerTime over the nominal RR interval; 5. the nominal percentage of the cardiac cycle
    def warn(message):
        warnings.warn(message, GatingWarning, stacklevel=5)  # the caller of compute_phase_report

    none = np.full(len(acq), np.nan)
    phases = nominal.trigger_phases(volume.slices, notes, warn)
    if phases is not None:
        note = ("TriggerTime over the nominal RR interval gives nominal phases: every beat is assumed to "
                "last the nominal interval; give R-peak times (--qrs) for measured phases")
        if waveforms or rpeaks_ms:  # the study's own R-peaks failed: said, not only noted
            warnings.warn(f"{note}; the study's own R-peak sources were not usable: {'; '.join(notes)}",
                          GatingWarning, stacklevel=2)
        notes.append(note)
        return _report(volume, acq if has_acq else none, phases, "TriggerTime / nominal RR interval",
                       "phases relative to each slice's own trigger R-peak", np.empty(0), notes)
    phases = nominal.percent_phases(volume.slices, notes, warn)
    if phases is not None:
        return _report(volume, acq if has_acq else none, phases, "NominalPercentageOfCardiacPhase",
                       "nominal (reconstruction) phase, no clock", np.empty(0), notes)
    not_gated = nominal.trigger_not_gated(volume.slices) or nominal.percent_not_gated(volume.slices)
    advice = (
        ". Check that the R-peak file's times are seconds after midnight on the slices' AcquisitionTime clock"
        if qrs_s is not None and has_acq
        else ". Pass an R-peak file with --qrs FILE (CSV, column time_s, seconds after midnight)"
    )
    error = GatingError("no cardiac gating information for the slices" + (f" ({not_gated})" if not_gated else "")
                        + "; looked for: " + "; ".join(notes) + advice + nominal.free_text_hint(volume.series))
    error.reason = not_gated  # a model records the phase as unknown, and why (heartreg.pipeline.open_study)
    raise error
