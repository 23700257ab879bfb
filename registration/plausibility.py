"""How far to trust a registration: point coverage and outlier samples.

Two checks that do not change a good registration but say when one is weak:

- :func:`assess_coverage`: a registration on few attachment points, or on
  points bunched on one side of the heart, can slide along the surface (the
  phantom's sessions of 8 and 20 points register 4 mm and 16 degrees off the
  truth, 44 and more are within tolerance).  It says so in notes and a
  :class:`PlausibilityWarning`.
- :func:`outlier_samples`: single tracker glitches in a point's record (a
  sample far from its neighbours) are found against a running median, so that
  they can be left out of that point's motion model and reported.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = [
    "MIN_POINTS",
    "MIN_SECTOR_FRACTION",
    "MIN_SPREAD_RATIO",
    "Coverage",
    "PlausibilityWarning",
    "assess_coverage",
    "outlier_samples",
]

#: fewer attachment points than this register poorly (the phantom's 20 do, 44 do not).
MIN_POINTS = 30
#: azimuth sectors (30 degrees each, about the heart's long axis z) that must hold a point.
MIN_SECTOR_FRACTION = 0.5
#: the points' spread along each principal axis of the surface, over the surface's own.
MIN_SPREAD_RATIO = 0.35
_SECTORS = 12
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
    notes = []
    if p.shape[0] < MIN_POINTS:
        notes.append(
            f"registration on {p.shape[0]} point(s), fewer than {MIN_POINTS}: the result may be several mm "
            "and degrees off; record more points"
        )
    if sector_fraction < MIN_SECTOR_FRACTION or spread_ratio < MIN_SPREAD_RATIO:
        notes.append(
            f"the points cover a narrow part of the heart ({sectors.size} of {_SECTORS} sectors around "
            f"its long axis, spread {spread_ratio:.2f} of the surface's along its thinnest axis): "
            "the registration can slide along the surface; spread the points over the heart"
        )
    if warn:
        for note in notes:
            warnings.warn(note, PlausibilityWarning, stacklevel=2)
    return Coverage(int(p.shape[0]), float(sector_fraction), spread_ratio, tuple(notes))


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
