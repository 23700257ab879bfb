"""Causal cardiac and respiration phases for live localisation.

:mod:`imaging.ecg` and :mod:`imaging.respiration` find R-peaks and starts of
expiration in a whole record, looking forwards and backwards (zero-phase
filters, search-back).  A robot on the beating heart needs its phases *now*,
from the signals so far.  This module gives them sample by sample, with a
bounded delay:

R-peaks and starts of expiration
    :class:`OnlineRPeakDetector` and :class:`OnlineExpirationDetector`
    (:mod:`registration.online_events`), each event confirmed after a bounded
    delay.
Phase (:class:`CausalPhase`)
    ``(t - e_k) / P`` with ``e_k`` the last confirmed event and ``P`` the
    median of the last few intervals (a prior period before there are any).
    The current cycle's end is not known yet: that is the price of causality.
    Past one expected period without a new event (a late beat, or one not yet
    confirmed) the phase runs on into the predicted next cycle and is flagged
    *predicted*; past ``max_gap_periods`` it is undefined (NaN, signal lost).

:class:`CausalPhases` runs all three on a stream of samples given in chunks of
any size: the output of a sample never depends on samples after it, so the
same stream in chunks of 1 or of 10 000 gives the same phases (tested).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from registration.online_events import OnlineExpirationDetector, OnlineRPeakDetector, StreamError

__all__ = [
    "CausalPhase",
    "CausalPhases",
    "OnlineExpirationDetector",
    "OnlineRPeakDetector",
    "PhaseChunk",
    "PhaseFlag",
    "StreamError",
]

#: Intervals whose median is the running period.
HISTORY = 5


class PhaseFlag:
    """Bits of the per-sample phase status (an ``int`` bit field)."""

    #: no cardiac phase: no R-peak yet, or none for ``max_gap_periods``.
    NO_CARDIAC = 1
    #: no respiration phase.
    NO_RESPIRATION = 2
    #: the cardiac phase runs past the expected next R-peak (predicted cycle).
    CARDIAC_PREDICTED = 4
    #: the respiration phase runs past the expected next start of expiration.
    RESPIRATION_PREDICTED = 8


class CausalPhase:
    """Phase from the events so far: ``(t - e_k) / P``, P the running period.

    Parameters
    ----------
    prior_period_s : float, s, optional
        Period assumed until two events have been seen (e.g. the mean RR of
        the registration session); without it there is no phase before the
        second event.
    history : int
        Number of last intervals whose median is the period.
    max_gap_periods : float
        Without a new event for this many periods the phase is undefined.
    """

    def __init__(self, *, prior_period_s: float | None = None, history: int = HISTORY,
                 max_gap_periods: float = 2.5):
        if prior_period_s is not None and not (np.isfinite(prior_period_s) and prior_period_s > 0):
            raise ValueError(f"prior_period_s must be a positive number of seconds, got {prior_period_s!r}")
        if history < 1:
            raise ValueError(f"history must be >= 1, got {history}")
        if not max_gap_periods > 1:
            raise ValueError(f"max_gap_periods must be > 1, got {max_gap_periods}")
        self._prior = None if prior_period_s is None else float(prior_period_s)
        self._intervals: deque[float] = deque(maxlen=int(history))
        self._last: float | None = None
        self._period = self._prior
        self._max_gap = float(max_gap_periods)

    @property
    def period_s(self) -> float | None:
        """The current period estimate (s), None before there is one."""
        return self._period

    def add_event(self, time_s: float) -> None:
        """Record an event (R-peak, start of expiration) at ``time_s``."""
        if self._last is not None:
            if time_s <= self._last:
                return  # a duplicate: events arrive in order
            self._intervals.append(time_s - self._last)
            self._period = float(np.median(self._intervals))
        self._last = float(time_s)

    def phase(self, time_s: float) -> tuple[float, bool]:
        """(phase in [0, 1) or NaN, predicted) at ``time_s``."""
        if self._last is None or self._period is None:
            return float("nan"), False
        x = (time_s - self._last) / self._period
        if x < 0.0:
            return float("nan"), False
        if x < 1.0:
            return x, False
        if x < self._max_gap:
            return x - np.floor(x), True
        return float("nan"), False

    def phases(self, time_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`phase` of many times with the events so far: (phase, predicted), (m,) each."""
        m = time_s.shape[0]
        if self._last is None or self._period is None:
            return np.full(m, np.nan), np.zeros(m, dtype=bool)
        x = (time_s - self._last) / self._period
        predicted = (x >= 1.0) & (x < self._max_gap)
        phase = np.where(predicted, x - np.floor(x), x)
        phase[(x < 0.0) | (x >= self._max_gap)] = np.nan
        return phase, predicted


@dataclass(frozen=True, eq=False)
class PhaseChunk:
    """Causal phases of a chunk of samples.

    Attributes
    ----------
    cardiac_phase, respiration_phase : (m,) float64, cycles
        Cardiac and respiration phase in [0, 1); NaN where undefined.
    flags : (m,) int64
        :class:`PhaseFlag` bits.
    r_peaks : tuple of (float, float)
        ``(R-peak time, confirmed at)`` confirmed in the chunk, s.
    onsets : tuple of (float, float)
        ``(start of expiration, confirmed at)`` confirmed in the chunk, s.
    """

    cardiac_phase: np.ndarray
    respiration_phase: np.ndarray
    flags: np.ndarray
    r_peaks: tuple
    onsets: tuple


class CausalPhases:
    """Cardiac and respiration phases of a live stream, sample by sample.

    Parameters
    ----------
    rate_hz : float, Hz
        Sample rate of the stream (ECG and airflow sampled with the poses).
    rr_prior_s, breath_prior_s : float, s, optional
        Periods assumed until two events are seen (e.g. the registration
        session's mean RR and breath).
    polarity : {1, -1}
        ECG lead polarity.

    Examples
    --------
    20 s at 100 Hz: an R spike every 0.8 s (75 /min), a breath every 4 s
    (expiratory flow in its first half).  The phases are defined once the
    detectors have learnt the signals; at t = 1017.5 s the heart is half-way
    between the beats at 1017.1 and 1017.9 s.

    >>> import numpy as np
    >>> from registration import CausalPhases
    >>> t_s = 1000.0 + np.arange(2000) / 100.0
    >>> ecg_mv = np.exp(-0.5 * ((t_s[:, None] - (1000.3 + 0.8 * np.arange(25))) / 0.01) ** 2).sum(axis=1)
    >>> flow = 20.0 * np.sin(2 * np.pi * (t_s - 1000.0) / 4.0)  # L/min, + while breathing out
    >>> phases = CausalPhases(100.0, rr_prior_s=0.8, breath_prior_s=4.0)
    >>> chunk = phases.update(t_s, ecg_mv, np.clip(-flow, 0, None), np.clip(flow, 0, None))
    >>> (peak_s, confirmed_s), *_ = chunk.r_peaks
    >>> print(f"first R-peak {peak_s:.2f} s (confirmed at {confirmed_s:.2f} s), {len(chunk.r_peaks)} R-peaks, "
    ...       f"{len(chunk.onsets)} starts of expiration")
    first R-peak 1002.70 s (confirmed at 1002.80 s), 22 R-peaks, 3 starts of expiration
    >>> k = int(np.argmin(abs(t_s - 1017.5)))
    >>> print(f"phi_C = {chunk.cardiac_phase[k]:.2f}, phi_R = {chunk.respiration_phase[k]:.2f}")
    phi_C = 0.50, phi_R = 0.39
    """

    def __init__(self, rate_hz: float, *, rr_prior_s: float | None = None,
                 breath_prior_s: float | None = None, polarity: int = 1):
        self.rate_hz = float(rate_hz)
        self.r_detector = OnlineRPeakDetector(rate_hz, polarity=polarity)
        learn = 8.0 if breath_prior_s is None else 1.2 * float(breath_prior_s)
        self.resp_detector = OnlineExpirationDetector(rate_hz, learn_s=learn)
        self.cardiac = CausalPhase(prior_period_s=rr_prior_s)
        self.respiration = CausalPhase(prior_period_s=breath_prior_s)
        self._last_t = -np.inf

    def update(self, time_s, ecg_mv, flow_insp_lpm, flow_exp_lpm) -> PhaseChunk:
        """Phases of each sample of a chunk, from the samples up to it only.

        Parameters
        ----------
        time_s : (m,) float, s
            Strictly increasing, later than every sample already seen.
        ecg_mv, flow_insp_lpm, flow_exp_lpm : (m,) float
            mV and L/min.

        Returns
        -------
        PhaseChunk
        """
        t = np.asarray(time_s, dtype=float)
        arrays = [np.asarray(a, dtype=float) for a in (ecg_mv, flow_insp_lpm, flow_exp_lpm)]
        if t.ndim != 1 or any(a.shape != t.shape for a in arrays):
            raise StreamError(
                f"time_s, ecg_mv and the flows must be 1-D of one length, got {t.shape} and "
                f"{[a.shape for a in arrays]}"
            )
        if t.size and (t[0] <= self._last_t or (t.size > 1 and not np.all(t[1:] > t[:-1]))):
            raise StreamError("sample times must increase strictly across the stream")
        if not np.isfinite(np.sum(arrays, axis=0) + t).all():
            raise StreamError("time, ECG and flow samples must be finite")
        ecg, insp, expi = arrays
        m = t.size
        if m == 1:  # a live sample: the events confirmed at it count for it
            self._last_t = float(t[0])
            peaks = self.r_detector.update(t, ecg)
            onsets = self.resp_detector.update(t, expi, insp)
            flags = 0
            out = []
            for events, phase, no, predicted in ((peaks, self.cardiac, PhaseFlag.NO_CARDIAC, PhaseFlag.CARDIAC_PREDICTED),
                                                 (onsets, self.respiration, PhaseFlag.NO_RESPIRATION,
                                                  PhaseFlag.RESPIRATION_PREDICTED)):
                for event, _ in events:
                    phase.add_event(event)
                value, pred = phase.phase(self._last_t)
                flags |= no if math.isnan(value) else (predicted if pred else 0)
                out.append(np.array([value]))
            return PhaseChunk(out[0], out[1], np.array([flags], dtype=np.int64), tuple(peaks), tuple(onsets))
        phase_c = np.empty(m)
        phase_r = np.empty(m)
        flags = np.zeros(m, dtype=np.int64)
        if m == 0:
            return PhaseChunk(phase_c, phase_r, flags, (), ())
        self._last_t = float(t[-1])
        # events are confirmed at a sample; phases from that sample on use them
        peaks = self.r_detector.update(t, ecg)
        onsets = self.resp_detector.update(t, expi, insp)
        pred_c = np.zeros(m, dtype=bool)
        pred_r = np.zeros(m, dtype=bool)
        for events, phase, out, pred in ((peaks, self.cardiac, phase_c, pred_c),
                                         (onsets, self.respiration, phase_r, pred_r)):
            # between confirmations the state is fixed: fill each run at once
            start = 0
            active = np.searchsorted(t, [c for _, c in events], side="left")
            for (event, _), i in zip(events, active.tolist()):
                if i > start:
                    out[start:i], pred[start:i] = phase.phases(t[start:i])
                    start = i
                phase.add_event(event)
            out[start:], pred[start:] = phase.phases(t[start:])
        no_c, no_r = np.isnan(phase_c), np.isnan(phase_r)
        flags = (np.where(no_c, PhaseFlag.NO_CARDIAC, np.where(pred_c, PhaseFlag.CARDIAC_PREDICTED, 0))
                 | np.where(no_r, PhaseFlag.NO_RESPIRATION, np.where(pred_r, PhaseFlag.RESPIRATION_PREDICTED, 0)))
        flags = flags.astype(np.int64)
        return PhaseChunk(phase_c, phase_r, flags, tuple(peaks), tuple(onsets))
