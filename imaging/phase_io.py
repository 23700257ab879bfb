"""Writing a PhaseReport: ``phases.csv``, ``phases.json`` and ``phases.png``."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from imaging.files import atomic_path, write_text_atomic
from imaging.phase import MOTION_FREE_WINDOW, PhaseReport

__all__ = ["write_phase_report", "plot_phases"]


def _csv_text(report: PhaseReport) -> str:
    out = io.StringIO()
    out.write("slice_index,position_mm,time_s,cardiac_phase,volume_k\n")
    for s in report.slices:
        time = "" if not np.isfinite(s.time_s) else f"{s.time_s:.6f}"
        out.write(f"{s.index},{s.position_mm:.4f},{time},{s.cardiac_phase:.6f},{s.volume_k:.4f}\n")
    return out.getvalue()


def plot_phases(report: PhaseReport, path, *, title: str = "Cardiac phase per slice") -> None:
    """Phase per slice like the paper's Fig. 4, motion-free window shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    phases = report.phases
    index = np.arange(len(phases))
    fig, ax = plt.subplots(figsize=(7.5, 4.0), dpi=120)
    lo, hi = MOTION_FREE_WINDOW
    ax.axhspan(lo, hi, color="tab:green", alpha=0.15, label=f"motion-free window {lo}-{hi}")
    ax.plot(index, phases, ".", ms=4, color="tab:blue", label="slice phase")
    ax.axhline(report.volume_cardiac_phase, color="k", ls="--", lw=1,
               label=f"volume phase {report.volume_cardiac_phase:.3f} (mean)")
    for j in report.jumps:
        ax.axvline(j + 0.5, color="tab:red", lw=0.8, alpha=0.6)
    ax.set_xlabel("slice index (along the slice normal)")
    ax.set_ylabel("cardiac phase")
    ax.set_ylim(0, 1)
    ax.set_xlim(-1, max(len(phases), 2))
    ax.set_title(f"{title}\nsource: {report.source}", fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_phase_report(report: PhaseReport, out_dir, *, extra: dict | None = None) -> dict:
    """Write ``phases.csv``, ``phases.json`` and ``phases.png`` into ``out_dir``.

    Returns the paths written, by name.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {name: out_dir / f"phases.{name}" for name in ("csv", "json", "png")}
    write_text_atomic(paths["csv"], _csv_text(report))
    payload = report.to_dict()
    if extra:
        payload.update(extra)
    write_text_atomic(paths["json"], json.dumps(payload, indent=1) + "\n")
    plot_phases(report, paths["png"])
    return paths
