"""Ellipses fitted to slabs of a surface's vertices (Wood et al. 2018, 2.2.3).

:func:`_fit_slabs` cuts vertices into slabs along an axis, projects each slab
on the plane normal to it and fits an ellipse (direct least-squares conic fit,
Halir & Flusser 1998); end caps and degenerate conics are rejected (see
:mod:`modeling.frame` for the rules). :func:`modeling.frame.fit_heart_frame`
iterates this to the heart's long axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SlabEllipse"]

#: Vertices with normalised elliptical radius below this are "inside" a slab.
CAP_RADIUS = 0.7
#: A slab with more than this fraction of inside vertices is an end cap.
CAP_FRACTION = 0.2
#: Largest semi-axis ratio accepted for a slab ellipse.
MAX_AXIS_RATIO = 6.0


@dataclass(frozen=True, eq=False)
class SlabEllipse:
    """Ellipse fitted to the vertices of one slab.

    Attributes
    ----------
    slab_index : int
        Position of the slab along z, 0 at the apex end.
    height_mm : float
        Mean height of the slab's vertices along the final z, relative to the origin.
    centre_mm : (3,) float64, patient frame
    semi_major_mm, semi_minor_mm : float
    minor_axis, major_axis : (3,) float64
        Unit directions in the patient frame, perpendicular to z; the minor axes
        are sign-aligned with the frame's x axis, ``major = z x minor``.
    eccentricity : float
        ``sqrt(1 - (b / a)^2)``.
    n_points : int
        Vertices used in the fit.
    """

    slab_index: int
    height_mm: float
    centre_mm: np.ndarray
    semi_major_mm: float
    semi_minor_mm: float
    minor_axis: np.ndarray
    major_axis: np.ndarray
    eccentricity: float
    n_points: int

    def __eq__(self, other):
        if not isinstance(other, SlabEllipse):
            return NotImplemented
        return all(
            np.array_equal(getattr(self, f), getattr(other, f))
            for f in self.__dataclass_fields__
        )

    __hash__ = None

    def to_dict(self) -> dict:
        return {
            "slab_index": int(self.slab_index),
            "height_mm": float(self.height_mm),
            "centre_mm": [float(c) for c in self.centre_mm],
            "semi_major_mm": float(self.semi_major_mm),
            "semi_minor_mm": float(self.semi_minor_mm),
            "minor_axis": [float(c) for c in self.minor_axis],
            "major_axis": [float(c) for c in self.major_axis],
            "eccentricity": float(self.eccentricity),
            "n_points": int(self.n_points),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "SlabEllipse":
        return cls(
            slab_index=int(d["slab_index"]),
            height_mm=float(d["height_mm"]),
            centre_mm=np.asarray(d["centre_mm"], dtype=np.float64),
            semi_major_mm=float(d["semi_major_mm"]),
            semi_minor_mm=float(d["semi_minor_mm"]),
            minor_axis=np.asarray(d["minor_axis"], dtype=np.float64),
            major_axis=np.asarray(d["major_axis"], dtype=np.float64),
            eccentricity=float(d["eccentricity"]),
            n_points=int(d["n_points"]),
        )

    def points(self, n: int = 120) -> np.ndarray:
        """(n, 3) points on the ellipse, patient frame, for drawing."""
        t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)[:, None]
        return (
            self.centre_mm
            + self.semi_minor_mm * np.cos(t) * self.minor_axis
            + self.semi_major_mm * np.sin(t) * self.major_axis
        )


def _plane_basis(z: np.ndarray):
    helper = np.eye(3)[np.argmin(np.abs(z))]
    e1 = np.cross(z, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(z, e1)


def _fit_line(points):
    """Least-squares line (centroid, unit direction) through 3-D points."""
    p = np.asarray(points, dtype=np.float64)
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    return c, vt[0]


def _fit_slabs(v: np.ndarray, z: np.ndarray, slab_mm: float, min_points: int):
    """Ellipse per slab about axis z. Returns (list of dicts, n_rejected)."""
    e1, e2 = _plane_basis(z)
    t = v @ z
    u = np.stack([v @ e1, v @ e2], axis=1)
    length = t.max() - t.min()
    n_slabs = max(1, int(np.ceil(length / slab_mm)))
    start = t.min() - 0.5 * (n_slabs * slab_mm - length)
    idx = np.clip(((t - start) // slab_mm).astype(int), 0, n_slabs - 1)
    out, rejected = [], 0
    for k in range(n_slabs):
        sel = idx == k
        n = int(sel.sum())
        if n < min_points:
            rejected += 1
            continue
        pts = u[sel]
        fit = _fit_ellipse(pts)
        if fit is None:
            rejected += 1
            continue
        inner = fit["radius"] < CAP_RADIUS
        if inner.mean() > CAP_FRACTION:
            rejected += 1
            continue
        if inner.any():
            pts = pts[~inner]
            fit = _fit_ellipse(pts) if len(pts) >= min_points else None
            if fit is None:
                rejected += 1
                continue
        c2, minor2 = fit["centre"], fit["minor"]
        out.append(
            {
                "slab": k,
                "centre": c2[0] * e1 + c2[1] * e2 + t[sel].mean() * z,
                "minor": minor2[0] * e1 + minor2[1] * e2,
                "a": fit["a"],
                "b": fit["b"],
                "ecc": float(np.sqrt(max(0.0, 1.0 - (fit["b"] / fit["a"]) ** 2))),
                "n": int(len(pts)),
            }
        )
    return out, rejected


def _longest_run(slabs: list, min_run: int = 3) -> list:
    """The longest run of accepted slabs with no rejected slab between them.

    ``slabs`` as returned by :func:`_fit_slabs` (in slab order); ties go to the
    run with more vertices. A run ends where a slab's cross-section is no
    single ellipse (the base, where atria and great vessels divide the
    section), so what lies beyond such a gap -- a vessel stub, an atrial roof
    -- does not tilt the line through the body's centres.  A mesh too coarse
    to give a run of ``min_run`` slabs (a few vertices a slab) keeps every
    accepted slab, as the paper's fit does.
    """
    runs = []
    for s in slabs:
        if runs and s["slab"] == runs[-1][-1]["slab"] + 1:
            runs[-1].append(s)
        else:
            runs.append([s])
    if not runs:
        return []
    longest = max(runs, key=lambda run: (len(run), sum(s["n"] for s in run)))
    return longest if len(longest) >= min_run else list(slabs)


def _fit_ellipse(pts: np.ndarray):
    """Direct least-squares ellipse (Halir & Flusser 1998) to (n, 2) points.

    Returns a dict with centre (2,), semi-axes a >= b, unit minor-axis
    direction (2,) and the normalised elliptical radius of each point, or None
    when the conic is not a usable ellipse.
    """
    mu = pts.mean(axis=0)
    scale = np.sqrt(((pts - mu) ** 2).sum(axis=1).mean())
    if not scale > 0:
        return None
    x, y = ((pts - mu) / scale).T
    D1 = np.stack([x * x, x * y, y * y], axis=1)
    D2 = np.stack([x, y, np.ones_like(x)], axis=1)
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    try:
        Tm = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError:
        return None
    M = S1 + S2 @ Tm
    M = np.stack([M[2] / 2.0, -M[1], M[0] / 2.0])
    w, vecs = np.linalg.eig(M)
    vecs = np.real(vecs)
    cond = 4 * vecs[0] * vecs[2] - vecs[1] ** 2
    ok = np.nonzero(cond > 0)[0]
    if ok.size == 0:
        return None
    a1 = vecs[:, ok[np.argmin(np.abs(np.real(w[ok])))]]
    A, B, C = a1
    Dc, Ec, Fc = Tm @ a1
    Q = np.array([[A, B / 2.0], [B / 2.0, C]])
    try:
        c = np.linalg.solve(2 * Q, -np.array([Dc, Ec]))
    except np.linalg.LinAlgError:
        return None
    F0 = c @ Q @ c + Dc * c[0] + Ec * c[1] + Fc
    if F0 > 0:  # the conic's overall sign is arbitrary: make Q positive definite
        Q, F0 = -Q, -F0
    lam, evec = np.linalg.eigh(Q)
    with np.errstate(divide="ignore", invalid="ignore"):
        semi = np.sqrt(-F0 / lam)
    if not np.all(np.isfinite(semi)) or np.any(semi <= 0):
        return None
    # eigh sorts lam ascending: larger lam -> smaller semi-axis (minor)
    b, a = semi[1], semi[0]
    if a / b > MAX_AXIS_RATIO:
        return None
    d = np.stack([x, y], axis=1) - c
    radius = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", d, Q, d) / -F0, 0.0))
    return {
        "centre": c * scale + mu,
        "a": float(a * scale),
        "b": float(b * scale),
        "minor": evec[:, 1],
        "radius": radius,
    }
