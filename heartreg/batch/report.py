"""The batch's summary: ``summary.csv`` (one row per case) and ``index.html``.

Both hold the case names, their status and numbers, errors and times: no
input path, series identity or anything else from the studies' headers.  The
page is self-contained (thumbnails embedded) and links each case's folder.
"""

from __future__ import annotations

import base64
import csv
import html
import io
from pathlib import Path

from heartreg.batch.case import THUMBNAIL, CaseRecord
from imaging.files import write_text_atomic

__all__ = ["COLUMNS", "index_html", "summary_csv"]

#: (column, header meaning) of ``summary.csv``, in order.
COLUMNS = (
    ("case", "case name (its folder in OUT)"),
    ("status", "done, failed or not run"),
    ("reused", "done by an earlier run with the same inputs and options (nothing ran now)"),
    ("phi_c", "image cardiac phase phi_C* (mean slice phase)"),
    ("phi_c_source", "R-peak source of the slice phases"),
    ("n_slices", "CT slices"),
    ("in_window", "fraction of slices in the motion-free window 0.6-0.8"),
    ("heart_volume_ml", "volume enclosed by the heart mesh, mL"),
    ("n_faces", "faces of the heart mesh"),
    ("euler_x_deg", "heart frame, intrinsic X-Y-Z Euler angles, deg"),
    ("euler_y_deg", ""),
    ("euler_z_deg", ""),
    ("axis_z_l", "heart long axis (apex to base), unit vector in patient LPS"),
    ("axis_z_p", ""),
    ("axis_z_s", ""),
    ("n_fiducials", "skin fiducials found"),
    ("phi_r", "respiration phase phi_R* (register's estimator)"),
    ("rms_mm", "RMS point-to-surface error at phi_R*, mm"),
    ("fre_mm", "fiducial registration error, mm"),
    ("translation_from_t0_mm", "final registration's distance from the fiducial seed T0, mm"),
    ("rotation_from_t0_deg", "deg"),
    ("delta_static_mean_mm", "mean delta between static and spatiotemporal registration, mm"),
    ("n_points", "registered attachment points"),
    ("n_excluded", "excluded attachment points"),
    ("trust", "how far to trust the registration: ok, caution or poor (registration.json)"),
    ("trust_reasons", "why not ok: the reasons' codes"),
    ("time_phases_s", "wall time of heartreg phases, s"),
    ("time_model_s", "of heartreg model, s"),
    ("time_register_s", "of heartreg register, s"),
    ("time_total_s", "of the whole case (with hashing its inputs), s"),
    ("error", "why the case failed: the command and its one-line message"),
    ("notes", "warnings the commands gave"),
)


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return format(value, ".10g")
    return str(value)


def _row(record: CaseRecord) -> dict:
    row = {"case": record.case, "status": record.status, "reused": record.reused if record.status == "done" else None,
           "error": record.error, "notes": " | ".join(record.notes)}
    row.update(record.values)
    for step in ("phases", "model", "register", "total"):
        row[f"time_{step}_s"] = record.times_s.get(step)
    return row


def summary_csv(records, path) -> Path:
    """Write ``summary.csv``: one row per record, the columns of :data:`COLUMNS`."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([name for name, _ in COLUMNS])
    for record in records:
        row = _row(record)
        writer.writerow([_cell(row.get(name)) for name, _ in COLUMNS])
    write_text_atomic(path, buffer.getvalue())
    return Path(path)


def _fmt(value, spec: str) -> str:
    return "" if value is None else format(value, spec)


_STYLE = """
body { font-family: sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; }
td, th { border-bottom: 1px solid #ddd; padding: 4px 10px; text-align: left; vertical-align: middle; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.failed td { background: #fde8e8; }
tr.notrun td { color: #888; }
img { display: block; max-width: 240px; max-height: 240px; }
td.trust-poor { background: #fdeeee; color: #b42318; font-weight: 600; }
td.trust-caution { background: #fdf6e7; color: #8a5a00; font-weight: 600; }
p.untrusted { border-left: 6px solid #b42318; background: #fdeeee; padding: .4em .9em; }
"""


def index_html(records, path, *, out_dir) -> Path:
    """Write ``index.html``: per case a thumbnail, its numbers and a link to its folder (self-contained)."""
    out_dir = Path(out_dir)
    counts = {s: sum(r.status == s for r in records) for s in ("done", "failed", "not run")}
    # a poor or caution registration stood as plain text among ok ones (a page audit): marked, and counted on top
    levels = {lvl: [r.case for r in records if r.values.get("trust") == lvl] for lvl in ("poor", "caution")}
    untrusted = "; ".join(f"{len(names)} {lvl} ({', '.join(map(html.escape, names))})"
                          for lvl, names in levels.items() if names)
    banner = (f'<p class="untrusted"><b>Registrations not trusted:</b> {untrusted}; see each case\'s trust '
              "reasons.</p>" if untrusted else "")
    rows = []
    for r in records:
        v = r.values
        thumb = ""
        picture = out_dir / r.case / THUMBNAIL
        if r.status == "done" and picture.exists():
            data = base64.b64encode(picture.read_bytes()).decode()
            thumb = f'<a href="{html.escape(r.case)}/"><img alt="{html.escape(r.case)}" src="data:image/png;base64,{data}"></a>'
        name = html.escape(r.case)
        link = f'<a href="{name}/">{name}</a>' if r.status == "done" else name
        status = r.status + (" (earlier run)" if r.reused else "")
        detail = html.escape(r.error) if r.error else html.escape(" | ".join(r.notes))
        cls = {"failed": "failed", "not run": "notrun"}.get(r.status, "")
        trust = html.escape(str(v.get("trust", "")))
        rows.append(
            f'<tr class="{cls}"><td>{thumb}</td><td>{link}</td><td>{html.escape(status)}</td>'
            f'<td class="num">{_fmt(v.get("phi_c"), ".4f")}</td>'
            f'<td class="num">{_fmt(v.get("heart_volume_ml"), ".1f")}</td>'
            f'<td class="num">{", ".join(_fmt(v.get(k), ".1f") for k in ("euler_x_deg", "euler_y_deg", "euler_z_deg")) if "euler_x_deg" in v else ""}</td>'
            f'<td class="num">{_fmt(v.get("phi_r"), ".2f")}</td>'
            f'<td class="num">{_fmt(v.get("rms_mm"), ".3f")}</td>'
            f'<td class="num">{_fmt(v.get("fre_mm"), ".2f")}</td>'
            f'<td class="trust-{trust}">{trust}'
            f'{"<br>" + html.escape(v["trust_reasons"]) if v.get("trust_reasons") else ""}</td>'
            f'<td class="num">{_fmt(r.times_s.get("total"), ".1f")}</td>'
            f"<td>{detail}</td></tr>"
        )
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>heartreg batch</title><style>{_STYLE}</style></head>
<body>
<h1>heartreg batch</h1>
<p>{len(records)} case(s): {counts['done']} done, {counts['failed']} failed, {counts['not run']} not run.
Every number is in <a href="summary.csv">summary.csv</a>; each case's outputs are in its folder.</p>
{banner}
<table>
<tr><th></th><th>case</th><th>status</th><th>phi_C*</th><th>heart volume (mL)</th><th>heart frame Euler XYZ (deg)</th>
<th>phi_R*</th><th>RMS (mm)</th><th>FRE (mm)</th><th>trust</th><th>time (s)</th><th>error / notes</th></tr>
{chr(10).join(rows)}
</table>
</body></html>
"""
    write_text_atomic(path, page)
    return Path(path)
