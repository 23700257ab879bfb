"""The paper's figures for a registration (matplotlib, Agg, no pyplot state).

``fig2_rms.png``, ``fig6_parameters.png``, ``fig7_distances.png``,
``fig9_delta.png`` and ``fig10_phase.png`` of :func:`write_plots`, written by
:func:`registration.report.write_registration` (see its module docstring).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hrcore.figlayout import PNG_OPTIONS, fixed_margins, subplots
from imaging.files import atomic_path
from registration.result import RegistrationResult

__all__ = ["write_plots"]

_DPI = 110


def _shade_interval(ax, estimate, colour, label):
    """Shade a phase interval (wrapping through 0 drawn as two spans)."""
    lo, hi = (float(x) for x in estimate.interval)
    if estimate.width >= 1.0 - 1e-9:
        spans = [(0.0, 1.0)]
    elif lo <= hi:
        spans = [(lo, hi)]
    else:
        spans = [(lo, 1.0), (0.0, hi)]
    for k, (a, b) in enumerate(spans):
        ax.axvspan(a, b, color=colour, alpha=0.15, lw=0, label=label if k == 0 else None)


# ------------------------------------------------------------------ plots
#: inches under a panel's axis label for one row of its legend (:func:`_legend_below`)
_LEGEND_ROW_IN = 0.2


def _figure(ncols, width=11.0, height=4.2, top_in=0.6, legend_rows=0):
    """A figure of ``ncols`` panels in a row; ``top_in`` (inches) holds the
    suptitle and the panels' titles (0.35 for a title alone); ``legend_rows``
    rows of legend fit under the panels (the figure grows by them)."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    legend_in = legend_rows * _LEGEND_ROW_IN + (0.15 if legend_rows else 0.0)
    fig = Figure(figsize=(width, height + legend_in), dpi=_DPI)
    axes = subplots(fig, 1, ncols, squeeze=False)[0]
    # fixed room (no layout engine: it cost half of writing the figures) for tick and axis labels
    fixed_margins(fig, left_in=0.68, right_in=0.15, bottom_in=0.55 + legend_in, top_in=top_in, wspace_in=0.8)
    return fig, axes


def _legend_below(ax, ncol=2):
    """The panel's legend under its axis label, where it covers no curve, marker or interval (inside the panels
    it hid Fig. 2B's peak, Fig. 7's eq. 10 minimum and Fig. 10A's cost: an audit)."""
    height_in = ax.get_figure().get_size_inches()[1] * ax.get_position().height
    ax.legend(fontsize=8, ncol=ncol, loc="upper center", frameon=False,
              bbox_to_anchor=(0.5, -0.48 / height_in))


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", pil_kwargs=PNG_OPTIONS)
    return path


def _mark(ax, x, label, colour="#c0392b"):
    ax.axvline(x, color=colour, linestyle="--", linewidth=1.2, label=label)


def write_plots(result: RegistrationResult, out_dir) -> dict:
    """Write fig2_rms, fig6_parameters, fig7_distances and fig9_delta PNGs.

    Returns
    -------
    dict of Path by name ("fig2", "fig6", "fig7", "fig9").
    """
    out = Path(out_dir)
    resp = result.respiration_sweep
    card = result.cardiac_sweep
    phi_r, phi_c = result.respiration_phase, result.cardiac_phase
    paths = {}

    # Fig. 2: RMS vs phase
    fig, (ax_c, ax_r) = _figure(2, legend_rows=1)
    if card is not None:
        ax_c.plot(card.phases, card.rms_mm, color="#2c3e50", marker=".", markersize=3)
        _mark(ax_c, phi_c, f"image phase $\\varphi_C^*$ = {phi_c:.2f}")
        _legend_below(ax_c)
    else:
        ax_c.text(0.5, 0.5, "cardiac sweep not run", ha="center", va="center", transform=ax_c.transAxes)
    ax_c.set_title(f"(A) cardiac phase swept at $\\varphi_R$ = {phi_r:.2f}", fontsize=10)
    ax_c.set_xlabel("cardiac phase $\\varphi_C$")
    ax_r.plot(resp.phases, resp.rms_mm, color="#2c3e50", marker=".", markersize=3)
    method = result.phase_estimates[0].method if result.phase_estimates else "eq10"
    _mark(ax_r, phi_r, f"$\\varphi_R^*$ = {phi_r:.2f} ({method})")
    _legend_below(ax_r)
    ax_r.set_title(f"(B) respiration phase swept at $\\varphi_C^*$ = {phi_c:.2f}", fontsize=10)
    ax_r.set_xlabel("respiration phase $\\varphi_R$")
    for ax in (ax_c, ax_r):
        ax.set_ylabel("RMS point-to-surface error (mm)")
        ax.set_xlim(0, 1)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    fig.suptitle("Registration error over phase (cf. Wood et al. 2018, Fig. 2)", fontsize=11)
    paths["fig2"] = _save(fig, out / "fig2_rms.png")

    # Fig. 6: registration parameters vs phi_R
    fig, (ax_t, ax_e) = _figure(2)
    colours = ("#c0392b", "#27ae60", "#2980b9")
    for j, (c, name) in enumerate(zip(colours, "xyz")):
        ax_t.plot(resp.phases, resp.correction_translation_mm[:, j], color=c, label=f"$t_{name}$")
        ax_e.plot(resp.phases, resp.correction_euler_xyz_deg[:, j], color=c, label=f"$r_{name}$")
    for ax, unit, title in ((ax_t, "mm", "(A) translation"), (ax_e, "deg", "(B) rotation, Euler X-Y-Z")):
        _mark(ax, phi_r, f"$\\varphi_R^*$ = {phi_r:.2f}", colour="#7f8c8d")
        ax.axhline(0.0, color="black", linewidth=0.6)
        ax.set_xlabel("respiration phase $\\varphi_R$")
        ax.set_ylabel(unit)
        ax.set_xlim(0, 1)
        ax.set_title(title, fontsize=10)
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, hi + 0.25 * (hi - lo))  # room for the legend
        ax.legend(fontsize=8, ncol=4, loc="upper right")
        ax.grid(alpha=0.3)
    fig.suptitle(
        "Correction $T\\,T_0^{-1}$ of the fiducial registration, heart frame, at the heart centre "
        "(cf. Fig. 6)", fontsize=11,
    )
    paths["fig6"] = _save(fig, out / "fig6_parameters.png")

    # Fig. 7: distance magnitudes vs phi_R
    fig, (ax_t, ax_r) = _figure(2, legend_rows=2)
    ax_t.plot(resp.phases, resp.translation_distance_mm, color="#2c3e50")
    ax_r.plot(resp.phases, resp.rotation_distance_deg, color="#2c3e50")
    estimates = {e.method: e for e in result.phase_estimates}
    i = result.phase_estimates[0].index if result.phase_estimates else resp.best_index
    j = resp.best_index
    if i != j:
        ax_t.plot([resp.phases[j]], [resp.translation_distance_mm[j]], "s", color="#e67e22",
                  label=f"eq. 10 minimum at {resp.phases[j]:.2f}")
    ax_t.plot([phi_r], [resp.translation_distance_mm[i]], "o", color="#c0392b",
              label=f"$\\varphi_R^*$ = {phi_r:.2f}: {resp.translation_distance_mm[i]:.2f} mm")
    ax_r.plot([phi_r], [resp.rotation_distance_deg[i]], "o", color="#c0392b",
              label=f"at $\\varphi_R^*$: {resp.rotation_distance_deg[i]:.2f} deg")
    for method, colour in (("shape", "#2980b9"), ("eq10", "#e67e22")):
        if method in estimates:
            e = estimates[method]
            for ax in (ax_t, ax_r):
                _shade_interval(ax, e, colour, f"{method} 90 % interval" + ("" if e.decided else " (undecided)"))
    for ax, unit, title in ((ax_t, "mm", "(A) translation distance from $T_0$"),
                            (ax_r, "deg", "(B) rotation distance from $T_0$")):
        _mark(ax, phi_r, None)
        ax.set_xlabel("respiration phase $\\varphi_R$")
        ax.set_ylabel(unit)
        ax.set_xlim(0, 1)
        ax.set_ylim(bottom=0)
        ax.set_title(title, fontsize=10)
        _legend_below(ax)
        ax.grid(alpha=0.3)
    fig.suptitle("Distance of the registration from the fiducial seed (cf. Fig. 7, eq. 10)", fontsize=11)
    paths["fig7"] = _save(fig, out / "fig7_distances.png")

    # Fig. 9: delta per point
    fig, (ax,) = _figure(1, width=7.5, height=4.2, top_in=0.35)
    delta = result.static.delta_mm
    ax.plot(result.point_ids, delta, "o", color="#2980b9", markersize=4, label="$\\delta_i$ per point")
    ax.axhline(result.delta_static_mean_mm, color="#c0392b", linewidth=1.5,
               label=f"mean {result.delta_static_mean_mm:.2f} mm ({delta.size} points)")
    ax.set_xlabel("point id")
    ax.set_ylabel("$\\delta_i$ (mm)")
    ax.set_ylim(0, 1.3 * max(float(delta.max()), 1e-3))  # room for the legend
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", ncol=2)
    ax.set_title("Surface distance between spatiotemporal and static registration (cf. Fig. 9)",
                 fontsize=10)
    paths["fig9"] = _save(fig, out / "fig9_delta.png")

    # Fig. 10 (ours): the evidence behind phi_R* and its bootstrap
    if result.phase_estimates:
        fig, (ax_j, ax_b) = _figure(2, legend_rows=2)
        for e in result.phase_estimates:
            if e.method == "shape":
                ax_j.plot(resp.phases, e.cost, color="#2c3e50", label="J, all terms")
                if "heart" in e.evidence:
                    ax_j.plot(resp.phases, e.cost_heart, color="#c0392b", lw=1, label="heart shape")
                if "fiducial_trace" in e.evidence:
                    ax_j.plot(resp.phases, e.cost_fiducial, color="#27ae60", lw=1, label="chest staples (trace)")
                if "breath_hold" in e.evidence:
                    ax_j.plot(resp.phases, e.cost_prior, color="#8e44ad", lw=1, label="stated breath-hold")
                _shade_interval(ax_j, e, "#2980b9", "90 % interval")
            colour = "#2980b9" if e.method == "shape" else "#e67e22"
            ax_b.hist(e.bootstrap_phases, bins=np.linspace(0, 1, 51), color=colour, alpha=0.6,
                      label=f"{e.method}: {e.respiration_phase:.2f}, {e.interval_text()}"
                      + ("" if e.decided else " (undecided)"))
        if any(e.method == "shape" for e in result.phase_estimates):
            ax_j.set_ylabel("J - min J (chi-square units)")
            ax_j.set_yscale("symlog", linthresh=10.0)
        else:  # an empty panel read as a flat, zero cost (an audit): say why it is empty
            ax_j.set_yticks([])
            ax_j.text(0.5, 0.5, f"the shape estimator was not run\n(phi_R* is {result.phase_estimates[0].method}'s; "
                      "the notes say why)", ha="center", va="center", transform=ax_j.transAxes, fontsize=10)
        ax_j.set_title("(A) shape estimator: cost over the respiration phase", fontsize=10)
        ax_b.set_ylabel("bootstrap resamples")
        ax_b.set_title("(B) phi_R* of each bootstrap resample", fontsize=10)
        for ax in (ax_j, ax_b):
            ax.set_xlabel("respiration phase $\\varphi_R$")
            ax.set_xlim(0, 1)
            ax.grid(alpha=0.3)
        if ax_j.get_legend_handles_labels()[1]:
            _legend_below(ax_j)
        _legend_below(ax_b, ncol=1)
        fig.suptitle("The image's respiration phase: evidence and uncertainty", fontsize=11)
        paths["fig10"] = _save(fig, out / "fig10_phase.png")
    return paths
