"""Heart-centric frame from ellipses fitted in slabs (Wood et al. 2018, 2.2.3).

Algorithm of :func:`fit_heart_frame` (the slab ellipses: :mod:`modeling.slab_ellipses`):

1. z starts along the principal axis of the vertices (largest variance), or
   along ``initial_axis``.
2. Repeat until z changes by less than ``tol_deg`` (or ``max_iterations``):
   cut the vertices into slabs ``slab_mm`` thick along z (a slab grid centred
   on the vertices' extent), project each slab's vertices on the plane normal
   to z, fit an ellipse (direct least-squares conic fit, Halir & Flusser 1998)
   to them, keep the longest run of adjacent accepted slabs (below), fit a
   line through their ellipse centres (least squares, every slab weighing the
   same) and take it as the new z.
3. x is the eccentricity-weighted mean of the ellipses' minor axes, each first
   flipped to agree with their common orientation, orthogonalised against z
   and signed to point anterior; y = z x x.

Slabs are rejected when they hold fewer than ``min_points`` vertices, when the
conic is not an ellipse, or when they are *caps*: a slab that holds the flat
base or the apex tip contains vertices spread over the whole cross-section
rather than a band around its rim. After a first fit, vertices with a
normalised elliptical radius below :data:`CAP_RADIUS` are counted; more than
:data:`CAP_FRACTION` of them marks a cap, fewer are dropped and the ellipse refitted.

Only the longest run of adjacent accepted slabs (no rejected slab between
them; ties to the run with more vertices) makes the line, the ellipses and x.
At the base the atria and the great vessels divide the cross-section into
shapes that are no single ellipse, so the slabs beyond such a gap hold what
the segmentation kept of the vessels and atrial roofs, which differs between
segmentations (measured on the real CT of the tests: a reference mask that
includes its pulmonary trunk, the same mask without it and the automatic
model, whose vessels are cut at their valves, gave long axes 10-18 degrees
apart with every accepted slab on the line, 1-4 degrees apart with the run).

Sign of z (apex to base): the base is the end whose cross-sections are wider
near the end. The median distance of the vertices from the axis is measured in
the band 10-25 % of the length in from each end; the base is the end with the
larger value (an apex tapers to a point, the base of a segmented heart is
broad and cut flat). ``base_hint`` (any vector pointing roughly from apex to
base) overrides the rule.

Sign of x: anterior, ``x . (0, -1, 0) > 0`` in LPS (docs/CONTRACTS.md).

Origin: on the fitted axis (the line through the ellipse centres), halfway
between the vertices' extreme heights along it (apex tip and top of the base).
Unlike the centroid of the ellipse centres, this does not jump by half a slab
when an end slab is accepted or rejected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from hrcore.errors import HeartregError
from hrcore.geometry import check_transform, frozen, invert
from modeling.slab_ellipses import SlabEllipse, _fit_line, _fit_slabs, _longest_run

__all__ = ["FrameError", "HeartFrame", "fit_heart_frame", "ANTERIOR_LPS"]

#: Anterior direction in LPS patient coordinates.
ANTERIOR_LPS = np.array([0.0, -1.0, 0.0])
#: A fit stopped by ``max_iterations`` while its axis still moved less than this (deg) has settled: it
#: alternates between axes this close (a vertex crossing a slab's edge; slicerio's CTChest4, 10 mm slices:
#: 0.029 deg, every iteration from the 3rd on), far within what any use of the frame can tell.  Not warned.
SETTLED_DEG = 0.5
#: The slabs' choice is discrete (which slab is accepted, which run of them is the longest), so the iteration
#: can come back to an axis it had: a limit cycle.  The axis is then the mean of the cycle's axes; a cycle whose
#: axes lie at most this far apart (deg) is not warned (the mean lies within half of it from each).  The real
#: CT's left heart dimmed as in a pulmonary CTA: a cycle of 3 axes up to 6.9 deg apart, whose last axis after 20
#: iterations was warned as unreliable.
CYCLE_SETTLED_DEG = 10.0


class FrameError(HeartregError, ValueError):
    """The vertices do not allow a heart frame fit."""


@dataclass(frozen=True, eq=False)
class HeartFrame:
    """Result of :func:`fit_heart_frame`.

    Attributes
    ----------
    T_heart_from_patient : (4, 4) float64
    euler_xyz_deg : (3,) float
        Intrinsic X-Y-Z angles of R = Rx(a) Ry(b) Rz(g), whose columns are the
        heart axes in patient coordinates (paper's Table 1), in degrees.
    ellipses : tuple of SlabEllipse
        Accepted slabs, apex to base, fitted about the final axis.
    iterations : int
        Axis updates performed.
    axis_change_deg : float
        Angle between the last two axis estimates; after a cycle, the largest
        angle between the cycle's axes.
    converged : bool
        ``axis_change_deg < tol_deg`` was reached within ``max_iterations``.
    cycle : int
        The number of axes the iteration cycled among (0: no cycle); the
        axis is then their mean (:data:`CYCLE_SETTLED_DEG`).
    base_rule : str
        ``"cross-section"`` or ``"hint"``: how the apex-to-base sign was chosen.
    n_rejected_slabs : int
        Slabs dropped (too few vertices, caps, non-elliptical), final fit.
    """

    T_heart_from_patient: np.ndarray
    euler_xyz_deg: tuple
    ellipses: tuple
    iterations: int
    axis_change_deg: float
    converged: bool
    base_rule: str
    n_rejected_slabs: int
    cycle: int = 0

    def __post_init__(self):
        T = frozen(check_transform(self.T_heart_from_patient, name="T_heart_from_patient"), np.float64)
        object.__setattr__(self, "T_heart_from_patient", T)
        object.__setattr__(self, "euler_xyz_deg", tuple(float(a) for a in self.euler_xyz_deg))
        object.__setattr__(self, "ellipses", tuple(self.ellipses))

    def __eq__(self, other):
        if not isinstance(other, HeartFrame):
            return NotImplemented
        return (
            np.array_equal(self.T_heart_from_patient, other.T_heart_from_patient)
            and self.euler_xyz_deg == other.euler_xyz_deg
            and self.ellipses == other.ellipses
            and self.iterations == other.iterations
            and self.axis_change_deg == other.axis_change_deg
            and self.converged == other.converged
            and self.base_rule == other.base_rule
            and self.n_rejected_slabs == other.n_rejected_slabs
            and self.cycle == other.cycle
        )

    __hash__ = None

    def convergence_warning(self) -> str | None:
        """One line when the axis fit did not converge (the model's warning), None when it did or settled
        (:data:`SETTLED_DEG`), or cycled among axes close together (:data:`CYCLE_SETTLED_DEG`)."""
        if self.converged or self.axis_change_deg < SETTLED_DEG:
            return None
        if self.cycle:
            if self.axis_change_deg <= CYCLE_SETTLED_DEG:
                return None
            return (f"the heart frame's fit cycled among {self.cycle} long axes up to {self.axis_change_deg:.1f} deg "
                    "apart: the frame's axes (z, x, the Euler angles), their mean, are unreliable; check that the mask "
                    "is one whole heart (its slabs' ellipses must line up)")
        return (f"the heart frame's fit did not converge ({self.iterations} iterations, the long axis still moved "
                f"{self.axis_change_deg:.1f} deg in the last): the frame's axes (z, x, the Euler angles) are "
                "unreliable; check that the mask is one whole heart (its slabs' ellipses must line up)")

    @property
    def T_patient_from_heart(self) -> np.ndarray:
        return invert(self.T_heart_from_patient)

    @property
    def axes_patient(self) -> np.ndarray:
        """(3, 3) columns x, y, z of the heart frame in patient coordinates."""
        return self.T_heart_from_patient[:3, :3].T.copy()

    @property
    def origin_patient_mm(self) -> np.ndarray:
        return self.T_patient_from_heart[:3, 3]


def fit_heart_frame(
    vertices_patient: np.ndarray,
    *,
    slab_mm: float = 10.0,
    max_iterations: int = 20,
    tol_deg: float = 0.01,
    initial_axis=None,
    base_hint=None,
    min_points: int = 30,
) -> HeartFrame:
    """Fit the heart-centric frame to surface vertices (paper section 2.2.3).

    Parameters
    ----------
    vertices_patient : (n, 3) float, mm
        Vertices of the heart surface in the patient (LPS) frame.
    slab_mm : float
        Slab thickness along z.
    max_iterations : int
        Upper bound on axis updates.
    tol_deg : float
        Stop when the axis moves less than this between iterations (degrees).
    initial_axis : (3,) float, optional
        Starting z (sign irrelevant); default the principal axis of the vertices.
    base_hint : (3,) float, optional
        A direction pointing roughly from apex to base (patient frame); fixes
        the sign of z instead of the cross-section rule.
    min_points : int
        Fewest vertices a slab needs for an ellipse.

    Returns
    -------
    HeartFrame

    Raises
    ------
    FrameError
        Fewer than three slabs give an ellipse (reduce ``slab_mm`` or check the mesh).

    Examples
    --------
    The long axis of an ellipsoid's surface, pointing to the hinted base:

    >>> import numpy as np
    >>> from modeling import fit_heart_frame, mask_to_mesh
    >>> k, j, i = np.mgrid[:50, :40, :40]
    >>> mask = ((k - 25) / 22) ** 2 + ((j - 20) / 14) ** 2 + ((i - 20) / 12) ** 2 < 1
    >>> mesh = mask_to_mesh(mask, np.diag([2.0, 2.0, 2.0, 1.0]), target_faces=2000)
    >>> frame = fit_heart_frame(mesh.vertices, base_hint=[0, 0, 1])
    >>> frame.T_patient_from_heart[:3, 2].round(2) + 0.0  # the heart's z in patient LPS
    array([0., 0., 1.])
    """
    v = np.asarray(vertices_patient, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices_patient must have shape (n, 3), got {v.shape}")
    if len(v) < 100:
        raise FrameError(f"need at least 100 vertices to fit a heart frame, got {len(v)}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices_patient contains NaN or infinity")
    if not slab_mm > 0:
        raise ValueError(f"slab_mm must be positive, got {slab_mm}")
    if int(max_iterations) < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
    if not tol_deg > 0:
        raise ValueError(f"tol_deg must be positive, got {tol_deg}")
    if int(min_points) < 6:
        raise ValueError(f"min_points must be >= 6 (a conic has 5 degrees of freedom), got {min_points}")

    mean = v.mean(axis=0)
    if initial_axis is None:
        _, _, vt = np.linalg.svd(v - mean, full_matrices=False)
        z = vt[0]
    else:
        z = _unit(initial_axis, "initial_axis")

    iterations = cycle = 0
    change_deg = np.inf
    axes = [z]
    while iterations < int(max_iterations):
        slabs = _longest_run(_fit_slabs(v, z, slab_mm, int(min_points))[0])
        if len(slabs) < 3:
            raise FrameError(
                f"only {len(slabs)} slabs of {slab_mm} mm gave an ellipse (need 3); "
                "reduce slab_mm or check that the mesh is a whole heart"
            )
        _, z_new = _fit_line([s["centre"] for s in slabs])
        if z_new @ z < 0:
            z_new = -z_new
        change_deg = _angle_deg(z_new, z)
        z = z_new
        iterations += 1
        if change_deg < tol_deg:
            break
        back = [k for k, earlier in enumerate(axes[:-1]) if _angle_deg(z, earlier) < tol_deg]
        if back:  # a limit cycle (CYCLE_SETTLED_DEG): the axis is the mean of the cycle's
            members = np.array([a if a @ z >= 0 else -a for a in axes[back[0]:]])
            z = _unit(members.sum(axis=0), "the cycle's mean axis")
            cycle = len(members)
            change_deg = max(_angle_deg(a, b) for a in members for b in members)
            break
        axes.append(z)
    converged = bool(change_deg < tol_deg)

    # final ellipses about the final axis
    accepted, n_rejected = _fit_slabs(v, z, slab_mm, int(min_points))
    slabs = _longest_run(accepted)
    n_rejected += len(accepted) - len(slabs)
    if len(slabs) < 3:
        raise FrameError(
            f"only {len(slabs)} slabs of {slab_mm} mm gave an ellipse about the final axis"
        )
    centres = np.array([s["centre"] for s in slabs])
    on_axis = centres.mean(axis=0)
    t = v @ z
    origin = on_axis + z * (0.5 * (t.min() + t.max()) - on_axis @ z)

    # sign of z: apex to base
    if base_hint is not None:
        hint = _unit(base_hint, "base_hint")
        if abs(hint @ z) < 1e-6:
            raise ValueError("base_hint is perpendicular to the heart axis; it cannot fix the sign")
        base_rule = "hint"
        if hint @ z < 0:
            z = -z
    else:
        base_rule = "cross-section"
        if _base_score(v, origin, z) < 0:
            z = -z

    # x: eccentricity-weighted mean of sign-aligned minor axes
    minors = np.array([s["minor"] for s in slabs])
    minors -= np.outer(minors @ z, z)
    minors /= np.linalg.norm(minors, axis=1, keepdims=True)
    ecc = np.array([s["ecc"] for s in slabs])
    w = ecc + 1e-9
    tensor = (minors * w[:, None]).T @ minors
    ref = np.linalg.eigh(tensor)[1][:, -1]
    minors[minors @ ref < 0] *= -1
    x = (minors * w[:, None]).sum(axis=0)
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    if x @ ANTERIOR_LPS < 0:
        x = -x
    y = np.cross(z, x)

    R = np.stack([x, y, z], axis=1)
    T_heart_from_patient = np.eye(4)
    T_heart_from_patient[:3, :3] = R.T
    T_heart_from_patient[:3, 3] = -R.T @ origin
    euler = Rotation.from_matrix(R).as_euler("XYZ", degrees=True)

    ellipses = []
    order = np.argsort([(s["centre"] - origin) @ z for s in slabs])
    for rank, k in enumerate(order):
        s = slabs[k]
        minor = minors[k]
        ellipses.append(
            SlabEllipse(
                slab_index=rank,
                height_mm=float((s["centre"] - origin) @ z),
                centre_mm=s["centre"],
                semi_major_mm=s["a"],
                semi_minor_mm=s["b"],
                minor_axis=minor,
                major_axis=np.cross(z, minor),
                eccentricity=s["ecc"],
                n_points=s["n"],
            )
        )
    return HeartFrame(
        T_heart_from_patient=T_heart_from_patient,
        euler_xyz_deg=tuple(euler),
        ellipses=tuple(ellipses),
        iterations=iterations,
        axis_change_deg=change_deg,
        converged=converged,
        base_rule=base_rule,
        n_rejected_slabs=n_rejected,
        cycle=cycle,
    )


def _angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def _unit(vec, name: str) -> np.ndarray:
    a = np.asarray(vec, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-12:
        raise ValueError(f"{name} must be a finite non-zero 3-vector, got {vec!r}")
    return a / np.linalg.norm(a)


def _base_score(v: np.ndarray, origin: np.ndarray, z: np.ndarray) -> float:
    """> 0 when the +z end is the broader one (the base), < 0 otherwise."""
    d = v - origin
    t = d @ z
    r = np.linalg.norm(d - np.outer(t, z), axis=1)
    lo, hi = t.min(), t.max()
    length = hi - lo
    near_hi = (t <= hi - 0.10 * length) & (t >= hi - 0.25 * length)
    near_lo = (t >= lo + 0.10 * length) & (t <= lo + 0.25 * length)
    if not near_hi.any() or not near_lo.any():
        return 0.0
    return float(np.median(r[near_hi]) - np.median(r[near_lo]))
