"""How far to trust a registration: point coverage, outlier samples, the verdict.

Checks that do not change a good registration but say when one is weak:

- :func:`assess_coverage`: a registration on few attachment points, or on
  points bunched on one side of the heart, can slide along the surface (the
  phantom's sessions of 8 and 20 points register 4 mm and 16 degrees off the
  truth, 44 and more are within tolerance).  It says so in notes and a
  :class:`PlausibilityWarning`.
- :func:`outlier_samples`: single tracker glitches in a point's record (a
  sample far from its neighbours) are found against a running median, so that
  they can be left out of that point's motion model and reported.
- :func:`assess_trust`: the verdict written with every registration
  (``registration.json``'s ``trust``): a :class:`TrustLevel` and the reasons
  for it, from the checks above and the registration's own diagnostics
  (phi_R*'s interval, the ICP's convergence and degeneracy, the fiducials).
"""

from __future__ import annotations

import enum
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = [
    "MAX_CORRECTION_DEG",
    "MAX_CORRECTION_MM",
    "MAX_RMS_MM",
    "MIN_POINTS",
    "MIN_SECTOR_FRACTION",
    "MIN_SPREAD_RATIO",
    "Coverage",
    "PlausibilityWarning",
    "Trust",
    "TrustLevel",
    "TrustReason",
    "assess_coverage",
    "assess_trust",
    "outlier_samples",
]

#: fewer attachment points than this register poorly (the phantom's 20 do, 44 do not).
MIN_POINTS = 30
#: azimuth sectors (30 degrees each, about the heart's long axis z) that must hold a point.
MIN_SECTOR_FRACTION = 0.5
#: the points' spread along each principal axis of the surface, over the surface's own.
MIN_SPREAD_RATIO = 0.35
_SECTORS = 12
#: points farther than this from the surface (RMS, mm) at phi_R*: the fit itself is in doubt.  Wood et
#: al. 2018 report about 2 mm RMS in live animals; the phantom's fits are 0.2-0.4 mm.
MAX_RMS_MM = 3.0
#: a surface fit this far from the fiducial seed T0 (rotation deg, translation mm at the heart's
#: centre) contradicts it: in Wood et al. 2018 the correction was 8.2 deg and 9.9 mm on average.
MAX_CORRECTION_DEG = 25.0
MAX_CORRECTION_MM = 30.0
#: Largest share of a point's samples the tracker may have marked invalid (dropped, the motion interpolated
#: across them) before the trust says so: an audit's PLUS session lost half of them and the trust was "ok".
MAX_INVALID_FRACTION = 0.1
#: running-median window of the outlier check, s (short against a 1 s heartbeat).
OUTLIER_WINDOW_S = 0.11
#: a sample is an outlier this many robust standard deviations from the running median ...
OUTLIER_SIGMAS = 8.0
#: ... and at least this far, mm (above the smoothing error of the median at fast motion).
OUTLIER_FLOOR_MM = 3.0


class PlausibilityWarning(UserWarning):
    """The registration ran but rests on weak data (few or bunched points)."""


@dataclass(frozen=True)
class Coverage:
    """How well the attachment points cover the heart.

    Attributes
    ----------
    n_points : int
    sector_fraction : float
        Share of the 12 azimuth sectors about the heart frame's z axis that hold
        at least one point.
    spread_ratio : float
        Smallest ratio, over the surface's principal axes, of the points'
        standard deviation to the surface vertices' one.
    notes : tuple of str
        One line per weakness found (empty when the coverage is fine).
    """

    n_points: int
    sector_fraction: float
    spread_ratio: float
    notes: tuple[str, ...]

    @property
    def weak(self) -> bool:
        return bool(self.notes)

    @property
    def few_points(self) -> bool:
        """Fewer points than :data:`MIN_POINTS`."""
        return self.n_points < MIN_POINTS

    @property
    def narrow(self) -> bool:
        """The points cover too few sectors or spread too little along an axis."""
        return self.sector_fraction < MIN_SECTOR_FRACTION or self.spread_ratio < MIN_SPREAD_RATIO


def assess_coverage(points_heart_mm, vertices_heart_mm, *, warn: bool = True) -> Coverage:
    """Judge how many points there are and how they spread over the surface.

    Parameters
    ----------
    points_heart_mm : (n, 3) float, mm
        The points' mean positions in the heart frame (e.g. through T0).
    vertices_heart_mm : (V, 3) float, mm
        The model surface in the heart frame.
    warn : bool
        Also issue a :class:`PlausibilityWarning` per weakness.

    Returns
    -------
    Coverage
    """
    p = np.asarray(points_heart_mm, dtype=float).reshape(-1, 3)
    v = np.asarray(vertices_heart_mm, dtype=float).reshape(-1, 3)
    centre = v.mean(axis=0)
    azimuth = np.arctan2(p[:, 1] - centre[1], p[:, 0] - centre[0])
    sectors = np.unique(np.floor((azimuth + np.pi) / (2 * np.pi) * _SECTORS).astype(int) % _SECTORS)
    sector_fraction = sectors.size / _SECTORS
    _, axes = np.linalg.eigh(np.cov((v - centre).T))
    spread_v = np.std((v - centre) @ axes, axis=0)
    spread_p = np.std((p - centre) @ axes, axis=0) if p.shape[0] > 1 else np.zeros(3)
    spread_ratio = float(np.min(spread_p / np.maximum(spread_v, 1e-9)))
    found = Coverage(int(p.shape[0]), float(sector_fraction), spread_ratio, ())
    notes = []
    if found.few_points:
        notes.append(
            f"registration on {p.shape[0]} point(s), fewer than {MIN_POINTS}: the result may be several mm "
            "and degrees off; record more points"
        )
    if found.narrow:
        notes.append(
            f"the points cover a narrow part of the heart ({sectors.size} of {_SECTORS} sectors around "
            f"its long axis, spread {spread_ratio:.2f} of the surface's along its thinnest axis): "
            "the registration can slide along the surface; spread the points over the heart"
        )
    if warn:
        for note in notes:
            warnings.warn(note, PlausibilityWarning, stacklevel=2)
    return Coverage(found.n_points, found.sector_fraction, found.spread_ratio, tuple(notes))


def outlier_samples(positions_mm, rate_hz: float) -> np.ndarray:
    """Samples far from the running median of their neighbours (tracker glitches).

    Parameters
    ----------
    positions_mm : (n, 3) float, mm
        One sensor's positions (e.g. the robot in the probe frame).
    rate_hz : float, Hz
        Sample rate.

    Returns
    -------
    (n,) bool
        True at outlier samples.
    """
    p = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    width = max(3, int(round(OUTLIER_WINDOW_S * rate_hz)) | 1)
    if p.shape[0] < 2 * width:
        return np.zeros(p.shape[0], bool)
    smooth = ndimage.median_filter(p, size=(width, 1), mode="nearest")
    residual = np.linalg.norm(p - smooth, axis=1)
    sigma = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    limit = max(OUTLIER_SIGMAS * sigma + float(np.median(residual)), OUTLIER_FLOOR_MM)
    return residual > limit


# ------------------------------------------------------------------ the verdict
class TrustLevel(str, enum.Enum):
    """How far to trust a registration.

    ``ok``: no weakness found.  ``caution``: usable, but it rests on weaker
    evidence than it could (an undecided phi_R*, points left out, outlier
    samples, a bunched layout ...): check it, e.g. on the 3-D view.  ``poor``:
    the data are known to let the result be several mm or degrees off (too
    few points, a degenerate or unconverged final ICP): record again or do not
    navigate on it unchecked.
    """

    OK = "ok"
    CAUTION = "caution"
    POOR = "poor"

    @property
    def rank(self) -> int:
        return ("ok", "caution", "poor").index(self.value)


@dataclass(frozen=True)
class TrustReason:
    """One reason to trust a registration less.

    Attributes
    ----------
    code : str
        Stable name: ``few_points``, ``narrow_coverage``, ``outlier_samples``,
        ``invalid_poses``, ``excluded_points``, ``phase_undecided``, ``sweep_not_converged``,
        ``icp_not_converged``, ``icp_degenerate``, ``fiducial_error``,
        ``fiducials_ambiguous``, ``surface_misfit``, ``seed_contradicted``.
    level : TrustLevel
        What this reason alone makes of the result.
    message : str
        One line: what was found and what to do.
    """

    code: str
    level: TrustLevel
    message: str

    def to_dict(self) -> dict:
        return {"code": self.code, "level": self.level.value, "message": self.message}

    @classmethod
    def from_dict(cls, data: dict) -> "TrustReason":
        """The inverse of :meth:`to_dict`."""
        return cls(str(data["code"]), TrustLevel(data["level"]), str(data["message"]))


@dataclass(frozen=True)
class Trust:
    """The verdict on a registration: the worst of its reasons' levels.

    Attributes
    ----------
    level : TrustLevel
    reasons : tuple of TrustReason
        Empty when ``level`` is ``ok``.
    """

    level: TrustLevel
    reasons: tuple[TrustReason, ...] = ()

    def to_dict(self) -> dict:
        return {"level": self.level.value, "reasons": [r.to_dict() for r in self.reasons]}

    @classmethod
    def from_dict(cls, data: dict) -> "Trust":
        """The inverse of :meth:`to_dict`."""
        return cls(TrustLevel(data["level"]), tuple(TrustReason.from_dict(r) for r in data["reasons"]))

    def summary(self) -> str:
        """One line: the level and the reasons' codes."""
        if not self.reasons:
            return self.level.value
        return f"{self.level.value} ({', '.join(r.code for r in self.reasons)})"


def assess_trust(
    *,
    coverage: Coverage,
    outlier_samples_per_point: dict,
    n_excluded: int,
    phase_estimate,
    icp_converged: bool,
    icp_degenerate: bool,
    sweep_unconverged: int,
    fre_mm: float,
    max_fre_mm: float,
    fiducials_ambiguous: bool,
    rms_mm: float,
    correction_mm: float,
    correction_deg: float,
    invalid_samples_per_point: dict | None = None,
) -> Trust:
    """The verdict on a registration from its checks and diagnostics.

    Parameters
    ----------
    coverage : Coverage
        From :func:`assess_coverage`.
    outlier_samples_per_point : dict of int to int
        Outlier samples left out of each point's motion model (point id: count).
    n_excluded : int
        Points of the session not registered.
    phase_estimate : registration.temporal.TemporalEstimate
        The phi_R* estimate used (its ``decided``, ``width``, ``confidence``,
        ``method``).
    icp_converged, icp_degenerate : bool
        Of the final ICP (:class:`registration.result.IcpReport`).
    sweep_unconverged : int
        Respiration-sweep phases whose ICP did not converge.
    fre_mm, max_fre_mm : float, mm
        The fiducial registration error and its limit.
    fiducials_ambiguous : bool
        The touched fiducials fit the model in more than one order.
    rms_mm : float, mm
        The points' RMS distance to the surface at phi_R* (:data:`MAX_RMS_MM`).
    correction_mm, correction_deg : float
        How far the final registration lies from T0: translation at the heart's
        centre and rotation (:data:`MAX_CORRECTION_MM`, :data:`MAX_CORRECTION_DEG`).
        A model of another heart (or of this one in another state) fits with
        its points mm off the surface, after the ICP turned tens of degrees away
        from what the staples say.
    invalid_samples_per_point : dict of int to (int, int), optional
        Point id: (samples the tracker marked invalid, samples recorded);
        more than :data:`MAX_INVALID_FRACTION` of a point's is a caution.

    Returns
    -------
    Trust
    """
    poor, caution = TrustLevel.POOR, TrustLevel.CAUTION
    reasons = []
    if coverage.few_points:
        reasons.append(TrustReason("few_points", poor, (
            f"{coverage.n_points} point(s), fewer than {MIN_POINTS}: the registration may be several mm "
            "and degrees off; record more points")))
    if coverage.narrow:
        reasons.append(TrustReason("narrow_coverage", caution, (
            f"the points cover {coverage.sector_fraction:.0%} of the sectors around the heart's long axis "
            f"and {coverage.spread_ratio:.2f} of its spread along the thinnest axis: the registration can "
            "slide along the surface; spread the points over the heart")))
    if icp_degenerate:
        reasons.append(TrustReason("icp_degenerate", poor, (
            "the final ICP is degenerate: the points can slide along the surface (icp.weakest_direction); "
            "spread the points over more of the heart")))
    if not icp_converged:
        reasons.append(TrustReason("icp_not_converged", poor, (
            "the final ICP did not converge: the transform may not be the best fit; raise the limit "
            "(--icp-max-iterations)")))
    if not phase_estimate.decided:
        reasons.append(TrustReason("phase_undecided", caution, (
            f"the data cannot decide phi_R* ({phase_estimate.method}): its {phase_estimate.confidence:.0%} "
            f"interval is {phase_estimate.width:.2f} of a cycle wide; {phase_estimate.advice()}")))
    if sweep_unconverged:
        reasons.append(TrustReason("sweep_not_converged", caution, (
            f"the ICP did not converge at {sweep_unconverged} phase(s) of the respiration sweep; raise the "
            "limit (--icp-max-iterations)")))
    bad = {int(k): int(v) for k, v in outlier_samples_per_point.items() if v}
    if bad:
        reasons.append(TrustReason("outlier_samples", caution, (
            f"{sum(bad.values())} outlier sample(s) (tracker glitches) in {len(bad)} point(s) "
            f"({', '.join(str(k) for k in sorted(bad))}) were left out of their motion models; check the tracker")))
    lossy = {int(k): d / n for k, (d, n) in (invalid_samples_per_point or {}).items()
             if n and d / n > MAX_INVALID_FRACTION}
    if lossy:
        reasons.append(TrustReason("invalid_poses", caution, (
            f"the tracker marked up to {max(lossy.values()):.0%} of the poses of {len(lossy)} point(s) "
            f"({', '.join(str(k) for k in sorted(lossy))}) invalid (more than {MAX_INVALID_FRACTION:.0%}): their "
            "motion is interpolated across the gaps; check the tracker's line of sight")))
    if n_excluded:
        reasons.append(TrustReason("excluded_points", caution, (
            f"{n_excluded} point(s) of the session could not be registered (see exclusions)")))
    if fre_mm > max_fre_mm:
        reasons.append(TrustReason("fiducial_error", caution, (
            f"fiducial registration error {fre_mm:.2f} mm exceeds {max_fre_mm:g} mm: the seed T0 is poor; "
            "check the staples touched and their order")))
    if fiducials_ambiguous:
        reasons.append(TrustReason("fiducials_ambiguous", caution, (
            "the touched fiducials fit the model in more than one order: check T0 visually")))
    if rms_mm > MAX_RMS_MM:
        reasons.append(TrustReason("surface_misfit", caution, (
            f"the points lie {rms_mm:.1f} mm RMS from the model's surface (more than {MAX_RMS_MM:g} mm): the model "
            "may be of another heart or scan, or the points off the surface; check the model and the session")))
    if correction_deg > MAX_CORRECTION_DEG or correction_mm > MAX_CORRECTION_MM:
        reasons.append(TrustReason("seed_contradicted", poor, (
            f"the surface fit lies {correction_deg:.0f} deg and {correction_mm:.0f} mm from the fiducial "
            f"registration T0 (more than {MAX_CORRECTION_DEG:g} deg or {MAX_CORRECTION_MM:g} mm): one of them is "
            "wrong (a model of another heart, staples touched in another order, points off the surface); "
            "do not navigate on it unchecked")))
    level = max((r.level for r in reasons), key=lambda x: x.rank, default=TrustLevel.OK)
    return Trust(level, tuple(reasons))
