"""Where the robot is on the map while the heart beats and the chest breathes.

On a static organ the robot's place on the map is ``T z`` (Wood et al. 2018,
section 1).  On the beating heart the map is a snapshot at the image phases
``(phi_C*, phi_R*)`` while the robot is measured at the current phases
``(phi_C, phi_R)``: the pose must first be moved along the surface's motion to
the image phases.  The motion is known only at the registered points (their
AM Fourier models, section 2.2.5), so it is interpolated around the robot:

1. every registered point's model is evaluated at the current phases, giving
   where each point is *now*, and at the image phases;
2. the displacement ``d_i = P_i(phi*) - P_i(phi)`` of the ``n_neighbours``
   points nearest to the robot now is interpolated at the robot by weighted
   linear least squares (moving least squares, weights
   ``(1 - (r / h)^2)^2`` with ``h`` the distance of the next-nearest point, so
   the field is continuous as neighbours change; a small ridge on the
   gradient keeps it stable across the nearly flat layout of points on the
   surface): a linear field (rigid respiratory rotation, locally linear
   contraction) is reproduced exactly, so a robot that crawled between the
   points is still placed right;
3. the orientation is corrected by the weighted mean of the neighbours'
   rotation changes ``R_i(phi*) R_i(phi)^T`` (exponential coordinates);
4. the moved pose is mapped by the registration ``T_heart_from_probe`` to the
   heart frame, and the nearest point of the surface and the signed distance
   to it are found (exactly, :func:`registration.icp.closest_points`).

Everything is vectorised over a batch of samples (a replay); a single live
sample takes a leaner path with the same maths (plain-float regressor and
closest-point search), so that its cost is a few dozen numpy calls.
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points, check_transform
from registration.icp import SurfaceIndex, closest_points
from registration.motion_model import MotionModel, design_matrix

__all__ = ["LocaliseError", "Localiser", "MapPositions", "registered_models"]

#: Neighbours whose displacement is interpolated.
N_NEIGHBOURS = 6
#: Ridge (mm^2) on the displacement gradient, per unit weight.
RIDGE_MM2 = 1.0
#: Beyond this distance (mm) from the nearest registered point the robot is
#: outside the modelled patch: its place is extrapolated (flagged).
FAR_MM = 20.0


class LocaliseError(HeartregError, ValueError):
    """The localiser cannot be built (too few points, mixed harmonics) or used."""


@dataclass(frozen=True, eq=False)
class MapPositions:
    """The robot on the map for a batch of samples (NaN where phases are undefined).

    Attributes
    ----------
    T_heart_from_robot : (m, 4, 4) float64
        The robot's pose moved to the image phases, heart (map) frame, mm.
    position_mm : (m, 3) float64
        Its translation: the robot's position on the map.
    static_mm : (m, 3) float64
        The pose mapped without the motion correction (``T z``, paper
        section 1), for comparison.
    surface_mm : (m, 3) float64
        The nearest point of the model surface, heart frame.
    distance_mm : (m,) float64
        Signed distance from the surface (positive outside).
    nearest_point_mm : (m,) float64
        Distance to the nearest registered point at the current phases.
    """

    T_heart_from_robot: np.ndarray
    position_mm: np.ndarray
    static_mm: np.ndarray
    surface_mm: np.ndarray
    distance_mm: np.ndarray
    nearest_point_mm: np.ndarray


class Localiser:
    """Map robot poses at the current phases to the static map at the image phases.

    Parameters
    ----------
    models : sequence of MotionModel
        The registered points' motion models (probe frame), same harmonics.
    T_heart_from_probe : (4, 4) float
        The registration.
    cardiac_phase, respiration_phase : float, cycles
        The image phases phi_C*, phi_R* of the registration.
    surface : SurfaceIndex or (vertices, faces)
        The model surface in the heart frame.
    n_neighbours : int
        Points whose displacement is interpolated (at most ``len(models) - 1``).
    ridge_mm2 : float, mm^2
        Ridge on the displacement gradient.

    Examples
    --------
    Nine registered points on an ellipsoidal heart (semi-axes 40, 30 and
    50 mm) that breathe up to 12 mm along z and lie on it at the image phase
    phi_R* = 0.3 (probe frame = heart frame).  The robot, seen at the second
    point at phi_R = 0.8, is 12 mm off the map when mapped statically; moved
    to the image phases it lands back on the point, on the surface.

    >>> import numpy as np
    >>> import trimesh
    >>> from registration import Harmonics, Localiser, fit_motion_model
    >>> sphere = trimesh.creation.icosphere(subdivisions=3)
    >>> vertices_mm = np.asarray(sphere.vertices) * [40.0, 30.0, 50.0]
    >>> t_s = np.arange(0.0, 30.0, 0.02)
    >>> phase_c, phase_r = (1.2 * t_s) % 1.0, (0.25 * t_s) % 1.0
    >>> models = []
    >>> for point_mm in vertices_mm[::80]:
    ...     T = np.tile(np.eye(4), (t_s.size, 1, 1))
    ...     T[:, :3, 3] = point_mm
    ...     T[:, 2, 3] += 6.0 * (np.cos(2 * np.pi * (phase_r - 0.3)) - 1.0)
    ...     models.append(fit_motion_model(phase_c, phase_r, T, harmonics=Harmonics(1, 1, 0, 0)))
    >>> localiser = Localiser(models, np.eye(4), 0.5, 0.3, (vertices_mm, np.asarray(sphere.faces)))
    >>> robot = np.eye(4)
    >>> robot[:3, 3] = vertices_mm[80] + [0.0, 0.0, -12.0]
    >>> where = localiser.locate(robot[None], [0.5], [0.8])
    >>> print(f"static {where.static_mm[0, 2] - vertices_mm[80, 2]:.1f} mm in z, moved "
    ...       f"{np.linalg.norm(where.position_mm[0] - vertices_mm[80]):.3f} mm from the point, "
    ...       f"{abs(where.distance_mm[0]):.3f} mm from the surface")
    static -12.0 mm in z, moved 0.000 mm from the point, 0.000 mm from the surface
    """

    def __init__(self, models: Sequence[MotionModel], T_heart_from_probe, cardiac_phase: float,
                 respiration_phase: float, surface, *, n_neighbours: int = N_NEIGHBOURS, ridge_mm2: float = RIDGE_MM2):
        models = list(models)
        if len(models) < 4:
            raise LocaliseError(f"at least 4 registered points are needed to interpolate, got {len(models)}")
        h = models[0].harmonics
        if any(m.harmonics != h for m in models):
            raise LocaliseError("all motion models must have the same harmonics")
        T = check_transform(T_heart_from_probe, name="T_heart_from_probe")
        for name, value in (("cardiac_phase", cardiac_phase), ("respiration_phase", respiration_phase)):
            if not (0.0 <= float(value) <= 1.0):
                raise ValueError(f"{name} must be a phase in [0, 1], got {value!r}")
        self.harmonics = h
        self.n_points = len(models)
        self.k = int(min(max(3, n_neighbours), self.n_points - 1))
        self.ridge_mm2 = float(ridge_mm2)
        self.T_heart_from_probe = T
        self.surface = surface if isinstance(surface, SurfaceIndex) else SurfaceIndex(*surface)
        n = self.n_points
        R = np.stack([m.mean_rotation for m in models])  # (n, 3, 3)
        # fold each point's mean rotation into its coefficients: X @ W -> probe-frame offsets
        Wt = np.einsum("nij,nkj->kni", R, np.stack([m.coef_translation for m in models]))
        Ww = np.einsum("nij,nkj->kni", R, np.stack([m.coef_rotation for m in models]))
        self._W = np.concatenate([Wt.reshape(-1, 3 * n), Ww.reshape(-1, 3 * n)], axis=1)  # (k, 6n)
        self._mean = np.concatenate([np.stack([m.mean_position_mm for m in models]).ravel(), np.zeros(3 * n)])
        star = self._evaluate(np.array([float(cardiac_phase)]), np.array([float(respiration_phase)]))[0]
        self._star_pos = star[: 3 * n].reshape(n, 3)
        self._star_rot = star[3 * n:].reshape(n, 3)
        self.cardiac_phase = float(cardiac_phase)
        self.respiration_phase = float(respiration_phase)
        S = self.surface
        self._tri = [tuple(a) + tuple(b) + tuple(c) + tuple(d) for a, b, c, d in
                     zip(S._a.tolist(), S._ab.tolist(), S._ac.tolist(), S._dots.tolist())]

    def _evaluate(self, phase_c, phase_r) -> np.ndarray:
        """(m, 6n): positions (3n, mm) and probe-frame rotation vectors (3n, rad)."""
        return design_matrix(phase_c, phase_r, self.harmonics) @ self._W + self._mean

    def points_at(self, phase_c: float, phase_r: float) -> np.ndarray:
        """(n, 3) registered points at the given phases, probe frame (mm)."""
        return self._evaluate(np.array([phase_c]), np.array([phase_r]))[0, : 3 * self.n_points].reshape(-1, 3)

    def locate(self, T_probe_from_robot, phase_c, phase_r) -> MapPositions:
        """Move robot poses from their phases to the image phases, onto the map.

        Parameters
        ----------
        T_probe_from_robot : (m, 4, 4) float
            Robot poses in the reference-probe frame, mm.
        phase_c, phase_r : (m,) float, cycles
            Their (causally estimated) phases; NaN gives NaN outputs.

        Returns
        -------
        MapPositions
        """
        T = check_transform(T_probe_from_robot, name="T_probe_from_robot", stack=True, finite=False)
        if T.ndim != 3:
            raise ValueError(f"T_probe_from_robot must have shape (m, 4, 4), got {T.shape}")
        m = T.shape[0]
        pc = np.asarray(phase_c, dtype=float).reshape(-1)
        pr = np.asarray(phase_r, dtype=float).reshape(-1)
        if pc.shape != (m,) or pr.shape != (m,):
            raise ValueError(f"phase_c and phase_r must have shape ({m},), got {pc.shape} and {pr.shape}")
        static = apply_to_points(self.T_heart_from_probe, T[:, :3, 3])
        if m == 1 and math.isfinite(pc[0] + pr[0]) and np.isfinite(T).all():
            # a live sample: the same maths with less set-up per call
            Tm, near = self._locate_one(T[0], float(pc[0]), float(pr[0]))
            p = Tm[0, :3, 3]
            cp, normal = self._nearest_one(p)
            return MapPositions(T_heart_from_robot=Tm, position_mm=Tm[:, :3, 3], static_mm=static,
                                surface_mm=cp[None], distance_mm=np.array([np.dot(p - cp, normal)]),
                                nearest_point_mm=near)
        ok = np.isfinite(pc) & np.isfinite(pr) & np.all(np.isfinite(T), axis=(1, 2))
        nan3 = np.full((m, 3), np.nan)
        out = {
            "T_heart_from_robot": np.full((m, 4, 4), np.nan),
            "position_mm": nan3.copy(),
            "surface_mm": nan3.copy(),
            "distance_mm": np.full(m, np.nan),
            "nearest_point_mm": np.full(m, np.nan),
        }
        idx = np.flatnonzero(ok)
        if idx.size:
            Tm = self._locate(T[idx], pc[idx], pr[idx])
            out["T_heart_from_robot"][idx] = Tm[0]
            out["position_mm"][idx] = Tm[0][:, :3, 3]
            out["nearest_point_mm"][idx] = Tm[1]
            q = Tm[0][:, :3, 3]
            cp = closest_points(self.surface, q)
            out["surface_mm"][idx] = cp.points
            out["distance_mm"][idx] = np.einsum("ij,ij->i", q - cp.points, cp.normals)
        return MapPositions(static_mm=static, **out)

    def _design_one(self, phase_c: float, phase_r: float) -> np.ndarray:
        """The regressor of one phase pair (as :func:`design_matrix`), in plain floats."""
        h = self.harmonics
        zc = cmath.exp(2j * math.pi * phase_c)
        zr = cmath.exp(2j * math.pi * phase_r)
        pc_ = [zc ** (i + 1) for i in range(max(h.cardiac, h.coupled_cardiac))]
        pr_ = [zr ** (j + 1) for j in range(max(h.respiratory, h.coupled_respiratory))]
        x = [1.0]
        for z in pr_[: h.respiratory]:
            x += (z.imag, z.real)
        for z in pc_[: h.cardiac]:
            x += (z.imag, z.real)
        for i in range(h.coupled_cardiac):
            for j in range(h.coupled_respiratory):
                minus = pc_[i] * pr_[j].conjugate()
                plus = pc_[i] * pr_[j]
                x += (minus.imag, minus.real, plus.imag, plus.real)
        return np.array(x)

    def _locate_one(self, T, pc: float, pr: float):
        """:meth:`_locate` for one sample."""
        n, k = self.n_points, self.k
        now = self._design_one(pc, pr) @ self._W + self._mean
        pos = now[: 3 * n].reshape(n, 3)
        p = T[:3, 3]
        diff = pos - p
        d2 = np.einsum("nj,nj->n", diff, diff)
        near = np.argpartition(d2, k)[: k + 1]
        near = near[np.argsort(d2[near])]
        dn = d2[near]
        w = (1.0 - dn[:k] / (dn[k] * 1.0001 + 1e-9)) ** 2
        nb = near[:k]
        basis = np.ones((k, 4))
        basis[:, 1:] = diff[nb]
        wb = basis * w[:, None]
        A = wb.T @ basis
        ridge = self.ridge_mm2 * w.sum()
        A[1, 1] += ridge
        A[2, 2] += ridge
        A[3, 3] += ridge
        shift = np.linalg.solve(A, wb.T @ (self._star_pos[nb] - pos[nb]))[0]
        dw = (w / w.sum()) @ (self._star_rot[nb] - now[3 * n:].reshape(n, 3)[nb])
        out = np.eye(4)
        out[:3, :3] = _rodrigues(dw) @ T[:3, :3]
        out[:3, 3] = p + shift
        return (self.T_heart_from_probe @ out)[None], np.array([math.sqrt(dn[0])])

    def _nearest_one(self, q):
        """Exact closest surface point and face normal of one point, plain floats.

        The faces of the 32 nearest search sites are tried in order of distance
        until no unseen face can be closer (the bound of :mod:`registration.icp`:
        a face is at least its site's distance less ``site_radius_mm`` away).
        Where they do not prove it (a robot more than a millimetre or so off
        the surface), the best so far, ``d``, bounds the answer: every face
        closer has a site within ``d + site_radius_mm``, and those are tried.
        """
        s = self.surface
        r = s.site_radius_mm
        kc = min(32, s._site_face.shape[0])
        dist_s, idx = s.tree.query(q, k=kc)
        qx, qy, qz = q.tolist()
        best = [math.inf, -1, None]
        seen = set()

        def try_faces(faces):
            for f in faces:
                if f not in seen:
                    seen.add(f)
                    d2, cp = _point_triangle(qx, qy, qz, self._tri[f])
                    if d2 < best[0]:
                        best[:] = d2, f, cp

        for ds, f in zip(dist_s.tolist(), s._site_face[idx].tolist()):
            if best[1] >= 0 and ds - r > math.sqrt(best[0]):
                break  # every face not tried yet is farther than the best
            try_faces((f,))
        if kc < s._site_face.shape[0] and math.sqrt(best[0]) > dist_s[-1] - r:
            ball = s.tree.query_ball_point(q, math.sqrt(best[0]) + r)
            try_faces(s._site_face[ball].tolist())
        return np.array(best[2]), s.normals[best[1]]

    def _locate(self, T, pc, pr):
        m, n, k = T.shape[0], self.n_points, self.k
        now = self._evaluate(pc, pr)  # (m, 6n)
        pos = now[:, : 3 * n].reshape(m, n, 3)
        rot = now[:, 3 * n:].reshape(m, n, 3)
        p = T[:, :3, 3]
        diff = pos - p[:, None, :]
        d2 = np.einsum("mnj,mnj->mn", diff, diff)
        near = np.argpartition(d2, k, axis=1)[:, : k + 1]  # k nearest and the next
        dn = np.take_along_axis(d2, near, axis=1)
        order = np.argsort(dn, axis=1)
        near = np.take_along_axis(near, order, axis=1)
        dn = np.take_along_axis(dn, order, axis=1)
        h2 = dn[:, k:k + 1] * 1.0001 + 1e-9
        w = (1.0 - dn[:, :k] / h2) ** 2  # (m, k)
        nb = near[:, :k]
        rows = np.arange(m)[:, None]
        x = diff[rows, nb]  # (m, k, 3): neighbour minus robot
        disp = self._star_pos[nb] - pos[rows, nb]  # (m, k, 3)
        basis = np.concatenate([np.ones((m, k, 1)), x], axis=2)  # (m, k, 4)
        wb = basis * w[..., None]
        A = np.einsum("mki,mkj->mij", wb, basis)
        A[:, 1:, 1:] += self.ridge_mm2 * w.sum(axis=1)[:, None, None] * np.eye(3)
        rhs = np.einsum("mki,mkj->mij", wb, disp)
        coef = np.linalg.solve(A, rhs)  # (m, 4, 3)
        shift = coef[:, 0, :]
        wn = w / w.sum(axis=1, keepdims=True)
        dw = np.einsum("mk,mkj->mj", wn, self._star_rot[nb] - rot[rows, nb])
        out = np.zeros((m, 4, 4))
        out[:, :3, :3] = Rotation.from_rotvec(dw).as_matrix() @ T[:, :3, :3]
        out[:, :3, 3] = p + shift
        out[:, 3, 3] = 1.0
        Th = self.T_heart_from_probe
        return Th @ out, np.sqrt(dn[:, 0])


def _rodrigues(w) -> np.ndarray:
    """Rotation matrix of a rotation vector (rad), (3, 3)."""
    x, y, z = (float(v) for v in w)
    t = math.sqrt(x * x + y * y + z * z)
    if t < 1e-12:
        return np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
    c, s, k = math.cos(t), math.sin(t) / t, (1.0 - math.cos(t)) / (t * t)
    return np.array([
        [c + k * x * x, k * x * y - s * z, k * x * z + s * y],
        [k * x * y + s * z, c + k * y * y, k * y * z - s * x],
        [k * x * z - s * y, k * y * z + s * x, c + k * z * z],
    ])


def _point_triangle(px, py, pz, tri):
    """Squared distance and closest point of p on a triangle (Ericson, Real-Time
    Collision Detection, 5.1.5), plain floats; ``tri`` = a, ab, ac, (ab.ab, ab.ac, ac.ac)."""
    ax, ay, az, bx, by, bz, cx, cy, cz, ab_ab, ab_ac, ac_ac = tri
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = bx * apx + by * apy + bz * apz
    d2 = cx * apx + cy * apy + cz * apz
    if d1 <= 0 and d2 <= 0:
        v = w = 0.0
    else:
        d3, d4 = d1 - ab_ab, d2 - ab_ac
        d5, d6 = d1 - ab_ac, d2 - ac_ac
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0 and d4 <= d3:
            v, w = 1.0, 0.0
        elif vc <= 0 and d1 >= 0 and d3 <= 0:
            v, w = d1 / (d1 - d3), 0.0
        elif d6 >= 0 and d5 <= d6:
            v, w = 0.0, 1.0
        elif vb <= 0 and d2 >= 0 and d6 <= 0:
            v, w = 0.0, d2 / (d2 - d6)
        elif va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            v = 1.0 - w
        else:
            den = va + vb + vc
            v, w = vb / den, vc / den
    qx, qy, qz = ax + v * bx + w * cx, ay + v * by + w * cy, az + v * bz + w * cz
    dx, dy, dz = px - qx, py - qy, pz - qz
    return dx * dx + dy * dy + dz * dz, (qx, qy, qz)


def registered_models(session, point_ids, *, harmonics, coverage_bins: int = 10) -> list[MotionModel]:
    """Re-fit the motion models of the registered points of a session.

    The registration (``registration.json``) records which points it used and
    with which harmonics, not the models' coefficients; the fit is a
    deterministic least-squares solve, so fitting the same records again
    gives the same models (:func:`registration.pipeline.register_session`
    fits them the same way).

    Parameters
    ----------
    session : registration.session.Session
        The session the registration was made from.
    point_ids : sequence of int
        The registered point ids (``point_ids`` of ``registration.json``).
    harmonics : Harmonics

    Returns
    -------
    list of MotionModel, in the order of ``point_ids``

    Raises
    ------
    LocaliseError
        A point id is not in the session, or its record gives no phases.
    """
    import warnings

    from imaging.events import SignalError
    from registration.motion_model import CoverageWarning, fit_motion_model
    from registration.point_models import point_phases

    by_id = {r.point_id: r for r in session.points}
    models = []
    for pid in point_ids:
        record = by_id.get(int(pid))
        if record is None:
            raise LocaliseError(
                f"point {pid} of the registration is not in the session {session.path}: "
                "give the session the registration was made from"
            )
        try:
            phase_c, phase_r, _, _ = point_phases(record)
        except SignalError as exc:
            raise LocaliseError(f"point {pid}: {exc}") from None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CoverageWarning)  # said by the registration already
            models.append(fit_motion_model(phase_c, phase_r, record.T_probe_from_robot,
                                           harmonics=harmonics, coverage_bins=coverage_bins))
    return models
