"""Causal event detectors for live localisation: R-peaks and starts of expiration.

:mod:`imaging.ecg` and :mod:`imaging.respiration` find these events in a whole
record, looking forwards and backwards.  The detectors here see the samples so
far only, and confirm each event after a bounded delay
(:class:`registration.online.CausalPhases` turns the events into phases):

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
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy import signal

from hrcore.errors import HeartregError

__all__ = ["OnlineExpirationDetector", "OnlineRPeakDetector", "StreamError"]

#: Band (Hz) of the causal QRS detection filter (Pan-Tompkins).
QRS_BAND_HZ = (5.0, 15.0)


class StreamError(HeartregError, ValueError):
    """A stream of samples that cannot be processed (rate, order, values)."""


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
