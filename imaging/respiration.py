"""Starts of expiration in ventilator airflow, and the respiration phase.

Wood et al. 2018 (section 2.2.4) take the respiration phase as 0 at the start
of expiration and linear in time up to the next start.  The airflow comes from
two sensors, in the inspiratory and the expiratory line of the ventilator; either
may be missing, and a single signed flow (expiration positive, inspiration
negative) works as well.

Detection runs on the signed flow ``q = expiratory - inspiratory``:

1. low-pass (1 Hz, Butterworth, zero phase) against the cardiogenic oscillation
   and sensor noise;
2. hysteresis on the low-passed flow: a start of expiration is an upward
   crossing of the level 50 % up the flow's robust range (5th to 95th percentile)
   after the flow was below the 25 % level; a breath phase shorter than
   ``min_phase_s`` is not a breath;
3. each start is refined on the raw flow: the steepest rise within +-0.5 s of
   the coarse crossing, and then the crossing, interpolated linearly between
   samples, of the level half way between the flow before the rise and its
   peak just after.  A ventilator's expiratory valve opens in a step, so the
   onset lies within that one sample interval.

A start of expiration less than 0.25 s after the start of the record (the flow
before it unseen) is not reported: the phase there is unknown, not extrapolated.
"""

from __future__ import annotations

import numpy as np

from imaging.events import SignalError, phase_from_events, zero_phase_filter

__all__ = ["SignalError", "expiration_onsets", "respiration_phase"]

#: Cut-off (Hz) of the low-pass used to find breaths (above breathing, below the heart rate).
LOWPASS_HZ = 1.0
#: Hysteresis levels as fractions of the robust flow range (upper: start of
#: expiration; lower: re-arm during inspiration).
UPPER_LEVEL = 0.50
LOWER_LEVEL = 0.25
#: Robust flow range (L/min) below which the flow is called flat.
MIN_RANGE_LPM = 0.5
#: Half-width (s) of the window searched for the step at a start of expiration.
REFINE_HALF_WIDTH_S = 0.5
#: Lowest sampling rate (Hz).
MIN_RATE_HZ = 5.0


def respiration_phase(time_s, onsets_s) -> np.ndarray:
    """Respiration phase, 0 at each start of expiration, linear up to the next.

    Parameters
    ----------
    time_s : float or array_like of float, s
        Query times, any shape.
    onsets_s : (m,) array_like of float, s
        Strictly increasing starts of expiration on the same clock, m >= 2.

    Returns
    -------
    float64 array of the shape of ``time_s``
        Phase in [0, 1); NaN before the first and from the last onset on.

    Raises
    ------
    SignalError
        If fewer than two onsets are given, or they are not strictly increasing.

    Examples
    --------
    >>> from imaging import respiration_phase
    >>> respiration_phase([1.0, 3.0, 5.5], [0.0, 4.0, 8.0])
    array([0.25 , 0.75 , 0.375])
    """
    return phase_from_events(time_s, onsets_s, name="onsets_s", what="start-of-expiration")


def _as_flow(flow, name: str) -> np.ndarray | None:
    if flow is None:
        return None
    q = np.asarray(flow, dtype=float)
    if q.ndim != 1:
        raise SignalError(f"{name} must have shape (n,), got {q.shape}")
    if q.size == 0:
        raise SignalError(f"{name} is empty: give the airflow samples in L/min")
    if not np.all(np.isfinite(q)):
        bad = int(np.count_nonzero(~np.isfinite(q)))
        raise SignalError(f"{name} contains {bad} NaN or infinite samples: interpolate or cut them out")
    return q


def _signed_flow(flow_exp_lpm, flow_insp_lpm) -> np.ndarray:
    exp = _as_flow(flow_exp_lpm, "flow_exp_lpm")
    insp = _as_flow(flow_insp_lpm, "flow_insp_lpm")
    if exp is None and insp is None:
        raise SignalError("give flow_exp_lpm, flow_insp_lpm or both: no airflow was given")
    if exp is not None and insp is not None:
        if exp.shape != insp.shape:
            raise SignalError(
                f"flow_exp_lpm and flow_insp_lpm must have the same shape, got {exp.shape} "
                f"and {insp.shape}: they are sampled together"
            )
        return exp - insp
    return exp if exp is not None else -insp


def expiration_onsets(
    *,
    rate_hz: float,
    flow_exp_lpm=None,
    flow_insp_lpm=None,
    start_s: float = 0.0,
    min_phase_s: float = 0.5,
) -> np.ndarray:
    """Times of the starts of expiration in ventilator airflow.

    Parameters
    ----------
    rate_hz : float, Hz
        Sampling rate of the flow signals (at least 5 Hz; 100 Hz in the paper).
    flow_exp_lpm : (n,) array_like of float, L/min, optional
        Flow in the expiratory line (non-negative), or a single signed flow with
        expiration positive and inspiration negative.
    flow_insp_lpm : (n,) array_like of float, L/min, optional
        Flow in the inspiratory line (non-negative).
    start_s : float, s
        Time of sample 0.
    min_phase_s : float, s
        Shortest expiration or inspiration accepted as a breath phase.

    Returns
    -------
    (m,) float64, s
        Strictly increasing starts of expiration on the clock of ``start_s``,
        interpolated between samples.

    Raises
    ------
    SignalError
        If no flow is given, the flows differ in shape, contain NaN, are flat,
        or no start of expiration is found.

    Examples
    --------
    A ventilator breathing every 4 s, expiring while the sine is negative:

    >>> import numpy as np
    >>> from imaging import expiration_onsets
    >>> breath = np.sin(2 * np.pi * np.arange(0, 20, 0.01) / 4)
    >>> onsets = expiration_onsets(rate_hz=100.0, flow_exp_lpm=30 * np.clip(-breath, 0, None),
    ...                            flow_insp_lpm=30 * np.clip(breath, 0, None))
    >>> onsets.round(1)
    array([ 2.,  6., 10., 14., 18.])
    """
    q = _signed_flow(flow_exp_lpm, flow_insp_lpm)
    try:
        rate = float(rate_hz)
    except (TypeError, ValueError):
        raise SignalError(f"rate_hz must be a number in Hz, got {rate_hz!r}") from None
    if not np.isfinite(rate) or rate < MIN_RATE_HZ:
        raise SignalError(f"rate_hz must be at least {MIN_RATE_HZ:g} Hz, got {rate_hz!r}")
    start = float(start_s)
    if not np.isfinite(start):
        raise SignalError(f"start_s must be a finite time in s, got {start_s!r}")
    if not (0.0 < float(min_phase_s) < 30.0):
        raise SignalError(f"min_phase_s must be in (0, 30) s, got {min_phase_s!r}")
    min_len = int(np.ceil(3.0 * rate))
    if q.size < min_len:
        raise SignalError(
            f"the airflow covers {q.size / rate:.3g} s: too short to hold a breath; "
            "record at least two breaths"
        )

    smooth = zero_phase_filter(q, min(LOWPASS_HZ, 0.4 * rate), "lowpass", rate)
    lo, hi = np.percentile(smooth, [5.0, 95.0])
    span = hi - lo
    if not span > MIN_RANGE_LPM:
        raise SignalError(
            f"the airflow is flat (robust range {span:.3g} L/min < {MIN_RANGE_LPM:g} L/min): "
            "is the ventilator running and the flow in L/min?"
        )
    upper = lo + UPPER_LEVEL * span
    lower = lo + LOWER_LEVEL * span
    coarse = _hysteresis_rises(smooth, upper, lower, int(round(float(min_phase_s) * rate)))
    if coarse.size == 0:
        raise SignalError(
            f"no breathing found in {q.size / rate:.3g} s of airflow: no start of expiration "
            "(rise of the expiratory flow) was seen; check which line each flow comes from"
        )
    onsets = [t for c in coarse if (t := _refine(q, int(c), rate)) is not None]
    if not onsets:
        raise SignalError("no complete start of expiration found in the airflow: record a longer signal")
    return start + np.unique(np.asarray(onsets)) / rate


def _hysteresis_rises(smooth: np.ndarray, upper: float, lower: float, min_len: int) -> np.ndarray:
    """Indices of upward crossings of ``upper`` after the flow was at or below ``lower``.

    At the start of the record the detector is armed if the flow is below
    ``upper`` (a rise seen whole is a start of expiration; one cut by the start
    is rejected later, in :func:`_refine`, for want of the flow before it).

    Consecutive crossings closer than ``2 * min_len`` samples (an expiration and
    an inspiration each at least ``min_len`` long) are not two breaths: the
    later one is dropped.
    """
    above = (smooth >= upper).astype(np.int8)
    below = (smooth <= lower).astype(np.int8)
    ups = np.flatnonzero(np.diff(above) == 1) + 1
    downs = np.flatnonzero(np.diff(below) == 1) + 1
    if smooth[0] < upper:  # the record starts outside an expiration: armed
        downs = np.concatenate([[0], downs])
    events = sorted([(int(k), 1) for k in ups] + [(int(k), 0) for k in downs])
    armed = False
    rises: list[int] = []
    for k, is_up in events:
        if not is_up:
            armed = True
        elif armed and (not rises or k - rises[-1] >= 2 * min_len):
            rises.append(k)
            armed = False
    return np.asarray(rises, dtype=int)


def _refine(q: np.ndarray, c: int, rate: float) -> float | None:
    """Sub-sample index of the half-rise crossing of the step near coarse index ``c``."""
    n = q.size
    w = max(2, int(round(REFINE_HALF_WIDTH_S * rate)))
    lo, hi = max(1, c - w), min(n - 1, c + w)
    if hi - lo < 2:
        return None
    d = np.diff(q[lo - 1 : hi + 1])  # d[j] = q[lo + j] - q[lo + j - 1]
    k = lo + int(np.argmax(d))  # first sample after the steepest rise
    pre_lo, pre_hi = k - int(round(0.25 * rate)), k - int(round(0.05 * rate))
    if pre_lo < 0 or pre_hi - pre_lo < 1:
        return None  # the flow before the step is not in the record
    pre = float(np.median(q[pre_lo:pre_hi]))
    post = float(q[k : min(n, k + max(1, int(round(0.1 * rate))))].max())
    level = 0.5 * (pre + post)
    # last upward crossing of the level at or before the peak after the step
    peak = k + int(np.argmax(q[k : min(n, k + max(1, int(round(0.1 * rate))))]))
    seg = q[max(0, k - int(round(0.1 * rate))) : peak + 1]
    base = max(0, k - int(round(0.1 * rate)))
    cross = np.flatnonzero((seg[:-1] < level) & (seg[1:] >= level))
    if cross.size == 0:
        return None
    j = base + int(cross[-1])
    return j + (level - q[j]) / (q[j + 1] - q[j])
