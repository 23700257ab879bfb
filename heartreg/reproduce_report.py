"""The reproduction's tables and page (see :mod:`heartreg.reproduce`).

Everything here is drawn from :class:`heartreg.reproduce_results.TrialResult`
values, which are read from the pipeline's output files: the Markdown and CSV
tables beside the paper's numbers and the self-contained HTML page with the
"where our numbers differ from the paper, and why" section. The figures are
:mod:`heartreg.reproduce_figures`.
"""

from __future__ import annotations

import csv
import html
import io
from pathlib import Path

import numpy as np

from heartreg.reproduce_results import COLUMNS, PAPER, TOL_PHASE_R
from registration.phase_estimate import wrap_phase

__all__ = ["csv_text", "markdown", "page_html"]

_STYLE = """
body { font-family: -apple-system, Segoe UI, Helvetica, Arial, sans-serif; margin: 2em auto;
       max-width: 1150px; color: #222; line-height: 1.45; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: .8em 0; font-size: .9em; }
th, td { border: 1px solid #ccc; padding: .3em .6em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.ok { color: #1a7f37; font-weight: 600; } .miss { color: #b42318; font-weight: 600; }
img { max-width: 100%; border: 1px solid #eee; margin: .5em 0; } li { margin: .4em 0; }
.note { color: #555; font-size: .9em; }
"""


def _fmt(v, digits=2) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "**no**"
    if isinstance(v, (float, np.floating)):
        return f"{v:.{digits}f}"
    return str(v)


def _md_table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(c).replace("|", "\\|") for c in r) + " |")
    return "\n".join(lines)


def _table_a(trials):
    """Table 1 beside the paper: header and rows of formatted strings."""
    header = ["trial", "points", "heart rate (Hz) ours / paper", "resp. rate (Hz) ours / paper",
              "phi_C* ours / truth / paper", "Euler X-Y-Z fitted (deg)", "preset (deg)", "paper (deg)",
              "z-axis error (deg)"]
    rows = []
    for t in trials:
        r = t.row
        rows.append([
            str(r["trial"]),
            f"{r['points_used']}" + (f" (+{r['points_excluded']} excl.)" if r["points_excluded"] else ""),
            f"{r['heart_rate_hz']:.2f} / {r['paper_heart_rate_hz']:.2f}",
            f"{r['resp_rate_hz']:.2f} / {r['paper_resp_rate_hz']:.2f}",
            f"{r['phi_c']:.3f} / {r['phi_c_truth']:.3f} / {r['phi_c_paper']:.2f}",
            ", ".join(f"{r[f'euler_fit_{k}_deg']:.1f}" for k in "abg"),
            ", ".join(f"{r[f'euler_preset_{k}_deg']:.1f}" for k in "abg"),
            ", ".join(f"{r[f'euler_paper_{k}_deg']:.1f}" for k in "abg"),
            f"{r['frame_z_error_deg']:.2f}",
        ])
    return header, rows


def _table_b(trials, summary):
    """Registration results beside the paper's: header and rows of formatted strings."""
    header = ["trial", "phi_R* ours / truth", "within ±0.05", "min translation (mm)", "rotation at min (deg)",
              "RMS over phi_R (mm)", "mean delta (mm)", "T0 error (mm, deg)", "final T error (mm, deg)",
              "static T error (mm, deg)"]
    rows = []
    for t in trials:
        r = t.row
        rows.append([
            str(r["trial"]), f"{r['phi_r']:.2f} / {r['phi_r_truth']:.2f}", _fmt(r["phi_r_within"]),
            f"{r['min_translation_mm']:.2f}", f"{r['rotation_at_min_deg']:.2f}",
            f"{r['rms_min_mm']:.2f}–{r['rms_max_mm']:.2f}", f"{r['mean_delta_mm']:.2f}",
            f"{r['t0_error_mm']:.2f}, {r['t0_error_deg']:.2f}",
            f"{r['final_error_mm']:.2f}, {r['final_error_deg']:.2f}",
            f"{r['static_error_mm']:.2f}, {r['static_error_deg']:.2f}",
        ])
    s = summary
    rows.append([
        "**mean**", f"{s['phi_r_within']} of {s['n_trials']} within", "",
        f"{s['mean_curve_min_translation_mm']:.2f} at phi_R {s['mean_curve_min_phase']:.2f} (mean curve)",
        f"{s['mean_curve_rotation_at_min_deg']:.2f}",
        f"{s['mean_rms_range_mm'][0]:.2f}–{s['mean_rms_range_mm'][1]:.2f} (mean curve)",
        f"{s['mean_delta_mm']:.2f} ({s['mean_delta_range_mm'][0]:.2f}–{s['mean_delta_range_mm'][1]:.2f})",
        f"{s['mean_t0_error_mm']:.2f}, {s['mean_t0_error_deg']:.2f}",
        f"{s['mean_final_error_mm']:.2f}, {s['mean_final_error_deg']:.2f}",
        f"{s['mean_static_error_mm']:.2f}, {s['mean_static_error_deg']:.2f}",
    ])
    p = PAPER
    rows.append([
        "**paper**", "≈0.3 in 5 of 6", "5 of 6",
        f"{p['mean_min_translation_mm']} at phi_R {p['mean_min_translation_phase']} (mean curve)",
        f"{p['mean_rotation_at_min_deg']}", f"≈{p['rms_mm']:g}, flat",
        f"{p['mean_delta_mm']} ({p['mean_delta_range_mm'][0]}–{p['mean_delta_range_mm'][1]})",
        "–", "– (no ground truth)", "–",
    ])
    return header, rows


def csv_text(trials) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow([k for k, _, _ in COLUMNS])
    for t in trials:
        writer.writerow([_csv_cell(t.row.get(k, "")) for k, _, _ in COLUMNS])
    return buf.getvalue()


def _csv_cell(v):
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return v


def markdown(trials, summary, *, size, seed, command) -> str:
    ha, ra = _table_a(trials)
    hb, rb = _table_b(trials, summary)
    misses = [t.row for t in trials if not t.row["phi_r_within"]]
    out = [
        "# Wood et al. 2018 reproduced on the phantom",
        "",
        f"Phantom size `{size}`, seed {seed}, trials {', '.join(str(t.trial) for t in trials)}."
        + (f" Command: `{command}`." if command else ""),
        "",
        "## Table 1 beside the paper",
        "",
        "Rates from the session's ECG and flows; phi_C* the mean slice phase of the CT; "
        "Euler angles of the fitted heart frame against the phantom preset and the paper.",
        "",
        _md_table(ha, ra),
        "",
        "## Registration beside the paper (sections 2.3 and 3)",
        "",
        "phi_R* by eq. 10 (minimum translation distance from the fiducial registration T0); "
        "distances from T0 at the surface centroid; delta = static vs spatiotemporal surface point "
        "(paper 2.3.2); errors against the phantom's truth, translation at the heart origin.",
        "",
        _md_table(hb, rb),
        "",
    ]
    if misses:
        out += ["Misses (phi_R* more than 0.05 from the truth):", ""]
        out += [f"- trial {r['trial']}: {r['miss_reason']}" for r in misses]
        out.append("")
    out += ["## Where our synthetic numbers differ from the paper and why", ""]
    out += ["- " + html.unescape(item.replace("<b>", "**").replace("</b>", "**"))
            for item in _differences(trials, summary)]
    out.append("")
    stages = ("phantom", "phases", "model", "registration", "pipeline")
    out += ["## Time per trial (s)", "",
            _md_table(["trial", *stages, "case reused"],
                      [[str(t.trial), *(f"{t.timings_s.get(k, float('nan')):.1f}" for k in stages),
                        _fmt(bool(t.row["case_reused"])).replace("**", "")] for t in trials]),
            "", "(phantom: writing the case, 0 when reused; pipeline = phases + model + registration + report.)", ""]
    return "\n".join(out)


def _trials_text(ks) -> str:
    ks = list(ks)
    return ("trial " if len(ks) == 1 else "trials ") + ", ".join(map(str, ks))


def static_rotation_text(static_deg: float, t0_deg: float, final_deg: float) -> str:
    """The sentence on the static registration's rotation error, compared with T0's and the final one's."""
    if static_deg > t0_deg:
        rel = "more than T0's"
    elif static_deg > final_deg:
        rel = "less than T0's, more than the final one's"
    else:
        rel = "less than T0's and the final one's"
    text = f"The static (mean-position) registration's averages {static_deg:.1f}°, {rel}"
    if static_deg <= final_deg:
        return text + "."
    return (text + "; a plausible cause, not isolated here, is the heartbeat's twist (apex +7°, base -4°) in the "
            "mean positions, which a rigid fit to the diastolic map turns into a rotation.")


def _differences(trials, summary) -> list[str]:
    """The honest section: where our synthetic numbers differ from the paper, and why.

    Every number is read from this run; the reasons name the phantom's settings
    (``heartreg/phantom/config.py``) that produce them.
    """
    s, p = summary, PAPER
    rows = [t.row for t in trials]
    items = []

    rms_lo, rms_hi = s["mean_rms_range_mm"]
    near = [r["trial"] for r in rows if abs(wrap_phase(r["rms_argmin_phase"] - r["phi_r_truth"])) <= TOL_PHASE_R]
    mirror = [r for r in rows if r["trial"] not in near
              and abs(wrap_phase(r["rms_argmin_phase"] - (1.0 - r["phi_r_truth"]))) <= TOL_PHASE_R]
    text = (
        f"<b>RMS error is far below the paper's ~{p['rms_mm']:g} mm.</b> The mean curve runs from "
        f"{rms_lo:.2f} to {rms_hi:.2f} mm over phi_R. The map is segmented from a CT whose heart shape is "
        "exact (only voxel noise and partial volume), the robot's points move exactly as the phantom's "
        "analytic surface does, and the tracker noise is 0.2 mm; the paper's 2 mm also carries the "
        "segmentation error of a real heart, its change of shape with the robot in the pericardium and "
        "magnetic-tracker distortion. As in the paper, RMS (eq. 9) is no temporal metric: its minimum over "
        f"phi_R lies within 0.05 of the truth in {len(near)} of {len(rows)} trials"
        + (f" ({_trials_text(near)})" if near else "")
    )
    if mirror:
        lo = min(r["rms_argmin_phase"] for r in mirror)
        hi = max(r["rms_argmin_phase"] for r in mirror)
        text += (
            f" and at the mirror phase 1 - phi_R* in {len(mirror)} ({lo:.2f}–{hi:.2f}). Our curves are not "
            "flat but have two near-equal minima: the phantom's only respiratory change of shape is the "
            "heartbeat's amplitude modulation 1 + 0.2 cos(2 pi phi_R), the same at phi_R and 1 - phi_R; the "
            "rest of its respiratory motion is rigid, which ICP absorbs."
        )
    else:
        text += "."
    items.append(text)

    hits = [r for r in rows if r["phi_r_within"]]
    text = (
        f"<b>The minimum translation distance ({s['mean_curve_min_translation_mm']:.1f} mm on the mean curve, "
        f"at phi_R {s['mean_curve_min_phase']:.2f}; paper {p['mean_min_translation_mm']} mm at "
        f"{p['mean_min_translation_phase']}) is set by construction</b>: each preset shifts the fiducials "
        "against the heart by 8–11 mm (fiducial_shift_mm), the CT-to-surgery error the paper's seed carried; "
        f"T0's error against the truth averages {s['mean_t0_error_mm']:.1f} mm. The agreement with 9.9 mm "
        "echoes the presets, it measures nothing physical."
    )
    if hits:
        gap = max(abs(r["min_translation_mm"] - r["t0_error_mm"]) for r in hits)
        text += (
            f" Where phi_R* is right, the minimum equals T0's true error to within {gap:.2f} mm: eq. 10 "
            "measures the fiducial registration's error, as the paper says of its Fig. 6."
        )
    items.append(text)

    text = (
        f"<b>The rotation distance at the minimum is {s['mean_curve_rotation_at_min_deg']:.1f}° on the mean "
        f"curve (paper {p['mean_rotation_at_min_deg']}°)</b>: the presets turn the fiducials against the heart "
        f"by only 2–3° (fiducial_shift_deg; T0's rotation error against the truth averages "
        f"{s['mean_t0_error_deg']:.1f}°), so there is little rotation to undo; the paper's 8.2° came from real "
        f"CT-to-surgery changes. ICP undoes it: the final rotation error averages {s['mean_final_error_deg']:.2f}°. "
        + static_rotation_text(s["mean_static_error_deg"], s["mean_t0_error_deg"], s["mean_final_error_deg"])
    )
    items.append(text)

    if s["sweep_unconverged"] or s["final_icp_unconverged"]:
        text = (
            f"<b>ICP stopped at its iteration limit at {s['sweep_unconverged']} of the {s['sweep_phases']} "
            "swept respiration phases</b> (column sweep_unconverged)"
            + (f" and in the final registration of {_trials_text(s['final_icp_unconverged'])}"
               if s["final_icp_unconverged"] else "")
            + ", and the rotation curves of Figs. 6B and 7B jump between some neighbouring phases while the "
            "translation distance that eq. 10 reads moves much less. The final ICP's weakest direction is a "
            f"turn about the heart's long axis (z-rotation component {s['mean_icp_weak_long_axis']:.2f} of the "
            "unit vector on average, registration.json icp.weakest_direction): the phantom's cross-sections are "
            "smooth ellipses, so that turn costs the fit little, the likely place where ICP creeps."
        )
        items.append(text)

    text = (
        f"<b>Mean delta {s['mean_delta_mm']:.2f} mm (per trial {s['mean_delta_range_mm'][0]:.2f}–"
        f"{s['mean_delta_range_mm'][1]:.2f}; paper {p['mean_delta_mm']} mm, "
        f"{p['mean_delta_range_mm'][0]}–{p['mean_delta_range_mm'][1]}).</b> "
        + ("The mean matches, the spread " if abs(s["mean_delta_mm"] - p["mean_delta_mm"]) <= 0.5
           else f"The mean differs from the paper's by {s['mean_delta_mm'] - p['mean_delta_mm']:+.2f} mm; the spread ")
        + "between trials is narrower: every preset has the same heart, the same breathing amplitudes (10 mm "
        "superior-inferior, 5 mm anterior-posterior) and the same beat, and differs only in rates, frame angles, "
        "point count and fiducial shift, while the paper's pigs differed in all of it. Against the truth the "
        f"static registration errs by {s['mean_static_error_mm']:.2f} mm on average and the spatiotemporal one "
        f"by {s['mean_final_error_mm']:.2f} mm, errors the paper could not measure."
    )
    items.append(text)

    miss = [r for r in rows if not r["phi_r_within"]]
    if miss:
        worse = [r for r in miss if r["final_error_mm"] > r["static_error_mm"]]
        items.append(
            "<b>Misses of phi_R*:</b> "
            + "; ".join(f"trial {r['trial']}: {_esc(r['miss_reason'])}" for r in miss)
            + (". Trial 4's preset puts its fiducial error along the respiratory path by design, to play the "
               "paper's one miss in six; the other presets err left-right, across the path."
               if any(r["trial"] == 4 for r in miss) else
               ". Only trial 4's preset is meant to miss; these misses are not by design (few points, or a "
               "change in the registration or the phantom).")
            + "".join(f" In trial {r['trial']} the miss leaves the spatiotemporal registration worse than the "
                      f"static one ({r['final_error_mm']:.2f} vs {r['static_error_mm']:.2f} mm)." for r in worse)
        )
    else:
        items.append(
            "<b>No trial missed phi_R*</b> (the paper had one miss in six)"
            + ("; trial 4's preset is meant to, so a change in the registration or the phantom has moved it."
               if any(r["trial"] == 4 for r in rows) else "; trial 4, whose preset is meant to miss, did not run.")
        )
    edge = [r for r in rows if r["phi_r_within"] and abs(r["phi_r_error"]) >= TOL_PHASE_R - 0.01 - 1e-9]
    if edge:
        items.append(
            "<b>At the edge of the band:</b> "
            + "; ".join(f"trial {r['trial']} (phi_R* {r['phi_r']:.2f}, error {r['phi_r_error']:+.2f})" for r in edge)
            + " counts as near the truth with the inclusive ±0.05 of the sweep's 0.01 grid; the paper's "
            "'approximately 0.3' gives no tolerance."
        )

    phi_c = s["phi_c_range"]
    items.append(
        f"<b>Image phase phi_C* {phi_c[0]:.3f}–{phi_c[1]:.3f} (paper 0.61–0.67).</b> The phantom gates at the "
        "paper's target 0.7 (gating_target_phase) with the trigger delay fixed from the RR before the scan; the "
        "breath-hold slows the heart by 8 % (breath_hold_slowing), so the imaged beats are longer than predicted "
        "and the slices land before the target, as the paper's did. "
        + (f"All {len(rows)} trials share one seed, so the same heart-rate variability and nearly one image phase; " if len(rows) > 1 else "")
        + "over seeds the phantom's phi_C* spans about 0.61–0.69. Table 1's image phases are informative only."
    )
    items.append(
        "<b>Heart-frame Euler angles match the paper's because the presets are Table 1</b>: the fitted frame's "
        f"long axis is within {s['mean_frame_z_error_deg']:.2f}° of the phantom's on average. The phantom's "
        "heart is a smooth prolate half-spheroid capped by a superellipsoid, an easier shape for the recursive "
        "ellipse fit than a real heart with its atria and vessels."
    )
    items.append(
        "<b>Heart and respiration rates</b> are the presets' (Table 1), measured back from the session's ECG "
        "and flows; the paper's were measured on the animals."
    )
    return items


def _esc(text: str) -> str:
    return html.escape(str(text))


def page_html(trials, summary, figs_paths, *, size, seed, command, timings) -> str:
    import base64

    from heartreg.report_html import html_table

    ha, ra = _table_a(trials)
    hb, rb = _table_b(trials, summary)
    rb = [[c.replace("**", "") for c in r] for r in rb]
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>heartreg: Wood et al. 2018 reproduced</title>"
        f"<style>{_STYLE}</style></head><body>",
        "<h1>Wood et al. 2018 reproduced on the phantom</h1>",
        "<p>The paper's experiment (sections 2.2.2, 2.3 and 3) run on the six phantom presets "
        "<code>wood2018-trial1</code>…<code>trial6</code>, which carry Table 1's settings. "
        f"Phantom size <code>{size}</code>, seed {seed}"
        + (f"; command <code>{_esc(command)}</code>" if command else "") + ".</p>",
        "<h2>Table 1 beside the paper</h2>",
        html_table(ha, ra),
        "<h2>Registration beside the paper</h2>",
        "<p class='note'>phi_R* by eq. 10; distances from the fiducial registration T0 at the surface centroid; "
        "delta = static vs spatiotemporal surface point; errors against the phantom's truth "
        "(translation at the heart origin).</p>",
        html_table(hb, rb),
        "<h2>Where our synthetic numbers differ from the paper and why</h2>",
        "<ul>" + "".join(f"<li>{item}</li>" for item in _differences(trials, summary)) + "</ul>",
        "<h2>Figures</h2>",
    ]
    captions = {
        "fig2": "Fig. 2: RMS error across (A) cardiac and (B) respiration phase, all trials; mean dashed.",
        "fig4": "Fig. 4: cardiac phase per CT slice, per trial; motion-free window shaded.",
        "fig6": "Fig. 6: registration parameters across respiration phase (A translation, B rotation); mean dashed.",
        "fig7": "Fig. 7: translation and rotation distance from T0; dots at each trial's phi_R*, square at "
                "the mean curve's minimum.",
        "fig9": "Fig. 9: delta per point per trial (dots) and the trial's mean (square).",
    }
    for name in ("fig2", "fig6", "fig7", "fig9", "fig4"):
        data = base64.b64encode(Path(figs_paths[name]).read_bytes()).decode("ascii")
        parts.append(f'<figure><img alt="{name}" src="data:image/png;base64,{data}">'
                     f'<figcaption class="note">{_esc(captions[name])}</figcaption></figure>')
    parts.append("<p class='note'>Per-trial outputs: trialN/run/report.html. Times (s): "
                 + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()) + ".</p></body></html>")
    return "\n".join(parts) + "\n"
