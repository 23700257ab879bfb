"""The anatomical phantom (four chambers, great vessels, fat, tight FOV, stent).

Truth: :class:`heartreg.phantom.anatomy.ChamberHeart`'s implicit epicardium and
its parts, the vessels and origins in ``truth.json``.  The files are read with
pydicom only (not ``imaging``), so the writer is checked independently of the
readers that are tested against it.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pydicom
import pytest
from scipy.ndimage import map_coordinates

from heartreg.cli import main
from heartreg.phantom import ChamberHeart, PhantomError, heart_from_truth, make_phantom
from heartreg.phantom.anatomy import ANATOMY_HU, WALL_THICKNESS_MM
from heartreg.phantom.chest import HU, build_chest
from heartreg.phantom.chest_render import render_slice
from heartreg.phantom.config import PRESETS, Anatomy, config_from_dict, make_config
from heartreg.phantom.heart import AnalyticHeart
from heartreg.phantom.layout import make_heart

FOV_MM = 200.0
NOISE_HU = 25.0


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A sample-size ``human`` case through the CLI: tight FOV, no skin markers, stent."""
    out = tmp_path_factory.mktemp("anatomy")
    argv = ["phantom", str(out), "--preset", "human", "--fov-mm", f"{FOV_MM:g}", "--no-markers",
            "--stent", "--no-session", "-q"]
    assert main(argv) == 0
    truth = json.loads((out / "truth.json").read_text())
    cts = [pydicom.dcmread(f) for f in sorted((out / "ct").iterdir())]
    cts = sorted((d for d in cts if d.Modality == "CT"), key=lambda d: float(d.ImagePositionPatient[2]))
    hu = np.stack([d.pixel_array.astype(float) * float(d.RescaleSlope) + float(d.RescaleIntercept) for d in cts])
    x0, y0, _ = (float(v) for v in cts[0].ImagePositionPatient)
    dy, dx = (float(v) for v in cts[0].PixelSpacing)
    xs = x0 + dx * np.arange(cts[0].Columns)
    ys = y0 + dy * np.arange(cts[0].Rows)
    zs = np.array([float(d.ImagePositionPatient[2]) for d in cts])
    config = config_from_dict(truth["config"])
    heart = heart_from_truth(truth)
    chest = build_chest(heart, anatomy=config.anatomy, phase_c=config.gating_target_phase)
    return dict(out=out, truth=truth, hu=hu, xs=xs, ys=ys, zs=zs, cts=cts, config=config, heart=heart,
                chest=chest)


def _slice_points(c, k):
    X, Y = np.meshgrid(c["xs"], c["ys"])
    return np.stack([X, Y, np.full_like(X, c["zs"][k])], axis=-1)


def _parts(c, k):
    """Every part's signed distance (mm) at the pixels of slice k, at its own phase."""
    heart = c["heart"]
    phase = c["truth"]["slice_cardiac_phase"][k]
    P = _slice_points(c, k)
    parts = heart.chambers_local(heart.to_reference(P, phase) @ heart.local_axes.T)
    parts["vessel"] = np.min([v.lumen_distance(P) - v.wall_mm for v in c["chest"].vessels], axis=0)
    parts["stent"] = c["chest"].stent.distance(P)
    return parts


# ------------------------------------------------------------------ structures
def test_hu_inside_each_structure(case):
    """Pixels at least 2 pixels deep inside one structure and 2 pixels clear of
    every structure painted over it have that structure's HU: the mean over
    >= 200 pixels within 4 HU (noise 25 HU: standard error < 2 HU), the spread
    the CT noise within 10 %."""
    c = case
    margin = 2.0 * (c["xs"][1] - c["xs"][0])
    blood = ("lv_blood", "la_blood", "rv_blood", "ra_blood")
    expected = {
        "lv_blood": ANATOMY_HU["blood_left"], "la_blood": ANATOMY_HU["blood_left"],
        "rv_blood": ANATOMY_HU["blood_right"], "ra_blood": ANATOMY_HU["blood_right"],
        "myocardium": ANATOMY_HU["myocardium"], "epicardial fat": ANATOMY_HU["fat"],
    }
    values = {name: [] for name in expected}
    for k in range(len(c["zs"])):  # every slice: the atria's pools keep a wall away from the aortic root
        p = _parts(c, k)
        clear = (p["vessel"] > margin) & (p["stent"] > margin)
        for name in blood:
            others = np.min([p[o] for o in blood if o != name], axis=0)
            values[name].append(c["hu"][k][clear & (p[name] < -margin) & (others > margin)])
        no_blood = np.min([p[o] for o in blood], axis=0) > margin
        values["myocardium"].append(c["hu"][k][clear & no_blood & (p["epicardium"] < -margin)])
        values["epicardial fat"].append(
            c["hu"][k][clear & (p["epicardium"] > margin) & (p["pericardium"] < -margin)])
    for name, hu_expected in expected.items():
        v = np.concatenate(values[name])
        assert v.size >= 200, f"{name}: only {v.size} pixels"
        assert abs(v.mean() - hu_expected) < 4.0, f"{name}: mean {v.mean():.1f} HU, expected {hu_expected}"
        assert abs(v.std() / NOISE_HU - 1) < 0.1, f"{name}: spread {v.std():.1f} HU"


def test_vessel_lumens_have_their_contrast(case):
    """Each great vessel's lumen, 2 pixels inside its wall, at its HU: the mean of
    >= 30 pixels within 3 standard errors (noise 25 HU)."""
    c = case
    margin = 2.0 * (c["xs"][1] - c["xs"][0])
    found = {v.name: [] for v in c["chest"].vessels}
    for k in range(len(c["zs"])):
        P = _slice_points(c, k)
        if k % 4 and c["zs"][k] < 40:  # every fourth slice, every slice above the heart
            continue
        d = {v.name: v.lumen_distance(P) for v in c["chest"].vessels}
        epi = c["heart"].epicardium_at(P, c["truth"]["slice_cardiac_phase"][k])
        for v in c["chest"].vessels:
            others = np.min([d[o] for o in d if o != v.name], axis=0)
            stent = c["chest"].stent.distance(P)
            ok = (d[v.name] < -margin) & (others > margin) & (epi > margin) & (stent > margin)
            found[v.name].append(c["hu"][k][ok])
    for v in c["chest"].vessels:
        values = np.concatenate(found[v.name])
        assert values.size >= 30, f"{v.name}: only {values.size} pixels in the field of view"
        assert abs(values.mean() - v.hu) < 3 * NOISE_HU / np.sqrt(values.size), f"{v.name}: mean {values.mean():.1f} HU, expected {v.hu}"


def _profile(chest, point, direction, phase, t, *, step_mm=0.1):
    """Noise-free HU along point + t * direction, direction in the axial plane of
    ``point``: a patch rendered at ``step_mm`` pixels (ramp 0.3 mm), read bilinearly."""
    d = np.asarray(direction, dtype=float)[:2] / np.linalg.norm(direction[:2])
    ext = np.abs(t).max() + 1.0
    xs = point[0] + np.arange(-ext, ext + step_mm, step_mm)
    ys = point[1] + np.arange(-ext, ext + step_mm, step_mm)
    img = render_slice(chest, z_mm=float(point[2]), phase_c=phase, xs_mm=xs, ys_mm=ys, edge_mm=0.3)
    line = point[:2] + t[:, None] * d
    return map_coordinates(img, [(line[:, 1] - ys[0]) / step_mm, (line[:, 0] - xs[0]) / step_mm], order=1)


def _along(polyline, start, length_mm):
    """The point ``length_mm`` along a polyline from ``start`` (on it), and the
    direction of the segment it lands on."""
    seg = int(np.argmin([np.linalg.norm(np.cross(b - a, start - a)) / np.linalg.norm(b - a)
                         + 1e3 * (np.dot(start - a, b - a) < 0) + 1e3 * (np.dot(start - b, a - b) < 0)
                         for a, b in zip(polyline[:-1], polyline[1:])]))
    p, left = np.asarray(start, dtype=float), length_mm
    for a, b in zip(polyline[seg:-1], polyline[seg + 1:]):
        step = min(left, np.linalg.norm(b - p))
        u = (b - a) / np.linalg.norm(b - a)
        p, left = p + step * u, left - step
        if left <= 0:
            break
    return p, u


def _on_plane(heart, pts, normals, z, phase, iterations=4, h=1e-4):
    """Surface points near the plane z moved into it exactly: along the tangent
    that climbs fastest, then Newton steps within the plane onto F = 0."""
    up = np.array([0.0, 0.0, 1.0])
    t = up - normals[:, 2:3] * normals
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    q = pts + ((z - pts[:, 2]) / t[:, 2])[:, None] * t
    for _ in range(iterations):
        f = heart.epicardium_at(q, phase)
        g = np.stack([(heart.epicardium_at(q + h * e, phase) - heart.epicardium_at(q - h * e, phase)) / (2 * h)
                      for e in (up[[2, 0, 1]], up[[1, 2, 0]])], axis=1)
        q[:, :2] -= (f / np.einsum("ij,ij->i", g, g))[:, None] * g
    return q, np.abs(heart.epicardium_at(q, phase))


def _nearest(crossings, at=0.0):
    return crossings[np.argmin(np.abs(crossings - at))]


def _crossings(t, values, level):
    s = np.sign(values - level)
    i = np.nonzero(s[:-1] != s[1:])[0]
    return t[i] + (level - values[i]) * (t[i + 1] - t[i]) / (values[i + 1] - values[i])


@pytest.mark.parametrize("wall, lo, hi", [("left_ventricle", 8.0, 12.0), ("right_ventricle", 3.0, 5.0)])
def test_myocardium_thickness_on_the_rendered_volume(case, wall, lo, hi):
    """Free-wall thickness along the true outward normal (points whose normal is
    within 6 degrees of the axial plane, so the in-plane profile is the normal's
    to 0.6 %), between the epicardium (fat/myocardium midpoint, 0 HU) and the
    endocardium (myocardium/blood midpoint), measured on the rendered HU at the
    image phase: within the issue's range (LV 8-12 mm, RV 3-5 mm) and within
    0.8 mm of the end-diastolic thickness (the beat thins the wall by up to ~3 %
    at phase 0.7)."""
    c = case
    heart, chest = c["heart"], c["chest"]
    phase = c["truth"]["cardiac_phase"]
    pts, normals = heart.sample_surface(phase)
    q = heart.to_reference(pts, phase) @ heart.local_axes.T
    parts = heart.chambers_local(q)
    if wall == "left_ventricle":
        # lateral LV wall: on the LV's own surface, away from the RV, atria and blends
        pick = (np.abs(parts["lv"]) < 0.01) & (parts["rv"] > 15) & (parts["la"] > 15) & (parts["ra"] > 15)
        pick &= (q[:, 2] > -40) & (q[:, 2] < 0)
        blood_hu = ANATOMY_HU["blood_left"]
    else:
        pick = (np.abs(parts["rv"]) < 0.01) & (parts["lv"] > 12) & (parts["ra"] > 15) & (parts["la"] > 15)
        pick &= (q[:, 2] > -30) & (q[:, 2] < 5)
        blood_hu = ANATOMY_HU["blood_right"]
    pick &= np.abs(normals[:, 2]) < 0.1
    assert pick.sum() > 20
    idx = np.random.default_rng(0).choice(np.nonzero(pick)[0], 4, replace=False)
    t = np.arange(-1.0, hi + 4.0, 0.02)
    thickness = []
    for i in idx:
        prof = _profile(chest, pts[i], -normals[i], phase, t, step_mm=0.15)
        epi = _nearest(_crossings(t, prof, 0.5 * (ANATOMY_HU["fat"] + ANATOMY_HU["myocardium"])))
        endo = _crossings(t, prof, 0.5 * (ANATOMY_HU["myocardium"] + blood_hu))
        assert abs(epi) < 0.05, f"epicardium at {epi:.3f} mm from the true surface"
        thickness.append(endo[endo > epi][0] - epi)
    thickness = np.array(thickness)
    print(f"{wall}: {np.round(thickness, 2)} mm")
    assert np.all((thickness >= lo) & (thickness <= hi))
    assert np.all(np.abs(thickness - WALL_THICKNESS_MM[wall]) < 0.8)


def test_vessel_diameters_and_origins(case):
    """Lumen diameters measured across each vessel on the rendered HU, 3 mm or
    more past its origin where the centreline is straight and no other vessel
    is near (the aortic and pulmonary roots abut), equal the truth within 0.1 mm
    (profile step 0.02 mm on 0.1 mm pixels, ramp 0.3 mm); the ascending aorta is
    25-35 mm across; the origins lie on the true epicardium (|F| < 1e-4 mm) with
    the vessel leaving outwards."""
    c = case
    heart, chest = c["heart"], c["chest"]
    truth = c["truth"]["anatomy"]
    phase = c["truth"]["cardiac_phase"]
    by_name = {v.name: v for v in chest.vessels}
    assert {o["name"] for o in truth["vessel_origins"]} == {
        "aorta", "pulmonary_trunk", "superior_vena_cava", "inferior_vena_cava",
        "right_superior_pulmonary_vein", "right_inferior_pulmonary_vein",
        "left_superior_pulmonary_vein", "left_inferior_pulmonary_vein"}
    for o in truth["vessel_origins"]:
        centre = np.asarray(o["centre_patient_mm"])
        u = np.asarray(o["direction_patient"])
        assert abs(heart.epicardium_at(centre[None], phase)[0]) < 1e-4
        assert heart.epicardium_at((centre + 2.0 * u)[None], phase)[0] > 0
        vessel = by_name[o["name"]]
        seg = np.diff(vessel.points_mm, axis=0)
        seg /= np.linalg.norm(seg, axis=1, keepdims=True)
        bent = np.einsum("ij,ij->i", seg[:-1], seg[1:]) < np.cos(np.radians(1.0))
        joints = np.concatenate([vessel.points_mm[1:-1][bent], [[np.inf] * 3]])
        others = [w for w in chest.vessels if w.name != vessel.name]
        t = np.arange(-o["outer_radius_mm"], o["outer_radius_mm"], 0.02)
        for length in np.arange(3.0, 60.0, 0.5):  # the first cross-section clear of bends and other lumens
            p, u = _along(vessel.points_mm, centre, length)
            across = np.cross(u, [0.0, 0.0, 1.0])  # horizontal: the profile stays in p's slice
            across /= np.linalg.norm(across)
            line = p + t[:, None] * across
            clear = min(w.lumen_distance(line).min() for w in others) > 0.5
            if clear and np.linalg.norm(joints - p, axis=1).min() > o["outer_radius_mm"] + 1.0:
                break
        else:
            raise AssertionError(f"{o['name']}: no straight stretch clear of other vessels within 60 mm")
        assert vessel.lumen_distance(p[None])[0] == pytest.approx(-vessel.lumen_radius_mm, abs=1e-6)
        prof = _profile(chest, p, across, phase, t)
        edges = _crossings(t, prof, 0.5 * (vessel.hu + ANATOMY_HU["vessel_wall"]))
        # across the axis of a tube tilted from the slice plane: the chord is the diameter
        diameter = edges[-1] - edges[0]
        assert abs(diameter - 2 * o["lumen_radius_mm"]) < 0.1, f"{o['name']}: {diameter:.2f} mm"
    aorta = next(o for o in truth["vessel_origins"] if o["name"] == "aorta")
    assert 25.0 <= 2 * aorta["lumen_radius_mm"] <= 35.0


def test_arteries_leave_at_their_valves(case):
    """The aorta's and the pulmonary trunk's origin is their valve plane (0.05 mm,
    normal within 0.5 degree): the true epicardium is capped there (outside 1 mm
    beyond it, inside 1 mm before it, where the lumen opens into the ventricle's
    own pool); beyond it the artery's lumen is not heart, and the other
    chambers' blood stays at least their wall thickness (less 0.05 mm) from it;
    the aorta's lumen stays more than 1.5 mm from the pulmonary trunk's, the
    right pulmonary artery's and the SVC's (measured 2.4, 1.9, 2.9 mm; the
    trunk's overlapped it by 12 mm before: the pulmonary valve lay inside the
    ascending aorta)."""
    c = case
    heart, chest = c["heart"], c["chest"]
    phase = c["truth"]["cardiac_phase"]
    origins = {o["name"]: o for o in c["truth"]["anatomy"]["vessel_origins"]}
    arteries = {v.name: v for v in chest.vessels if v.valve_mm is not None}
    assert set(arteries) == {"aorta", "pulmonary_trunk"}
    assert {r.name for r in heart.roots} == set(arteries)
    rng = np.random.default_rng(2)
    for name, v in arteries.items():
        o = origins[name]
        # the valve is placed at the gating target, the origin reported at phi_C* (the heart beats ~0.01 mm)
        np.testing.assert_allclose(o["centre_patient_mm"], v.valve_mm, atol=0.05)
        assert np.dot(o["direction_patient"], v.valve_normal) > np.cos(np.radians(0.5))
        n = v.valve_normal
        assert heart.epicardium_at((v.valve_mm + n)[None], phase)[0] > 0
        assert heart.epicardium_at((v.valve_mm - n)[None], phase)[0] < 0
        q = heart.to_reference((v.valve_mm - n)[None], phase) @ heart.local_axes.T
        assert heart.chambers_local(q)[f"{v.chamber}_blood"][0] < 0
        # the lumen beyond the valve (0.2 mm in: the lumen stands still, the heart beats 0.04 mm off it
        # between phi_C* and the gating target) is not heart; near it the other chambers' blood is not
        lo, hi = v.bbox(0.0)
        p = lo + rng.random((300_000, 3)) * (hi - lo)
        assert np.all(heart.epicardium_at(p[v.lumen_distance(p) < -0.2], phase) > 0)
        q = heart.to_reference(p, phase) @ heart.local_axes.T
        d = heart.root_distances(q)[name]
        parts = heart.chambers_local(q)
        for chamber, wall in (("lv", "left_ventricle"), ("rv", "right_ventricle"), ("la", "atria"), ("ra", "atria")):
            if chamber != v.chamber:
                near = (d > 0) & (d < WALL_THICKNESS_MM[wall] - 0.05)
                assert near.sum() > 1000 and np.all(parts[f"{chamber}_blood"][near] >= 0), chamber
    # a lumen's signed distance is exact inside and a lower bound beyond its valve plane: a sufficient test
    by_name = {v.name: v for v in chest.vessels}
    aorta = by_name["aorta"]
    lo, hi = aorta.bbox(0.0)
    p = lo + rng.random((1_000_000, 3)) * (hi - lo)
    p = p[aorta.lumen_distance(p) < 0]
    for other in ("pulmonary_trunk", "right_pulmonary_artery", "superior_vena_cava"):
        assert by_name[other].lumen_distance(p).min() > 1.5, other


# ----------------------------------------------------------------------- truth
def test_truth_surface_sampler_is_exact_and_moves_with_the_heart(case):
    """sample_surface points are on F = 0 (1e-6 mm) at any (phi_C, phi_R), their
    surface_distance is 0 (0.02 mm: tangent-plane error of ~1 mm sampling),
    points 1 mm out along the normal are 1 mm away (0.05 mm); the surface beats
    (several mm between systole and diastole) and breathes (moves with T_resp)."""
    heart = case["heart"]
    rng = np.random.default_rng(1)
    for phase_c, phase_r in ((case["truth"]["cardiac_phase"], None), (0.25, 0.8)):
        pts, n = heart.sample_surface(phase_c, phase_r)
        assert len(pts) > 20000
        assert np.abs(heart.epicardium_at(pts, phase_c, phase_r)).max() < 1e-6
        sub = rng.choice(len(pts), 500, replace=False)
        d0 = heart.surface_distance(pts[sub], phase_c, phase_r)
        assert np.abs(d0).max() < 0.02
        # away from the narrow creases (where 1 mm reaches another part of the surface)
        d1 = heart.surface_distance(pts[sub] + n[sub], phase_c, phase_r)
        dm = heart.surface_distance(pts[sub] - 0.5 * n[sub], phase_c, phase_r)
        assert np.median(np.abs(d1 - 1.0)) < 0.01 and np.percentile(np.abs(d1 - 1.0), 90) < 0.05
        assert np.all(dm < 0)
    # (u, v) rays land on the surface too
    u, v = rng.random(200), rng.random(200)
    assert np.abs(heart.epicardium_reference(heart.reference_points(u, v))).max() < 1e-6
    diastole, _ = heart.sample_surface(0.7, 0.3)
    systole, _ = heart.sample_surface(0.3, 0.3)
    breath, _ = heart.sample_surface(0.7, 0.6)
    assert np.percentile(np.linalg.norm(diastole - systole, axis=1), 90) > 3.0
    # respiration: the rigid T_resp and the non-rigid respiratory stretch (both
    # exact), plus the heartbeat's small respiratory modulation
    T = heart.T_resp(0.6)
    stretched = diastole + heart.resp_stretch(heart.to_reference(diastole, 0.7, 0.3), 0.6)
    moved = stretched @ T[:3, :3].T + T[:3, 3]
    assert np.linalg.norm(T[:3, 3]) > 3.0
    assert np.percentile(np.linalg.norm(breath - moved, axis=1), 95) < 0.5


def test_ct_epicardium_lies_on_the_truth(case):
    """Where the true epicardium (at each slice's own phase) crosses a slice, the
    noise-free image on the file's grid crosses the fat/myocardium midpoint
    (0 HU) within a voxel along the in-plane normal (measured: within half a
    pixel); the vessels' mouths (lumen within 5 mm) are skipped."""
    c = case
    heart, chest = c["heart"], c["chest"]
    pixel = c["xs"][1] - c["xs"][0]
    errors = []
    for k in range(2, len(c["zs"]), 9):
        z = c["zs"][k]
        phase = c["truth"]["slice_cardiac_phase"][k]
        pts, n = heart.sample_surface(phase)
        near = (np.abs(pts[:, 2] - z) < 0.5) & (np.linalg.norm(n[:, :2], axis=1) > 0.7)
        near &= chest.vessel_distance_mm(pts) > 5.0
        if not near.any():
            continue
        on, residual = _on_plane(heart, pts[near][::3], n[near][::3], z, phase)
        assert residual.max() < 1e-6
        pts, n = on, n[near][::3]
        img = render_slice(chest, z_mm=float(z), phase_c=phase, xs_mm=c["xs"], ys_mm=c["ys"])
        np.testing.assert_allclose(img, c["hu"][k], atol=5 * NOISE_HU)  # the file is this plus noise
        for q, d in zip(pts, n):
            d = d[:2] / np.linalg.norm(d[:2])
            t = np.linspace(-2 * pixel, 2 * pixel, 401)
            line = q[:2] + t[:, None] * d
            vals = map_coordinates(img, [(line[:, 1] - c["ys"][0]) / pixel, (line[:, 0] - c["xs"][0]) / pixel],
                                   order=1)
            cross = _crossings(t, vals, 0.0)
            assert cross.size, f"no fat/myocardium crossing near {q}"
            errors.append(cross[np.argmin(np.abs(cross))])
    errors = np.abs(errors)
    print(f"{errors.size} points, max {errors.max():.3f} mm, rms {np.sqrt(np.mean(errors**2)):.3f} mm")
    assert errors.size > 300
    assert errors.max() < pixel


# ----------------------------------------------------------- files and options
def test_tight_fov_no_markers_and_stent_are_in_the_files(case):
    c = case
    truth, cts = c["truth"], c["cts"]
    # tight FOV: 200 mm over 128 columns, centred on the heart, through the lungs
    assert float(cts[0].PixelSpacing[0]) == pytest.approx(FOV_MM / 128)
    assert truth["geometry"]["pixel_mm"] == pytest.approx(FOV_MM / 128)
    centre = 0.5 * (c["xs"][0] + c["xs"][-1]), 0.5 * (c["ys"][0] + c["ys"][-1])
    np.testing.assert_allclose(centre, truth["config"]["heart_origin_mm"][:2], atol=0.1)
    right_edge = c["hu"][:, :, 0]  # patient right, 100 mm from the heart: through the lung
    assert np.mean(np.abs(right_edge - HU["lung"]) < 4 * NOISE_HU) > 0.3
    assert truth["anatomy"]["fov_mm"] == FOV_MM
    # no skin markers: nothing metal outside the stent, no fiducials in the truth
    assert truth["fiducials_patient_mm"] == [] and truth["anatomy"]["markers"] is False
    stent = truth["anatomy"]["stent"]
    lo = np.minimum(stent["start_patient_mm"], stent["end_patient_mm"]) - stent["radius_mm"] - 3
    hi = np.maximum(stent["start_patient_mm"], stent["end_patient_mm"]) + stent["radius_mm"] + 3
    K, J, I = np.nonzero(c["hu"] > 1200)
    p = np.stack([c["xs"][I], c["ys"][J], c["zs"][K]], axis=1)
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    assert inside.all(), f"metal outside the stent at {p[~inside][:3]}"
    # the stent: metal in (nearly) every slice it spans, on its cylinder
    z0, z1 = sorted((stent["start_patient_mm"][2], stent["end_patient_mm"][2]))
    spans = (c["zs"] > z0 + 1) & (c["zs"] < z1 - 1)
    per_slice = [(c["hu"][k] > 1200).sum() for k in np.nonzero(spans)[0]]
    assert np.mean(np.array(per_slice) > 0) > 0.9
    r = np.linalg.norm(p[:, :2] - np.asarray(stent["start_patient_mm"])[:2], axis=1)
    assert np.all(np.abs(r - stent["radius_mm"]) < 2 * (c["xs"][1] - c["xs"][0]))


def test_truth_json_anatomy_block(case):
    a = case["truth"]["anatomy"]
    assert a["heart"] == "chambers"
    assert a["wall_thickness_mm"] == WALL_THICKNESS_MM
    assert abs(a["epicardium"]["phase_c"] - case["truth"]["cardiac_phase"]) < 1e-12
    names = [v["name"] for v in a["vessels"]]
    assert "descending_aorta" in names and len(names) == len(set(names))
    axes = np.asarray(a["local_axes_patient"])
    np.testing.assert_allclose(axes.T @ axes, np.eye(3), atol=1e-12)
    # the long axis is the heart's z: apex left-anterior-inferior in LPS
    assert axes[0, 2] < 0 and axes[1, 2] > 0 and axes[2, 2] > 0


def test_no_markers_needs_no_session_and_bad_fov(tmp_path, capsys):
    with pytest.raises(PhantomError, match="without skin markers.*session=False"):
        make_phantom(tmp_path / "a", preset="human", markers=False)
    assert main(["phantom", str(tmp_path / "b"), "--no-markers"]) != 0
    assert "--no-session" in capsys.readouterr().err
    with pytest.raises(PhantomError, match=r"fov_mm \(--fov-mm\) must be within 100..500 mm"):
        make_phantom(tmp_path / "c", fov_mm=50.0, session=False)
    with pytest.raises(PhantomError, match="anatomy heart must be one of spheroid, chambers"):
        make_phantom(tmp_path / "d", anatomy="cube", session=False)
    # a field of view that leaves staples out, with a session to touch them (the model found 6 of 9 at 170 mm):
    # refused before anything is written, naming the narrowest that shows them all
    assert main(["phantom", str(tmp_path / "e"), "--fov-mm", "170"]) != 0
    assert "leaves skin staples out of the CT" in capsys.readouterr().err
    with pytest.raises(PhantomError, match=r"give --fov-mm 176 or more, or pass --no-session"):
        make_phantom(tmp_path / "e", fov_mm=175.0)
    assert not any((tmp_path / n).exists() and any((tmp_path / n).iterdir()) for n in "abcde")


def test_paper_presets_are_unchanged():
    """The six presets (and default) keep the spheroid, their config dict (so their
    UIDs and bytes) and their truth keys; ``human`` is the chambers preset."""
    for name, config in PRESETS.items():
        if name == "human":
            assert isinstance(make_heart(config), ChamberHeart)
            assert config.to_dict()["anatomy"]["heart"] == "chambers"
            continue
        heart = make_heart(config)
        assert type(heart) is AnalyticHeart
        assert "anatomy" not in config.to_dict()
        assert config_from_dict(json.loads(json.dumps(config.to_dict()))) == config
    spheroid_stent = make_config("default", anatomy=Anatomy(stent=True))
    assert config_from_dict(json.loads(json.dumps(spheroid_stent.to_dict()))) == spheroid_stent
    assert dataclasses.replace(PRESETS["human"], anatomy=Anatomy()).to_dict().keys() == PRESETS[
        "default"].to_dict().keys()


def test_phantom_imports_nothing_it_tests():
    """No module of heartreg.phantom imports imaging, modeling or registration,
    statically (import statements) or at run time (a fresh interpreter)."""
    forbidden = {"imaging", "modeling", "registration"}
    folder = Path(__file__).resolve().parents[2] / "heartreg" / "phantom"
    for path in folder.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                assert name.split(".")[0] not in forbidden, f"{path.name} imports {name}"
    code = ("import sys, heartreg.phantom, heartreg.phantom.anatomy, heartreg.phantom.generate;"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in {'imaging','modeling','registration'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.strip() == "[]"
