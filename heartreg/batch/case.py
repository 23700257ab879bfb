"""One case of a batch: the task a Dask worker runs.

:func:`run_case` takes paths in and returns a small :class:`CaseRecord`.  It
runs the case's single commands (``heartreg phases``, ``model``, ``register``:
the CLI's own parser and command functions, so the bytes are those of the
commands typed by hand) into a staging folder beside the output, writes
``case.json`` and a thumbnail, and renames the staging folder to
``OUT/<case>/`` in one step::

    OUT/<case>/phases/          phases.csv, phases.json, phases.png
    OUT/<case>/model/           heart.ply, heart.stl, model.json, model.png
    OUT/<case>/registration/    registration.json, sweep.csv, figures (with a session)
    OUT/<case>/thumbnail.png    small picture for the batch's index.html
    OUT/<case>/case.json        the record: key, numbers, times

A case is a pure function of its inputs and options: its *key* hashes the
content of every input (study, session, mask, any path option), the command
lines (with the inputs' paths replaced by their roles, so a moved cohort keeps
its keys) and heartreg's version.  A case whose ``case.json`` holds the same
key is done and is not run again.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import tempfile
import time
import uuid
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from heartreg import __version__
from heartreg.batch.cohort import COMMANDS, Case
from hrcore.errors import HeartregError
from imaging.files import umask_mode, write_text_atomic

__all__ = ["CASE_FILE", "CaseError", "CaseRecord", "case_key", "read_case_record", "run_case"]

#: The record of a finished case, inside its folder (written last, renamed in with it).
CASE_FILE = "case.json"
#: Folder of each command's outputs inside ``OUT/<case>/``.
SUBFOLDER = {"phases": "phases", "model": "model", "register": "registration"}
THUMBNAIL = "thumbnail.png"
THUMBNAIL_PX = 240
_CHUNK = 1 << 20


@dataclass(frozen=True)
class CaseRecord:
    """What a case returns to the client: small, picklable, no arrays.

    Attributes
    ----------
    case : str
        The case name.
    status : {'done', 'failed', 'not run'}
    reused : bool
        Done by an earlier run with the same key (nothing ran now).
    key : str
        SHA-256 of the case's inputs and options (hex); ``""`` when the
        inputs could not be read.
    error : str
        One line, ``"<command>: <message>"``; ``""`` unless failed.  Input
        paths appear as their roles (``<study>``, ``<session>``, ...).
    values : dict
        Summary numbers read from the written outputs (phi_C*, heart volume,
        frame angles, phi_R*, errors); see :data:`heartreg.batch.report.COLUMNS`.
    times_s : dict
        Wall time of each command and in total, seconds.
    notes : tuple of str
        Warnings the commands gave.
    """

    case: str
    status: str
    reused: bool = False
    key: str = ""
    error: str = ""
    values: dict = field(default_factory=dict)
    times_s: dict = field(default_factory=dict)
    notes: tuple = ()

    def to_json(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_json(cls, data: dict) -> CaseRecord:
        names = cls.__dataclass_fields__
        data = {k: v for k, v in data.items() if k in names}
        data["notes"] = tuple(data.get("notes", ()))
        return cls(**data)


class CaseError(HeartregError, ValueError):
    """A case's inputs or output folder cannot be used (the message says which and what to do)."""


# ------------------------------------------------------------------ key
def _digest_path(path: Path, role: str):
    """SHA-256 of a file's bytes, or of a folder's relative file names and bytes (sorted)."""
    h = hashlib.sha256()
    if path.is_file():
        files = [(path.name, path)]
    elif path.is_dir():
        files = sorted((p.relative_to(path).as_posix(), p) for p in path.rglob("*") if p.is_file())
    else:
        raise CaseError(f"{role} {path} does not exist; fix the cohort's path")
    for rel, p in files:
        h.update(rel.encode() + b"\0")
        with open(p, "rb") as f:
            while chunk := f.read(_CHUNK):
                h.update(chunk)
        h.update(b"\0")
    return h.hexdigest()


def _placeholders(case: Case) -> list[tuple[str, str]]:
    """(path, role token) for every input, longest path first (so nested paths replace right)."""
    pairs = [(p, f"<{role}>") for role, p in case.inputs.items() if p]
    return sorted(pairs, key=lambda pair: -len(pair[0]))


def _redact(text: str, pairs) -> str:
    for path, token in pairs:
        text = text.replace(path, token)
    return text


def _without_file_names(case: Case):
    """A function dropping the names of the case's input files from a text (they can name the patient)."""
    from hrcore.redact import PSEUDONYM_IN_TEXT, UID_IN_TEXT, file_namer

    namers = [file_namer(p) for role, p in case.inputs.items() if p and role != "session"]

    def clean(text: str) -> str:
        for namer in namers:
            text = namer(text)
        # a series' UID, or its pseudonym (the refusals print them): summary.csv holds none
        return PSEUDONYM_IN_TEXT.sub("<uid>", UID_IN_TEXT.sub("<uid>", text))

    return clean


def case_key(case: Case) -> str:
    """The case's key: SHA-256 (hex) of its inputs' contents, its command lines and heartreg's version.

    Raises
    ------
    CaseError
        An input path does not exist.
    """
    pairs = _placeholders(case)
    payload = {
        "format": "heartreg-batch-case-key",
        "version": 1,
        "heartreg": __version__,
        "session": case.has_session,
        "argv": {c: [_redact(a, pairs) for a in case.argv[c]] for c in COMMANDS},
        "inputs": {role: _digest_path(Path(p), role) for role, p in sorted(case.inputs.items()) if p},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


# ------------------------------------------------------------------ values
def _read_json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.exists() else {}


def _values(case_dir: Path) -> dict:
    """The summary numbers of a finished case, read back from its output files."""
    phases = _read_json(case_dir / "phases" / "phases.json")
    model = _read_json(case_dir / "model" / "model.json")
    reg = _read_json(case_dir / "registration" / "registration.json")
    values = {
        "phi_c": phases.get("volume_cardiac_phase"),
        "phi_c_source": phases.get("source"),
        "n_slices": phases.get("n_slices"),
        "in_window": phases.get("fraction_in_window"),
    }
    if model:
        euler = model.get("euler_xyz_deg", [None] * 3)
        R = np.asarray(model["T_heart_from_patient"], dtype=float)[:3, :3]
        volume = model.get("volume_mm3")
        values.update({
            "heart_volume_ml": None if volume is None else float(volume) / 1000.0,
            "n_faces": model.get("n_faces"),
            "euler_x_deg": euler[0], "euler_y_deg": euler[1], "euler_z_deg": euler[2],
            # the heart's long (z) axis in patient LPS: the third row of the rotation patient -> heart
            "axis_z_l": float(R[2, 0]), "axis_z_p": float(R[2, 1]), "axis_z_s": float(R[2, 2]),
            "n_fiducials": len(model.get("fiducials_patient_mm") or []),
        })
    if reg:
        trust = reg.get("trust") or {}  # registration.json's Trust.to_dict()
        values.update({
            "phi_r": reg.get("respiration_phase"),
            "rms_mm": reg.get("rms_mm"),
            "fre_mm": reg.get("fre_mm"),
            "translation_from_t0_mm": reg.get("translation_distance_mm"),
            "rotation_from_t0_deg": reg.get("rotation_distance_deg"),
            "delta_static_mean_mm": reg.get("delta_static_mean_mm"),
            "n_points": reg.get("n_points"),
            "n_excluded": len(reg.get("exclusions") or []),
            "trust": trust.get("level"),
            "trust_reasons": "; ".join(r["code"] for r in trust.get("reasons", [])) or None,
        })
    return {k: v for k, v in values.items() if v is not None}


def _thumbnail(case_dir: Path) -> None:
    """A small PNG of the model (or, without offscreen 3-D, of the slice phases) for the index page."""
    from PIL import Image

    for source in (case_dir / "model" / "model.png", case_dir / "phases" / "phases.png"):
        if source.exists():
            with Image.open(source) as image:
                image = image.convert("RGB")
                image.thumbnail((THUMBNAIL_PX, THUMBNAIL_PX))
                image.save(case_dir / THUMBNAIL, optimize=True)
            return


# ------------------------------------------------------------------ running
def _command_lines(case: Case, staging: Path) -> list[tuple[str, list[str]]]:
    """Each command's full argument list, writing into ``staging``."""
    lines = [
        ("phases", ["phases", case.study, "-o", str(staging / "phases"), "-q", *case.argv["phases"]]),
        ("model", ["model", case.study, "-o", str(staging / "model"), "-q", *case.argv["model"]]),
    ]
    if case.has_session:
        lines.append(("register", ["register", str(staging / "model"), case.session,
                                   "-o", str(staging / "registration"), "-q", *case.argv["register"]]))
    return lines


def _run_command(argv: list[str], notes: list[str]) -> None:
    """Run one single command as ``heartreg`` would, its printed summary discarded, warnings kept."""
    from heartreg.cli import command_parser

    args = command_parser().parse_args(argv)
    out, err = io.StringIO(), io.StringIO()
    with warnings.catch_warnings(record=True) as caught, \
            contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        warnings.simplefilter("default")
        args.func(args)
    notes.extend(str(w.message) for w in caught)
    notes.extend(line for line in err.getvalue().splitlines() if line.strip())


def _error_line(exc: BaseException) -> str:
    """One line for the summary: a refusal as the command prints it, anything else with its type."""
    from hrcore.output import refusal_line

    line = refusal_line(exc)
    if line is not None:
        return line
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"internal error ({type(exc).__name__}: {text}); a bug in heartreg, please report it"


def remove_leftovers(out: Path, name: str) -> None:
    """Staging folders a stopped run left for this case (only this case's: other cases may be running)."""
    for pattern in (f".{name}.staging-*", f".{name}.old-*"):
        for leftover in out.glob(pattern):
            shutil.rmtree(leftover, ignore_errors=True)


def _place(staging: Path, final: Path) -> None:
    """Move the staged case into place in one rename (an earlier version is swapped out first)."""
    os.chmod(staging, umask_mode(directory=True))
    if final.exists():
        old = final.with_name(f".{final.name}.old-{uuid.uuid4().hex[:8]}")
        os.rename(final, old)
        os.rename(staging, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(staging, final)


def read_case_record(case_dir) -> CaseRecord | None:
    """The record of a finished case folder, or None when there is none (or it is unreadable)."""
    try:
        data = json.loads((Path(case_dir) / CASE_FILE).read_text())
    except (OSError, ValueError):
        return None
    if data.get("format") != "heartreg-batch-case":
        return None
    return CaseRecord.from_json(data["record"])


def run_case(case: Case, out_dir: str) -> CaseRecord:
    """Run one case into ``out_dir/<case>/`` (or find it done) and return its record.

    Never raises for a problem of the case: a failure comes back as a record
    with ``status='failed'`` and a one-line ``error``, and leaves no
    ``out_dir/<case>/`` behind (an earlier finished version stays as it was).

    Parameters
    ----------
    case : Case
    out_dir : str
        The batch's output folder (absolute; on a cluster, seen by every worker).

    Returns
    -------
    CaseRecord
    """
    t_start = time.perf_counter()
    out = Path(out_dir)
    final = out / case.name
    pairs = _placeholders(case)
    step = "inputs"
    try:
        key = case_key(case)
        earlier = read_case_record(final)
        if earlier is not None and earlier.status == "done" and earlier.key == key:
            return CaseRecord(case=case.name, status="done", reused=True, key=key, values=earlier.values,
                              times_s=earlier.times_s, notes=earlier.notes)
        if final.exists() and earlier is None:
            raise CaseError(f"{final.name} in the output folder was not written by heartreg batch; "
                            "move it away or choose another output folder")
    except Exception as exc:  # noqa: BLE001 - every failure becomes the case's record
        return CaseRecord(case=case.name, status="failed",
                          error=f"{step}: {_without_file_names(case)(_redact(_error_line(exc), pairs))}",
                          times_s={"total": time.perf_counter() - t_start})

    remove_leftovers(out, case.name)
    staging = Path(tempfile.mkdtemp(prefix=f".{case.name}.staging-", dir=out))
    pairs = pairs + [(str(staging), f"<out>/{case.name}")]
    times, notes = {}, []
    try:
        for step, argv in _command_lines(case, staging):
            t = time.perf_counter()
            _run_command(argv, notes)
            times[step] = time.perf_counter() - t
        step = "record"
        _thumbnail(staging)
        times["total"] = time.perf_counter() - t_start
        unnamed = _without_file_names(case)
        notes = list(dict.fromkeys(unnamed(_redact(" ".join(n.split()), pairs)) for n in notes))
        record = CaseRecord(case=case.name, status="done", key=key, values=_values(staging), times_s=times,
                            notes=tuple(notes))
        write_text_atomic(staging / CASE_FILE, json.dumps({
            "format": "heartreg-batch-case",
            "version": 1,
            "heartreg": __version__,
            "commands": {c: ["heartreg", *(_redact(a, pairs) for a in argv)] for c, argv in
                         _command_lines(case, staging)},
            "record": record.to_json(),
        }, indent=1) + "\n")
        _place(staging, final)
        return record
    except Exception as exc:  # noqa: BLE001 - every failure becomes the case's record
        times["total"] = time.perf_counter() - t_start
        return CaseRecord(case=case.name, status="failed", key=key, times_s=times,
                          error=f"{step}: {_without_file_names(case)(_redact(_error_line(exc), pairs))}")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
