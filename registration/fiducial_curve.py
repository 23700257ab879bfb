"""The traced staples over the breath and their rigid fit onto the CT's at every phase.

A format-2 session holds the stylus on each chest staple over at least a
breath (``fiducial_trace.csv``); :func:`fiducial_curve` fits each staple's
position as a Fourier series in the respiration phase and registers the nine
onto the CT's staples at each swept phase (the chest-shape evidence of
:func:`registration.temporal.estimate_phase`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hrcore.geometry import kabsch
from registration.phase_estimate import TemporalError

__all__ = ["FiducialCurve", "fiducial_curve", "TRACE_HARMONICS"]

#: Fourier harmonics of each staple's position over the breath.
TRACE_HARMONICS = 2


def _fourier(phase, harmonics):
    cols = [np.ones_like(phase)]
    for k in range(1, harmonics + 1):
        cols += [np.cos(2 * np.pi * k * phase), np.sin(2 * np.pi * k * phase)]
    return np.stack(cols, axis=-1)


@dataclass(frozen=True, eq=False)
class FiducialCurve:
    """The traced staples as a function of phi_R, and their fit onto the CT's.

    Attributes
    ----------
    phases : (m,) float64, cycles
    positions_probe_mm : (m, 9, 3) float64
        Staples at each phase (source, i.e. probe, frame), documented order.
    T0_heart_from_probe : (m, 4, 4) float64
        Rigid fit of those staples onto the map's at each phase: ``T0(phi_R)``.
    residuals_mm : (m, 9) float64
        Distance of each fitted staple from its map position.
    sse_mm2 : (m,) float64
        Sum of squared residuals.
    trace_rms_mm : (9,) float64
        RMS of each staple's samples about its Fourier fit (tracker noise and
        hand tremor).
    n_samples : (9,) int64
        Samples with a defined respiration phase per staple.
    """

    phases: np.ndarray
    positions_probe_mm: np.ndarray
    T0_heart_from_probe: np.ndarray
    residuals_mm: np.ndarray
    sse_mm2: np.ndarray
    trace_rms_mm: np.ndarray
    n_samples: np.ndarray


def fiducial_curve(
    fiducial, stylus_source_mm, phase_r, target_mm, phases, *, order=None, harmonics: int = TRACE_HARMONICS,
    coverage_bins: int = 4,
) -> FiducialCurve:
    """Fit each staple's traced position over the breath and register it at every phase.

    Parameters
    ----------
    fiducial : (s,) int
        Staple 1..9 held at each sample, 0 in transit.
    stylus_source_mm : (s, 3) float, mm
        Stylus tip, source (probe) frame.
    phase_r : (s,) float, cycles
        Respiration phase of each sample (NaN where undefined).
    target_mm : (9, 3) float, mm
        The staples in the map frame, documented order.
    phases : (m,) float, cycles
        Phases at which to evaluate.
    order : (9,) int, optional
        ``target[order[i]]`` corresponds to staple ``i + 1`` (from the fiducial
        registration); the documented order by default.
    harmonics : int
        Fourier harmonics per staple.
    coverage_bins : int
        Every staple's samples must fall in each of this many phase bins.

    Returns
    -------
    FiducialCurve

    Raises
    ------
    TemporalError
        A staple held for too short a part of the breath.
    """
    fiducial = np.asarray(fiducial)
    tip = np.asarray(stylus_source_mm, dtype=float)
    phase_r = np.asarray(phase_r, dtype=float)
    target = np.asarray(target_mm, dtype=float)
    phases = np.asarray(phases, dtype=float)
    n_fid = target.shape[0]
    if order is not None:
        target = target[np.asarray(order)]
    basis = _fourier(phases, harmonics)
    curves = np.empty((phases.size, n_fid, 3))
    rms = np.empty(n_fid)
    counts = np.empty(n_fid, dtype=np.int64)
    for k in range(n_fid):
        sel = (fiducial == k + 1) & np.isfinite(phase_r)
        counts[k] = int(sel.sum())
        bins = np.unique(np.floor(phase_r[sel] * coverage_bins).astype(int))
        if bins.size < coverage_bins or counts[k] < 4 * (2 * harmonics + 1):
            raise TemporalError(
                f"fiducial trace: staple {k + 1} is held over {bins.size} of {coverage_bins} quarters of "
                "the breath; hold each staple for at least one whole breath"
            )
        A = _fourier(phase_r[sel], harmonics)
        coef, *_ = np.linalg.lstsq(A, tip[sel], rcond=None)
        rms[k] = float(np.sqrt(np.mean(np.sum((tip[sel] - A @ coef) ** 2, axis=1))))
        curves[:, k] = basis @ coef
    T = kabsch(curves, np.broadcast_to(target, curves.shape))
    fitted = np.einsum("mij,mkj->mki", T[:, :3, :3], curves) + T[:, None, :3, 3]
    res = np.linalg.norm(fitted - target, axis=2)
    return FiducialCurve(
        phases=phases.copy(),
        positions_probe_mm=curves,
        T0_heart_from_probe=T,
        residuals_mm=res,
        sse_mm2=np.sum(res**2, axis=1),
        trace_rms_mm=rms,
        n_samples=counts,
    )
