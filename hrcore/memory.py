"""Give freed heap memory back to the system between the stages of a command.

glibc keeps memory that Python and numpy have freed in its heap, to reuse it;
after a stage that made many medium-sized arrays (a dense mesh, its edge
lists), that can be a hundred MB or more that no later stage reuses, and every
later stage's peak sits on top of it.  :func:`release_free_memory` asks glibc
to return it (``malloc_trim``); elsewhere it does nothing.

A process started with ``MALLOC_TRIM_THRESHOLD_`` in its environment (Dask's nanny
sets it for every worker, with ``distributed.nanny.pre-spawn-environ``) has
told glibc when to give memory back, and that also turns off glibc's rising
mmap threshold: large arrays then live in mappings of their own and go back
when freed.  There an explicit trim only costs time (the pages it returns
fault back in at the next stage): a batch of six sample cases on two workers
ran 1.54x faster than on one with it and 1.84x without it
(``bench/bench_batch.py``), so :func:`release_free_memory` then does nothing.
"""

from __future__ import annotations

import ctypes
import functools

__all__ = ["available_memory_bytes", "release_free_memory"]


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    try:
        fn = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


@functools.lru_cache(maxsize=1)
def _glibc_trims_by_itself() -> bool:
    """Whether this process *started* with ``MALLOC_TRIM_THRESHOLD_`` set.

    glibc reads it once, at start-up, so the environment as it is now does
    not tell: Dask sets it in the parent process while it spawns workers.
    """
    try:
        with open("/proc/self/environ", "rb") as f:
            return b"\0MALLOC_TRIM_THRESHOLD_=" in b"\0" + f.read()
    except OSError:  # not Linux: no malloc_trim either
        return False


def release_free_memory() -> bool:
    """Return the heap's free pages to the system (glibc ``malloc_trim(0)``, ~10 ms).

    Returns
    -------
    bool
        Whether any memory was returned (False where the C library has no
        ``malloc_trim`` or ``MALLOC_TRIM_THRESHOLD_`` is set).
    """
    if _glibc_trims_by_itself():  # the module docstring
        return False
    fn = _malloc_trim()
    return bool(fn(0)) if fn is not None else False


#: The process's cgroups, one line per hierarchy (``0::/path`` for v2).
_PROC_CGROUP = "/proc/self/cgroup"
#: Where each cgroup version keeps its memory files: (root, limit, usage, the droppable file cache in memory.stat).
_CGROUP_FILES = {
    "v2": ("/sys/fs/cgroup", "memory.max", "memory.current", "inactive_file"),
    "v1": ("/sys/fs/cgroup/memory", "memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file"),
}


def _cgroup_room() -> int | None:
    """Bytes the process's cgroup may still take, or None without a limit.

    The tightest limit from the process's own cgroup (``/proc/self/cgroup``; v2, or v1's memory controller)
    up to the root, less what that cgroup holds but the page cache it can drop (``inactive_file``): a
    container whose file cache grew to its limit has that room still.
    """
    from pathlib import Path

    try:
        lines = Path(_PROC_CGROUP).read_text().splitlines()
    except OSError:
        return None
    rooms = []
    for line in lines:
        _, controllers, own = line.split(":", 2)
        version = "v2" if controllers == "" else "v1" if "memory" in controllers.split(",") else None
        if version is None:
            continue
        root, limit_file, usage_file, cache_key = _CGROUP_FILES[version]
        folder = Path(root) / own.strip().lstrip("/")
        for cgroup in (folder, *folder.parents):
            if not str(cgroup).startswith(root):
                break
            try:
                limit = (cgroup / limit_file).read_text().strip()
                if limit == "max" or int(limit) >= 1 << 60:  # no limit (v1 writes a number near 2^63)
                    continue
                stat = dict(line.split()[:2] for line in (cgroup / "memory.stat").read_text().splitlines())
                usage = int((cgroup / usage_file).read_text())
                rooms.append(max(0, int(limit) - usage + int(stat.get(cache_key, 0))))
            except (OSError, ValueError):
                continue
    return min(rooms) if rooms else None


def available_memory_bytes() -> int | None:
    """Memory a new allocation can take without swapping or the OOM killer, in bytes.

    The kernel's ``MemAvailable`` (free memory and the page cache it can drop),
    capped by the container's cgroup limit when there is one.  With Linux's
    overcommit a large ``np.empty`` succeeds whatever this says, and the
    process is killed minutes later as it fills the array: a command that
    knows how much it will need asks here first.

    Returns
    -------
    int or None
        None where it cannot be told (not Linux): then nothing is refused.
    """
    try:
        with open("/proc/meminfo") as f:
            free = next((int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:")), None)
    except (OSError, ValueError):
        free = None
    room = _cgroup_room()
    known = [b for b in (free, room) if b is not None]
    return min(known) if known else None
