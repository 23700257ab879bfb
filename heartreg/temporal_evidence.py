"""A grid case's saved sweep, read back: the shape estimator of phi_R* re-run without ICP (issue 12).

``heartreg evaluate-temporal`` (:mod:`heartreg.temporal_eval`) saves each case's
sweep as ``OUT/cases/<preset>_s<seed>.npz``: the per-phase ICP transforms and
distances, the traced staples' residuals, the registered points and the map's
vertices.  :func:`shape_from_evidence` runs
:func:`registration.temporal.estimate_phase` on them again (with no options it
gives the case's stored row back), so that a variant of the estimator is
scored on the grid's own cases in seconds (``bench/temporal_rescore.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hrcore.errors import UsageError
from heartreg.temporal_eval import _transform_error

__all__ = ["read_evidence", "shape_from_evidence", "transform_error"]


def transform_error(T, evidence) -> tuple[float, float]:
    """Error of a final transform ``T`` (heart from probe) of a saved case: mean displacement (mm) of the map's
    vertices and rotation (deg) from the truth, as the case's rows are scored (:func:`run_case`).

    Parameters
    ----------
    T : (4, 4) float
    evidence : mapping
        The case's evidence (:func:`read_evidence`); needs ``T_true`` and ``vertices_all_mm``.
    """
    return _transform_error(np.asarray(T, dtype=float), np.asarray(evidence["T_true"]),
                            np.asarray(evidence["vertices_all_mm"]))


def read_evidence(out_dir, preset: str, seed: int) -> dict:
    """A case's saved sweep evidence, ``OUT/cases/<preset>_s<seed>.npz`` (:func:`run_case`), as a dict of arrays."""
    path = Path(out_dir) / "cases" / f"{preset}_s{int(seed)}.npz"
    if not path.is_file():
        raise UsageError(f"no evidence {path}: run the case first (heartreg evaluate-temporal -o {out_dir})")
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def shape_from_evidence(evidence, **options):
    """The shape estimate of phi_R* re-run from a case's saved evidence, as ``heartreg register`` ran it.

    With no ``options`` it gives the case's stored ``shape`` row again (phase, interval, the transform's
    90 % radius; ``tests/heartreg/test_temporal_eval.py``); ``options`` go to
    :func:`registration.temporal.estimate_phase` (``n_bootstrap``, ``curvature_per_mm``, ...), so that a
    variant is scored on the same cases without new ICP runs.  Needs evidence saved with
    ``mean_points_map_mm`` and ``vertices_all_mm`` (grids run since issue 12's re-scoring).

    Returns
    -------
    TemporalEstimate
    """
    from registration.fiducial_curve import FiducialCurve
    from registration.temporal import estimate_phase

    missing = [k for k in ("mean_points_map_mm", "vertices_all_mm") if k not in evidence]
    if missing:
        raise UsageError(f"the case's evidence lacks {', '.join(missing)} (saved by an older heartreg): run the "
                         "grid again into a new output folder to re-score it")
    curve = None
    if "fiducial_residuals_mm" in evidence:
        res = np.asarray(evidence["fiducial_residuals_mm"])
        curve = FiducialCurve(
            phases=np.asarray(evidence["phases"]), positions_probe_mm=np.asarray(evidence["fiducial_curve_source_mm"]),
            T0_heart_from_probe=np.asarray(evidence["fiducial_curve_T"]), residuals_mm=res,
            sse_mm2=(res ** 2).sum(axis=1), trace_rms_mm=np.asarray(evidence["fiducial_trace_rms_mm"]),
            n_samples=np.asarray(evidence.get("fiducial_curve_n_samples", np.zeros(res.shape[1], dtype=np.int64))))
    kwargs = {"distances_mm": evidence["distances_mm"]}
    if options.get("curvature_per_mm") is not None:  # the map's offsets are removed from the signed distances
        kwargs["distances_mm"] = evidence["signed_distances_mm"]
    kwargs.update(options)
    return estimate_phase(evidence["phases"], T_heart_from_probe=evidence["T_heart_from_probe"],
                          vertices_mm=evidence["vertices_all_mm"], fiducials=curve,
                          points_mm=evidence["mean_points_map_mm"], **kwargs)
