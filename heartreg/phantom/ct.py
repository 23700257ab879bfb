"""The phantom's prospectively gated ("step-and-shoot") cardiac CT: the written study and its truth.

Timing (paper Fig. 4, GE LightSpeed VCT SnapShot Pulse), planned by
:mod:`heartreg.phantom.acquisition`:

- The scan origin is 10:31:07.250 plus a seeded offset of 0..600 s (ms steps);
  every time is rounded to microseconds so the files reproduce it exactly.
- R-peaks come from :func:`signals.r_peak_times` (the configured heart rate,
  variability and ectopic beats), starting shortly after the scan origin.
- The volume covers z from :data:`~heartreg.phantom.acquisition.Z_START_MM` upwards (-100..+80 mm for both
  sizes) in stacks of ``geometry.slices_per_stack`` slices (a 40 mm detector),
  acquired from superior to inferior.  Stack j is acquired in beat
  ``k = FIRST_BEAT + 2 j``: the scanner triggers at
  ``R_k + gating_target_phase * RR_pre``, with ``RR_pre`` the mean RR before the
  scan (fixed for the scan); the table moves during the next beat.
- The breath-hold slows the heart (``config.breath_hold_slowing``, 8 % by
  default, setting in over BREATH_HOLD_BEATS beats), so the beats imaged are
  longer than predicted and the slices land before the target, at 0.6-0.7 as in
  the paper's Fig. 4 (its scans aimed at 0.7 and got 0.61-0.67).
- Within a stack, the images of the detector rows have a small time offset:
  the half-scan window of the central row is centred on the trigger and the
  outer rows' (cone-beam) windows lag linearly with their distance from it, by
  -ROW_SPREAD_S at the centre to +ROW_SPREAD_S at the edges (-20..+20 ms).  So
  InstanceNumber, which follows acquisition time, interleaves positions.
- Each slice is rendered at the cardiac phase of its own time,
  ``(t - R_k) / (R_{k+1} - R_k)``; when the beat is much shorter than predicted
  (an ectopic beat) the phase lands late or wraps past 1 into the next beat, a
  jump as in the paper's Fig. 4.

Output folder layout of :func:`write_ct_study`::

    out_dir/ct/IM<8 hex>.dcm   one CT Image Storage file per slice, plus the ECG
                               waveform instance (same naming, random order)
    out_dir/qrs.csv            column ``time_s``: R-peak times, s after midnight
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from heartreg.phantom.acquisition import (
    _check_args,
    _streams,
    pixel_grid,
    plan_acquisition,
)
from heartreg.phantom.chest import build_chest
from heartreg.phantom.chest_render import render_slice
from heartreg.phantom.config import CTGeometry, PhantomConfig
from heartreg.phantom.dicom_ct import ct_slice_dataset, derive_uid, ecg_dataset
from heartreg.phantom.geometry import frozen
from heartreg.phantom.layout import fiducials_patient_mm, make_heart
from heartreg.phantom.signals import synthesize_ecg
from hrcore.errors import HeartregError

__all__ = ["CTTruth", "CTStudyExistsError", "write_ct_study"]

#: what the truth copies from the plan unchanged.
_FROM_PLAN = (
    "r_peaks_s", "stack_trigger_s", "slice_position_mm", "slice_time_s", "slice_cardiac_phase",
    "slice_stack", "slice_instance_number", "cardiac_phase", "circular_mean_phase",
)  # fmt: skip
#: the ECG recording starts this long after the scan origin (s).
ECG_START_AFTER_ORIGIN_S = 0.050
#: and ends this long after the last R-peak (s).
ECG_TAIL_S = 0.4


class CTStudyExistsError(HeartregError, FileExistsError):
    """The output folder already holds a CT series."""


@dataclass(frozen=True, eq=False)
class CTTruth:
    """Ground truth of a written CT study.

    Per-slice arrays are sorted by position along the slice normal (+z),
    i.e. voxel index k of ``T_patient_from_voxel``.

    Attributes
    ----------
    size : str
    seed : int
    config_name : str
    geometry : CTGeometry
    T_patient_from_voxel : (4, 4) float64
        Homogeneous (i, j, k, 1) -> LPS mm (i column, j row, k sorted slice).
    scan_origin_s : float, s after midnight
    r_peaks_s : (n_peaks,) float64, s after midnight (= qrs.csv)
    stack_trigger_s : (n_stacks,) float64, s after midnight
    slice_position_mm : (n_slices,) float64, z of each slice centre
    slice_time_s : (n_slices,) float64, s after midnight (AcquisitionTime)
    slice_cardiac_phase : (n_slices,) float64 in [0, 1), the phase rendered
    slice_stack, slice_instance_number : (n_slices,) int
    slice_file : tuple of str, file names inside ``ct/``
    slice_sop_instance_uid : tuple of str
    cardiac_phase : float
        phi_C*, the mean of the slice phases (paper section 2.3).
    circular_mean_phase : float
    fiducials_patient_mm : (9, 3) float64, staple centres (layout order);
        (0, 3) when the anatomy has no skin markers
    study_instance_uid, series_instance_uid, frame_of_reference_uid : str
    ecg_file, ecg_sop_instance_uid, ecg_series_instance_uid : str or None
        None when the ECG waveform instance was not written.
    """

    size: str
    seed: int
    config_name: str
    geometry: CTGeometry
    T_patient_from_voxel: np.ndarray
    scan_origin_s: float
    r_peaks_s: np.ndarray
    stack_trigger_s: np.ndarray
    slice_position_mm: np.ndarray
    slice_time_s: np.ndarray
    slice_cardiac_phase: np.ndarray
    slice_stack: np.ndarray
    slice_instance_number: np.ndarray
    slice_file: tuple
    slice_sop_instance_uid: tuple
    cardiac_phase: float
    circular_mean_phase: float
    fiducials_patient_mm: np.ndarray
    study_instance_uid: str
    series_instance_uid: str
    frame_of_reference_uid: str
    ecg_file: str | None = None
    ecg_sop_instance_uid: str | None = None
    ecg_series_instance_uid: str | None = None
    image_resp_phase: float = field(default=0.3)

    def to_dict(self) -> dict:
        """JSON-ready dict (lists and floats); keys are the attribute names."""
        out = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if isinstance(value, np.ndarray):
                value = value.tolist()
            elif isinstance(value, tuple):
                value = list(value)
            elif isinstance(value, CTGeometry):
                value = {
                    "n_rows": value.n_rows,
                    "n_cols": value.n_cols,
                    "n_slices": value.n_slices,
                    "pixel_mm": value.pixel_mm,
                    "slice_mm": value.slice_mm,
                    "stack_mm": value.stack_mm,
                    "slices_per_stack": value.slices_per_stack,
                }
            out[name] = value
        return out


def _check_out_dir(out_dir) -> Path:
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise NotADirectoryError(f"out_dir {str(out_dir)!r} exists and is not a folder")
    ct = out_dir / "ct"
    if ct.exists():
        if not ct.is_dir():
            raise CTStudyExistsError(f"{str(ct)!r} exists and is not a folder; remove it or choose another out_dir")
        n = sum(1 for _ in ct.iterdir())
        if n:
            raise CTStudyExistsError(
                f"{str(ct)!r} already holds {n} entries; remove it or choose another out_dir"
            )
    return out_dir


def write_ct_study(
    out_dir: Path,
    config: PhantomConfig,
    *,
    size: str = "sample",
    seed: int = 0,
    progress: bool = False,
    ecg_waveform: bool = True,
) -> CTTruth:
    """Acquire the phantom's gated CT and write it as DICOM.

    Writes ``out_dir/ct/*.dcm`` (one CT Image Storage file per slice and, with
    ``ecg_waveform``, one General ECG Waveform Storage file) and
    ``out_dir/qrs.csv``.  Everything is written under temporary names and
    renamed at the end, so a failure leaves no half-written study.

    Parameters
    ----------
    out_dir : path
        Created if missing.  ``out_dir/ct`` must not exist or be empty (a
        :class:`CTStudyExistsError` otherwise); an existing ``qrs.csv`` is replaced.
    config : PhantomConfig
    size : {'sample', 'full'}
        128 x 128 x 72 at 1.95 / 2.5 mm or 512 x 512 x 288 at 0.49 / 0.625 mm.
    seed : int >= 0
        Fixes every byte written.
    progress : bool
        Show a progress bar on stderr.
    ecg_waveform : bool
        Also write the ECG recorded during the scan as a DICOM waveform.

    Returns
    -------
    CTTruth
    """
    _check_args(config, size, seed)
    seed = int(seed)
    out_dir = _check_out_dir(out_dir)
    plan = plan_acquisition(config, size=size, seed=seed)
    g = plan.geometry
    heart = make_heart(config)
    chest = build_chest(heart, anatomy=config.anatomy, phase_c=config.gating_target_phase)
    _, s_ecg, s_noise, s_names = _streams(seed)

    key = json.dumps(config.to_dict(), sort_keys=True)

    def uid(*parts) -> str:
        return derive_uid("heartreg-phantom-ct", key, size, seed, *parts)

    study_uid, series_uid, frame_uid = uid("study"), uid("series"), uid("frame")
    ecg_series_uid, ecg_sop_uid = uid("ecg-series"), uid("ecg-sop")
    sop_uids = tuple(uid("sop", k) for k in range(g.n_slices))

    names_rng = np.random.default_rng(s_names)
    codes: list[int] = []
    while len(codes) < g.n_slices + 1:
        c = int(names_rng.integers(0, 16**8))
        if c not in codes:
            codes.append(c)
    files = tuple(f"IM{c:08X}.dcm" for c in codes[: g.n_slices])
    ecg_file = f"IM{codes[-1]:08X}.dcm"

    xs, ys, pixel_mm = pixel_grid(config, g)
    origin = plan.scan_origin_s
    peaks_ms = np.round((plan.r_peaks_s - origin) * 1000.0, 3)
    nominal_ms = float(np.mean(np.diff(plan.r_peaks_s))) * 1000.0
    noise_seeds = s_noise.spawn(g.n_slices)
    order = np.argsort(plan.slice_instance_number)  # render in acquisition order

    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir / f".ct.partial-{os.getpid()}"
    if tmp.exists():  # left over by a killed run of this process id
        shutil.rmtree(tmp)
    tmp.mkdir()
    qrs_tmp = out_dir / ".qrs.csv.partial"
    try:
        for k in tqdm(order, desc="CT slices", unit="slice", file=sys.stderr, disable=not progress):
            z = float(plan.slice_position_mm[k])
            hu = render_slice(
                chest,
                z_mm=z,
                phase_c=float(plan.slice_cardiac_phase[k]),
                xs_mm=xs,
                ys_mm=ys,
                rng=np.random.default_rng(noise_seeds[k]),
                noise_hu=config.noise.ct_noise_hu,
            )
            stack = int(plan.slice_stack[k])
            ds = ct_slice_dataset(
                hu,
                seed=seed,
                study_uid=study_uid,
                series_uid=series_uid,
                frame_uid=frame_uid,
                sop_uid=sop_uids[k],
                instance_number=int(plan.slice_instance_number[k]),
                acquisition_number=stack + 1,
                position_mm=(xs[0], ys[0], z),
                pixel_mm=pixel_mm,
                slice_mm=g.slice_mm,
                origin_s=origin,
                time_s=float(plan.slice_time_s[k]),
                trigger_ms=(plan.stack_trigger_s[stack] - plan.stack_r_peak_s[stack]) * 1000.0,
                r_peaks_ms=peaks_ms,
                nominal_interval_ms=nominal_ms,
            )
            ds.save_as(tmp / files[k], enforce_file_format=True)
        if ecg_waveform:
            ecg_start = round(origin + ECG_START_AFTER_ORIGIN_S, 6)
            duration = plan.r_peaks_s[-1] + ECG_TAIL_S - ecg_start
            n = int(round(duration * config.ecg_rate_hz))
            ecg = synthesize_ecg(
                np.random.default_rng(s_ecg),
                np.asarray(plan.r_peaks_s),
                start_s=ecg_start,
                duration_s=n / config.ecg_rate_hz,
                rate_hz=config.ecg_rate_hz,
                noise_mv=config.noise.ecg_noise_mv,
                wander_mv=config.noise.ecg_wander_mv,
                resp_rate_hz=config.resp_rate_hz,
            )
            ds = ecg_dataset(
                ecg,
                seed=seed,
                study_uid=study_uid,
                series_uid=ecg_series_uid,
                sop_uid=ecg_sop_uid,
                origin_s=origin,
                start_offset_ms=ECG_START_AFTER_ORIGIN_S * 1000.0,
                rate_hz=config.ecg_rate_hz,
            )
            ds.save_as(tmp / ecg_file, enforce_file_format=True)
        with open(qrs_tmp, "w", newline="") as fh:
            fh.write("time_s\n")
            fh.writelines(f"{t:.6f}\n" for t in plan.r_peaks_s)
        ct = out_dir / "ct"
        if ct.exists():
            ct.rmdir()  # checked empty above
        os.replace(tmp, ct)
        os.replace(qrs_tmp, out_dir / "qrs.csv")
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        qrs_tmp.unlink(missing_ok=True)
        raise

    T = np.diag([pixel_mm, pixel_mm, g.slice_mm, 1.0])
    T[:3, 3] = [xs[0], ys[0], plan.slice_position_mm[0]]
    fiducials = fiducials_patient_mm() if config.anatomy.markers else np.zeros((0, 3))
    return CTTruth(
        size=size,
        seed=seed,
        config_name=config.name,
        geometry=g if pixel_mm == g.pixel_mm else dataclasses.replace(g, pixel_mm=pixel_mm),
        T_patient_from_voxel=frozen(T),
        scan_origin_s=origin,
        **{name: getattr(plan, name) for name in _FROM_PLAN},
        slice_file=files,
        slice_sop_instance_uid=sop_uids,
        fiducials_patient_mm=frozen(fiducials),
        study_instance_uid=study_uid,
        series_instance_uid=series_uid,
        frame_of_reference_uid=frame_uid,
        ecg_file=ecg_file if ecg_waveform else None,
        ecg_sop_instance_uid=ecg_sop_uid if ecg_waveform else None,
        ecg_series_instance_uid=ecg_series_uid if ecg_waveform else None,
        image_resp_phase=config.image_resp_phase,
    )
