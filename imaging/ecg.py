"""QRS (R-peak) detection in an ECG and the cardiac phase between R-peaks.

The detector follows Pan and Tompkins (IEEE Trans Biomed Eng 1985;32:230), the
choice of Wood et al. 2018 (section 2.2.4):

1. band-pass 5-25 Hz (Butterworth, run forwards and backwards: zero phase; the
   upper edge at most 0.8 of the Nyquist frequency) of the ECG through a 4 ms
   running median (pacing spikes and one-sample artefacts removed);
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
   Steps 3 to 5 are :mod:`imaging.qrs_classify`.

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
from scipy import ndimage

from imaging.events import SignalError, phase_from_events, zero_phase_filter
from imaging.qrs_classify import _Classifier, _search_edges

__all__ = ["RPeaks", "SignalError", "detect_r_peaks", "cardiac_phase"]

#: Pan-Tompkins band (Hz) of the detection filter.
QRS_BAND_HZ = (5.0, 25.0)
#: Band (Hz) of the light filter on which R maxima are located.
REFINE_BAND_HZ = (0.5, 40.0)
#: Moving-window integration length (s).
INTEGRATION_S = 0.150
#: Half-width (s) of the window in which a detection is moved to the R maximum.
REFINE_HALF_WIDTH_S = 0.065
#: Seconds at the start from which the first signal and noise levels are learnt: the median of 2 s blocks'
#: energy maxima, so that a start of noise shorter than half of it (an electrode put on late) is not
#: learnt as the signal (8 s: ten seconds of noise first gave 14-23 false beats on each MIT-BIH record).
LEARN_S = 60.0
#: Half-width (s) of the window whose median is a beat's baseline.
BASELINE_HALF_WIDTH_S = 0.25
#: A beat's R-peak goes to the record's minor side when that side's excursion
#: is this many times the dominant side's.
LOCAL_POLARITY_RATIO = 1.0
#: A beat whose R-peak lies closer than this (s) to either end of the record is
#: incomplete (half a QRS complex) and is left out.
EDGE_MARGIN_S = 0.050
#: Shortest record (s) on which detection is attempted.
MIN_DURATION_S = 2.0
#: Lowest sampling rate (Hz): the QRS band's upper edge is cut to 0.8 Nyquist (20 Hz here).
MIN_RATE_HZ = 50.0
#: Below this 99.9th-percentile absolute value of the QRS-band signal (mV) the
#: record is called flat.
MIN_QRS_BAND_MV = 0.02
#: Detection sees the ECG through a running median this long (s; at least 3 samples): a pacemaker's spike
#: or a one-sample artefact (1-2 ms) goes, a QRS (60-120 ms) stays.  A 5 mV one-sample spike between every two
#: beats (asynchronous pacing) gave F1 0.43-0.73 on MIT-BIH 102, 104, 106 and 108; 0.99-1.00 now.
SPIKE_S = 0.004
#: Time (s) at the record's extreme value in a row that makes a clipped (saturated) R: 3 samples at
#: MIT-BIH's 360 Hz.  As a count of samples, a pacemaker's 2 ms spike clipped at the rail was a "clipped R"
#: from 1500 Hz on, and every R-peak moved onto the spike 50 ms before it (median error 49 ms).
MIN_CLIPPED_RUN_S = 0.008
#: Half-width (s) of the window in which a beat's QRS-band peak is taken for its contrast.
CONTRAST_HALF_WIDTH_S = 0.060
#: Below this QRS contrast (:attr:`RPeaks.qrs_contrast`) the record holds no QRS
#: complexes, only noise: the detector's peaks in white or coloured noise reach
#: 2.5-3.8, the 30 s windows of the eight MIT-BIH records 6.8-79 (median 30).
MIN_QRS_CONTRAST = 4.5


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
    qrs_contrast : float
        How far the beats stand out: the median over beats of the largest
        absolute QRS-band (5-25 Hz) value within 60 ms of the R-peak, over the
        record's median absolute QRS-band value.  Noise alone gives 2.5-4 (the
        largest of ~40 correlated samples over their median); a real ECG more
        than 5 even in the noisiest MIT-BIH records.
    """

    times_s: np.ndarray
    indices: np.ndarray
    amplitudes_mv: np.ndarray
    rate_hz: float
    start_s: float
    polarity: int
    qrs_contrast: float

    def __len__(self) -> int:
        return int(self.times_s.size)


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

    Examples
    --------
    >>> from imaging import cardiac_phase
    >>> cardiac_phase([0.5, 1.25, 1.9, 2.5], [0.0, 1.0, 2.0])  # after the last R-peak: unknown
    array([0.5 , 0.25, 0.9 ,  nan])
    """
    return phase_from_events(time_s, r_peaks_s, name="r_peaks_s", what="R-peak")


def _check_signal(signal_mv, rate_hz) -> tuple[np.ndarray, float]:
    if signal_mv is None:
        raise SignalError("signal_mv is None: give the ECG samples in mV")
    if np.iscomplexobj(signal_mv):
        raise SignalError("signal_mv is complex: give the ECG's real samples in mV")
    try:
        x = np.asarray(signal_mv, dtype=float)
    except (TypeError, ValueError):
        raise SignalError(f"signal_mv must be numbers (the ECG in mV), got {type(signal_mv).__name__}") from None
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
    return zero_phase_filter(x, (band_hz[0], hi), "bandpass", rate)


def _running_median(x: np.ndarray, size: int) -> np.ndarray:
    """``ndimage.median_filter(x, size, mode="nearest")`` of a 1-D signal, ``size`` odd.

    The 3-sample median (every rate below 750 Hz, :data:`SPIKE_S`) is taken as
    ``max(min(a, b), min(max(a, b), c))`` of each sample and its neighbours: it
    selects the same sample as the rank filter (equal values; a zero's sign may differ) at
    a tenth of the time.  At the ends the record's first or last sample counts
    twice ("nearest"), and the median of ``(a, a, b)`` is ``a``: they stay.
    """
    if size != 3:
        return ndimage.median_filter(x, size=size, mode="nearest")
    out = np.empty_like(x)
    out[0], out[-1] = x[0], x[-1]
    before, here, after = x[:-2], x[1:-1], x[2:]
    inner = out[1:-1]
    np.maximum(before, here, out=inner)
    np.minimum(inner, after, out=inner)
    np.maximum(np.minimum(before, here), inner, out=inner)
    return out


def _parabolic(y_m: np.ndarray, y_0: np.ndarray, y_p: np.ndarray) -> np.ndarray:
    """Offset in samples (within [-0.5, 0.5]) of the vertex of the parabola through 3 points."""
    den = y_m - 2.0 * y_0 + y_p
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(den < 0, 0.5 * (y_m - y_p) / den, 0.0)
    return np.clip(delta, -0.5, 0.5)


def _number(value, name: str) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise SignalError(f"{name} must be a number in s, got {value!r}") from None


def detect_r_peaks(
    signal_mv,
    rate_hz: float,
    *,
    start_s: float = 0.0,
    refractory_s: float = 0.200,
    polarity: int | str = "auto",
) -> RPeaks:
    """Detect QRS complexes and locate each R-peak below one sample.

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
        Side of the QRS deflection the R-peak is put on.  "auto" chooses it per
        beat: the record's dominant side (from the median upward and downward
        QRS excursions), unless the other side's excursion of that beat is
        larger (ectopic beats of the opposite polarity).  1 or -1 fixes it.

    Returns
    -------
    RPeaks
        R-peak times (s, on the clock of ``start_s``), nearest indices, amplitudes.

    Raises
    ------
    SignalError
        If the signal is absent, empty, not 1-D, contains NaN, is constant or flat,
        is shorter than 2 s, the rate is below 50 Hz, or no QRS complex is found
        (none, or none standing out of the noise: :data:`MIN_QRS_CONTRAST`).

    References
    ----------
    Pan J, Tompkins WJ. A real-time QRS detection algorithm. IEEE Trans Biomed
    Eng 1985;32(3):230-236. doi:10.1109/TBME.1985.325532

    Examples
    --------
    >>> import numpy as np
    >>> rate = 250.0
    >>> t = np.arange(int(10 * rate)) / rate
    >>> beats = np.arange(0.5, 10.0, 0.8)
    >>> ecg = sum(np.exp(-0.5 * ((t - b) / 0.012) ** 2) for b in beats)
    >>> peaks = detect_r_peaks(ecg, rate)
    >>> np.allclose(peaks.times_s, beats, atol=1e-3)
    True
    """
    x, rate = _check_signal(signal_mv, rate_hz)
    start, refractory_s = _number(start_s, "start_s"), _number(refractory_s, "refractory_s")
    if not np.isfinite(start):
        raise SignalError(f"start_s must be a finite time in s, got {start_s!r}")
    if not (0.05 <= refractory_s <= 1.0):
        raise SignalError(f"refractory_s must be in [0.05, 1.0] s, got {refractory_s!r}")
    if not (isinstance(polarity, str) and polarity == "auto") and not (
            isinstance(polarity, (int, np.integer)) and not isinstance(polarity, bool) and polarity in (1, -1)):
        raise SignalError(f"polarity must be 'auto', 1 or -1, got {polarity!r}")

    # --- energy of the QRS band: band-pass, derivative, square, integrate ---
    spikes = max(3, 2 * int(round(SPIKE_S * rate / 2.0)) + 1)  # samples, odd
    band = _bandpass(_running_median(x, spikes), QRS_BAND_HZ, rate)
    band_abs = np.abs(band)
    if _flat(band_abs):
        raise SignalError(
            "signal_mv is flat: no QRS-band activity above "
            f"{MIN_QRS_BAND_MV:g} mV (is the lead connected, and is the signal in mV?)"
        )
    deriv = ndimage.convolve1d(band, np.array([-1.0, -2.0, 0.0, 2.0, 1.0]) * (rate / 8.0), mode="nearest")
    win = max(1, int(round(INTEGRATION_S * rate)))
    refractory = int(round(float(refractory_s) * rate))
    pad = max(1, refractory)  # zero padding: a maximum at the very first or last sample counts
    padded = np.zeros(x.size + 2 * pad)  # the energy is written between the padding, not copied into it
    energy = padded[pad : pad + x.size]
    squared = np.multiply(deriv, deriv, out=band)  # into the band's memory: the band is not needed again
    ndimage.uniform_filter1d(squared, win, mode="constant", output=energy)
    # mean over the in-record part of the window only, at both ends
    edge = min(win, energy.size // 2)
    coverage = ndimage.uniform_filter1d(np.ones(min(3 * win, energy.size)), win, mode="constant")
    energy[:edge] /= coverage[:edge]
    energy[energy.size - edge :] /= coverage[coverage.size - edge :]
    from scipy import signal  # on first use, as in imaging.events

    peaks, _ = signal.find_peaks(padded, distance=pad)
    peaks = peaks - pad
    if peaks.size == 0:
        raise SignalError("no QRS complex found in signal_mv: check the lead and the units (mV)")
    values = energy[peaks]
    half = max(2, int(round(0.075 * rate)))
    around = np.clip(peaks[:, None] + np.arange(-half, half + 1), 0, deriv.size - 1)
    slopes = np.abs(deriv[around]).max(axis=1)
    light = _bandpass(x, REFINE_BAND_HZ, rate)
    heights = np.ptp(light[around], axis=1)  # peak to peak in the R-peak's band: a QRS's size, a P wave's

    # --- classification: initial levels from the first seconds -------------
    learn_n = min(x.size, int(LEARN_S * rate))
    block = int(2.0 * rate)
    starts = range(0, learn_n - block + 1, block)
    tops = [energy[i : i + block].max() for i in starts] or [energy[:learn_n].max()]
    means = [energy[i : i + block].mean() for i in starts] or [energy[:learn_n].mean()]
    clf = _Classifier(peaks, values, slopes, heights, rate, refractory)
    qrs = clf.run(float(np.median(tops)), 0.5 * float(np.median(means)))  # medians: a transient is not learnt
    if not qrs:
        raise SignalError("no QRS complex found in signal_mv: check the lead and the units (mV)")
    qrs = _search_edges(clf, qrs, x.size)
    coarse = np.asarray([clf.peaks[j] for j in sorted(qrs)], dtype=np.int64)

    # --- move each detection to its R-peak ---------------------------------
    idx, amp, sign = _refine(light, coarse, rate, polarity)
    margin = int(np.ceil(EDGE_MARGIN_S * rate))
    inside = (idx >= max(1, margin)) & (idx <= x.size - 1 - max(1, margin))
    idx, amp = idx[inside], amp[inside]
    if idx.size == 0:
        raise SignalError("no complete QRS complex found in signal_mv: give a longer record")
    idx, amp, keep = _dedupe(idx, amp, refractory)
    side = sign[inside][keep]
    delta = _parabolic(side * light[idx - 1], side * light[idx], side * light[idx + 1])
    times = start + _unclipped(x, idx + delta, side, int(round(REFINE_HALF_WIDTH_S * rate)),
                               max(3, int(round(MIN_CLIPPED_RUN_S * rate)))) / rate
    for arr in (times, idx, amp):
        arr.setflags(write=False)
    dominant = 1 if np.count_nonzero(side > 0) >= np.count_nonzero(side < 0) else -1
    contrast = _qrs_contrast(band_abs, idx, rate)  # the last use of band_abs: it is reordered
    if contrast < MIN_QRS_CONTRAST:
        raise SignalError(
            f"the ECG holds no QRS complexes that stand out of its noise (the {idx.size} peaks found are "
            f"{contrast:.1f} times its median QRS-band level, an ECG's more than {MIN_QRS_CONTRAST:g}): check the lead"
        )
    return RPeaks(times_s=times, indices=idx, amplitudes_mv=amp, rate_hz=rate, start_s=start, polarity=dominant,
                  qrs_contrast=contrast)


def _unclipped(x: np.ndarray, at: np.ndarray, side: np.ndarray, reach: int, min_run: int) -> np.ndarray:
    """R-peak positions (samples) with the beats whose R the amplifier clipped put mid-plateau.

    A saturated R is a run of at least ``min_run`` samples (:data:`MIN_CLIPPED_RUN_S`) at the
    record's extreme value; the filtered signal's maximum wanders over such a
    plateau (up to 40 ms from the R on MIT-BIH 119 clipped at 1.5 mV, a fifth of
    its beats), its middle is the best estimate.  ``at`` within ``reach``
    samples of a run on the beat's side moves to the run's middle.
    """
    out = np.array(at, dtype=float)
    for sign, rail in ((1, x.max()), (-1, x.min())):
        at_rail = np.flatnonzero(x == rail)
        breaks = np.flatnonzero(np.diff(at_rail) > 1)
        starts = at_rail[np.concatenate([[0], breaks + 1])]
        stops = at_rail[np.concatenate([breaks, [at_rail.size - 1]])] + 1
        long = stops - starts >= min_run
        starts, stops = starts[long], stops[long]
        if starts.size == 0:
            continue
        # the runs within reach of a beat are consecutive (runs are disjoint, in time order): those from
        # the first ending at most ``reach`` before it to the last starting at most ``reach`` after it
        first = np.searchsorted(stops - 1 + reach, at, side="left")
        after_last = np.searchsorted(starts - reach, at, side="right")
        for k in np.flatnonzero((side == sign) & (first < after_last)):
            near = np.arange(first[k], after_last[k])
            j = near[np.argmin(np.abs(0.5 * (starts[near] + stops[near] - 1) - at[k]))]
            out[k] = 0.5 * (starts[j] + stops[j] - 1)
    return out


def _flat(band_abs: np.ndarray) -> bool:
    """Whether the 99.9th percentile (``np.percentile``'s, linear) of the absolute QRS-band signal is below
    :data:`MIN_QRS_BAND_MV`.

    The number of samples below the bound decides it without a sort (a copy and a partial sort of the
    record) unless the bound lies among the sorted values the percentile interpolates between; the
    margin of one value either side covers the rounding of their position.
    """
    below = int(np.count_nonzero(band_abs < MIN_QRS_BAND_MV))
    rank = int(np.floor(0.999 * (band_abs.size - 1)))  # the percentile lies between sorted values rank, rank + 1
    if below >= rank + 3:
        return True  # the values around rank all below the bound
    if below <= rank - 1:
        return False  # the values around rank all at or above it
    return bool(np.percentile(band_abs, 99.9) < MIN_QRS_BAND_MV)


def _qrs_contrast(band_abs: np.ndarray, idx: np.ndarray, rate: float) -> float:
    """:attr:`RPeaks.qrs_contrast` of the beats at ``idx`` in the absolute QRS-band signal.

    ``band_abs`` is reordered (its median taken in place, without a copy of the record).
    """
    peaks = np.nanmax(_windows(band_abs, idx, max(1, int(round(CONTRAST_HALF_WIDTH_S * rate)))), axis=1)
    level = float(np.median(band_abs, overwrite_input=True))
    return float(np.median(peaks) / level) if level > 0 else float("inf")


def _windows(y: np.ndarray, centres: np.ndarray, half: int) -> np.ndarray:
    """(m, 2 half + 1) samples of ``y`` around each centre, NaN outside the record."""
    offsets = np.arange(-half, half + 1)
    index = centres[:, None] + offsets
    out = y[np.clip(index, 0, y.size - 1)]
    out[(index < 0) | (index >= y.size)] = np.nan
    return out


def _refine(light: np.ndarray, coarse: np.ndarray, rate: float, polarity):
    """R-peak index, amplitude (mV) and side (+1/-1) of every coarse detection.

    Each beat's R-peak is the extremum of the lightly filtered signal within
    +-REFINE_HALF_WIDTH_S of the detection, on the side chosen by ``polarity``
    ("auto": the record's dominant side unless this beat's excursion on the other
    side is larger), measured from the beat's local baseline (median over +-250 ms).
    """
    w = max(2, int(round(REFINE_HALF_WIDTH_S * rate)))
    seg = _windows(light, coarse, w)
    bw = int(round(BASELINE_HALF_WIDTH_S * rate))
    around = light[np.clip(coarse[:, None] + np.arange(-bw, bw + 1), 0, light.size - 1)]
    base = np.partition(around, bw, axis=1)[:, bw]  # the median of the 2 bw + 1 samples: the middle one
    up = np.nanmax(seg, axis=1) - base
    down = base - np.nanmin(seg, axis=1)
    if polarity == "auto":
        dominant = 1 if np.median(up) >= np.median(down) else -1
        mine, other = (up, down) if dominant == 1 else (down, up)
        sign = np.where(other > LOCAL_POLARITY_RATIO * mine, -dominant, dominant)
    else:
        sign = np.full(coarse.size, int(polarity))
    signed = seg * sign[:, None]
    k = np.nanargmax(signed, axis=1)
    idx = coarse - w + k
    # a maximum at the window's border may sit on a slope: climb to the extremum
    y_n = light.size
    for _ in range(w):
        i = np.clip(idx, 1, y_n - 2)
        here = sign * light[i]
        step = np.where(sign * light[i + 1] > here, 1, np.where(sign * light[i - 1] > here, -1, 0))
        step[(idx <= 0) | (idx >= y_n - 1)] = 0
        if not step.any():
            break
        idx = idx + step
    amp = np.where(sign > 0, up, down)
    # only an interior local extremum is an R-peak: one at the record's edge is cut
    n = light.size
    ok = (idx > 0) & (idx < n - 1)
    ii = np.clip(idx, 1, n - 2)
    ok &= (sign * light[ii] >= sign * light[ii - 1]) & (sign * light[ii] >= sign * light[ii + 1])
    return idx[ok].astype(np.int64), amp[ok].astype(float), sign[ok]


def _dedupe(idx: np.ndarray, amp: np.ndarray, refractory: int):
    """Drop the smaller of two R-peaks closer than the refractory period; also
    return the kept positions in the input."""
    order = np.argsort(idx, kind="stable").tolist()
    at, height = idx.tolist(), amp.tolist()  # Python numbers: the loop runs over every beat
    keep = [order[0]]
    for o in order[1:]:
        if at[o] - at[keep[-1]] < refractory:
            if height[o] > height[keep[-1]]:
                keep[-1] = o
            continue
        keep.append(o)
    keep_arr = np.asarray(keep, dtype=np.int64)
    return idx[keep_arr].copy(), amp[keep_arr].copy(), keep_arr
