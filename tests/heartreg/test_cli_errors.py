"""The command's error contract: a refusal of bad input is one line and status 1;
anything else is a bug, shown with its traceback and status 70."""

from __future__ import annotations

import pytest

from heartreg import cli, cli_parser
from hrcore.errors import HeartregError, UsageError


def _run_phases_raising(monkeypatch, tmp_path, exc):
    def boom(args):
        raise exc

    monkeypatch.setattr(cli_parser, "_cmd_phases", boom)  # the parser binds each command
    return cli.main(["phases", str(tmp_path)])


def test_a_refusal_is_one_line(monkeypatch, tmp_path, capsys):
    status = _run_phases_raising(monkeypatch, tmp_path, UsageError("step (--step) must be in (0, 0.5] cycles, got 2"))
    err = capsys.readouterr().err
    assert status == 1
    assert err == "heartreg phases: error: step (--step) must be in (0, 0.5] cycles, got 2\n"


@pytest.mark.parametrize("exc", [ZeroDivisionError("division by zero"), ValueError("operands could not be broadcast"),
                                 KeyError("rr_s")])
def test_a_bug_shows_its_traceback(monkeypatch, tmp_path, capsys, exc):
    status = _run_phases_raising(monkeypatch, tmp_path, exc)
    err = capsys.readouterr().err
    assert status == cli.EXIT_BUG == 70
    assert "Traceback (most recent call last)" in err and type(exc).__name__ in err
    assert err.rstrip().splitlines()[-1].startswith("heartreg phases: internal error (a bug in heartreg")


def test_usage_errors_are_heartreg_errors_and_value_errors():
    assert issubclass(UsageError, HeartregError) and issubclass(UsageError, ValueError)
    assert issubclass(cli.CommandLineError, UsageError)


def test_output_piped_into_a_reader_that_leaves(sample_case, tmp_path):
    """``heartreg phases STUDY -o OUT | head -1``: the reader leaves before the summary
    is printed; the command ends quietly with 141 (as ``yes | head`` ends ``yes``),
    its outputs complete, instead of "error: a file: Broken pipe" and status 1.  A
    broken pipe that is not standard output's stays the one-line error."""
    import json
    import subprocess
    import sys

    case, _ = sample_case
    out = tmp_path / "phases"
    proc = subprocess.Popen([sys.executable, "-m", "heartreg", "phases", str(case / "ct"), "-o", str(out), "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader leaves at once
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == cli.EXIT_PIPE == 141, err
    assert err == ""
    assert json.loads((out / "phases.json").read_text())["volume_cardiac_phase"] >= 0


def test_a_broken_pipe_elsewhere_is_still_an_error(monkeypatch, tmp_path, capsys):
    status = _run_phases_raising(monkeypatch, tmp_path, BrokenPipeError(32, "Broken pipe"))
    assert status == 1
    assert capsys.readouterr().err.startswith("heartreg phases: error: ")


def test_list_series_needs_no_output_folder(tmp_path, capsys):
    """``model --list-series`` demanded -o (``phases`` did not), and ``pipeline --list-series`` ran the whole
    pipeline; a volume file has one series, said so instead of 'no DICOM images found'."""
    from pathlib import Path

    import nibabel as nib
    import numpy as np

    study = str(Path(__file__).resolve().parents[2] / "sample_dicom" / "ct")
    for argv in (["model", study, "--list-series"], ["pipeline", study, str(tmp_path / "no-session"), "--list-series"]):
        assert cli.main(argv) == 0
        assert "[0] " in capsys.readouterr().out
    assert cli.main(["model", study]) == 1
    assert "give an output folder with -o OUT_DIR (or --list-series)" in capsys.readouterr().err
    nib.save(nib.Nifti1Image(np.zeros((4, 4, 4), np.int16), np.eye(4)), str(tmp_path / "ct.nii.gz"))
    assert cli.main(["model", str(tmp_path / "ct.nii.gz"), "--list-series"]) == 1
    assert "is a volume file, one series: --list-series lists a DICOM folder's" in capsys.readouterr().err
    assert not (tmp_path / "no-session").exists()


def test_pipeline_of_a_volume_file_says_it_needs_dicom_and_where_a_volume_goes(tmp_path, capsys):
    """``heartreg pipeline CT.nii.gz`` said "no DICOM images found under 'CT.nii.gz'" (an audit); phases said
    why, pipeline now says the same (one check) and that 'heartreg model' takes the volume."""
    (tmp_path / "ct.nii.gz").write_bytes(b"\x1f\x8b")  # never read: the name says what it is
    for command, rest in (("pipeline", [str(tmp_path / "session")]), ("phases", [])):
        assert cli.main([command, str(tmp_path / "ct.nii.gz"), *rest, "-o", str(tmp_path / "out"), "-q"]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert f"is a volume file: {command} reads a DICOM study (its slice times and ECG)" in err
        assert "make the model from the volume with 'heartreg model'" in err
        assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", ["-1e9", "50", "1e5"])
def test_a_fiducial_floor_outside_tissue_and_metal_is_refused(tmp_path, capsys, value):
    """--fiducial-floor-hu=-1e9 was taken: every voxel 'dense', no marker found, exit 0."""
    with pytest.raises(SystemExit) as info:
        cli.main(["model", "STUDY", "-o", str(tmp_path / "m"), f"--fiducial-floor-hu={value}"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"heartreg model: error: argument --fiducial-floor-hu: {value} HU is not between soft tissue "
                   "(100) and metal (3000) (see heartreg model --help)"]


def test_sigterm_while_the_command_line_is_read_is_143(monkeypatch, capsys):
    """The parser's build imports the library (~1 s): SIGTERM then killed the process (-15) without a word,
    the handler was installed after it."""
    import os
    import signal

    built = cli_parser._build_parser

    def build_then_terminated():
        parser = built()
        os.kill(os.getpid(), signal.SIGTERM)
        return parser

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(cli, "_build_parser", build_then_terminated)
    assert cli.main(["model", "STUDY", "-o", "OUT"]) == 143
    assert capsys.readouterr().err == "heartreg: terminated (SIGTERM); nothing was written\n"
    assert signal.getsignal(signal.SIGTERM) == before


def test_a_signal_after_the_command_is_done_changes_nothing(monkeypatch):
    """SIGINT just after the summary was printed ended the process by the signal (-2), the outputs whole:
    once main has returned, run ignores SIGINT and SIGTERM while the interpreter exits."""
    import signal

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    seen = {}

    def exit_(status):
        seen.update({s: signal.getsignal(s) for s in before}, status=status)

    monkeypatch.setattr(cli, "main", lambda: 0)
    monkeypatch.setattr(cli.sys, "exit", exit_)
    try:
        cli.run()
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
    assert seen == {signal.SIGINT: signal.SIG_IGN, signal.SIGTERM: signal.SIG_IGN, "status": 0}


def _misleading_inputs(tmp, make_series):
    """The files of a new user's audit that got a misleading refusal, and what the one line must say now."""
    import shutil

    import nibabel as nib
    import numpy as np
    import pydicom

    nib.save(nib.Nifti1Image(np.full((10, 10, 10), -1000, np.int16), np.eye(4)), str(tmp / "plain.nii"))
    shutil.copy(tmp / "plain.nii", tmp / "misnamed.nii.gz")
    (tmp / "junk.nii.gz").write_bytes(b"not a volume at all" * 30)
    nib.save(nib.AnalyzeImage(np.full((10, 10, 10), -1000, np.int16), np.eye(4)), str(tmp / "analyze.img"))
    files = make_series(tmp / "series", n_slices=5, ge_private=None)
    shutil.copy(files[0], tmp / "single.dcm")
    ds = pydicom.dcmread(files[0])
    ds.NumberOfFrames = 5
    ds.PixelData = ds.PixelData * 5
    ds.save_as(tmp / "multiframe.dcm")
    header = ("NRRD0004\ntype: short\ndimension: 3\nspace: scanner-xyz\nsizes: 4 4 4\n"
              "space directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (0,0,0)\nencoding: raw\nendian: little\n\n")
    (tmp / "scanner.nrrd").write_bytes(header.encode() + bytes(128))
    return [
        ("misnamed.nii.gz", "is an uncompressed NIfTI file named .nii.gz (no gzip compression): rename it to .nii"),
        ("junk.nii.gz", "is not gzip-compressed, as a .nii.gz must be, nor a NIfTI file"),
        ("analyze.hdr", "is an Analyze 7.5 image (.hdr/.img pair), not DICOM: convert it to NIfTI"),
        ("analyze.img", "is an Analyze 7.5 image (.hdr/.img pair), not DICOM: convert it to NIfTI"),
        ("single.dcm", "is one DICOM image (a single slice), not a study: give the folder that holds the whole CT"),
        ("multiframe.dcm", "a classic multi-frame CT image (5 frames in one file, one ImagePositionPatient for them "
                           "all): its frames cannot be placed; export the series as single-frame CT images"),
        ("scanner.nrrd", "space 'scanner-xyz' names no patient directions"),
    ]


def test_misleading_refusals_say_what_the_file_is(tmp_path, capsys):
    """Before: 'damaged (Not a gzipped file)', 'no DICOM images found', 'the CT spans only 2 mm', 'repeated slice
    positions that no attribute separates; choose one with --series', 'missing or bad header field
    ('scanner-xyz')' (a new user's audit)."""
    from tests.imaging.dicom_factory import write_ct_series

    for name, said in _misleading_inputs(tmp_path, write_ct_series):
        assert cli.main(["model", str(tmp_path / name), "-o", str(tmp_path / "out"), "-q"]) == 1, name
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and said in err and name in err, (name, err)
        assert not (tmp_path / "out").exists()


def test_a_warning_is_a_line_of_its_own_under_a_progress_bar():
    """A warning under a progress bar ran on from the bar's text ('model:   0%| ... mask]warning: ...', an audit):
    it starts a line of its own while a bar is drawn."""
    import io
    import warnings

    from tqdm import tqdm

    from heartreg.cli import _one_line_warning

    assert _one_line_warning(UserWarning("the heart is cut"), UserWarning, "x.py", 1) == "warning: the heart is cut\n"
    with tqdm(total=5, desc="model", file=io.StringIO()):
        line = _one_line_warning(UserWarning("the heart is cut"), UserWarning, "x.py", 1)
    assert line == "\nwarning: the heart is cut\n"
    assert warnings.formatwarning is not _one_line_warning  # the command's format, not the process's


def test_an_unknown_option_is_named_with_its_command(capsys):
    """'heartreg pipeline ... --cardiac-phase 0.2' said 'heartreg: error: unrecognized arguments ... (see heartreg
    --help)', which names neither the command nor its help (an audit)."""
    from heartreg.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["pipeline", "ct", "session", "-o", "out", "--cardiac-phase", "0.2"])
    assert stop.value.code == 2
    assert capsys.readouterr().err == ("heartreg pipeline: error: unrecognized arguments: --cardiac-phase 0.2 "
                                       "(see heartreg pipeline --help)\n")


def test_a_path_the_terminal_cannot_encode_is_escaped(tmp_path):
    """With an ASCII-only terminal (PYTHONIOENCODING=ascii) a non-ASCII path in the summary crashed the command
    after its work was written ('internal error', 70; the next run found the folder not empty; an audit)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    study = Path(__file__).resolve().parents[2] / "sample_dicom" / "ct"
    out = tmp_path / "J\u00f6rg"
    env = dict(os.environ, PYTHONIOENCODING="ascii")
    done = subprocess.run([sys.executable, "-m", "heartreg", "phases", str(study), "-o", str(out), "-q"],
                          capture_output=True, env=env, timeout=120)
    assert done.returncode == 0 and "J\\xf6rg" in done.stdout.decode("ascii"), done.stderr.decode("ascii")
    assert (out / "phases.json").is_file()


def test_track_help_states_its_defaults(capsys):
    """The README gives --igtl-rate's default (100/s); --help said nothing of it, nor that without --igtl-port
    nothing is served."""
    with pytest.raises(SystemExit):
        cli.main(["track", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "end after this many idle seconds (default 5)" in text
    assert "0: any free; default: no server, nothing sent)" in text
    assert "most samples per second sent over OpenIGTLink (default 100; 0: all)" in text
    assert "before the stream starts (default 0)" in text


def test_batch_help_says_a_run_again_skips_done_cases(capsys):
    """The README says a batch run again into its folder skips the cases done before; --help did not (an audit)."""
    with pytest.raises(SystemExit):
        cli.main(["batch", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "run again into it, a case whose inputs, options and heartreg version are unchanged is skipped" in text
