"""PLUS sequence files (tracking only): the phantom's writer against the reader,
invalid poses, the clock match with the signals' CSV, and bad files.

The registration through a PLUS session is checked against the CSV session in
``test_slicer.py`` (same bytes of registration.json).
"""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from heartreg.phantom.plus import write_plus_sequence
from registration.plus import PlusFileError, read_plus_sequence
from registration.session import SessionError, read_session


def _poses(rng, n):
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-300, 300, (n, 3))
    return T


@pytest.mark.parametrize("name", ["rec.seq.mha", "rec.igs.nrrd"])
def test_sequence_round_trip_with_invalid_poses(tmp_path, name):
    rng = np.random.default_rng(3)
    n = 50
    time_s = 36000.0 + np.arange(n) / 100.0
    robot, probe = _poses(rng, n), _poses(rng, n)
    seen = np.ones(n, bool)
    seen[[4, 17, 18]] = False
    path = write_plus_sequence(tmp_path / name, time_s, {"RobotToTracker": robot, "ProbeToTracker": probe},
                               valid={"RobotToTracker": seen})
    seq = read_plus_sequence(path)
    np.testing.assert_array_equal(seq.time_s, time_s)
    # repr-written floats read back to the same bits
    np.testing.assert_array_equal(seq.transform("RobotToTracker")[seen], robot[seen])
    np.testing.assert_array_equal(seq.transform("ProbeToTracker"), probe)
    np.testing.assert_array_equal(seq.valid["RobotToTracker"], seen)
    assert np.isnan(seq.transform("RobotToTracker")[~seen]).all()
    with pytest.raises(PlusFileError, match="has no transform 'StylusToTracker'"):
        seq.transform("StylusToTracker")
    # a MetaImage / NRRD reader (ITK's) opens the file as the 1 x 1 x n image PLUS writes
    sitk = pytest.importorskip("SimpleITK")
    assert np.prod(sitk.ReadImage(str(path)).GetSize()) * sitk.ReadImage(str(path)).GetNumberOfComponentsPerPixel() == n


def _plus_session(tmp_path, n=1500, rate=100.0, invalid=(), shift_s=0.0, signals=None):
    """A small PLUS session: one point of n samples, robot fixed in the probe frame; ``signals(t)``
    gives its ECG and flows (default: constant)."""
    rng = np.random.default_rng(5)
    folder = tmp_path / "plus"
    (folder / "points").mkdir(parents=True)
    time_s = np.round(30000.0 + np.arange(n) / rate, 3)
    probe = _poses(rng, n)
    T_probe_from_robot = _poses(rng, 1)[0]
    robot = probe @ T_probe_from_robot
    seen = np.ones(n, bool)
    seen[list(invalid)] = False
    write_plus_sequence(folder / "track.igs.nrrd", time_s + shift_s, {"RobotToTracker": robot, "ProbeToTracker": probe},
                        valid={"ProbeToTracker": seen})
    cols = signals(time_s - time_s[0]) if signals else (np.full(n, 0.1), np.ones(n), np.zeros(n))
    _write_signals_and_meta(folder, time_s, cols, rate)
    return folder, T_probe_from_robot, time_s


def _write_signals_and_meta(folder, time_s, cols, rate, **meta_extra):
    """The point's signals CSV ``(ecg, flow_insp, flow_exp)`` at ``time_s``, the fiducials and session.json
    naming ``track.igs.nrrd`` as the point's poses."""
    rows = ["time_s,ecg_mv,flow_insp_lpm,flow_exp_lpm"] + [
        f"{t:.3f},{e:.4f},{i:.3f},{x:.3f}" for t, e, i, x in zip(time_s, *cols)]
    (folder / "points" / "p0.csv").write_text("\n".join(rows) + "\n")
    (folder / "fiducials.csv").write_text("fiducial,x_mm,y_mm,z_mm\n" + "".join(
        f"{k},{k}.0,{2 * k}.0,{k * k}.0\n" for k in range(1, 10)))
    meta = {
        "format": "heartreg-session", "version": 1,
        "units": {"position": "mm", "time": "s", "ecg": "mV", "flow": "L/min"},
        "quaternion_order": "wxyz", "frames": {"poses": "tracker"}, "sample_rate_hz": rate,
        "points": [{"id": 0, "file": "points/p0.csv", "poses": "track.igs.nrrd", "surface_point": 7}],
        "fiducials_file": "fiducials.csv",
        "fiducial_order": "rows superior to inferior, within a row patient right to left", **meta_extra,
    }
    (folder / "session.json").write_text(json.dumps(meta))


def test_session_poses_from_plus_drop_invalid_samples(tmp_path):
    folder, T_true, time_s = _plus_session(tmp_path, invalid=(10, 11, 500))
    session = read_session(folder)
    rec = session.points[0]
    assert rec.n_samples == len(time_s) - 3 and rec.surface_point == 7
    np.testing.assert_array_equal(rec.time_s, np.delete(time_s, [10, 11, 500]))
    # inv(ProbeToTracker) @ RobotToTracker is the fixed pose, to rounding (1e-9 mm at 300 mm)
    np.testing.assert_allclose(rec.T_probe_from_robot, np.broadcast_to(T_true, rec.T_probe_from_robot.shape),
                               atol=1e-9)
    note = "point 0: 3 of 1500 samples dropped, the tracker marked the pose invalid in its PLUS sequence"
    assert session.notes == (note,)
    assert rec.n_invalid == 3  # the trust's share (registration.plausibility.MAX_INVALID_FRACTION)
    assert session.pose_source == "PLUS sequence"


def test_plus_clock_must_match_the_signals(tmp_path):
    folder, _, _ = _plus_session(tmp_path, shift_s=0.002)  # within a quarter step (2.5 ms): same frames
    assert read_session(folder).points[0].n_samples == 1500
    shutil.rmtree(folder)
    folder, _, _ = _plus_session(tmp_path, shift_s=2.0)
    with pytest.raises(SessionError, match=r"points/p0.csv: row 1 \(time_s 30000.000\) lies outside the frames of "
                                           r"track.igs.nrrd \(30002.000-30016.990 s; 198 such rows\): a tracker "
                                           r"recording covers its points; if PLUS ran on its own clock, give "
                                           r"session.json 'poses_time_offset_s'"):
        read_session(folder)
    meta = json.loads((folder / "session.json").read_text())
    meta["poses_time_offset_s"] = -2.0  # the documented fix: the PLUS clock's offset
    (folder / "session.json").write_text(json.dumps(meta))
    assert read_session(folder).points[0].n_samples == 1500


def test_bad_plus_files(tmp_path):
    f = tmp_path / "a.seq.mha"
    f.write_text("ObjectType = Image\nNDims = 3\nElementDataFile = LOCAL\n")
    with pytest.raises(PlusFileError, match="no Seq_Frame####_Timestamp"):
        read_plus_sequence(f)
    eye = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"
    f.write_text(f"Seq_Frame0000_Timestamp = 1.0\nSeq_Frame0000_XToYTransform = {eye}\n"
                 f"Seq_Frame0001_Timestamp = 1.0\nSeq_Frame0001_XToYTransform = {eye}\nElementDataFile = LOCAL\n")
    with pytest.raises(PlusFileError, match="share the Timestamp 1.0"):
        read_plus_sequence(f)
    f.write_text("Seq_Frame0000_Timestamp = 1.0\nSeq_Frame0000_XToYTransform = 2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n"
                 "ElementDataFile = LOCAL\n")
    with pytest.raises(PlusFileError, match="Seq_Frame0000_XToYTransform is not a rigid pose"):
        read_plus_sequence(f)
    f.write_text("Seq_Frame0000_Timestamp = 1.0\nSeq_Frame0000_XToYTransform = 1 0 0\nElementDataFile = LOCAL\n")
    with pytest.raises(PlusFileError, match="XToYTransform must be 16 numbers"):
        read_plus_sequence(f)
    f.write_text(f"Seq_Frame0000_Timestamp = 1.0\nSeq_Frame0000_XToYTransform = {eye}\n"
                 "Seq_Frame0001_Timestamp = 2.0\nElementDataFile = LOCAL\n")
    with pytest.raises(PlusFileError, match="frame 1 has no XToYTransform"):
        read_plus_sequence(f)
    # cut short before its last line (a copy that stopped): said, not blamed on the clock (session 16's sweep)
    f.write_text(f"Seq_Frame0000_Timestamp = 1.0\nSeq_Frame0000_XToYTransform = {eye}\nSeq_Frame0001_Timest")
    with pytest.raises(PlusFileError, match="no ElementDataFile line, the MetaImage header's last: the file is cut short"):
        read_plus_sequence(f)
    with pytest.raises(PlusFileError, match="ends in"):
        read_plus_sequence(tmp_path / "a.csv")
    with pytest.raises(PlusFileError, match="does not exist"):
        read_plus_sequence(tmp_path / "none.seq.mha")


def test_nrrd_with_crlf_lines_a_bom_and_pixels(tmp_path):
    """A .seq.nrrd written on Windows (CRLF header, a blank CRLF line, then binary pixels) was "not text"; one
    with a UTF-8 byte-order mark was read as MetaImage ("no Seq_Frame####_Timestamp")."""
    eye = "1 0 0 5 0 1 0 6 0 0 1 7 0 0 0 1"
    header = ["NRRD0004", "type: uint8", "dimension: 3", "sizes: 2 2 2", "encoding: raw",
              "Seq_Frame0000_Timestamp:=10.0", f"Seq_Frame0000_XToYTransform:={eye}",
              "Seq_Frame0001_Timestamp:=10.01", f"Seq_Frame0001_XToYTransform:={eye}"]
    pixels = bytes([0xff, 0xfe, 0x80, 0x81, 0x00, 0xc3, 0x28, 0xa0])  # not UTF-8
    for name, raw in (("crlf.seq.nrrd", "\r\n".join(header).encode() + b"\r\n\r\n" + pixels),
                      ("bom.seq.nrrd", b"\xef\xbb\xbf" + "\n".join(header).encode() + b"\n\n" + pixels)):
        (tmp_path / name).write_bytes(raw)
        seq = read_plus_sequence(tmp_path / name)
        assert seq.time_s.tolist() == [10.0, 10.01]
        assert seq.transform("XToY")[:, :3, 3].tolist() == [[5.0, 6.0, 7.0]] * 2


def test_session_names_missing_plus_parts(tmp_path):
    folder, _, _ = _plus_session(tmp_path)
    (folder / "track.igs.nrrd").unlink()
    with pytest.raises(SessionError, match="track.igs.nrrd is listed in session.json but missing"):
        read_session(folder)
    shutil.rmtree(folder)
    folder, _, _ = _plus_session(tmp_path)
    text = (folder / "track.igs.nrrd").read_bytes().replace(b"ProbeToTracker", b"StylusToTracker")
    (folder / "track.igs.nrrd").write_bytes(text)
    with pytest.raises(SessionError, match="has no transform 'ProbeToTracker'"):
        read_session(folder)


def _ecg_and_breaths(t):
    """ECG: an R every 0.8 s from 0.3 s (Gaussian, 12 ms); flows: a 4 s breath, expiration from 1.5 s in."""
    beats = np.arange(0.3, t[-1], 0.8)
    ecg = np.exp(-0.5 * ((t[:, None] - beats[None]) / 0.012) ** 2).sum(axis=1)
    cycle = t % 4.0  # a ventilator: constant inspiratory flow, the expiratory valve opening in a step
    insp = np.where(cycle < 1.5, 20.0, 0.0)
    exp = np.where(cycle >= 1.5, 30.0 * np.exp(-(cycle - 1.5) / 0.6), 0.0)
    return ecg, insp, exp


def test_phases_keep_their_clock_across_dropped_samples(tmp_path):
    from registration.point_models import point_phases

    # the tracker loses the robot 12 times for 80 ms (the ECG and flows of those rows go with the poses),
    # one dropout over the R at 33.9 s; every other R lies outside the dropouts
    starts = [130, 480, 810, 1190, 1530, 1980, 2300, 2705, 3100, 3385, 3775, 4170]
    invalid = [s + k for s in starts for k in range(8)]
    folder, _, time_s = _plus_session(tmp_path, n=4500, invalid=invalid, signals=_ecg_and_breaths)
    record = read_session(folder).points[0]
    assert record.n_invalid == 96
    phase_c, phase_r, peaks, onsets = point_phases(record)
    beats = 30000.0 + np.arange(0.3, 45.0, 0.8)
    kept = beats[np.abs(beats - 30033.9) > 0.01]
    # every R found at its time (before: each dropout put the R-peaks after it 80 ms early, up to 0.96 s by
    # the end; median cardiac phase error 0.2 cycle)
    np.testing.assert_allclose(peaks, kept[(kept > 30000.1) & (kept < 30044.9)], atol=0.002)
    t = record.time_s
    true_c = np.mod(t - 30000.3, 0.8) / 0.8
    lost = (t > 30033.101) & (t < 30034.699)  # the R-R interval whose R the dropout took: no phase, not a wrong one
    assert np.isnan(phase_c[lost]).all()
    ok = np.isfinite(phase_c)
    d = np.mod(phase_c[ok] - true_c[ok] + 0.5, 1.0) - 0.5
    assert np.abs(d).max() < 0.005 and ok.sum() > 0.9 * t.size
    # the starts of expiration too (the expiratory valve opens 1.5 s into each 4 s breath)
    np.testing.assert_allclose(onsets, 30000.0 + np.arange(1.5, 45.0, 4.0), atol=0.011)


def _rewrite_poses(folder, keep=slice(None), scale=1.0):
    """Write the session's PLUS file again: only the frames ``keep``, translations times ``scale``."""
    seq = read_plus_sequence(folder / "track.igs.nrrd")
    poses = {}
    for name in ("RobotToTracker", "ProbeToTracker"):
        T = np.array(seq.transform(name)[keep])
        T[:, :3, 3] *= scale
        poses[name] = T
    write_plus_sequence(folder / "track.igs.nrrd", seq.time_s[keep], poses)


def _refused(folder) -> str:
    """The one line ``read_session`` refuses ``folder`` with."""
    with pytest.raises(SessionError) as info:
        read_session(folder)
    return str(info.value)


def test_poses_every_third_sample_are_interpolated(tmp_path):
    """A PLUS file with a pose every 3rd sample (33 Hz) was first blamed on the clock ('check the PLUS clock'),
    then refused as a video capture (an audit); a tracker at its own rate is now interpolated (the test below).
    The fixed robot of this session is read back at every sample, to rounding."""
    folder, T_true, time_s = _plus_session(tmp_path)
    _rewrite_poses(folder, keep=slice(None, None, 3))
    session = read_session(folder)
    rec = session.points[0]
    assert session.notes == ("poses interpolated from the PLUS sequence's 33.3 Hz frames to the samples' 100 Hz "
                             "(translation linear, rotation along the shortest arc)",
                             "2 of 1500 samples of 1 point(s) dropped (point 0: 2): no tracked pose within 2.5 "
                             "frame steps of them in the PLUS sequence (a record's first or last samples, or the "
                             "tracker's dropouts)")  # the two after the last frame
    np.testing.assert_array_equal(rec.time_s, time_s[:-2])
    np.testing.assert_allclose(rec.T_probe_from_robot, np.broadcast_to(T_true, rec.T_probe_from_robot.shape),
                               atol=1e-9)


def test_plus_poses_in_metres_are_refused(tmp_path):
    """A tracker exporting metres: the robot sat a fraction of a millimetre from the chest probe and the
    registration ran on it to 'trust poor' without a word on units (an audit)."""
    folder, T_true, _ = _plus_session(tmp_path)
    _rewrite_poses(folder, scale=1e-3)
    distance = np.linalg.norm(T_true[:3, 3]) / 1000
    assert _refused(folder) == (
        f"session {folder}: track.igs.nrrd: the robot sensor is a median {distance:.3g} mm from the reference "
        "probe, closer than two tools can be (1 mm): are the positions in metres? the format needs mm "
        "(multiply them by 1000)")
    assert 0.1 < distance < 0.6


def test_a_plus_clock_reset_is_refused_not_sorted_in(tmp_path):
    """PLUS restarted mid-recording: its clock went back and the later frames landed among the earlier ones.
    The reader sorted them by timestamp, and with the PLUS clock 1.5 ms off the signals' (within the quarter
    step) the first 300 samples silently took the later frames' poses, 1 ms from them (an audit)."""
    folder, _, time_s = _plus_session(tmp_path, shift_s=0.0015)
    seq = read_plus_sequence(folder / "track.igs.nrrd")
    poses = {name: np.concatenate([seq.transform(name), _poses(np.random.default_rng(9), 300)])
             for name in ("RobotToTracker", "ProbeToTracker")}
    times = np.concatenate([seq.time_s, time_s[:300] + 0.001])  # frame 1500 on: the restarted clock
    write_plus_sequence(folder / "track.igs.nrrd", times, poses)
    assert _refused(folder) == (
        f"{folder / 'track.igs.nrrd'}: Seq_Frame1500_Timestamp = {float(time_s[0] + 0.001)!r} is earlier than frame "
        f"1499's {float(seq.time_s[-1])!r}: the PLUS clock went back (a restart?) and the frames after it are on another "
        "clock; record again or split the file there")


def _tracker_session(tmp_path, frame_times, T_probe_from_robot, *, rate=100.0, n=1500, t0=30000.0, offset=None):
    """A PLUS session whose tracker runs on its own clock (``frame_times``, s) beside signals at ``rate``;
    the probe still, the robot at ``T_probe_from_robot(t)`` relative to it."""
    folder = tmp_path / "plus"
    (folder / "points").mkdir(parents=True)
    time_s = np.round(t0 + np.arange(n) / rate, 3)
    probe = np.tile(np.eye(4), (len(frame_times), 1, 1))
    probe[:, :3, 3] = [10.0, -200.0, 50.0]
    write_plus_sequence(folder / "track.igs.nrrd", frame_times,
                        {"RobotToTracker": probe @ T_probe_from_robot(np.asarray(frame_times)), "ProbeToTracker": probe})
    _write_signals_and_meta(folder, time_s, (np.full(n, 0.1), np.ones(n), np.zeros(n)), rate,
                            **({} if offset is None else {"poses_time_offset_s": offset}))
    return folder, time_s


def _beating(t):
    """A robot 100 mm from the probe, moving 5 mm and turning 5 degrees at 1.2 Hz (with a third harmonic)."""
    w = 2 * np.pi * 1.2 * (t - 30000.0)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, 3] = np.stack([100 + 5 * np.sin(w), 2 * np.cos(w) + np.sin(3 * w), 3 * np.sin(2 * w)], axis=1)
    T[:, :3, :3] = Rotation.from_rotvec(np.radians(5) * np.stack(
        [np.sin(w), np.cos(w), 0.5 * np.sin(3 * w)], axis=1)).as_matrix()
    return T


def test_a_tracker_at_its_own_rate_is_interpolated_to_the_samples(tmp_path):
    """Real trackers run at their own rate and clock (an optical tracker at 40-60 Hz, PLUS's timestamps
    jittered, a frame lost now and then), not the signals' 100 Hz; such a sequence was refused ("record the
    poses at the signals' rate").  Its poses are now interpolated to each sample: exact at a frame's time,
    within linear interpolation's error between frames, and the samples with no frames around them dropped."""
    rng = np.random.default_rng(11)
    frames = 30000.03 + np.arange(0.0, 14.95, 1 / 40) + rng.uniform(-0.004, 0.004, 598)
    frames = np.delete(frames, [100] + list(range(300, 306)))  # one frame lost, then a 0.18 s dropout
    folder, time_s = _tracker_session(tmp_path, frames, _beating)
    session = read_session(folder)
    rec = session.points[0]
    assert session.notes[0] == ("poses interpolated from the PLUS sequence's 39.9 Hz frames to the samples' 100 Hz "
                                "(translation linear, rotation along the shortest arc)")
    # before the first frame (~30 ms), after the last and inside the dropout: no pose
    first, last = frames[0], frames[-1]
    inside = (time_s >= first) & (time_s <= last)
    k = int(np.argmax(np.diff(frames)))  # the dropout's last frame before it
    dropout = (time_s > frames[k]) & (time_s < frames[k + 1])
    assert frames[k + 1] - frames[k] > 0.17 and dropout.sum() >= 15
    kept = inside & ~dropout
    np.testing.assert_array_equal(rec.time_s, time_s[kept])
    assert rec.n_invalid == int((~kept).sum()) and session.notes[1].startswith(
        f"{int((~kept).sum())} of 1500 samples of 1 point(s) dropped (point 0: {int((~kept).sum())}): no "
        "tracked pose within 2.5 frame steps")
    truth = _beating(rec.time_s)
    err_mm = np.linalg.norm(rec.T_probe_from_robot[:, :3, 3] - truth[:, :3, 3], axis=1)
    rel = Rotation.from_matrix(rec.T_probe_from_robot[:, :3, :3]) * Rotation.from_matrix(truth[:, :3, :3]).inv()
    err_deg = np.degrees(rel.magnitude())
    # linear interpolation's bound, step^2 / 8 * |x''|: |x''| up to ~1000 mm/s^2 and ~1560 deg/s^2 here, so
    # 0.08 mm and 0.12 deg over a 25 ms step, 0.42 mm and 0.66 deg across the lost frame (58 ms)
    assert np.percentile(err_mm, 95) < 0.08 and err_mm.max() < 0.42, (np.percentile(err_mm, 95), err_mm.max())
    assert np.percentile(err_deg, 95) < 0.12 and err_deg.max() < 0.66, (np.percentile(err_deg, 95), err_deg.max())
    at_frames = np.isin(rec.time_s, frames)
    assert at_frames.sum() == 0 or err_mm[at_frames].max() < 1e-6  # a frame's own pose as written
    # the same registration input as a tracker at 100 Hz would give: the motion models see the beat
    assert rec.T_probe_from_robot.shape == (int(kept.sum()), 4, 4)


def test_a_tracker_too_slow_or_on_another_clock(tmp_path):
    # PLUS's own freehand recording (PlusLibData, NwirePhantomFreehand.igs.nrrd): frames at video rate, 78 ms
    frames = 30000.0 + np.arange(0.0, 15.0, 0.078)
    folder, _ = _tracker_session(tmp_path, frames, _beating)
    with pytest.raises(SessionError, match=r"track.igs.nrrd: its frames come every 0.078 s \(12.8 Hz\), too seldom "
                                           r"for the heartbeat's motion .* at 20 Hz or more"):
        read_session(folder)
    shutil.rmtree(folder)
    # PLUS's clock counts from the application's start (345.6 s in that recording), the signals' from midnight
    frames = 345.6 + np.arange(0.0, 15.0, 1 / 40)
    folder, _ = _tracker_session(tmp_path, frames, lambda t: _beating(t + 30000.0 - 345.6))
    with pytest.raises(SessionError, match=r"points/p0.csv: row 1 \(time_s 30000.000\) lies outside the frames of "
                                           r"track.igs.nrrd \(345.600-360.575 s; 1500 such rows\): a tracker "
                                           r"recording covers its points; if PLUS ran on its own clock, give "
                                           r"session.json 'poses_time_offset_s'"):
        read_session(folder)
    shutil.rmtree(folder)
    folder, _ = _tracker_session(tmp_path, frames, lambda t: _beating(t + 30000.0 - 345.6), offset=30000.0 - 345.6)
    rec = read_session(folder).points[0]
    np.testing.assert_allclose(rec.T_probe_from_robot[:, :3, 3], _beating(rec.time_s)[:, :3, 3], atol=0.2)
    shutil.rmtree(folder)
    # a tracker at the signals' 100 Hz on its own clock, 4 ms off theirs: no frame within a quarter step of a
    # sample (refused as a clock offset before), interpolated between its frames
    frames = 30000.004 + np.arange(0.0, 15.0, 0.01)
    folder, time_s = _tracker_session(tmp_path, frames, _beating)
    session = read_session(folder)
    assert session.notes[0].startswith("poses interpolated from the PLUS sequence's 100 Hz frames")
    rec = session.points[0]
    assert rec.n_samples == 1499  # the first sample lies before the first frame
    np.testing.assert_allclose(rec.T_probe_from_robot[:, :3, 3], _beating(rec.time_s)[:, :3, 3], atol=0.02)


def test_a_session_tracked_at_40_hz_registers_like_the_100_hz_one(sample_case, sample_outputs, tmp_path):
    """The shared sample session again with its tracker at 40 Hz on its own clock (each frame a row of the
    100 Hz session, its time jittered by up to a fifth of a step), registered at the CT's breath-hold phase as
    the 100 Hz session is: the interpolated poses move the final transform by a fraction of a millimetre, and
    both lie within the pipeline's 2 mm and 2 degrees of the truth.  (Measured at phi_R 0.3 on seeds 1-3:
    0.05-0.30 mm from the 100 Hz session's at 60 and 40 Hz, 0.16-0.61 mm at 25 Hz; this 30-point session
    alone leaves phi_R* undecided, so the phase is stated.)"""
    from heartreg.phantom.plus import write_plus_session
    from modeling.model import read_model
    from registration.pipeline import register_session

    case, truth = sample_case
    model = read_model(sample_outputs / "model")
    T_true = model.T_heart_from_patient @ np.asarray(truth["T_patient_from_probe"])
    vertices = np.asarray(model.mesh.vertices)

    def error(T, T_ref):
        E = T @ np.linalg.inv(T_ref)
        mm = np.linalg.norm(vertices @ E[:3, :3].T + E[:3, 3] - vertices, axis=1).mean()
        return mm, np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))

    plus = read_session(write_plus_session(case / "session", tmp_path / "plus", tracker_rate_hz=40.0, seed=1))
    assert plus.notes[0].startswith("poses interpolated from the PLUS sequence's")
    at_breath_hold = dict(cardiac_sweep=False, breath_hold_phase=truth["respiration_phase"], breath_hold_sd=0.002)
    csv_T, plus_T = (register_session(model, s, **at_breath_hold).T_heart_from_probe
                     for s in (read_session(case / "session"), plus))
    for T in (csv_T, plus_T):
        mm, deg = error(T, T_true)
        assert mm <= 2.0 and deg <= 2.0, (mm, deg)
    mm, deg = error(plus_T, csv_T)
    assert mm <= 0.4 and deg <= 0.4, (mm, deg)


@pytest.mark.parametrize("offset", [1e20, 1e308, -1e300])
def test_an_offset_no_two_clocks_have_is_refused(tmp_path, offset):
    """A huge poses_time_offset_s put every frame on one time: ZeroDivisionError (the frames' rate) before."""
    folder, _ = _tracker_session(tmp_path, 30000.004 + np.arange(0.0, 15.0, 0.01), _beating, offset=offset)
    assert _refused(folder) == (
        f"session {folder}: session.json: 'poses_time_offset_s' is {offset:.6g} s, more than the 1e+10 s (three "
        "centuries) two clocks can differ by: give the PLUS clock's offset from the signals' clock in seconds")


def test_frames_an_offset_puts_on_one_time_are_refused(tmp_path):
    """Within the bound, an offset can still round frames a microsecond apart onto one time (1e10 s: 2e-6 s)."""
    folder, _ = _tracker_session(tmp_path, 1e-6 * np.arange(1500), _beating, offset=1e10)
    assert _refused(folder) == (
        f"session {folder}: track.igs.nrrd: with session.json 'poses_time_offset_s' = 1e+10 s its frames 1 and 2 "
        "fall on one time (713 such pairs): the offset is too large for the timestamps' precision; give the PLUS "
        "clock's offset in seconds")


@pytest.mark.parametrize("value", ["1e300", "-2e4"])
def test_a_pose_beyond_the_csv_bound_is_refused_naming_file_and_frame(tmp_path, value):
    """A 1e300 mm pose in a PLUS file was read (two bare overflow warnings, exit 0) while the CSV reader refused
    1e30 mm naming file, row and value: the same bound (MAX_ABS['mm']) now holds for the PLUS frames."""
    folder, _, _ = _plus_session(tmp_path, n=200)
    f = folder / "track.igs.nrrd"
    lines = f.read_bytes().decode().split("\n")
    at = next(j for j, ln in enumerate(lines) if ln.startswith("Seq_Frame0007_RobotToTrackerTransform:="))
    key, numbers = lines[at].split(":=")
    cells = numbers.split()
    cells[7] = value  # the y translation
    lines[at] = f"{key}:={' '.join(cells)}"
    f.write_bytes("\n".join(lines).encode())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        message = _refused(folder)
    assert message == (f"{f}: Seq_Frame0007_RobotToTrackerTransform: translation {float(value):.6g} mm (its 8th "
                       "number) is beyond the plausible 10000 mm (1 such frame(s)); check the tracker's units or "
                       "record again")
