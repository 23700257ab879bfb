"""Writing a PhaseReport (``phases.csv``, ``phases.json``, ``phases.png``) and reading it back."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError
from hrcore.figlayout import PNG_OPTIONS, fixed_margins, subplots
from hrcore.output import staged_output
from imaging.files import atomic_path, write_text_atomic
from imaging.phase import JUMP_THRESHOLD, MOTION_FREE_WINDOW, PhaseReport, SlicePhase

__all__ = ["PhaseFileError", "write_phase_report", "read_phase_report", "plot_phases"]

#: The file that marks a folder as a phase report (``--overwrite`` replaces such a folder only).
JSON_FILE = "phases.json"
#: ``format`` and ``format_version`` of phases.json (docs/formats.md), as model.json and registration.json name theirs.
FORMAT, FORMAT_VERSION = "heartreg-phases", 1

#: Columns of ``phases.csv``, in order.
CSV_COLUMNS = ("slice_index", "position_mm", "time_s", "cardiac_phase", "volume_k")


class PhaseFileError(HeartregError, ValueError):
    """A ``phases.csv``/``phases.json`` pair that is not one :func:`write_phase_report` wrote."""


def _csv_text(report: PhaseReport) -> str:
    out = io.StringIO()
    out.write(",".join(CSV_COLUMNS) + "\n")
    for s in report.slices:
        time = "" if not np.isfinite(s.time_s) else f"{s.time_s:.6f}"
        out.write(f"{s.index},{s.position_mm:.4f},{time},{s.cardiac_phase:.6f},{s.volume_k:.4f}\n")
    return out.getvalue()


def plot_phases(report: PhaseReport, path, *, title: str = "Cardiac phase per slice") -> None:
    """Phase per slice like the paper's Fig. 4, motion-free window shaded.

    Examples
    --------
    >>> import tempfile
    >>> from imaging import compute_phase_report, load_study, plot_phases
    >>> path = tempfile.mkdtemp() + "/phases.png"
    >>> plot_phases(compute_phase_report(load_study("sample_dicom/ct")), path)
    """
    from matplotlib.figure import Figure  # no pyplot: no global backend state, a second less to import

    phases = report.phases
    index = np.arange(len(phases))
    fig = Figure(figsize=(7.5, 4.0), dpi=120)
    ax = subplots(fig)
    lo, hi = MOTION_FREE_WINDOW
    ax.axhspan(lo, hi, color="tab:green", alpha=0.15, label=f"motion-free window {lo}-{hi}")
    ax.plot(index, phases, ".", ms=4, color="tab:blue", label="slice phase")
    ax.axhline(report.volume_cardiac_phase, color="k", ls="--", lw=1,
               label=f"volume phase {report.volume_cardiac_phase:.3f} (mean)")
    for k, j in enumerate(report.jumps):  # named in the legend: unexplained red lines (a page audit)
        ax.axvline(j + 0.5, color="tab:red", lw=0.8, alpha=0.6,
                   label=f"phase jump > {JUMP_THRESHOLD:g} between slices" if k == 0 else None)
    ax.set_xlabel("slice index (along the slice normal)")
    ax.set_ylabel("cardiac phase")
    ax.set_ylim(0, 1)
    ax.set_xlim(-1, max(len(phases), 2))
    ax.set_title(f"{title}\nsource: {report.source}", fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    fixed_margins(fig, left_in=0.65, right_in=0.15, bottom_in=0.5, top_in=0.5)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", pil_kwargs=PNG_OPTIONS)


def write_phase_report(report: PhaseReport, out_dir, *, extra: dict | None = None, overwrite: bool = False,
                       inputs=()) -> dict:
    """Write ``phases.csv``, ``phases.json`` and ``phases.png`` into the folder ``out_dir``, atomically.

    The files are written into a staging folder beside ``out_dir`` that
    replaces it in one rename (:func:`hrcore.output.staged_output`): a failure
    leaves ``out_dir`` as it was, and no file of an earlier run survives.

    Parameters
    ----------
    report : PhaseReport
    out_dir : str or Path
        Created if missing; an existing non-empty folder is refused unless ``overwrite``.
    extra : dict, optional
        More keys for ``phases.json`` (the command's series UID and volume notes).
    overwrite : bool
        Replace an existing non-empty ``out_dir`` (``--overwrite``).
    inputs : iterable of str or Path
        The inputs (study folder, QRS file): ``out_dir`` may not be, lie in or contain one.

    Returns
    -------
    dict
        The paths written (in ``out_dir``), by name: ``csv``, ``json``, ``png``.

    Raises
    ------
    hrcore.output.OutputError
        A refused ``out_dir`` or a full disk.

    Examples
    --------
    >>> import tempfile
    >>> from imaging import compute_phase_report, load_study, read_phase_report, write_phase_report
    >>> report = compute_phase_report(load_study("sample_dicom/ct"))
    >>> written = write_phase_report(report, tempfile.mkdtemp() + "/phases")
    >>> sorted(written)
    ['csv', 'json', 'png']
    >>> read_phase_report(written["json"].parent).volume_cardiac_phase == report.volume_cardiac_phase
    True
    """
    out_dir = Path(out_dir)
    with staged_output(out_dir, inputs=inputs, overwrite=overwrite, earlier=(JSON_FILE,)) as stage:
        write_text_atomic(stage / "phases.csv", _csv_text(report))
        payload = {"format": FORMAT, "format_version": FORMAT_VERSION, **report.to_dict()}
        if extra:
            payload.update(extra)
        write_text_atomic(stage / JSON_FILE, json.dumps(payload, indent=1) + "\n")
        plot_phases(report, stage / "phases.png")
    return {name: out_dir / f"phases.{name}" for name in ("csv", "json", "png")}


def read_phase_report(out_dir) -> PhaseReport:
    """Read back the :class:`PhaseReport` that :func:`write_phase_report` wrote into ``out_dir``.

    Parameters
    ----------
    out_dir : str or Path
        The folder holding ``phases.json`` and ``phases.csv``.

    Returns
    -------
    PhaseReport
        The report written, its slices to the precision of ``phases.csv``
        (position and volume index 1e-4, time and phase 1e-6); writing it again
        gives the same bytes (with the same ``extra``, whose keys are not part of it).

    Raises
    ------
    PhaseFileError
        A file missing, not the format written, or the two files disagree.

    Examples
    --------
    >>> import tempfile
    >>> from imaging.phase import PhaseReport, SlicePhase
    >>> report = PhaseReport(slices=(SlicePhase(0, -10.0, 0.5, 0.7, 0.0),), volume_cardiac_phase=0.7,
    ...                      circular_mean_phase=0.7, source="qrs.csv", clock="trigger time",
    ...                      r_peaks_s=np.array([0.0, 1.0]), jumps=(), fraction_in_window=1.0)
    >>> with tempfile.TemporaryDirectory() as out:
    ...     _ = write_phase_report(report, out)
    ...     read_phase_report(out).slices == report.slices
    True
    """
    out_dir = Path(out_dir)
    json_path, csv_path = out_dir / JSON_FILE, out_dir / "phases.csv"
    for path in (json_path, csv_path):
        if not path.is_file():
            raise PhaseFileError(f"{path} not found: give the output folder of heartreg phases")
    try:
        meta = json.loads(json_path.read_text(encoding="utf-8"))
        # (files of heartreg before session 17 have neither field)
        fmt = (meta.get("format", FORMAT), meta.get("format_version", FORMAT_VERSION))
        if fmt != (FORMAT, FORMAT_VERSION):
            raise ValueError(f"it is {fmt[0]!r} version {fmt[1]!r}, not {FORMAT!r} version {FORMAT_VERSION}")
        report_fields = dict(
            volume_cardiac_phase=float(meta["volume_cardiac_phase"]),
            circular_mean_phase=float(meta["circular_mean_phase"]),
            source=str(meta["source"]),
            clock=str(meta["clock"]),
            r_peaks_s=np.array(meta["r_peaks_s"], dtype=np.float64).reshape(-1),
            jumps=tuple(int(j) for j in meta["jumps"]),
            fraction_in_window=float(meta["fraction_in_window"]),
            notes=tuple(str(n) for n in meta["notes"]),
        )
        n_slices = int(meta["n_slices"])
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise PhaseFileError(f"{json_path}: not a phases.json of heartreg ({type(exc).__name__}: {exc})") from None
    slices = _read_slices(csv_path)
    if len(slices) != n_slices:
        raise PhaseFileError(f"{csv_path}: {len(slices)} slice rows, but {json_path.name} says n_slices = {n_slices}")
    report_fields["r_peaks_s"].setflags(write=False)
    return PhaseReport(slices=slices, **report_fields)


def _read_slices(path: Path) -> tuple[SlicePhase, ...]:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise PhaseFileError(f"{path}: not readable ({exc})") from None
    if not lines or tuple(lines[0].split(",")) != CSV_COLUMNS:
        raise PhaseFileError(f"{path}: the header must be {','.join(CSV_COLUMNS)}")
    slices = []
    for row, line in enumerate(lines[1:], start=2):
        cells = line.split(",")
        try:
            if len(cells) != len(CSV_COLUMNS):
                raise ValueError(f"{len(cells)} cells")
            index, position, time, phase, k = cells
            slices.append(SlicePhase(int(index), float(position), float(time) if time else float("nan"),
                                     float(phase), float(k)))
        except ValueError as exc:
            raise PhaseFileError(f"{path}: line {row} is not a slice row ({exc})") from None
    return tuple(slices)
