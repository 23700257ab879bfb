"""Physiological clocks and signals of the phantom: R-peaks, breaths, ECG, airflow.

Times are seconds on one clock (the phantom uses seconds after midnight, the
clock of DICOM *AcquisitionTime*).  A cardiac phase is
``(t - R_k) / (R_{k+1} - R_k)``; a respiration phase is the same between starts
of expiration (paper section 2.2.4).  Outside the covered events the phase is
NaN: it is never extrapolated.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "r_peak_times",
    "expiration_onsets",
    "phase_from_events",
    "synthesize_ecg",
    "synthesize_airflow",
]


def r_peak_times(
    rng: np.random.Generator,
    *,
    start_s: float,
    end_s: float,
    heart_rate_hz: float,
    hrv_fraction: float,
    ectopic_probability: float,
    resp_rate_hz: float,
) -> np.ndarray:
    """R-peak times covering [start_s, end_s] with one beat before and after.

    RR intervals vary with respiration (sinus arrhythmia, ``hrv_fraction / 2``),
    randomly (``hrv_fraction / 2`` standard deviation), and an ectopic beat
    (probability ``ectopic_probability`` per beat) comes 28 % early and is
    followed by a compensatory pause.

    Returns
    -------
    (n,) float64, s, strictly increasing.
    """
    rr0 = 1.0 / heart_rate_hz
    t = start_s - rng.uniform(0.3, 0.9) * rr0
    peaks = [t]
    compensate = None
    while t < end_s + rr0:
        if compensate is not None:
            rr, compensate = compensate, None
        else:
            rr = rr0 * (
                1.0
                + 0.5 * hrv_fraction * np.sin(2 * np.pi * resp_rate_hz * t)
                + 0.5 * hrv_fraction * rng.standard_normal()
            )
            rr = float(np.clip(rr, 0.7 * rr0, 1.3 * rr0))
            if rng.random() < ectopic_probability:
                early = 0.72 * rr
                compensate, rr = 2.0 * rr - early, early
        t += rr
        peaks.append(t)
    return np.asarray(peaks)


def expiration_onsets(
    rng: np.random.Generator, *, start_s: float, end_s: float, resp_rate_hz: float
) -> np.ndarray:
    """Starts of expiration of a ventilator breathing at ``resp_rate_hz`` (1 % jitter),
    covering [start_s, end_s] with one onset before and after."""
    period = 1.0 / resp_rate_hz
    t = start_s - rng.uniform(0.1, 0.9) * period
    onsets = [t]
    while t < end_s + period:
        t += period * (1.0 + 0.01 * rng.standard_normal())
        onsets.append(t)
    return np.asarray(onsets)


def phase_from_events(time_s, events_s) -> np.ndarray:
    """Phase in [0, 1) of each time between consecutive events; NaN outside."""
    time_s = np.asarray(time_s, dtype=float)
    events_s = np.asarray(events_s, dtype=float)
    k = np.searchsorted(events_s, time_s, side="right") - 1
    ok = (k >= 0) & (k < len(events_s) - 1)
    phase = np.full(time_s.shape, np.nan)
    kk = k[ok]
    phase[ok] = (time_s[ok] - events_s[kk]) / (events_s[kk + 1] - events_s[kk])
    return phase


# PQRST waves: (offset from R in s, amplitude in mV, width sigma in s).  Q and S
# are mirror images about R so the R-wave maximum is exactly at the R time.
_WAVES = (
    (-0.165, 0.12, 0.022),  # P
    (-0.028, -0.14, 0.009),  # Q
    (0.0, 1.25, 0.011),  # R
    (0.028, -0.14, 0.009),  # S
)
_T_WAVE = (0.30, 0.32, 0.045)  # offset scales with sqrt(RR) (Bazett)


def synthesize_ecg(
    rng: np.random.Generator,
    r_peaks_s: np.ndarray,
    *,
    start_s: float,
    duration_s: float,
    rate_hz: float,
    noise_mv: float,
    wander_mv: float,
    resp_rate_hz: float = 0.2,
) -> np.ndarray:
    """A lead-II-like ECG (mV) sampled at ``rate_hz`` from ``start_s``.

    Sum of Gaussian P, Q, R, S, T waves per beat, baseline wander (respiratory and
    slow drift), white noise and mains interference.  The clean signal's maxima
    are at the R-peak times.
    """
    n = int(round(duration_s * rate_hz))
    t = start_s + np.arange(n) / rate_hz
    ecg = np.zeros(n)
    r_peaks_s = np.asarray(r_peaks_s, dtype=float)
    rr = np.diff(r_peaks_s, append=r_peaks_s[-1] + np.median(np.diff(r_peaks_s)))
    # each beat's window [r - 0.4, r + 0.8) s; the session's beats outside the samples add nothing
    lo_all, hi_all = np.searchsorted(t, r_peaks_s - 0.4), np.searchsorted(t, r_peaks_s + 0.8)
    for k in np.flatnonzero(hi_all > lo_all):
        r, interval, lo, hi = r_peaks_s[k], rr[k], lo_all[k], hi_all[k]
        dt = t[lo:hi] - r
        for offset, amp, sigma in _WAVES:
            ecg[lo:hi] += amp * np.exp(-0.5 * ((dt - offset) / sigma) ** 2)
        offset, amp, sigma = _T_WAVE
        ecg[lo:hi] += amp * np.exp(-0.5 * ((dt - offset * np.sqrt(interval)) / sigma) ** 2)
    ph = rng.uniform(0, 2 * np.pi, 3)
    ecg += wander_mv * (
        np.sin(2 * np.pi * resp_rate_hz * t + ph[0]) + 0.6 * np.sin(2 * np.pi * 0.05 * t + ph[1])
    )
    ecg += 0.02 * np.sin(2 * np.pi * 50.0 * t + ph[2])
    ecg += noise_mv * rng.standard_normal(n)
    return ecg


def synthesize_airflow(
    rng: np.random.Generator,
    onsets_s: np.ndarray,
    r_peaks_s: np.ndarray,
    *,
    start_s: float,
    duration_s: float,
    rate_hz: float,
    noise_lpm: float,
    peak_flow_lpm: float = 30.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Inspiratory and expiratory airflow (L/min) of a volume-controlled ventilator.

    I:E = 1:2: expiration starts at each onset with a passive exponential decay;
    inspiration fills the last third of each breath with a decelerating flow.
    Cardiogenic oscillations (1 L/min at the heart rate) ride on both.

    Returns
    -------
    inspiratory, expiratory : (n,) float64, L/min, non-negative
    """
    n = int(round(duration_s * rate_hz))
    t = start_s + np.arange(n) / rate_hz
    k = np.searchsorted(onsets_s, t, side="right") - 1
    k = np.clip(k, 0, len(onsets_s) - 2)
    period = onsets_s[k + 1] - onsets_s[k]
    since = t - onsets_s[k]
    frac = since / period
    exp_flow = np.where(frac < 2 / 3, peak_flow_lpm * np.exp(-since / (0.12 * period)), 0.0)
    x = (frac - 2 / 3) * 3
    insp_flow = np.where(frac >= 2 / 3, 0.6 * peak_flow_lpm * (1.2 - 0.6 * x), 0.0)
    cardio_phase = np.nan_to_num(phase_from_events(t, r_peaks_s))
    ripple = 1.0 * np.sin(2 * np.pi * cardio_phase)
    insp = np.clip(insp_flow + np.where(insp_flow > 0, ripple, 0) + noise_lpm * rng.standard_normal(n), 0, None)
    expi = np.clip(exp_flow + 0.5 * ripple + noise_lpm * rng.standard_normal(n), 0, None)
    return insp, expi
