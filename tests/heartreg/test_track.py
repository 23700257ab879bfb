"""``heartreg track`` on a phantom navigation session, against the phantom's truth.

The case is the shared sample-size phantom (trial 1, 30 points); its model is
built from its CT by the real chain (phases, segmentation, mesh, frame) and
registered without the cardiac sweep (not used by track).  The robot then
crawls for 60 s to places between the registration points
(:mod:`heartreg.phantom.navigation`); the truth is its surface point at the
image phases, in the CT patient frame, compared in the model's heart frame.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np
import pytest

from heartreg.cli import main
from heartreg.igtl import (
    DEVICE_PROBE,
    DEVICE_ROBOT,
    DEVICE_SIGNALS,
    IgtlError,
    IgtlSink,
    igtl_client_chunks,
    lossless_client,
    unpack_polydata,
)
from heartreg.phantom.layout import make_heart
from heartreg.phantom.navigation import NavigationTruth, write_navigation
from heartreg.track import (
    T_RAS_FROM_LPS,
    TRACK_COLUMNS,
    RateLimiter,
    Tracker,
    chunks_from_samples,
    load_tracker,
    run_track,
    session_chunks,
)
from registration.online import CausalPhases
from registration.point_models import point_phases
from registration.session import read_session


@pytest.fixture(scope="module")
def nav(sample_case, sample_outputs, tmp_path_factory):
    from modeling.model import read_model
    from registration.pipeline import register_session
    from registration.report import write_registration

    case_dir, truth = sample_case
    root = tmp_path_factory.mktemp("track")
    model_dir = sample_outputs / "model"  # ``heartreg model`` of the sample CT (default options)
    model = read_model(model_dir)
    session = read_session(case_dir / "session")
    result = register_session(model, session, cardiac_sweep=False)
    write_registration(result, root / "registration", view=False)
    write_navigation(case_dir, out_dir=root)
    log = root / "track.csv"
    status = main(["track", str(model_dir), str(root / "registration"), str(case_dir / "session"),
                   "--replay", str(root / "navigation"), "--log", str(log), "-q"])
    assert status == 0
    with open(log, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return dict(root=root, model_dir=model_dir, case=case_dir, truth=truth, model=model, rows=rows,
                nav_truth=NavigationTruth.read(root, case_dir))


@pytest.fixture(scope="module")
def loaded(nav):
    """The tracker parts (motion models re-fitted once); ``fresh()`` gives a new tracker."""
    tracker, _, rate = load_tracker(nav["model_dir"], nav["root"] / "registration", nav["case"] / "session")
    return lambda: Tracker(tracker.localiser, rate, **tracker._priors)


def _column(rows, *names):
    return np.array([[float(r[n]) for n in names] for r in rows])


def test_navigation_session_is_true_and_goes_between_the_registered_points(nav):
    truth, nt = nav["truth"], nav["nav_truth"]
    record = read_session(nav["root"] / "navigation").points[0]
    assert record.n_samples == nt.time_s.size and np.array_equal(np.round(record.time_s, 3), nt.time_s)
    # the written poses are the analytic surface at the true phases, through T*,
    # up to the tracker noise (0.2 mm per axis on each of two sensors: ~0.5 mm 3-D)
    from heartreg.phantom.config import make_config

    heart = make_heart(make_config(truth["preset"]))
    T_star = np.asarray(truth["T_patient_from_probe"])
    robot = record.T_probe_from_robot[:, :3, 3] @ T_star[:3, :3].T + T_star[:3, 3]
    clean = heart.surface_points(nt.u, nt.v, nt.phase_c, nt.phase_r)
    assert np.sqrt(np.mean(np.sum((robot - clean) ** 2, axis=1))) < 0.6
    # it crawls (metres of path would be wrong, millimetres of standing still too)
    on_map = nt.map_patient_mm
    assert 60.0 < np.linalg.norm(np.diff(on_map, axis=0), axis=1).sum() < 400.0
    # mostly where the registration had no point: median > 5 mm from the nearest
    assert np.median(nt.nearest_registered_mm) > 5.0


def test_map_position_error_against_truth(nav):
    rows, model, nt = nav["rows"], nav["model"], nav["nav_truth"]
    assert [*rows[0].keys()] == list(TRACK_COLUMNS)
    T = model.T_heart_from_patient
    truth_heart = nt.map_patient_mm @ T[:3, :3].T + T[:3, 3]
    pos = _column(rows, "map_x_mm", "map_y_mm", "map_z_mm")
    static = _column(rows, "static_x_mm", "static_y_mm", "static_z_mm")
    placed = np.isfinite(pos[:, 0])
    quality = np.array([r["quality"] for r in rows])
    # the phases need one R-peak (after a 2 s learning window) and one start of
    # expiration (after one breath, ~5 s): the first ~8 s of 60 have no place
    assert placed.mean() > 0.8
    assert np.all(quality[~placed] == "no_phase")
    err = np.linalg.norm(pos[placed] - truth_heart[placed], axis=1)
    err_static = np.linalg.norm(static[placed] - truth_heart[placed], axis=1)
    # Done-when of issue 13: mean <= 2 mm, p95 <= 4 mm (measured 1.3 / 2.8 mm, 1.7 / 3.1 mm before the map
    # moved onto the CT's edge: the
    # registration's ~0.8 mm, the motion interpolation between points ~14 mm
    # apart, and causal phases that cannot know the current beat's length)
    assert err.mean() <= 2.0 and np.percentile(err, 95) <= 4.0
    # T z without the motion correction (paper section 1) is far worse
    assert err_static.mean() > 2.0 * err.mean()
    # the robot is on the surface: nearest-surface distance within a few mm
    dist = _column(rows, "distance_mm")[placed, 0]
    assert np.median(np.abs(dist)) < 1.5


def test_causal_cardiac_phase_lags_the_offline_one_by_the_detection_delay(nav, loaded):
    rows = nav["rows"]
    record = read_session(nav["root"] / "navigation").points[0]
    offline, _, peaks, _ = point_phases(record)
    live = _column(rows, "cardiac_phase")[:, 0]
    both = np.isfinite(live) & np.isfinite(offline)
    d = np.mod(live[both] - offline[both] + 0.5, 1.0) - 0.5
    # most of each beat agrees closely (only the RR estimate differs); the beat
    # is known ~0.1 s late, and an ectopic beat (6 % of beats, each followed by
    # a compensatory pause: 11 % of this record's RR intervals) cannot be
    # foreseen: measured median 0.013 cycles, 83 % of samples within 0.1
    assert np.median(np.abs(d)) < 0.03
    assert np.mean(np.abs(d) < 0.1) > 0.75
    # the same R-peaks as the offline detector, within 2 ms
    tracker = loaded()
    cp = CausalPhases(tracker.rate_hz, rr_prior_s=tracker._priors["rr_prior_s"])
    out = cp.update(record.time_s, record.ecg_mv, record.flow_insp_lpm, record.flow_exp_lpm)
    live_r = np.array([r for r, _ in out.r_peaks])
    latency = np.array([c - r for r, c in out.r_peaks])
    near = np.min(np.abs(live_r[:, None] - peaks[None]), axis=1)
    assert np.all(near < 0.002)
    assert np.all(latency <= 0.13)  # confirm_s = 0.1 after the QRS onset crossing


def test_phases_do_not_depend_on_the_chunking(nav):
    record = read_session(nav["root"] / "navigation").points[0]
    n = 1500
    args = (record.time_s[:n], record.ecg_mv[:n], record.flow_insp_lpm[:n], record.flow_exp_lpm[:n])
    whole = CausalPhases(100.0, rr_prior_s=0.9, breath_prior_s=5.0).update(*args)
    for size in (7, 1):  # 1: a live stream's sample at a time
        cp = CausalPhases(100.0, rr_prior_s=0.9, breath_prior_s=5.0)
        parts = [cp.update(*(a[i:i + size] for a in args)) for i in range(0, n, size)]
        for name in ("cardiac_phase", "respiration_phase", "flags"):
            np.testing.assert_array_equal(np.concatenate([getattr(p, name) for p in parts]), getattr(whole, name))
        assert sum((p.r_peaks for p in parts), ()) == whole.r_peaks


def test_openigtlink_stream_matches_the_log(nav, loaded, tmp_path):
    root, model = nav["root"], nav["model"]
    tracker = loaded()
    replay = read_session(root / "navigation")
    mesh = model.mesh
    T_ras = T_RAS_FROM_LPS @ model.T_patient_from_heart
    import signal

    ctrl_c = signal.getsignal(signal.SIGINT)
    sink = IgtlSink(0, mesh.vertices @ T_ras[:3, :3].T + T_ras[:3, 3], mesh.faces)  # ephemeral port
    assert signal.getsignal(signal.SIGINT) is ctrl_c  # pyigtl's server does not take Ctrl-C away
    client, received = lossless_client("127.0.0.1", sink.port)
    try:
        assert sink.wait_for_client(10.0)
        chunks = [c for i, c in zip(range(1), session_chunks(replay, chunk=1500))]  # the first 15 s
        summary = run_track(tracker, chunks, tmp_path / "log.csv", model=model, sink=sink, igtl_rate_hz=None)
        deadline = time.monotonic() + 10.0  # bounded wait for the last messages
        while time.monotonic() < deadline and sum(m.message_type == "TRANSFORM" for m in list(received)) < summary.n_sent:
            time.sleep(0.01)
    finally:
        client.stop()
        sink.close()
    msgs = list(received)
    polys = [m for m in msgs if m.message_type == "POLYDATA"]
    assert len(polys) == 1 and summary.models_sent == 1
    points, faces = unpack_polydata(polys[0].content)
    # the model in Slicer's RAS scene: float32 coordinates of ~100 mm (1e-5 mm steps)
    np.testing.assert_allclose(points, mesh.vertices @ T_ras[:3, :3].T + T_ras[:3, 3], atol=1e-4)
    np.testing.assert_array_equal(faces, mesh.faces)
    with open(tmp_path / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    sent = {round(float(r["time_s"]), 3): r for r in rows if r["sent"] == "1"}
    assert summary.n_sent == len(sent) > 400  # 15 s at 100 Hz, the first ~8 s without phases
    transforms = {round(m.timestamp, 3): m for m in msgs if m.message_type == "TRANSFORM"}
    assert len(transforms) >= 0.99 * len(sent)
    status = {round(m.timestamp, 3): m for m in msgs if m.message_type == "STRING"}
    for t, m in transforms.items():
        r = sent[t]
        lps = np.linalg.inv(T_RAS_FROM_LPS) @ m.matrix
        heart = model.T_heart_from_patient @ lps
        # float32 matrices: ~1e-5 relative; the log has 4 decimals
        np.testing.assert_allclose(heart[:3, 3], [float(r["map_x_mm"]), float(r["map_y_mm"]), float(r["map_z_mm"])],
                                   atol=2e-3)
        assert f'"quality":"{r["quality"]}"' in status[t].string


def _serve_stream(rec, n, run, *, bad=None, poses=None):
    """A pyigtl server sending the record's first ``n`` samples as a PLUS-like stream (``bad``: sample index ->
    (time, Signals text) replacing that sample's; ``poses``: sample index -> (RobotToTracker, ProbeToTracker)
    replacing its poses); ``run(port)`` consumes it.  Returns what ``run`` returns."""
    import pyigtl

    bad, poses = bad or {}, poses or {}

    def messages():
        for i in range(n):
            t, text = bad.get(i, (float(rec.time_s[i]), _signals_text(rec, i)))
            robot, probe = poses.get(i, (rec.T_probe_from_robot[i], np.eye(4)))
            yield pyigtl.TransformMessage(robot, timestamp=t, device_name=DEVICE_ROBOT)
            yield pyigtl.TransformMessage(probe, timestamp=t, device_name=DEVICE_PROBE)
            yield pyigtl.StringMessage(text, timestamp=t, device_name=DEVICE_SIGNALS)

    return _serve_messages(messages(), run)


def _signals_text(rec, i: int) -> str:
    return f"{float(rec.ecg_mv[i])!r},{float(rec.flow_insp_lpm[i])!r},{float(rec.flow_exp_lpm[i])!r}"


def _serve_messages(messages, run):
    """A pyigtl server sending ``messages`` (pyigtl messages, in order) to the first client; ``run(port)``
    consumes them.  Returns what ``run`` returns."""
    import signal
    import threading

    import pyigtl

    server = pyigtl.OpenIGTLinkServer(port=0, local_server=True)
    for s in (signal.SIGINT, signal.SIGTERM):  # pyigtl's handlers: give Ctrl-C back to pytest
        signal.signal(s, signal.default_int_handler if s == signal.SIGINT else signal.SIG_DFL)

    def send():
        while not server.is_connected():
            time.sleep(0.005)
        for k, message in enumerate(messages):
            server.send_message(message, wait=k % 75 == 74)  # keep pyigtl's 100-message queue from overflowing

    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    try:
        return run(server.server_address[1])
    finally:
        thread.join(timeout=10)
        server.stop()


def test_openigtlink_input_gives_the_replay_results(nav, loaded, tmp_path):
    root = nav["root"]
    tracker = loaded()
    rec = read_session(root / "navigation").points[0]
    n = 900
    summary = _serve_stream(rec, n, lambda port: run_track(
        tracker, igtl_client_chunks("127.0.0.1", port, idle_timeout_s=3.0), tmp_path / "in.csv"))
    assert summary.n_samples == n
    ref = loaded()
    rows_ref = run_track(ref, session_chunks(read_session(root / "navigation"), chunk=n), tmp_path / "ref.csv")
    assert rows_ref.n_samples == 6000
    with open(tmp_path / "in.csv", newline="") as fh:
        got = list(csv.DictReader(fh))
    with open(tmp_path / "ref.csv", newline="") as fh:
        want = list(csv.DictReader(fh))[:n]
    assert [r["cardiac_phase"] for r in got] == [r["cardiac_phase"] for r in want]
    a = _column(got, "map_x_mm", "map_y_mm", "map_z_mm")
    b = _column(want, "map_x_mm", "map_y_mm", "map_z_mm")
    np.testing.assert_allclose(a, b, atol=2e-3, equal_nan=True)  # poses went as float32


def test_bad_live_samples_are_skipped_not_fatal(nav, loaded, tmp_path):
    """A sample with a NaN or a missing signal, or a timestamp going back, is skipped and counted: the live run
    goes on and keeps its log (before session 16 each ended the run with exit 1 or a traceback, and the log of
    every sample before it was lost)."""
    rec = read_session(nav["root"] / "navigation").points[0]
    t = rec.time_s
    bad = {100: (float(t[100]), "nan,1.0,2.0"), 150: (float(t[150]), "0.1,2.0"), 200: (float(t[190]), "0.1,1.0,2.0")}
    skipped = {}
    summary = _serve_stream(rec, 300, lambda port: run_track(
        loaded(), igtl_client_chunks("127.0.0.1", port, idle_timeout_s=2.0, skipped=skipped), tmp_path / "bad.csv"),
        bad=bad)
    assert summary.n_samples == 297
    assert sum(skipped.values()) == 3 and skipped["timestamp not later than the sample before"] == 1, skipped
    with open(tmp_path / "bad.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 297
    # a server that is not there is said, not taken for an empty stream
    with pytest.raises(IgtlError, match="no connection within 0.5 s"):
        list(igtl_client_chunks("127.0.0.1", _free_port(), idle_timeout_s=0.5))


def test_a_pose_that_is_no_rigid_transform_is_not_placed(nav, loaded, tmp_path, capsys):
    """A pose over OpenIGTLink with a NaN or an infinity, a scaled rotation or a reflection (det -1) was
    logged 'ok' and placed (the NaN one at NaN, the scaled one at a plausible place), and a reflection ended the
    run with scipy's traceback and no log (a user's audit).  Now each is a sample whose sensor was not seen:
    quality 'tracker', not placed, counted in the summary; the phases go on (its ECG and airflow are fine)."""
    rec = read_session(nav["root"] / "navigation").points[0]
    T = rec.T_probe_from_robot
    nan, inf, scaled, mirrored, probe_nan = T[1000].copy(), T[1010].copy(), T[1020].copy(), T[1030].copy(), np.eye(4)
    nan[0, 0], inf[1, 3], probe_nan[2, 3] = np.nan, np.inf, np.nan
    scaled[:3, :3] *= 1.5
    mirrored[:3, 0] *= -1.0
    poses = {1000: (nan, np.eye(4)), 1010: (inf, np.eye(4)), 1020: (scaled, np.eye(4)), 1030: (mirrored, np.eye(4)),
             1040: (T[1040], probe_nan)}
    log = tmp_path / "live.csv"
    args = [str(nav["model_dir"]), str(nav["root"] / "registration"), str(nav["case"] / "session"), "-q",
            "--idle-timeout", "2", "--log", str(log)]
    status = _serve_stream(rec, 1200, lambda port: main(["track", *args, "--igtl-in", f"127.0.0.1:{port}"]),
                           poses=poses)
    out = capsys.readouterr().out
    assert status == 0
    assert "  invalid poses     5 sample(s): a pose not a rigid transform (NaN or inf" in out
    with open(log, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 1200
    for i in poses:
        assert rows[i]["quality"] == "tracker" and rows[i]["map_x_mm"] == "nan" and rows[i]["sent"] == "0", rows[i]
        assert rows[i]["cardiac_phase"] != "nan"  # the signals of the sample were used
    assert sum(r["quality"] == "tracker" for r in rows) == 5
    assert all(r["map_x_mm"] != "nan" for i, r in enumerate(rows) if i >= 1000 and i not in poses
               and r["quality"] in ("ok", "predicted"))
    # a last row that is not 0 0 0 1 (OpenIGTLink cannot carry one: a PLUS reader or another source can)
    tracker = loaded()
    s = (rec.time_s[0], T[0], np.eye(4), True, rec.ecg_mv[0], rec.flow_insp_lpm[0], rec.flow_exp_lpm[0])
    skewed = T[1].copy()
    skewed[3] = [0.0, 0.0, 0.1, 1.0]
    s2 = (rec.time_s[1], skewed, np.eye(4), True, rec.ecg_mv[1], rec.flow_insp_lpm[1], rec.flow_exp_lpm[1])
    rows = tracker.process(next(chunks_from_samples([s, s2], chunk=2)))
    assert list(rows.pose_ok) == [True, False] and rows.quality[1] == "tracker"


def test_a_run_that_placed_nothing_exits_1_and_keeps_its_log(nav, tmp_path, capsys):
    """A run that placed no sample exited 0 as if fine: every pose invalid, no pose at all (every sample
    skipped), a server that sent nothing (a user's audit; the last exited 1 but lost the log).  Now each is
    exit 1 and one line saying why, and the log is written (it is the run's record)."""
    rec = read_session(nav["root"] / "navigation").points[0]
    args = [str(nav["model_dir"]), str(nav["root"] / "registration"), str(nav["case"] / "session"), "-q",
            "--idle-timeout", "1"]

    def run(log, n, **kw):
        return _serve_stream(rec, n, lambda port: (port, main(["track", *args, "--log", str(tmp_path / log),
                                                                "--igtl-in", f"127.0.0.1:{port}"])), **kw)

    def errors(err):  # but the warning on the fixture's registration ('caution', test_an_untrusted_registration...)
        return [line for line in err.strip().splitlines() if not line.startswith("warning: registration ")]

    nan = rec.T_probe_from_robot[0].copy()
    nan[0, 3] = np.nan
    port, status = run("invalid.csv", 300, poses={i: (nan, np.eye(4)) for i in range(300)})
    lines = errors(capsys.readouterr().err)
    assert status == 1 and lines == [
        f"heartreg track: error: nothing was placed on the map: all 300 poses from --igtl-in 127.0.0.1:{port} were "
        "invalid (no rigid transform); check the tracker's RobotToTracker and ProbeToTracker transforms; the log "
        f"{tmp_path / 'invalid.csv'} was written"], lines
    with open(tmp_path / "invalid.csv", newline="") as fh:
        assert [r["quality"] for r in csv.DictReader(fh)] == ["tracker"] * 300

    port, status = run("none.csv", 50, bad={i: (float(rec.time_s[i]), "x") for i in range(50)})
    captured = capsys.readouterr()
    assert status == 1 and errors(captured.err) == [
        f"heartreg track: error: nothing was placed on the map: no pose arrived from --igtl-in 127.0.0.1:{port} "
        f"before it went quiet for --idle-timeout 1 s; 50 sample(s) were skipped, see above; the log "
        f"{tmp_path / 'none.csv'} was written"]
    assert "skipped           50 sample(s) from --igtl-in: Signals not three finite numbers" in captured.out
    assert (tmp_path / "none.csv").read_text().splitlines() == [",".join(TRACK_COLUMNS)]

    port, status = run("silent.csv", 0)
    lines = errors(capsys.readouterr().err)
    assert status == 1 and len(lines) == 1 and lines[0].startswith(
        f"heartreg track: error: nothing was placed on the map: --igtl-in 127.0.0.1:{port}: connected but sent "
        "nothing within 1 s"), lines
    assert lines[0].endswith(f"(the log {tmp_path / 'silent.csv'} was written: the 0 sample(s) before it)")
    assert (tmp_path / "silent.csv").read_text().splitlines() == [",".join(TRACK_COLUMNS)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["invalid.csv", "none.csv", "silent.csv"]


def test_an_untrusted_registration_is_said_once_and_logged(nav, tmp_path, capsys):
    """registration.json's trust verdict ('caution' or 'poor', e.g. 'the data cannot decide phi_R*') was
    ignored: track placed the robot on it without a word (a user's audit).  Now one warning line on stderr before
    the stream, and every log row carries it (registration_trust); a trusted one says nothing."""
    import json
    import shutil

    reg = tmp_path / "registration"
    shutil.copytree(nav["root"] / "registration", reg)
    doc = json.loads((reg / "registration.json").read_text())
    cases = {
        "caution": (doc["trust"], "caution:phase_undecided", "is trusted 'caution (phase_undecided)': the data cannot "
                    "decide phi_R*"),
        "poor": ({"level": "poor", "reasons": [
            {"code": "phase_undecided", "level": "caution", "message": "phi_R* undecided"},
            {"code": "icp_degenerate", "level": "poor", "message": "the final ICP can slide along the surface"}]},
            "poor:phase_undecided+icp_degenerate",
            "is trusted 'poor (phase_undecided, icp_degenerate)': the final ICP can slide along the surface; every "
            "place on the map rests on it"),
        "ok": ({"level": "ok", "reasons": []}, "ok", None),
    }
    assert doc["trust"]["reasons"][0]["code"] == "phase_undecided"  # the fixture's own registration
    for name, (trust, cell, said) in cases.items():
        doc["trust"] = trust
        (reg / "registration.json").write_text(json.dumps(doc))
        log = tmp_path / f"{name}.csv"
        assert main(["track", str(nav["model_dir"]), str(reg), str(nav["case"] / "session"), "-q",
                     "--replay", str(nav["root"] / "navigation"), "--log", str(log)]) == 0
        err = capsys.readouterr().err.strip().splitlines()
        if said is None:
            assert err == [], err
        else:
            assert len(err) == 1 and err[0].startswith(f"warning: registration {reg} {said}"), err
        with open(log, newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert len(rows) == 6000 and {r["registration_trust"] for r in rows} == {cell}


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_replay_sampled_at_its_own_rate(nav, tmp_path):
    """A replay recorded at 50 Hz while the registration's session was at 100 Hz: the causal phases follow the
    replay's rate (they took the session's before session 16: 79 % of the cardiac phases > 0.1 cycle off)."""
    import json
    import shutil

    replay = tmp_path / "nav50"
    shutil.copytree(nav["root"] / "navigation", replay)
    meta = json.loads((replay / "session.json").read_text())
    meta["sample_rate_hz"] = 50.0
    (replay / "session.json").write_text(json.dumps(meta))
    for f in (replay / "points").glob("*.csv"):
        lines = f.read_text().splitlines()
        f.write_text("\n".join(lines[:1] + lines[1::2]) + "\n")
    log = tmp_path / "track50.csv"
    assert main(["track", str(nav["model_dir"]), str(nav["root"] / "registration"), str(nav["case"] / "session"),
                 "--replay", str(replay), "--log", str(log), "-q"]) == 0
    with open(log, newline="") as fh:
        rows = list(csv.DictReader(fh))
    nt, T = nav["nav_truth"], nav["model"].T_heart_from_patient
    at = np.searchsorted(np.round(nt.time_s, 3), np.round(_column(rows, "time_s")[:, 0], 3))
    truth_heart = nt.map_patient_mm[at] @ T[:3, :3].T + T[:3, 3]
    pos = _column(rows, "map_x_mm", "map_y_mm", "map_z_mm")
    placed = np.isfinite(pos[:, 0])
    err = np.linalg.norm(pos[placed] - truth_heart[placed], axis=1)
    assert placed.mean() > 0.8 and err.mean() <= 2.0 and np.percentile(err, 95) <= 4.0, (err.mean(), placed.mean())


def test_rate_limiter_and_ctrl_c(nav, loaded, tmp_path):
    clock = iter(np.arange(0.0, 1.0, 0.001))  # 1 kHz of events for 1 s
    limiter = RateLimiter(100.0, clock=lambda: next(clock))
    passed = sum(limiter.allow() for _ in range(1000))
    assert passed == 100 and limiter.dropped == 900

    # pacing: a replay at 10x real time never runs ahead of the stream's clock
    import itertools

    paced = itertools.islice(session_chunks(read_session(nav["root"] / "navigation"), chunk=1), 200)
    summary = run_track(loaded(), paced, tmp_path / "paced.csv", speed=10.0)
    assert summary.n_samples == 200 and summary.wall_s >= 199 * 0.01 / 10.0
    (tmp_path / "paced.csv").unlink()

    tracker = loaded()

    def interrupted():
        for i, chunk in enumerate(session_chunks(read_session(nav["root"] / "navigation"), chunk=500)):
            if i == 3:
                raise KeyboardInterrupt
            yield chunk

    summary = run_track(tracker, interrupted(), tmp_path / "cut.csv")
    assert summary.interrupted and summary.n_samples == 1500
    with open(tmp_path / "cut.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 1500
    assert [p.name for p in tmp_path.iterdir()] == ["cut.csv"]  # no temporary file left


def test_a_full_disk_names_the_log(nav, loaded, tmp_path, monkeypatch):
    """A write to the open log has no file name: the error said 'a file: No space left on device'."""
    import errno

    import heartreg.track as track

    def full(*_):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(track, "_csv_lines", full)
    chunks = session_chunks(read_session(nav["root"] / "navigation"), chunk=500)
    with pytest.raises(track.TrackError, match=r"^--log .*full.csv: No space left on device; free disk space"):
        run_track(loaded(), chunks, tmp_path / "full.csv")
    assert list(tmp_path.iterdir()) == []


def test_missing_folders_above_the_log_are_made_and_removed_with_a_refused_run(nav, loaded, tmp_path, capsys,
                                                                             monkeypatch):
    """A --log below missing folders: they are made, as for every -o; a run refused before its log was written
    (a busy --igtl-port, a full disk) left them behind, empty (a user's audit).  Now they go with it."""
    import errno
    import socket

    import heartreg.track as track

    args = [str(nav["model_dir"]), str(nav["root"] / "registration"), str(nav["case"] / "session"), "-q",
            "--replay", str(nav["root"] / "navigation")]
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["track", *args, "--log", str(tmp_path / "new" / "a" / "log.csv"), "--igtl-port", str(port)]) == 1
    assert f"--igtl-port {port}: cannot listen" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []

    def full(*_):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(track, "_csv_lines", full)
        with pytest.raises(track.TrackError, match="No space left on device"):
            run_track(loaded(), session_chunks(read_session(nav["root"] / "navigation"), chunk=500),
                      tmp_path / "new" / "b" / "log.csv")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "new").mkdir()  # a folder that was there stays, the ones made go

    def refused(**_):
        raise PermissionError(errno.EACCES, "Permission denied")

    with monkeypatch.context() as m:
        m.setattr(track.tempfile, "mkstemp", refused)
        with pytest.raises(track.TrackError, match="cannot write there"):
            run_track(loaded(), session_chunks(read_session(nav["root"] / "navigation"), chunk=500),
                      tmp_path / "new" / "c" / "d" / "log.csv")
    assert [p.relative_to(tmp_path) for p in tmp_path.rglob("*")] == [Path("new")]
    # a run that writes its log keeps the folders made for it
    assert main(["track", *args, "--log", str(tmp_path / "new" / "e" / "log.csv")]) == 0
    assert (tmp_path / "new" / "e" / "log.csv").is_file()


def test_bad_inputs_say_what_is_wrong(nav, tmp_path, capsys):
    root = nav["root"]
    (tmp_path / "empty").mkdir()
    status = main(["track", str(nav["model_dir"]), str(tmp_path / "empty"), str(nav["case"] / "session"),
                   "--log", str(tmp_path / "x.csv")])
    assert status == 1
    assert "registration.json not found" in capsys.readouterr().err
    inputs = [str(nav["model_dir"]), str(root / "registration"), str(nav["case"] / "session")]
    # the log never overwrites an input (before session 16 it replaced registration.json, a session record, ...)
    before = (root / "registration" / "registration.json").read_bytes()
    assert main(["track", *inputs, "--log", str(root / "registration" / "registration.json")]) == 1
    assert f"lies inside the input {root / 'registration'}" in capsys.readouterr().err
    assert (root / "registration" / "registration.json").read_bytes() == before
    # nor an earlier log, unless --overwrite
    (tmp_path / "old.csv").write_text("an earlier run\n")
    assert main(["track", *inputs, "--log", str(tmp_path / "old.csv")]) == 1
    assert "old.csv exists; choose another name or pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "old.csv").read_text() == "an earlier run\n"
    for extra, said in ((["--igtl-in", "127.0.0.1:1", "--replay", str(root / "navigation")], "give one"),
                        (["--igtl-rate", "-5"], "--igtl-rate must be 0")):
        assert main(["track", *inputs, "--log", str(tmp_path / "y.csv"), *extra]) == 1
        assert said in capsys.readouterr().err
    (tmp_path / "afile").write_text("x")  # a log below a file: one line, not a bare "File exists"
    assert main(["track", *inputs, "--log", str(tmp_path / "afile" / "x.csv")]) == 1
    assert f"{tmp_path / 'afile'} is a file, not a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["track", *inputs, "--log", str(tmp_path / "y.csv"), "--igtl-port", "70000"])
    assert "70000 is not a TCP port" in capsys.readouterr().err
    # a registration made with another model (the same mesh moved 3 mm) is refused
    import dataclasses

    from modeling.mesh import Mesh
    from modeling.model import write_model

    model = nav["model"]
    moved = dataclasses.replace(model, mesh=Mesh(model.mesh.vertices + [3.0, 0.0, 0.0], model.mesh.faces))
    write_model(moved, tmp_path / "other_model")
    assert main(["track", str(tmp_path / "other_model"), *inputs[1:], "--log", str(tmp_path / "y.csv")]) == 1
    assert "was not made with the model" in capsys.readouterr().err
    assert not (tmp_path / "y.csv").exists()
    status = main(["track", str(nav["model_dir"]), str(root / "registration"), str(root / "navigation"),
                   "--log", str(tmp_path / "x.csv")])
    assert status == 1
    assert "give the session the registration was made from" in capsys.readouterr().err
    with pytest.raises(ValueError, match="sample times must increase"):
        CausalPhases(100.0).update([1.0, 1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0])
    assert not (tmp_path / "x.csv").exists()
    from heartreg.phantom import PhantomError

    with pytest.raises(PhantomError, match="no readable truth.json"):
        write_navigation(tmp_path)
    with pytest.raises(PhantomError, match="speed_mm_s must be positive"):
        write_navigation(nav["case"], out_dir=tmp_path, speed_mm_s=0.0)


def test_the_log_replaces_only_a_regular_file(nav, loaded, tmp_path, capsys):
    """``--log X --overwrite`` replaced whatever X was: a symbolic link, a named pipe, a device node (as root:
    /dev/null) became the log (a user's audit).  Now each is one line and left as it was; the check is
    :func:`hrcore.output.check_output_file`, run again just before the log's rename."""
    import os

    from hrcore.output import OutputError

    inputs = [str(nav["model_dir"]), str(nav["root"] / "registration"), str(nav["case"] / "session"),
              "--replay", str(nav["root"] / "navigation"), "-q", "--overwrite"]
    (tmp_path / "target.txt").write_text("theirs")
    (tmp_path / "link.csv").symlink_to(tmp_path / "target.txt")
    os.mkfifo(tmp_path / "fifo.csv")
    said = {"link.csv": "is a symbolic link, which is never followed nor replaced",
            "fifo.csv": "is a named pipe, not a regular file"}
    if os.geteuid() == 0:
        import stat

        os.mknod(tmp_path / "dev.csv", 0o644 | stat.S_IFCHR, os.makedev(1, 3))
        said["dev.csv"] = "is a character device, not a regular file"
    for name, words in said.items():
        before = os.lstat(tmp_path / name)
        assert main(["track", *inputs, "--log", str(tmp_path / name)]) == 1
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"heartreg track: error: --log {tmp_path / name} {words}"), lines
        after = os.lstat(tmp_path / name)
        assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino), name
    assert (tmp_path / "target.txt").read_text() == "theirs"

    # a link put there while the stream runs is not replaced at the end either (the run is refused, nothing left)
    def chunks():
        for i, chunk in enumerate(session_chunks(read_session(nav["root"] / "navigation"), chunk=500)):
            if i == 1:
                (tmp_path / "late.csv").symlink_to(tmp_path / "target.txt")
            yield chunk

    with pytest.raises(OutputError, match=r"^--log .*late.csv is a symbolic link"):
        run_track(loaded(), chunks(), tmp_path / "late.csv")
    assert (tmp_path / "late.csv").is_symlink() and (tmp_path / "target.txt").read_text() == "theirs"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["target.txt", "late.csv", *said])


def test_navigation_of_a_case_with_its_own_anatomy(nav, tmp_path):
    """A case made with ``--fov-mm 200 --stent`` (its truth.json holds the anatomy) gets its navigation:
    before session 18 ``heartreg phantom --fov-mm 200 --stent --navigation`` ended in a traceback (the
    navigation rebuilt the case's configuration by hand and left the anatomy a dict).  The field of view and
    the stent do not move the heart: the same samples as the case without them."""
    import json

    truth = json.loads((nav["case"] / "truth.json").read_text())
    truth["config"]["anatomy"] = {"heart": "spheroid", "fov_mm": 200.0, "markers": True, "stent": True}
    (tmp_path / "truth.json").write_text(json.dumps(truth))
    write_navigation(tmp_path)
    written = [p.relative_to(nav["root"]) for p in sorted((nav["root"] / "navigation").rglob("*")) if p.is_file()]
    assert written
    for name in [Path("navigation_truth.csv"), *written]:
        assert (tmp_path / name).read_bytes() == (nav["root"] / name).read_bytes(), name


def test_a_client_that_connects_while_another_is_served_gets_the_model(capfd):
    """pyigtl serves one client at a time; the next one's handler starts the moment the last one's ends, too
    soon for ``connected`` to change between two polls: before session 16 the second client never got the
    heart model (Slicer showed the robot on no heart)."""
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    sink = IgtlSink(0, vertices, faces)
    first, got_first = lossless_client("127.0.0.1", sink.port)
    second = None
    try:
        end = time.monotonic() + 5
        while not any(m.message_type == "POLYDATA" for m in list(got_first)) and time.monotonic() < end:
            sink.poll()
            time.sleep(0.01)
        # the second connects once the first is served (each client connects from its own thread: made together,
        # either may come first)
        second, got = lossless_client("127.0.0.1", sink.port)
        time.sleep(0.3)
        first.stop()
        end = time.monotonic() + 10
        while time.monotonic() < end and not any(m.message_type == "POLYDATA" for m in list(got)):
            if sink.poll():  # the stream goes on: a send finds the first client gone
                sink.send(time.monotonic(), np.eye(4), "{}")
            time.sleep(0.01)
        assert any(m.message_type == "POLYDATA" for m in list(got)) and sink.models_sent == 2
    finally:
        if second is not None:
            second.stop()
        first.stop()
        sink.close()
    assert "Traceback" not in capfd.readouterr().err  # the first client left quietly (pyigtl printed two)


def test_slicer_learns_the_port_under_quiet_and_the_trust_with_every_place(nav, tmp_path):
    """Two gaps on Slicer's side (a robotics user's audit): with ``-q`` the 'OpenIGTLink server on port N' line was
    not printed, so ``--igtl-port 0 -q`` served on a port nobody could learn; and ``RobotStatus`` carried no word
    of the registration's trust (the fixture's is 'caution'), which only the log and stderr said.  Now the port
    line is printed with ``-q`` too, and every ``RobotStatus`` carries ``registration_trust`` as the log does."""
    import json
    import os
    import re
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    cmd = [sys.executable, "-m", "heartreg", "track", str(nav["model_dir"]), str(nav["root"] / "registration"),
           str(nav["case"] / "session"), "-q", "--replay", str(nav["root"] / "navigation"), "--igtl-port", "0",
           "--wait-client", "10", "--speed", "20", "--log", str(tmp_path / "log.csv")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=root)
    client = None
    try:
        line = proc.stdout.readline()  # the first line: the run waits for a client (--wait-client), bounded
        m = re.fullmatch(r"OpenIGTLink server on port (\d+)\n", line)
        assert m, f"no 'OpenIGTLink server on port N' line with -q: {line!r}"
        client, received = lossless_client("127.0.0.1", int(m.group(1)))
        assert proc.wait(timeout=60) == 0
    finally:
        if client is not None:
            client.stop()
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()
    texts = [json.loads(m.string) for m in list(received) if m.message_type == "STRING"]
    assert len(texts) > 100 and {t["registration_trust"] for t in texts} == {"caution:phase_undecided"}


def _tracker_stream(rec, n, rate_hz, *, seed=0):
    """The record's first ``n`` samples as a tracker at its own rate beside 100 Hz signals, on one clock, as a
    PlusServer streams them: frames are the rows nearest to times ``1 / rate_hz`` apart, jittered by up to a
    fifth of a step (as :func:`heartreg.phantom.plus.write_plus_session` picks them; the first and last rows are
    frames), the probe moving (the robot sent as ``probe @ T_probe_from_robot``).  Returns (messages in time
    order, the frames' rows)."""
    import pyigtl
    from scipy.spatial.transform import Rotation

    t = rec.time_s[:n]
    step = 1.0 / rate_hz
    nominal = np.arange(t[0], t[-1], step)[1:]
    nominal = nominal + np.random.default_rng(seed).uniform(-0.2, 0.2, nominal.size) * step
    rows = np.unique(np.concatenate([[0], np.abs(t[None, :] - nominal[:, None]).argmin(axis=1), [n - 1]]))
    frames = set(rows.tolist())
    messages = []
    for i in range(n):
        ti = float(t[i])
        messages.append(pyigtl.StringMessage(_signals_text(rec, i), timestamp=ti, device_name=DEVICE_SIGNALS))
        if i in frames:
            probe = np.eye(4)
            probe[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.2 * np.sin(ti)]).as_matrix()
            probe[:3, 3] = [100.0 + 5.0 * np.sin(7.5 * ti), -50.0, 20.0 * np.cos(ti)]
            messages.append(pyigtl.TransformMessage(probe @ rec.T_probe_from_robot[i], timestamp=ti,
                                                    device_name=DEVICE_ROBOT))
            messages.append(pyigtl.TransformMessage(probe, timestamp=ti, device_name=DEVICE_PROBE))
    return messages, rows


def test_a_tracker_at_its_own_rate_is_interpolated_to_the_signals(nav, loaded, tmp_path):
    """A PlusServer streams the tracker's frames at its own rate (40 Hz, jittered) and the ECG and airflow at
    theirs (100 Hz) on the same clock: a sample needed a frame with its very timestamp, so every other sample
    was dropped unsaid (here 60 %, the frames' times being rows' times; with a real tracker's timestamps, all of
    them: nothing placed).  Now each takes the pose interpolated between the frames around it (waiting for the
    frame after it) and lands where the replay of the 100 Hz session puts it."""
    root = nav["root"]
    rec = read_session(root / "navigation").points[0]
    n = 1300
    messages, rows = _tracker_stream(rec, n, 40.0)
    skipped: dict = {}
    summary = _serve_messages(messages, lambda port: run_track(
        loaded(), igtl_client_chunks("127.0.0.1", port, idle_timeout_s=1.5, skipped=skipped), tmp_path / "in.csv"))
    run_track(loaded(), session_chunks(read_session(root / "navigation"), chunk=n), tmp_path / "ref.csv")
    with open(tmp_path / "in.csv", newline="") as fh:
        got = list(csv.DictReader(fh))
    with open(tmp_path / "ref.csv", newline="") as fh:
        want = list(csv.DictReader(fh))[:n]
    assert summary.n_samples == n and not skipped, skipped  # every sample lies between two frames
    assert [r["cardiac_phase"] for r in got] == [r["cardiac_phase"] for r in want]  # the same signals
    a = _column(got, "map_x_mm", "map_y_mm", "map_z_mm")
    b = _column(want, "map_x_mm", "map_y_mm", "map_z_mm")
    placed = np.isfinite(b[:, 0])
    np.testing.assert_array_equal(np.isfinite(a[:, 0]), placed)
    assert summary.n_placed == placed.sum() > 300
    at_frame = np.isin(np.arange(n), rows)
    d = np.linalg.norm(a - b, axis=1)
    # at a frame the pose is the one sent (float32: measured 1e-4 mm); between frames the interpolated pose
    # differs from the 100 Hz row by the tracker's noise (0.2 mm, 0.15 deg per tool and sample) and the motion's
    # curvature over 25 ms: measured mean 0.71 mm, max 1.9 mm; against the truth the interpolated places are
    # no worse (measured mean 0.75 mm, p95 1.16 mm; the replay's 0.80 / 1.28 mm: the noise averaged)
    assert d[placed & at_frame].max() <= 2e-3
    assert d[placed & ~at_frame].mean() <= 1.0 and d[placed & ~at_frame].max() <= 3.0
    T = nav["model"].T_heart_from_patient
    truth = (nav["nav_truth"].map_patient_mm @ T[:3, :3].T + T[:3, 3])[:n][placed]
    err, err_ref = (np.linalg.norm(x[placed] - truth, axis=1) for x in (a, b))
    assert err.mean() <= err_ref.mean() + 0.2 and np.percentile(err, 95) <= np.percentile(err_ref, 95) + 0.3
