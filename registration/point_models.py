"""Phases and motion models of every point of a session (Wood et al. 2018, 2.2.4-2.2.5).

For every attachment point:

1. R-peaks are detected in the point's ECG (:func:`imaging.ecg.detect_r_peaks`)
   and the cardiac phase of each sample follows from them; the starts of
   expiration are found in the ventilator flows
   (:func:`imaging.respiration.expiration_onsets`) and give the respiration
   phase.  Samples outside the covered events have no phase (NaN): they are
   dropped and counted, never extrapolated.
2. A point with fewer than ``min_beats`` complete heartbeats or ``min_breaths``
   complete breaths, or whose signals give no events at all, is *excluded* and
   the reason is recorded (never silently).
3. Tracker glitches (:func:`registration.plausibility.outlier_samples`) are
   left out, and the AM dual Fourier model (paper eq. 6-8) is fitted by linear
   least squares; phases that leave part of the cycle empty are recorded as a
   note.
"""

from __future__ import annotations

import warnings

import numpy as np

from hrcore.geometry import frozen
from imaging.ecg import cardiac_phase, detect_r_peaks
from imaging.events import SignalError
from imaging.respiration import expiration_onsets, respiration_phase
from registration.motion_model import CoverageWarning, Harmonics, MotionModel, MotionModelError, fit_motion_model
from registration.plausibility import outlier_samples
from registration.result import PointFit
from registration.session import PointRecord, Session

__all__ = ["fit_point_models", "on_sample_clock", "point_phases", "respiration_of"]

#: An R-R interval that holds a gap in the samples and lasts this many times the median R-R lost its beat in
#: the gap (a dropout over the R): its samples get no cardiac phase (NaN, left out of the fit and counted).
LOST_BEAT_RR_RATIO = 1.5


def fit_point_models(
    session: Session,
    harmonics: Harmonics,
    *,
    min_beats: int,
    min_breaths: int,
    coverage_bins: int,
    progress: bool = False,
) -> tuple[list[MotionModel], list[PointFit], list[tuple[int, str]], list[str]]:
    """The motion model of every point of ``session`` that can have one.

    Parameters
    ----------
    session : Session
    harmonics : Harmonics
    min_beats, min_breaths : int
        Fewer complete heartbeats or breaths exclude a point.
    coverage_bins : int
        Phase bins checked for samples (:func:`registration.motion_model.fit_motion_model`).
    progress : bool
        A progress bar on stderr over the points.

    Returns
    -------
    models : list of MotionModel
    fits : list of PointFit
        One per model, in the session's order.
    exclusions : list of (int, str)
        The session's own exclusions, then each point left out here with the reason.
    notes : list of str
        What the fits noted (outlier samples, uncovered phases).
    """
    exclusions = list(session.exclusions)
    models: list[MotionModel] = []
    fits: list[PointFit] = []
    notes: list[str] = []
    bar = _progress(progress, len(session.points), "motion models")
    try:
        for record in session.points:
            try:
                m, f = _fit_point(record, harmonics, min_beats, min_breaths, coverage_bins)
            except _Excluded as exc:
                exclusions.append((record.point_id, str(exc)))
            else:
                models.append(m)
                fits.append(f)
                notes.extend(f.notes)
            if bar is not None:
                bar.update()
    finally:
        if bar is not None:
            bar.close()
    return models, fits, exclusions, notes


def point_phases(record: PointRecord):
    """Cardiac and respiration phase of every sample of one record.

    Parameters
    ----------
    record : PointRecord

    Returns
    -------
    phase_c, phase_r : (n,) float64, cycles
        NaN where the phase is undefined, and (cardiac) in an R-R interval
        whose beat was lost in a gap of the samples (:data:`LOST_BEAT_RR_RATIO`).
    r_peaks_s, onsets_s : (m,) float64, s
        Detected R-peaks and starts of expiration.

    Raises
    ------
    imaging.events.SignalError
        The ECG or the flows give fewer than two events.
    """
    t = record.time_s
    peaks = on_sample_clock(detect_r_peaks(record.ecg_mv, record.rate_hz).times_s, t, record.rate_hz)
    phase_r, onsets = respiration_of(record)
    phase_c = cardiac_phase(t, peaks)
    # a beat in a gap is lost: the R-R interval around it spans two beats and its phases run at half speed
    gaps = t[:-1][np.diff(t) > 1.5 / record.rate_hz]
    if gaps.size and peaks.size >= 3:
        rr = np.diff(peaks)
        holds_gap = np.searchsorted(gaps, peaks[1:]) > np.searchsorted(gaps, peaks[:-1])
        for k in np.flatnonzero(holds_gap & (rr > LOST_BEAT_RR_RATIO * np.median(rr))):
            phase_c[(t >= peaks[k]) & (t < peaks[k + 1])] = np.nan
    return phase_c, phase_r, peaks, onsets


def respiration_of(record) -> tuple[np.ndarray, np.ndarray]:
    """Respiration phase per sample and starts of expiration (s) of a record with ``time_s``, ``rate_hz``
    and airflows (a point's :class:`PointRecord`, the traced staples' ``FiducialTrace``), on its own clock
    (:func:`on_sample_clock`: dropped samples leave gaps)."""
    onsets = on_sample_clock(expiration_onsets(rate_hz=record.rate_hz, flow_exp_lpm=record.flow_exp_lpm,
                                               flow_insp_lpm=record.flow_insp_lpm), record.time_s, record.rate_hz)
    return respiration_phase(record.time_s, onsets), onsets


def on_sample_clock(events_s, time_s, rate_hz: float) -> np.ndarray:
    """Event times found with sample ``i`` at ``i / rate_hz`` put on the samples' own clock ``time_s``.

    The detectors count samples.  A record may miss some (poses its PLUS sequence marks invalid are
    dropped with their ECG and flow; a logger's pauses up to ``registration.session.MAX_GAP_S``):
    ``time_s[0] + i / rate_hz`` then put every event after a gap early by the gap (twelve 80 ms
    dropouts in a minute of MIT-BIH 100 at 100 Hz: median cardiac phase error 0.29 cycle).  Each
    event goes to the time of its (fractional) sample, interpolated between the two it lies between.
    """
    t = np.asarray(time_s, dtype=float)
    return np.interp(np.asarray(events_s, dtype=float) * float(rate_hz), np.arange(t.size), t)


def _fit_point(record, harmonics, min_beats, min_breaths, coverage_bins):
    """(MotionModel, PointFit) or raise _Excluded(reason)."""
    try:
        phase_c, phase_r, peaks, onsets = point_phases(record)
    except SignalError as exc:
        raise _Excluded(str(exc)) from None
    n_beats, n_breaths = peaks.size - 1, onsets.size - 1
    if n_beats < min_beats:
        raise _Excluded(
            f"{n_beats} complete heartbeat(s) detected, fewer than "
            f"min_beats = {min_beats}; record longer or check the ECG lead"
        )
    if n_breaths < min_breaths:
        raise _Excluded(
            f"{n_breaths} complete breath(s) detected, fewer than "
            f"min_breaths = {min_breaths}; record at least {min_breaths + 1} starts of expiration"
        )
    notes = []
    outliers = outlier_samples(record.T_probe_from_robot[:, :3, 3], record.rate_hz)
    if outliers.any():  # tracker glitches: a NaN phase leaves the sample out of the fit
        phase_c = np.where(outliers, np.nan, phase_c)
        notes.append(
            f"point {record.point_id}: {int(outliers.sum())} outlier sample(s) (robot position far from "
            f"its running median, first at t = {float(record.time_s[outliers][0]):.2f} s) left out of its motion model"
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CoverageWarning)
        try:
            model = fit_motion_model(
                phase_c, phase_r, record.T_probe_from_robot,
                harmonics=harmonics, coverage_bins=coverage_bins,
            )
        except MotionModelError as exc:
            raise _Excluded(str(exc)) from None
    for w in caught:
        if issubclass(w.category, CoverageWarning):
            notes.append(f"point {record.point_id}: {w.message}")
    fit = PointFit(
        point_id=record.point_id,
        surface_point=record.surface_point,
        n_samples=record.n_samples,
        n_used=model.n_samples,
        n_nan_phase=model.n_dropped,
        n_beats=int(n_beats),
        n_breaths=int(n_breaths),
        heart_rate_hz=float(n_beats / (peaks[-1] - peaks[0])),
        resp_rate_hz=float(n_breaths / (onsets[-1] - onsets[0])),
        residual_rms_mm=frozen(model.residual_rms_mm),
        residual_rms_3d_mm=float(model.residual_rms_3d_mm),
        residual_rms_deg=float(model.residual_rms_deg),
        condition_number=float(model.condition_number),
        notes=tuple(notes),
        n_outlier_samples=int(outliers.sum()),
    )
    return model, fit


class _Excluded(Exception):
    """Internal: a point left out, with the reason as message."""


def _progress(enabled: bool, total: int, desc: str):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="point", leave=False)
