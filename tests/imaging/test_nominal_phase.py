"""Nominal phases (TriggerTime, NominalPercentageOfCardiacPhase) and when they are no gating (imaging.nominal).

A new user's audit: a CT without ECG gating (CardiacSynchronizationTechnique NONE or absent, TriggerTime 0 on
every slice, a HeartRate, no ECG) got cardiac phase 0.0 on every slice, silently (issue #9 wants it unknown).
"""

from __future__ import annotations

import warnings

import numpy as np
import pydicom
import pytest

from heartreg.cli import main
from heartreg.pipeline import open_study
from imaging import GatingError, compute_phase_report, load_study
from imaging.phase import GatingWarning

from . import dicom_factory as fac


def _series(tmp_path, name="ct", *, technique=None, trigger=0.0, interval=None, rate=None, percent=None, **kw):
    """A tiny CT series (no GE stamps, no ECG) with these gating tags; ``trigger``/``percent`` a value or a
    callable of the slice index; None leaves the tag out."""

    def tags(ds, k):
        for keyword, value in (("CardiacSynchronizationTechnique", technique), ("TriggerTime", trigger),
                               ("NominalInterval", interval), ("HeartRate", rate),
                               ("NominalPercentageOfCardiacPhase", percent)):
            value = value(k) if callable(value) else value
            if value is not None:
                setattr(ds, keyword, value)

    folder = tmp_path / name
    fac.write_ct_series(folder, ge_private=None, extra=tags, **kw)
    return folder


@pytest.mark.parametrize("technique, rate, interval, why", [
    ("NONE", 72, None, "CardiacSynchronizationTechnique NONE: the scan was not ECG-gated"),
    ("NONE", None, 850, "CardiacSynchronizationTechnique NONE: the scan was not ECG-gated"),
    (None, 72, None, "TriggerTime 0 on every slice, with no CardiacSynchronizationTechnique and no NominalInterval"),
])
def test_an_ungated_ct_has_no_phase(tmp_path, technique, rate, interval, why):
    """Before: phase 0.0 from 'TriggerTime / nominal RR interval' on every slice, no word said."""
    folder = _series(tmp_path, technique=technique, rate=rate, interval=interval)
    volume = load_study(folder)
    assert {s.cardiac_sync_technique for s in volume.slices} == {technique}
    with warnings.catch_warnings():
        warnings.simplefilter("error", GatingWarning)
        with pytest.raises(GatingError, match=rf"no cardiac gating information for the slices \({why}.*TriggerTime "
                                              r"not used.*--qrs") as caught:
            compute_phase_report(volume)
    assert why in caught.value.reason
    # what heartreg model does: the phase unknown, and why (model.json's cardiac_phase_source)
    _, reason = open_study(folder, phase_required=False)
    assert reason.startswith("no ECG gating (") and why in reason


def test_phases_command_says_why_in_one_line(tmp_path, capsys):
    folder = _series(tmp_path, technique="NONE", rate=72)
    assert main(["phases", str(folder), "-o", str(tmp_path / "out"), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "CardiacSynchronizationTechnique NONE" in err, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


@pytest.mark.parametrize("technique, interval, rate", [
    ("PROSPECTIVE", 850, None),  # prospective gating at 0 % of a real RR interval
    ("RETROSPECTIVE", None, 70),
    (None, 850, None),  # no technique, but the nominal RR interval the gating used
])
def test_gated_at_zero_percent_keeps_its_phase(tmp_path, technique, interval, rate):
    report = compute_phase_report(load_study(_series(tmp_path, technique=technique, interval=interval, rate=rate)))
    assert report.source == "TriggerTime / nominal RR interval"
    np.testing.assert_array_equal(report.phases, 0.0)
    assert any("taken as gating at 0 %" in n for n in report.notes) == (technique is None)


def test_trigger_times_of_a_gated_scan_are_used_without_a_technique(tmp_path):
    """Trigger times that vary (retrospective reconstruction) or sit at one non-zero delay are gating."""
    report = compute_phase_report(load_study(_series(tmp_path, trigger=lambda k: 40.0 * k, rate=75)))
    np.testing.assert_allclose(report.phases, 40.0 * np.arange(20) / 800.0)
    report = compute_phase_report(load_study(_series(tmp_path, "ct2", trigger=560.0, rate=75)))
    np.testing.assert_allclose(report.phases, 0.7)


def test_percentages_of_an_ungated_scan_are_not_a_phase(tmp_path):
    folder = _series(tmp_path, technique="NONE", trigger=None, percent=70)
    with pytest.raises(GatingError, match=r"NominalPercentageOfCardiacPhase not used: CardiacSynchronization"):
        compute_phase_report(load_study(folder))
    folder = _series(tmp_path, "ct2", trigger=0.0, percent=0)
    with pytest.raises(GatingError, match=r"NominalPercentageOfCardiacPhase 0 on every slice"):
        compute_phase_report(load_study(folder))
    report = compute_phase_report(load_study(_series(tmp_path, "ct3", trigger=None, percent=70)))
    assert report.source == "NominalPercentageOfCardiacPhase" and np.allclose(report.phases, 0.7)


def test_an_ecg_still_times_an_ungated_scan(sample_case, tmp_path):
    """A measured R-peak source (here the sample study's GE stamps) is used whatever the technique says."""
    case, truth = sample_case
    out = tmp_path / "ct"
    out.mkdir()
    for f in sorted((case / "ct").iterdir()):
        ds = pydicom.dcmread(f)
        if ds.Modality == "CT":
            ds.CardiacSynchronizationTechnique = "NONE"
        ds.save_as(out / f.name)
    report = compute_phase_report(load_study(out))
    assert report.source.startswith("GE RpeakTimeStamps")
    assert abs(report.volume_cardiac_phase - truth["cardiac_phase"]) <= 0.005


def test_the_automatic_choice_does_not_count_an_ungated_series_as_gated(tmp_path):
    """Two series, the larger one ungated with TriggerTime 0 and a HeartRate: --prefer-gated took it for gated."""
    study = tmp_path / "study"
    _series(study, "a", technique="NONE", rate=72, n_slices=24, series_number=3)
    gated = _series(study, "b", technique="PROSPECTIVE", trigger=560.0, rate=75, n_slices=12, series_number=4)
    uid = pydicom.dcmread(next(gated.iterdir())).SeriesInstanceUID
    volume = load_study(study, prefer_gated=True)
    assert volume.series.series_instance_uid == uid
    note = next(n for n in volume.notes if n.startswith("chose series"))
    assert "cardiac gating from TriggerTime" in note, note


def test_trigger_times_beyond_the_rr_interval_are_warned(tmp_path):
    """A TriggerTime longer than the nominal RR interval was wrapped into the next beat without a word (a new
    user's audit): kept wrapped, warned with the count and the values' range."""
    folder = _series(tmp_path, technique="RETROSPECTIVE", trigger=lambda k: 600.0 + 25.0 * k, interval=800)
    with pytest.warns(GatingWarning, match=r"TriggerTime: 11 of 20 slice\(s\) at 825\.\.1075 ms, beyond the nominal "
                                           r"RR interval \(800 ms\).*wrapped into the next beat \(phases 0\.03125\.\.0\.3438\)"):
        report = compute_phase_report(load_study(folder))
    np.testing.assert_allclose(report.phases, np.mod((600.0 + 25.0 * np.arange(20)) / 800.0, 1.0))
    assert any("beyond the nominal RR interval" in n for n in report.notes)


@pytest.mark.parametrize("trigger", [lambda k: 2000.0 if k == 3 else 500.0, lambda k: -50.0 if k == 3 else 500.0])
def test_trigger_times_of_no_beat_are_not_used(tmp_path, trigger):
    """Two RR intervals or more, or negative: no delay within a beat; the source is not used (and says so)."""
    folder = _series(tmp_path, technique="PROSPECTIVE", trigger=trigger, interval=800)
    with pytest.raises(GatingError, match=r"TriggerTime: 1 of 20 slice\(s\) at -?\d+ ms, negative or 2 times the "
                                          r"nominal RR interval \(800 ms\) or more: not a phase within a beat; not used"):
        compute_phase_report(load_study(folder))


def test_percentages_over_100_are_warned(tmp_path):
    folder = _series(tmp_path, technique="RETROSPECTIVE", trigger=None, percent=lambda k: 95 + k)
    with pytest.warns(GatingWarning, match=r"NominalPercentageOfCardiacPhase: 14 of 20 slice\(s\) at 101\.\.114 %, "
                                           r"beyond 100 %"):
        report = compute_phase_report(load_study(folder))
    np.testing.assert_allclose(report.phases, np.mod((95 + np.arange(20)) / 100.0, 1.0))


def test_trigger_time_and_percentage_that_disagree_are_warned(tmp_path):
    """Gating audit: TriggerTime 300 ms of a nominal 800 ms RR interval (0.375) beside a NominalPercentageOfCardiacPhase
    of 75 %: before, phase 0.375 with no word of the contradiction."""
    folder = _series(tmp_path, technique="RETROSPECTIVE", trigger=300.0, interval=800, percent=75)
    with pytest.warns(GatingWarning) as caught:
        report = compute_phase_report(load_study(folder))
    np.testing.assert_allclose(report.phases, 0.375)
    message = ("TriggerTime and NominalPercentageOfCardiacPhase disagree on 20 of 20 slice(s): TriggerTime gives "
               "phases 0.375, the percentage says 75 %; the TriggerTime phases are used; check which is right, "
               "or give R-peak times with --qrs or the phase with --cardiac-phase")
    assert [str(w.message) for w in caught] == [message] and message in report.notes


@pytest.mark.parametrize("trigger, interval, rate", [(600.0, 800, None), (600.0, None, 75), (612.0, 800, None)])
def test_trigger_time_and_percentage_that_agree_say_nothing(tmp_path, trigger, interval, rate):
    """600 ms of 800 ms (or at 75 bpm) is 75 %: phase 0.75, no warning; a delay 1.5 % off is within tolerance."""
    folder = _series(tmp_path, technique="RETROSPECTIVE", trigger=trigger, interval=interval, rate=rate, percent=75)
    with warnings.catch_warnings():
        warnings.simplefilter("error", GatingWarning)
        report = compute_phase_report(load_study(folder))
    np.testing.assert_allclose(report.phases, trigger / 800.0)


@pytest.mark.parametrize("description, hint", [
    ("Cardiac 0.75 Bv36 75%", "The series description states 75 % (free text, not a gating tag, so not used): if "
                              "that is the phase the CT was reconstructed at, give it to heartreg register with "
                              "--cardiac-phase 0.75"),
    ("CorCTA BestDiast 0.6 I26f", "The series description names the scanner's automatic best diastolic phase "
                                  "without its value: read it on the scanner's protocol and give it to heartreg "
                                  "register with --cardiac-phase P"),
])
def test_a_phase_stated_only_in_free_text_is_named_with_what_to_give(tmp_path, capsys, description, hint):
    """Gating audit: a series whose only phase statement is its description ("75%", Siemens' "BestDiast"): before,
    'no cardiac gating information' and --qrs only, the stated phase not mentioned."""
    folder = _series(tmp_path, trigger=None, description=description)
    with pytest.raises(GatingError) as caught:
        compute_phase_report(load_study(folder))
    assert str(caught.value).endswith(hint)
    assert main(["phases", str(folder), "-o", str(tmp_path / "out"), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.endswith(hint) and "Traceback" not in err
    assert "Bv36" not in err and "CorCTA" not in err  # the free text itself is not repeated
