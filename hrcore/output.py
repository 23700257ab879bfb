"""One output contract for every writer and command.

An output (a folder, or a single file) is written into a *staging* path beside
its target and becomes visible in one rename at the very end.  A failure, an
exception or a signal before that rename leaves the target exactly as it was:
no empty folder, no half-written file, no stray staging path (and a later run
removes the staging paths of processes that were killed with ``kill -9``).

An output path that is, contains or lies inside one of the command's inputs is
refused before any work.

Examples
--------
>>> import tempfile, pathlib
>>> root = pathlib.Path(tempfile.mkdtemp())
>>> with staged_output(root / "out") as stage:
...     _ = (stage / "a.txt").write_text("done")
>>> sorted(p.name for p in root.iterdir())
['out']
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import re
import secrets
import shutil
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path

from hrcore.errors import HeartregError, os_error_message, refusal_line, root_os_error  # noqa: F401 - theirs, as before
from hrcore.folders import make_folders, remove_folders

__all__ = [
    "OutputError",
    "check_output_file",
    "check_output_path",
    "clean_stale_staging",
    "os_error_message",
    "staged_output",
    "study_folder",
]

_MARK = "heartreg"
#: ``.<name>.heartreg-<pid>-<token>.tmp`` (staging) and ``.old`` (a replaced target).
_STAGING_RE = re.compile(r"^\..*\.heartreg-(\d+)-[0-9a-f]+\.(tmp|old)$")
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


class OutputError(HeartregError, ValueError):
    """An output path that cannot be used (an input, a file, not empty, ...) or
    a write that failed (disk full, no permission)."""


# ------------------------------------------------------------------ checks
def _resolved(path) -> Path:
    return Path(os.path.abspath(Path(path).expanduser())).resolve()


def check_output_path(
    out,
    *,
    inputs: Iterable = (),
    what: str = "output folder",
    overwrite: bool = False,
    folder: bool = True,
    earlier: Iterable[str] = (),
) -> Path:
    """Check an output path before any work; create nothing.

    Parameters
    ----------
    out : str or Path
        The output folder (``folder=True``) or file.
    inputs : iterable of str or Path
        The command's inputs (folders or files; ``None`` entries are ignored).
        ``out`` may not be one of them, lie inside one or contain one.
    what : str
        How messages name ``out`` (e.g. ``"model folder"``, ``"-o"``).
    overwrite : bool
        Accept an existing file, or an existing non-empty folder that holds an
        earlier output of the same kind (``earlier``): a folder holding
        anything else is refused even so (``-o ~ --overwrite`` would have
        emptied the home folder).
    folder : bool
        ``out`` is a folder (else a single file).
    earlier : iterable of str
        Names of the files that mark the folder as an earlier output of this
        kind (``model.json`` for a model): one of them at its top level.
        Without them ``overwrite`` replaces no non-empty folder.

    Returns
    -------
    Path
        ``out`` as given.

    Raises
    ------
    OutputError
        With one line naming ``out`` and what to do.
    """
    out = Path(out)
    _check_inputs(out, inputs, what)
    if folder:
        _refuse_dangling_link(out, what)
        if out.exists() and not out.is_dir():
            raise OutputError(f"{what} {out} exists and is not a folder; choose a folder")
        if out.is_dir() and any(out.iterdir()):
            if not overwrite:
                raise OutputError(f"{what} {out} is not empty; choose an empty folder or pass --overwrite")
            if not any((out / name).is_file() for name in earlier):
                marks = " or ".join(earlier) or "file marking an earlier output"
                raise OutputError(
                    f"{what} {out} is not empty and holds no {marks}: it is no earlier output of this command, "
                    "whose files alone are ever replaced; choose an empty folder or a new name"
                )
    else:
        check_output_file(out, what=what)
        if out.is_dir():
            raise OutputError(f"{what} {out} is a folder; give a file name")
        if out.exists() and not overwrite:
            raise OutputError(f"{what} {out} exists; choose another name or pass --overwrite")
    parent = _existing_parent(_resolved(out))
    if not parent.is_dir():
        raise OutputError(f"{what} {out}: {parent} is a file, not a folder; choose another output path")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {out}: folder {parent} is not writable; choose another output path")
    return out


_KINDS = ((stat.S_ISFIFO, "named pipe"), (stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"),
          (stat.S_ISSOCK, "socket"))


def check_output_file(out, *, what: str = "output file") -> Path:
    """Refuse an output file's path that holds anything but a regular file (or nothing).

    A symbolic link (dangling or not) is never followed nor replaced, nor is a
    named pipe, a device (a log with ``--overwrite`` replaced ``/dev/null`` by a
    regular file, as root) or a socket.  :func:`check_output_path` calls it for a
    file; a writer calls it again just before its rename.

    Raises
    ------
    OutputError
        One line naming ``what``, ``out`` and what to do.
    """
    out = Path(out)
    try:
        mode = os.lstat(out).st_mode
    except OSError:  # nothing there (or a place that cannot be looked at: refused by the checks of its folder)
        return out
    if stat.S_ISLNK(mode):
        raise OutputError(f"{what} {out} is a symbolic link, which is never followed nor replaced; "
                          "give a regular file's own path or a new name")
    for test, kind in _KINDS:
        if test(mode):
            raise OutputError(f"{what} {out} is a {kind}, not a regular file (only a regular file is ever "
                              "replaced); choose another name")
    return out


def study_folder(path) -> Path:
    """The folder a study path stands for: a DICOMDIR file is the index of the files beside it, its folder;
    any other path is itself."""
    path = Path(path)
    return path.parent if path.name.upper() == "DICOMDIR" and path.is_file() else path


def _refuse_dangling_link(out: Path, what: str) -> None:
    """Refuse a link to nothing: the output would replace the link, not appear where it points."""
    if out.is_symlink() and not out.exists():
        raise OutputError(f"{what} {out} is a symbolic link to {os.readlink(out)}, which does not exist; make that "
                          "folder or give another path")


def _check_inputs(out: Path, inputs: Iterable, what: str, *, contains: bool = True) -> None:
    target = _resolved(out)
    for inp in inputs:
        if inp is None:
            continue
        source = study_folder(_resolved(inp))
        if target == source:
            raise OutputError(f"{what} {out} is the input {inp}; choose another output path")
        if target.is_relative_to(source):
            raise OutputError(f"{what} {out} lies inside the input {inp}; choose an output path outside it")
        if contains and source.is_relative_to(target):
            raise OutputError(f"{what} {out} contains the input {inp}; choose an output path that does not")


def _existing_parent(path: Path) -> Path:
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    return parent


# ------------------------------------------------------------------ stale staging
def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    return True


def clean_stale_staging(folder) -> list[Path]:
    """Remove the staging paths that killed heartreg processes left in ``folder``.

    A ``.old`` path (a target moved aside just before its replacement) whose
    target is missing is moved back: the previous state is restored.

    Returns
    -------
    list of Path
        The paths removed or restored.
    """
    folder = Path(folder)
    done = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return done
    for entry in entries:
        m = _STAGING_RE.match(entry.name)
        if m is None or _alive(int(m.group(1))):
            continue
        path = Path(entry.path)
        if m.group(2) == "old":
            target = folder / entry.name[1:].rsplit(f".{_MARK}-", 1)[0]
            if not os.path.lexists(target):
                with contextlib.suppress(OSError):
                    os.rename(path, target)
                    done.append(path)
                    continue
        _remove(path)
        done.append(path)
    return done


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


# ------------------------------------------------------------------ atomic swap
def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``).

    Returns False when the system cannot (the caller falls back to two renames).
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


#: An interrupt (Ctrl-C, or SIGTERM turned into an exception) that Python could not raise where it arrived: in a
#: garbage collector's callback it is printed as "Exception ignored" and dropped.  The command line keeps it here
#: (:func:`defer_interrupt`); no output is committed while it waits, and the command raises it at the end.
_deferred: list = []


def defer_interrupt(exc: BaseException | None) -> None:
    """Keep an interrupt that could not be raised (``None`` forgets one)."""
    _deferred[:] = [] if exc is None else [exc]


def take_deferred_interrupt() -> BaseException | None:
    """The interrupt :func:`defer_interrupt` kept, forgotten here (None if there is none)."""
    return _deferred.pop() if _deferred else None


def raise_deferred_interrupt() -> None:
    """Raise the interrupt :func:`defer_interrupt` kept, if any."""
    exc = take_deferred_interrupt()
    if exc is not None:
        raise exc


def _commit(stage: Path, out: Path) -> None:
    """Make ``stage`` visible as ``out`` in one step; remove what ``out`` held."""
    if not os.path.lexists(out):
        os.rename(stage, out)
        return
    if _exchange(stage, out):
        _remove(stage)  # now holds the previous output
        return
    old = out.parent / f".{out.name}.{_MARK}-{os.getpid()}-{secrets.token_hex(4)}.old"
    os.rename(out, old)  # a kill here: clean_stale_staging moves it back
    os.rename(stage, out)
    _remove(old)


def _size_bytes(path: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(dirpath, f)).st_size
    if path.is_file():
        total = path.stat().st_size
    return total


def _amount(n_bytes: float) -> str:
    """A size in words: ``2.0 MB``, ``35 kB``."""
    return f"{n_bytes / 1e6:.1f} MB" if n_bytes >= 1e6 else f"{n_bytes / 1e3:.0f} kB"


def _named_in_out(filename, stage: Path, out: Path) -> str:
    """The file an error names, as it would have been in ``out`` (not in the staging path)."""
    if not filename:
        return str(out)
    path = Path(os.fsdecode(filename))
    with contextlib.suppress(ValueError):
        return str(out / Path(os.path.abspath(path)).relative_to(os.path.abspath(stage)))
    return str(path)


# ------------------------------------------------------------------ staging
def _missing_or_empty(path: Path) -> bool:
    """True when nothing is at ``path`` but, at most, an empty folder."""
    return not os.path.lexists(path) or (path.is_dir() and not any(os.scandir(path)))


def _holds_only(folder: Path, parts) -> bool:
    """True when ``folder`` holds nothing but entries named in ``parts``."""
    return all(entry.name in parts for entry in os.scandir(folder))


def _check_parts(out: Path, parts, inputs, what: str, overwrite: bool, earlier) -> None:
    if out.exists() and not out.is_dir():
        raise OutputError(f"{what} {out} exists and is not a folder; choose a folder")
    _check_inputs(out, inputs, what, contains=False)  # inputs beside the parts are fine
    for name in parts:
        target = out / name
        _check_inputs(target, inputs, what)
        if not target.exists() or (target.is_dir() and not any(target.iterdir())):
            continue
        if not overwrite:
            raise OutputError(f"{what} {out} already holds {name}; choose another folder or pass --overwrite")
        if earlier and not any((out / mark).is_file() for mark in earlier):
            raise OutputError(
                f"{what} {out} holds {name} but no {' or '.join(earlier)}: it is no earlier output of this command, "
                "whose files alone are ever replaced; choose another folder"
            )
    parent = _existing_parent(_resolved(out) / "x")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {out}: folder {parent} is not writable; choose another output path")


@contextlib.contextmanager
def staged_output(
    out,
    *,
    inputs: Iterable = (),
    what: str = "output folder",
    overwrite: bool = False,
    folder: bool = True,
    parts: Iterable[str] | None = None,
    earlier: Iterable[str] = (),
) -> Iterator[Path]:
    """Stage an output beside its target; rename it into place on success.

    Parameters
    ----------
    out : str or Path
        Target folder (or file, with ``folder=False``).
    inputs, what, overwrite, folder, earlier
        As for :func:`check_output_path` (called first).  With ``parts``,
        ``earlier`` names the files (paths inside ``out``) that mark ``out``
        as an earlier output of the command: without one of them an existing
        part is not replaced, even with ``overwrite`` (a user's own
        ``model/`` folder is not the pipeline's).
    parts : iterable of str, optional
        Names of the entries this output owns inside an ``out`` folder that
        may hold other things (the pipeline's ``phases/``, ``model/``, ...).
        When ``out`` does not exist or holds nothing but these parts (an
        earlier run's output), the whole folder is still staged and swapped
        in one step: a kill at any moment leaves the earlier output or the
        new one.  When ``out`` holds other things too (the demo's folder),
        each part is swapped into place atomically, one after the other, and
        nothing else in ``out`` is touched.  ``overwrite`` applies to the
        parts.

    Yields
    ------
    Path
        The staging folder (created, empty) or the staging file name (not
        created).  Write everything there, under the same names as in ``out``.

    Raises
    ------
    OutputError
        A refused output path, or a write that failed for lack of space (the
        message names the file and how much had been written).

    Notes
    -----
    On any exception (``KeyboardInterrupt`` and signals turned into
    exceptions included) the staging path is removed, the folders created for
    it are removed again, and ``out`` is untouched.  Missing parent folders of
    ``out`` are created only for the staging path.  A kill -9 leaves at most a
    staging path named ``.<name>.heartreg-<pid>-<token>.tmp`` beside ``out``,
    which the next run that writes there removes.

    Examples
    --------
    Nothing is visible at the target until the block ends without an error:

    >>> import pathlib
    >>> import tempfile
    >>> from hrcore import staged_output
    >>> out = pathlib.Path(tempfile.mkdtemp()) / "result"
    >>> with staged_output(out) as stage:
    ...     _ = (stage / "a.txt").write_text("done")
    ...     print(out.exists())
    False
    >>> (out / "a.txt").read_text()
    'done'
    """
    out = Path(out)
    parts = tuple(parts) if parts is not None else None
    whole = parts is None or not out.exists() or (out.is_dir() and _holds_only(out, parts))
    if parts is not None:
        _refuse_dangling_link(out, what)
        _check_parts(out, parts, inputs, what, overwrite, tuple(earlier))
        if whole:
            _check_inputs(out, inputs, what)
    else:
        check_output_path(out, inputs=inputs, what=what, overwrite=overwrite, folder=folder, earlier=earlier)
    absolute = Path(os.path.abspath(out))
    if absolute.is_symlink() and absolute.is_dir():  # the folder it links to is the output, the link stays (an audit)
        absolute = Path(os.path.realpath(absolute))
    new = _missing_or_empty(absolute)
    home = absolute.parent if whole else absolute
    created: list[Path] = []
    stage = home / f".{absolute.name}.{_MARK}-{os.getpid()}-{secrets.token_hex(4)}.tmp"
    try:
        created = make_folders(home)
        clean_stale_staging(home)
        if folder or parts is not None:
            os.mkdir(stage)
        yield stage
        raise_deferred_interrupt()
        if new and not overwrite and not _missing_or_empty(absolute):
            raise OutputError(f"{what} {out} was written by another run meanwhile; nothing of this run was kept "
                              "(run again with --overwrite to replace it)")
        if whole:
            _commit(stage, absolute)
        else:
            for name in parts:
                if os.path.lexists(stage / name):
                    _commit(stage / name, absolute / name)
            _remove(stage)
    except OSError as exc:
        written = _size_bytes(stage) if os.path.lexists(stage) else 0
        _cleanup(stage, created)
        exc = root_os_error(exc)
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            free = shutil.disk_usage(_existing_parent(absolute)).free
            raise OutputError(f"disk full writing {_named_in_out(exc.filename, stage, out)}: {what} {out} needed more "
                              f"than the {_amount(written)} written before the disk ran out ({_amount(free)} free now, "
                              "nothing was kept); free space or choose another output path") from None
        if exc.filename is not None:  # named as the user gave it: '/sys/.x.heartreg-1234-ab12.tmp' was (an audit)
            raise OSError(exc.errno, exc.strerror, _named_in_out(exc.filename, stage, out)) from None
        raise
    except BaseException:
        _cleanup(stage, created)
        raise


def _cleanup(stage: Path, created: list) -> None:
    if os.path.lexists(stage):
        _remove(stage)
    remove_folders(created)
