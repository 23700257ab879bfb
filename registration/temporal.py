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
  The map's own error is the same at every phase and carries no phase
  information: given the map's curvature at the points
  (``curvature_per_mm``, :mod:`registration.mesh_bias`), the signed
  distances first lose, at each phase, their least-squares fit by
  ``a + k H`` (a threshold's uniform offset, the CT blur's ``sigma^2 H``).
  Optional: ``register`` does not pass it yet (on the phantom's grid it
  helped phi_R* and hurt the final transform and the interval's coverage,
  docs/reproduction.md).
- **a stated breath-hold phase** (optional): ``((phi_R - phi_u) / sd)^2``.

``J(phi_R) = S_H / s_H^2 + S_F / s_F^2 (+ prior)``, with ``s^2`` each term's
minimum over phase divided by its degrees of freedom (n - 6, or n - 8 without
the map's offsets, and 3 * 9 - 6), the heart's ``s_H`` at least
:data:`HEART_NOISE_FLOOR_MM`: a profile likelihood under Gaussian residuals;
``phi_R* = argmin J``.

Interval
--------
The 90 % interval is the likelihood-ratio interval of ``J``, adjusted for
errors that the sum of squares counts as independent but are not: the
sample-size mesh's errors, and the motion model's, are alike at neighbouring
points, so near end-expiration, where the chest and the heart change least,
a few nearby points can pull the minimum and a plain interval is too narrow.
The points are grouped into spatial blocks of about five neighbours
(:func:`spatial_blocks`; the staples are blocks of one); near phi_R* each
block's cost is fitted by a quadratic in the phase.  ``H``, the curvature of
``J``, is the information the cost assumes; ``V``, the spread of the blocks'
slopes, the information the data show (the sandwich, or Godambe, estimate
of composite likelihood).  Neither sees an error shared by all of a term's
evidence (the heart term can prefer a phase a tenth of a cycle off with
twenty chi-square units to spare where breathing barely changes the heart's
shape); what shows it is that the heart and the chest, two independent
measurements of one phase, then disagree.  Each term's own minimum against
the minimum of their sum gives the Birge ratio ``R`` (:func:`disagreement`,
chi-square with one degree of freedom per extra term when they agree within
their noise).  The interval is the run of phases about phi_R* with
``J - min J <= chi2_1(0.90) * max(1, V / H) * max(1, R)``, widened by half a
sweep step (the grid's resolution); where ``J`` is flat it is wide, whatever
the curvature at the minimum says.  A bootstrap over the same blocks and staples
(B = 500, the per-phase ICP solutions held fixed) resamples the evidence and
takes the argmin again; the interval reported spans both (the bootstrap's
5th-95th percentiles cover a cost too rough for the quadratic, as when no
phase carries more evidence than another).  When it spans more than
:data:`UNDECIDED_WIDTH` of a cycle the data cannot decide phi_R*, and the
estimate says so.

The final transform's uncertainty is that of phi_R* carried through the
sweep: the largest mean displacement of the map's vertices between ``T(phi)``
and ``T(phi_R*)`` over the phases inside the interval, and the largest
rotation (phi_R* lies in the interval with 90 % confidence, so the final
transform's error from the phase is within these with at least that much);
the ICP's own noise at a fixed phase is far smaller (see ``icp``'s Hessian
report).
"""

from __future__ import annotations

import enum

import numpy as np

from hrcore.errors import UsageError
from hrcore.geometry import kabsch
from registration.fiducial_curve import FiducialCurve, fiducial_curve
from registration.phase_estimate import UNDECIDED_WIDTH, TemporalError, TemporalEstimate, wrap_phase

__all__ = [
    "TemporalEstimator",
    "TemporalError",
    "FiducialCurve",
    "TemporalEstimate",
    "fiducial_curve",
    "estimate_phase",
    "paper_phase",
    "disagreement",
]

#: resamples of the bootstrap, and the interval's confidence.
N_BOOTSTRAP = 500
CONFIDENCE = 0.9
#: points per spatial block of the heart term's bootstrap and sandwich.
BLOCK_POINTS = 5
#: half-width (cycles) of the window about phi_R* where each unit's cost is fitted by a quadratic.
WINDOW = 0.04
#: Least noise (mm RMS) of the heart term's distances: with few points the rigid fit leaves next to no residual
#: (8 points, 2 degrees of freedom: 0.007 mm where a phantom's tracker and map put it at ~0.15 mm with 100
#: points), which made every other phase look impossible: a 90 % interval [0.17, 0.18], 'final T within
#: 0.0 mm', the truth 0.30 and the transform 3.6 mm off (an audit); with the floor [0.15, 0.34], 4.5 mm.
HEART_NOISE_FLOOR_MM = 0.05


class TemporalEstimator(str, enum.Enum):
    """How phi_R* is chosen."""

    #: chest and heart shape (and a stated breath-hold phase): :func:`estimate_phase`.
    SHAPE = "shape"
    #: the paper's empirical metric, eq. 10: :func:`paper_phase`.
    PAPER = "eq10"


def spatial_blocks(points_mm, n_blocks: int) -> np.ndarray:
    """Partition points into ``n_blocks`` spatial blocks, (n,) int block labels.

    Block centres by farthest-point sampling from the first point (so the
    same points give the same blocks), each point in its nearest centre's
    block: neighbouring points, whose errors (the mesh's, the motion
    model's) are alike, fall in one block.
    """
    p = np.asarray(points_mm, dtype=float)
    n_blocks = int(min(max(1, n_blocks), p.shape[0]))
    centres = [0]
    d = np.linalg.norm(p - p[0], axis=1)
    for _ in range(n_blocks - 1):
        centres.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(p - p[centres[-1]], axis=1))
    return np.argmin(np.linalg.norm(p[:, None] - p[centres][None], axis=2), axis=1)


def _interval(phases, best, boot, confidence, step):
    offsets = wrap_phase(boot - phases[best])
    tail = 100 * (1 - confidence) / 2
    lo, hi = np.percentile(offsets, [tail, 100 - tail])
    lo, hi = min(lo, 0.0) - step / 2, max(hi, 0.0) + step / 2
    if hi - lo >= 1.0:
        lo, hi = -0.5, 0.5
    return np.array([lo, hi])


def _sandwich_interval(phases, J, units, best, confidence, step, inflation=1.0):
    """Offsets (lo, hi) of the adjusted likelihood-ratio interval of argmin J (module docstring).

    ``J`` (m,) the cost over the circular grid ``phases``, ``units`` (m, u)
    its independent parts (spatial blocks of points, staples).  Near the
    minimum each unit is fitted by a quadratic in the phase: the sum of the
    curvatures is the information the cost assumes (``H``), the spread of the
    units' slopes the information the data show (``V``, the sandwich's meat);
    the interval is the run of phases about the minimum where
    ``J - min J <= chi2_1(confidence) * max(1, V / H)``.
    """
    from scipy.stats import chi2

    m = phases.size
    x = wrap_phase(phases - phases[best])
    win = np.abs(x) <= max(WINDOW, 2.01 * step)
    X = np.stack([np.ones(int(win.sum())), x[win], x[win] ** 2], axis=1)
    coef = np.linalg.lstsq(X, np.column_stack([J[win], units[win]]), rcond=None)[0]
    curvature, slopes = coef[2, 0], coef[1, 1:] / 2
    u = slopes.size
    meat = float(np.sum((slopes - slopes.mean()) ** 2) * u / (u - 1)) if u > 1 else 0.0
    scale = max(1.0, meat / curvature) * max(1.0, inflation) if curvature > 0 else np.inf
    inside = (J - J[best]) <= chi2.ppf(confidence, 1) * scale
    lo = hi = 0
    while lo > -(m // 2) and inside[(best + lo - 1) % m]:
        lo -= 1
    while hi < m // 2 and inside[(best + hi + 1) % m]:
        hi += 1
    lo_off = float(wrap_phase(phases[(best + lo) % m] - phases[best])) - step / 2 if lo else -step / 2
    hi_off = float(wrap_phase(phases[(best + hi) % m] - phases[best])) + step / 2 if hi else step / 2
    if hi - lo + 1 >= m or hi_off - lo_off >= 1.0:
        return np.array([-0.5, 0.5])
    return np.array([min(lo_off, 0.0), max(hi_off, 0.0)])


def disagreement(J, terms) -> float:
    """Birge ratio of the terms of ``J``: how far they disagree, per degree of freedom.

    Each term alone has its own minimum; where all measure the same phase with
    the noise their scales say, ``min J - sum(min term)`` is chi-square with
    (number of terms - 1) degrees of freedom, mean 1.  More means an error
    that none of the terms' own scatter shows (a shared model error, a
    biased term); the interval's threshold is multiplied by it (the Particle
    Data Group's scale factor for inconsistent measurements).  1.0 for one term.

    Parameters
    ----------
    J : (m,) float
        The total cost over the sweep (chi-square units).
    terms : sequence of (m,) float
        Its terms, ``J = sum(terms)``.

    Returns
    -------
    float
    """
    if len(terms) < 2:
        return 1.0
    return float(np.min(J) - sum(np.min(t) for t in terms)) / (len(terms) - 1)


def _transform_spread(Ts, phases, best, offsets, vertices_mm):
    """Largest mean vertex displacement (mm) and rotation (deg) between ``T(phi)`` and
    ``T(phi_R*)`` over the sweep's phases inside the interval (``offsets`` about ``phases[best]``).

    With 90 % confidence phi_R* lies in the interval, so the final transform's
    error from the phase is within these with at least that confidence.
    """
    v = np.asarray(vertices_mm, dtype=float)
    if v.shape[0] > 2000:
        v = v[:: int(np.ceil(v.shape[0] / 2000))]
    x = wrap_phase(np.asarray(phases, dtype=float) - phases[best])
    idx = np.flatnonzero((x >= offsets[0] - 1e-9) & (x <= offsets[1] + 1e-9))
    dT = Ts[idx] @ np.linalg.inv(Ts[best])
    moved = np.einsum("aij,vj->avi", dT[:, :3, :3], v) + dT[:, None, :3, 3]
    disp = np.linalg.norm(moved - v, axis=2).mean(axis=1)
    cos = np.clip((np.trace(dT[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return float(disp.max()), float(np.degrees(np.arccos(cos)).max())


def _without_map_offsets(signed_mm, curvature_per_mm) -> np.ndarray:
    """Signed distances (m, n) minus, at each phase, their least-squares fit by ``a + k H``."""
    H = np.broadcast_to(np.asarray(curvature_per_mm, dtype=float), signed_mm.shape)
    if not np.all(np.isfinite(H)):
        raise ValueError("curvature_per_mm must be finite")
    X = np.stack([np.ones_like(H), H - H.mean(axis=1, keepdims=True)], axis=2)  # (m, n, 2)
    # normal equations in numpy's own loops (no BLAS: the same sums on any thread count)
    gram = np.einsum("mni,mnj->mij", X, X) + 1e-12 * np.eye(2)
    coef = np.linalg.solve(gram, np.einsum("mni,mn->mi", X, signed_mm)[..., None])[..., 0]
    return signed_mm - np.einsum("mni,mi->mn", X, coef)


def estimate_phase(
    phases,
    distances_mm,
    T_heart_from_probe,
    vertices_mm,
    *,
    fiducials: FiducialCurve | None = None,
    breath_hold_phase: float | None = None,
    breath_hold_sd: float = 0.05,
    points_mm=None,
    curvature_per_mm=None,
    block_points: int = BLOCK_POINTS,
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
        Per-point distance to the map after ICP at each phase; signed (> 0
        outside) when ``curvature_per_mm`` is given.
    T_heart_from_probe : (m, 4, 4) float
        ICP registration at each phase.
    vertices_mm : (V, 3) float, mm
        The map's vertices (for the transform's uncertainty).
    fiducials : FiducialCurve, optional
        The traced staples (format-2 sessions).
    breath_hold_phase : float, optional
        A breath-hold phase stated by the user, with standard deviation
        ``breath_hold_sd`` (cycles).
    points_mm : (n, 3) float, mm, optional
        Where the points lie on the map (any phase's registration will do):
        the bootstrap resamples spatial blocks of about ``block_points``
        neighbouring points; without it, single points.
    curvature_per_mm : (m, n) or (n,) float, 1/mm, optional
        The map's mean curvature at each point's closest location
        (:mod:`registration.mesh_bias`): the heart term then removes, at each
        phase, the least-squares fit of the signed distances by ``a + k H``,
        the map's own offsets (a threshold's, the CT blur's ``sigma^2 H``),
        which are the same at every phase; n - 8 degrees of freedom (with
        at least 9 points; fewer keep the plain distances).
    block_points : int
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
    dof_h = n - 6
    if curvature_per_mm is not None and n >= 9:
        d2, dof_h = _without_map_offsets(np.asarray(distances_mm, dtype=float), curvature_per_mm) ** 2, n - 8
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
    same = np.isclose(wrap_phase(phases[-1] - phases[0]), 0.0) and m > 1
    usable = np.arange(m - 1 if same else m)
    step = float(np.median(np.diff(phases))) if m > 1 else 0.0
    evidence = ["heart"]
    e_h = d2[usable] / max(d2[usable].sum(axis=1).min() / dof_h, HEART_NOISE_FLOOR_MM ** 2)  # (m', n)
    e_f = np.zeros((usable.size, 0))
    if fiducials is not None:
        r2 = fiducials.residuals_mm[usable] ** 2
        k = r2.shape[1]
        e_f = r2 / (r2.sum(axis=1).min() / (3 * k - 6))
        evidence.append("fiducial_trace")
    prior = np.zeros(usable.size)
    if breath_hold_phase is not None:
        if not 0.0 <= breath_hold_phase <= 1.0:
            raise UsageError(f"breath_hold_phase (--breath-hold-phase) must be a phase in [0, 1], got {breath_hold_phase}")
        prior = (wrap_phase(phases[usable] - breath_hold_phase) / breath_hold_sd) ** 2
        evidence.append("breath_hold")
    J_h, J_f = e_h.sum(axis=1), e_f.sum(axis=1)
    J = J_h + J_f + prior
    best = int(np.argmin(J))

    rng = np.random.default_rng([int(seed), 0x7E3])
    groups = np.arange(n) if points_mm is None else spatial_blocks(points_mm, max(2, n // int(block_points)))
    g = int(groups.max()) + 1
    e_blocks = np.zeros((usable.size, g))
    np.add.at(e_blocks.T, groups, e_h.T)
    W_h = rng.multinomial(g, np.full(g, 1.0 / g), size=n_bootstrap).astype(float)
    J_b = W_h @ e_blocks.T + prior
    if e_f.shape[1]:
        k = e_f.shape[1]
        W_f = rng.multinomial(k, np.full(k, 1.0 / k), size=n_bootstrap).astype(float)
        J_b = J_b + W_f @ e_f.T
    boot_idx = usable[np.argmin(J_b, axis=1)]
    terms = [J_h] + ([J_f] if e_f.shape[1] else []) + ([prior] if breath_hold_phase is not None else [])
    inflation = disagreement(J, terms)
    lr = _sandwich_interval(phases[usable], J, np.concatenate([e_blocks, e_f], axis=1), best, confidence, step, inflation)
    boot = _interval(phases, usable[best], phases[boot_idx], confidence, step)
    offsets = np.array([min(lr[0], boot[0]), max(lr[1], boot[1])])
    t_mm, t_deg = _transform_spread(np.asarray(T_heart_from_probe), phases, usable[best], offsets, vertices_mm)

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
        respiration_phase=phase,
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
        breath_hold_phase=None if breath_hold_phase is None else float(breath_hold_phase),
        transform_mm=t_mm,
        transform_deg=t_deg,
        disagreement=inflation,
    )


def paper_phase(
    phases,
    T_heart_from_probe,
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
    T_heart_from_probe : (m, 4, 4) float
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
    Ts = np.asarray(T_heart_from_probe, dtype=float)
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
    t_mm, t_deg = _transform_spread(Ts, phases, best, offsets, vertices_mm)
    phase = float(phases[best] % 1.0)
    zeros = np.zeros(m)
    return TemporalEstimate(
        method=TemporalEstimator.PAPER.value,
        evidence=("fiducials",),
        respiration_phase=phase,
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
