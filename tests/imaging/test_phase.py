"""Per-slice cardiac phases against the phantom's truth, for every R-peak source."""

from __future__ import annotations

import dataclasses
import re
import json
import shutil

import numpy as np
import pydicom
import pytest

from hrcore.output import OutputError

from heartreg.cli import main
from imaging import (
    GatingError,
    PhaseReport,
    compute_phase_report,
    load_study,
    read_ecg_waveform,
    read_phase_report,
    read_qrs_file,
    write_phase_report,
)
from imaging.phase import GatingWarning, SlicePhase
from imaging.phase_io import PhaseFileError

#: the slice clocks are written with microsecond resolution: phases agree to 1e-5;
#: the issue's tolerances (1e-3 per slice, 0.005 for the volume) leave room for
#: QRS detection on the ECG waveform (sub-sample, < 1 ms at 500 Hz = 1e-3 phase).
SLICE_TOL = 1e-3
VOLUME_TOL = 0.005


def _copy_without(case_dir, tmp_path, *, private=False, ecg=False, gating=False):
    """A copy of the case's CT folder with GE private tags / ECG / gating tags removed."""
    out = tmp_path / "ct"
    out.mkdir()
    for f in sorted((case_dir / "ct").iterdir()):
        ds = pydicom.dcmread(f)
        if ds.Modality == "ECG":
            if not ecg:
                shutil.copy(f, out / f.name)
            continue
        if private:
            ds.remove_private_tags()
        if gating:
            for kw in ("TriggerTime", "NominalInterval", "HeartRate", "CardiacSynchronizationTechnique"):
                if kw in ds:
                    delattr(ds, kw)
        ds.save_as(out / f.name)
    return out


def _check(report, truth):
    truth_phase = np.asarray(truth["slice_cardiac_phase"])
    assert report.n_slices == len(truth_phase)
    np.testing.assert_allclose(report.phases, truth_phase, atol=SLICE_TOL)
    assert abs(report.volume_cardiac_phase - truth["cardiac_phase"]) <= VOLUME_TOL


def test_ge_rpeak_timestamps(sample_case):
    case, truth = sample_case
    report = compute_phase_report(load_study(case / "ct"))
    assert report.source.startswith("GE RpeakTimeStamps")
    _check(report, truth)
    assert "origin" in report.clock


def _with_ge_stamps(case_dir, tmp_path, stamps):
    """A copy of the case's CT folder with (0049,xx0C) *RpeakTimeStamps* replaced by ``stamps(old)``."""
    out = tmp_path / "ct"
    out.mkdir()
    for f in sorted((case_dir / "ct").iterdir()):
        ds = pydicom.dcmread(f)
        if ds.Modality == "CT":
            element = ds.private_block(0x0049, "GEMS_CT_CARDIAC_001")[0x0C]
            element.value = stamps(list(element.value))
        ds.save_as(out / f.name)
    return out


def test_ge_stamps_written_twice_over(sample_case, tmp_path):
    """GE scanners may write (0049,xx0C) twice over, the list and then the same again with the next beat
    (pydicom's real ``dicomdirtests/98892001/CT2N``): the distinct stamps in order are the R-peaks, noted.
    Before session 22 'r_peaks_s must be strictly increasing' stopped ``phases`` and ``model``."""
    case, truth = sample_case
    report = compute_phase_report(load_study(_with_ge_stamps(case, tmp_path, lambda r: r[:-1] + r)))
    assert report.source.startswith("GE RpeakTimeStamps")
    _check(report, truth)
    assert any("out of order or repeated" in n for n in report.notes)


def test_ge_stamps_all_alike_fall_through(sample_case, tmp_path):
    """Stamps that time no beat (all one value, as in pydicom's real ``98892001/CT5N``) are noted and the
    next source is used: the study's ECG waveform."""
    case, truth = sample_case
    report = compute_phase_report(load_study(_with_ge_stamps(case, tmp_path, lambda r: [r[0], r[0]])))
    assert "ECG waveform" in report.source
    _check(report, truth)
    assert any("fewer than two distinct stamps (2 given); not used" in n for n in report.notes)


def test_qrs_file_wins_over_metadata(sample_case):
    case, truth = sample_case
    volume = load_study(case / "ct")
    report = compute_phase_report(volume, qrs_s=read_qrs_file(case / "qrs.csv"), qrs_label="qrs.csv")
    assert report.source.startswith("qrs.csv")
    _check(report, truth)
    np.testing.assert_allclose(report.r_peaks_s, truth["r_peaks_s"], atol=1e-6)


def test_slices_in_a_long_rr_interval_are_warned(sample_case, tmp_path):
    """R-peaks missing under the scan (a lead off or in noise: the detector finds no beat there) make one
    R-R interval hold slices whose phases are then uncertain: warned and noted, the phases still given
    (review of session 20: a waveform with 8 s of noise under the slices gave phases 0.2 off, silently)."""
    case, truth = sample_case
    r = np.asarray(truth["r_peaks_s"], dtype=float)
    volume = load_study(case / "ct")
    acq = np.array([s.acquisition_time_s for s in volume.slices])
    under = np.flatnonzero((r > acq.min()) & (r < acq.max()))
    assert under.size >= 1
    thinned = tmp_path / "missing.csv"
    kept = np.delete(r, under[:2])
    thinned.write_text("time_s\n" + "\n".join(f"{t:.6f}" for t in kept) + "\n")
    with pytest.warns(GatingWarning, match=r"missing.csv: \d+ slice\(s\) lie in R-R intervals up to .* times the "
                                           r"median .*beats missing there"):
        report = compute_phase_report(volume, qrs_s=read_qrs_file(thinned), qrs_label="missing.csv")
    assert report.source.startswith("missing.csv")
    assert any("their phases are uncertain" in n for n in report.notes)
    # the study's own R-peaks: no such interval, no such note
    assert not any("uncertain" in n for n in compute_phase_report(volume).notes)


def test_ecg_waveform_when_no_ge_tags(sample_case, tmp_path):
    case, truth = sample_case
    ct = _copy_without(case, tmp_path, private=True)
    volume = load_study(ct)
    assert volume.series.rpeak_timestamps_ms is None and len(volume.waveform_files) == 1
    records = [read_ecg_waveform(p) for p in volume.waveform_files]
    report = compute_phase_report(volume, ecg_records=records)
    assert "ECG waveform" in report.source and "QRS" in report.source
    _check(report, truth)


def test_trigger_time_fallback(sample_case, tmp_path):
    """TriggerTime over the nominal RR interval is the scanner's prediction: it is
    only as good as the RR prediction (HRV of a few %), so within 0.1 of truth."""
    case, truth = sample_case
    ct = _copy_without(case, tmp_path, private=True, ecg=True)
    report = compute_phase_report(load_study(ct))
    assert report.source.startswith("TriggerTime")
    truth_phase = np.asarray(truth["slice_cardiac_phase"])
    err = np.abs(report.phases - truth_phase)
    assert np.median(np.minimum(err, 1 - err)) < 0.1
    assert any("no GE RpeakTimeStamps" in n for n in report.notes)


def _with_waveform_data(case_dir, tmp_path, change):
    """A copy of the case's CT folder without GE private tags, its ECG waveform's data replaced by ``change(data)``."""
    ct = _copy_without(case_dir, tmp_path, private=True)
    for f in ct.iterdir():
        ds = pydicom.dcmread(f)
        if ds.Modality == "ECG":
            item = ds.WaveformSequence[0]
            item.WaveformData = change(item.WaveformData)
            ds.save_as(f)
    return ct


def test_nominal_phases_after_a_flat_ecg_are_warned(sample_case, tmp_path):
    """The study's ECG waveform unusable (all zeros: a lead off) and no GE stamps: the phases fall back to
    TriggerTime over the nominal RR interval, now warned with the waveform's reason (only noted in
    phases.json before the review of session 22)."""
    ct = _with_waveform_data(sample_case[0], tmp_path, lambda data: bytes(len(data)))
    with pytest.warns(GatingWarning, match=r"nominal phases.*own R-peak sources were not usable: .*ECG waveform: .* constant"):
        report = compute_phase_report(load_study(ct))
    assert report.source.startswith("TriggerTime")


def test_a_truncated_waveform_is_said_so(sample_case, tmp_path):
    """The study's ECG waveform cut to half its bytes: said in plain words (numpy's 'cannot reshape array of size
    2840' before), the notes no longer say there is no waveform, and the nominal phases are warned."""
    ct = _with_waveform_data(sample_case[0], tmp_path, lambda data: data[: len(data) // 2])
    with pytest.warns(GatingWarning, match="nominal phases"):
        report = compute_phase_report(load_study(ct))
    assert any(re.search(r"ECG waveform unreadable: .*holds \d+ bytes where its header's samples and channels need "
                         r"\d+", n) for n in report.notes), report.notes
    assert not any("no DICOM ECG waveform instance" in n for n in report.notes)


def test_no_gating_is_a_clear_error(sample_case, tmp_path):
    case, _ = sample_case
    ct = _copy_without(case, tmp_path, private=True, ecg=True, gating=True)
    with pytest.raises(GatingError, match=r"no cardiac gating information.*--qrs"):
        compute_phase_report(load_study(ct))


def test_qrs_outside_scan_is_not_extrapolated(sample_case, tmp_path):
    case, truth = sample_case
    bad = tmp_path / "late.csv"
    bad.write_text("time_s\n" + "\n".join(str(t + 3600) for t in truth["r_peaks_s"]) + "\n")
    with pytest.warns(GatingWarning, match=r"late.csv.*not used.*not extrapolated"):
        report = compute_phase_report(load_study(case / "ct"), qrs_s=read_qrs_file(bad), qrs_label="late.csv")
    assert report.source.startswith("GE")  # fell through to the next source
    assert any("not extrapolated" in n for n in report.notes)
    # both ranges, so that an ECG of another hour or day shows as such (an audit: the R-peaks' range alone, on
    # another clock, read 412 million seconds and nothing to compare it with)
    note = next(n for n in report.notes if "not extrapolated" in n)
    assert re.search(r"fall outside the R-peaks \(slices \d+\.\d{3}\.\.\d+\.\d{3} s, R-peaks \d+\.\d{3}\.\.\d+\.\d{3} s; "
                     r"they do not overlap at all\); not extrapolated", note), note
    # nothing to fall through to: the error asks to check the file given, not to give one
    (tmp_path / "ungated").mkdir()
    ungated = _copy_without(case, tmp_path / "ungated", private=True, ecg=True, gating=True)
    with pytest.warns(GatingWarning), pytest.raises(GatingError, match=r"not extrapolated.*Check that the R-peak "
                                                                         r"file's times are seconds after midnight"):
        compute_phase_report(load_study(ungated), qrs_s=read_qrs_file(bad), qrs_label="late.csv")


@pytest.mark.parametrize(
    "text, match",
    [("t\n1\n2\n", "time_s"), ("time_s\n1\n", "at least 2"), ("time_s\n2\n1\n", "increasing"),
     ("time_s\nabc\n", "not a number"), (b"\xce\xff\x00binary", "not a UTF-8 text CSV"),
     # a decimal comma split each time in two, and the file was refused as 'not increasing' (review, session 22)
     ("time_s\n38330,986044\n38331,9\n", r"line 2: more values than the header's columns; a decimal comma")],
)
def test_bad_qrs_file(tmp_path, text, match):
    path = tmp_path / "qrs.csv"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(GatingError, match=match):
        read_qrs_file(path)


def test_cli_phases_outputs_match_truth(sample_case, tmp_path, capsys):
    case, truth = sample_case
    out = tmp_path / "out"
    assert main(["phases", str(case / "ct"), "-o", str(out), "-q"]) == 0
    summary = capsys.readouterr().out
    assert "GE RpeakTimeStamps" in summary and f"{truth['cardiac_phase']:.4f}" in summary
    payload = json.loads((out / "phases.json").read_text())
    assert abs(payload["volume_cardiac_phase"] - truth["cardiac_phase"]) <= VOLUME_TOL
    assert payload["n_slices"] == len(truth["slice_cardiac_phase"])
    assert payload["jumps"] == []
    assert payload["fraction_in_window"] == pytest.approx(
        np.mean((np.array(truth["slice_cardiac_phase"]) >= 0.6) & (np.array(truth["slice_cardiac_phase"]) <= 0.8))
    )
    rows = np.genfromtxt(out / "phases.csv", delimiter=",", names=True)
    np.testing.assert_allclose(rows["cardiac_phase"], truth["slice_cardiac_phase"], atol=SLICE_TOL)
    np.testing.assert_allclose(np.diff(rows["position_mm"]), 2.5, atol=1e-3)
    png = (out / "phases.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    text = " ".join(p.read_text() for p in (out / "phases.json", out / "phases.csv"))
    assert "PHANTOM" not in text  # no patient identity in outputs
    from imaging.files import umask_mode

    for name in ("phases.csv", "phases.json", "phases.png"):  # not private temporary files
        assert (out / name).stat().st_mode & 0o777 == umask_mode()
    _check_reads_back(out, tmp_path / "again")


def _check_reads_back(out, again):
    """read_phase_report gives the report written: the same files when written again."""
    report = read_phase_report(out)
    assert report.n_slices == json.loads((out / "phases.json").read_text())["n_slices"]
    assert not report.r_peaks_s.flags.writeable
    extra = {k: v for k, v in json.loads((out / "phases.json").read_text()).items() if k not in report.to_dict()}
    write_phase_report(report, again, extra=extra)
    for name in ("phases.csv", "phases.json"):
        assert (again / name).read_bytes() == (out / name).read_bytes()
    table = [[np.array(dataclasses.astuple(s)) for s in r.slices] for r in (report, read_phase_report(again))]
    np.testing.assert_array_equal(*table)  # NaN times (no clock) equal too


def test_phase_report_round_trip_and_bad_files(tmp_path):
    nan = float("nan")
    report = PhaseReport(
        slices=(SlicePhase(0, -12.5, 0.25, 0.7, 0.0), SlicePhase(1, -10.0, nan, 0.75, 1.5)),
        volume_cardiac_phase=0.725, circular_mean_phase=0.7249, source="qrs.csv", clock="trigger time",
        r_peaks_s=np.array([0.0, 0.8, 1.6]), jumps=(0,), fraction_in_window=1.0, notes=("a note",),
    )
    write_phase_report(report, tmp_path / "a")
    (tmp_path / "a" / "stale.txt").write_text("an earlier run's file")
    with pytest.raises(OutputError, match="not empty.*--overwrite"):  # never overwritten silently
        write_phase_report(report, tmp_path / "a")
    write_phase_report(report, tmp_path / "a", overwrite=True)  # the writer removes what the new run does not write
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["phases.csv", "phases.json", "phases.png"]
    back = read_phase_report(tmp_path / "a")
    assert back.slices[0] == report.slices[0] and np.isnan(back.slices[1].time_s)
    assert back.to_dict() == report.to_dict()
    _check_reads_back(tmp_path / "a", tmp_path / "b")
    meta = json.loads((tmp_path / "a" / "phases.json").read_text())
    assert (meta["format"], meta["format_version"]) == ("heartreg-phases", 1)  # as model.json and registration.json
    for key, value in (("format", "heartreg-model"), ("format_version", 2)):
        (tmp_path / "b" / "phases.json").write_text(json.dumps({**meta, key: value}))
        with pytest.raises(PhaseFileError, match="not a phases.json of heartreg .* not 'heartreg-phases' version 1"):
            read_phase_report(tmp_path / "b")
    del meta["format"], meta["format_version"]  # a file written before session 17
    (tmp_path / "b" / "phases.json").write_text(json.dumps(meta))
    assert read_phase_report(tmp_path / "b").to_dict() == report.to_dict()
    with pytest.raises(PhaseFileError, match="phases.json not found"):
        read_phase_report(tmp_path / "none")
    csv = tmp_path / "a" / "phases.csv"
    csv.write_text(csv.read_text() + "2,1.0,0.5\n")
    with pytest.raises(PhaseFileError, match="phases.csv: line 4 is not a slice row"):
        read_phase_report(tmp_path / "a")
    csv.write_text("\n".join(csv.read_text().splitlines()[:2]) + "\n")
    with pytest.raises(PhaseFileError, match="1 slice rows, but phases.json says n_slices = 2"):
        read_phase_report(tmp_path / "a")


def test_cli_phases_errors(tmp_path, capsys):
    study = tmp_path / "study"
    study.mkdir()
    assert main(["phases", str(study), "-o", str(tmp_path / "o")]) == 1
    assert "no DICOM images" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["study"]  # no empty -o folder left
    assert main(["phases", str(tmp_path)]) == 1
    assert "-o OUT_DIR" in capsys.readouterr().err


@pytest.mark.slow
def test_full_size_phases(full_case):
    case, truth = full_case
    volume = load_study(case / "ct")
    assert volume.shape == (288, 512, 512)
    report = compute_phase_report(volume)
    _check(report, truth)
    report = compute_phase_report(volume, qrs_s=read_qrs_file(case / "qrs.csv"))
    _check(report, truth)


def test_library_and_command_agree_on_an_ecg_only_study(sample_case, tmp_path):
    """Issue 10: a study whose only R-peak source is its ECG waveform (no GE stamps,
    no TriggerTime): ``compute_phase_report(volume)`` reads the waveform itself and
    gives the command's phi_C* (the truth, within VOLUME_TOL), naming the waveform
    by what it is, not by its file (a file or folder name can name the patient)."""
    case, truth = sample_case
    ct = _copy_without(case, tmp_path, private=True, gating=True)
    report = compute_phase_report(load_study(ct))
    assert report.source == "ECG waveform (Pan-Tompkins QRS detection)"
    _check(report, truth)
    out = tmp_path / "out"
    assert main(["phases", str(ct), "-o", str(out), "-q"]) == 0
    written = json.loads((out / "phases.json").read_text())
    assert written["volume_cardiac_phase"] == report.volume_cardiac_phase
    assert written["source"] == report.source


def test_a_dead_lead_ii_gives_way_to_another_lead(sample_case, tmp_path):
    """Lead II off (flat) in a two-lead waveform whose other lead is good: the phases come from the other lead,
    and the notes say so.  Before session 16 the waveform was given up and the nominal TriggerTime phases taken
    (on real 12-lead MIT-BIH studies 0.27 of a cycle off)."""
    import copy

    case, truth = sample_case
    ct = _copy_without(case, tmp_path, private=True, gating=True)
    wave = next(f for f in ct.iterdir() if pydicom.dcmread(f, stop_before_pixels=True).Modality == "ECG")
    ds = pydicom.dcmread(wave)
    group = ds.WaveformSequence[0]
    good = np.frombuffer(group.WaveformData, dtype="<i2")  # the one lead's stored samples
    v5 = copy.deepcopy(group.ChannelDefinitionSequence[0])
    v5.ChannelLabel = "V5"
    del v5.ChannelSourceSequence
    group.ChannelDefinitionSequence.append(v5)
    group.NumberOfWaveformChannels = 2
    group.WaveformData = np.stack([np.zeros_like(good), good], axis=1).tobytes()  # lead II flat, V5 the ECG
    ds.save_as(wave)
    report = compute_phase_report(load_study(ct))
    assert report.source == "ECG waveform (lead V5) (Pan-Tompkins QRS detection)", report.source
    assert any("lead II has no usable QRS complexes, lead V5 used" in n for n in report.notes), report.notes
    _check(report, truth)


def test_unreadable_waveform_is_named_by_its_place_in_the_notes(sample_case, tmp_path):
    """A broken ECG waveform instance: the report falls back and its note names neither the file nor its
    folder (either can name the patient)."""
    case, _ = sample_case
    ct = _copy_without(case, tmp_path, private=True)
    wave = next(f for f in ct.iterdir() if pydicom.dcmread(f, stop_before_pixels=True).Modality == "ECG")
    ds = pydicom.dcmread(wave)
    del ds.WaveformSequence[0].WaveformData
    ds.save_as(wave)
    report = compute_phase_report(load_study(ct))
    assert report.source.startswith("TriggerTime")
    note = next(n for n in report.notes if "unreadable" in n)
    assert note.startswith("ECG waveform unreadable") and wave.name not in note and str(tmp_path) not in note


def test_a_waveform_error_loses_its_path_not_its_words():
    """A DICOM export names files 1, 2, ...: the path goes, the numbers in the message stay."""
    from imaging.phase import _strip_paths

    text = _strip_paths("/data/Smith_John/1: waveform has 12 channels, 1 multiplex group", "/data/Smith_John/1")
    assert text == "the file: waveform has 12 channels, 1 multiplex group"


def _shift_clock(path, shift_s):
    """Move every time of a DICOM file by ``shift_s`` seconds, with its dates."""
    import datetime

    ds = pydicom.dcmread(path)
    study_day = datetime.datetime.strptime(ds.StudyDate, "%Y%m%d")
    for date_kw, time_kw in (("AcquisitionDate", "AcquisitionTime"), ("ContentDate", "ContentTime"),
                             ("StudyDate", "StudyTime"), ("SeriesDate", "SeriesTime")):
        if time_kw not in ds:
            continue
        t = datetime.datetime.strptime(ds.get(date_kw) or ds.StudyDate, "%Y%m%d") + datetime.timedelta(
            seconds=pydicom.valuerep.TM(ds.get(time_kw)).hour * 3600.0
            + pydicom.valuerep.TM(ds.get(time_kw)).minute * 60.0
            + pydicom.valuerep.TM(ds.get(time_kw)).second
            + pydicom.valuerep.TM(ds.get(time_kw)).microsecond * 1e-6
            + shift_s
        )
        setattr(ds, date_kw, t.strftime("%Y%m%d"))
        setattr(ds, time_kw, t.strftime("%H%M%S.%f"))
    if "AcquisitionDateTime" in ds:
        t = datetime.datetime.strptime(str(ds.AcquisitionDateTime)[:21].ljust(21, "0")[:14], "%Y%m%d%H%M%S")
        frac = str(ds.AcquisitionDateTime)[14:].split("+")[0].split("-")[0]
        t = t + datetime.timedelta(seconds=float("0" + frac) + shift_s)
        ds.AcquisitionDateTime = t.strftime("%Y%m%d%H%M%S.%f")
    ds.save_as(path)
    return study_day


def test_scan_across_midnight(sample_case, tmp_path):
    """Issue 10: slices and ECG at 23:59:5x -> 00:00:xx, dates +1: phases as without the
    crossing (the truth), not 'slice times outside the R-peaks'."""
    case, truth = sample_case
    ct = _copy_without(case, tmp_path, private=True, gating=True)
    volume = load_study(ct)
    times = np.array([s.acquisition_time_s for s in volume.slices])
    midnight_in = 0.5 * (times.min() + times.max())
    shift = 86400.0 - midnight_in  # midnight falls in the middle of the scan
    for f in ct.iterdir():
        _shift_clock(f, shift)
    moved = load_study(ct)
    shifted = np.array([s.acquisition_time_s for s in moved.slices])
    assert shifted.min() < 86400.0 < shifted.max()  # on the study day's clock, past 24 h
    np.testing.assert_allclose(shifted, times + shift, atol=1e-5)
    report = compute_phase_report(moved)
    assert report.source.startswith("ECG waveform")
    _check(report, truth)


def test_automatic_choice_prefers_the_gated_series(sample_case, tmp_path, capsys):
    """Issue 10: a larger series without any cardiac gating beside the gated one.
    The phase commands take the gated one and say so (and how to choose another);
    plain ``load_study`` still takes the largest."""
    case, truth = sample_case
    study = tmp_path / "study"
    study.mkdir()
    cts = []
    for f in sorted((case / "ct").iterdir()):
        ds = pydicom.dcmread(f)
        if ds.Modality == "ECG":
            continue
        cts.append((float(ds.ImagePositionPatient[2]), f, ds))
    cts.sort(key=lambda c: c[0])
    ungated_uid = pydicom.uid.generate_uid(entropy_srcs=["ungated"])
    for i, (_, f, ds) in enumerate(cts):
        if 10 <= i < 50:
            shutil.copy(f, study / f"gated_{f.name}")  # 40 contiguous gated slices (GE stamps)
        ds.remove_private_tags()
        for kw in ("TriggerTime", "NominalInterval", "HeartRate", "AcquisitionTime", "ContentTime",
                   "AcquisitionDateTime"):
            if kw in ds:
                delattr(ds, kw)
        ds.SeriesInstanceUID = ungated_uid
        ds.SOPInstanceUID = pydicom.uid.generate_uid(entropy_srcs=[f.name])
        ds.SeriesDescription = "ungated"
        ds.save_as(study / f"plain_{f.name}")
    assert load_study(study).series.series_instance_uid == ungated_uid
    volume = load_study(study, prefer_gated=True)
    assert volume.series.series_instance_uid != ungated_uid and volume.hu.shape[0] == 40
    note = next(n for n in volume.notes if n.startswith("chose series"))
    assert "cardiac gating from GE RpeakTimeStamps" in note and "larger series without cardiac gating" in note
    out = tmp_path / "out"
    assert main(["phases", str(study), "-o", str(out), "-q"]) == 0
    err = capsys.readouterr().err
    assert "chose series" in err and "--series" in err
    report = json.loads((out / "phases.json").read_text())
    assert report["n_slices"] == 40
    np.testing.assert_allclose(
        json.loads((out / "phases.json").read_text())["volume_cardiac_phase"],
        np.mean(np.asarray(truth["slice_cardiac_phase"])[10:50]), atol=VOLUME_TOL,
    )


def test_phases_of_a_volume_file_says_it_needs_dicom(tmp_path, capsys):
    """``heartreg phases CT.nii.gz`` said "no DICOM images found" (session 15's sweep): it now says why."""
    (tmp_path / "ct.nii.gz").write_bytes(b"\x1f\x8b")  # never read: the name says what it is
    assert main(["phases", str(tmp_path / "ct.nii.gz"), "-o", str(tmp_path / "out"), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "is a volume file: phases reads a DICOM study" in err, err
    assert not (tmp_path / "out").exists()


def test_phases_png_legend_names_the_jump_lines(tmp_path, monkeypatch):
    """phases.png draws a red line at every jump between slices; the legend did not say what the lines were
    (a page audit). The first line is now named in the legend, once however many jumps there are."""
    from matplotlib.figure import Figure

    import imaging.phase_io as phase_io

    slices = tuple(SlicePhase(i, 2.5 * i, float(i), p, float(i)) for i, p in enumerate([0.7, 0.72, 0.55, 0.56, 0.7]))
    report = PhaseReport(slices=slices, volume_cardiac_phase=0.646, circular_mean_phase=0.646, source="qrs.csv",
                         clock="trigger time", r_peaks_s=np.array([0.0, 5.0]), jumps=(1, 3), fraction_in_window=0.6)
    drawn = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: drawn.append(fig))
    phase_io.plot_phases(report, tmp_path / "phases.png")
    (ax,) = drawn[0].axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels.count("phase jump > 0.1 between slices") == 1
    red = [line for line in ax.lines if line.get_color() == "tab:red"]
    assert sorted(line.get_xdata()[0] for line in red) == [1.5, 3.5]
