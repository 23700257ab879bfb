"""``heartreg batch``: a cohort's cases on Dask, resumable, with a summary.

::

    OUT/<case>/             each finished case (see heartreg.batch.case)
    OUT/_failed/<case>.json the record of a case that failed (removed when it succeeds)
    OUT/summary.csv         one row per case of the cohort
    OUT/index.html          thumbnails, numbers and links (self-contained)

The summary covers the whole cohort: this run's cases as they ended, the
others (``--num-parts``: other parts') as their records in OUT say, or
``not run``.  Each part writes it when it ends, so the last part to end
writes the complete one.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from heartreg.batch.case import CaseRecord, read_case_record, remove_leftovers, run_case
from heartreg.batch.cluster import (
    DEFAULT_MEMORY_LIMIT,
    TaskFailure,
    open_client,
    run_tasks,
)
from heartreg.batch.cohort import Case, CohortError, is_batch_output, read_cohort, select_part
from heartreg.batch.report import index_html, summary_csv
from imaging.files import write_text_atomic

__all__ = ["BatchResult", "run_batch"]

FAILED_DIR = "_failed"
_RESERVED_NAMES = {"summary.csv", "index.html", FAILED_DIR}


@dataclass(frozen=True)
class BatchResult:
    """A batch run: every case's record (cohort order), which ran now, files written.

    Attributes
    ----------
    out_dir : Path
    records : tuple of CaseRecord
        One per case of the whole cohort.
    ran : tuple of str
        Names of the cases this run attempted (done now, or failed now);
        a case found done by an earlier run is not among them.
    paths : dict of str to Path
        ``summary`` and ``index``.
    timings_s : dict
    interrupted : bool
    """

    out_dir: Path
    records: tuple
    ran: tuple
    paths: dict
    timings_s: dict
    interrupted: bool = False

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.records)


def _check_out(out: Path, cases) -> Path:
    from heartreg.pipeline import check_out_dir

    out = Path(out).resolve()
    for case in cases:
        if case.name in _RESERVED_NAMES:
            raise CohortError(f"case name {case.name!r} is a file of the batch's own; rename that case")
        for role, path in case.inputs.items():
            p = Path(path)
            if out == p or p in out.parents:
                raise CohortError(f"the output folder {out} is inside case {case.name}'s {role} {p}; "
                                  "choose an output folder outside the inputs")
            if out in p.parents:
                raise CohortError(f"case {case.name}'s {role} {p} is inside the output folder {out}; "
                                  "choose an output folder outside the cohort's folders")
    check_out_dir(out, what="batch output folder", create=False)
    if out.is_dir() and any(out.iterdir()) and not _earlier_run(out):
        raise CohortError(f"the output folder {out} holds files that are not an earlier batch's; "
                          "choose a new or empty folder (a batch goes on only in its own output folder)")
    return out


def _earlier_run(out: Path) -> bool:
    """Whether ``out`` holds only what a batch writes: its summary and index, failure records,
    staging folders and finished cases (a run killed before its first summary has only these)."""
    ours = is_batch_output(out)  # its summary.csv is a batch's
    for entry in out.iterdir():
        if entry.name.startswith(".") or entry.name == FAILED_DIR:
            continue
        if entry.name in ("summary.csv", "index.html"):
            if ours:
                continue
            return False
        if not (entry.is_dir() and read_case_record(entry) is not None):
            return False
    return True


def _record_of(name: str, result) -> CaseRecord:
    if isinstance(result, TaskFailure):
        return CaseRecord(case=name, status="failed", error=f"task: {result.error}")
    return result


def _on_disk(out: Path, name: str) -> CaseRecord:
    """A case not run now, as OUT records it."""
    done = read_case_record(out / name)
    if done is not None:
        return CaseRecord(case=name, status="done", reused=True, key=done.key, values=done.values,
                          times_s=done.times_s, notes=done.notes)
    try:
        return CaseRecord.from_json(json.loads((out / FAILED_DIR / f"{name}.json").read_text()))
    except (OSError, ValueError, TypeError):
        return CaseRecord(case=name, status="not run")


def _keep_failure(out: Path, record: CaseRecord) -> None:
    path = out / FAILED_DIR / f"{record.case}.json"
    if record.status == "failed":
        write_text_atomic(path, json.dumps(record.to_json(), indent=1) + "\n")
    else:
        path.unlink(missing_ok=True)


def run_batch(
    cohort,
    out_dir,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    memory_limit: str = DEFAULT_MEMORY_LIMIT,
    num_parts: int = 1,
    part_id: int = 0,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> BatchResult:
    """Run a cohort's cases (phases -> model -> register) on Dask into ``out_dir``.

    Parameters
    ----------
    cohort : path or sequence of Case
        A cohort CSV file or folder (:func:`heartreg.batch.read_cohort`), or its cases.
    out_dir : path
        Output folder; cases already done there with the same key are skipped.
    workers : int, optional
        Local worker processes (one thread each); default: the usable cores.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://HOST:PORT``) instead of a local cluster.
    memory_limit : str
        Memory limit per local worker.
    num_parts, part_id : int
        Run only part ``part_id`` (0-based) of ``num_parts`` (every ``num_parts``-th case).
    progress : bool
        A progress bar on stderr.
    log : callable, optional
        Receives one-line messages (dashboard link, interruption).

    Returns
    -------
    BatchResult
        Failed cases are records with ``status='failed'``, not exceptions.

    Raises
    ------
    CohortError
        Unreadable cohort, bad part, output folder inside an input.
    ClusterError
        The cluster cannot be started or the scheduler reached.
    """
    from heartreg.pipeline import check_out_dir

    t0 = time.perf_counter()
    say = log or (lambda msg: None)
    cases = tuple(cohort) if not isinstance(cohort, (str, os.PathLike)) else read_cohort(cohort)
    if not all(isinstance(c, Case) for c in cases):
        raise CohortError("cohort must be a CSV file, a folder or a sequence of Case")
    mine = select_part(cases, num_parts, part_id)
    out = _check_out(Path(out_dir), cases)
    for case in mine:  # on the terminal only: the study's folder name can name the patient
        if case.unnamed_study:
            say(f"case {case.name}: study {case.unnamed_study}")
    now: dict[str, CaseRecord] = {}
    interrupted = False
    counts = {"done": 0, "failed": 0}

    def postfix(name, result):
        status = "failed" if isinstance(result, TaskFailure) else result.status
        counts[status] = counts.get(status, 0) + 1
        return f"{counts['done']} done, {counts['failed']} failed"

    try:
        if not mine:
            check_out_dir(out, what="batch output folder")
        else:
            with open_client(workers=workers, scheduler=scheduler, memory_limit=memory_limit, log=say) as client:
                check_out_dir(out, what="batch output folder")  # made once the cluster is up: a refusal writes nothing
                for name, result in run_tasks(client, run_case, mine, names=[c.name for c in mine],
                                              args=(str(out),), progress=progress, desc="batch",
                                              on_result=postfix):
                    record = _record_of(name, result)
                    now[name] = record
                    _keep_failure(out, record)
    except KeyboardInterrupt:
        interrupted = True
        say(f"interrupted: {len(now)} of {len(mine)} case(s) finished; run the same command again to go on")
        for case in mine:  # the local workers are stopped (a scheduler's own may still be writing theirs)
            if scheduler is None and case.name not in now and out.is_dir():
                remove_leftovers(out, case.name)
        raise
    finally:
        records = tuple(now.get(c.name) or _on_disk(out, c.name) for c in cases)
        paths = {}
        if out.is_dir():
            paths = {"summary": summary_csv(records, out / "summary.csv"),
                     "index": index_html(records, out / "index.html", out_dir=out)}
    ran = tuple(name for name, r in now.items() if not r.reused)
    return BatchResult(out_dir=out, records=records, ran=ran, paths=paths,
                       timings_s={"total": time.perf_counter() - t0}, interrupted=interrupted)
