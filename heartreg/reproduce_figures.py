"""The paper's figures, redrawn from a reproduction's trials (Wood et al. 2018, Figs. 2, 4, 6, 7, 9).

:func:`figure_data` gathers the data behind every figure, curve by curve (written
as ``figures.json``); :func:`plot_figures` draws them as PNG files, every trial
and the mean over trials.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import numpy as np

from heartreg.reproduce_results import TrialResult, _mean_curve
from hrcore.figlayout import PNG_OPTIONS, fixed_margins, subplots

__all__ = ["figure_data", "plot_figures"]


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
_MEAN_STYLE = {"color": "black", "linestyle": "--", "linewidth": 2.2}


def _tex(text: str) -> str:
    """Plot text: ``phi_R*`` -> mathtext phi with sub- and superscript."""
    return re.sub(r"phi_([RC])(\*?)", lambda m: f"$\\varphi_{m[1]}{'^*' if m[2] else ''}$", text)


def _colours(n):
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


def _save(fig, path: Path) -> Path:
    fig.savefig(path, format="png", pil_kwargs=PNG_OPTIONS)  # into the caller's staging folder (hrcore.output)
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
    fig = Figure(figsize=(11, 4.4), dpi=_DPI)
    axes = subplots(fig, 1, len(panels), squeeze=False)[0]
    fixed_margins(fig, left_in=0.68, right_in=0.15, bottom_in=0.55, top_in=0.6, wspace_in=0.8)
    for ax, panel in zip(axes, panels):
        _draw_curves(ax, panel, colours)
        ax.set_ylim(bottom=0, top=1.25 * max(max(s["y"]) for s in panel["series"]))
    axes[-1].legend(fontsize=8, ncol=4, loc="upper right")
    fig.suptitle(figs["fig2"]["title"], fontsize=11)
    paths["fig2"] = _save(fig, out / "fig2_rms.png")

    # Fig. 6: 2 x 3
    panels = figs["fig6"]["panels"]
    fig = Figure(figsize=(13, 7.2), dpi=_DPI)
    axes = subplots(fig, 2, 3)
    fixed_margins(fig, left_in=0.6, right_in=0.15, bottom_in=0.85, top_in=0.62, wspace_in=0.75, hspace_in=0.72)
    for ax, panel in zip(axes.ravel(), panels):
        _draw_curves(ax, panel, colours)
        ax.axhline(0.0, color="grey", linewidth=0.6)
    axes[0, 0].set_title("(A) " + axes[0, 0].get_title(), fontsize=10)
    axes[1, 0].set_title("(B) " + axes[1, 0].get_title(), fontsize=10)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9)
    fig.suptitle(figs["fig6"]["title"].replace("T inv(T0)", "$T\\,T_0^{-1}$"), fontsize=11)
    paths["fig6"] = _save(fig, out / "fig6_parameters.png")

    # Fig. 7
    panels = figs["fig7"]["panels"]
    fig = Figure(figsize=(11, 4.6), dpi=_DPI)
    axes = subplots(fig, 1, 2)
    fixed_margins(fig, left_in=0.68, right_in=0.15, bottom_in=0.55, top_in=0.6, wspace_in=0.8)
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
    fig = Figure(figsize=(7.5, 4.6), dpi=_DPI)
    ax = subplots(fig)
    fixed_margins(fig, left_in=0.68, right_in=0.15, bottom_in=0.45, top_in=0.35)
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
    # room above the highest dot for the legend (it covered a trial's top dots: a page audit)
    ax.set_ylim(bottom=0, top=1.25 * max(max(s["y"]) for s in trial_series))
    ax.set_ylabel(panel["ylabel"])
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(figs["fig9"]["title"], fontsize=10)
    paths["fig9"] = _save(fig, out / "fig9_delta.png")

    # Fig. 4: one panel per trial, up to 3 per row
    panels = figs["fig4"]["panels"]
    ncols = min(3, len(panels))
    nrows = -(-len(panels) // ncols)
    fig = Figure(figsize=(4.2 * ncols, 3.4 * nrows + 0.6), dpi=_DPI)
    axes = np.atleast_1d(subplots(fig, nrows, ncols, squeeze=False)).ravel()
    fixed_margins(fig, left_in=0.6, right_in=0.15, bottom_in=0.5, top_in=0.6, wspace_in=0.7, hspace_in=0.75)
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
