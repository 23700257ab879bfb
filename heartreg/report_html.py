"""One self-contained HTML page per run: tables and the PNGs embedded (base64)."""

from __future__ import annotations

import base64
import itertools
import html
from pathlib import Path

import numpy as np

from hrcore.geometry import apply_to_points
from imaging.files import write_text_atomic

__all__ = ["html_table", "registration_view_html", "trust_html", "write_html_report"]

_STYLE = """
body { font-family: -apple-system, Segoe UI, Helvetica, Arial, sans-serif; margin: 2em auto;
       max-width: 1100px; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ddd; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: .8em 0; font-size: .92em; }
th, td { border: 1px solid #ccc; padding: .3em .6em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.ok { color: #1a7f37; font-weight: 600; } .miss { color: #b42318; font-weight: 600; }
img { max-width: 100%; border: 1px solid #eee; margin: .5em 0; }
.note { color: #555; font-size: .9em; }
.trust { border-left: 6px solid; padding: .4em .9em; margin: 1em 0; }
.trust-ok { border-color: #1a7f37; background: #eef8f0; }
.trust-caution { border-color: #b7791f; background: #fdf6e7; }
.trust-poor { border-color: #b42318; background: #fdeeee; }
"""


def _cell(value) -> str:
    if isinstance(value, bool):
        return '<td class="ok">yes</td>' if value else '<td class="miss">no</td>'
    if isinstance(value, (float, np.floating)):
        return f'<td class="num">{value:.4g}</td>'
    if isinstance(value, (int, np.integer)):
        return f'<td class="num">{value}</td>'
    return f"<td>{html.escape(str(value))}</td>"


def html_table(header, rows) -> str:
    """An HTML table; booleans render as green yes / red no."""
    out = ["<table><tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>"]
    for row in rows:
        out.append("<tr>" + "".join(_cell(v) for v in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _image(path, caption: str) -> str:
    path = Path(path)
    if not path.exists():
        return f'<p class="note">{html.escape(caption)}: not drawn.</p>'
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{data}"><figcaption class="note">{html.escape(caption)}</figcaption></figure>'


def registration_view_html(model, reg, *, element_id: str = "view3d") -> str:
    """The interactive 3-D view of a registration: the model's surface (heart frame),
    the registered points by the final and by the fiducial registration, and the
    robot's track (its attachment points in recording order)."""
    from heartreg.view3d import Layer, viewer_html

    final = apply_to_points(reg.T_heart_from_probe, reg.points_probe_mm)
    seed = apply_to_points(reg.T0_heart_from_probe, reg.points_probe_mm)
    centre = model.mesh.vertices.mean(axis=0)
    towards = final.mean(axis=0) - centre
    towards[2] *= 0.35  # mostly from the side, a little from the points' end
    layers = [
        Layer("robot's track (attachment points in recording order)", _on_surface(model.mesh.vertices, final),
              "#3b3b9a", kind="line", size_px=2.5),
        Layer("registered points, fiducial registration T0", seed, "#f2a93b", size_px=7.0, visible=False),
        Layer(f"registered points, spatiotemporal registration (phi_R* = {reg.respiration_phase:.2f})", final, "#22a35a",
              size_px=10.0),
    ]
    return viewer_html(
        model.mesh.vertices, model.mesh.faces, layers=layers, element_id=element_id,
        surface_label=f"heart model at phi_C* = {model.cardiac_phase:.2f} ({model.mesh.n_faces} faces)",
        frame_note="Heart frame (mm): x anterior, z from apex to base. Points: motion-model positions at the "
                   "image phases (phi_C*, phi_R*), mapped by each registration.",
        view_from=towards,
    )


def _on_surface(vertices, points, steps: int = 16):
    """A polyline through ``points`` that follows the surface: each segment cut in
    ``steps`` and every cut moved to the nearest surface vertex."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return points
    t = np.linspace(0.0, 1.0, steps, endpoint=False)[:, None]
    cuts = np.concatenate([a + t * (b - a) for a, b in itertools.pairwise(points)] + [points[-1:]])
    _, nearest = cKDTree(vertices).query(cuts)
    path = vertices[nearest]
    path[::steps] = points  # the points themselves stay where they are
    return path


def trust_html(trust) -> str:
    """How far to trust the registration (:class:`registration.plausibility.Trust`), as a box."""
    level = trust.level.value
    words = {"ok": "no weakness found", "caution": "usable, but check it",
             "poor": "may be several mm or degrees off"}[level]
    items = "".join(f"<li><b>{html.escape(r.level.value)}</b>: {html.escape(r.message)}</li>" for r in trust.reasons)
    return (f'<div class="trust trust-{level}"><b>Trust in this registration: {level.upper()}</b> '
            f"({words}).{'<ul>' + items + '</ul>' if items else ''}</div>")


def write_html_report(run, path, *, truth_rows=None, title: str = "heartreg run") -> Path:
    """Write the run's report page.

    Parameters
    ----------
    run : heartreg.pipeline.PipelineResult
    path : path of the ``.html`` file
    truth_rows : list of rows, optional
        ``(quantity, recovered, truth, error, tolerance, within)`` rows (the demo).
    """
    report, build, reg = run.phase_report, run.model_build, run.registration
    model = build.model
    out = run.out_dir
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_STYLE}</style></head><body><h1>{html.escape(title)}</h1>"]
    parts.append(
        "<p>Beating-heart registration for organ-mounted robots (Wood et al. 2018): cardiac phase of the "
        "gated CT, heart model in the heart-centric frame, and spatiotemporal registration of the robot's "
        "points. Frames: patient = DICOM LPS, heart = fitted heart-centric frame; mm, phases in [0, 1).</p>"
    )
    parts.append(trust_html(reg.trust))
    parts.append("<h2>Overview: the registration in 3-D</h2>")
    parts.append(registration_view_html(model, reg))
    if truth_rows:
        parts.append("<h2>Recovered against the phantom's truth</h2>")
        parts.append(html_table(["quantity", "recovered", "truth", "error", "tolerance", "within"], truth_rows))

    parts.append("<h2>1. Cardiac phase of the CT (paper Fig. 4)</h2>")
    parts.append(html_table(["quantity", "value"], [
        ("R-peak source", report.source), ("clock", report.clock), ("slices", report.n_slices),
        ("volume phase phi_C* (mean)", report.volume_cardiac_phase),
        ("circular mean", report.circular_mean_phase),
        ("fraction in 0.6-0.8", report.fraction_in_window), ("jumps", len(report.jumps)),
    ]))
    parts.append(_image(out / "phases" / "phases.png", "phase per slice; motion-free window shaded"))

    parts.append("<h2>2. Heart model (paper Fig. 5)</h2>")
    e = model.frame.euler_xyz_deg
    parts.append(html_table(["quantity", "value"], [
        ("mask", build.mask_source), ("faces", int(model.mesh.faces.shape[0])),
        ("heart frame Euler X-Y-Z (deg)", f"{e[0]:.1f}, {e[1]:.1f}, {e[2]:.1f}"),
        ("frame fit iterations", model.frame.iterations),
        ("fiducials found", len(model.fiducials_patient_mm)),
        ("stage times (s)", ", ".join(f"{k} {v:.2f}" for k, v in build.timings_s.items())),
    ]))
    parts.append(_image(out / "model" / "model.png", "mesh, fitted ellipses and heart frame axes"))
    parts.append(_image(out / "model" / "model_ct.png", "the surface's outline over the CT: four axial planes through "
                        "the heart, a coronal and a sagittal one through its centre"))

    parts.append("<h2>3. Spatiotemporal registration (paper Figs. 2, 6-9)</h2>")
    t = reg.T_heart_from_probe[:3, 3]
    phase_rows = [
        (f"respiration phase phi_R* by {e.method}" + (" (used)" if k == 0 else ""),
         f"{e.respiration_phase:.2f}, 90 % interval {e.interval_text()}; final T within "
         f"{e.transform_mm:.1f} mm, {e.transform_deg:.1f} deg"
         + ("" if e.decided else " — UNDECIDED: the data cannot decide phi_R*"))
        for k, e in enumerate(reg.phase_estimates)
    ] or [("respiration phase phi_R*", reg.respiration_phase)]
    parts.append(html_table(["quantity", "value"], [
        *phase_rows, ("cardiac phase phi_C*", reg.cardiac_phase),
        ("translation (mm)", f"{t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}"),
        ("Euler X-Y-Z (deg)", ", ".join(f"{a:.2f}" for a in reg.euler_xyz_deg)),
        ("RMS point-to-surface (mm)", reg.rms_mm), ("fiducial FRE (mm)", reg.fre_mm),
        ("distance from fiducial registration (mm)", reg.translation_distance_mm),
        ("rotation from fiducial registration (deg)", reg.rotation_distance_deg),
        ("static vs spatiotemporal, mean delta (mm)", reg.static.mean_delta_mm),
        ("points registered / excluded", f"{len(reg.point_ids)} / {len(reg.exclusions)}"),
    ]))
    reg_dir = out / "registration"
    for name, caption in [
        ("fig2_rms.png", "Fig. 2: RMS registration error across cardiac and respiration phase"),
        ("fig6_parameters.png", "Fig. 6: registration parameters across respiration phase"),
        ("fig7_distances.png", "Fig. 7: translation and rotation distance from the fiducial registration"),
        ("fig9_delta.png", "Fig. 9: static vs spatiotemporal registration, delta per point"),
        ("fig10_phase.png", "The evidence behind phi_R* and its bootstrap interval"),
        ("fig8_view.png", "Fig. 8: points and predicted normals on the mesh, fiducial vs final registration"),
    ]:
        parts.append(_image(reg_dir / name, caption))
    if reg.exclusions:
        parts.append("<h3>Excluded points</h3>")
        parts.append(html_table(["point", "reason"], reg.exclusions))
    notes = list(report.notes) + list(build.notes) + list(reg.notes)
    if notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")
    parts.append(
        "<p class='note'>Files: phases/ (CSV, JSON, PNG), model/ (PLY, STL, JSON, PNG), registration/ "
        "(JSON, CSV, PNG). Stage times (s): "
        + ", ".join(f"{k} {v:.1f}" for k, v in run.timings_s.items()) + ".</p></body></html>"
    )
    path = Path(path)
    write_text_atomic(path, "\n".join(parts) + "\n")
    return path
