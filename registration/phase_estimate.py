"""phi_R* with its interval: the value :mod:`registration.temporal`'s estimators return.

:class:`TemporalEstimate` (written in ``registration.json``'s
``phase_estimates``, read back by :meth:`TemporalEstimate.from_dict`) and
:class:`TemporalError`, the error of evidence that cannot give a phase.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hrcore.errors import HeartregError
from hrcore.jsonarrays import float_array, json_floats

__all__ = ["TemporalError", "TemporalEstimate", "wrap_phase"]

#: an interval wider than this (cycles) means the data cannot decide phi_R*.
UNDECIDED_WIDTH = 0.3
#: a Birge ratio above this (chi-square, 1 degree of freedom, 90 %) means the terms disagree.
DISAGREE_RATIO = 2.706


class TemporalError(HeartregError, ValueError):
    """Evidence that cannot give a respiration phase (a trace that misses phases, ...)."""


def wrap_phase(d) -> np.ndarray:
    """Phase differences wrapped into [-0.5, 0.5) cycles.

    Parameters
    ----------
    d : float or array of float, cycles
        Differences of phases (any real values).

    Returns
    -------
    float64 ndarray of the same shape, cycles
        ``d`` plus the whole number of cycles that brings it into [-0.5, 0.5).

    Examples
    --------
    >>> from registration.phase_estimate import wrap_phase
    >>> wrap_phase([0.9, 0.5, -0.75]).round(2).tolist()
    [-0.1, -0.5, 0.25]
    """
    return (np.asarray(d, dtype=float) + 0.5) % 1.0 - 0.5


@dataclass(frozen=True, eq=False)
class TemporalEstimate:
    """phi_R* with its interval, and how it was found.

    Attributes
    ----------
    method : str
        ``"shape"`` or ``"eq10"`` (:class:`TemporalEstimator`).
    evidence : tuple of str
        The terms used: ``"heart"``, ``"fiducial_trace"``, ``"breath_hold"``,
        ``"fiducials"`` (eq. 10's T0).
    respiration_phase : float, cycles
    index : int
        Its index in the sweep.
    interval : (2,) float64, cycles
        90 % interval ``(low, high)`` as phases in [0, 1); ``low > high`` when it
        wraps through 0.
    interval_offsets : (2,) float64, cycles
        The same as offsets from ``phase_r`` (``low <= 0 <= high``).
    confidence : float
    decided : bool
        False when the interval is wider than :data:`UNDECIDED_WIDTH`.
    bootstrap_phases : (B,) float64
        phi_R* of every resample.
    cost : (m,) float64
        ``J - min J`` over the sweep (unitless, chi-square-like); for ``eq10``
        the translation distance from T0 minus its minimum (mm).
    cost_heart, cost_fiducial, cost_prior : (m,) float64
        Its terms (zeros where a term is not used), each minus its own minimum.
    transform_mm, transform_deg : float
        Largest mean map-vertex displacement (mm) and rotation (deg) between
        ``T(phi)`` and ``T(phi_R*)`` over the sweep's phases in the interval.
    disagreement : float
        Birge ratio of the evidence's terms
        (:func:`registration.temporal.disagreement`): about 1 when they agree
        within their noise, 1.0 with a single term; the interval's threshold
        was multiplied by it where it exceeds 1.
    breath_hold_phase : float or None, cycles
        The stated breath-hold phase (``"breath_hold"`` evidence), None when none was used.
    """

    method: str
    evidence: tuple[str, ...]
    respiration_phase: float
    index: int
    interval: np.ndarray
    interval_offsets: np.ndarray
    confidence: float
    decided: bool
    bootstrap_phases: np.ndarray
    cost: np.ndarray
    cost_heart: np.ndarray
    cost_fiducial: np.ndarray
    cost_prior: np.ndarray
    transform_mm: float
    transform_deg: float
    disagreement: float = 1.0
    breath_hold_phase: float | None = None

    @property
    def width(self) -> float:
        """Width of the interval, cycles."""
        return float(self.interval_offsets[1] - self.interval_offsets[0])

    def contains(self, phase: float) -> bool:
        """True when ``phase`` lies in the interval (circularly)."""
        d = float(wrap_phase(phase - self.respiration_phase))
        return bool(self.interval_offsets[0] - 1e-9 <= d <= self.interval_offsets[1] + 1e-9)

    def interval_text(self) -> str:
        """The interval as printed: ``[0.25, 0.35]``, ``[0.95, 0.05] through 0`` when it wraps, ``the whole
        cycle`` when it leaves out less than 0.02 of it (an audit read ``[0.79, 0.78]`` as a narrow interval)."""
        lo, hi = self.interval
        if self.width >= 0.98:
            return "the whole cycle"
        return f"[{lo:.2f}, {hi:.2f}]" + (" through 0" if lo > hi else "")

    def summary(self) -> str:
        """One line: phase, interval, and whether the data decide."""
        text = (f"phi_R* {self.respiration_phase:.2f} ({self.method}), {100 * self.confidence:.0f} % interval "
                f"{self.interval_text()}; final T within {self.transform_mm:.1f} mm, {self.transform_deg:.1f} deg")
        if not self.decided:
            text += f"; UNDECIDED: the data cannot decide phi_R* (interval {self.width:.2f} of a cycle wide): {self.advice()}"
        return text

    def advice(self) -> str:
        """What would decide an undecided phi_R*, from the evidence this estimate used (the summary's, the
        registration's note's and the trust report's hint: an audit was told to trace the staples and state the
        breath-hold phase after doing both)."""
        if "fiducials" in self.evidence:  # eq. 10: the fiducial seed T0 alone
            return ("eq. 10 reads only the fiducial registration T0; the shape estimator (--estimator shape) also "
                    "reads the heart's shape, the staples' trace and a stated breath-hold phase")
        traced, stated = "fiducial_trace" in self.evidence, "breath_hold" in self.evidence
        if stated and (self.cost_prior[self.index] > DISAGREE_RATIO or
                       (not traced and self.disagreement > DISAGREE_RATIO)):
            phase = "" if self.breath_hold_phase is None else f" {self.breath_hold_phase:.2f}"
            return (f"the stated breath-hold phase{phase} disagrees with the data; check it or leave it out "
                    "(--breath-hold-phase)")
        if self.disagreement > DISAGREE_RATIO:  # the heart and the staples' trace
            text = f"the heart and the staples' trace disagree ({self.disagreement:.1f} times their noise); "
            if stated:
                return text + "the stated breath-hold phase does not settle it: check the trace and the stated phase"
            return text + "state the breath-hold phase (--breath-hold-phase)"
        steps = ([] if traced else ["trace the staples over a breath (session format 2)"]) + (
            [] if stated else ["state the breath-hold phase (--breath-hold-phase)"])
        if steps:
            return " or ".join(steps)
        return ("the heart, the staples' trace and the stated breath-hold phase leave it open; "
                "record more points, spread over the heart")

    def to_dict(self) -> dict:
        """JSON-ready, keys equal to the attribute names; non-finite numbers as ``None``."""
        return {
            "method": self.method,
            "evidence": list(self.evidence),
            "respiration_phase": self.respiration_phase,
            "index": self.index,
            "interval": json_floats(self.interval),
            "interval_offsets": json_floats(self.interval_offsets),
            "confidence": self.confidence,
            "decided": self.decided,
            "bootstrap_phases": json_floats(self.bootstrap_phases),
            "cost": json_floats(self.cost),
            "cost_heart": json_floats(self.cost_heart),
            "cost_fiducial": json_floats(self.cost_fiducial),
            "cost_prior": json_floats(self.cost_prior),
            "transform_mm": self.transform_mm,
            "transform_deg": self.transform_deg,
            "disagreement": self.disagreement,
            "breath_hold_phase": self.breath_hold_phase,
        }

    @classmethod
    def from_dict(cls, data: dict) -> "TemporalEstimate":
        """The inverse of :meth:`to_dict` (``None`` reads as NaN)."""
        return cls(
            method=str(data["method"]),
            evidence=tuple(str(e) for e in data["evidence"]),
            respiration_phase=float(data["respiration_phase"]),
            index=int(data["index"]),
            **{k: float_array(data[k]) for k in ("interval", "interval_offsets", "bootstrap_phases", "cost",
                                                  "cost_heart", "cost_fiducial", "cost_prior")},
            confidence=float(data["confidence"]),
            decided=bool(data["decided"]),
            transform_mm=float(data["transform_mm"]),
            transform_deg=float(data["transform_deg"]),
            disagreement=float(data.get("disagreement", 1.0)),  # absent before it was written
            breath_hold_phase=None if data.get("breath_hold_phase") is None else float(data["breath_hold_phase"]),
        )
