"""Causal cardiac and respiration phases for live localisation.

:mod:`imaging.ecg` and :mod:`imaging.respiration` find R-peaks and starts of
expiration in a whole record, looking forwards and backwards (zero-phase
filters, search-back).  A robot on the beating heart needs its phases *now*,
from the signals so far.  This module gives them sample by sample, with a
bounded delay:

R-peaks (:class:`OnlineRPeakDetector`)
    A causal band-pass (5-15 Hz, Butterworth, the Pan-Tompkins band) flags a
    QRS when its magnitude crosses ``threshold_fraction`` of the running QRS
    level (learnt over the first ``learn_s`` seconds, then tracked beat by
    beat); a refractory period (200 ms) keeps T waves out.  The R-peak is then
    located, as offline, at the extremum of the ECG (3-tap smoothed, which
    nulls mains at Nyquist and leaves a symmetric peak where it is) within
    ``search_back_s`` before and ``confirm_s`` after the crossing, below one
    sample by a parabola.  It is *confirmed* ``confirm_s`` after the crossing:
    that bounds the latency of every detection.
Starts of expiration (:class:`OnlineExpirationDetector`)
    On the signed flow ``expiratory - inspiratory``, hysteresis between 25 % and
    50 % of the flow's running range (learnt over one breath), as offline; the
    onset is the crossing of the level half way between the flow before the
    step and its peak just after, interpolated between samples, confirmed two
    samples later.
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
from scipy import signal

from hrcore.errors import HeartregError

__all__ = [
    "CausalPhase",
    "CausalPhases",
    "OnlineExpirationDetector",
    "OnlineRPeakDetector",
    "PhaseChunk",
    "PhaseFlag",
    "StreamError",
]

#: Band (Hz) of the causal QRS detection filter (Pan-Tompkins).
QRS_BAND_HZ = (5.0, 15.0)
#: Intervals whose median is the running period.
HISTORY = 5


class StreamError(HeartregError, ValueError):
    """A stream of samples that cannot be processed (rate, order, values)."""


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


class _Ring:
    """Fixed-size history of (time, value) samples addressed by global index."""

    def __init__(self, size: int):
        self.size = size
        self.t = [0.0] * size
        self.v = [0.0] * size

    def put(self, i: int, t: float, v: float) -> None:
        j = i % self.size
        self.t[j] = t
        self.v[j] = v


def _parabolic(ym: float, y0: float, yp: float) -> float:
    den = ym - 2.0 * y0 + yp
    if den >= 0.0:
        return 0.0
    return min(0.5, max(-0.5, 0.5 * (ym - yp) / den))


class OnlineRPeakDetector:
    """Causal R-peak detection with a bounded latency (see the module docstring).

    Parameters
    ----------
    rate_hz : float, Hz
        Sampling rate of the ECG (at least 50 Hz).
    polarity : {1, -1}
        Side of the dominant QRS deflection (-1 for an inverted lead).
    refractory_s : float, s
        Shortest RR interval accepted.
    learn_s : float, s
        The QRS level is learnt over the first ``learn_s`` seconds; nothing is
        detected before.
    threshold_fraction : float
        A QRS starts where the band-passed magnitude crosses this fraction of
        the running QRS level.
    search_back_s, confirm_s : float, s
        The R extremum is searched from ``search_back_s`` before the crossing
        to ``confirm_s`` after it; the detection is reported ``confirm_s``
        after the crossing.
    """

    def __init__(self, rate_hz: float, *, polarity: int = 1, refractory_s: float = 0.2,
                 learn_s: float = 2.0, threshold_fraction: float = 0.35,
                 search_back_s: float = 0.08, confirm_s: float = 0.10):
        rate = float(rate_hz)
        if not (np.isfinite(rate) and rate >= 50.0):
            raise StreamError(f"rate_hz must be at least 50 Hz for QRS detection, got {rate_hz!r}")
        if polarity not in (1, -1):
            raise ValueError(f"polarity must be 1 or -1, got {polarity!r}")
        self.rate_hz = rate
        self.polarity = int(polarity)
        hi = min(QRS_BAND_HZ[1], 0.4 * rate)
        self._sos = signal.butter(2, [QRS_BAND_HZ[0], hi], btype="bandpass", fs=rate, output="sos")
        self._sos_list = [tuple(float(c) for c in row) for row in self._sos]
        self._zi = None
        self._refractory = float(refractory_s)
        self._learn_s = float(learn_s)
        self._fraction = float(threshold_fraction)
        self._back = max(2, int(round(search_back_s * rate)))
        self._fwd = max(2, int(round(confirm_s * rate)))
        self._ring = _Ring(self._back + self._fwd + 8)
        self._i = 0
        self._t0: float | None = None
        self._level = 0.0
        self._learning = True
        self._open_until = -1  # global index at which the open window closes
        self._cross = -1
        self._last_r = -np.inf
        self._band_max = 0.0  # max |band| inside the open window

    def update(self, time_s, ecg_mv) -> list[tuple[float, float]]:
        """Feed a chunk of samples; return the R-peaks confirmed in it.

        Parameters
        ----------
        time_s, ecg_mv : (m,) float
            Sample times (s, increasing) and ECG values (mV).

        Returns
        -------
        list of (r_time_s, confirmed_at_s)
            Each R-peak confirmed in this chunk and the time of the sample at
            which it was confirmed (the latency is their difference).
        """
        t = np.asarray(time_s, dtype=float)
        x = np.asarray(ecg_mv, dtype=float)
        if t.size == 0:
            return []
        if self._zi is None:
            self._zi = (signal.sosfilt_zi(self._sos) * x[0]).tolist()
            self._t0 = float(t[0])
        out: list[tuple[float, float]] = []
        ring = self._ring
        pol = self.polarity
        sos, zi = self._sos_list, self._zi
        for ti, xi in zip(t.tolist(), x.tolist()):
            # the band-pass, second-order sections in transposed direct form II
            # (as scipy's sosfilt), in plain floats: a sample costs a microsecond
            y = xi
            for (b0, b1, b2, _, a1, a2), z in zip(sos, zi):
                out_y = b0 * y + z[0]
                z[0] = b1 * y - a1 * out_y + z[1]
                z[1] = b2 * y - a2 * out_y
                y = out_y
            bi = y if y >= 0.0 else -y
            i = self._i
            ring.put(i, ti, pol * xi)
            self._i = i + 1
            if self._learning:
                self._level = max(self._level, bi)
                if ti - self._t0 >= self._learn_s:
                    self._learning = False
                continue
            if self._open_until >= 0:
                self._band_max = max(self._band_max, bi)
                if i >= self._open_until:
                    r = self._locate()
                    self._open_until = -1
                    self._level = 0.875 * self._level + 0.125 * self._band_max
                    if r is not None and r - self._last_r >= self._refractory:
                        self._last_r = r
                        out.append((r, ti))
                continue
            if bi > self._fraction * self._level and ti - self._last_r >= self._refractory:
                self._cross = i
                self._open_until = i + self._fwd
                self._band_max = bi
        return out

    def _locate(self) -> float | None:
        """Sub-sample time of the extremum in the window around the crossing."""
        ring = self._ring
        lo = max(self._cross - self._back, self._i - ring.size + 1, 0)
        hi = self._i - 1  # last sample stored
        if hi - lo < 4:
            return None
        v = [ring.v[j % ring.size] for j in range(lo, hi + 1)]
        s = [0.25 * v[k - 1] + 0.5 * v[k] + 0.25 * v[k + 1] for k in range(1, len(v) - 1)]
        k = max(range(len(s)), key=s.__getitem__)
        if k == 0 or k == len(s) - 1:
            return None  # extremum at the window's edge: not a QRS peak
        delta = _parabolic(s[k - 1], s[k], s[k + 1])
        g = lo + 1 + k  # global index of the extremum
        t0 = ring.t[g % ring.size]
        t1 = ring.t[(g + 1) % ring.size] if delta >= 0 else ring.t[(g - 1) % ring.size]
        return t0 + abs(delta) * (t1 - t0)


class OnlineExpirationDetector:
    """Causal starts of expiration in ventilator airflow (see the module docstring).

    Parameters
    ----------
    rate_hz : float, Hz
    learn_s : float, s
        The flow's range is learnt over this long (at least one breath) before
        the first detection.
    window_s : float, s
        The running range is that of the last ``window_s`` seconds (two or
        three breaths).
    min_phase_s : float, s
        Shortest expiration or inspiration accepted as a breath phase.
    """

    def __init__(self, rate_hz: float, *, learn_s: float = 8.0, window_s: float = 15.0,
                 min_phase_s: float = 0.5):
        rate = float(rate_hz)
        if not (np.isfinite(rate) and rate >= 5.0):
            raise StreamError(f"rate_hz must be at least 5 Hz for the airflow, got {rate_hz!r}")
        self.rate_hz = rate
        self._learn_s = float(learn_s)
        self._block = max(1, int(round(0.5 * rate)))  # range kept per half-second block
        self._blocks: deque[tuple[float, float]] = deque(maxlen=max(2, int(round(window_s / 0.5))))
        self._cur = [np.inf, -np.inf, 0]
        self._t0: float | None = None
        self._armed = False
        self._min_gap = 2.0 * float(min_phase_s)
        self._last = -np.inf
        self._pending = -1  # index at which a rise is confirmed
        self._ring = _Ring(int(round(0.4 * rate)) + 8)
        self._i = 0

    def _range(self) -> tuple[float, float]:
        lo = min([b[0] for b in self._blocks] + [self._cur[0]])
        hi = max([b[1] for b in self._blocks] + [self._cur[1]])
        return lo, hi

    def update(self, time_s, flow_exp_lpm, flow_insp_lpm) -> list[tuple[float, float]]:
        """Feed a chunk; return ``(onset_s, confirmed_at_s)`` of the starts confirmed in it."""
        t = np.asarray(time_s, dtype=float)
        q = np.asarray(flow_exp_lpm, dtype=float) - np.asarray(flow_insp_lpm, dtype=float)
        out: list[tuple[float, float]] = []
        if t.size == 0:
            return out
        if self._t0 is None:
            self._t0 = float(t[0])
        ring = self._ring
        lo, hi = self._range()
        for ti, qi in zip(t.tolist(), q.tolist()):
            i = self._i
            ring.put(i, ti, qi)
            self._i = i + 1
            cur = self._cur
            cur[0] = min(cur[0], qi)
            cur[1] = max(cur[1], qi)
            cur[2] += 1
            if cur[2] >= self._block:
                self._blocks.append((cur[0], cur[1]))
                self._cur = [np.inf, -np.inf, 0]
                lo, hi = self._range()
            if ti - self._t0 < self._learn_s:
                continue
            span = hi - lo
            if not span > 0.5:
                continue
            if self._pending >= 0:
                if i >= self._pending:
                    onset = self._refine(self._pending - 2)
                    self._pending = -1
                    if onset is not None and onset - self._last >= self._min_gap:
                        self._last = onset
                        out.append((onset, ti))
                continue
            if qi <= lo + 0.25 * span:
                self._armed = True
            elif self._armed and qi >= lo + 0.5 * span and ti - self._last >= self._min_gap:
                self._armed = False
                self._pending = i + 2
        return out

    def _refine(self, j: int) -> float | None:
        """Half-rise crossing of the step whose upper crossing was at index ``j``."""
        ring, n = self._ring, self.rate_hz
        first = max(0, self._i - ring.size + 1)
        pre_lo, pre_hi = j - int(round(0.25 * n)), j - int(round(0.05 * n))
        if pre_lo < first:
            return None
        pre = float(np.median([ring.v[k % ring.size] for k in range(pre_lo, pre_hi)]))
        post = max(ring.v[k % ring.size] for k in range(j, self._i))
        level = 0.5 * (pre + post)
        for k in range(self._i - 2, max(first, j - int(round(0.1 * n))) - 1, -1):
            a, b = ring.v[k % ring.size], ring.v[(k + 1) % ring.size]
            if a < level <= b:
                ta, tb = ring.t[k % ring.size], ring.t[(k + 1) % ring.size]
                return ta + (level - a) / (b - a) * (tb - ta)
        return None


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
