"""Accuracy of ``modeling`` on the anatomical phantom (four chambers, great vessels).

Writes (``--reuse``: once) a ``human``-preset phantom case (``--anatomy chambers``)
into ``bench/out/anatomy/<size>/``, builds the heart model from its CT with the
library exactly as ``heartreg model`` does, and reports against the phantom's
exact epicardium (without the great vessels) at the volume's phase phi_C*:

- mesh -> truth: signed distance of every model vertex to the true epicardium
  (mean / p95 / max of its absolute value), over the whole mesh, away from
  the vessels' mouths (farther than the vessel's outer radius + 3 mm from each
  origin), and off every vessel (farther than its outer radius + 3 mm from its
  centreline: the chambers alone);
- truth -> mesh: distance of dense true-surface samples (~0.5 mm apart) to the
  mesh (nearest of 400k area-uniform mesh samples, so within ~0.1 mm);
- per great vessel: how far past its origin the mesh still runs up the vessel
  (the largest distance beyond the mouth plane of a mesh surface sample inside
  the vessel's lumen less 1 mm, minus the same for the true surface, which bulges
  a little over a vein's mouth), and the largest truth -> mesh gap over the
  mouth (> 0 when the cut went below the origin into the heart; each true
  point counts for the nearest origin only, so neighbouring caps stay apart).

The aorta's and the pulmonary trunk's origin is their valve plane (the
phantom's true epicardium is capped there: :mod:`heartreg.phantom.anatomy`),
the veins' where they leave the chambers' outer surface.  Issue 9's targets
(full size): mean <= 0.3 mm, p95 <= 0.8 mm, every vessel cut within 5 mm of
its origin.  This is a measurement, not a test: it prints a table,
writes ``anatomy_accuracy.json`` beside the case and exits 0 even when the
targets are missed (1 only when the model cannot be built at all).

    .venv/bin/python bench/anatomy_accuracy.py --size sample
    .venv/bin/python bench/anatomy_accuracy.py --size full [--fov-mm 200] [--stent] [--no-markers]

Measured (seed 0, valve-capped truth): full size mesh -> truth 0.14 / 0.55 mm
(mean / p95), truth -> mesh 0.32 / 1.50 mm, mouths: aorta 2.3 mm (its root's
35 mm well kept down to the valve: its walls within 1.5 mm of the true ones,
which "mesh past origin", the surface inside the lumen less 1 mm, counts as
26 mm up the well), pulmonary trunk 2.2 (1.3 mm past the valve at most), SVC
4.8, IVC 1.4, pulmonary veins 2.4-3.6; sample size 0.18 / 0.51 mm, aorta 2.8,
trunk 5.0, SVC 4.7, IVC 3.0, veins 2.2-3.9.  Before the outflow tract thinner
than the bridge opening's ball was given back (:mod:`modeling.outflow`) the
trunk was closed inside it: 9.6 mm at full size (truth -> mesh 0.50 / 2.34
mm, mesh -> truth p95 0.57 mm), 12.0 at sample size.  Before session 14 the stub trim
removed the well's floor and lidded it at its rim (full size 0.14 / 0.61 mm,
truth -> mesh 0.94 / 6.49 mm, aorta 14.3, trunk 10.5, SVC 5.3).  With the
truth capped at the RVOT's outer surface (before the valve planes) full size
gave 0.05 / 0.12 mm and 19 mm at both arteries.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from heartreg.phantom import heart_from_truth, make_phantom  # noqa: E402

#: vertices farther than this beyond a vessel's outer radius from its origin
#: are "the epicardium proper"
MOUTH_CLEARANCE_MM = 3.0


def _case(out: Path, size: str, seed: int, fov_mm, stent: bool, markers: bool, reuse: bool) -> dict:
    truth_path = out / "truth.json"
    if reuse and truth_path.exists():
        truth = json.loads(truth_path.read_text())
        a = truth.get("anatomy", {})
        if (truth["size"], truth["seed"], a.get("fov_mm"), "stent" in a, a.get("markers", True)) == (
            size, seed, fov_mm, stent, markers,
        ):
            return truth
    t0 = time.perf_counter()
    truth = make_phantom(out, preset="human", size=size, seed=seed, session=False, overwrite=True,
                         progress=True, fov_mm=fov_mm, stent=stent or None, markers=markers)
    print(f"phantom written in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return truth


def _to_line(p, line) -> np.ndarray:
    """Distance (mm) of points ``p`` (n, 3) to a polyline ``line`` (m, 3)."""
    dist = np.full(len(p), np.inf)
    for a, b in zip(line[:-1], line[1:]):
        ab = b - a
        t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
        dist = np.minimum(dist, np.linalg.norm(p - (a + t[:, None] * ab), axis=1))
    return dist


def measure(case_dir: Path, truth: dict, *, faces: int = 20000) -> dict:
    """Build the model of ``case_dir/ct`` and measure it against ``truth``."""
    import trimesh
    from scipy.spatial import cKDTree

    from imaging import load_study
    from modeling import build_heart_model

    t0 = time.perf_counter()
    volume = load_study(case_dir / "ct")
    expected = 9 if truth.get("anatomy", {}).get("markers", True) else None
    build = build_heart_model(
        volume, cardiac_phase=truth["cardiac_phase"], cardiac_phase_source="truth",
        target_faces=faces, expected_fiducials=expected,
    )
    build_s = time.perf_counter() - t0
    model = build.model
    T = np.linalg.inv(model.T_heart_from_patient)
    verts = model.mesh.vertices @ T[:3, :3].T + T[:3, 3]
    heart = heart_from_truth(truth)
    phase_c = truth["anatomy"]["epicardium"]["phase_c"]
    phase_r = truth["anatomy"]["epicardium"]["phase_r"]
    d = heart.surface_distance(verts, phase_c, phase_r)
    origins = truth["anatomy"]["vessel_origins"]
    away = np.ones(len(verts), bool)
    for o in origins:
        c = np.asarray(o["centre_patient_mm"])
        away &= np.linalg.norm(verts - c, axis=1) > o["outer_radius_mm"] + MOUTH_CLEARANCE_MM

    # vertices off every vessel: farther than its outer wall + 3 mm from its centreline
    off_vessels = np.ones(len(verts), bool)
    centrelines = {v["name"]: np.asarray(v["centreline_patient_mm"]) for v in truth["anatomy"]["vessels"]}
    for v in truth["anatomy"]["vessels"]:
        outer = v["lumen_radius_mm"] + v["wall_mm"]
        off_vessels &= _to_line(verts, centrelines[v["name"]]) > outer + MOUTH_CLEARANCE_MM

    pts, _ = heart.sample_surface(phase_c, phase_r)
    tm = trimesh.Trimesh(verts, model.mesh.faces, process=False)
    samples, _ = trimesh.sample.sample_surface_even(tm, 400_000, seed=0)
    back, _ = cKDTree(samples).query(pts, k=1)

    # each true surface point belongs to the cap of the origin nearest to it (the aortic and pulmonary caps
    # lie 12 mm apart: the aorta's cylinder would otherwise also count the pulmonary cap)
    centres = np.asarray([o["centre_patient_mm"] for o in origins])
    owner = cKDTree(centres).query(pts, k=1)[1]
    vessels = []
    for index, o in enumerate(origins):
        c = np.asarray(o["centre_patient_mm"])
        u = np.asarray(o["direction_patient"])
        radius = o["lumen_radius_mm"] - 1.0  # the lumen: an artery's true surface beyond its valve is its lumen's wall
        line = centrelines[o["name"]]

        def extent(p, c=c, u=u, radius=radius, line=line):
            """How far past the mouth plane points of ``p`` run inside the vessel's lumen (along a bent one too)."""
            s = (p - c) @ u
            near = s > 0
            near[near] = _to_line(p[near], line) <= radius
            return float(s[near].max()) if near.any() else 0.0

        s_t = (pts - c) @ u
        r_t = np.linalg.norm((pts - c) - s_t[:, None] * u, axis=1)
        mouth = (r_t <= o["lumen_radius_mm"]) & (np.abs(s_t) <= MOUTH_CLEARANCE_MM + 2.0) & (owner == index)  # its cap
        vessels.append({
            "name": o["name"],
            "lumen_diameter_mm": 2 * o["lumen_radius_mm"],
            # the surface, not the vertices: a lid across a mouth has no vertex inside
            "mesh_past_origin_mm": extent(samples) - extent(pts),
            "gap_over_mouth_mm": float(back[mouth].max()) if mouth.any() else float("nan"),
        })
    absd = np.abs(d)
    return {
        "size": truth["size"],
        "seed": truth["seed"],
        "fov_mm": truth["anatomy"]["fov_mm"],
        "stent": "stent" in truth["anatomy"],
        "markers": truth["anatomy"]["markers"],
        "build_s": build_s,
        "notes": list(build.notes),
        "faces": int(len(model.mesh.faces)),
        "mesh_to_truth_mm": {"mean": float(absd.mean()), "p95": float(np.percentile(absd, 95)),
                             "max": float(absd.max())},
        "mesh_to_truth_away_from_mouths_mm": {
            "mean": float(absd[away].mean()), "p95": float(np.percentile(absd[away], 95)),
            "fraction_of_vertices": float(away.mean())},
        "mesh_to_truth_off_vessels_mm": {
            "mean": float(absd[off_vessels].mean()), "p95": float(np.percentile(absd[off_vessels], 95)),
            "fraction_of_vertices": float(off_vessels.mean())},
        "truth_to_mesh_mm": {"mean": float(back.mean()), "p95": float(np.percentile(back, 95)),
                             "max": float(back.max())},
        "fiducials_found": int(len(build.fiducials.centres_patient_mm)),
        "vessels": vessels,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="sample", choices=("sample", "full"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fov-mm", type=float, default=None)
    ap.add_argument("--stent", action="store_true")
    ap.add_argument("--no-markers", action="store_true")
    ap.add_argument("--out", type=Path, default=HERE / "out" / "anatomy")
    ap.add_argument("--reuse", action="store_true",
                    help="reuse the case written by an earlier run with the same options (same phantom code only)")
    args = ap.parse_args(argv)
    tag = args.size + (f"-fov{args.fov_mm:g}" if args.fov_mm else "") + ("-stent" if args.stent else "") + (
        "-nomarkers" if args.no_markers else "")
    case = args.out / tag
    truth = _case(case, args.size, args.seed, args.fov_mm, args.stent, not args.no_markers, args.reuse)
    try:
        r = measure(case, truth)
    except Exception as exc:  # a measurement: report why the model could not be built
        print(f"model not built: {type(exc).__name__}: {exc}")
        return 1
    (case / "anatomy_accuracy.json").write_text(json.dumps(r, indent=1) + "\n")
    m, a, b = r["mesh_to_truth_mm"], r["mesh_to_truth_away_from_mouths_mm"], r["truth_to_mesh_mm"]
    print(f"anatomical phantom ({tag}, seed {args.seed}), model built in {r['build_s']:.1f} s, {r['faces']} faces")
    print(f"  mesh -> true epicardium   mean {m['mean']:.2f}  p95 {m['p95']:.2f}  max {m['max']:.1f} mm"
          "   (target mean <= 0.3, p95 <= 0.8)")
    print(f"  same, away from mouths    mean {a['mean']:.2f}  p95 {a['p95']:.2f} mm"
          f"  ({100 * a['fraction_of_vertices']:.0f} % of vertices)")
    o = r["mesh_to_truth_off_vessels_mm"]
    print(f"  same, off every vessel    mean {o['mean']:.2f}  p95 {o['p95']:.2f} mm"
          f"  ({100 * o['fraction_of_vertices']:.0f} % of vertices)")
    print(f"  true epicardium -> mesh   mean {b['mean']:.2f}  p95 {b['p95']:.2f}  max {b['max']:.1f} mm")
    print(f"  skin fiducials found      {r['fiducials_found']}")
    print("  vessel                          lumen (mm)  mesh past origin (mm)  gap over mouth (mm)   (target <= 5)")
    for v in r["vessels"]:
        print(f"  {v['name']:32s} {v['lumen_diameter_mm']:5.1f}  {v['mesh_past_origin_mm']:16.1f}"
              f"  {v['gap_over_mouth_mm']:18.1f}")
    for note in r["notes"]:
        print(f"  note: {note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
