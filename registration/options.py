"""The options of a registration, written once: the library, the pipeline and the
command all take a :class:`RegistrationOptions` (the command's flags fill one).

Examples
--------
>>> from registration.options import RegistrationOptions
>>> opts = RegistrationOptions(harmonics=(3, 2, 1, 1), phase_step=0.02)
>>> opts.harmonics.cardiac, opts.estimator
(3, 'shape')
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType

from hrcore.errors import UsageError
from hrcore.options import OptionsRecord
from registration.motion_model import Harmonics

__all__ = ["DEFAULT_HARMONICS", "DEFAULT_STEP", "MIN_BEATS", "MIN_BREATHS", "RegistrationOptions"]

#: fewest complete heartbeats a point's record must hold to be used.
MIN_BEATS = 4
#: fewest complete breaths.
MIN_BREATHS = 2
#: step of the sweeps (cycles): 101 phases, as the paper.
DEFAULT_STEP = 0.01
#: harmonics (Hc, Hr, Hmc, Hmr) of the motion models by default: the paper's (5, 4, 2, 1)
#: with more coupled terms, which hold a heartbeat whose amplitude breathes (docs/reproduction.md).
DEFAULT_HARMONICS = Harmonics(5, 4, 5, 2)
#: how phi_R* is chosen by default (see :mod:`registration.temporal`).
ESTIMATORS = ("shape", "eq10")


@dataclass(frozen=True)
class RegistrationOptions(OptionsRecord):
    """How a session is registered (:func:`registration.register_session`).

    Attributes
    ----------
    harmonics : Harmonics or (Hc, Hr, Hmc, Hmr)
        Fourier harmonics of the motion models (``--harmonics``; default
        :data:`DEFAULT_HARMONICS` (5, 4, 5, 2); the paper's: ``Harmonics()``, 5, 4, 2, 1).
    phase_step : float, cycles
        Step of both sweeps (``--step``; 0.01: 101 phases, as the paper).
    cardiac_sweep : bool
        Also sweep phi_C at phi_R* (paper Fig. 2A).
    cardiac_phase_step : float, cycles, optional
        Step of the cardiac sweep when other than ``phase_step``.
    icp_options : mapping, optional
        Keyword arguments of :func:`registration.icp.icp` (``max_iterations``:
        ``--icp-max-iterations``; method, trim_fraction, huber_mm, tolerances ...).
    min_beats, min_breaths : int
        Fewest complete heartbeats and breaths a record must hold to be used.
    coverage_bins : int
        Phase bins checked for coverage (a note per point with empty bins).
    max_fre_mm : float, mm
        Above this FRE in the documented order the fiducial correspondence is
        searched.
    estimator : {"shape", "eq10"}
        How phi_R* is chosen (``--estimator``): the chest's traced staples and
        the heart's shape over the sweep, with a bootstrap interval, or the
        paper's empirical metric (eq. 10).
    breath_hold_phase : float, optional
        The CT's breath-hold respiration phase if known (``--breath-hold-phase``),
        with standard deviation ``breath_hold_sd`` (cycles); used by ``"shape"``.
    slice_phases : bool
        Predict each point at the cardiac phase of the CT slices it lies on
        when the model carries them (``HeartModel.slice_phases``;
        :mod:`registration.slice_phase`); False (``--no-slice-phases``): every
        point at the model's phi_C*, as the paper.
    """

    harmonics: Harmonics = DEFAULT_HARMONICS
    phase_step: float = DEFAULT_STEP
    cardiac_sweep: bool = True
    cardiac_phase_step: float | None = None
    icp_options: MappingProxyType | None = None
    min_beats: int = MIN_BEATS
    min_breaths: int = MIN_BREATHS
    coverage_bins: int = 10
    max_fre_mm: float = 3.0
    estimator: str = "shape"
    breath_hold_phase: float | None = None
    breath_hold_sd: float = 0.05
    slice_phases: bool = True

    def __post_init__(self):
        h = self.harmonics
        if not isinstance(h, Harmonics):
            values = tuple(h)
            if len(values) != 4:
                raise UsageError(f"harmonics (--harmonics) must be a Harmonics or (Hc, Hr, Hmc, Hmr), got {h!r}")
            try:
                h = Harmonics(*values)
            except ValueError as exc:
                raise UsageError(f"harmonics (--harmonics HC HR HMC HMR): {exc}") from None
            object.__setattr__(self, "harmonics", h)
        if h.respiratory < 1 or h.cardiac < 1:
            raise UsageError(
                "harmonics (--harmonics HC HR HMC HMR): the sweeps need at least one cardiac and one "
                f"respiratory harmonic, got Hc={h.cardiac}, Hr={h.respiratory}"
            )
        estimator = getattr(self.estimator, "value", self.estimator)
        if estimator not in ESTIMATORS:
            raise UsageError(f"estimator (--estimator) must be one of {list(ESTIMATORS)}, got {self.estimator!r}")
        object.__setattr__(self, "estimator", estimator)
        for name in ("min_beats", "min_breaths", "coverage_bins"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise UsageError(f"{name} must be a positive integer, got {value!r}")
        if self.breath_hold_phase is not None and not 0.0 <= self.breath_hold_phase <= 1.0:
            raise UsageError(
                f"breath_hold_phase (--breath-hold-phase) must be a phase in [0, 1], got {self.breath_hold_phase}"
            )
        if not self.breath_hold_sd > 0:
            raise UsageError(f"breath_hold_sd must be positive, got {self.breath_hold_sd!r}")
        self._freeze_mapping("icp_options")
