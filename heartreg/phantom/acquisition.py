"""When and where every slice of the phantom's prospectively gated scan is acquired.

:func:`plan_acquisition` lays out the R-peaks of the breath-hold (the heart
slows over its first beats), triggers one stack of detector rows per beat at
the gating's target phase, and gives each slice its position, time, cardiac
phase and instance number. :mod:`heartreg.phantom.ct` renders and writes the
planned slices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from heartreg.phantom.config import SIZES, CTGeometry, PhantomConfig
from heartreg.phantom.geometry import frozen
from heartreg.phantom.signals import phase_from_events, r_peak_times

__all__ = ["AcquisitionPlan", "pixel_grid", "plan_acquisition", "Z_START_MM", "ROW_SPREAD_S"]


#: inferior edge of the scanned range (mm); the range is n_slices * slice_mm long.
Z_START_MM = -100.0
#: time offset of the outermost detector rows relative to the central one: +-20 ms.
ROW_SPREAD_S = 0.020
#: scan origin before the seeded offset: 10:31:07.250, s after midnight.
SCAN_ORIGIN_BASE_S = 10 * 3600 + 31 * 60 + 7.250
#: the first stack is acquired in beat R[FIRST_BEAT] (R[FIRST_BEAT-1] gives the prediction).
FIRST_BEAT = 2
#: beats over which the breath-hold's slowing of the heart sets in
BREATH_HOLD_BEATS = 3


def _us(t):
    return np.round(np.asarray(t, dtype=float) * 1e6) / 1e6


def _circular_mean(phase) -> float:
    z = np.mean(np.exp(2j * np.pi * np.asarray(phase)))
    return float(np.mod(np.angle(z) / (2 * np.pi), 1.0))


def _streams(seed: int):
    """Independent generators: timing, ECG, CT noise, file names."""
    return np.random.SeedSequence([seed, 0x4354]).spawn(4)


@dataclass(frozen=True, eq=False)
class AcquisitionPlan:
    """When and where every slice of the gated scan is acquired.

    Per-slice arrays are sorted by position along the slice normal (+z).

    Attributes
    ----------
    geometry : CTGeometry
    scan_origin_s : float, s after midnight
    r_peaks_s : (n_peaks,) float64, s after midnight
    stack_trigger_s : (n_stacks,) float64, s after midnight
    stack_r_peak_s : (n_stacks,) float64
        The R-peak that triggered each stack.
    slice_position_mm : (n_slices,) float64, patient z of each slice centre
    slice_time_s : (n_slices,) float64, mid-scan time
    slice_cardiac_phase : (n_slices,) float64 in [0, 1)
    slice_stack : (n_slices,) int, stack index (0 = first acquired, most superior)
    slice_instance_number : (n_slices,) int, 1-based rank in acquisition time
    """

    geometry: CTGeometry
    scan_origin_s: float
    r_peaks_s: np.ndarray
    stack_trigger_s: np.ndarray
    stack_r_peak_s: np.ndarray
    slice_position_mm: np.ndarray
    slice_time_s: np.ndarray
    slice_cardiac_phase: np.ndarray
    slice_stack: np.ndarray
    slice_instance_number: np.ndarray

    @property
    def cardiac_phase(self) -> float:
        """Volume phase phi_C*: mean of the slice phases (the paper's estimate)."""
        return float(np.mean(self.slice_cardiac_phase))

    @property
    def circular_mean_phase(self) -> float:
        return _circular_mean(self.slice_cardiac_phase)

    @property
    def pixel_centres_mm(self) -> np.ndarray:
        """(n_cols,) patient x (= y, square FOV centred on 0) of the pixel centres, mm."""
        g = self.geometry
        return _pixel_centres(g.n_cols, g.pixel_mm)


def _pixel_centres(n: int, pixel_mm: float, centre_mm: float = 0.0) -> np.ndarray:
    return np.round(centre_mm - 0.5 * n * pixel_mm + (np.arange(n) + 0.5) * pixel_mm, 4)


def fov_centre_mm(config: PhantomConfig) -> tuple[float, float]:
    """Patient (x, y) mm at the centre of a tight field of view: the heart's origin rounded to 0.1 mm."""
    cx, cy = (round(float(c), 1) for c in config.heart_origin_mm[:2])
    return cx, cy


def pixel_grid(config: PhantomConfig, geometry: CTGeometry):
    """Pixel centres of the CT's axial grid (patient x of the columns, y of the rows).

    The size's own field of view is centred on the body; a tight
    ``config.anatomy.fov_mm`` is centred on the heart's origin (rounded to
    0.1 mm) and keeps the matrix, so its pixels are ``fov_mm / n_cols``.

    Returns
    -------
    xs_mm : (n_cols,) float64
    ys_mm : (n_rows,) float64
    pixel_mm : float
    """
    fov = config.anatomy.fov_mm
    if fov is None:
        return (_pixel_centres(geometry.n_cols, geometry.pixel_mm),
                _pixel_centres(geometry.n_rows, geometry.pixel_mm), geometry.pixel_mm)
    pixel = round(float(fov) / geometry.n_cols, 6)
    cx, cy = fov_centre_mm(config)
    return _pixel_centres(geometry.n_cols, pixel, cx), _pixel_centres(geometry.n_rows, pixel, cy), pixel


def _check_args(config, size, seed):
    if not isinstance(config, PhantomConfig):
        raise TypeError(f"config must be a PhantomConfig (see make_config), got {type(config).__name__}")
    if size not in SIZES:
        raise ValueError(f"unknown size {size!r}; choose one of: {', '.join(sorted(SIZES))}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")


def plan_acquisition(config: PhantomConfig, *, size: str = "sample", seed: int = 0) -> AcquisitionPlan:
    """Schedule the gated scan: R-peaks, triggers, slice times and phases.

    Cheap (no rendering); :func:`write_ct_study` renders and writes this plan.
    The timing does not depend on ``size`` when both sizes have the same number
    of stacks (true for the built-in sizes).

    Parameters
    ----------
    config : PhantomConfig
    size : {'sample', 'full'}
        Key of :data:`config.SIZES`.
    seed : int >= 0

    Returns
    -------
    AcquisitionPlan
    """
    _check_args(config, size, seed)
    g = SIZES[size]
    timing = np.random.default_rng(_streams(int(seed))[0])
    origin = round(SCAN_ORIGIN_BASE_S + int(timing.integers(0, 600_000)) / 1000.0, 3)
    rr0 = 1.0 / config.heart_rate_hz
    per = g.slices_per_stack
    n_stacks = math.ceil(g.n_slices / per)
    start = origin + 1.2 * rr0  # so the first R-peak falls 0.3..0.9 RR after the origin
    beats_needed = FIRST_BEAT + 2 * n_stacks + 3
    peaks = r_peak_times(
        timing,
        start_s=start,
        end_s=start + beats_needed * 1.7 * rr0,
        heart_rate_hz=config.heart_rate_hz,
        hrv_fraction=config.hrv_fraction,
        ectopic_probability=config.ectopic_probability,
        resp_rate_hz=config.resp_rate_hz,
    )
    # the breath-hold slows the heart: beats from the scan's first R-peak on
    # lengthen, reaching 1 + breath_hold_slowing over BREATH_HOLD_BEATS beats
    rr = np.diff(peaks)
    ramp = np.clip((np.arange(rr.size) - FIRST_BEAT + 1) / BREATH_HOLD_BEATS, 0.0, 1.0)
    rr = rr * (1.0 + config.breath_hold_slowing * ramp)
    peaks = _us(peaks[0] + np.concatenate([[0.0], np.cumsum(rr)]))
    k = FIRST_BEAT + 2 * np.arange(n_stacks)
    # the trigger delay comes from the mean RR before the scan, fixed for the scan
    rr_pred = float(np.mean(np.diff(peaks[: FIRST_BEAT + 1])))
    trigger = _us(peaks[k] + config.gating_target_phase * rr_pred)

    z = np.round(Z_START_MM + (np.arange(g.n_slices) + 0.5) * g.slice_mm, 4)
    order_sup = np.arange(g.n_slices)[::-1]  # acquisition goes superior -> inferior
    m = np.empty(g.n_slices, dtype=int)
    m[order_sup] = np.arange(g.n_slices)
    stack = m // per
    row = m % per
    centre = 0.5 * (per - 1)
    lag = np.abs(row - centre) / centre if per > 1 else np.zeros(g.n_slices)
    time = _us(trigger[stack] + ROW_SPREAD_S * (2.0 * lag - 1.0))
    phase = phase_from_events(time, peaks)
    if np.any(np.isnan(phase)):
        raise RuntimeError("internal error: the R-peaks do not cover the scan; please report")
    # acquisition order: by time, ties superior first
    rank = np.lexsort((-z, time))
    instance = np.empty(g.n_slices, dtype=int)
    instance[rank] = np.arange(1, g.n_slices + 1)
    # keep the R-peaks up to one beat after the last slice
    last = int(np.searchsorted(peaks, time.max(), side="right"))
    peaks = peaks[: last + 2]
    return AcquisitionPlan(
        geometry=g,
        scan_origin_s=float(origin),
        r_peaks_s=frozen(peaks),
        stack_trigger_s=frozen(trigger),
        stack_r_peak_s=frozen(peaks[k]),
        slice_position_mm=frozen(z),
        slice_time_s=frozen(time),
        slice_cardiac_phase=frozen(phase),
        slice_stack=frozen(stack, int),
        slice_instance_number=frozen(instance, int),
    )
