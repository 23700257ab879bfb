"""QRS (R-peak) detection in an ECG and the cardiac phase between R-peaks.

The detector follows Pan and Tompkins (IEEE Trans Biomed Eng 1985;32:230), the
choice of Wood et al. 2018 (section 2.2.4):

1. band-pass 5-15 Hz (Butterworth, run forwards and backwards: zero phase);
2. five-point derivative, squaring, moving-window integration (150 ms,
   centred: no delay);
3. peaks of the integrated signal at least one refractory period (200 ms)
   apart, classified sequentially with adaptive signal/noise peak levels
   (``SPKI``, ``NPKI``; threshold ``NPKI + 0.25 (SPKI - NPKI)``);
4. T-wave discrimination: a peak within 360 ms of the previous QRS whose
   maximal slope is below half that QRS's slope is a T wave;
5. search-back: when no QRS came for 1.66 times the regular RR interval, the
   largest peak above half the threshold in the gap is taken as a QRS (also in
   the gaps before the first and after the last detection).

Each detection is then moved to the true R-peak: the extremum of the lightly
filtered (0.5-40 Hz, zero phase) signal within +-80 ms, on the side of the
dominant QRS deflection of the record (inverted leads are handled), refined
below one sample by a parabola through the extremum and its two neighbours.
Filter delays therefore do not leak into the R-peak times or the phases.

A beat is reported only if it is complete: its extremum is an interior local
extremum of the record, so a QRS cut by the start or the end is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal

from imaging.events import SignalError, phase_from_events

__all__ = ["RPeaks", "SignalError", "detect_r_peaks", "cardiac_phase"]

#: Pan-Tompkins band (Hz) of the detection filter.
QRS_BAND_HZ = (5.0, 15.0)
#: Band (Hz) of the light filter on which R maxima are located.
REFINE_BAND_HZ = (0.5, 40.0)
#: Moving-window integration length (s).
INTEGRATION_S = 0.150
#: Half-width (s) of the window in which a detection is moved to the R maximum.
REFINE_HALF_WIDTH_S = 0.080
#: A peak this close (s) after a QRS is tested for being a T wave.
T_WAVE_WINDOW_S = 0.360
#: Search back when no QRS came for this multiple of the regular RR interval.
SEARCH_BACK_FACTOR = 1.66
#: Shortest record (s) on which detection is attempted.
MIN_DURATION_S = 2.0
#: Lowest sampling rate (Hz): the 5-15 Hz band must sit well below Nyquist.
MIN_RATE_HZ = 50.0
#: Below this 99.9th-percentile absolute value of the QRS-band signal (mV) the
#: record is called flat.
MIN_QRS_BAND_MV = 0.02


@dataclass(frozen=True)
class RPeaks:
    """R-peaks found in an ECG.

    Attributes
    ----------
    times_s : (n,) float64, s
        Sub-sample R-peak times on the signal's clock (``start_s + i / rate_hz``),
        strictly increasing.
    indices : (n,) int64
        Sample index nearest to each R-peak.
    amplitudes_mv : (n,) float64, mV
        Height of each R (S for an inverted lead) above the local baseline of the
        lightly filtered signal, as a positive number.
    rate_hz : float
        Sampling rate of the signal.
    start_s : float, s
        Time of sample 0.
    polarity : int
        +1 if the dominant QRS deflection is upwards, -1 if the lead is inverted.
    """

    times_s: np.ndarray
    indices: np.ndarray
    amplitudes_mv: np.ndarray
    rate_hz: float
    start_s: float
    polarity: int

    def __len__(self) -> int:
        return int(self.times_s.size)

    @property
    def rr_s(self) -> np.ndarray:
        """(n - 1,) float64, s: intervals between consecutive R-peaks."""
        return np.diff(self.times_s)


def cardiac_phase(time_s, r_peaks_s) -> np.ndarray:
    """Cardiac phase ``(t - R_k) / (R_{k+1} - R_k)`` for ``R_k <= t < R_{k+1}``.

    Parameters
    ----------
    time_s : float or array_like of float, s
        Query times, any shape.
    r_peaks_s : (m,) array_like of float, s, or RPeaks
        Strictly increasing R-peak times on the same clock, m >= 2.

    Returns
    -------
    float64 array of the shape of ``time_s``
        Phase in [0, 1); NaN before the first and from the last R-peak on (never
        extrapolated) and for NaN times.

    Raises
    ------
    SignalError
        If fewer than two R-peaks are given, or they are not strictly increasing.
    """
    return phase_from_events(time_s, r_peaks_s, name="r_peaks_s", what="R-peak")


def _check_signal(signal_mv, rate_hz) -> tuple[np.ndarray, float]:
    if signal_mv is None:
        raise SignalError("signal_mv is None: give the ECG samples in mV")
    x = np.asarray(signal_mv, dtype=float)
    if x.ndim != 1:
        raise SignalError(f"signal_mv must have shape (n,), got {x.shape}: pick one lead")
    try:
        rate = float(rate_hz)
    except (TypeError, ValueError):
        raise SignalError(f"rate_hz must be a number in Hz, got {rate_hz!r}") from None
    if not np.isfinite(rate) or rate < MIN_RATE_HZ:
        raise SignalError(
            f"rate_hz must be at least {MIN_RATE_HZ:g} Hz for QRS detection, got {rate_hz!r}"
        )
    if x.size == 0:
        raise SignalError("signal_mv is empty: there is no ECG to detect QRS complexes in")
    if not np.all(np.isfinite(x)):
        bad = int(np.count_nonzero(~np.isfinite(x)))
        raise SignalError(
            f"signal_mv contains {bad} NaN or infinite samples: interpolate or cut them out first"
        )
    duration = x.size / rate
    if duration < MIN_DURATION_S:
        raise SignalError(
            f"signal_mv covers {duration:.3g} s; QRS detection needs at least "
            f"{MIN_DURATION_S:g} s (a few beats): give a longer record"
        )
    if np.ptp(x) == 0.0:
        raise SignalError("signal_mv is constant: the lead is disconnected or not an ECG")
    return x, rate


def _bandpass(x: np.ndarray, band_hz: tuple[float, float], rate: float) -> np.ndarray:
    nyquist = 0.5 * rate
    hi = min(band_hz[1], 0.8 * nyquist)
    sos = signal.butter(2, [band_hz[0], hi], btype="bandpass", fs=rate, output="sos")
    return signal.sosfiltfilt(sos, x)


def _parabolic(y_m: np.ndarray, y_0: np.ndarray, y_p: np.ndarray) -> np.ndarray:
    """Offset in samples (within [-0.5, 0.5]) of the vertex of the parabola through 3 points."""
    den = y_m - 2.0 * y_0 + y_p
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(den < 0, 0.5 * (y_m - y_p) / den, 0.0)
    return np.clip(delta, -0.5, 0.5)


class _PanTompkins:
    """Sequential adaptive-threshold classification of integrated-signal peaks."""

    def __init__(self, peaks, values, slopes, rate, refractory):
        self.peaks, self.values, self.slopes = peaks, values, slopes
        self.rate, self.refractory = rate, refractory

    def run(self, learn_max: float, learn_mean: float) -> list[int]:
        spk, npk = 0.25 * learn_max, 0.5 * learn_mean
        qrs: list[int] = []  # indices into self.peaks
        rr: list[float] = []
        self.first_threshold2 = None
        for j in range(self.peaks.size):
            p, v = self.peaks[j], self.values[j]
            th1 = npk + 0.25 * (spk - npk)
            if qrs:
                last = qrs[-1]
                limit = self._rr_limit(rr)
                if limit is not None and p - self.peaks[last] > limit:
                    found = self._search_back(last, j, 0.5 * th1)
                    if found is not None:
                        spk = 0.25 * self.values[found] + 0.75 * spk
                        self._accept(qrs, rr, found)
                        th1 = npk + 0.25 * (spk - npk)
            if v > th1:
                if qrs and p - self.peaks[qrs[-1]] < T_WAVE_WINDOW_S * self.rate:
                    if self.slopes[j] < 0.5 * self.slopes[qrs[-1]]:
                        npk = 0.125 * v + 0.875 * npk  # a T wave
                        continue
                spk = 0.125 * v + 0.875 * spk
                if not qrs:
                    self.first_threshold2 = 0.5 * th1
                self._accept(qrs, rr, j)
            else:
                npk = 0.125 * v + 0.875 * npk
        self.last_threshold2 = 0.5 * (npk + 0.25 * (spk - npk))
        return qrs

    def _accept(self, qrs, rr, j):
        if qrs:
            rr.append(float(self.peaks[j] - self.peaks[qrs[-1]]))
        qrs.append(j)

    @staticmethod
    def _rr_limit(rr: list[float]) -> float | None:
        """1.66 x the regular RR average (Pan-Tompkins RR AVERAGE2), samples."""
        if len(rr) < 2:
            return None
        recent = np.asarray(rr[-8:])
        avg1 = float(np.mean(recent))
        regular = [r for r in rr[-32:] if 0.92 * avg1 <= r <= 1.16 * avg1][-8:]
        avg = float(np.mean(regular)) if regular else avg1
        return SEARCH_BACK_FACTOR * avg

    def _search_back(self, last: int, j: int, threshold: float) -> int | None:
        lo = self.peaks[last] + self.refractory
        hi = self.peaks[j] - self.refractory
        cand = [k for k in range(last + 1, j) if lo <= self.peaks[k] <= hi]
        return self._best(cand, threshold)

    def _best(self, cand, threshold) -> int | None:
        if not cand:
            return None
        k = max(cand, key=lambda c: self.values[c])
        return k if self.values[k] > threshold else None


def detect_r_peaks(
    signal_mv,
    rate_hz: float,
    *,
    start_s: float = 0.0,
    refractory_s: float = 0.200,
    polarity: int | str = "auto",
) -> RPeaks:
    """Detect QRS complexes (Pan-Tompkins) and locate each R-peak below one sample.

    Parameters
    ----------
    signal_mv : (n,) array_like of float, mV
        One ECG lead, uniformly sampled, at least 2 s long, finite.
    rate_hz : float, Hz
        Sampling rate, at least 50 Hz (100-1000 Hz tested).
    start_s : float, s
        Time of sample 0 (e.g. seconds after midnight on the study clock).
    refractory_s : float, s
        Shortest RR interval accepted (Pan-Tompkins: 200 ms).
    polarity : {"auto", 1, -1}
        Side of the dominant QRS deflection.  "auto" chooses it from the median
        upward and downward QRS excursions of the record (inverted leads give -1).

    Returns
    -------
    RPeaks
        R-peak times (s, on the clock of ``start_s``), nearest indices, amplitudes.

    Raises
    ------
    SignalError
        If the signal is absent, empty, not 1-D, contains NaN, is constant or flat,
        is shorter than 2 s, the rate is below 50 Hz, or no QRS complex is found.
    """
    x, rate = _check_signal(signal_mv, rate_hz)
    start = float(start_s)
    if not np.isfinite(start):
        raise SignalError(f"start_s must be a finite time in s, got {start_s!r}")
    if not (0.05 <= float(refractory_s) <= 1.0):
        raise SignalError(f"refractory_s must be in [0.05, 1.0] s, got {refractory_s!r}")
    if polarity not in ("auto", 1, -1):
        raise SignalError(f"polarity must be 'auto', 1 or -1, got {polarity!r}")

    # --- Pan-Tompkins front end -------------------------------------------
    band = _bandpass(x, QRS_BAND_HZ, rate)
    if np.percentile(np.abs(band), 99.9) < MIN_QRS_BAND_MV:
        raise SignalError(
            "signal_mv is flat: no QRS-band activity above "
            f"{MIN_QRS_BAND_MV:g} mV (is the lead connected, and is the signal in mV?)"
        )
    deriv = np.convolve(band, np.array([1.0, 2.0, 0.0, -2.0, -1.0]) * (rate / 8.0), mode="same")
    win = max(1, int(round(INTEGRATION_S * rate)))
    # Mean over the in-record part of the window, so a QRS at an edge keeps its level.
    ones = np.ones_like(deriv)
    mwi = ndimage.uniform_filter1d(deriv**2, win, mode="constant") / ndimage.uniform_filter1d(
        ones, win, mode="constant"
    )
    refractory = int(round(float(refractory_s) * rate))
    # Zero padding lets a maximum at the very first or last sample count as a peak.
    pad = max(1, refractory)
    padded = np.concatenate([np.zeros(pad), mwi, np.zeros(pad)])
    peaks, _ = signal.find_peaks(padded, distance=pad)
    peaks = peaks - pad
    if peaks.size == 0:
        raise SignalError("no QRS complex found in signal_mv: check the lead and the units (mV)")
    values = mwi[peaks]
    half = max(2, int(round(0.075 * rate)))
    abs_deriv = np.abs(deriv)
    slopes = np.array([abs_deriv[max(0, p - half) : p + half + 1].max() for p in peaks])

    learn = mwi[: int(2.0 * rate)]
    pt = _PanTompkins(peaks, values, slopes, rate, refractory)
    qrs = pt.run(float(learn.max()), float(learn.mean()))
    if not qrs:
        raise SignalError("no QRS complex found in signal_mv: check the lead and the units (mV)")
    qrs = _search_edges(pt, qrs, x.size)
    coarse = peaks[np.asarray(sorted(qrs), dtype=int)]

    # --- move each detection to the R maximum ------------------------------
    light = _bandpass(x, REFINE_BAND_HZ, rate)
    w = max(2, int(round(REFINE_HALF_WIDTH_S * rate)))
    sign = _polarity(light, coarse, w, rate) if polarity == "auto" else int(polarity)
    y = sign * light
    n = y.size
    idx, amp = [], []
    base_w = int(round(0.25 * rate))
    for c in coarse:
        lo, hi = max(0, c - w), min(n, c + w + 1)
        k = lo + int(np.argmax(y[lo:hi]))
        if k <= 0 or k >= n - 1 or y[k] < y[k - 1] or y[k] < y[k + 1]:
            continue  # extremum at the record's edge: an incomplete beat
        idx.append(k)
        amp.append(y[k] - np.median(y[max(0, k - base_w) : k + base_w + 1]))
    if not idx:
        raise SignalError("no complete QRS complex found in signal_mv: give a longer record")
    idx_arr = np.asarray(idx, dtype=np.int64)
    amp_arr = np.asarray(amp, dtype=float)
    idx_arr, amp_arr = _dedupe(idx_arr, amp_arr, refractory)
    delta = _parabolic(y[idx_arr - 1], y[idx_arr], y[idx_arr + 1])
    times = start + (idx_arr + delta) / rate
    for arr in (times, idx_arr, amp_arr):
        arr.setflags(write=False)
    return RPeaks(
        times_s=times,
        indices=idx_arr,
        amplitudes_mv=amp_arr,
        rate_hz=rate,
        start_s=start,
        polarity=sign,
    )


def _search_edges(pt: _PanTompkins, qrs: list[int], n: int) -> list[int]:
    """Search back in the gaps before the first and after the last detection."""
    qrs = list(qrs)
    if len(qrs) >= 2:
        rr = np.diff(pt.peaks[np.asarray(qrs)])
        limit = SEARCH_BACK_FACTOR * float(np.median(rr))
    else:
        limit = SEARCH_BACK_FACTOR * pt.rate  # assume 60 bpm when nothing better is known
    first, last = qrs[0], qrs[-1]
    if pt.peaks[first] > limit:
        cand = [k for k in range(first) if pt.peaks[k] <= pt.peaks[first] - pt.refractory]
        found = pt._best(cand, pt.first_threshold2)
        if found is not None:
            qrs.insert(0, found)
    if n - 1 - pt.peaks[last] > limit:
        cand = [
            k for k in range(last + 1, pt.peaks.size) if pt.peaks[k] >= pt.peaks[last] + pt.refractory
        ]
        found = pt._best(cand, pt.last_threshold2)
        if found is not None:
            qrs.append(found)
    return qrs


def _polarity(light: np.ndarray, coarse: np.ndarray, w: int, rate: float) -> int:
    """+1 if the median upward QRS excursion beats the median downward one, else -1."""
    up, down = [], []
    base_w = int(round(0.25 * rate))
    for c in coarse:
        seg = light[max(0, c - w) : c + w + 1]
        base = np.median(light[max(0, c - base_w) : c + base_w + 1])
        up.append(seg.max() - base)
        down.append(base - seg.min())
    return 1 if np.median(up) >= np.median(down) else -1


def _dedupe(idx: np.ndarray, amp: np.ndarray, refractory: int):
    """Drop the smaller of two refined peaks closer than the refractory period."""
    order = np.argsort(idx, kind="stable")
    idx, amp = idx[order], amp[order]
    keep_i, keep_a = [int(idx[0])], [float(amp[0])]
    for k, a in zip(idx[1:], amp[1:]):
        if k - keep_i[-1] < refractory:
            if a > keep_a[-1]:
                keep_i[-1], keep_a[-1] = int(k), float(a)
            continue
        keep_i.append(int(k))
        keep_a.append(float(a))
    return np.asarray(keep_i, dtype=np.int64), np.asarray(keep_a, dtype=float)
