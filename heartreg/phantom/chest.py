"""The phantom's chest: its structures and their Hounsfield units (rendered by :mod:`heartreg.phantom.chest_render`).

The chest is a stack of analytic structures, each described by an approximate
signed distance (mm, negative inside) and painted in a fixed order, later
structures over earlier ones.  Every boundary is blended with a linear ramp of
width ``edge_mm`` (one pixel by default) in its signed distance, so the
midpoint between the HU of the two sides lies exactly on the true surface
(partial volume in the image plane; the slice profile along z is not
integrated: each slice samples its centre plane).

Anatomy (patient frame, LPS, mm; see :mod:`heartreg.phantom.layout`):

====================  ==========  ==============================================
structure             HU          where
====================  ==========  ==============================================
air                   -1000       outside the body ellipse
subcutaneous fat      -100        outer 8 mm of the body
muscle                40          chest wall inside the fat
ribs                  700         bands in the wall, higher posteriorly
sternum               450         anterior midline of the wall
lungs                 -800        thoracic cavity left and right
mediastinal fat       -100        central band, around vessels and the heart
liver                 65          below a diaphragm dome touching the heart
spine                 380 / 700   vertebral body (cancellous / cortex), discs 90,
                                  canal 20, neural arch 600
oesophagus            40          in front of the spine, right of the aorta
trachea               -1000       superior to the heart
pericardial fat       -100        a 4 mm shell around the epicardium
myocardium            100         between epicardium and blood pool
blood (contrast)      350         blood pool, aorta, pulmonary arteries
fiducial staples      2800        9 ellipsoids on the anterior skin
====================  ==========  ==============================================

The heart comes from :meth:`AnalyticHeart.signed_distance` at the requested
cardiac phase and the CT breath-hold; the blood pool is the concentric inner
surface at ``scale = 1 - wall_thickness / mean(semi axes)``.  The great vessels
start inside the blood pool near the base and leave through the base cap, so
the epicardium is a myocardium/fat boundary everywhere except where they join.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from heartreg.phantom.anatomy import ChamberHeart
from heartreg.phantom.config import Anatomy
from heartreg.phantom.geometry import apply
from heartreg.phantom.great_vessels import Stent, Vessel, descending_stent, great_vessels
from heartreg.phantom.heart import AnalyticHeart
from heartreg.phantom.sdf import _polyline_distance

__all__ = ["HU", "ChestModel", "build_chest"]

#: Hounsfield units of the tissues (see the module table).
HU = {
    "air": -1000.0,
    "fat": -100.0,
    "muscle": 40.0,
    "bone": 700.0,
    "sternum": 450.0,
    "cancellous": 380.0,
    "arch": 600.0,
    "disc": 90.0,
    "csf": 20.0,
    "lung": -800.0,
    "liver": 65.0,
    "myocardium": 100.0,
    "blood": 350.0,
    "metal": 2800.0,
}

#: pericardial fat shell thickness around the epicardium (mm)
PERICARDIAL_FAT_MM = 4.0
#: diaphragm dome: radius of curvature (mm), right-higher tilt (dz/d(-x)), centre
DOME_RADIUS_MM = 160.0
DOME_TILT = 0.15


@dataclass(frozen=True)
class _Tube:
    """A tube of constant radius around a polyline (capsule chain)."""

    points_mm: np.ndarray  # (m, 3)
    radius_mm: float

    def bbox(self, margin_mm: float) -> tuple[np.ndarray, np.ndarray]:
        pad = self.radius_mm + margin_mm
        return self.points_mm.min(axis=0) - pad, self.points_mm.max(axis=0) + pad


def dome_z_mm(dome_top_mm: float, x_mm, y_mm):
    """Diaphragm height z (mm) at (x, y): a tilted paraboloid, right side higher,
    its vertex (before the tilt) at ``dome_top_mm``."""
    x = np.asarray(x_mm, dtype=float)
    y = np.asarray(y_mm, dtype=float)
    return dome_top_mm - (x**2 + y**2) / (2.0 * DOME_RADIUS_MM) - DOME_TILT * x


@dataclass(frozen=True)
class ChestModel:
    """Everything the renderer needs that depends on the heart's placement.

    Build it once per phantom with :func:`build_chest`; rendering is then a pure
    function of (z, phase, grid).

    Attributes
    ----------
    heart : AnalyticHeart
    blood_scale : float
        ``scale`` of the blood-pool surface in ``implicit_reference``.
    dome_top_mm : float
        Height z of the diaphragm dome's vertex (at x = y = 0, before tilt).
    heart_lo_mm, heart_hi_mm : (3,) float64
        Bounding box of the epicardium over all cardiac phases at the breath-hold,
        patient frame.
    tubes : tuple of (name, _Tube)
        Aorta, pulmonary arteries, trachea, oesophagus (the spheroid's chest;
        trachea and oesophagus only with a :class:`ChamberHeart`).
    vessels : tuple of Vessel
        The great vessels of a :class:`ChamberHeart` (empty for the spheroid).
    stent : Stent or None
        The metal stent, when the anatomy asks for one.
    markers : bool
        Whether the 9 skin staples are drawn.
    """

    heart: AnalyticHeart
    blood_scale: float
    dome_top_mm: float
    heart_lo_mm: np.ndarray
    heart_hi_mm: np.ndarray
    tubes: tuple
    vessels: tuple = ()
    stent: Stent | None = None
    markers: bool = True

    def vessel_distance_mm(self, points_mm) -> np.ndarray:
        """Distance (mm) of patient points to the lumen of the contrast vessels
        (negative inside).  Tests use it to skip the heart base where they join.

        Parameters
        ----------
        points_mm : (n, 3) float, mm, patient frame

        Returns
        -------
        (n,) float64, mm
        """
        p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
        d = np.full(len(p), np.inf)
        for vessel in self.vessels:
            d = np.minimum(d, vessel.lumen_distance(p))
        for name, tube in self.tubes:
            if name in ("aorta", "pulmonary"):
                d = np.minimum(d, _tube_distance(p, tube))
        return d


def build_chest(heart: AnalyticHeart, *, anatomy: Anatomy | None = None, phase_c: float = 0.7) -> ChestModel:
    """Place the chest's heart-dependent parts (dome, great vessels) around ``heart``.

    Parameters
    ----------
    heart : AnalyticHeart
        The phantom heart in the CT patient frame (see ``layout.make_heart``);
        a :class:`ChamberHeart` gets the anatomical great vessels.
    anatomy : Anatomy, optional
        Skin markers and stent (default: markers, no stent).
    phase_c : float
        Cardiac phase at which the great vessels of a :class:`ChamberHeart`
        meet it (the gating's target phase).

    Returns
    -------
    ChestModel
    """
    if not isinstance(heart, AnalyticHeart):
        raise TypeError(f"heart must be an AnalyticHeart, got {type(heart).__name__}")
    anatomy = Anatomy() if anatomy is None else anatomy
    shape = heart.shape
    mean_semi = 0.5 * (shape.semi_minor_mm + shape.semi_major_mm)
    blood_scale = float(np.clip(1.0 - shape.wall_thickness_mm / mean_semi, 0.3, 0.95))

    # epicardium over a grid of (u, v) and all cardiac phases at the breath-hold
    u, v = np.meshgrid(np.linspace(0, 1, 72, endpoint=False), np.linspace(0, 1, 49))
    u, v = u.ravel(), v.ravel()
    ref = heart.reference_points(u, v)
    pts = np.concatenate(
        [heart.move(ref, ph, heart.image_resp_phase) for ph in np.linspace(0, 1, 24, endpoint=False)]
    )
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    # dome vertex: every epicardial point sits at least the fat shell above the dome
    lift = (pts[:, 0] ** 2 + pts[:, 1] ** 2) / (2.0 * DOME_RADIUS_MM) + DOME_TILT * pts[:, 0]
    dome_top = float(np.min(pts[:, 2] + lift) - PERICARDIAL_FAT_MM)

    if isinstance(heart, ChamberHeart):
        vessels = great_vessels(heart, phase_c=phase_c)
        tubes = (
            ("trachea", _Tube(np.array([[-12.0, 30.0, 75.0], [-12.0, 30.0, 300.0]]), 8.0)),
            ("oesophagus", _Tube(np.array([[-6.0, 40.0, -200.0], [-6.0, 40.0, 300.0]]), 5.0)),
        )
        return ChestModel(
            heart=heart, blood_scale=blood_scale, dome_top_mm=dome_top, heart_lo_mm=lo, heart_hi_mm=hi,
            tubes=tubes, vessels=vessels, stent=descending_stent(vessels) if anatomy.stent else None,
            markers=anatomy.markers,
        )

    T = heart.T_patient_from_heart

    def at(p_heart):
        return apply(T, p_heart)

    base = shape.base_length_mm
    base_pole = at([0.0, 0.0, base])
    # ascending aorta from inside the blood pool, out of the base cap, up and right,
    # over the arch to the left of the spine and down through the diaphragm
    a0 = at([-4.0, 6.0, 0.45 * base])
    a1 = base_pole + np.array([-12.0, -6.0, 12.0])
    a2 = np.array([a1[0], a1[1] + 8.0, 66.0])
    a3 = np.array([0.5 * (a1[0] + 24.0), 28.0, 73.0])
    a4 = np.array([24.0, 50.0, 64.0])
    a5 = np.array([24.0, 50.0, -200.0])
    aorta = _Tube(np.stack([a0, a1, a2, a3, a4, a5]), 11.0)
    # pulmonary trunk from the anterior base, splitting into left and right arteries
    p0 = at([14.0, -8.0, 0.45 * base])
    p1 = base_pole + np.array([10.0, -14.0, 14.0])
    pulmonary = _Tube(np.stack([p0, p1, np.array([55.0, 22.0, 60.0]), np.array([82.0, 32.0, 54.0])]), 8.5)
    pulmonary_r = _Tube(np.stack([p1, np.array([-4.0, 12.0, 58.0]), np.array([-70.0, 22.0, 52.0])]), 7.5)
    trachea = _Tube(np.array([[-12.0, 36.0, 66.0], [-12.0, 36.0, 300.0]]), 8.0)
    oesophagus = _Tube(np.array([[-4.0, 42.0, -200.0], [-4.0, 42.0, 300.0]]), 6.0)
    tubes = (
        ("aorta", aorta),
        ("pulmonary", pulmonary),
        ("pulmonary", pulmonary_r),
        ("trachea", trachea),
        ("oesophagus", oesophagus),
    )
    stent = None
    if anatomy.stent:
        stent = descending_stent((Vessel("descending_aorta", np.stack([a4, a5]), aorta.radius_mm, 0.0, HU["blood"]),))
    return ChestModel(
        heart=heart,
        blood_scale=blood_scale,
        dome_top_mm=dome_top,
        heart_lo_mm=lo,
        heart_hi_mm=hi,
        tubes=tubes,
        stent=stent,
        markers=anatomy.markers,
    )


def _tube_distance(points, tube: _Tube):
    """Distance (mm) of (n, 3) points to a tube's wall, negative inside."""
    return _polyline_distance(points, tube.points_mm, tube.radius_mm)
