"""The ``heartreg`` command line's parser: commands, flag groups shared between commands, argument types.

Flag groups (the model's, the registration's, the study's, the cluster's) are
added once and shared by every command that takes them, so ``pipeline`` reaches
every stage option; their defaults come from the options dataclasses.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from heartreg import __version__
from heartreg.cli_commands import (
    _cmd_batch,
    _cmd_demo,
    _cmd_evaluate_temporal,
    _cmd_model,
    _cmd_phantom,
    _cmd_phases,
    _cmd_pipeline,
    _cmd_register,
    _cmd_reproduce,
)
from heartreg.cli_track import _cmd_track


def _finite(value: str) -> float:
    """A float option: a finite number (``nan`` and ``inf`` are refused by name)."""
    import math

    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a number") from None
    if not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"{value} is not a finite number")
    return number


def _path(value: str) -> Path:
    """A file or folder argument: never empty (``Path("")`` is the working folder: an unset ``$OUT``)."""
    if not value.strip():
        raise argparse.ArgumentTypeError("is empty; give a file or folder path")
    return Path(value)


def _count(value: str) -> int:
    """A count option: an integer of 1 or more."""
    if not value.strip().isdigit() or int(value) < 1:
        raise argparse.ArgumentTypeError(f"{value!r} is not a whole number of 1 or more")
    return int(value)


def _port(value: str) -> int:
    """A TCP port option: an integer 0..65535 (0: any free port)."""
    try:
        port = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a TCP port (0..65535)")
    return port


def _label_arg(value: str):
    """``--label``: a label value, or its name in the label map (TotalSegmentator, DICOM SEG)."""
    return int(value) if value.lstrip("-").isdigit() else value


def _seed_arg(value: str):
    """``--seed``: ``X,Y,Z`` in patient LPS mm, or a 3D Slicer markups file (``.mrk.json``) whose first point is read."""
    if value.lower().endswith((".json", ".fcsv")):
        return Path(value)
    parts = value.replace(",", " ").split()
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"{value!r} is neither X,Y,Z (patient LPS mm) nor a .mrk.json markups file")
    return tuple(_finite(x) for x in parts)


def _fiducials_arg(value: str):
    """``--fiducials``: a count of skin staples to insist on, or a 3D Slicer markups file of their positions."""
    if value.lower().endswith((".json", ".fcsv")):
        return Path(value)
    if not value.lstrip("-").isdigit():  # a negative count is refused by ModelOptions, naming the option
        raise argparse.ArgumentTypeError(f"{value!r} is neither a count of fiducials nor a .mrk.json markups file")
    return int(value)


def _tracker_rate_arg(value: str) -> float:
    """``phantom --plus HZ``: a tracker's rate between the slowest the reader takes (20 Hz) and the signals'."""
    try:
        number = _finite(value)
    except argparse.ArgumentTypeError:  # most likely the output folder, given after a bare --plus
        raise argparse.ArgumentTypeError(f"{value!r} is no tracker rate in Hz (give the output folder before "
                                         "--plus, or a rate after it)") from None
    if not 20.0 <= number <= 100.0:
        raise argparse.ArgumentTypeError(f"{value} Hz is not a tracker's rate between 20 and 100 Hz (the signals')")
    return number


def _floor_hu_arg(value: str) -> float:
    """``--fiducial-floor-hu``: between soft tissue (100 HU) and metal (3000 HU)."""
    number = _finite(value)
    if not 100.0 <= number <= 3000.0:
        raise argparse.ArgumentTypeError(f"{value} HU is not between soft tissue (100) and metal (3000)")
    return number


def _series_arg(value: str):
    """``--series``: an index from ``--list-series`` or a SeriesInstanceUID."""
    return int(value) if value.isdigit() else value


def _add_cluster_options(p, local_help: str = "") -> None:
    from heartreg.batch.cluster import DEFAULT_MEMORY_LIMIT

    p.add_argument("--workers", type=int, default=None,
                   help="local worker processes, one thread each (default: the usable cores"
                   + (f"; {local_help})" if local_help else ")"))
    p.add_argument("--memory-limit", default=DEFAULT_MEMORY_LIMIT,
                   help=f"memory limit of each local worker (default {DEFAULT_MEMORY_LIMIT})")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run on this Dask scheduler instead of a local cluster")


def _add_model_options(p) -> None:
    """The flags of :class:`modeling.ModelOptions` (model and pipeline)."""
    from modeling.options import ModelOptions

    p.add_argument("--mask", type=_path, default=None,
                   help="external label map (NIfTI, NRRD or a 3D Slicer .seg.nrrd, DICOM SEG, or a TotalSegmentator "
                        "folder) instead of the automatic segmentation")
    p.add_argument("--label", type=_label_arg, default=None, help="heart label in --mask: value or name (e.g. heart; a Slicer segment's name)")
    p.add_argument("--seed", type=_seed_arg, default=None, metavar="X,Y,Z|POINT.mrk.json",
                   help="a point inside the heart to start the automatic segmentation from, when its own start "
                        "fails: patient LPS mm (--seed=-12.5,40,-100 when it starts with a minus), or a 3D Slicer "
                        "markups file (.mrk.json or the legacy .fcsv; its first point, LPS or RAS as it says)")
    p.add_argument("--faces", type=int, default=None,
                   help=f"faces of the decimated mesh (default {ModelOptions.target_faces})")
    p.add_argument("--fiducials", type=_fiducials_arg, default=None, metavar="N|POINTS.mrk.json",
                   help="skin fiducials expected, insisted on (default: those found on the skin; 0: none), or their "
                        "positions in a 3D Slicer markups file (.mrk.json or .fcsv: every placed point, LPS or RAS "
                        "as it says; e.g. the "
                        "model's fiducials_ct.mrk.json corrected in Slicer), used instead of the search")
    p.add_argument("--fiducial-floor-hu", type=_floor_hu_arg, default=None,
                   help="HU above which fiducial excess density counts (100-3000)")
    p.add_argument("--keep-vessels", action="store_true",
                   help="keep the great-vessel stubs (do not trim them off the base)")
    p.add_argument("--trim-vessels", action="store_true",
                   help="trim vessel stubs off a --mask too (by default a given mask is meshed as it is)")


def _add_harmonics_option(p) -> None:
    from registration.options import DEFAULT_HARMONICS

    p.add_argument("--harmonics", type=int, nargs=4, metavar=("HC", "HR", "HMC", "HMR"), default=None,
                   help="Fourier harmonics of the motion models (default "
                        + " ".join(str(v) for v in dataclasses.astuple(DEFAULT_HARMONICS)) + "; the paper's: 5 4 2 1)")


def _add_registration_options(p) -> None:
    """The flags of :class:`registration.RegistrationOptions` (register and pipeline)."""
    from registration.options import ESTIMATORS, RegistrationOptions

    defaults = RegistrationOptions()
    p.add_argument("--step", type=_finite, default=None,
                   help=f"phase step of the sweeps (default {defaults.phase_step})")
    _add_harmonics_option(p)
    p.add_argument("--estimator", default=defaults.estimator, choices=list(ESTIMATORS),
                   help="how phi_R* is chosen: chest and heart shape with a 90%% interval (default), "
                        "or the paper's eq. 10")
    p.add_argument("--breath-hold-phase", type=_finite, default=None, metavar="PHASE",
                   help=f"the CT's breath-hold respiration phase if known (sd {defaults.breath_hold_sd}), "
                        "used by --estimator shape")
    p.add_argument("--no-slice-phases", action="store_true",
                   help="predict every point at the model's phi_C* (as the paper), not at the cardiac phase "
                        "of the CT slices it lies on")
    p.add_argument("--icp-max-iterations", type=int, default=None, metavar="N",
                   help="most ICP steps per phase (default 50); ICP stops before on a step below 0.001 mm "
                   "and 0.001 deg or a loss that falls by less than 1e-4, and says where the limit stopped it")
    p.add_argument("--no-view", action="store_true", help="skip the 3-D view (fig8_view.png)")


def _add_study_options(p, study_help: str = "folder holding the DICOM study (searched recursively)") -> None:
    p.add_argument("study_dir", type=_path, help=study_help)
    p.add_argument("--qrs", type=_path, default=None,
                   help="R-peak times, CSV with column time_s (seconds after midnight, AcquisitionTime clock)")
    p.add_argument("--series", type=_series_arg, default=None,
                   help="series to use: index from --list-series or SeriesInstanceUID (default: automatic)")
    p.add_argument("--list-series", action="store_true", help="list the series found and exit")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def _build_parser() -> argparse.ArgumentParser:
    from heartreg.phantom.config import PRESETS, SIZES

    parser = argparse.ArgumentParser(
        prog="heartreg",
        description="Beating-heart registration for organ-mounted robots (Wood et al. 2018).",
    )
    parser.add_argument("--version", action="version", version=f"heartreg {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("phantom", help="write a synthetic beating-heart case (CT, session, truth)")
    p.add_argument("out_dir", type=_path, help="output folder")
    p.add_argument("--preset", default="default", choices=sorted(PRESETS), help="phantom settings")
    p.add_argument("--size", default="sample", choices=sorted(SIZES), help="CT grid size")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same bytes)")
    p.add_argument("--points", type=int, default=None, help="number of robot attachment points")
    p.add_argument("--resp-phase", type=_finite, default=None, metavar="PHASE",
                   help="respiration phase of the CT breath-hold (default the preset's, 0.3)")
    p.add_argument("--chest-wall-mm", type=_finite, default=None, metavar="MM",
                   help="sternal excursion over a breath (default the preset's; 0: a still chest)")
    p.add_argument("--no-session", action="store_true", help="write the CT study only")
    p.add_argument("--plus", nargs="?", const=True, default=False, type=_tracker_rate_arg, metavar="HZ",
                   help="also write the session with its poses in a PLUS sequence file (session_plus/): a frame per "
                        "sample, or the tracker at its own rate of HZ (20-100), its frames jittered")
    p.add_argument("--navigation", action="store_true",
                   help="also a 60 s navigation session (the robot crawling) and its truth, for heartreg track")
    p.add_argument("--anatomy", default=None, choices=("spheroid", "chambers"),
                   help="heart: the paper's spheroid or four chambers with great vessels (default: the preset's)")
    p.add_argument("--fov-mm", type=_finite, default=None, help="tight CT field of view centred on the heart (mm)")
    p.add_argument("--no-markers", action="store_true", help="no skin staples (needs --no-session)")
    p.add_argument("--stent", action="store_true", help="a metal stent in the descending aorta")
    p.add_argument("--overwrite", action="store_true", help="replace existing phantom outputs")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_phantom)

    p = sub.add_parser("phases", help="cardiac phase of every CT slice (paper Fig. 4)")
    _add_study_options(p)
    p.add_argument("-o", "--out-dir", type=_path, default=None, help="folder for phases.csv/json/png")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier phases output in OUT_DIR (a folder holding phases.json)")
    p.set_defaults(func=_cmd_phases)

    p = sub.add_parser("model", help="CT study (DICOM folder, NIfTI or NRRD file) -> heart model in the heart-centric "
                                     "frame")
    _add_study_options(p, "folder holding the DICOM study (searched recursively), or a NIfTI (.nii, .nii.gz) or "
                          "NRRD (.nrrd) CT volume")
    p.add_argument("-o", "--out-dir", type=_path, default=None, help="model folder to write")
    _add_model_options(p)
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing model folder (one holding model.json)")
    p.set_defaults(func=_cmd_model)

    p = sub.add_parser("pipeline", help="study + session -> phases, model, registration, report.html")
    _add_study_options(p)
    p.add_argument("session_dir", type=_path, help="intra-operative session folder (docs/formats.md)")
    p.add_argument("-o", "--out-dir", type=_path, default=None, help="output folder")
    _add_model_options(p)
    _add_registration_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace the outputs of an earlier run in OUT_DIR")
    p.set_defaults(func=_cmd_pipeline)

    p = sub.add_parser("demo", help="the whole chain on the bundled sample, recovered vs truth",
                       description="The whole chain (phases, model, registration, report) on the bundled sample or "
                                   "a phantom case, each result against the case's truth. Exits 1 when a row is "
                                   "outside its tolerance.")
    p.add_argument("-o", "--out-dir", type=_path, default=Path("demo_out"), help="output folder (default demo_out)")
    p.add_argument("--sample", type=_path, default=None,
                   help="phantom case to use instead of sample_dicom/ (heartreg phantom's folder): its own session/, "
                        "or without one the session the phantom writes from its truth.json's settings and seed")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("register", help="register a session to a heart model in space and phase")
    p.add_argument("model_dir", type=_path, help="heart model folder (heartreg model)")
    p.add_argument("session_dir", type=_path, help="session folder (heartreg-session)")
    p.add_argument("-o", "--out-dir", type=_path, required=True, help="folder for registration.json, CSVs, PNGs")
    _add_registration_options(p)
    p.add_argument("--cardiac-phase", type=_finite, default=None, metavar="P",
                   help="the CT's cardiac phase (0..1), needed when the model's is unknown; replaces it otherwise")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier registration in OUT_DIR (a folder holding registration.json)")
    p.set_defaults(func=_cmd_register)

    p = sub.add_parser("track", help="the robot on the map, live: causal phases, CSV log, OpenIGTLink to Slicer")
    p.add_argument("model_dir", type=_path, help="heart model folder (heartreg model)")
    p.add_argument("registration_dir", type=_path, help="registration folder (heartreg register)")
    p.add_argument("session_dir", type=_path,
                   help="the session the registration was made from (its records give the motion models)")
    p.add_argument("--replay", type=_path, default=None,
                   help="session folder to replay as the pose stream (default SESSION_DIR)")
    p.add_argument("--igtl-in", default=None, metavar="HOST:PORT",
                   help="take the stream from an OpenIGTLink server instead (docs/formats.md)")
    p.add_argument("--idle-timeout", type=_finite, default=5.0, help="--igtl-in: end after this many idle seconds (default %(default)g)")
    p.add_argument("--speed", type=_finite, default=None,
                   help="replay pacing: 1 = real time, 2 = twice as fast (default: as fast as possible)")
    p.add_argument("--log", type=_path, required=True,
                   help="CSV log to write (one row per sample), outside the input folders")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --log")
    p.add_argument("--igtl-port", type=_port, default=None,
                   help="serve OpenIGTLink to Slicer on this port (18944 is Slicer's default; 0: any free; "
                        "default: no server, nothing sent)")
    p.add_argument("--igtl-rate", type=_finite, default=100.0,
                   help="most samples per second sent over OpenIGTLink (default %(default)g; 0: all)")
    p.add_argument("--wait-client", type=_finite, default=0.0,
                   help="seconds to wait for an OpenIGTLink client before the stream starts (default %(default)g)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("evaluate-temporal",
                       help="phi_R* and final T of both estimators on a grid of phantom cases vs truth")
    p.add_argument("-o", "--out-dir", type=_path, required=True, help="output folder (cases resume from OUT/cases)")
    p.add_argument("--seeds", type=_count, default=6, help="seeds 1..N per preset (default 6)")
    p.add_argument("--trials", type=int, nargs="+", default=None, metavar="N", choices=range(1, 7),
                   help="presets wood2018-trialN to run, N in 1..6 (default all six)")
    p.add_argument("--size", default="sample", choices=sorted(SIZES), help="phantom CT grid (default sample)")
    _add_harmonics_option(p)
    p.add_argument("--report-only", action="store_true", help="summarize the cases already run; run nothing")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    _add_cluster_options(p, local_help="0: one by one in this process")
    p.set_defaults(func=_cmd_evaluate_temporal)

    p = sub.add_parser("reproduce", help="the paper's experiment on the six phantom presets, beside its numbers")
    p.add_argument("-o", "--out-dir", type=_path, required=True, help="output folder (phantom cases reused)")
    p.add_argument("--size", default="full", choices=sorted(SIZES), help="phantom CT grid (default full)")
    p.add_argument("--seed", type=int, default=0, help="phantom seed of every trial")
    p.add_argument("--trials", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6], metavar="N",
                   help="trials of Table 1 to run (default all six)")
    p.add_argument("--points", type=int, default=None, help="attachment points per session instead of Table 1's")
    p.add_argument("--step", type=_finite, default=0.01, help="phase step of the sweeps (default 0.01)")
    p.add_argument("--report-only", action="store_true",
                   help="re-draw the tables, figures and page from an earlier run in OUT_DIR; run nothing")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    _add_cluster_options(p)
    p.set_defaults(func=_cmd_reproduce)

    p = sub.add_parser("batch", help="a cohort of studies (CSV or folder) through phases, model, register on Dask")
    p.add_argument("cohort", type=_path, help="cohort CSV (columns case, study, session, mask, options) or a folder "
                   "of study folders")
    p.add_argument("-o", "--out-dir", type=_path, required=True, help="output folder: one folder per case, "
                   "summary.csv, index.html; run again into it, a case whose inputs, options and heartreg version "
                   "are unchanged is skipped")
    _add_cluster_options(p)
    p.add_argument("--num-parts", type=int, default=1, help="split the cohort into this many parts (array jobs)")
    p.add_argument("--part-id", type=int, default=0, help="the part to run, 0 .. NUM_PARTS-1")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_batch)
    return parser
