"""Nominal cardiac phases from the slices' gating tags (sources 4 and 5 of :mod:`imaging.phase`).

(0018,1060) *Trigger Time* over the nominal RR interval ((0018,1062) *Nominal
Interval*, else 60000 / (0018,1088) *Heart Rate*), and (0020,9241) *Nominal
Percentage of Cardiac Phase*: what the scanner meant to acquire, every beat
assumed to last the nominal interval.

When these tags carry no gating information (issue #9)
------------------------------------------------------
A scan without ECG gating may still carry the tags, with nothing in them: a
phase taken from them would be a made-up 0.0 on every slice. The rule, by the
(0018,9037) *Cardiac Synchronization Technique* and by whether an RR interval
is known:

* technique ``NONE`` on every slice: the scan was not ECG-gated; its trigger
  times and percentages are not used, whatever their values;
* a gating technique (``PROSPECTIVE``, ``RETROSPECTIVE``, ``TRIGGERED``,
  ``PACED``, ``REALTIME``, ...): the values are used as written, 0 included
  (prospective gating at 0 % of the RR interval is a real phase);
* no technique: trigger times that are all 0 are used only with a
  *Nominal Interval* (the RR interval a gated scan used); 0 with at most a
  *Heart Rate* (a monitor's reading, which ungated scans record too) is the
  value an ungated scanner writes, not a phase. Percentages that are all 0,
  with no trigger time other than 0 and no *Nominal Interval*, likewise. Any
  other values (non-zero, or differing between slices) are gating and used.

The phase is then unknown (:func:`imaging.compute_phase_report` raises
``GatingError`` with the reason, a model records it and registration asks for
``--cardiac-phase``), unless a measured R-peak source times the slices.

Values beyond one RR interval
-----------------------------
A trigger time longer than the nominal RR interval (a percentage over 100)
means the beat lasted longer than nominal, or the value is bad. Such phases are
kept wrapped into the next beat (``trigger / RR - 1``), with a warning giving
their count and range: a prospective trigger delay longer than the beat does
acquire in the next beat, and the other slices' phases stay usable; a trigger
time counted from the slice's own R-peak (retrospective) is late in a long beat
instead, which the warning says to check. Values of 2 RR intervals (200 %) or
more, or negative ones, are no delay within a beat: the source is not used.

TriggerTime and percentage disagreeing
--------------------------------------
When the slices carry both, TriggerTime is used; a percentage more than
``DISAGREE`` of the RR interval away from its phase is warned about (one of the
two is wrong). A phase stated only in the series description ("75%",
"BestDiast") is free text, not used: the error says what it states and to give
it with ``--cardiac-phase``.
"""

from __future__ import annotations

import re

import numpy as np

#: (0018,9037) *Cardiac Synchronization Technique* of a scan without ECG gating.
NOT_GATED = "NONE"
#: A trigger time at this many nominal RR intervals or more (or negative) is no delay within a beat: not used.
MAX_RR_RATIO = 2.0
#: TriggerTime and percentage phases further apart than this (share of the RR interval) disagree: warned.
DISAGREE = 0.1


def _column(items, name) -> np.ndarray:
    return np.array([np.nan if getattr(s, name, None) is None else float(getattr(s, name)) for s in items])


def _techniques(items) -> set:
    return {getattr(s, "cardiac_sync_technique", None) for s in items} - {None}


def _all_zero(values: np.ndarray) -> bool:
    return bool(values.size) and bool(np.all(values == 0))


def _no_interval(items) -> bool:
    interval = _column(items, "nominal_interval_ms")
    return not np.any(np.isfinite(interval) & (interval > 0))


def trigger_not_gated(items) -> str | None:
    """Why the TriggerTime values of ``items`` (slices or frames) time no beat (module docstring), or None."""
    techniques = _techniques(items)
    if techniques == {NOT_GATED}:
        return f"CardiacSynchronizationTechnique {NOT_GATED}: the scan was not ECG-gated"
    if not techniques and _all_zero(_column(items, "trigger_time_ms")) and _no_interval(items):
        return ("TriggerTime 0 on every slice, with no CardiacSynchronizationTechnique and no NominalInterval: "
                "the values of a scan without ECG gating")
    return None


def percent_not_gated(items) -> str | None:
    """Why the NominalPercentageOfCardiacPhase values of ``items`` give no phase (module docstring), or None."""
    techniques = _techniques(items)
    if techniques == {NOT_GATED}:
        return f"CardiacSynchronizationTechnique {NOT_GATED}: the scan was not ECG-gated"
    trigger = _column(items, "trigger_time_ms")
    if (not techniques and _all_zero(_column(items, "nominal_cardiac_percent")) and _no_interval(items)
            and not np.any(np.isfinite(trigger) & (trigger != 0))):
        return ("NominalPercentageOfCardiacPhase 0 on every slice, with no CardiacSynchronizationTechnique, "
                "TriggerTime or NominalInterval: the values of a scan without ECG gating")
    return None


def _range(values: np.ndarray, unit: str = "") -> str:
    lo, hi = (float(f"{v:.4g}") for v in (np.min(values), np.max(values)))
    return (f"{lo:g}" if lo == hi else f"{lo:g}..{hi:g}") + (f" {unit}" if unit else "")


def _wrapped(ratio: np.ndarray, what: str, values: np.ndarray, unit: str, limit: str, notes: list, warn):
    """``ratio`` wrapped into [0, 1), or None when some value is negative or 2 cycles or more (noted);
    values over one cycle are warned about with their count and range (module docstring)."""
    n = ratio.size
    bad = (ratio < 0) | (ratio >= MAX_RR_RATIO)
    if bad.any():
        notes.append(f"{what}: {int(bad.sum())} of {n} slice(s) at {_range(values[bad], unit)}, negative or "
                     f"{MAX_RR_RATIO:g} times {limit} or more: not a phase within a beat; not used")
        return None
    over = ratio > 1.0
    if over.any():
        message = (f"{what}: {int(over.sum())} of {n} slice(s) at {_range(values[over], unit)}, beyond {limit}: "
                   "the beat lasted longer than nominal, or the values are bad; their phases are wrapped into "
                   f"the next beat (phases {_range(ratio[over] - 1.0)}); check them, or give R-peak times with --qrs "
                   "or the phase with --cardiac-phase")
        notes.append(message)
        warn(message)
    return np.mod(ratio, 1.0)


def _not_gated(items, what: str, why_not, notes: list) -> bool:
    """Whether the ``what`` values of ``items`` are no gating (``why_not(items)`` says why, noted)."""
    why = why_not(items)
    if why:
        notes.append(f"{what} not used: {why}")
    return bool(why)


def trigger_phases(items, notes: list, warn) -> np.ndarray | None:
    """Phases ``TriggerTime / RR`` of ``items``, or None (why noted) when not every slice has both or they
    are no gating (module docstring); ``warn(message)`` is called for values beyond the RR interval."""
    trigger = _column(items, "trigger_time_ms")
    interval = _column(items, "nominal_interval_ms")
    rate = _column(items, "heart_rate_bpm")
    rr_ms = np.where(np.isfinite(interval) & (interval > 0), interval,
                     60000.0 / np.where(rate > 0, rate, np.nan))
    if not (np.all(np.isfinite(trigger)) and np.all(np.isfinite(rr_ms))):
        notes.append("no TriggerTime with NominalInterval or HeartRate on every slice")
        return None
    if _not_gated(items, "TriggerTime", trigger_not_gated, notes):
        return None
    if not _techniques(items) and _all_zero(trigger):
        notes.append("TriggerTime 0 on every slice with a NominalInterval and no CardiacSynchronizationTechnique: "
                     "taken as gating at 0 % of the RR interval")
    phases = _wrapped(trigger / rr_ms, "TriggerTime", trigger, "ms",
                      f"the nominal RR interval ({_range(rr_ms, 'ms')})", notes, warn)
    if phases is not None:
        _check_percent(items, phases, notes, warn)
    return phases


def _check_percent(items, phases: np.ndarray, notes: list, warn) -> None:
    """Warn when the slices' NominalPercentageOfCardiacPhase states other phases than their TriggerTime
    (more than ``DISAGREE`` of the RR interval apart, circularly): one of the two is wrong."""
    pct = _column(items, "nominal_cardiac_percent")
    usable = np.isfinite(pct)
    if not usable.any() or percent_not_gated(items):
        return
    gap = np.abs(phases[usable] - np.mod(pct[usable] / 100.0, 1.0))
    off = np.minimum(gap, 1.0 - gap) > DISAGREE
    if off.any():
        message = (f"TriggerTime and NominalPercentageOfCardiacPhase disagree on {int(off.sum())} of {phases.size} "
                   f"slice(s): TriggerTime gives phases {_range(phases[usable][off])}, the percentage says "
                   f"{_range(pct[usable][off], '%')}; the TriggerTime phases are used; check which is right, "
                   "or give R-peak times with --qrs or the phase with --cardiac-phase")
        notes.append(message)
        warn(message)


def percent_phases(items, notes: list, warn) -> np.ndarray | None:
    """Phases ``NominalPercentageOfCardiacPhase / 100`` of ``items``, or None (why noted)."""
    pct = _column(items, "nominal_cardiac_percent")
    if not np.all(np.isfinite(pct)):
        notes.append("no NominalPercentageOfCardiacPhase on every slice")
        return None
    if _not_gated(items, "NominalPercentageOfCardiacPhase", percent_not_gated, notes):
        return None
    return _wrapped(pct / 100.0, "NominalPercentageOfCardiacPhase", pct, "%", "100 %", notes, warn)


_PERCENT = re.compile(r"(?<![\d.])(\d{1,2}(?:\.\d+)?)\s*%")
_BEST = re.compile(r"best\s*(diast|syst)", re.IGNORECASE)


def free_text_hint(series) -> str:
    """What the series description states of the phase in free text ("75%", "BestDiast"), as advice for a
    CT whose phase is unknown, or "".  Free text is no gating tag and is not used as the phase; the text
    itself is not repeated (a description can name the patient), only the values found."""
    text = str(getattr(series, "description", "") or "")
    values = sorted({float(v) for v in _PERCENT.findall(text)})
    if len(values) == 1:
        return (f". The series description states {values[0]:g} % (free text, not a gating tag, so not used): if "
                f"that is the phase the CT was reconstructed at, give it to heartreg register with "
                f"--cardiac-phase {values[0] / 100:g}")
    if values:
        return (". The series description states " + ", ".join(f"{v:g} %" for v in values) + " (free text, not "
                "used): give the CT's phase to heartreg register with --cardiac-phase P")
    best = _BEST.search(text)
    if best:
        kind = "diastolic" if best.group(1).lower() == "diast" else "systolic"
        return (f". The series description names the scanner's automatic best {kind} phase without its value: "
                "read it on the scanner's protocol and give it to heartreg register with --cardiac-phase P")
    return ""
