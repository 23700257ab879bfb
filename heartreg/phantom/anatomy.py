"""A heart with anatomy: four chambers, myocardium, great vessels, epicardial fat.

The chambers are built from shapes whose signed distances are exact (spheres
and round cones, iq's ``sdRoundCone``: :mod:`heartreg.phantom.sdf`) joined by smooth unions, in the
end-diastolic reference frame of the heart (``heart``, as
:class:`~heartreg.phantom.heart.AnalyticHeart`), so the true epicardium is the
zero set of one implicit function ``F(p)`` (mm, negative inside) that can be
evaluated, root-found and projected onto to machine precision.  The heartbeat
and the respiration move it exactly as they move the spheroid (the same
analytic, invertible deformation: :meth:`AnalyticHeart.move` /
:meth:`AnalyticHeart.unbeat`), so a CT slab rendered at its own cardiac phase
stays consistent with the truth at that phase.

Layout, in a *local* frame of the heart frame (``anterior``, ``left``, ``z``):
``z`` the heart's long axis (apex to base), ``anterior`` the patient's
anterior direction projected on the short-axis plane, ``left = z x anterior``.

==================  ===========================================================
part                shape (end-diastole, mm)
==================  ===========================================================
left ventricle      round cone from the apex to the base, cut flat at the
                    mitral level; wall 10 mm (cavity = the shape offset inwards)
right ventricle     round cone anterior-right of the LV plus the outflow tract
                    (RVOT) rising anterior-left of the aortic root to the
                    pulmonary valve; wall 4 mm, its cavity wraps the LV (the
                    septum is LV wall)
atria               spheres behind (left) and right of the base; wall 2.5 mm
valves              mitral and tricuspid openings join atria and ventricles; the
                    aortic and pulmonary valves are planes across the arteries'
                    lumens where they leave the LV's pool and the RVOT's end
epicardium          smooth union (blend ``BLEND_MM``) of the four chambers less
                    the arteries' lumens beyond their valves (:class:`ArterialRoot`):
                    the truth, *without* the great vessels
epicardial fat      a wider smooth union (fills the grooves) 1.5 mm out, then a
                    1.2 mm pericardium
great vessels       ascending aorta (29 mm lumen, 33 mm root), descending aorta,
                    pulmonary trunk (25 mm) and arteries, superior and inferior
                    venae cavae, four pulmonary veins; each starts inside its
                    chamber's blood pool and leaves through the epicardium at its
                    *origin* (centre, radius and direction in ``truth.json``)
==================  ===========================================================

The great vessels (:mod:`heartreg.phantom.great_vessels`) do not beat: they are placed once, at the gating's target
phase and the breath-hold, in the patient frame (like the spheroid's vessels),
and their origins are reported at the volume's phase phi_C*.

An epicardial model "without the great vessels" ends at the semilunar valves:
the aortic and pulmonary roots above them (the sinuses) are artery, not
ventricle, even where the chambers' envelope wraps them (the aortic root sits
between the RVOT, the atria and the LV's top).  So each artery's lumen is taken
out of the envelope from its valve plane on (:class:`ArterialRoot`, built by
:func:`heartreg.phantom.great_vessels.arterial_roots`): the true cap over an
artery's mouth is its valve.  Inside the envelope the chambers' myocardium is
the root's wall (the other chambers' blood keeps its own wall thickness away
from the lumen), so the CT shows the lumen against muscle down to the valve,
where it opens into the ventricle's pool.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from heartreg.phantom.geometry import apply
from heartreg.phantom.heart import AnalyticHeart
from heartreg.phantom.sdf import _capsule, _lumen_beyond_valve, _round_cone, _smax, _smin, _sphere

__all__ = [
    "ANATOMY_HU",
    "ArterialRoot",
    "WALL_THICKNESS_MM",
    "ChamberHeart",
]

#: Hounsfield units of the anatomical heart (contrast in the arterial phase:
#: left heart brightest, right heart mixed, the injected SVC very bright, the
#: IVC barely opacified).
ANATOMY_HU = {
    "myocardium": 100.0,
    "fat": -100.0,
    "pericardium": 30.0,
    "vessel_wall": 40.0,
    "blood_left": 380.0,
    "blood_right": 300.0,
    "svc": 600.0,
    "ivc": 150.0,
}

#: myocardial wall thickness (mm, end-diastole) of the chambers.
WALL_THICKNESS_MM = {"left_ventricle": 10.0, "right_ventricle": 4.0, "atria": 2.5}
#: blend radius of the smooth union of the chambers into one epicardium (mm).
BLEND_MM = 8.0
#: blend radius of the epicardial fat (fills the grooves), its least thickness
#: and the pericardium's thickness (mm).
FAT_BLEND_MM = 24.0
FAT_MIN_MM = 1.5
PERICARDIUM_MM = 1.2

# ---- chamber layout, local frame (anterior, left, z), mm, end-diastole
LV_APEX, LV_APEX_R = (0.0, 8.0, -54.0), 17.0
LV_BASE, LV_BASE_R = (-6.0, 8.0, 0.0), 34.0
LV_TOP_Z, LV_TOP_BLEND = 18.0, 10.0
RV_APEX, RV_APEX_R = (14.0, -14.0, -40.0), 12.0
RV_BASE, RV_BASE_R = (14.0, -20.0, 4.0), 27.0
RV_TOP_Z, RV_TOP_BLEND = 18.0, 8.0
RVOT_A, RVOT_A_R = (17.0, -10.0, 6.0), 18.0
#: the RVOT ends at the pulmonary valve, anterior-left of the aortic root, as wide as the trunk's lumen (so the
#: trunk's lumen beyond the valve takes the whole end of the RVOT out of the epicardium)
RVOT_B, RVOT_B_R = (30.0, 20.0, 28.0), 12.5
LA_CENTRE, LA_R = (-24.0, 8.0, 32.0), 23.0
RA_CENTRE, RA_R = (0.0, -36.0, 28.0), 24.0
MITRAL = ((-8.0, 8.0, 4.0), (-20.0, 8.0, 26.0), 8.0)
TRICUSPID = ((11.0, -20.0, 4.0), (3.0, -30.0, 20.0), 9.0)


_RAY_CENTRE_Z = -5.0
_RAY_STEP_MM = 1.0
_RAY_MAX_MM = 150.0


def _outer(q):
    """Outer myocardial surfaces (lv, rv, la, ra) at local points q, (..., 3) mm."""
    z = q[..., 2]
    lv = _smax(_round_cone(q, LV_APEX, LV_BASE, LV_APEX_R, LV_BASE_R), z - LV_TOP_Z, LV_TOP_BLEND)
    rv_body = _smax(_round_cone(q, RV_APEX, RV_BASE, RV_APEX_R, RV_BASE_R), z - RV_TOP_Z, RV_TOP_BLEND)
    rv = _smin(rv_body, _round_cone(q, RVOT_A, RVOT_B, RVOT_A_R, RVOT_B_R), 6.0)
    return lv, rv, _sphere(q, LA_CENTRE, LA_R), _sphere(q, RA_CENTRE, RA_R)


@dataclass(frozen=True)
class ArterialRoot:
    """An artery's lumen beyond its valve, carried by the heartbeat.

    The lumen is placed in the patient frame at ``phase_c`` (as the vessel is);
    the heart's local points are carried there by the heartbeat to measure it,
    so at ``phase_c`` the root is exactly the painted lumen, and at other phases
    it moves with the heart.  Where the chambers' envelope wraps the root, their
    myocardium is its wall (the other chambers' blood keeps its own wall
    thickness away from it).

    Attributes
    ----------
    name : str
    chamber : str
        The ventricle it leaves (``lv``, ``rv``): the only pool it opens into.
    points_mm : (m, 3) float64, mm, patient frame
        The centreline from the valve until it is clear of the chambers.
    lumen_radius_mm : float
    valve_mm, normal : (3,) float64
        The valve plane's centre and unit normal (into the artery), patient frame.
    phase_c : float
        The cardiac phase it is placed at (the gating's target).
    box_local : (2, 3) float64
        Local end-diastolic box around it (beyond: no lumen).
    """

    name: str
    chamber: str
    points_mm: np.ndarray
    lumen_radius_mm: float
    valve_mm: np.ndarray
    normal: np.ndarray
    phase_c: float
    box_local: np.ndarray

    def distance(self, points_patient) -> np.ndarray:
        """(...,) mm, negative inside the lumen beyond the valve plane, of patient points at ``phase_c``."""
        return _lumen_beyond_valve(points_patient, self.points_mm, self.lumen_radius_mm, self.valve_mm, self.normal)


# ---------------------------------------------------------------------- heart
@dataclass(frozen=True)
class ChamberHeart(AnalyticHeart):
    """The phantom heart with four chambers (see the module's table).

    The same interface as :class:`AnalyticHeart` (placement, heartbeat,
    respiration, ``reference_points(u, v)``, ``surface_points``,
    ``surface_frames``, ``signed_distance``, ``surface_distance``), with the
    epicardium of the chambers instead of the spheroid.  ``shape`` is kept
    only for the motion's reference lengths; the chambers' sizes are this
    module's constants.  ``roots`` are the arteries beyond their valves, taken
    out of the epicardium (empty: the chambers' envelope alone, as
    :func:`heartreg.phantom.great_vessels.great_vessels` places the vessels on).
    """

    roots: tuple = ()

    # ------------------------------------------------------------ local frame
    @cached_property
    def local_axes(self) -> np.ndarray:
        """(3, 3) rows: anterior, left, z of the local frame, in the heart frame."""
        R = self.T_patient_from_heart[:3, :3]
        anterior = R.T @ np.array([0.0, -1.0, 0.0])  # patient anterior (LPS -y), heart frame
        anterior[2] = 0.0
        if np.linalg.norm(anterior) < 1e-6:  # long axis along anterior-posterior
            anterior = R.T @ np.array([0.0, 0.0, 1.0])
            anterior[2] = 0.0
        anterior /= np.linalg.norm(anterior)
        z = np.array([0.0, 0.0, 1.0])
        return np.stack([anterior, np.cross(z, anterior), z])

    def local_to_heart(self, points_local) -> np.ndarray:
        """Local (anterior, left, z) coordinates to the heart frame, (..., 3) mm."""
        return np.asarray(points_local, dtype=float) @ self.local_axes

    @property
    def z_apex_mm(self) -> float:
        return LV_APEX[2] - LV_APEX_R

    @property
    def z_base_mm(self) -> float:
        return max(LA_CENTRE[2] + LA_R, RA_CENTRE[2] + RA_R)

    @property
    def length_mm(self) -> float:
        return self.z_base_mm - self.z_apex_mm

    # ------------------------------------------------------------ implicit parts
    def chambers_local(self, q) -> dict:
        """Signed distances (mm, negative inside) of local points to each part.

        Parameters
        ----------
        q : (..., 3) float, mm, local frame, end-diastolic reference

        Returns
        -------
        dict of str to (...,) float64
            ``lv, rv, la, ra`` (outer myocardial surfaces), ``epicardium``,
            ``fat`` (outer surface of the epicardial fat), ``pericardium``,
            cavities ``lv_blood, rv_blood, la_blood, ra_blood`` (valve openings
            included in the ventricles' pools).
        """
        lv, rv, la, ra = _outer(q)
        roots = self.root_distances(q)
        epi = self._without_roots(q, _smin(_smin(_smin(lv, rv, BLEND_MM), la, BLEND_MM), ra, BLEND_MM), roots)
        fat = _smin(_smin(_smin(lv, rv, FAT_BLEND_MM), la, FAT_BLEND_MM), ra, FAT_BLEND_MM) - FAT_MIN_MM
        w = WALL_THICKNESS_MM
        lv_blood = _smin(lv + w["left_ventricle"], _capsule(q, *MITRAL), 3.0)
        rv_blood = np.maximum(rv + w["right_ventricle"], np.maximum(-lv, -ra))
        rv_blood = _smin(rv_blood, _capsule(q, *TRICUSPID), 3.0)
        la_blood = np.maximum(la + w["atria"], -lv - w["left_ventricle"] + 2.5)
        ra_blood = np.maximum(ra + w["atria"], -rv - 1.0)
        pools = {"lv": lv_blood, "rv": rv_blood, "la": la_blood, "ra": ra_blood}
        walls = {"lv": w["left_ventricle"], "rv": w["right_ventricle"], "la": w["atria"], "ra": w["atria"]}
        for root in self.roots:  # the other chambers' blood stays a wall away from an artery's root
            d = roots[root.name]
            for name in pools:
                if name != root.chamber:
                    pools[name] = np.maximum(pools[name], walls[name] - d)
        lv_blood, rv_blood, la_blood, ra_blood = (pools[k] for k in ("lv", "rv", "la", "ra"))
        return {
            "lv": lv, "rv": rv, "la": la, "ra": ra, "epicardium": epi,
            "fat": fat, "pericardium": fat - PERICARDIUM_MM,
            "lv_blood": lv_blood, "rv_blood": rv_blood, "la_blood": la_blood, "ra_blood": ra_blood,
        }

    def epicardium_reference(self, points_heart) -> np.ndarray:
        """Implicit epicardium F (mm, negative inside; a signed distance away from
        the blends, within a few per cent in them) at end-diastolic heart-frame points.

        Parameters
        ----------
        points_heart : (..., 3) float, mm

        Returns
        -------
        (...,) float64
        """
        q = np.asarray(points_heart, dtype=float) @ self.local_axes.T
        lv, rv, la, ra = _outer(q)
        return self._without_roots(q, _smin(_smin(_smin(lv, rv, BLEND_MM), la, BLEND_MM), ra, BLEND_MM))

    def root_distances(self, q) -> dict:
        """Signed distance (mm, negative inside) of local end-diastolic points q (..., 3)
        to each artery's lumen beyond its valve (``inf`` far from it), by name."""
        out = {}
        for root in self.roots:
            d = np.full(q.shape[:-1], np.inf)
            near = np.all((q >= root.box_local[0]) & (q <= root.box_local[1]), axis=-1)
            if near.any():
                p = self.move(self.local_to_heart(q[near]), root.phase_c, self.image_resp_phase)
                d[near] = root.distance(p)
            out[root.name] = d
        return out

    def _without_roots(self, q, epi, distances=None):
        """The envelope ``epi`` less the arterial roots beyond their valves."""
        distances = self.root_distances(q) if distances is None else distances
        for d in distances.values():
            epi = np.maximum(epi, -d)
        return epi

    def implicit_reference(self, points_heart, *, scale: float = 1.0):
        """The epicardium's implicit function (``scale`` must be 1: the chambers'
        blood pools are not concentric copies; see :meth:`chambers_local`)."""
        if scale != 1.0:
            raise ValueError("a ChamberHeart has no concentric inner surface; use chambers_local() for the cavities")
        return self.epicardium_reference(points_heart)

    def to_reference(self, points_patient, phase_c, phase_r=None) -> np.ndarray:
        """Patient points at (phi_C, phi_R) back to the end-diastolic heart frame.

        ``phase_r`` defaults to the CT breath-hold.  (..., 3) mm in, (..., 3) mm out.
        """
        p = np.asarray(points_patient, dtype=float)
        phase_r = self.image_resp_phase if phase_r is None else phase_r
        T = np.linalg.inv(self.T_resp(phase_r))
        p = apply(T, p)
        h = apply(self.T_heart_from_patient, p)
        s = self.contraction(phase_c, phase_r)
        ref = self.unbeat(h, s)
        if self.motion.resp_nonrigid_mm:
            # move() adds the respiratory stretch of the reference point itself
            # (linear in it, a few % at most): h = beat(ref) + stretch(ref), solved
            # by fixed-point iteration, which contracts by that few % per step.
            R = self.T_patient_from_heart[:3, :3]
            for _ in range(10):
                ref = self.unbeat(h - self.resp_stretch(ref, phase_r) @ R, s)
        return ref

    def epicardium_at(self, points_patient, phase_c, phase_r=None) -> np.ndarray:
        """F of patient points at (phi_C, phi_R): exact zero set, sign inside < 0."""
        return self.epicardium_reference(self.to_reference(points_patient, phase_c, phase_r))

    # --------------------------------------------------------- surface sampling
    def reference_points(self, u, v) -> np.ndarray:
        """End-diastolic epicardial points where rays from a centre on the long
        axis leave the heart for the last time.

        Parameters
        ----------
        u : (n,) float in [0, 1)
            Angle around the long axis, theta = 2 pi u from +x towards +y.
        v : (n,) float in [0, 1]
            Polar angle pi v from the apex direction (-z) to the base (+z).

        Returns
        -------
        (n, 3) float64, mm, heart frame; ``F`` is zero there to 1e-9 mm.
        """
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        shape = np.broadcast(u, v).shape
        uv = np.stack([np.broadcast_to(u, shape).ravel(), np.broadcast_to(v, shape).ravel()], axis=1)
        # cast each distinct ray once (the session asks for one point at many phases)
        uv, again = np.unique(uv, axis=0, return_inverse=True)
        theta = 2.0 * np.pi * uv[:, 0]
        psi = np.pi * np.clip(uv[:, 1], 0.0, 1.0)
        d = np.stack([np.sin(psi) * np.cos(theta), np.sin(psi) * np.sin(theta), -np.cos(psi)], axis=-1)
        c = np.array([0.0, 0.0, _RAY_CENTRE_Z])
        t = np.arange(0.0, _RAY_MAX_MM + _RAY_STEP_MM, _RAY_STEP_MM)
        out = np.empty((len(d), 3))
        for start in range(0, len(d), 4096):
            dd = d[start:start + 4096]
            f = self.epicardium_reference(c + t[None, :, None] * dd[:, None, :])
            inside = f < 0
            last = inside.shape[1] - 1 - np.argmax(inside[:, ::-1], axis=1)
            lo, hi = t[last], t[np.minimum(last + 1, t.size - 1)]
            for _ in range(48):
                mid = 0.5 * (lo + hi)
                neg = self.epicardium_reference(c + mid[:, None] * dd) < 0
                lo, hi = np.where(neg, mid, lo), np.where(neg, hi, mid)
            out[start:start + 4096] = c + (0.5 * (lo + hi))[:, None] * dd
        return out[again.ravel()].reshape(shape + (3,))

    def _gradient(self, points_heart, step: float = 1e-4) -> np.ndarray:
        g = np.empty(points_heart.shape)
        for i in range(3):
            e = np.zeros(3)
            e[i] = step
            g[..., i] = (self.epicardium_reference(points_heart + e)
                         - self.epicardium_reference(points_heart - e)) / (2 * step)
        return g

    def project_reference(self, points_heart, *, iterations: int = 6) -> np.ndarray:
        """Newton projection of heart-frame points onto F = 0 (to ~1e-9 mm)."""
        p = np.array(points_heart, dtype=float)
        for _ in range(iterations):
            g = self._gradient(p)
            f = self.epicardium_reference(p)
            p -= (f / np.maximum(np.einsum("...i,...i", g, g), 1e-12))[..., None] * g
        return p

    @cached_property
    def _reference_cloud(self):
        """Dense end-diastolic surface samples (~1 mm apart) and outward normals:
        marching cubes of F on a 2 mm grid, one midpoint subdivision, then
        Newton projection onto F = 0."""
        from skimage.measure import marching_cubes

        spacing = 2.0
        lo = np.array([-90.0, -90.0, self.z_apex_mm - 6.0])
        hi = np.array([90.0, 90.0, self.z_base_mm + 6.0])
        axes = [np.arange(a, b + spacing, spacing) for a, b in zip(lo, hi)]
        X, Y, Z = np.meshgrid(*axes, indexing="ij")
        f = self.epicardium_reference(np.stack([X, Y, Z], axis=-1))
        verts, faces, _, _ = marching_cubes(f, 0.0, spacing=(spacing,) * 3)
        verts += lo
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        edges = np.unique(np.sort(edges, axis=1), axis=0)
        pts = np.concatenate([verts, 0.5 * (verts[edges[:, 0]] + verts[edges[:, 1]])])
        pts = self.project_reference(pts, iterations=4)
        # Newton's steps zigzag on the creases where an artery's lumen cuts the chambers (F is a max there):
        # the few points they leave off F = 0 are dropped
        pts = pts[np.abs(self.epicardium_reference(pts)) < 1e-9]
        g = self._gradient(pts)
        return pts, g / np.linalg.norm(g, axis=1, keepdims=True)

    def sample_surface(self, phase_c, phase_r=None):
        """The true epicardium at (phi_C, phi_R) as a dense cloud with normals.

        Points are exact surface points (F = 0 to 1e-9 mm, then moved by the
        exact deformation), about 1 mm apart; normals are carried through the
        deformation's Jacobian.  ``phase_r`` defaults to the CT breath-hold.

        Returns
        -------
        points : (n, 3) float64, mm, patient frame
        normals : (n, 3) float64, unit, outward
        """
        phase_r = self.image_resp_phase if phase_r is None else phase_r
        ref, n_ref = self._reference_cloud
        s = self.contraction(phase_c, phase_r)
        step = 1e-3
        J = np.empty(ref.shape + (3,))
        for i in range(3):
            e = np.zeros(3)
            e[i] = step
            J[..., i] = (self.beat(ref + e, s) - self.beat(ref - e, s)) / (2 * step)
        n_heart = np.linalg.solve(np.transpose(J, (0, 2, 1)), n_ref[..., None])[..., 0]
        T = self.T_resp(phase_r) @ self.T_patient_from_heart
        n = n_heart @ T[:3, :3].T
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return self.move(ref, phase_c, phase_r), n

    def surface_distance(self, points_patient, phase_c, phase_r=None, **_ignored):
        """Signed distance (mm, > 0 outside) of patient points to the epicardium at
        (phi_C, phi_R), through the tangent plane of the nearest dense sample
        (spacing h ~1 mm, local radius R >= 8 mm: error <= h^2 / 8R ~ 0.02 mm)."""
        from scipy.spatial import cKDTree

        pts, normals = self.sample_surface(phase_c, phase_r)
        q = np.asarray(points_patient, dtype=float).reshape(-1, 3)
        _, idx = cKDTree(pts).query(q, k=1)
        return np.einsum("ij,ij->i", q - pts[idx], normals[idx])
