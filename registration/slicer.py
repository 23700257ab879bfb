"""A registration's files for 3D Slicer: its transforms as ITK ``.tfm`` files, its
points and the touched fiducials as markups (``.mrk.json``).

Written by :func:`registration.report.write_registration` beside
``registration.json`` (how to load them: ``docs/slicer.md``).  Every transform
of the result is written as the to-parent transform of a Slicer node named in
SlicerIGT's ``FromToTo`` style; the file holds its inverse, ITK's resampling
direction (:mod:`modeling.slicer`):

==================================  =====================================================
file                                 Slicer node's to-parent (mm, LPS)
==================================  =====================================================
``ProbeToHeart.tfm``                 ``T_heart_from_probe``, the final registration
``ProbeToHeart_fiducial.tfm``        ``T0_heart_from_probe``, the fiducial registration
``ProbeToHeart_static.tfm``          the static (mean-position) registration
``ProbeToPatient*.tfm``              the same three composed with the model's frame:
                                     ``T_patient_from_heart @ T_heart_from_probe``
                                     (only when the model is given)
==================================  =====================================================

The probe frame is the tracker's, not a patient's: its points are written as
they are (``coordinateSystem: "LPS"``, the convention the transforms share), so
that in Slicer they land on the CT when placed under ``ProbeToPatient``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from modeling.slicer import write_itk_transform, write_markups
from registration.result import RegistrationResult

__all__ = ["POINTS_FILE", "TOUCHED_FIDUCIALS_FILE", "write_slicer_files"]

TOUCHED_FIDUCIALS_FILE = "fiducials_touched.mrk.json"
POINTS_FILE = "points_registered.mrk.json"
_ORDER = "rows superior to inferior, within a row patient right to left"


def _transforms(result: RegistrationResult) -> dict:
    return {
        "": result.T_heart_from_probe,
        "_fiducial": result.T0_heart_from_probe,
        "_static": result.static.T_static_heart_from_probe,
    }


def write_slicer_files(
    result: RegistrationResult,
    out_dir,
    *,
    T_patient_from_heart=None,
    fiducials_probe_mm=None,
) -> dict:
    """Write the registration's transforms and points for 3D Slicer.

    Parameters
    ----------
    result : RegistrationResult
    out_dir : str or Path
        Existing folder (the registration's).
    T_patient_from_heart : (4, 4) float64, optional
        The model's frame (``HeartModel.T_patient_from_heart``); with it the
        ``ProbeToPatient*.tfm`` files are written too.
    fiducials_probe_mm : (n, 3) float, mm, optional
        The touched fiducials (``Session.fiducials_probe_mm``), written as
        ``fiducials_touched.mrk.json`` in the probe frame.

    Returns
    -------
    dict of Path by name (``"ProbeToHeart"``, ... and ``"touched_fiducials"``,
    ``"points"``).
    """
    if not isinstance(result, RegistrationResult):
        raise TypeError(f"result must be a RegistrationResult, got {type(result).__name__}")
    out = Path(out_dir)
    paths = {}
    what = {"": "final spatiotemporal", "_fiducial": "fiducial (T0)", "_static": "static (mean-position)"}
    for suffix, T_heart_from_probe in _transforms(result).items():
        name = f"ProbeToHeart{suffix}"
        paths[name] = write_itk_transform(
            out / f"{name}.tfm", T_heart_from_probe,
            note=f"Slicer node {name}: {what[suffix]} registration, to-parent T_heart_from_probe, mm",
        )
        if T_patient_from_heart is not None:
            name = f"ProbeToPatient{suffix}"
            paths[name] = write_itk_transform(
                out / f"{name}.tfm", np.asarray(T_patient_from_heart, dtype=np.float64) @ T_heart_from_probe,
                note=f"Slicer node {name}: {what[suffix]} registration, to-parent "
                "T_patient_from_heart @ T_heart_from_probe, LPS, mm",
            )
    if fiducials_probe_mm is not None:
        fid = np.asarray(fiducials_probe_mm, dtype=np.float64).reshape(-1, 3)
        paths["touched_fiducials"] = write_markups(
            out / TOUCHED_FIDUCIALS_FILE, fid, labels=[f"T-{k}" for k in range(1, len(fid) + 1)],
            name="touched fiducials", color=(0.2, 0.6, 1.0),
            descriptions=[f"touched with the tracked stylus, reference-probe frame; {_ORDER}; "
                          f"residual {r:.2f} mm" for r in result.fiducial_residuals_mm]
            if len(result.fiducial_residuals_mm) == len(fid) else None,
        )
    paths["points"] = write_markups(
        out / POINTS_FILE, result.points_probe_mm, labels=[f"P{int(i)}" for i in result.point_ids],
        name="registered points", color=(0.1, 0.55, 0.25),
        descriptions=[f"point {int(i)}: motion-model position at phi_C* = {result.cardiac_phase:.3f}, "
                      f"phi_R* = {result.respiration_phase:.2f}, reference-probe frame" for i in result.point_ids],
    )
    return paths
