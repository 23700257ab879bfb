"""``heartreg track``: the robot on the map, live, streamed to 3D Slicer.

From a heart model, a registration and the session it was made from (whose
records give the registered points' motion models), consume a pose stream
with its ECG and airflow and, for every sample, say where the robot is on the
static map (:mod:`registration.online` for the causal phases,
:mod:`registration.localise` for the mapping).  Outputs:

- a CSV log, one row per sample (``docs/formats.md``, *Track log*), written
  under a temporary name and renamed when the stream ends or is interrupted;
- over OpenIGTLink (:mod:`heartreg.igtl`, a pyigtl server Slicer's OpenIGTLinkIF connects to):
  the model once per connection as ``POLYDATA`` ``HeartModel``, then per
  sample a ``TRANSFORM`` ``RobotToRAS`` and a ``STRING`` ``RobotStatus``
  (phases, quality), in Slicer's RAS scene (the CT's patient frame, LPS
  turned to RAS), rate-limited: samples beyond ``igtl_rate_hz`` are dropped
  from the stream quietly (counted, and marked in the log's ``sent`` column).

Pose sources are iterables of :class:`StreamChunk` (arrays of samples):
:func:`session_chunks` replays a session folder; a PLUS sequence reader or an
OpenIGTLink receiver plugs in the same way (:func:`chunks_from_samples`
groups ``(time, T_tracker_from_robot, T_tracker_from_probe, status, ecg,
flow_insp, flow_exp)`` samples; :func:`heartreg.igtl.igtl_client_chunks` is one).
"""

from __future__ import annotations

import errno
import math
import os
import tempfile
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from heartreg.igtl import IgtlSink, RateLimiter
from heartreg.track_log import TRACK_COLUMNS, TrackSummary
from heartreg.track_log import csv_lines as _csv_lines
from heartreg.track_log import status_text as _status_text
from heartreg.track_log import trust_cell
from hrcore.errors import HeartregError
from hrcore.folders import make_folders, remove_folders
from hrcore.geometry import apply_to_points, is_rigid
from hrcore.output import check_output_file
from imaging.files import umask_mode
from registration.localise import FAR_MM, Localiser, registered_models
from registration.motion_model import Harmonics
from registration.online import CausalPhases, PhaseFlag
from registration.plus import RIGID_TOL as POSE_TOL

__all__ = [
    "TRACK_COLUMNS",
    "T_RAS_FROM_LPS",
    "RateLimiter",
    "StreamChunk",
    "TrackError",
    "TrackSummary",
    "Tracker",
    "chunks_from_samples",
    "load_tracker",
    "run_track",
    "session_chunks",
]

#: LPS -> RAS (a rotation by 180 degrees about z: no change of handedness).
T_RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
#: |distance| to the surface (mm) above which a sample is flagged off_surface.
OFF_SURFACE_MM = 5.0
#: a gap between samples longer than this many sample intervals restarts the phases.
GAP_SAMPLES = 10


class TrackError(HeartregError, ValueError):
    """Inputs of ``heartreg track`` that cannot be used (named in the message)."""


@dataclass(frozen=True, eq=False)
class StreamChunk:
    """A run of stream samples.

    Attributes
    ----------
    time_s : (m,) float64, s
    T_tracker_from_robot, T_tracker_from_probe : (m, 4, 4) float64, mm
    ecg_mv, flow_insp_lpm, flow_exp_lpm : (m,) float64, mV and L/min
    status : (m,) bool
        The tracker saw both sensors (PLUS ``TransformStatus`` OK).
    """

    time_s: np.ndarray
    T_tracker_from_robot: np.ndarray
    T_tracker_from_probe: np.ndarray
    ecg_mv: np.ndarray
    flow_insp_lpm: np.ndarray
    flow_exp_lpm: np.ndarray
    status: np.ndarray

    def __len__(self) -> int:
        return int(self.time_s.shape[0])


def session_chunks(session, *, chunk: int = 1000) -> Iterator[StreamChunk]:
    """Replay a session's records in order, ``chunk`` samples at a time.

    The session reader keeps ``T_probe_from_robot``; it is given as
    ``T_tracker_from_robot`` with an identity probe, which is the same pose
    relative to the probe.
    """
    for record in session.points:
        n = record.n_samples
        for lo in range(0, n, chunk):
            sl = slice(lo, min(n, lo + chunk))
            m = sl.stop - sl.start
            yield StreamChunk(
                time_s=record.time_s[sl], T_tracker_from_robot=record.T_probe_from_robot[sl],
                T_tracker_from_probe=np.broadcast_to(np.eye(4), (m, 4, 4)),
                ecg_mv=record.ecg_mv[sl], flow_insp_lpm=record.flow_insp_lpm[sl],
                flow_exp_lpm=record.flow_exp_lpm[sl], status=np.ones(m, dtype=bool),
            )


def chunks_from_samples(samples: Iterable, *, chunk: int = 1) -> Iterator[StreamChunk]:
    """Group samples ``(time_s, T_tracker_from_robot, T_tracker_from_probe, status,
    ecg_mv, flow_insp_lpm, flow_exp_lpm)`` (e.g. from a PLUS sequence or an
    OpenIGTLink receiver) into chunks of ``chunk``."""
    buf: list = []
    for s in samples:
        buf.append(s)
        if len(buf) >= chunk:
            yield _stack(buf)
            buf = []
    if buf:
        yield _stack(buf)


def _stack(buf) -> StreamChunk:
    t, Tr, Tp, st, ecg, fi, fe = zip(*buf)
    return StreamChunk(np.array(t, float), np.array(Tr, float), np.array(Tp, float), np.array(ecg, float),
                       np.array(fi, float), np.array(fe, float), np.array(st, bool))


@dataclass(frozen=True, eq=False)
class TrackRows:
    """The outputs of a chunk (see :data:`TRACK_COLUMNS`)."""

    time_s: np.ndarray
    cardiac_phase: np.ndarray
    respiration_phase: np.ndarray
    quality: tuple
    flags: np.ndarray
    T_heart_from_robot: np.ndarray
    surface_mm: np.ndarray
    distance_mm: np.ndarray
    nearest_point_mm: np.ndarray
    static_mm: np.ndarray
    #: (m,) bool: both poses were finite rigid transforms (else the sample's quality is ``tracker``, unplaced)
    pose_ok: np.ndarray


def _quality(flags: int, distance: float, nearest: float, status: bool) -> str:
    if not status:
        return "tracker"
    if flags & (PhaseFlag.NO_CARDIAC | PhaseFlag.NO_RESPIRATION):
        return "no_phase"
    if abs(distance) > OFF_SURFACE_MM:
        return "off_surface"
    if nearest > FAR_MM:
        return "far"
    if flags & (PhaseFlag.CARDIAC_PREDICTED | PhaseFlag.RESPIRATION_PREDICTED):
        return "predicted"
    return "ok"


class Tracker:
    """Causal phases + localisation of a stream (no I/O).

    Parameters
    ----------
    localiser : Localiser
    rate_hz : float, Hz
        The stream's sample rate.
    rr_prior_s, breath_prior_s : float, s, optional
        Periods assumed before two events are seen.
    trust : registration.plausibility.Trust, optional
        The registration's verdict (``registration.json``), written in every log row.
    """

    def __init__(self, localiser: Localiser, rate_hz: float, *, rr_prior_s=None, breath_prior_s=None, trust=None):
        self.localiser = localiser
        self.trust = trust
        self.rate_hz = float(rate_hz)
        self._priors = dict(rr_prior_s=rr_prior_s, breath_prior_s=breath_prior_s)
        self.phases = CausalPhases(self.rate_hz, **self._priors)
        self._last_t = -np.inf
        self.r_peaks: list[tuple[float, float]] = []
        self.onsets: list[tuple[float, float]] = []

    def at_rate(self, rate_hz: float) -> "Tracker":
        """The same tracker for a stream sampled at ``rate_hz`` (its causal filters are built for its rate)."""
        return Tracker(self.localiser, rate_hz, trust=self.trust, **self._priors)

    def process(self, chunk: StreamChunk) -> TrackRows:
        """Phases and map positions of every sample of ``chunk``."""
        t = chunk.time_s
        if len(chunk) and t[0] - self._last_t > GAP_SAMPLES / self.rate_hz and np.isfinite(self._last_t):
            self.phases = CausalPhases(self.rate_hz, **self._priors)  # a gap: the signals restart
        if len(chunk):
            self._last_t = float(t[-1])
        ph = self.phases.update(t, chunk.ecg_mv, chunk.flow_insp_lpm, chunk.flow_exp_lpm)
        self.r_peaks.extend(ph.r_peaks)
        self.onsets.extend(ph.onsets)
        Tp = chunk.T_tracker_from_probe
        # a pose that is no rigid transform (NaN, a scaled or reflected rotation, a last row not 0 0 0 1) is a
        # sensor not seen: it was placed and logged 'ok' (a reflection ended the run with a traceback)
        pose_ok = _rigid_poses(chunk.T_tracker_from_robot, Tp)
        status = chunk.status & pose_ok
        Rt = np.swapaxes(Tp[:, :3, :3], 1, 2)
        T_probe_from_robot = np.zeros_like(chunk.T_tracker_from_robot)
        T_probe_from_robot[:, :3, :3] = Rt @ chunk.T_tracker_from_robot[:, :3, :3]
        T_probe_from_robot[:, :3, 3] = np.einsum("mij,mj->mi", Rt, chunk.T_tracker_from_robot[:, :3, 3] - Tp[:, :3, 3])
        T_probe_from_robot[:, 3, 3] = 1.0
        T_probe_from_robot[~pose_ok] = np.nan
        pc = np.where(status, ph.cardiac_phase, np.nan)
        mp = self.localiser.locate(T_probe_from_robot, pc, ph.respiration_phase)
        quality = tuple(
            _quality(int(f), float(d), float(nn), bool(s))
            for f, d, nn, s in zip(ph.flags, mp.distance_mm, mp.nearest_point_mm, status)
        )
        return TrackRows(t, ph.cardiac_phase, ph.respiration_phase, quality, ph.flags, mp.T_heart_from_robot,
                         mp.surface_mm, mp.distance_mm, mp.nearest_point_mm, mp.static_mm, pose_ok)


def _rigid_poses(Tr: np.ndarray, Tp: np.ndarray) -> np.ndarray:
    """(m,) bool: both poses of a sample are finite rigid transforms (:func:`hrcore.geometry.is_rigid`, within
    :data:`POSE_TOL`); a live sample (m = 1) in plain floats, as :func:`is_rigid`'s set-up took 0.06 ms of it."""
    if Tr.shape[0] != 1:
        return is_rigid(Tr, tol=POSE_TOL) & is_rigid(Tp, tol=POSE_TOL)
    for T in (Tr[0].tolist(), Tp[0].tolist()):
        if not all(math.isfinite(x) for row in T for x in row):
            return np.zeros(1, bool)
        (a, b, c, _), (d, e, f, _), (g, h, k, _), last = T
        cols = ((a, d, g), (b, e, h), (c, f, k))
        for i in range(3):
            for j in range(i, 3):
                if abs(sum(x * y for x, y in zip(cols[i], cols[j])) - (i == j)) > POSE_TOL:
                    return np.zeros(1, bool)
        det = a * (e * k - f * h) - b * (d * k - f * g) + c * (d * h - e * g)
        if abs(det - 1.0) > POSE_TOL or max(abs(x - y) for x, y in zip(last, (0.0, 0.0, 0.0, 1.0))) > POSE_TOL:
            return np.zeros(1, bool)
    return np.ones(1, bool)


def load_tracker(model_dir, registration_dir, session_dir):
    """(Tracker, HeartModel, sample rate) for a model, a registration and its session.

    The registered points' motion models are fitted again from the session and
    checked against the registration's fit residuals, so a session other than
    the registration's is refused.
    """
    from modeling.model import read_model
    from registration.icp import SurfaceIndex
    from registration.report import read_registration
    from registration.session import read_session

    model = read_model(model_dir)
    reg = read_registration(registration_dir)
    surface = SurfaceIndex(model.mesh.vertices, model.mesh.faces)
    _check_same_model(model, surface, reg, model_dir, registration_dir)
    session = read_session(session_dir)
    ids = [int(i) for i in reg.point_ids]
    parameters = reg.parameters
    try:
        harmonics = Harmonics(**parameters["harmonics"])
    except (KeyError, TypeError) as exc:
        raise TrackError(f"{Path(registration_dir) / 'registration.json'}: parameters.harmonics missing or bad "
                         f"({exc}); re-run heartreg register") from None
    models = registered_models(session, ids, harmonics=harmonics,
                               coverage_bins=int(parameters.get("coverage_bins", 10)))
    fits = {f.point_id: f for f in reg.point_fits}
    for pid, m in zip(ids, models):
        want = fits[pid].residual_rms_3d_mm
        if not np.isclose(m.residual_rms_3d_mm, want, rtol=1e-6, atol=1e-9):
            raise TrackError(
                f"{session_dir}: point {pid} fits with residual {m.residual_rms_3d_mm:.6f} mm, the "
                f"registration's was {want:.6f} mm: give the session the registration was made from"
            )
    localiser = Localiser(models, reg.T_heart_from_probe, reg.cardiac_phase, reg.respiration_phase, surface)
    rr = 1.0 / float(np.mean([f.heart_rate_hz for f in reg.point_fits]))
    br = 1.0 / float(np.mean([f.resp_rate_hz for f in reg.point_fits]))
    tracker = Tracker(localiser, session.sample_rate_hz, rr_prior_s=rr, breath_prior_s=br, trust=reg.trust)
    return tracker, model, session.sample_rate_hz


def _check_same_model(model, surface, reg, model_dir, registration_dir) -> None:
    """Refuse a registration made to another model: its points, placed by its transform, must lie on this
    model's surface (its ``SurfaceIndex``) as they lay on the registration's (the same RMS distance; another
    heart puts them mm off)."""
    from registration.closest import closest_points

    why = None
    if model.mesh.n_faces != reg.n_faces:
        why = f"it was registered to a mesh of {reg.n_faces} faces, the model has {model.mesh.n_faces}"
    else:
        d = closest_points(surface, apply_to_points(reg.T_heart_from_probe, reg.points_probe_mm)).distances_mm
        rms = float(np.sqrt(np.mean(d**2)))
        if not np.isclose(rms, reg.rms_mm, rtol=1e-3, atol=1e-3):
            why = f"its points lie {rms:.3f} mm (RMS) from this model's surface, {reg.rms_mm:.3f} mm from its own"
    if why:
        raise TrackError(f"{registration_dir} was not made with the model {model_dir}: {why}; "
                         "give the model the session was registered to")


def run_track(
    tracker: Tracker,
    chunks: Iterable[StreamChunk],
    csv_path,
    *,
    model=None,
    speed: float | None = None,
    igtl_port: int | None = None,
    igtl_rate_hz: float | None = 100.0,
    wait_client_s: float = 0.0,
    sink: IgtlSink | None = None,
    progress=None,
    listening=None,
) -> TrackSummary:
    """Run a stream through the tracker to the CSV log and OpenIGTLink.

    Parameters
    ----------
    tracker : Tracker
    chunks : iterable of StreamChunk
    csv_path : path
        The log; written as ``.name-XXXX`` beside it and renamed at the end
        (also after Ctrl-C: the log then holds every sample processed).
    model : HeartModel, optional
        Needed for OpenIGTLink (the POLYDATA).
    speed : float, optional
        Replay pacing: 1.0 real time (each sample processed at its time), 2.0
        twice as fast, None as fast as possible.
    igtl_port : int, optional
        Serve OpenIGTLink on this port (0: a free one); None: no streaming.
    igtl_rate_hz : float, optional
        Most samples per second sent (None: all).
    wait_client_s : float, s
        Wait this long for a client before the stream starts.
    sink : IgtlSink, optional
        An open sink to use instead of ``igtl_port`` (left open).
    progress : callable, optional
        Called with each :class:`TrackRows` (e.g. a progress bar).
    listening : callable, optional
        Called with the port once the OpenIGTLink server listens (``igtl_port`` 0 picks a free one).

    Returns
    -------
    TrackSummary
    """
    csv_path = Path(csv_path)
    check_output_file(csv_path, what="--log")  # a link, a FIFO, a device is never replaced
    if csv_path.is_dir():
        raise TrackError(f"--log {csv_path} is a folder; give a file name")
    own_sink = False
    if sink is None and igtl_port is not None:
        if model is None:
            raise TrackError("OpenIGTLink needs the model (its POLYDATA)")
        mesh = model.mesh
        vertices_ras = apply_to_points(T_RAS_FROM_LPS @ model.T_patient_from_heart, mesh.vertices)
        sink = IgtlSink(igtl_port, vertices_ras, mesh.faces)
        own_sink = True
        if listening is not None:
            listening(sink.port)
    T_ras_from_heart = None if model is None else T_RAS_FROM_LPS @ model.T_patient_from_heart
    if sink is not None and T_ras_from_heart is None:
        raise TrackError("OpenIGTLink needs the model (its frame)")
    limiter = RateLimiter(igtl_rate_hz)
    made: list[Path] = []  # missing folders above the log, made now and removed unless it is written (as for -o)
    try:
        made = make_folders(Path(os.path.abspath(csv_path)).parent)
        fd, tmp = tempfile.mkstemp(prefix=f".{csv_path.stem}-", suffix=".csv", dir=csv_path.parent)
    except OSError as exc:
        remove_folders(made)
        if own_sink:
            sink.close()
        raise TrackError(f"--log {csv_path}: cannot write there ({exc.strerror or exc}); give a writable place") from None
    n = placed = sent_total = invalid = 0
    interrupted_by = None
    qualities: dict[str, int] = {}
    source_error: list = []
    trust = trust_cell(tracker.trust)  # every row's registration_trust
    t_wall0 = time.perf_counter()
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            fh.write(",".join(TRACK_COLUMNS) + "\n")
            if sink is not None and wait_client_s > 0:
                sink.wait_for_client(wait_client_s)
            t_stream0 = None
            try:
                for chunk in _until_error(chunks, source_error):
                    if speed is not None and len(chunk):
                        if t_stream0 is None:
                            t_stream0, t_real0 = float(chunk.time_s[0]), time.monotonic()
                        rows_list = []
                        for k in range(len(chunk)):  # each sample at its own time
                            due = t_real0 + (float(chunk.time_s[k]) - t_stream0) / speed
                            delay = due - time.monotonic()
                            if delay > 0:
                                time.sleep(delay)
                            one = StreamChunk(*(getattr(chunk, f)[k:k + 1] for f in StreamChunk.__dataclass_fields__))
                            rows_list.append(_emit(tracker.process(one), sink, limiter, T_ras_from_heart, trust))
                    else:
                        rows_list = [_emit(tracker.process(chunk), sink, limiter, T_ras_from_heart, trust)]
                    for rows, sent in rows_list:
                        fh.write(_csv_lines(rows, sent, trust))
                        n += len(rows.time_s)
                        placed += int(np.count_nonzero(np.isfinite(rows.T_heart_from_robot[:, 0, 3])))
                        sent_total += int(sent.sum())
                        invalid += int(np.count_nonzero(~rows.pose_ok))
                        for q in rows.quality:
                            qualities[q] = qualities.get(q, 0) + 1
                        if progress is not None:
                            progress(rows)
            except KeyboardInterrupt as exc:
                interrupted_by = type(exc)
        if sink is not None:
            sink.flush()
        os.chmod(tmp, umask_mode())
        check_output_file(csv_path, what="--log")  # again: one may have been put there meanwhile
        os.replace(tmp, csv_path)
    except OSError as exc:  # a write to the open log (a disk's error, not the OpenIGTLink socket's): name it
        if exc.filename is None and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO):
            raise TrackError(f"--log {csv_path}: {exc.strerror}; free disk space or give a log on another disk") from None
        raise
    finally:
        if os.path.exists(tmp):  # not renamed: no log, and no folder made for it
            os.unlink(tmp)
            remove_folders(made)
        if own_sink:
            sink.close()
    if source_error:  # after the rename: the log is a record of the run
        raise TrackError(f"{'nothing was placed on the map: ' if not placed else ''}{source_error[0]} (the log "
                         f"{csv_path} was written: the {n} sample(s) before it)") from None
    lat = np.array([c - r for r, c in tracker.r_peaks]) * 1000.0
    return TrackSummary(
        n_samples=n, n_placed=placed, n_sent=sent_total, n_dropped=limiter.dropped,
        models_sent=0 if sink is None else sink.models_sent, wall_s=time.perf_counter() - t_wall0,
        r_peak_latency_ms=(float(lat.mean()), float(lat.max())) if lat.size else (float("nan"),) * 2,
        interrupted=interrupted_by is not None, interrupted_by=interrupted_by, n_invalid_pose=invalid,
        qualities=qualities,
    )


def _until_error(chunks, errors: list):
    """The chunks of a source until it fails with a refusal (a server that never answered, a bad file), kept in
    ``errors``: the log keeps the samples before it."""
    try:
        yield from chunks
    except HeartregError as exc:
        errors.append(exc)


def _emit(rows: TrackRows, sink, limiter, T_ras_from_heart, trust: str = "unknown"):
    m = len(rows.time_s)
    sent = np.zeros(m, dtype=bool)
    if sink is None or not sink.poll():
        return rows, sent
    for i in range(m):
        if np.isnan(rows.T_heart_from_robot[i, 0, 3]) or not limiter.allow():
            continue
        sink.send(float(rows.time_s[i]), T_ras_from_heart @ rows.T_heart_from_robot[i],
                  _status_text(rows, i, trust))
        sent[i] = True
    return rows, sent
