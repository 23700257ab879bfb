"""`heartreg phantom`: the whole case on disk, its truth, determinism and bad arguments."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from hrcore.output import OutputError

from heartreg.cli import main
from heartreg.phantom import PhantomError, make_phantom
from heartreg.phantom.heart import T_from_euler_xyz_deg

REQUIRED_TRUTH = (
    "cardiac_phase", "respiration_phase", "slice_cardiac_phase", "r_peaks_s", "T_patient_from_probe",
    "heart_axes_patient", "heart_origin_patient_mm", "fiducials_patient_mm",
)


def _digest(folder):
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_cli_writes_a_complete_case(tmp_path, capsys):
    out = tmp_path / "case"
    argv = ["phantom", str(out), "--preset", "wood2018-trial2", "--seed", "3", "--points", "6", "--plus", "-q"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "wood2018-trial2" in printed and "session_plus" in printed
    truth = json.loads((out / "truth.json").read_text())
    for key in REQUIRED_TRUTH:
        assert key in truth, key
    # the truth is self-consistent: phi_C* is the mean of the slice phases, the
    # heart axes are the preset's Euler angles, T* is rigid
    assert truth["cardiac_phase"] == pytest.approx(np.mean(truth["slice_cardiac_phase"]))
    R = T_from_euler_xyz_deg(truth["config"]["euler_xyz_deg"])[:3, :3]
    np.testing.assert_allclose(truth["heart_axes_patient"], R, atol=1e-12)
    T = np.asarray(truth["T_patient_from_probe"])
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert len(truth["session"]["points"]) == 6
    assert len(list((out / "session" / "points").glob("*.csv"))) == 6
    qrs = np.genfromtxt(out / "qrs.csv", delimiter=",", names=True)
    np.testing.assert_allclose(qrs["time_s"], truth["r_peaks_s"], atol=1e-6)
    assert not list(out.glob(".phantom-*"))  # no staging left behind
    # --plus: the same session with its poses in a PLUS sequence file, read back to the same bits
    from registration.session import read_session

    csv, plus = read_session(out / "session"), read_session(out / "session_plus")
    assert plus.pose_source == "PLUS sequence" and len(plus.points) == 6
    for a, b in zip(csv.points, plus.points):
        np.testing.assert_array_equal(a.T_probe_from_robot, b.T_probe_from_robot)
        np.testing.assert_array_equal(a.ecg_mv, b.ecg_mv)
    np.testing.assert_array_equal(csv.fiducials_probe_mm, plus.fiducials_probe_mm)


def test_same_seed_same_bytes(tmp_path):
    a = make_phantom(tmp_path / "a", seed=5, n_points=3)
    b = make_phantom(tmp_path / "b", seed=5, n_points=3)
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")
    c = make_phantom(tmp_path / "c", seed=6, n_points=3)
    assert _digest(tmp_path / "a") != _digest(tmp_path / "c")
    assert a["r_peaks_s"] == b["r_peaks_s"] != c["r_peaks_s"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--preset", "trial9"], "invalid choice"),
        (["--size", "huge"], "invalid choice"),
    ],
)
def test_bad_cli_choices(tmp_path, argv, message, capsys):
    with pytest.raises(SystemExit):
        main(["phantom", str(tmp_path / "x"), *argv])
    assert message in capsys.readouterr().err


def test_bad_arguments_are_clear_errors(tmp_path, capsys):
    assert main(["phantom", str(tmp_path / "x"), "--seed", "-1"]) == 1
    assert "seed (--seed) must be a non-negative integer" in capsys.readouterr().err
    assert main(["phantom", str(tmp_path / "x"), "--points", "0"]) == 1
    assert "n_points (--points) must be positive" in capsys.readouterr().err
    # session 17's sweep: --points 100000 ran for minutes towards ~55 GB; --chest-wall-mm 1e6 was accepted;
    # --plus --no-session wrote no PLUS session without a word
    for flags, message in ((["--points", "100000"], "n_points (--points) must be within 3..1000"),
                           (["--chest-wall-mm", "1e6"], "chest_wall_ap_mm (--chest-wall-mm) must be within 0..30 mm"),
                           (["--plus", "--no-session"], "--plus needs the session"),
                           (["--plus", "40", "--no-session"], "--plus needs the session")):
        assert main(["phantom", str(tmp_path / "x"), *flags, "-q"]) == 1
        assert message in capsys.readouterr().err and not (tmp_path / "x").exists()
    # a tracker's rate for the PLUS session: one the reader takes (20 Hz and up) and no faster than the signals
    with pytest.raises(SystemExit) as exit_:
        main(["phantom", str(tmp_path / "x"), "--plus", "12.8", "-q"])
    assert exit_.value.code == 2 and "12.8 Hz is not a tracker's rate between 20 and 100 Hz" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    with pytest.raises(PhantomError, match="heart_rate_hz must be within"):
        make_phantom(tmp_path / "y", heart_rate_hz=9.0)
    with pytest.raises(PhantomError, match="unknown preset"):
        make_phantom(tmp_path / "y", preset="nope")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(PhantomError, match="not a folder"):
        make_phantom(blocker)


def test_existing_outputs_are_refused_then_replaced(tmp_path):
    make_phantom(tmp_path, seed=1, session=False)
    with pytest.raises(PhantomError, match="already holds phantom outputs.*overwrite"):
        make_phantom(tmp_path, seed=1, session=False)
    truth = make_phantom(tmp_path, seed=2, session=False, overwrite=True)
    assert json.loads((tmp_path / "truth.json").read_text())["seed"] == 2 == truth["seed"]
    # a folder of the user's that only shares a name with an output is no earlier phantom (it was deleted)
    (tmp_path / "mine" / "session").mkdir(parents=True)
    (tmp_path / "mine" / "session" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="mine holds session but no truth.json: it is no earlier output of this command"):
        make_phantom(tmp_path / "mine", seed=1, session=False, overwrite=True)
    assert (tmp_path / "mine" / "session" / "notes.txt").read_text() == "mine"
