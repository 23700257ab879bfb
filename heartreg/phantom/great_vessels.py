"""The phantom's great vessels: aorta, pulmonary trunk and arteries, venae cavae, pulmonary veins.

The vessels do not beat: they are placed once, at the gating's target phase and
the breath-hold, in the patient frame, each starting inside its chamber's blood
pool of a :class:`~heartreg.phantom.anatomy.ChamberHeart` and leaving through the
epicardium at its *origin* (:func:`vessel_origins`, reported in ``truth.json``
at the volume's phase phi_C*). The two arteries start at their valve instead
(``Vessel.valve_mm``): the aortic valve where the centreline leaves the LV's
blood pool, the pulmonary valve at the end of the RV outflow tract; their lumen
beyond it is taken out of the epicardium (:func:`arterial_roots`),
so their origin *is* the valve plane.  The pulmonary valve lies anterior-left
of the aortic root and the ascending aorta runs up and to the right, so the
aorta's lumen stays apart from the pulmonary trunk's, the right pulmonary
artery's (under the arch) and the SVC's (1.9-2.9 mm: their walls merge where
they touch), as in a normal heart.  A stent in the descending aorta is the metal artefact of the hard preset.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from heartreg.phantom.anatomy import (
    ANATOMY_HU, LA_CENTRE, RA_CENTRE, RVOT_A, RVOT_B, RVOT_B_R, ArterialRoot, ChamberHeart,
)
from heartreg.phantom.sdf import _lumen_beyond_valve, _polyline_distance

__all__ = ["Stent", "Vessel", "arterial_roots", "descending_stent", "great_vessels", "vessel_origins"]

#: the LV outflow (local: in the LV's pool, then out through its top), the
#: aortic root (local) and the ascending aorta's direction (patient LPS: up and
#: to the right, clear of the pulmonary trunk on its left and the SVC behind)
LV_OUTFLOW = ((-4.0, 2.0, 0.0), (0.0, -6.0, 12.0))
AORTIC_ROOT = (6.0, -12.0, 22.0)
ASCENDING_DIRECTION = (-0.25, -0.1, 1.0)
#: pulmonary trunk direction and the right pulmonary artery's path (patient, mm
#: from the bifurcation: down under the arch, behind the ascending aorta and the SVC)
TRUNK_DIRECTION = (0.35, 0.55, 0.8)
RPA_BEND = (-12.0, 44.0, -26.0)
RPA_END = (-56.0, 52.0, -14.0)


@dataclass(frozen=True)
class Vessel:
    """A great vessel: a lumen of constant radius around a polyline, with a wall.

    Attributes
    ----------
    name : str
    points_mm : (m, 3) float64, patient frame; the first point lies inside the
        blood pool of the chamber the vessel leaves (``None``: not a heart vessel)
    lumen_radius_mm, wall_mm : float
    hu : float
        Contrast in the lumen.
    chamber : str or None
        The chamber it joins (``lv, rv, la, ra``), None for vessels that do not
        touch the heart (descending aorta, branch arteries).
    valve_mm, valve_normal : (3,) float64 or None
        An artery's valve plane (centre on the centreline, unit normal into the
        artery), patient frame: its lumen starts there (below it is the
        ventricle's own blood).  None for veins and branches.
    """

    name: str
    points_mm: np.ndarray
    lumen_radius_mm: float
    wall_mm: float
    hu: float
    chamber: str | None = None
    valve_mm: np.ndarray | None = None
    valve_normal: np.ndarray | None = None

    @property
    def outer_radius_mm(self) -> float:
        return self.lumen_radius_mm + self.wall_mm

    def lumen_distance(self, points) -> np.ndarray:
        """(...,) mm, negative inside the lumen (beyond the valve, if any), of (..., 3) patient points."""
        if self.valve_mm is None:
            return _polyline_distance(points, self.points_mm, self.lumen_radius_mm)
        return _lumen_beyond_valve(points, self.points_mm, self.lumen_radius_mm, self.valve_mm, self.valve_normal)

    def bbox(self, margin_mm: float):
        pad = self.outer_radius_mm + margin_mm
        return self.points_mm.min(axis=0) - pad, self.points_mm.max(axis=0) + pad


@dataclass(frozen=True)
class Stent:
    """A balloon-expandable metal stent: a lattice of struts on a cylinder.

    Attributes
    ----------
    start_mm, end_mm : (3,) float64, patient frame, ends of its axis
    radius_mm : float
        Radius of the strut cylinder (mid-strut).
    strut_mm : float
        Strut width and thickness.
    cells : int
        Diamond cells around the circumference.
    hu : float
    """

    start_mm: np.ndarray
    end_mm: np.ndarray
    radius_mm: float
    strut_mm: float = 0.6
    cells: int = 8
    hu: float = 3000.0

    def distance(self, points) -> np.ndarray:
        """Signed distance-like value (mm, negative in metal) of (..., 3) points."""
        a, b = np.asarray(self.start_mm, float), np.asarray(self.end_mm, float)
        axis = b - a
        length = float(np.linalg.norm(axis))
        axis = axis / length
        p = points - a
        h = p @ axis
        radial = p - h[..., None] * axis
        r = np.linalg.norm(radial, axis=-1)
        ref = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        ref /= np.linalg.norm(ref)
        phi = np.arctan2(radial @ np.cross(axis, ref), radial @ ref)
        arc = self.radius_mm * phi
        pitch = 2.0 * np.pi * self.radius_mm / self.cells  # one diamond per cell
        s1 = (arc + h) / np.sqrt(2.0)
        s2 = (arc - h) / np.sqrt(2.0)
        c = pitch / np.sqrt(2.0)
        d1 = np.abs(s1 - c * np.round(s1 / c))
        d2 = np.abs(s2 - c * np.round(s2 / c))
        strut = np.minimum(d1, d2) - 0.5 * self.strut_mm
        shell = np.abs(r - self.radius_mm) - 0.5 * self.strut_mm
        ends = np.maximum(-h, h - length)
        return np.maximum(np.maximum(shell, strut), ends)

    def bbox(self, margin_mm: float):
        pts = np.stack([self.start_mm, self.end_mm])
        pad = self.radius_mm + self.strut_mm + margin_mm
        return pts.min(axis=0) - pad, pts.max(axis=0) + pad


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def great_vessels(heart: ChamberHeart, *, phase_c: float) -> tuple[Vessel, ...]:
    """Place the great vessels around ``heart`` (patient frame, breath-hold).

    Near the heart the vessels are anchored in the heart's local frame and
    carried by the heartbeat at ``phase_c`` (the gating's target phase), so
    they meet the chambers where the CT images them; away from it they run
    to the patient's fixed landmarks (arch, spine, lungs, diaphragm).

    Returns
    -------
    tuple of Vessel
    """

    def at(local):
        h = heart.local_to_heart(np.asarray(local, dtype=float))
        return heart.move(h[None], phase_c, heart.image_resp_phase)[0]

    up = np.array([0.0, 0.0, 1.0])
    hu = ANATOMY_HU
    # aorta: from the LV outflow through its valve (where the centreline leaves the LV's pool: the annulus)
    # and the root (sinus) up, then the arch
    a, b = (np.asarray(p, dtype=float) for p in LV_OUTFLOW)
    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if heart.chambers_local((a + mid * (b - a))[None])["lv_blood"][0] < 0:
            lo = mid
        else:
            hi = mid
    aortic_valve = at(a + lo * (b - a))
    root = at(AORTIC_ROOT)
    asc = [at(a), at(b), root]
    for k in (15.0, 30.0, 45.0, 60.0):
        asc.append(root + k * _unit(ASCENDING_DIRECTION))
    top = asc[-1]
    arch = [top + (8.0, 10.0, 14.0), top + (24.0, 32.0, 18.0)]
    desc_x, desc_y = 30.0, 48.0
    arch_end = np.array([desc_x, desc_y, top[2] + 6.0])
    aorta = Vessel("aorta", np.stack(asc + arch + [arch_end]), 14.5, 2.0, hu["blood_left"], "lv",
                   aortic_valve, _unit(at(b) - at(a)))
    descending = Vessel(
        "descending_aorta",
        np.stack([arch_end, np.array([desc_x, desc_y, -260.0])]),
        11.5, 1.5, hu["blood_left"],
    )
    # pulmonary trunk from its valve at the end of the RVOT, first along the RVOT's axis (the valve's normal)
    # as far as the RVOT's rounded end would reach, then up and back to the bifurcation
    rvot_a, rvot_b = np.asarray(RVOT_A, dtype=float), np.asarray(RVOT_B, dtype=float)
    axis = (rvot_b - rvot_a) / np.linalg.norm(rvot_b - rvot_a)
    pv_valve, straight = at(rvot_b), at(rvot_b + RVOT_B_R * axis)
    trunk_end = straight + 32.0 * _unit(TRUNK_DIRECTION)
    trunk = Vessel(
        "pulmonary_trunk", np.stack([at(0.5 * (rvot_a + rvot_b)), pv_valve, straight, trunk_end]),
        RVOT_B_R, 1.5, hu["blood_right"], "rv", pv_valve, _unit(at(rvot_b + axis) - pv_valve),
    )
    lpa = Vessel("left_pulmonary_artery",
                 np.stack([trunk_end, trunk_end + (25.0, 10.0, 2.0), trunk_end + (45.0, 14.0, -6.0)]),
                 10.0, 1.0, hu["blood_right"])
    rpa = Vessel("right_pulmonary_artery",
                 np.stack([trunk_end, trunk_end + RPA_BEND, trunk_end + RPA_END]),
                 9.5, 1.0, hu["blood_right"])
    # venae cavae into the right atrium
    ra_c = at(RA_CENTRE)
    svc_entry = at((RA_CENTRE[0] - 4.0, RA_CENTRE[1] - 4.0, RA_CENTRE[2] + 10.0))
    svc = Vessel("superior_vena_cava",
                 np.stack([ra_c + 0.5 * (svc_entry - ra_c), svc_entry, svc_entry + 40.0 * up + (-4.0, 0.0, 0.0),
                           svc_entry + 300.0 * up + (-4.0, 0.0, 0.0)]),
                 10.0, 1.0, hu["svc"], "ra")
    ivc_entry = at((RA_CENTRE[0] - 4.0, RA_CENTRE[1] - 2.0, RA_CENTRE[2] - 12.0))
    ivc = Vessel("inferior_vena_cava",
                 np.stack([ra_c + 0.5 * (ivc_entry - ra_c), ivc_entry, ivc_entry - 30.0 * up + (0.0, 6.0, 0.0),
                           ivc_entry - 300.0 * up + (0.0, 6.0, 0.0)]),
                 12.0, 1.0, hu["ivc"], "ra")
    # four pulmonary veins into the left atrium, out to the lungs
    la_c = at(LA_CENTRE)
    veins = []
    for name, side, dz, back in (("right_superior", -1.0, 10.0, 6.0), ("right_inferior", -1.0, -6.0, 14.0),
                                 ("left_superior", 1.0, 10.0, 6.0), ("left_inferior", 1.0, -6.0, 14.0)):
        start = la_c + (0.0, 0.0, dz)
        mid = start + (side * 26.0, back, 0.3 * dz)
        end = mid + (side * 22.0, 6.0, 0.5 * dz)
        veins.append(Vessel(f"{name}_pulmonary_vein", np.stack([start, mid, end]), 7.0, 1.0,
                            hu["blood_left"], "la"))
    return (aorta, descending, trunk, lpa, rpa, svc, ivc, *veins)


def arterial_roots(heart: ChamberHeart, vessels, phase_c: float) -> tuple[ArterialRoot, ...]:
    """The arteries' lumens beyond their valves, for ``heart``'s epicardium.

    Each valved vessel's centreline from its valve until the first vertex clear
    of the chambers' envelope (``F`` > its outer radius), at ``phase_c`` (where
    :func:`great_vessels` placed it), with a local end-diastolic box around it.

    Returns
    -------
    tuple of :class:`~heartreg.phantom.anatomy.ArterialRoot`
    """
    bare = dataclasses.replace(heart, roots=())
    roots = []
    for vessel in vessels:
        if vessel.valve_mm is None:
            continue
        pts = vessel.points_mm
        beyond = (pts - vessel.valve_mm) @ vessel.valve_normal > 0
        path = [vessel.valve_mm]
        for p in pts[beyond]:
            path.append(p)
            if bare.epicardium_at(p[None], phase_c)[0] > vessel.outer_radius_mm:
                break
        path = np.stack(path)
        local = bare.to_reference(path, phase_c) @ bare.local_axes.T
        pad = vessel.lumen_radius_mm + 5.0  # the beat bends the box's edges a few per cent
        box = np.stack([local.min(axis=0) - pad, local.max(axis=0) + pad])
        roots.append(ArterialRoot(vessel.name, vessel.chamber, path, vessel.lumen_radius_mm, vessel.valve_mm,
                                  vessel.valve_normal, phase_c, box))
    return tuple(roots)


def vessel_origins(heart: ChamberHeart, vessels, phase_c: float, phase_r=None, *, step_mm: float = 0.02):
    """Where each heart vessel leaves the epicardium at (phi_C, phi_R).

    The origin is the last crossing of the vessel's centreline from inside to
    outside the epicardium (F = 0, bisected to 1e-6 mm).

    Returns
    -------
    list of dict
        ``name``, ``chamber``, ``centre_patient_mm`` (3,), ``direction_patient``
        (unit, out of the heart), ``lumen_radius_mm``, ``outer_radius_mm``.
    """
    out = []
    for vessel in vessels:
        if vessel.chamber is None:
            continue
        found = None
        pts = vessel.points_mm
        for a, b in pairwise(pts):
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / step_mm)))
            t = np.linspace(0.0, 1.0, n + 1)
            f = heart.epicardium_at(a + t[:, None] * (b - a), phase_c, phase_r)
            cross = np.nonzero((f[:-1] < 0) & (f[1:] >= 0))[0]
            if cross.size:
                lo, hi = t[cross[-1]], t[cross[-1] + 1]
                for _ in range(40):
                    mid = 0.5 * (lo + hi)
                    if heart.epicardium_at((a + mid * (b - a))[None], phase_c, phase_r)[0] < 0:
                        lo = mid
                    else:
                        hi = mid
                found = (a + 0.5 * (lo + hi) * (b - a), _unit(b - a))
        if found is None:
            raise RuntimeError(f"internal error: the {vessel.name} never leaves the heart; please report")
        out.append({
            "name": vessel.name,
            "chamber": vessel.chamber,
            "centre_patient_mm": found[0],
            "direction_patient": found[1],
            "lumen_radius_mm": vessel.lumen_radius_mm,
            "outer_radius_mm": vessel.outer_radius_mm,
        })
    return out


def descending_stent(vessels, *, z_range_mm=(-40.0, 20.0)) -> Stent:
    """A 60 mm stent in the descending aorta at the heart's level."""
    desc = next(v for v in vessels if v.name == "descending_aorta")
    a, b = desc.points_mm[0], desc.points_mm[-1]
    ends = [a + (z - a[2]) / (b[2] - a[2]) * (b - a) for z in z_range_mm]
    return Stent(start_mm=ends[0], end_mm=ends[1], radius_mm=desc.lumen_radius_mm - 0.3)
