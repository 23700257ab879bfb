"""The CT's cardiac phase slice by slice, as a heart model carries it.

A prospectively gated CT is a patchwork: each stack of slices is imaged in its
own heartbeat, at its own cardiac phase (paper Fig. 4).  The model's phi_C* is
the mean; :class:`SlicePhases` keeps each slice's phase and position so that
registration can predict every point at the phase of the slices it lies on
(:mod:`registration.slice_phase`).  In ``model.json`` it is the optional field
``slice_phases`` (absent or ``null`` in models written before it, or for a CT
without a slice clock).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SlicePhases"]


@dataclass(frozen=True, eq=False)
class SlicePhases:
    """Cardiac phase of each CT slice, and where the slices lie.

    Attributes
    ----------
    positions_mm : (k,) float64, mm
        Slice centres along ``normal_patient`` (``ImagePositionPatient . normal``),
        sorted ascending.
    phases : (k,) float64, cycles
        Cardiac phase of each slice (:class:`imaging.phase.PhaseReport`), same order.
    normal_patient : (3,) float64
        Unit slice normal, patient frame.

    Examples
    --------
    >>> s = SlicePhases([2.5, 0.0], [0.49, 0.63], [0, 0, 2])
    >>> s.positions_mm.tolist(), s.phases.tolist(), s.normal_patient.tolist()
    ([0.0, 2.5], [0.63, 0.49], [0.0, 0.0, 1.0])
    >>> SlicePhases.from_dict(s.to_dict()) == s
    True
    """

    positions_mm: np.ndarray
    phases: np.ndarray
    normal_patient: np.ndarray

    def __post_init__(self):
        pos = np.asarray(self.positions_mm, dtype=float).ravel()
        ph = np.asarray(self.phases, dtype=float).ravel()
        normal = np.asarray(self.normal_patient, dtype=float).ravel()
        if pos.size == 0 or pos.shape != ph.shape:
            raise ValueError(f"positions_mm and phases must have the same shape (k,), k >= 1; got {pos.shape}, {ph.shape}")
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(ph))):
            raise ValueError("slice positions and phases must be finite")
        if normal.shape != (3,) or not np.linalg.norm(normal) > 0:
            raise ValueError(f"normal_patient must be a non-zero (3,) vector, got {normal}")
        order = np.argsort(pos, kind="stable")
        for name, value in (("positions_mm", pos[order]), ("phases", np.mod(ph[order], 1.0)),
                            ("normal_patient", normal / np.linalg.norm(normal))):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def __eq__(self, other):
        if not isinstance(other, SlicePhases):
            return NotImplemented
        return all(np.array_equal(getattr(self, n), getattr(other, n))
                   for n in ("positions_mm", "phases", "normal_patient"))

    __hash__ = None

    @classmethod
    def from_report(cls, report, T_patient_from_voxel) -> SlicePhases | None:
        """From a phase report (:func:`imaging.compute_phase_report`) and the volume's affine.

        None when ``report`` is None or not a report (a CT without a slice clock).
        """
        slices = getattr(report, "slices", None)
        if not slices:
            return None
        return cls(
            positions_mm=np.array([s.position_mm for s in slices]),
            phases=np.array([s.cardiac_phase for s in slices]),
            normal_patient=np.asarray(T_patient_from_voxel, dtype=float)[:3, 2],
        )

    def to_dict(self) -> dict:
        """JSON-ready: ``positions_mm``, ``phases``, ``normal_patient`` as lists."""
        return {"positions_mm": self.positions_mm.tolist(), "phases": self.phases.tolist(),
                "normal_patient": self.normal_patient.tolist()}

    @classmethod
    def from_dict(cls, d) -> SlicePhases:
        """Inverse of :meth:`to_dict`; ValueError/KeyError/TypeError on a malformed one."""
        if not isinstance(d, dict):
            raise TypeError(f"slice_phases must be an object, got {type(d).__name__}")
        return cls(d["positions_mm"], d["phases"], d["normal_patient"])

    @property
    def spread(self) -> float:
        """Largest circular distance of a slice phase from their circular mean (cycles)."""
        mean = np.angle(np.mean(np.exp(2j * np.pi * self.phases))) / (2 * np.pi)
        return float(np.max(np.abs((self.phases - mean + 0.5) % 1.0 - 0.5)))
