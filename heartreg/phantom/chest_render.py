"""Hounsfield-unit rendering of a built :class:`~heartreg.phantom.chest.ChestModel` in axial planes.

Every structure of the chest (see the table of :mod:`heartreg.phantom.chest`)
is an approximate signed distance (mm, negative inside) painted in a fixed
order, later structures over earlier ones. Every boundary is blended with a
linear ramp of width ``edge_mm`` (one pixel by default) in its signed
distance, so the midpoint between the HU of the two sides lies exactly on the
true surface (partial volume in the image plane; each slice samples its centre
plane).
"""

from __future__ import annotations

import functools
from numbers import Real
from types import SimpleNamespace

import numpy as np

from heartreg.phantom.anatomy import ANATOMY_HU, ChamberHeart
from heartreg.phantom.chest import (
    DOME_RADIUS_MM,
    DOME_TILT,
    HU,
    PERICARDIAL_FAT_MM,
    ChestModel,
    _tube_distance,
    build_chest,
    dome_z_mm,
)
from heartreg.phantom.geometry import apply
from heartreg.phantom.heart import AnalyticHeart
from heartreg.phantom.layout import (
    BODY_SEMI_AP_MM,
    BODY_SEMI_LR_MM,
    FIDUCIAL_SIZE_MM,
    fiducials_patient_mm,
    skin_y_mm,
)

__all__ = ["render_slice"]

#: body wall layers, inset from the skin ellipse (mm)
FAT_LAYER_MM = 8.0
RIB_OUTER_INSET_MM = 12.0
CAVITY_INSET_MM = 20.0
#: ribs: vertical pitch, half height, slope dz/dy (higher posteriorly), midline gap
RIB_PITCH_MM = 26.0
RIB_HALF_HEIGHT_MM = 5.0
RIB_SLOPE = 0.35
RIB_MIDLINE_GAP_MM = 20.0
#: fat rim around the great vessels (mm)
VESSEL_FAT_MM = 3.0
#: mediastinal band half width (mm) and spine placement (mm)
MEDIASTINUM_HALF_WIDTH_MM = 20.0
VERTEBRA_CENTRE_MM = (0.0, 60.0)
VERTEBRA_RADIUS_MM = 14.0
CORTEX_MM = 2.0
DISC_PITCH_MM = 28.0
DISC_HALF_MM = 2.5
CANAL_CENTRE_MM = (0.0, 80.0)
CANAL_RADIUS_MM = 7.0
ARCH_RADIUS_MM = 11.0
STERNUM_CENTRE_MM = (0.0, -79.0)
STERNUM_SEMI_MM = (14.0, 5.0)
STERNUM_Z_MM = (-60.0, 200.0)


def _ramp(sd, edge_mm):
    """Occupancy in [0, 1] of a structure with signed distance ``sd``: 1/2 on the surface."""
    return np.clip(0.5 - sd / edge_mm, 0.0, 1.0)


def _paint(img, sd, hu, edge_mm):
    _blend(img, _ramp(sd, edge_mm), hu)


def _blend(img, w, hu):
    """Blend ``hu`` into ``img`` with occupancy ``w`` (:func:`_ramp`)."""
    img += w * (hu - img)


@functools.lru_cache(maxsize=1)  # one study at a time: ~35 MB at 512 x 512
def _plane_fields(xs_bytes: bytes, ys_bytes: bytes, edge_mm: float, dome_top_mm: float) -> SimpleNamespace:
    """What :func:`render_slice` paints the same on every axial plane of one grid.

    The body wall, lungs, mediastinum and spine are prisms along z (ribs,
    sternum, liver and discs change with z); their signed distances and
    occupancies are computed once per grid (a study's slices share it), the
    same numbers the per-slice arithmetic gave.
    """
    xs, ys = np.frombuffer(xs_bytes), np.frombuffer(ys_bytes)
    X, Y = np.meshgrid(xs, ys)
    a, b = BODY_SEMI_LR_MM, BODY_SEMI_AP_MM
    cavity = _ellipse_sd(X, Y, a - CAVITY_INSET_MM, b - CAVITY_INSET_MM)
    vertebra = _circle_sd(X, Y, *VERTEBRA_CENTRE_MM, VERTEBRA_RADIUS_MM)
    slope2 = (X / DOME_RADIUS_MM + DOME_TILT) ** 2 + (Y / DOME_RADIUS_MM) ** 2
    fields = dict(
        Y=Y,
        cavity=cavity,
        rib_shell=np.maximum(_ellipse_sd(X, Y, a - RIB_OUTER_INSET_MM, b - RIB_OUTER_INSET_MM), -cavity),
        rib_gap=RIB_MIDLINE_GAP_MM - np.abs(X),
        sternum=_ellipse_sd(X - STERNUM_CENTRE_MM[0], Y - STERNUM_CENTRE_MM[1], *STERNUM_SEMI_MM),
        dome_z=dome_z_mm(dome_top_mm, X, Y),
        dome_norm=np.sqrt(1.0 + slope2),
        vertebra=vertebra,
        w_body=_ramp(_ellipse_sd(X, Y, a, b), edge_mm),
        w_muscle=_ramp(_ellipse_sd(X, Y, a - FAT_LAYER_MM, b - FAT_LAYER_MM), edge_mm),
        w_lung=_ramp(cavity, edge_mm),
        w_mediastinum=_ramp(np.maximum(cavity, np.abs(X) - MEDIASTINUM_HALF_WIDTH_MM), edge_mm),
        w_vertebra=_ramp(vertebra, edge_mm),
        w_cancellous=_ramp(vertebra + CORTEX_MM, edge_mm),
        w_arch=_ramp(_circle_sd(X, Y, *CANAL_CENTRE_MM, ARCH_RADIUS_MM), edge_mm),
        w_canal=_ramp(_circle_sd(X, Y, *CANAL_CENTRE_MM, CANAL_RADIUS_MM), edge_mm),
    )
    for value in fields.values():  # shared by every call on this grid
        value.setflags(write=False)
    return SimpleNamespace(shape=X.shape, **fields)


def _ellipse_sd(x, y, a, b):
    """First-order signed distance (mm) to the ellipse (x/a)^2 + (y/b)^2 = 1."""
    xa, yb = x / a, y / b
    g = np.maximum(np.sqrt(xa * xa + yb * yb), 1e-9)
    grad = np.sqrt((xa / a) ** 2 + (yb / b) ** 2) / g
    return (g - 1.0) / np.maximum(grad, 1e-12)


def _circle_sd(x, y, cx, cy, r):
    return np.hypot(x - cx, y - cy) - r


def _window(coords, lo, hi):
    """Indices of ``coords`` inside [lo, hi]."""
    return np.nonzero((coords >= lo) & (coords <= hi))[0]


def _tube_on_slice(img, tube, xs, ys, z, hu, edge_mm, offset_mm=0.0):
    """Paint the part of ``tube`` (inflated by ``offset_mm``) cut by plane z."""
    margin = offset_mm + edge_mm
    lo, hi = tube.bbox(margin)
    if not lo[2] <= z <= hi[2]:
        return
    ix, iy = _window(xs, lo[0], hi[0]), _window(ys, lo[1], hi[1])
    if ix.size == 0 or iy.size == 0:
        return
    X, Y = np.meshgrid(xs[ix], ys[iy])
    P = np.stack([X, Y, np.full_like(X, z)], axis=-1)
    sd = _tube_distance(P, tube) - offset_mm
    sub = np.ix_(iy, ix)
    block = img[sub]
    _paint(block, sd, hu, edge_mm)
    img[sub] = block


def render_slice(
    chest: ChestModel | AnalyticHeart,
    *,
    z_mm: float,
    phase_c: float,
    xs_mm,
    ys_mm,
    rng: np.random.Generator | None = None,
    noise_hu: float = 0.0,
    edge_mm: float | None = None,
) -> np.ndarray:
    """Render one axial slice of the chest in Hounsfield units.

    Parameters
    ----------
    chest : ChestModel or AnalyticHeart
        The chest (from :func:`build_chest`); a bare heart is wrapped on the fly
        (slower: build the chest once when rendering many slices).
    z_mm : float
        Height of the axial plane, patient frame (LPS, +z superior), mm.
    phase_c : float
        Cardiac phase in [0, 1) at which the heart is drawn (breath-hold at the
        heart's ``image_resp_phase``).
    xs_mm : (n_cols,) float, mm
        Patient x of the pixel centres of each column (+x patient left).
    ys_mm : (n_rows,) float, mm
        Patient y of the pixel centres of each row (+y posterior).
    rng : numpy.random.Generator, optional
        Source of the CT noise; required when ``noise_hu > 0``.
    noise_hu : float
        Standard deviation of additive white Gaussian noise, HU.
    edge_mm : float, optional
        Width of the partial-volume ramp across every boundary, mm.  Default:
        the mean pixel spacing of ``xs_mm`` and ``ys_mm``.

    Returns
    -------
    (n_rows, n_cols) float32, HU
        Row j, column i is the point (xs_mm[i], ys_mm[j], z_mm).
    """
    if isinstance(chest, AnalyticHeart):
        chest = build_chest(chest)
    if not isinstance(chest, ChestModel):
        raise TypeError(f"chest must be a ChestModel (see build_chest), got {type(chest).__name__}")
    xs = np.asarray(xs_mm, dtype=float)
    ys = np.asarray(ys_mm, dtype=float)
    for name, arr in (("xs_mm", xs), ("ys_mm", ys)):
        if arr.ndim != 1 or arr.size < 1 or not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be a non-empty 1-D array of finite mm, got shape {arr.shape}")
    if not isinstance(z_mm, Real) or not np.isfinite(z_mm):
        raise ValueError(f"z_mm must be a finite number of mm, got {z_mm!r}")
    if not isinstance(phase_c, Real) or not 0.0 <= phase_c < 1.0:
        raise ValueError(f"phase_c must be a cardiac phase in [0, 1), got {phase_c!r}")
    if not noise_hu >= 0:
        raise ValueError(f"noise_hu must be >= 0, got {noise_hu!r}")
    if noise_hu > 0 and not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator when noise_hu > 0; pass np.random.default_rng(seed)")
    if edge_mm is None:
        steps = [np.abs(np.diff(a)).mean() for a in (xs, ys) if a.size > 1]
        edge_mm = float(np.mean(steps)) if steps else 1.0
    if not edge_mm > 0:
        raise ValueError(f"edge_mm must be positive, got {edge_mm!r}")
    z = float(z_mm)

    plane = _plane_fields(xs.tobytes(), ys.tobytes(), float(edge_mm), float(chest.dome_top_mm))
    img = np.full(plane.shape, HU["air"])

    # body wall: fat, muscle, ribs
    _blend(img, plane.w_body, HU["fat"])
    _blend(img, plane.w_muscle, HU["muscle"])
    q = (z - RIB_SLOPE * plane.Y) / RIB_PITCH_MM
    band = (np.abs(q - np.round(q)) * RIB_PITCH_MM - RIB_HALF_HEIGHT_MM) / np.sqrt(1.0 + RIB_SLOPE**2)
    ribs = np.maximum(np.maximum(plane.rib_shell, band), plane.rib_gap)
    _paint(img, ribs, HU["bone"], edge_mm)
    if STERNUM_Z_MM[0] <= z <= STERNUM_Z_MM[1]:
        _paint(img, np.maximum(plane.sternum, STERNUM_Z_MM[0] - z), HU["sternum"], edge_mm)

    # thoracic cavity: lungs, mediastinum, liver below the dome
    _blend(img, plane.w_lung, HU["lung"])
    _blend(img, plane.w_mediastinum, HU["fat"])
    below = (z - plane.dome_z) / plane.dome_norm
    _paint(img, np.maximum(plane.cavity, below), HU["liver"], edge_mm)

    # spine: vertebral body (cortex, cancellous, discs), neural arch, canal
    _blend(img, plane.w_vertebra, HU["bone"])
    _blend(img, plane.w_cancellous, HU["cancellous"])
    qd = z / DISC_PITCH_MM
    disc = abs(qd - round(qd)) * DISC_PITCH_MM - DISC_HALF_MM
    if disc < edge_mm:
        _paint(img, np.maximum(plane.vertebra, disc), HU["disc"], edge_mm)
    _blend(img, plane.w_arch, HU["arch"])
    _blend(img, plane.w_canal, HU["csf"])

    # mediastinal contents: fat around vessels, oesophagus, trachea
    tubes = dict()
    for name, tube in chest.tubes:
        tubes.setdefault(name, []).append(tube)
    for name in ("aorta", "pulmonary"):
        for tube in tubes.get(name, []):
            _tube_on_slice(img, tube, xs, ys, z, HU["fat"], edge_mm, offset_mm=VESSEL_FAT_MM)
    for tube in tubes.get("oesophagus", []):
        _tube_on_slice(img, tube, xs, ys, z, HU["muscle"], edge_mm)
    for tube in tubes.get("trachea", []):
        _tube_on_slice(img, tube, xs, ys, z, HU["air"], edge_mm)

    if isinstance(chest.heart, ChamberHeart):
        _render_chambers(img, chest, xs, ys, z, phase_c, edge_mm)
    else:
        # heart: pericardial fat shell, myocardium, contrast blood pool
        _render_heart(img, chest, xs, ys, z, phase_c, edge_mm)
        for name in ("aorta", "pulmonary"):
            for tube in tubes.get(name, []):
                _tube_on_slice(img, tube, xs, ys, z, HU["blood"], edge_mm)

    if chest.stent is not None:
        _paint_window(img, xs, ys, z, chest.stent.bbox(edge_mm), chest.stent.distance, chest.stent.hu, edge_mm)
    if chest.markers:
        _render_fiducials(img, xs, ys, z, edge_mm)

    if noise_hu > 0:
        img += noise_hu * rng.standard_normal(img.shape)
    return img.astype(np.float32)


def _render_heart(img, chest: ChestModel, xs, ys, z, phase_c, edge_mm):
    margin = PERICARDIAL_FAT_MM + 2.0 * edge_mm + 1.0
    lo, hi = chest.heart_lo_mm - margin, chest.heart_hi_mm + margin
    if not lo[2] <= z <= hi[2]:
        return
    ix, iy = _window(xs, lo[0], hi[0]), _window(ys, lo[1], hi[1])
    if ix.size == 0 or iy.size == 0:
        return
    heart = chest.heart
    X, Y = np.meshgrid(xs[ix], ys[iy])
    P = np.stack([X, Y, np.full_like(X, z)], axis=-1).reshape(-1, 3)
    h = apply(heart.T_heart_from_patient, P)
    ref = heart.unbeat(h, heart.contraction(phase_c, heart.image_resp_phase))
    epi = heart.implicit_reference(ref).reshape(X.shape)
    inner = heart.implicit_reference(ref, scale=chest.blood_scale).reshape(X.shape)
    sub = np.ix_(iy, ix)
    block = img[sub]
    _paint(block, epi - PERICARDIAL_FAT_MM, HU["fat"], edge_mm)
    _paint(block, epi, HU["myocardium"], edge_mm)
    _paint(block, inner, HU["blood"], edge_mm)
    img[sub] = block


def _slice_window(xs, ys, z, box):
    """Pixel index arrays (rows, cols) of ``xs``/``ys`` inside the box (lo, hi), or None."""
    lo, hi = box
    if not lo[2] <= z <= hi[2]:
        return None
    ix, iy = _window(xs, lo[0], hi[0]), _window(ys, lo[1], hi[1])
    if ix.size == 0 or iy.size == 0:
        return None
    return iy, ix


def _paint_window(img, xs, ys, z, box, distance, hu, edge_mm):
    """Paint a structure given by ``distance((..., 3) mm)`` inside its bounding box."""
    win = _slice_window(xs, ys, z, box)
    if win is None:
        return
    iy, ix = win
    X, Y = np.meshgrid(xs[ix], ys[iy])
    sub = np.ix_(iy, ix)
    block = img[sub]
    _paint(block, distance(np.stack([X, Y, np.full_like(X, z)], axis=-1)), hu, edge_mm)
    img[sub] = block


def _render_chambers(img, chest: ChestModel, xs, ys, z, phase_c, edge_mm):
    """Four chambers, epicardial fat, pericardium and the great vessels (see
    :mod:`heartreg.phantom.anatomy`).  Vessel walls stop at the epicardium; the
    lumens run on into their chambers' blood pools."""
    heart = chest.heart
    epi_full = np.full((ys.size, xs.size), np.inf)
    # fat around the vessels first (the heart's own layers paint over it)
    for vessel in chest.vessels:
        _paint_window(img, xs, ys, z, vessel.bbox(VESSEL_FAT_MM + edge_mm),
                      lambda p, v=vessel: v.lumen_distance(p) - v.wall_mm - VESSEL_FAT_MM, HU["fat"], edge_mm)
    margin = PERICARDIAL_FAT_MM + 8.0 + 2.0 * edge_mm
    win = _slice_window(xs, ys, z, (chest.heart_lo_mm - margin, chest.heart_hi_mm + margin))
    if win is not None:
        iy, ix = win
        X, Y = np.meshgrid(xs[ix], ys[iy])
        P = np.stack([X, Y, np.full_like(X, z)], axis=-1)
        q = heart.to_reference(P, phase_c) @ heart.local_axes.T
        parts = heart.chambers_local(q)
        sub = np.ix_(iy, ix)
        block = img[sub]
        hu = ANATOMY_HU
        for name, value in (
            ("pericardium", hu["pericardium"]), ("fat", hu["fat"]), ("epicardium", hu["myocardium"]),
            ("lv_blood", hu["blood_left"]), ("la_blood", hu["blood_left"]),
            ("rv_blood", hu["blood_right"]), ("ra_blood", hu["blood_right"]),
        ):
            _paint(block, parts[name], value, edge_mm)
        img[sub] = block
        epi_full[sub] = parts["epicardium"]
    for vessel in chest.vessels:
        box = vessel.bbox(edge_mm)
        w = _slice_window(xs, ys, z, box)
        if w is None:
            continue
        iy, ix = w
        X, Y = np.meshgrid(xs[ix], ys[iy])
        lumen = vessel.lumen_distance(np.stack([X, Y, np.full_like(X, z)], axis=-1))
        sub = np.ix_(iy, ix)
        block = img[sub]
        _paint(block, np.maximum(lumen - vessel.wall_mm, -epi_full[sub]), ANATOMY_HU["vessel_wall"], edge_mm)
        _paint(block, lumen, vessel.hu, edge_mm)
        img[sub] = block


def _render_fiducials(img, xs, ys, z, edge_mm):
    semi = 0.5 * np.asarray(FIDUCIAL_SIZE_MM, dtype=float)  # tangent, SI, thickness
    reach = semi.max() + edge_mm
    for c in fiducials_patient_mm():
        if abs(z - c[2]) > semi[1] + edge_mm:
            continue
        ix, iy = _window(xs, c[0] - reach, c[0] + reach), _window(ys, c[1] - reach, c[1] + reach)
        if ix.size == 0 or iy.size == 0:
            continue
        # outward skin normal in the axial plane at the staple
        dx = 1e-3
        dy = skin_y_mm(c[0] + dx) - skin_y_mm(c[0] - dx)
        tangent = np.array([2 * dx, dy]) / np.hypot(2 * dx, dy)
        normal = np.array([tangent[1], -tangent[0]])  # points anterior (-y)
        X, Y = np.meshgrid(xs[ix] - c[0], ys[iy] - c[1])
        p_t = (X * tangent[0] + Y * tangent[1]) / semi[0]
        p_n = (X * normal[0] + Y * normal[1]) / semi[2]
        p_z = np.full_like(X, (z - c[2]) / semi[1])
        g = np.maximum(np.sqrt(p_t**2 + p_n**2 + p_z**2), 1e-9)
        grad = np.sqrt((p_t / semi[0]) ** 2 + (p_n / semi[2]) ** 2 + (p_z / semi[1]) ** 2) / g
        sd = np.where(g > 1e-6, (g - 1.0) / np.maximum(grad, 1e-12), -semi[2])
        sub = np.ix_(iy, ix)
        block = img[sub]
        _paint(block, sd, HU["metal"], edge_mm)
        img[sub] = block
