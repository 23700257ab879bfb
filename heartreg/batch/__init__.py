"""Cohorts: many studies at once on Dask distributed, from a laptop to a cluster.

``run_batch(cohort, out_dir)`` (``heartreg batch COHORT -o OUT``) runs every
case of a cohort through the single commands (phases -> model -> register
when the case has a session) on a local cluster of worker processes or an
existing scheduler; a case is a pure function of its inputs and options, so a
stopped batch resumes where it was and a cluster can run it.  The same
machinery (:func:`open_client`, :func:`run_tasks`) runs ``heartreg
reproduce``'s trials.
"""

from heartreg.batch.case import CaseRecord, case_key, run_case
from heartreg.batch.cluster import ClusterError, TaskFailure, open_client, run_tasks
from heartreg.batch.cohort import Case, CohortError, read_cohort
from heartreg.batch.runner import BatchResult, run_batch

__all__ = [
    "BatchResult",
    "Case",
    "CaseRecord",
    "ClusterError",
    "CohortError",
    "TaskFailure",
    "case_key",
    "open_client",
    "read_cohort",
    "run_batch",
    "run_case",
    "run_tasks",
]
