"""The map's cardiac phase slice by slice: predict each point at the phase of the slices it lies on.

A prospectively gated CT is a patchwork: each stack of slices is imaged in its
own heartbeat, at its own cardiac phase (paper Fig. 4: 0.61-0.67, with jumps
where a beat was shorter or longer than predicted).  The map's phi_C* is the
mean of the slice phases; a stack imaged well away from it (e.g. at 0.48-0.51
while the others lie at 0.62-0.69, as in the phantom's seed 4) shows that part
of the heart in another state of contraction.  Predicting every point at
phi_C* then leaves the points on that part of the map ~1 mm off the surface at
the true respiration phase, and the heartbeat's respiratory modulation lets a
wrong phi_R take that difference up (the shape estimator missed by 0.3 of a
cycle on those cases).

The remedy here uses what the CT states, not a nuisance parameter: each point
is predicted at the cardiac phase of the slices at its position along the
slice normal (:func:`point_cardiac_phases`, linear between neighbouring slice
centres), its position taken from the points' mean positions under a rough
registration (``T0``, or a first sweep's answer: a stack is 40 mm thick, the
registration errors a few mm).  A profile over a uniform cardiac-phase offset
(phi_C* +- 0.08) was tried first and does not help: the heart's cost changes by
< 2 % over the offset while the mismatch is local to one stack.

Measured (phantom, sample size, the six seed-4 cases of ``evaluate-temporal``
and two others): at the true phase the points of the early stack come from
0.95 mm RMS to 0.18 mm, and the final T at the true phase of trial 1 from
2.0 mm, 2.8 deg to 0.26 mm, 0.23 deg; the 90 % interval then covers the truth
in 4 of 7 cases (1 of 7 at phi_C*); but phi_R* itself moves little: the heart
term still prefers a phase 0.07-0.3 off, a bias this does not explain alone.
Together with coupled harmonics that can hold the phantom's modulated beat
c(phi_C) (1 + 0.2 cos 2 pi phi_R) (``harmonics=(5, 4, 5, 1)``; the default
Hmc = 2 cannot) phi_R* of trials 1 and 5, seed 4, comes from +0.29/-0.29 to
-0.03/+0.01, and with ``(5, 4, 5, 2)`` trial 6's from -0.28 to 0.00
(docs/reproduction.md, "Beyond eq. 10").

The model carries the slice phases (``HeartModel.slice_phases``, written by
``heartreg model``); :func:`registration.register_session` uses them unless
``RegistrationOptions.slice_phases`` is off (``--no-slice-phases``).
"""

from __future__ import annotations

import numpy as np

from hrcore.geometry import apply_to_points
from modeling.slice_phases import SlicePhases
from registration.phase_estimate import wrap_phase

__all__ = ["SlicePhases", "point_cardiac_phases", "predict_at_point_phases"]


def point_cardiac_phases(points_map_mm, T_map_from_patient, slices: SlicePhases) -> np.ndarray:
    """Cardiac phase of the slices at each point's position, (n,) cycles.

    Parameters
    ----------
    points_map_mm : (n, 3) float, mm
        Points in the map (heart) frame.
    T_map_from_patient : (4, 4) float
        The map frame from the CT's patient frame (``HeartModel.T_heart_from_patient``).
    slices : SlicePhases

    Returns
    -------
    (n,) float64
        Linear between neighbouring slice centres (circularly, so that a
        stack at 0.95 beside one at 0.02 interpolates through 0); the end
        slices' phases beyond the scanned range.
    """
    p = apply_to_points(np.linalg.inv(np.asarray(T_map_from_patient, dtype=float)),
                        np.asarray(points_map_mm, dtype=float).reshape(-1, 3))
    s = p @ slices.normal_patient
    unwrapped = slices.phases[0] + np.concatenate([[0.0], np.cumsum(wrap_phase(np.diff(slices.phases)))])
    return np.mod(np.interp(s, slices.positions_mm, unwrapped), 1.0)


def predict_at_point_phases(models, point_phases_c, phases_r) -> np.ndarray:
    """Predicted points, each at its own cardiac phase, over respiration phases.

    Parameters
    ----------
    models : sequence of MotionModel, length n
    point_phases_c : (n,) float, cycles
        Each point's cardiac phase.
    phases_r : (m,) float, cycles

    Returns
    -------
    (m, n, 3) float64, mm, source (probe) frame
    """
    from registration.motion_model import common_harmonics, design_matrix, predict_from_design

    models = list(models)
    pc = np.asarray(point_phases_c, dtype=float).ravel()
    pr = np.atleast_1d(np.asarray(phases_r, dtype=float))
    if pc.shape != (len(models),):
        raise ValueError(f"point_phases_c must have shape ({len(models)},), got {pc.shape}")
    X = design_matrix(np.repeat(pc, pr.size), np.tile(pr, pc.size), common_harmonics(models))
    return predict_from_design(models, X.reshape(pc.size, pr.size, -1))
