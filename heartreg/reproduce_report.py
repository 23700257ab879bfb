"""The reproduction's tables, figures and page (see :mod:`heartreg.reproduce`).

Everything here is drawn from :class:`heartreg.reproduce.TrialResult` values,
which are read from the pipeline's output files: the Markdown and CSV tables
beside the paper's numbers, the data behind every figure and the figures
themselves (matplotlib, Agg), and the self-contained HTML page with the
"where our numbers differ from the paper, and why" section.
"""

from __future__ import annotations

import csv
import html
import io
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from heartreg.reproduce import COLUMNS, PAPER, TOL_PHASE_R, TrialResult, _mean_curve, _wrap

__all__ = ["figure_data", "plot_figures", "csv_text", "markdown", "page_html"]


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


# ----------------------------------------------------------------- figures
def _series(label, x, y, kind="trial"):
    return {"label": label, "kind": kind, "x": [float(v) for v in x], "y": [float(v) for v in y]}


def _panel(title, xlabel, ylabel, series, **extra):
    return {"title": title, "xlabel": xlabel, "ylabel": ylabel, "series": series, **extra}


def figure_data(trials: Sequence[TrialResult]) -> dict:
    """The data behind every figure: ``{fig: {"title", "panels": [panel, ...]}}``.

    Each panel holds ``series``: dicts with ``label``, ``kind`` (``"trial"``,
    ``"mean"``, ``"marker"`` or ``"window"``), ``x`` and ``y``.  Per-trial curves
    come first, in trial order, then the mean, then markers.
    """
    trials = list(trials)
    names = [f"trial {t.trial}" for t in trials]
    figs = {}

    # Fig. 2: RMS over phi_C (at phi_R*) and over phi_R (at phi_C*)
    panels = []
    have_c = all(t.phases_c.size for t in trials)
    if have_c:
        xc, mc = _mean_curve(trials, "rms_c_mm", "phases_c")
        s = [_series(n, t.phases_c, t.rms_c_mm) for n, t in zip(names, trials)]
        s.append(_series("mean", xc, mc, "mean"))
        panels.append(_panel("(A) cardiac phase swept at each trial's phi_R*", "cardiac phase phi_C",
                             "RMS point-to-surface error (mm)", s))
    xr, mr = _mean_curve(trials, "rms_r_mm")
    s = [_series(n, t.phases_r, t.rms_r_mm) for n, t in zip(names, trials)]
    s.append(_series("mean", xr, mr, "mean"))
    panels.append(_panel(f"({'B' if have_c else 'A'}) respiration phase swept at each trial's phi_C*",
                         "respiration phase phi_R", "RMS point-to-surface error (mm)", s))
    figs["fig2"] = {"title": "Registration RMS error across phase, all trials (cf. Wood et al. 2018, Fig. 2)",
                    "panels": panels}

    # Fig. 6: correction components over phi_R
    panels = []
    for attr, what, unit, comps in (
        ("correction_translation_mm", "translation", "mm", ("x", "y", "z")),
        ("correction_euler_xyz_deg", "rotation", "deg", ("alpha (X)", "beta (Y)", "gamma (Z)")),
    ):
        for j, comp in enumerate(comps):
            s = [_series(n, t.phases_r, getattr(t, attr)[:, j]) for n, t in zip(names, trials)]
            s.append(_series("mean", xr, np.mean([getattr(t, attr)[:, j] for t in trials], axis=0), "mean"))
            panels.append(_panel(f"{what} {comp}", "respiration phase phi_R", unit, s))
    figs["fig6"] = {"title": "Registration parameters T inv(T0) across respiration phase, heart frame "
                             "(cf. Fig. 6: A translation, B rotation)", "panels": panels}

    # Fig. 7: distance magnitudes over phi_R, minima marked
    panels = []
    _, mt = _mean_curve(trials, "translation_distance_mm")
    _, mrot = _mean_curve(trials, "rotation_distance_deg")
    i_mean = int(np.argmin(mt))
    for attr, mean_curve, title, unit in (
        ("translation_distance_mm", mt, "(A) translation distance from T0", "mm"),
        ("rotation_distance_deg", mrot, "(B) rotation distance from T0", "deg"),
    ):
        s = [_series(n, t.phases_r, getattr(t, attr)) for n, t in zip(names, trials)]
        s.append(_series("mean", xr, mean_curve, "mean"))
        idx = [int(np.argmin(t.translation_distance_mm)) for t in trials]
        s.append(_series("phi_R* per trial", [t.phases_r[i] for t, i in zip(trials, idx)],
                         [getattr(t, attr)[i] for t, i in zip(trials, idx)], "marker"))
        s.append(_series("mean at its minimum translation", [xr[i_mean]], [mean_curve[i_mean]], "marker"))
        panels.append(_panel(title, "respiration phase phi_R", unit, s))
    figs["fig7"] = {"title": "Distance of the registration from the fiducial seed T0 (cf. Fig. 7, eq. 10)",
                    "panels": panels}

    # Fig. 9: delta per point per trial, mean as a square
    s = [_series(n, np.full(t.delta_mm.size, float(t.trial)), t.delta_mm) for n, t in zip(names, trials)]
    s.append(_series("mean per trial", [t.trial for t in trials], [t.delta_mm.mean() for t in trials], "marker"))
    figs["fig9"] = {"title": "Static vs spatiotemporal registration: delta per point (cf. Fig. 9)",
                    "panels": [_panel("", "trial", "delta (mm)", s)]}

    # Fig. 4: cardiac phase per slice, per trial
    panels = []
    for n, t in zip(names, trials):
        s = [_series(n, t.slice_position_mm, t.slice_phase),
             _series("phi_C* (mean)", [t.slice_position_mm.min(), t.slice_position_mm.max()],
                     [t.row["phi_c"]] * 2, "mean"),
             _series("motion-free window 0.6-0.8", [0.6, 0.8], [0.6, 0.8], "window")]
        panels.append(_panel(f"{n}: phi_C* = {t.row['phi_c']:.3f} (paper {t.row['phi_c_paper']:.2f})",
                             "slice position (mm)", "cardiac phase", s))
    figs["fig4"] = {"title": "Cardiac phase of every CT slice (cf. Fig. 4)", "panels": panels}
    return figs


_DPI = 110
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
_MEAN_STYLE = {"color": "black", "linestyle": "--", "linewidth": 2.2}


def _tex(text: str) -> str:
    """Plot text: ``phi_R*`` -> mathtext phi with sub- and superscript."""
    return re.sub(r"phi_([RC])(\*?)", lambda m: f"$\\varphi_{m[1]}{'^*' if m[2] else ''}$", text)


def _colours(n):
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


def _save(fig, path: Path) -> Path:
    fig.savefig(path, format="png")  # into the caller's staging folder (hrcore.output)
    return path


def _draw_curves(ax, panel, colours):
    k = 0
    for s in panel["series"]:
        if s["kind"] == "trial":
            ax.plot(s["x"], s["y"], color=colours[k], linewidth=1.1, alpha=0.85, label=_tex(s["label"]))
            k += 1
        elif s["kind"] == "mean":
            ax.plot(s["x"], s["y"], label=_tex(s["label"]), **_MEAN_STYLE)
    ax.set_xlabel(_tex(panel["xlabel"]))
    ax.set_ylabel(_tex(panel["ylabel"]))
    ax.set_xlim(0, 1)
    ax.grid(alpha=0.3)
    ax.set_title(_tex(panel["title"]), fontsize=10)


def plot_figures(figs: dict, out: Path) -> dict:
    """Draw the figures of :func:`figure_data` into ``out`` (a staging folder:
    :func:`hrcore.output.staged_output`); ``{name: Path}``."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    paths = {}
    n_trials = sum(s["kind"] == "trial" for s in figs["fig2"]["panels"][0]["series"])
    colours = _colours(n_trials)

    # Fig. 2
    panels = figs["fig2"]["panels"]
    fig = Figure(figsize=(11, 4.4), dpi=_DPI, layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels):
        _draw_curves(ax, panel, colours)
        ax.set_ylim(bottom=0, top=1.25 * max(max(s["y"]) for s in panel["series"]))
    axes[-1].legend(fontsize=8, ncol=4, loc="upper right")
    fig.suptitle(figs["fig2"]["title"], fontsize=11)
    paths["fig2"] = _save(fig, out / "fig2_rms.png")

    # Fig. 6: 2 x 3
    panels = figs["fig6"]["panels"]
    fig = Figure(figsize=(13, 7.2), dpi=_DPI, layout="constrained")
    axes = fig.subplots(2, 3)
    for ax, panel in zip(axes.ravel(), panels):
        _draw_curves(ax, panel, colours)
        ax.axhline(0.0, color="grey", linewidth=0.6)
    axes[0, 0].set_title("(A) " + axes[0, 0].get_title(), fontsize=10)
    axes[1, 0].set_title("(B) " + axes[1, 0].get_title(), fontsize=10)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=9)
    fig.suptitle(figs["fig6"]["title"].replace("T inv(T0)", "$T\\,T_0^{-1}$"), fontsize=11)
    paths["fig6"] = _save(fig, out / "fig6_parameters.png")

    # Fig. 7
    panels = figs["fig7"]["panels"]
    fig = Figure(figsize=(11, 4.6), dpi=_DPI, layout="constrained")
    axes = fig.subplots(1, 2)
    for ax, panel in zip(axes, panels):
        _draw_curves(ax, panel, colours)
        markers = [s for s in panel["series"] if s["kind"] == "marker"]
        per_trial, mean_min = markers[0], markers[1]
        ax.scatter(per_trial["x"], per_trial["y"], c=colours[:len(per_trial["x"])], edgecolors="black",
                   s=40, zorder=3, label=_tex(per_trial["label"]))
        ax.plot(mean_min["x"], mean_min["y"], "s", color="black", markersize=9, zorder=4,
                label=_tex(f"mean curve at phi_R = {mean_min['x'][0]:.2f}: {mean_min['y'][0]:.2f} {panel['ylabel']}"))
        ax.set_ylim(bottom=0, top=1.3 * max(max(s["y"]) for s in panel["series"]))
        ax.legend(fontsize=8, ncol=3, loc="upper center")
    fig.suptitle(figs["fig7"]["title"], fontsize=11)
    paths["fig7"] = _save(fig, out / "fig7_distances.png")

    # Fig. 9
    (panel,) = figs["fig9"]["panels"]
    fig = Figure(figsize=(7.5, 4.6), dpi=_DPI, layout="constrained")
    ax = fig.subplots()
    trial_series = [s for s in panel["series"] if s["kind"] == "trial"]
    for k, s in enumerate(trial_series):
        n = len(s["y"])
        jitter = np.linspace(-0.18, 0.18, n) if n > 1 else np.zeros(1)
        ax.plot(np.asarray(s["x"]) + jitter, s["y"], "o", color=colours[k], markersize=3.5, alpha=0.7)
    means = [s for s in panel["series"] if s["kind"] == "marker"][0]
    ax.plot(means["x"], means["y"], "s", color="black", markerfacecolor="white", markersize=10,
            markeredgewidth=2, label="mean over the trial's points")
    for x, y in zip(means["x"], means["y"]):
        ax.annotate(f"{y:.2f}", (x, y), xytext=(12, 0), textcoords="offset points", va="center", fontsize=8)
    ax.set_xticks(means["x"])
    ax.set_xticklabels([s["label"] for s in trial_series])
    ax.set_xlim(min(means["x"]) - 0.6, max(means["x"]) + 0.8)
    ax.set_ylim(bottom=0)
    ax.set_ylabel(panel["ylabel"])
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(figs["fig9"]["title"], fontsize=10)
    paths["fig9"] = _save(fig, out / "fig9_delta.png")

    # Fig. 4: one panel per trial, up to 3 per row
    panels = figs["fig4"]["panels"]
    ncols = min(3, len(panels))
    nrows = -(-len(panels) // ncols)
    fig = Figure(figsize=(4.2 * ncols, 3.4 * nrows + 0.6), dpi=_DPI, layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    for k, (ax, panel) in enumerate(zip(axes, panels)):
        data, mean, window = panel["series"]
        ax.axhspan(window["y"][0], window["y"][1], color="#2ecc71", alpha=0.15, label=window["label"])
        ax.plot(data["x"], data["y"], ".", color=colours[k], markersize=3)
        ax.plot(mean["x"], mean["y"], label=_tex(mean["label"]), **{**_MEAN_STYLE, "linewidth": 1.4})
        ax.set_ylim(0, 1)
        ax.set_xlabel(panel["xlabel"])
        ax.set_ylabel(panel["ylabel"])
        ax.set_title(_tex(panel["title"]), fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(figs["fig4"]["title"], fontsize=11)
    paths["fig4"] = _save(fig, out / "fig4_phases.png")
    return paths


# ----------------------------------------------------------------- HTML
def _trials_text(ks) -> str:
    ks = list(ks)
    return ("trial " if len(ks) == 1 else "trials ") + ", ".join(map(str, ks))


def _differences(trials, summary) -> list[str]:
    """The honest section: where our synthetic numbers differ from the paper, and why.

    Every number is read from this run; the reasons name the phantom's settings
    (``heartreg/phantom/config.py``) that produce them.
    """
    s, p = summary, PAPER
    rows = [t.row for t in trials]
    items = []

    rms_lo, rms_hi = s["mean_rms_range_mm"]
    near = [r["trial"] for r in rows if abs(_wrap(r["rms_argmin_phase"] - r["phi_r_truth"])) <= TOL_PHASE_R]
    mirror = [r for r in rows if r["trial"] not in near
              and abs(_wrap(r["rms_argmin_phase"] - (1.0 - r["phi_r_truth"]))) <= TOL_PHASE_R]
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
        f"The static (mean-position) registration's averages {s['mean_static_error_deg']:.1f}°, more than T0's; "
        "a plausible cause, not isolated here, is the heartbeat's twist (apex +7°, base -4°) in the mean "
        "positions, which a rigid fit to the diastolic map turns into a rotation."
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
