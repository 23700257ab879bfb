"""Phase of a quasi-periodic process from the times of its events.

A cardiac phase is ``(t - R_k) / (R_{k+1} - R_k)`` for ``R_k <= t < R_{k+1}``
(R-peaks); a respiration phase is the same between starts of expiration (Wood
et al. 2018, section 2.2.4).  Outside the covered events the phase is undefined
and returned as NaN: it is never extrapolated.  The events are found in signals
smoothed by :func:`zero_phase_filter`, whose designs are kept per rate.
"""

from __future__ import annotations

import functools

import numpy as np

from hrcore.errors import HeartregError

__all__ = ["SignalError", "phase_from_events", "zero_phase_filter"]


class SignalError(HeartregError, ValueError):
    """A physiological signal or event list that cannot give what was asked."""


def _as_events(events_s, *, name: str, what: str) -> np.ndarray:
    """Check and return a strictly increasing (m,) float64 array of event times."""
    if events_s is None:
        raise SignalError(f"{name} is None: give the {what} times in seconds")
    events = np.asarray(getattr(events_s, "times_s", events_s), dtype=float)
    if events.ndim != 1:
        raise SignalError(f"{name} must have shape (m,), got {events.shape}")
    if events.size < 2:
        raise SignalError(
            f"{name} has {events.size} {what} time(s); a phase needs at least two "
            f"consecutive {what}s: record a longer signal"
        )
    if not np.all(np.isfinite(events)):
        raise SignalError(f"{name} contains NaN or infinite times: remove them")
    if np.any(np.diff(events) <= 0):
        raise SignalError(f"{name} must be strictly increasing: sort it and drop duplicates")
    return events


def phase_from_events(time_s, events_s, *, name: str = "events_s", what: str = "event") -> np.ndarray:
    """Phase in [0, 1) of each time between consecutive events; NaN outside.

    Parameters
    ----------
    time_s : float or array_like of float, s
        Query times (any shape).  NaN times give NaN.
    events_s : (m,) array_like of float, s
        Strictly increasing event times, m >= 2 (or an object with a ``times_s``
        attribute).
    name, what : str
        Argument name and event noun used in error messages.

    Returns
    -------
    float64 array of the shape of ``time_s``
        ``(t - e_k) / (e_{k+1} - e_k)`` for ``e_k <= t < e_{k+1}``; NaN for
        ``t < e_0``, ``t >= e_{m-1}`` or NaN ``t``.

    Raises
    ------
    SignalError
        If ``events_s`` has fewer than two times, is not 1-D, not finite or not
        strictly increasing.
    """
    events = _as_events(events_s, name=name, what=what)
    time = np.asarray(time_s, dtype=float)
    k = np.searchsorted(events, time, side="right") - 1
    ok = (k >= 0) & (k < events.size - 1) & np.isfinite(time)
    phase = np.full(time.shape, np.nan)
    kk = k[ok]
    lo = events[kk]
    phase[ok] = (time[ok] - lo) / (events[kk + 1] - lo)
    # Rounding can give exactly 1.0 just below the next event: keep [0, 1).
    phase[ok] = np.minimum(phase[ok], np.nextafter(1.0, 0.0))
    return phase


@functools.lru_cache(maxsize=64)
def _butter_sos(cutoff_hz: float | tuple[float, float], btype: str, rate_hz: float) -> np.ndarray:
    # scipy.signal (~0.6 s to import) on first use: ``heartreg model`` needs the phases, not the
    # filters; the batch's workers import it at start-up (heartreg.batch.cluster.PRELOAD)
    from scipy import signal

    return signal.butter(2, cutoff_hz, btype=btype, fs=rate_hz, output="sos")


def zero_phase_filter(x: np.ndarray, cutoff_hz, btype: str, rate_hz: float) -> np.ndarray:
    """``x`` through a 2nd-order Butterworth filter forwards and backwards (zero phase).

    The filter's design depends on the cut-off and the rate only, and every
    point of a session has the same rate: it is designed once and kept.

    Parameters
    ----------
    x : (n,) float64
    cutoff_hz : float or (float, float), Hz
        Cut-off, or the band for ``btype="bandpass"``.
    btype : {"lowpass", "bandpass"}
    rate_hz : float, Hz

    Returns
    -------
    (n,) float64
    """
    band = tuple(float(f) for f in cutoff_hz) if np.ndim(cutoff_hz) else float(cutoff_hz)
    # a copy: the cached design stays as designed (scipy's filter wants a writeable array)
    from scipy import signal

    return signal.sosfiltfilt(_butter_sos(band, btype, float(rate_hz)).copy(), x)
