"""Notes written to disk name no file of the study (``hrcore.redact``): exported files are often named after
the patient (session 16's sweep found such a name in phases.json, case.json, summary.csv and index.html)."""

from __future__ import annotations

from types import SimpleNamespace

from heartreg.pipeline import phase_report_extra
from hrcore.redact import file_namer


def test_file_names_become_a_file_and_numbers_stay(tmp_path):
    (tmp_path / "CT").mkdir()
    for name in ("CT/SMITHERS_WAYLON.CT.0005.dcm", "1", "42", "IM0001", "IM00010"):
        (tmp_path / name).write_text("x")
    unnamed = file_namer(tmp_path)
    assert (unnamed("skipped CT/SMITHERS_WAYLON.CT.0005.dcm: truncated; 1 file(s), 42 slices")
            == "skipped a file: truncated; 1 file(s), 42 slices")
    assert unnamed("largest between IM0001 and IM00010.") == "largest between a file and a file."
    assert unnamed("IM0001x and XIM0001 are other words") == "IM0001x and XIM0001 are other words"
    single = tmp_path / "CT" / "SMITHERS_WAYLON.CT.0005.dcm"
    assert file_namer(single)("'SMITHERS_WAYLON.CT.0005.dcm' unreadable") == "'a file' unreadable"
    assert file_namer(tmp_path / "nothing")("IM0001") == "IM0001"


def test_phases_json_notes_name_no_file(tmp_path):
    (tmp_path / "SMITHERS_WAYLON.CT.0005.dcm").write_text("x")
    volume = SimpleNamespace(notes=(f"skipped 1 DICOM file(s) that cannot be read: {tmp_path}/"
                                    "SMITHERS_WAYLON.CT.0005.dcm: Pixel Data holds 1134 of 32768 bytes",),
                             series=SimpleNamespace(series_instance_uid="1.2.3"))
    extra = phase_report_extra(volume, tmp_path)
    assert extra["volume_notes"] == ["skipped 1 DICOM file(s) that cannot be read: a file: Pixel Data holds 1134 of "
                                     "32768 bytes"]
