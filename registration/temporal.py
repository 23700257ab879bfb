"""The image's respiration phase phi_R* from all the evidence, with an interval.

The paper (Wood et al. 2018, section 2.3.1, eq. 10) takes phi_R* as the phase
whose ICP registration lies closest, in translation, to the fiducial
registration ``T0``.  That uses one number per phase and trusts ``T0``, whose
error (the skin moved between CT and surgery, ~10 mm) can run along the heart's
respiratory path and pull the answer away (:func:`paper_phase`).

:func:`estimate_phase` (the default of ``heartreg register``) uses the evidence
eq. 10 leaves out, each term a sum of squares scaled by its own noise:

- **the chest's shape** (format-2 sessions): the stylus held on each staple
  over a breath gives the staples as a function of phi_R
  (:func:`fiducial_curve`, a 2-harmonic Fourier fit per staple).  The chest
  wall does not breathe rigidly, so the staples' shape matches the CT's only at
  the CT's phase: the residual of the rigid fit of the traced staples onto the
  CT staples at phi_R, ``S_F(phi_R)``.  A rigid skin shift between CT and
  surgery, the error that misleads eq. 10, does not change this residual.
- **the heart's shape**: respiration deforms the heart too (the diaphragm
  stretches it), so the predicted points fit the map best at the map's phase;
  the per-point squared distances after ICP at each phase, ``S_H(phi_R)``.
- **a stated breath-hold phase** (optional): ``((phi_R - phi_u) / sd)^2``.

``J(phi_R) = S_H / s_H^2 + S_F / s_F^2 (+ prior)``, with ``s^2`` each term's
minimum over phase divided by its degrees of freedom (n - 6 and 3 * 9 - 6): a
profile likelihood under Gaussian residuals; ``phi_R* = argmin J``.

Interval
--------
The interval is a bootstrap over the evidence: the attachment points and the
staples are resampled with replacement (B = 500), ``J`` re-summed and its
argmin taken; the 5th and 95th percentiles of the resampled phases about
phi_R* (circularly), widened by half a sweep step (the grid's resolution), give
the 90 % interval.  Resampling the points, rather than trusting the Gaussian
curvature of ``J``, keeps the points' own systematic errors (mesh, motion
model), which differ from point to point, in the spread.  The per-phase ICP
solutions are held fixed (re-running ICP per resample would cost B sweeps).
When the interval spans more than :data:`UNDECIDED_WIDTH` of a cycle the data
cannot decide phi_R*, and the estimate says so.

The final transform's uncertainty is that of phi_R* carried through the sweep:
the mean displacement of the map's vertices between ``T(phi_b)`` and
``T(phi_R*)`` over the resamples (90th percentile), and the rotation between
them; the ICP's own noise at a fixed phase is far smaller (see ``icp``'s
Hessian report).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from hrcore.errors import HeartregError
from hrcore.geometry import kabsch

__all__ = [
    "TemporalEstimator",
    "TemporalError",
    "FiducialCurve",
    "TemporalEstimate",
    "fiducial_curve",
    "estimate_phase",
    "paper_phase",
]

#: an interval wider than this (cycles) means the data cannot decide phi_R*.
UNDECIDED_WIDTH = 0.3
#: resamples of the bootstrap, and the interval's confidence.
N_BOOTSTRAP = 500
CONFIDENCE = 0.9
#: Fourier harmonics of each staple's position over the breath.
TRACE_HARMONICS = 2


class TemporalEstimator(str, enum.Enum):
    """How phi_R* is chosen."""

    #: chest and heart shape (and a stated breath-hold phase): :func:`estimate_phase`.
    SHAPE = "shape"
    #: the paper's empirical metric, eq. 10: :func:`paper_phase`.
    PAPER = "eq10"


class TemporalError(HeartregError, ValueError):
    """Evidence that cannot give a respiration phase (a trace that misses phases, ...)."""


def _wrap(d):
    return (np.asarray(d, dtype=float) + 0.5) % 1.0 - 0.5


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
    positions_source_mm : (m, 9, 3) float64
        Staples at each phase (source, i.e. probe, frame), documented order.
    T_map_from_source : (m, 4, 4) float64
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
    positions_source_mm: np.ndarray
    T_map_from_source: np.ndarray
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
        positions_source_mm=curves,
        T_map_from_source=T,
        residuals_mm=res,
        sse_mm2=np.sum(res**2, axis=1),
        trace_rms_mm=rms,
        n_samples=counts,
    )


@dataclass(frozen=True, eq=False)
class TemporalEstimate:
    """phi_R* with its interval, and how it was found.

    Attributes
    ----------
    method : str
        ``"shape"`` or ``"eq10"`` (:class:`TemporalEstimator`).
    evidence : tuple of str
        The terms used: ``"heart"``, ``"fiducial_trace"``, ``"breath_hold"``,
        ``"fiducials"`` (eq. 10's T0).
    phase_r : float, cycles
    index : int
        Its index in the sweep.
    interval : (2,) float64, cycles
        90 % interval ``(low, high)`` as phases in [0, 1); ``low > high`` when it
        wraps through 0.
    interval_offsets : (2,) float64, cycles
        The same as offsets from ``phase_r`` (``low <= 0 <= high``).
    confidence : float
    decided : bool
        False when the interval is wider than :data:`UNDECIDED_WIDTH`.
    bootstrap_phases : (B,) float64
        phi_R* of every resample.
    cost : (m,) float64
        ``J - min J`` over the sweep (unitless, chi-square-like); for ``eq10``
        the translation distance from T0 minus its minimum (mm).
    cost_heart, cost_fiducial, cost_prior : (m,) float64
        Its terms (zeros where a term is not used), each minus its own minimum.
    transform_mm, transform_deg : float
        90th percentile over the resamples of the mean map-vertex displacement
        (mm) and of the rotation (deg) between ``T(phi_b)`` and ``T(phi_R*)``.
    """

    method: str
    evidence: tuple[str, ...]
    phase_r: float
    index: int
    interval: np.ndarray
    interval_offsets: np.ndarray
    confidence: float
    decided: bool
    bootstrap_phases: np.ndarray
    cost: np.ndarray
    cost_heart: np.ndarray
    cost_fiducial: np.ndarray
    cost_prior: np.ndarray
    transform_mm: float
    transform_deg: float

    @property
    def width(self) -> float:
        """Width of the interval, cycles."""
        return float(self.interval_offsets[1] - self.interval_offsets[0])

    def contains(self, phase: float) -> bool:
        """True when ``phase`` lies in the interval (circularly)."""
        d = float(_wrap(phase - self.phase_r))
        return bool(self.interval_offsets[0] - 1e-9 <= d <= self.interval_offsets[1] + 1e-9)

    def summary(self) -> str:
        """One line: phase, interval, and whether the data decide."""
        lo, hi = self.interval
        text = (f"phi_R* {self.phase_r:.2f} ({self.method}), {100 * self.confidence:.0f} % interval "
                f"[{lo:.2f}, {hi:.2f}]; final T within {self.transform_mm:.1f} mm, {self.transform_deg:.1f} deg")
        if not self.decided:
            text += (f"; UNDECIDED: the data cannot decide phi_R* (interval {self.width:.2f} of a cycle "
                     "wide): trace the staples over a breath or state the breath-hold phase")
        return text

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "evidence": list(self.evidence),
            "phase": self.phase_r,
            "interval": [float(x) for x in self.interval],
            "interval_offsets": [float(x) for x in self.interval_offsets],
            "confidence": self.confidence,
            "decided": self.decided,
            "n_bootstrap": int(self.bootstrap_phases.size),
            "transform_90_mm": self.transform_mm,
            "transform_90_deg": self.transform_deg,
        }


def _interval(phases, best, boot, confidence, step):
    offsets = _wrap(boot - phases[best])
    tail = 100 * (1 - confidence) / 2
    lo, hi = np.percentile(offsets, [tail, 100 - tail])
    lo, hi = min(lo, 0.0) - step / 2, max(hi, 0.0) + step / 2
    if hi - lo >= 1.0:
        lo, hi = -0.5, 0.5
    return np.array([lo, hi])


def _transform_spread(Ts, best, boot_idx, vertices_mm):
    """90th percentiles of mean vertex displacement (mm) and rotation (deg)."""
    v = np.asarray(vertices_mm, dtype=float)
    if v.shape[0] > 2000:
        v = v[:: int(np.ceil(v.shape[0] / 2000))]
    idx, counts = np.unique(boot_idx, return_counts=True)
    dT = Ts[idx] @ np.linalg.inv(Ts[best])
    moved = np.einsum("aij,vj->avi", dT[:, :3, :3], v) + dT[:, None, :3, 3]
    disp = np.linalg.norm(moved - v, axis=2).mean(axis=1)
    cos = np.clip((np.trace(dT[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    return (float(np.percentile(np.repeat(disp, counts), 90)),
            float(np.percentile(np.repeat(angle, counts), 90)))


def estimate_phase(
    phases,
    distances_mm,
    T_map_from_source,
    vertices_mm,
    *,
    fiducials: FiducialCurve | None = None,
    breath_hold_phase: float | None = None,
    breath_hold_sd: float = 0.05,
    n_bootstrap: int = N_BOOTSTRAP,
    confidence: float = CONFIDENCE,
    seed: int = 0,
) -> TemporalEstimate:
    """phi_R* from the heart's and the chest's shape (module docstring), with its interval.

    Parameters
    ----------
    phases : (m,) float, cycles
        The respiration sweep.
    distances_mm : (m, n) float, mm
        Per-point distance to the map after ICP at each phase.
    T_map_from_source : (m, 4, 4) float
        ICP registration at each phase.
    vertices_mm : (V, 3) float, mm
        The map's vertices (for the transform's uncertainty).
    fiducials : FiducialCurve, optional
        The traced staples (format-2 sessions).
    breath_hold_phase : float, optional
        A breath-hold phase stated by the user, with standard deviation
        ``breath_hold_sd`` (cycles).
    n_bootstrap : int
    confidence : float
    seed : int
        Seed of the resampling (the same inputs give the same interval).

    Returns
    -------
    TemporalEstimate
    """
    phases = np.asarray(phases, dtype=float)
    d2 = np.asarray(distances_mm, dtype=float) ** 2
    m, n = d2.shape
    if phases.shape != (m,):
        raise ValueError(f"phases must have shape ({m},), got {phases.shape}")
    if n < 7:
        raise TemporalError(
            f"the shape estimator of phi_R* needs at least 7 registered points, got {n}: "
            "record more points, or choose the paper's eq. 10 (estimator='eq10', --estimator eq10)"
        )
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if not breath_hold_sd > 0:
        raise ValueError(f"breath_hold_sd must be positive, got {breath_hold_sd}")
    # the sweep's ends are the same phase: keep one
    same = np.isclose(_wrap(phases[-1] - phases[0]), 0.0) and m > 1
    usable = np.arange(m - 1 if same else m)
    step = float(np.median(np.diff(phases))) if m > 1 else 0.0
    evidence = ["heart"]
    e_h = d2[usable] / (d2[usable].sum(axis=1).min() / (n - 6))  # (m', n)
    e_f = np.zeros((usable.size, 0))
    if fiducials is not None:
        r2 = fiducials.residuals_mm[usable] ** 2
        k = r2.shape[1]
        e_f = r2 / (r2.sum(axis=1).min() / (3 * k - 6))
        evidence.append("fiducial_trace")
    prior = np.zeros(usable.size)
    if breath_hold_phase is not None:
        if not 0.0 <= breath_hold_phase <= 1.0:
            raise ValueError(f"breath_hold_phase must be a phase in [0, 1], got {breath_hold_phase}")
        prior = (_wrap(phases[usable] - breath_hold_phase) / breath_hold_sd) ** 2
        evidence.append("breath_hold")
    J_h, J_f = e_h.sum(axis=1), e_f.sum(axis=1)
    J = J_h + J_f + prior
    best = int(np.argmin(J))

    rng = np.random.default_rng([int(seed), 0x7E3])
    W_h = rng.multinomial(n, np.full(n, 1.0 / n), size=n_bootstrap).astype(float)
    J_b = W_h @ e_h.T + prior
    if e_f.shape[1]:
        k = e_f.shape[1]
        W_f = rng.multinomial(k, np.full(k, 1.0 / k), size=n_bootstrap).astype(float)
        J_b = J_b + W_f @ e_f.T
    boot_idx = usable[np.argmin(J_b, axis=1)]
    offsets = _interval(phases, usable[best], phases[boot_idx], confidence, step)
    t_mm, t_deg = _transform_spread(np.asarray(T_map_from_source), usable[best], boot_idx, vertices_mm)

    def full(x):
        out = np.zeros(m)
        out[usable] = x - x.min() if x.size else 0.0
        if same:
            out[-1] = out[0]
        return out

    phase = float(phases[usable[best]] % 1.0)
    return TemporalEstimate(
        method=TemporalEstimator.SHAPE.value,
        evidence=tuple(evidence),
        phase_r=phase,
        index=int(usable[best]),
        interval=np.mod(phase + offsets, 1.0),
        interval_offsets=offsets,
        confidence=float(confidence),
        decided=bool(offsets[1] - offsets[0] <= UNDECIDED_WIDTH),
        bootstrap_phases=np.mod(phases[boot_idx], 1.0),
        cost=full(J),
        cost_heart=full(J_h),
        cost_fiducial=full(J_f) if e_f.shape[1] else np.zeros(m),
        cost_prior=full(prior) if breath_hold_phase is not None else np.zeros(m),
        transform_mm=t_mm,
        transform_deg=t_deg,
    )


def paper_phase(
    phases,
    T_map_from_source,
    fiducials_source_mm,
    fiducials_map_mm,
    pivot_mm,
    vertices_mm,
    *,
    order=None,
    n_bootstrap: int = N_BOOTSTRAP,
    confidence: float = CONFIDENCE,
    seed: int = 0,
) -> TemporalEstimate:
    """The paper's eq. 10 with a bootstrap interval over the touched staples.

    phi_R* is the phase whose registration lies closest, in translation at
    ``pivot_mm``, to ``T0`` (the rigid fit of the touched staples); the interval
    resamples the staples, refits ``T0`` and takes the argmin again.  It carries
    the touch noise only: a skin shift between CT and surgery moves ``T0``
    without showing in the resamples, which is why eq. 10 can miss with a narrow
    interval.

    Parameters
    ----------
    phases : (m,) float
    T_map_from_source : (m, 4, 4) float
        ICP registration at each phase.
    fiducials_source_mm, fiducials_map_mm : (k, 3) float, mm
        Touched staples (source frame) and the map's, corresponding rows (after
        ``order``).
    pivot_mm : (3,) float, mm
        Map-frame pivot of the translation distance.
    vertices_mm : (V, 3) float, mm
    order : (k,) int, optional
        ``map[order[i]]`` corresponds to ``source[i]``.

    Returns
    -------
    TemporalEstimate
    """
    phases = np.asarray(phases, dtype=float)
    Ts = np.asarray(T_map_from_source, dtype=float)
    src = np.asarray(fiducials_source_mm, dtype=float)
    dst = np.asarray(fiducials_map_mm, dtype=float)
    if order is not None:
        dst = dst[np.asarray(order)]
    pivot = np.asarray(pivot_mm, dtype=float)
    m = phases.size
    step = float(np.median(np.diff(phases))) if m > 1 else 0.0

    def distances(T0s):  # (b, 4, 4) -> (b, m)
        s = np.einsum("bij,bj->bi", np.linalg.inv(T0s)[:, :3, :3], pivot - T0s[:, :3, 3])
        at = np.einsum("mij,bj->bmi", Ts[:, :3, :3], s) + Ts[None, :, :3, 3]
        return np.linalg.norm(at - pivot, axis=2)

    T0 = kabsch(src[None], dst[None])
    dist = distances(T0)[0]
    best = int(np.argmin(dist))
    rng = np.random.default_rng([int(seed), 0xE910])
    k = src.shape[0]
    idx = rng.integers(0, k, size=(n_bootstrap, k))
    boot_idx = np.argmin(distances(kabsch(src[idx], dst[idx])), axis=1)
    offsets = _interval(phases, best, phases[boot_idx], confidence, step)
    t_mm, t_deg = _transform_spread(Ts, best, boot_idx, vertices_mm)
    phase = float(phases[best] % 1.0)
    zeros = np.zeros(m)
    return TemporalEstimate(
        method=TemporalEstimator.PAPER.value,
        evidence=("fiducials",),
        phase_r=phase,
        index=best,
        interval=np.mod(phase + offsets, 1.0),
        interval_offsets=offsets,
        confidence=float(confidence),
        decided=bool(offsets[1] - offsets[0] <= UNDECIDED_WIDTH),
        bootstrap_phases=np.mod(phases[boot_idx], 1.0),
        cost=dist - dist.min(),
        cost_heart=zeros,
        cost_fiducial=zeros,
        cost_prior=zeros,
        transform_mm=t_mm,
        transform_deg=t_deg,
    )
