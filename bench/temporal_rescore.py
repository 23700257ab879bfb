"""The final transform from phi_R*'s uncertainty: re-scored on a ``heartreg evaluate-temporal`` grid (issue 12).

``heartreg register`` takes the final transform at the shape estimator's argmin,
``T_ICP(phi_R*)``.  Under a squared-displacement loss the optimal estimate is
the posterior mean of the transform; this script scores averages over the
phase's uncertainty against the argmin on the grid's own cases, from the
sweep evidence each case saved (no ICP is run again; every case's argmin row
is checked to be the stored one):

- ``argmin``: ``T(phi_R*)``, the default;
- ``bag``: the rigid average of ``T(phi_b)`` over the bootstrap's 500 argmins
  (phi: their circular median);
- ``posterior``: the rigid average of ``T(phi)`` over the sweep weighted by
  ``exp(-(J - min J) / (2 s))``, ``s`` = 1 (the cost as a likelihood), the
  interval's sandwich scale ``max(1, V / H)``, or that times the Birge ratio
  (phi: the weights' circular median);
- ``curv_*``: the same with the map's curvature offsets removed from the
  heart term (``estimate_phase(curvature_per_mm=...)``), whose coverage is
  reported beside.

The rigid average: the mean of the map's vertices moved by each ``T``, then
the Kabsch fit of the vertices onto it.

Usage::

    .venv/bin/python -m heartreg.cli evaluate-temporal -o OUT --seeds 12 --workers 2
    .venv/bin/python bench/temporal_rescore.py OUT [--json OUT/rescore.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrcore.errors import UsageError  # noqa: E402
from hrcore.geometry import kabsch  # noqa: E402
from heartreg.temporal_eval import CRITERIA  # noqa: E402
from heartreg.temporal_evidence import read_evidence, shape_from_evidence, transform_error  # noqa: E402
import registration.temporal as temporal  # noqa: E402
from registration.phase_estimate import wrap_phase  # noqa: E402


def rigid_average(Ts, weights, vertices):
    """The rigid transform whose moved ``vertices`` lie closest to the ``weights``-mean of each ``T``'s."""
    w = np.asarray(weights, dtype=float)
    keep = w > 0
    moved = np.einsum("aij,vj->avi", Ts[keep, :3, :3], vertices) + Ts[keep, None, :3, 3]
    target = np.tensordot(w[keep] / w[keep].sum(), moved, axes=1)
    return kabsch(vertices[None], target[None])[0]


def circular_median(phases, weights, about):
    """The weighted median of ``phases`` unwrapped about ``about`` (cycles, in [0, 1))."""
    x = wrap_phase(np.asarray(phases) - about)
    order = np.argsort(x)
    c = np.cumsum(np.asarray(weights, dtype=float)[order])
    return float(about + x[order][np.searchsorted(c, 0.5 * c[-1])]) % 1.0


def sandwich_scale(args):
    """``J - min J`` and ``max(1, V / H)`` as :func:`registration.temporal._sandwich_interval` computes them
    from its arguments, and the Birge ratio it was given."""
    phases, J, units, best, _, step, inflation = args
    x = wrap_phase(phases - phases[best])
    win = np.abs(x) <= max(temporal.WINDOW, 2.01 * step)
    X = np.stack([np.ones(int(win.sum())), x[win], x[win] ** 2], axis=1)
    coef = np.linalg.lstsq(X, np.column_stack([J[win], units[win]]), rcond=None)[0]
    curvature, slopes = coef[2, 0], coef[1, 1:] / 2
    u = slopes.size
    meat = float(np.sum((slopes - slopes.mean()) ** 2) * u / (u - 1)) if u > 1 else 0.0
    scale = max(1.0, meat / curvature) if curvature > 0 else np.inf
    return J - J.min(), scale, max(1.0, inflation)


def score_case(out, case):
    ev = read_evidence(out, case["preset"], case["seed"])
    stored = next(r for r in case["estimates"] if r["estimator"] == "shape")
    phases, Ts, v = ev["phases"], ev["T_heart_from_probe"], ev["vertices_all_mm"]
    usable = np.arange(phases.size - 1)  # the sweep's ends are one phase (estimate_phase keeps the first)
    ph, Tu = phases[usable] % 1.0, Ts[usable]
    variants, covered = {}, {}
    for tag, options in (("", {}), ("curv_", {"curvature_per_mm": ev["curvature_per_mm"]})):
        with mock.patch.object(temporal, "_sandwich_interval", wraps=temporal._sandwich_interval) as spy:
            est = shape_from_evidence(ev, **options)
        J, scale, birge = sandwich_scale(spy.call_args.args)  # register_session's call: all positional
        covered[tag] = est.contains(case["phase_true"])
        variants[tag + "argmin"] = (Ts[est.index], est.respiration_phase)
        if not tag:
            if not (abs(est.respiration_phase - stored["phase"]) < 1e-12
                    and abs(est.transform_mm - stored["transform_90_mm"]) < 1e-9):
                raise SystemExit(f"{case['preset']} s{case['seed']}: the evidence does not give the stored row "
                                 f"again ({est.respiration_phase} vs {stored['phase']})")
        counts = np.bincount(np.rint(est.bootstrap_phases * usable.size).astype(int) % usable.size,
                             minlength=usable.size)
        variants[tag + "bag"] = (rigid_average(Tu, counts, v), circular_median(ph, counts, est.respiration_phase))
        for name, s in (("post_1", 1.0), ("post_sandwich", scale), ("post_sandwich_birge", scale * birge)):
            w = np.exp(-J / (2 * min(s, 1e9)))
            variants[tag + name] = (rigid_average(Tu, w, v), circular_median(ph, w, est.respiration_phase))
    truth = case["phase_true"]
    at_truth = int(np.argmin(np.abs(wrap_phase(ph - truth))))
    rows = {}
    for name, (T, phase) in variants.items():
        mm, deg = transform_error(T, ev)
        rows[name] = {"phase": phase, "phase_error": float(wrap_phase(phase - truth)), "mm": mm, "deg": deg}
    return {"case": f"{case['preset']}_s{case['seed']}", "phase_true": truth, "covered": covered[""],
            "curv_covered": covered["curv_"], "interval": [stored["interval_low"], stored["interval_high"]],
            "at_truth_mm_deg": transform_error(Tu[at_truth], ev), "variants": rows}


def ok_phase(r):
    return abs(r["phase_error"]) <= CRITERIA["phase"] + 1e-9


def ok_T(r):
    return r["mm"] <= CRITERIA["transform_mm"] and r["deg"] <= CRITERIA["transform_deg"]


def report(records) -> str:
    n = len(records)
    lines = [f"| variant ({n} cases) | phi_R* within ±0.05 | final T within 2 mm and 2° | 90 % interval covers "
             "truth | median phase error | median T error | mean T error |", "|---|---|---|---|---|---|---|"]
    for name in records[0]["variants"]:
        rs = [r["variants"][name] for r in records]
        cov = sum(r["curv_covered" if name.startswith("curv_") else "covered"] for r in records)
        lines.append(
            f"| {name} | {sum(map(ok_phase, rs))}/{n} | {sum(map(ok_T, rs))}/{n} | {cov}/{n} "
            f"| {np.median([abs(r['phase_error']) for r in rs]):.3f} "
            f"| {np.median([r['mm'] for r in rs]):.2f} mm, {np.median([r['deg'] for r in rs]):.2f}° "
            f"| {np.mean([r['mm'] for r in rs]):.2f} mm |")
    names = [k for k in records[0]["variants"] if not k.startswith("curv_")]
    lines += ["", "Cases any of " + ", ".join(names) + " misses (phase, mm, deg; * = outside 2 mm / 2°):", "",
              "| case | truth | interval | " + " | ".join(names) + " | T at the truth's phase |",
              "|---|---|---|" + "---|" * (len(names) + 1)]
    for r in records:
        if all(ok_T(r["variants"][k]) and ok_phase(r["variants"][k]) for k in names):
            continue
        cells = [f"{v['phase']:.2f}, {v['mm']:.2f}, {v['deg']:.2f}{'' if ok_T(v) else ' *'}"
                 for v in (r["variants"][k] for k in names)]
        lines.append(f"| {r['case']} | {r['phase_true']:.2f} | [{r['interval'][0]:.2f}, {r['interval'][1]:.2f}]"
                     f"{'' if r['covered'] else ' (misses)'} | " + " | ".join(cells)
                     + f" | {r['at_truth_mm_deg'][0]:.2f}, {r['at_truth_mm_deg'][1]:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="an evaluate-temporal output folder")
    parser.add_argument("--json", type=Path, help="write every case's variants here")
    a = parser.parse_args(argv)
    t = time.perf_counter()
    cases = [json.loads(p.read_text()) for p in sorted((a.out / "cases").glob("*.json"))]
    if not cases:
        print(f"no case in {a.out / 'cases'}: run heartreg evaluate-temporal -o {a.out} first", file=sys.stderr)
        return 2
    try:
        records = [score_case(a.out, c) for c in cases]
    except UsageError as exc:  # an older grid's evidence, a case without its .npz
        print(exc, file=sys.stderr)
        return 2
    print(report(records))
    print(f"({len(records)} cases re-scored in {time.perf_counter() - t:.0f} s)")
    if a.json:
        a.json.write_text(json.dumps(records, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
