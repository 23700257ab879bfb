"""One phantom case on disk: the gated CT study, the QRS file, the session, the truth.

``make_phantom(out_dir, preset=..., size=..., seed=...)`` writes::

    OUT_DIR/ct/          the gated CT series and its ECG waveform instance (DICOM)
    OUT_DIR/qrs.csv      R-peak times of the CT, column time_s (AcquisitionTime clock)
    OUT_DIR/session/     the intra-operative session (docs/formats.md)
    OUT_DIR/truth.json   every true value, the configuration and the seed
    OUT_DIR/session_plus/  with ``plus=True``: the same session, poses in a PLUS
                         sequence file (:mod:`heartreg.phantom.plus`)

Everything is written under a temporary name inside ``OUT_DIR`` first and moved
into place at the end, so a failure never leaves a half-written case.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from heartreg import __version__
from heartreg.phantom.acquisition import fov_centre_mm
from heartreg.phantom.config import PAPER_IMAGE_PHASE, SIZES, Anatomy, config_from_dict, make_config
from heartreg.phantom.ct import write_ct_study
from heartreg.phantom.layout import T_patient_from_probe, fiducials_patient_mm, make_heart
from heartreg.phantom.plus import write_plus_session
from heartreg.phantom.session import write_session
from hrcore.errors import HeartregError
from hrcore.output import staged_output

__all__ = ["make_phantom", "heart_from_truth", "PhantomError", "TRUTH_FORMAT_VERSION"]

TRUTH_FORMAT_VERSION = 1
_OUTPUTS = ("ct", "qrs.csv", "session", "session_plus", "truth.json")


class PhantomError(HeartregError, ValueError):
    """Invalid phantom request (bad argument or an output folder in the way)."""


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


#: room (mm) between a staple's centre and the edge of the field of view: measured on the default preset
#: (staples 83.8 mm in front of the heart's centre), at 170 mm (1.2 mm of room) the model found 6 of 9
#: staples, at 172 mm (2.2 mm) all 9; twice that, for the skin around a staple that its localisation reads.
STAPLE_ROOM_MM = 4.0


def _fov_showing_staples(config) -> float:
    """Narrowest tight field of view (mm, centred where ``pixel_grid`` centres it) holding every staple."""
    return float(2 * (np.abs(fiducials_patient_mm()[:, :2] - fov_centre_mm(config)).max() + STAPLE_ROOM_MM))


def make_phantom(
    out_dir,
    *,
    preset: str = "default",
    size: str = "sample",
    seed: int = 0,
    session: bool = True,
    progress: bool = False,
    overwrite: bool = False,
    plus: bool | float = False,
    anatomy: str | None = None,
    fov_mm: float | None = None,
    markers: bool | None = None,
    stent: bool | None = None,
    **overrides,
) -> dict:
    """Write a complete phantom case to ``out_dir`` and return its truth.

    Parameters
    ----------
    out_dir : path
        Output folder; created if missing.  Existing phantom outputs in it are
        refused unless ``overwrite``.
    preset : str
        A name from :data:`heartreg.phantom.config.PRESETS`.
    size : {'sample', 'full'}
        CT grid (see :data:`heartreg.phantom.config.SIZES`).
    seed : int
        Non-negative seed: the same seed gives the same bytes.
    session : bool
        Also write the intra-operative session.
    plus : bool or float
        Also write the session with its poses in a PLUS sequence file
        (``session_plus/``): a frame per sample (True), or the tracker at its
        own rate, this many Hz, its frames jittered (a number).
    anatomy : {'spheroid', 'chambers'}, optional
        The heart: the paper's analytic spheroid or four chambers with great
        vessels (default: the preset's; ``human`` has chambers).
    fov_mm : float, optional
        A tight CT field of view (mm, square, centred on the heart); with a session it
        must show every skin staple (:data:`STAPLE_ROOM_MM` beyond each centre).
    markers : bool, optional
        Draw the 9 skin staples (default: the preset's, True).  Without them
        there is nothing to touch in surgery: pass ``session=False``.
    stent : bool, optional
        A metal stent in the descending aorta.
    **overrides
        Fields of :class:`~heartreg.phantom.config.PhantomConfig` to replace
        (e.g. ``n_points=20``).

    Returns
    -------
    dict
        The contents of ``truth.json``.
    """
    if size not in SIZES:
        raise PhantomError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise PhantomError(f"seed (--seed) must be a non-negative integer, got {seed!r}")
    if isinstance(plus, (bool, np.bool_)):
        plus_rate = bool(plus)
    elif isinstance(plus, (int, float, np.integer, np.floating)) and 20.0 <= float(plus) <= 100.0:
        plus_rate = float(plus)  # the tracker's own rate (Hz): between the slowest the reader takes and the signals'
    else:
        raise PhantomError(f"plus (--plus) must be True, False or a tracker's rate of 20-100 Hz, got {plus!r}")
    try:
        config = make_config(preset, **overrides)
        choices = {"heart": anatomy, "fov_mm": fov_mm, "markers": markers, "stent": stent}
        choices = {k: v for k, v in choices.items() if v is not None}
        if choices:
            config = dataclasses.replace(config, anatomy=dataclasses.replace(config.anatomy, **choices))
    except (ValueError, TypeError) as exc:
        raise PhantomError(str(exc)) from None
    if session and not config.anatomy.markers:
        raise PhantomError(
            "a case without skin markers has no fiducials for the session to touch; "
            "pass session=False (--no-session) with markers=False (--no-markers)"
        )
    if session and config.anatomy.fov_mm is not None:
        narrowest = _fov_showing_staples(config)
        if config.anatomy.fov_mm < narrowest:
            raise PhantomError(
                f"a {config.anatomy.fov_mm:g} mm field of view centred on the heart leaves skin staples out of the "
                f"CT, so the session would touch fiducials the model cannot find; give --fov-mm "
                f"{np.ceil(narrowest):g} or more, or pass --no-session"
            )

    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise PhantomError(f"output {out_dir} exists and is not a folder")
    present = [name for name in _OUTPUTS if (out_dir / name).exists()]
    if present and not overwrite:
        raise PhantomError(
            f"{out_dir} already holds phantom outputs ({', '.join(present)}); "
            "choose an empty folder or pass overwrite=True (--overwrite)"
        )
    # staged beside (or, when out_dir holds other things, inside) out_dir and renamed
    # into place at the end: a failure, a signal or kill -9 leaves out_dir as it was
    with staged_output(out_dir, parts=_OUTPUTS, overwrite=True, earlier=("truth.json",),
                       what="phantom folder") as staging:
        ct_truth = write_ct_study(staging, config, size=size, seed=int(seed), progress=progress)
        truth = {
            "format": "heartreg-phantom-truth",
            "version": TRUTH_FORMAT_VERSION,
            "generator": f"heartreg {__version__}",
            "preset": config.name,
            "size": size,
            "seed": int(seed),
            "paper_image_phase": PAPER_IMAGE_PHASE.get(config.name),
        }
        truth.update(ct_truth.to_dict())
        heart = make_heart(config)
        truth.update(
            {
                "respiration_phase": config.image_resp_phase,
                "heart_axes_patient": heart.axes_patient,
                "heart_axes_note": "columns x, y, z of the heart construction frame in the CT patient frame (LPS)",
                "heart_origin_patient_mm": heart.origin_patient_mm,
                "T_patient_from_heart": heart.T_patient_from_heart,
                "heart_euler_xyz_deg": list(config.euler_xyz_deg),
                "T_patient_from_probe": T_patient_from_probe(),
            }
        )
        if config.anatomy != Anatomy():
            truth["anatomy"] = _anatomy_truth(config, heart, truth["cardiac_phase"])
        if session:
            session_truth = write_session(staging, config, seed=int(seed), progress=progress)
            truth["session"] = session_truth.to_dict()
            if plus_rate is not False:
                rate = None if plus_rate is True else plus_rate
                write_plus_session(staging / "session", staging / "session_plus", tracker_rate_hz=rate, seed=int(seed))
        truth["config"] = config.to_dict()
        truth = _jsonable(truth)
        (staging / "truth.json").write_text(json.dumps(truth, indent=1, sort_keys=True) + "\n")
    return truth


def _anatomy_truth(config, heart, phase_c: float) -> dict:
    """The ``anatomy`` block of ``truth.json`` (docs/formats.md)."""
    from heartreg.phantom.anatomy import ANATOMY_HU, WALL_THICKNESS_MM, ChamberHeart
    from heartreg.phantom.great_vessels import vessel_origins
    from heartreg.phantom.chest import build_chest

    a = config.anatomy
    chest = build_chest(heart, anatomy=a, phase_c=config.gating_target_phase)
    out = {"heart": a.heart, "fov_mm": a.fov_mm, "markers": a.markers}
    if chest.stent is not None:
        st = chest.stent
        out["stent"] = {
            "vessel": "descending_aorta",
            "start_patient_mm": st.start_mm,
            "end_patient_mm": st.end_mm,
            "radius_mm": st.radius_mm,
            "strut_mm": st.strut_mm,
            "hu": st.hu,
        }
    if isinstance(heart, ChamberHeart):
        phase_r = config.image_resp_phase
        out.update({
            "epicardium": {
                "phase_c": phase_c,
                "phase_r": phase_r,
                "note": "the myocardium's outer surface without the great vessels (closed over their "
                        "mouths); sample it with heartreg.phantom.heart_from_truth(truth)"
                        ".sample_surface(phase_c, phase_r) or .surface_distance(points, phase_c, phase_r)",
            },
            "vessel_origins": vessel_origins(heart, chest.vessels, phase_c, phase_r),
            "vessels": [
                {"name": v.name, "chamber": v.chamber, "lumen_radius_mm": v.lumen_radius_mm,
                 "wall_mm": v.wall_mm, "hu": v.hu, "centreline_patient_mm": v.points_mm}
                for v in chest.vessels
            ],
            "wall_thickness_mm": dict(WALL_THICKNESS_MM),
            "hu": dict(ANATOMY_HU),
            "local_axes_patient": heart.T_patient_from_heart[:3, :3] @ heart.local_axes.T,
            "local_axes_note": "columns anterior, left, long axis of the chambers' layout frame (LPS)",
        })
    return out


def heart_from_truth(truth: dict):
    """The phantom heart of a ``truth.json`` (as a dict): the exact epicardium.

    ``heart.surface_distance(points, phase_c, phase_r)`` gives the signed
    distance (mm, > 0 outside) of patient points to the true epicardium,
    ``heart.sample_surface(phase_c, phase_r)`` (chambers) exact surface points.
    """
    return make_heart(config_from_dict(truth["config"]))
