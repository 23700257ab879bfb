"""A cohort: the cases of a batch, read from a CSV file or a folder of studies.

A case is the three single commands it would be typed as::

    heartreg phases   STUDY -o OUT/<case>/phases        [options for phases]
    heartreg model    STUDY -o OUT/<case>/model         [--mask MASK] [options for model]
    heartreg register OUT/<case>/model SESSION -o OUT/<case>/registration   [options for register]

(``register`` only when the case has a session).  The ``options`` column holds
flags of those commands, written as on the command line; each flag goes to
every one of the three commands that has it (``--qrs`` and ``--series`` to
``phases`` and ``model``, ``--faces`` to ``model``, ``--step`` to
``register``).  Paths in the CSV, the flags' included, are relative to the
CSV file's folder.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

from hrcore.errors import HeartregError, UsageError

__all__ = ["COMMANDS", "Case", "CohortError", "read_cohort", "select_part"]

#: The single commands a case runs, in order.
COMMANDS = ("phases", "model", "register")

#: Flags the batch sets itself (outputs, overwriting, quiet); refused in ``options``.
_RESERVED = {"-o", "--out-dir", "--overwrite", "-q", "--quiet", "--list-series", "-h", "--help"}

#: A case name: it names the case's output folder.
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")

_COLUMNS = ("case", "study", "session", "mask", "options")


class CohortError(HeartregError, ValueError):
    """The cohort file or folder cannot be read as asked (the message names the file and row)."""


@dataclass(frozen=True)
class Case:
    """One case of a cohort: its name, inputs and each command's arguments.

    Attributes
    ----------
    name : str
        Names the case's output folder ``OUT/<name>/`` (letters, digits, ``._-``).
    study : str
        Absolute path of the DICOM study folder.
    session : str
        Absolute path of the session folder, ``""`` for phases and model only.
    argv : dict of str to tuple of str
        Extra arguments of each command (``phases``, ``model``, ``register``),
        paths absolute; the inputs and outputs are added when the case runs.
    inputs : dict of str to str
        Every input path of the case by role (``study``, ``session``,
        ``model --mask``, ``phases --qrs``, ...): what its key hashes.
    unnamed_study : str
        The study as the cohort gives it when the cohort gives no name
        (the case is :func:`default_name` of it), else ``""``.
    """

    name: str
    study: str
    session: str
    argv: dict
    inputs: dict
    unnamed_study: str = ""

    @property
    def has_session(self) -> bool:
        return bool(self.session)


def _command_actions() -> dict[str, dict[str, argparse.Action]]:
    """Option string -> argparse action, for each of :data:`COMMANDS`, from the CLI's own parsers."""
    from heartreg.cli import command_parser

    parser = command_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    table = {}
    for command in COMMANDS:
        actions = {}
        for action in sub.choices[command]._actions:
            for flag in action.option_strings:
                actions[flag] = action
        table[command] = actions
    return table


def _n_values(action: argparse.Action, tokens: list[str], flag: str, where: str) -> int:
    """How many of ``tokens`` (those after ``flag``) are its values."""
    nargs = action.nargs
    if nargs is None:
        n = 1
    elif isinstance(nargs, int):
        n = nargs
    elif nargs == "?":
        n = 1 if tokens and not tokens[0].startswith("--") else 0
    else:  # "+" / "*": up to the next flag
        n = 0
        while n < len(tokens) and not (tokens[n].startswith("-") and not _is_number(tokens[n])):
            n += 1
    if len(tokens) < n:
        raise CohortError(f"{where}: option {flag} needs {n} value(s)")
    return n


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def route_options(text: str, where: str, table=None) -> dict[str, list[str]]:
    """Split an ``options`` cell into each command's arguments.

    Parameters
    ----------
    text : str
        Flags as on the command line (shell quoting), e.g. ``--faces 8000 --step 0.02``.
    where : str
        Names the cell in error messages (``cohort.csv row 3``).

    Returns
    -------
    dict of str to list of str
        Arguments for each of :data:`COMMANDS` (every flag goes to every command that has it).
    """
    table = table if table is not None else _command_actions()
    try:
        tokens = shlex.split(text)
    except ValueError as exc:
        raise CohortError(f"{where}: options {text!r} cannot be split ({exc})") from None
    routed = {command: [] for command in COMMANDS}
    i = 0
    while i < len(tokens):
        token = tokens[i]
        flag, eq, _ = token.partition("=") if token.startswith("--") else (token, "", "")
        if flag in _RESERVED:
            raise CohortError(f"{where}: option {flag} is set by the batch itself; remove it from options")
        owners = [c for c in COMMANDS if flag in table[c]]
        if not token.startswith("-") or not owners:
            raise CohortError(
                f"{where}: {token!r} is not an option of heartreg {', '.join(COMMANDS)}; "
                "see heartreg COMMAND --help"
            )
        action = table[owners[0]][flag]
        n = 0 if eq else _n_values(action, tokens[i + 1:], flag, where)
        group = tokens[i:i + 1 + n]
        for command in owners:
            routed[command].extend(group)
        i += 1 + n
    return routed


def _names_a_file(action, raw: str) -> bool:
    """Whether an option's value is a path: options of type Path, and those whose value may be one
    (``model --seed``: X,Y,Z or a markups file)."""
    if action.type is Path:
        return True
    try:
        return isinstance(action.type(raw), Path) if callable(action.type) else False
    except (TypeError, ValueError, argparse.ArgumentTypeError):
        return False  # a bad value: the command's own parser says so (_check_parse)


def _absolute_paths(argv: list[str], actions: dict, base: Path) -> tuple[list[str], dict[str, str]]:
    """``argv`` with the values of path options made absolute (relative to ``base``), and those paths."""
    out, paths = [], {}
    i = 0
    while i < len(argv):
        token = argv[i]
        flag, eq, value = token.partition("=") if token.startswith("--") else (token, "", "")
        action = actions.get(flag)
        raw = value if eq else (argv[i + 1] if i + 1 < len(argv) else "")
        if action is not None and action.nargs is None and _names_a_file(action, raw):
            path = str((base / raw).resolve()) if raw else raw
            paths[flag] = path
            out.append(f"{flag}={path}" if eq else flag)
            if not eq:
                out.append(path)
                i += 1
        else:
            out.append(token)
        i += 1
    return out, paths


def default_name(study: str) -> str:
    """A case's name when the cohort gives none: ``case-`` and 10 hex digits of the SHA-256 of the study's path as
    the cohort gives it (a folder's name is often the patient's: it would name the output folder, the summary's
    rows and the page; the hash is the same on every run, so a run goes on where the last one stopped)."""
    return "case-" + hashlib.sha256(study.encode()).hexdigest()[:10]


def _make_case(name, study, session, mask, options, *, base: Path, where: str, table) -> Case:
    unnamed = "" if name else study
    name = name or default_name(study)
    if not _NAME.match(name):
        raise CohortError(
            f"{where}: case name {name!r} must start with a letter or digit and hold only letters, digits, "
            "'.', '_' and '-' (it names the case's output folder)"
        )
    if not study:
        raise CohortError(f"{where}: no study folder; fill the study column")
    routed = route_options(options, where, table)
    if mask:
        if any(t.split("=")[0] == "--mask" for t in routed["model"]):
            raise CohortError(f"{where}: the mask is given twice (mask column and --mask in options); keep one")
        routed["model"] += ["--mask", mask]
    if not session and routed["register"]:
        only = [t for t in routed["register"] if t.startswith("-") and
                not any(t.split("=")[0] in table[c] for c in ("phases", "model"))]
        if only:
            raise CohortError(f"{where}: {' '.join(only)} is an option of register, but the case has no session")
    inputs = {"study": str((base / study).resolve())}
    if session:
        inputs["session"] = str((base / session).resolve())
    argv = {}
    for command in COMMANDS:
        args, paths = _absolute_paths(routed[command], table[command], base)
        argv[command] = tuple(args)
        inputs.update({f"{command} {flag}": path for flag, path in paths.items()})
    if not session:
        argv["register"] = ()
    _check_parse(argv, inputs, where)
    return Case(name=name, study=inputs["study"], session=inputs.get("session", ""), argv=argv, inputs=inputs,
                unnamed_study=unnamed)


def _check_parse(argv: dict, inputs: dict, where: str) -> None:
    """Parse each command line as the CLI will and make its options (bad values fail here, before any work: a
    cohort's '--faces -5' failed each case once it ran, an audit)."""
    from heartreg.cli import CommandLineError, command_parser
    from heartreg.cli_commands import _model_options, _registration_options

    options = {"model": _model_options, "register": _registration_options}
    parser = command_parser()
    lines = {"phases": ["phases", inputs["study"], "-o", "OUT"], "model": ["model", inputs["study"], "-o", "OUT"]}
    if "session" in inputs:
        lines["register"] = ["register", "MODEL", inputs["session"], "-o", "OUT"]
    for command, head in lines.items():
        try:
            args = parser.parse_args([*head, *argv[command]])
            options.get(command, lambda a: None)(args)
        except (CommandLineError, UsageError) as exc:
            raise CohortError(f"{where}: heartreg {command}: {exc}") from None
        except HeartregError:  # an input it reads (a --seed file) missing or bad: that case fails, as for a study
            pass


#: Separators a spreadsheet writes a CSV with: ',' (English locales), ';' (where ',' is the decimal mark), tab.
_DELIMITERS = (",", ";", "\t")


def _read_rows(path: Path) -> list[tuple[int, list[str]]]:
    """The non-blank rows of a cohort CSV with their line numbers, as spreadsheets save it: UTF-8 (with or
    without Excel's byte order mark) or UTF-16 with its mark, CRLF or LF, separated by ',', ';' or tab (the
    header's separator: the one that makes 'study' a column of its own)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CohortError(f"cannot read cohort file {path}: {exc.strerror or exc}") from None
    encoding = "utf-16" if data[:2] in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise CohortError(
            f"cohort file {path} line {line} is not UTF-8 text (byte 0x{data[exc.start]:02x}; Excel's plain 'CSV' "
            "is written in the Windows code page): save it as 'CSV UTF-8' or UTF-8 text") from None
    first = next((ln for ln in text.splitlines() if ln.strip()), "")
    delimiter = next((d for d in _DELIMITERS
                      if "study" in (h.strip().lower() for h in next(csv.reader([first], delimiter=d), []))), ",")
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    rows, start = [], 1
    try:
        for row in reader:
            if any(cell.strip() for cell in row):
                rows.append((start, row))
            start = reader.line_num + 1
    except csv.Error as exc:
        raise CohortError(f"cohort file {path} line {reader.line_num}: {exc}; check its quotes") from None
    return rows


def _without_unnamed_columns(numbered, path: Path):
    """Drop columns without a header that hold nothing (a spreadsheet saves the empty columns after the last
    used one); refuse one that holds a value."""
    header = numbered[0][1]
    blank = [i for i, h in enumerate(header) if not h.strip()]
    if not blank:
        return numbered
    for n, row in numbered[1:]:
        for i in blank:
            if i < len(row) and row[i].strip():
                raise CohortError(f"cohort file {path.name} line {n}: {row[i].strip()!r} is in column {i + 1}, "
                                  "which has no name in the header; name it or move the value")
    keep = [i for i in range(len(header)) if i not in blank]
    return [(n, [row[i] for i in keep if i < len(row)] + row[len(header):]) for n, row in numbered]


def is_batch_output(folder) -> bool:
    """Whether ``folder`` holds an earlier ``heartreg batch`` output (its ``summary.csv``, whose
    header starts ``case,status``): not a study, and an output folder a batch may go on in."""
    try:
        with (Path(folder) / "summary.csv").open(encoding="utf-8") as f:
            return f.readline().startswith("case,status,")
    except (OSError, UnicodeDecodeError):
        return False


def read_cohort(path) -> tuple[Case, ...]:
    """Read a cohort: a CSV file (one row per case) or a folder of study folders.

    Parameters
    ----------
    path : path
        A CSV file with a header and the columns ``study`` (required),
        ``case``, ``session``, ``mask`` and ``options`` (optional; see the
        module docstring), paths relative to the file's folder; or a folder
        whose every subfolder is one study (phases and model; a batch's
        output folder inside it is not one).  A case the cohort does not name
        is named by :func:`default_name`, never by its folder.

    Returns
    -------
    tuple of Case
        In the file's (or the sorted folder's) order.

    Raises
    ------
    CohortError
        Unreadable file, unknown columns, repeated or invalid case names,
        options that none of the commands accepts.  Missing inputs are not
        refused here: that case fails when it runs, the others go on.
    """
    path = Path(path)
    table = _command_actions()
    where_of: list[str] = []  # a CSV's line of each case
    if path.is_dir():
        # not a batch's output folder put inside the cohort's (it is no study)
        # a symbolic link counts even when broken: a study moved away is a case that fails, not one that vanishes
        folders = sorted(p for p in path.iterdir() if (p.is_dir() or p.is_symlink()) and not p.name.startswith(".")
                         and not is_batch_output(p))
        if not folders:
            raise CohortError(f"cohort folder {path} holds no study folders; give a folder of study folders or a CSV")
        cases = [_make_case("", p.name, "", "", "", base=path, where=f"cohort folder {path}", table=table)
                 for p in folders]
    elif path.is_file():
        numbered = _read_rows(path)
        if not numbered:
            raise CohortError(f"cohort file {path} is empty; give a header row and one row per case")
        numbered = _without_unnamed_columns(numbered, path)
        lines = [n for n, _ in numbered]
        rows = [r for _, r in numbered]
        header = [h.strip().lower() for h in rows[0]]
        unknown = [h for h in header if h not in _COLUMNS]
        if unknown or "study" not in header:
            raise CohortError(
                f"cohort file {path}: columns must be among {', '.join(_COLUMNS)} with 'study' required, "
                f"got {', '.join(header)}"
            )
        cases = []
        for n, row in zip(lines[1:], rows[1:]):
            where = f"cohort file {path.name} line {n}"
            if len(row) != len(header):
                raise CohortError(f"{where}: {len(row)} fields for {len(header)} columns")
            cell = dict(zip(header, (c.strip() for c in row)))
            study = cell.get("study", "")
            cases.append(_make_case(cell.get("case", ""), study, cell.get("session", ""), cell.get("mask", ""),
                                    cell.get("options", ""), base=path.parent, where=where, table=table))
            where_of.append(f"line {n}")
        if not cases:
            raise CohortError(f"cohort file {path} has a header but no cases")
    else:
        raise CohortError(f"cohort {path} " + ("does not exist" if not path.exists() else
                                               "is no regular file nor folder (a named pipe or device)")
                          + "; give a CSV file or a folder of study folders")
    seen = {}
    for i, case in enumerate(cases):
        if case.name.lower() in seen:
            j = seen[case.name.lower()]
            rows = f" ({where_of[j]} and {where_of[i]})" if where_of else ""
            same = "" if cases[j].name == case.name else f" as {cases[j].name!r} (one folder on many file systems)"
            raise CohortError(f"cohort {path}: case name {case.name!r} is used twice{same}{rows}; "
                              "give each row its own case name")
        seen[case.name.lower()] = i
    return tuple(cases)


def select_part(cases, num_parts: int, part_id: int) -> tuple[Case, ...]:
    """The cases of part ``part_id`` (0-based) of ``num_parts``: every ``num_parts``-th case.

    Round robin, so that each part gets a share of every stretch of the cohort.
    """
    if num_parts < 1:
        raise CohortError(f"--num-parts must be at least 1, got {num_parts}")
    if not 0 <= part_id < num_parts:
        raise CohortError(f"--part-id must be in 0..{num_parts - 1} for --num-parts {num_parts}, got {part_id}")
    return tuple(cases[part_id::num_parts])
