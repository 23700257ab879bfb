"""Run tasks on Dask distributed: a local cluster of processes, or an existing scheduler.

:func:`open_client` gives a ``distributed.Client`` on a local cluster (``n``
worker processes of one thread each, a memory limit per worker) or connected
to a running scheduler (a cluster's, started by dask-jobqueue, Kubernetes or
by hand).  :func:`run_tasks` submits one task per item, shows a progress bar,
and hands each result back as it arrives; a task that raises or whose worker
dies comes back as a :class:`TaskFailure` instead of stopping the others.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

from hrcore.errors import HeartregError

__all__ = ["DEFAULT_MEMORY_LIMIT", "ClusterError", "TaskFailure", "default_workers", "open_client", "run_tasks"]

#: Memory limit of each local worker: a full-size case (512 x 512 x 288) peaks near 0.8 GB.
DEFAULT_MEMORY_LIMIT = "4GB"
#: Seconds to wait for a scheduler to answer before giving up.
CONNECT_TIMEOUT_S = 30
#: Seconds the client and a local cluster get to close before the command goes on.
CLOSE_TIMEOUT_S = 30
#: Modules every worker imports when it joins, in its own (main) thread, before it
#: runs a task: the compiled ones a case loads on first use.  Loaded first inside a
#: task's thread they left workers' heaps corrupt at exit (glibc:
#: "malloc_consolidate(): unaligned fastbin chunk detected", after every result was
#: in): in 4-case evaluate-temporal runs on 2 workers, 1 of 3 runs with scipy.signal
#: alone imported beforehand (then by ``imaging``'s import), 2 of 6 with it preloaded
#: here, every run with nothing preloaded, none of 11 with all three preloaded.
PRELOAD = ("scipy.signal", "pymeshlab", "registration._closest_kernel")


class ClusterError(HeartregError, RuntimeError):
    """The Dask cluster cannot be started or reached (the message says which address and what to do)."""


@dataclass(frozen=True)
class TaskFailure:
    """A task that raised, or whose worker died, in one line."""

    name: str
    error: str


def default_workers() -> int:
    """The local cluster's default size: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _preload(dask_worker=None) -> None:
    """Import :data:`PRELOAD` in a worker's own thread (``Client.register_worker_callbacks``)."""
    import importlib

    for module in PRELOAD:
        importlib.import_module(module)


#: A -W option: no warning from multiprocessing's resource tracker about semaphores left by stopped workers.
_TRACKER_QUIET = "ignore:resource_tracker:UserWarning"


@contextlib.contextmanager
def _children_ignore_sigint():
    """Processes started meanwhile ignore SIGINT (an ignored signal stays ignored through exec, and Python
    keeps it so): a terminal's Ctrl-C reaches the whole process group, and each local worker's own
    KeyboardInterrupt and lost heartbeats printed tracebacks over the command's one line; the command stops
    its workers itself.  Ctrl-C during the start is lost (a second or two)."""
    import signal
    import threading

    # multiprocessing's resource tracker, a process started with this interpreter's -W options, warned at exit
    # of the semaphores of workers stopped mid-task ("2 leaked semaphore objects"): nothing for the user to do
    if _TRACKER_QUIET not in sys.warnoptions:
        sys.warnoptions.append(_TRACKER_QUIET)
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _dashboard_link(client) -> str:
    """The dashboard's address when the scheduler serves its pages (they need bokeh), else ``""``."""
    import urllib.request

    try:
        if "dashboard" not in client.scheduler_info().get("services", {}):
            return ""
        link = client.dashboard_link
        with urllib.request.urlopen(link, timeout=2) as response:
            page = response.read(4096)
        # without bokeh the scheduler serves a page that says so instead of the dashboard
        return "" if b"needs bokeh" in page else link
    except Exception:  # noqa: BLE001 - the link is a courtesy: no page, no link
        return ""


#: Least memory (bytes) a local worker may be given: a sample-size case peaks near 0.4 GB, a full-size one 0.8 GB.
MIN_MEMORY_LIMIT = 512 * 2**20


def _check_memory_limit(memory_limit) -> None:
    """Refuse a per-worker memory limit no case fits in (Dask then failed with a closed stream)."""
    from dask.utils import parse_bytes

    if isinstance(memory_limit, str) and memory_limit.strip().lower() in ("auto", "0", "none", ""):
        return
    try:
        n_bytes = parse_bytes(memory_limit) if isinstance(memory_limit, str) else int(memory_limit)
    except (ValueError, TypeError):
        n_bytes = -1
    if n_bytes < 0:  # dask reads '-1GB' as minus a gigabyte, and its nanny then fails to start
        raise ClusterError(f"--memory-limit {memory_limit!r} is not an amount of memory (e.g. 4GB, or auto)")
    if 0 < n_bytes < MIN_MEMORY_LIMIT:
        raise ClusterError(f"--memory-limit {memory_limit} per worker is less than a case needs "
                           f"({MIN_MEMORY_LIMIT // 2**20} MB and up: a full-size case peaks near 0.8 GB)")


#: Most local workers per core: more only wait for each other (and each holds a case's memory).
MAX_WORKERS_PER_CORE = 4


def _probe_scheduler(address: str, timeout_s: float) -> None:
    """Refuse, in one line, an address that is malformed or where no Dask scheduler answers.

    A Dask scheduler writes its handshake (a frame count, 8 bytes little-endian) as soon as a
    connection opens; another service (an HTTP server) waits for a request, and ``distributed.Client``
    then waits past its own timeout, forever.  Only ``tcp://`` addresses are probed.
    """
    import socket

    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme != "tcp":
            return
        host, port = parse_host_port(location)
    except ValueError as exc:
        raise ClusterError(f"--scheduler {address!r} is not a scheduler address ({exc}): give tcp://HOST:PORT") from None
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s) as conn:
            conn.settimeout(timeout_s)
            head = b""
            while len(head) < 8:
                chunk = conn.recv(8 - len(head))
                if not chunk:
                    break
                head += chunk
    except socket.timeout:
        head = b""
    except OSError as exc:
        raise ClusterError(f"cannot reach the Dask scheduler at {address} ({exc}); "
                           "check --scheduler and that the scheduler is running") from None
    if len(head) < 8 or int.from_bytes(head, "little") > 1000:
        raise ClusterError(f"{address} answers, but not as a Dask scheduler (no handshake within {timeout_s:g} s): "
                           "check --scheduler (the scheduler's port, 8786 by default, not its dashboard's)")


@contextlib.contextmanager
def open_client(*, workers: int | None = None, scheduler: str | None = None,
                memory_limit: str = DEFAULT_MEMORY_LIMIT, log: Callable[[str], None] | None = None):
    """A Dask client on a new local cluster, or on the scheduler at ``scheduler``.

    Parameters
    ----------
    workers : int, optional
        Local worker processes (one thread each); default :func:`default_workers`.
        Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a running scheduler, e.g. ``tcp://10.0.0.5:8786``.
    memory_limit : str
        Memory limit of each local worker (Dask's syntax: ``"4GB"``, ``"auto"``).
    log : callable, optional
        Receives a line with the dashboard link when there is one.

    Yields
    ------
    distributed.Client
    """
    from distributed import Client, LocalCluster

    say = log or (lambda msg: None)
    cluster = None
    if scheduler:
        _probe_scheduler(scheduler, min(CONNECT_TIMEOUT_S, 10))
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ClusterError(f"cannot reach the Dask scheduler at {scheduler} ({exc}); "
                               "check --scheduler and that the scheduler is running") from None
        n = len(client.scheduler_info().get("workers", {}))
        say(f"scheduler {scheduler}: {n} worker(s) now" + ("; waiting for workers to join" if n == 0 else ""))
    else:
        n = default_workers() if workers is None else int(workers)
        if n < 1:
            raise ClusterError(f"--workers must be at least 1, got {n}")
        if n > MAX_WORKERS_PER_CORE * default_workers():
            raise ClusterError(f"--workers {n} on {default_workers()} core(s): at most {MAX_WORKERS_PER_CORE} per core "
                               "(more only wait for each other); for more, start a cluster and give --scheduler")
        _check_memory_limit(memory_limit)
        try:  # the scheduler's http server (the dashboard's, with bokeh) on a free loopback port
            # the workers' own log only at CRITICAL: a heartbeat that meets the scheduler closing after a Ctrl-C
            # logs an ERROR with its traceback (a fresh CI run); a case's failure comes back with its result
            with _children_ignore_sigint():
                cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, memory_limit=memory_limit,
                                       host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                       silence_logs=logging.CRITICAL)
        except ValueError as exc:
            raise ClusterError(f"cannot start {n} local worker(s) with memory limit {memory_limit!r}: {exc}") from None
        client = Client(cluster, set_as_default=False)
    try:
        try:
            client.register_worker_callbacks(_preload)  # every worker, also those that join later
        except ImportError as exc:
            raise ClusterError(f"a Dask worker cannot import {exc.name or exc}: install heartreg and its "
                               "dependencies where the workers run") from None
        link = _dashboard_link(client)
        if link:
            say(f"Dask dashboard: {link}")
        yield client
    finally:
        # every result is back by now: a cluster slow to wind down (workers of a
        # loaded machine killed after the nanny's grace time) is not a failure
        with contextlib.suppress(TimeoutError, OSError):
            client.close(timeout=CLOSE_TIMEOUT_S)
        if cluster is not None:
            with contextlib.suppress(TimeoutError, OSError):
                cluster.close(timeout=CLOSE_TIMEOUT_S)


def _failure_line(exc: BaseException) -> str:
    from distributed import KilledWorker

    if isinstance(exc, KilledWorker):
        return ("its worker died while running it (out of memory? the limit is per worker: "
                "raise --memory-limit or lower --workers)")
    if isinstance(exc, HeartregError):
        return " ".join(str(exc).split())
    return " ".join(f"{type(exc).__name__}: {exc}".split())


def run_tasks(client, function: Callable, items: Sequence, *, names: Sequence[str], args: tuple = (),
              progress: bool = True, desc: str = "tasks",
              on_result: Callable | None = None) -> Iterator:
    """Submit ``function(item, *args)`` for every item; yield ``(name, result)`` as they finish.

    ``result`` is the function's return value, or a :class:`TaskFailure` when
    it raised or its worker died (Dask retries a task whose worker died on
    another worker first).  Items run in their order as workers free up.

    Parameters
    ----------
    client : distributed.Client
    function : callable
        A module-level function (the workers import it), taking an item and ``args``.
    items : sequence
        Small, picklable inputs (paths, not data).
    names : sequence of str
        One name per item (the progress bar and failures name it).
    progress : bool
        A progress bar on stderr.
    on_result : callable, optional
        Called as ``on_result(name, result)`` for the progress bar's postfix:
        returns a short text.
    """
    from distributed import as_completed
    from tqdm import tqdm

    run_id = uuid.uuid4().hex[:8]
    futures = {}
    for priority, (name, item) in enumerate(zip(names, items)):
        future = client.submit(function, item, *args, key=f"heartreg-{name}-{run_id}", pure=False,
                               priority=-priority)
        futures[future] = name
    bar = tqdm(total=len(futures), desc=desc, file=sys.stderr, disable=not progress, unit="case")
    try:
        for future in as_completed(futures, loop=client.loop):
            name = futures[future]
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - one task's failure is its result
                result = TaskFailure(name=name, error=_failure_line(exc))
            future.release()
            if on_result is not None:
                bar.set_postfix_str(on_result(name, result), refresh=False)
            bar.update(1)
            yield name, result
    finally:
        bar.close()
        for future in futures:
            future.cancel()
