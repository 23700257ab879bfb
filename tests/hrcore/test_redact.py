"""Notes written to disk name no file of the study (``hrcore.redact``): exported files are often named after
the patient (session 16's sweep found such a name in phases.json, case.json, summary.csv and index.html); the
study's DICOM UIDs are written as their pseudonyms (DICOM PS3.15)."""

from __future__ import annotations

import hashlib
import re
from types import SimpleNamespace

from heartreg.pipeline import phase_report_extra
from hrcore.redact import file_namer, pseudonym_uid, pseudonymize_uids

#: A DICOM UID (PS3.5 9.1): at most 64 characters, digit components without a leading zero.
VALID_UID = re.compile(r"(0|[1-9]\d*)(\.(0|[1-9]\d*))*")
STUDY = "1.2.826.0.1.3680043.8.498.41277198919281116875750323738303205845"
SERIES = "1.2.826.0.1.3680043.8.498.66619507006363438244667089610910371537"


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


def test_pseudonym_uid_is_a_valid_uid_of_the_study_uids_hash():
    uids = [STUDY, SERIES, "1.2.3", "2.25.0", "9" * 64, "1.2.840.113619.2.55.3.604688119.868.1234567890.123"]
    pseudonyms = [pseudonym_uid(u) for u in uids]
    for uid, pseudonym in zip(uids, pseudonyms):
        assert VALID_UID.fullmatch(pseudonym) and len(pseudonym) <= 64, pseudonym
        assert pseudonym.startswith("2.25.") and pseudonym != uid
        # what the docs tell a user who holds the study to compute
        assert pseudonym == "2.25." + str(int.from_bytes(hashlib.sha256(uid.encode()).digest()[:16], "big"))
        assert pseudonym_uid(uid) == pseudonym and pseudonym_uid(uid + "\0") == pseudonym  # DICOM's padding
    assert len(set(pseudonyms)) == len(uids)
    # 1000 UIDs differing in their last digits: 1000 pseudonyms, none with a leading zero (checked above)
    assert len({pseudonym_uid(f"1.2.826.0.1.3680043.8.498.{k}") for k in range(1000)}) == 1000
    assert pseudonym_uid("") == "" and pseudonym_uid("\0") == ""


def test_uids_in_a_text_become_their_pseudonyms_but_the_standards_own():
    text = (f"chose series [0] {SERIES}: axial CT; series {STUDY}: 1 image(s) of another size; "
            "no image (SOP Class 1.2.840.10008.5.1.4.1.1.9.1.1); heartreg 1.2.3, 1.5 mm")
    assert pseudonymize_uids(text) == (
        f"chose series [0] {pseudonym_uid(SERIES)}: axial CT; series {pseudonym_uid(STUDY)}: 1 image(s) of another "
        "size; no image (SOP Class 1.2.840.10008.5.1.4.1.1.9.1.1); heartreg 1.2.3, 1.5 mm")


def test_phases_json_carries_the_pseudonym_of_the_series_uid(tmp_path):
    volume = SimpleNamespace(notes=(f"chose series [0] {SERIES}: axial CT, 72 image(s)",),
                             series=SimpleNamespace(series_instance_uid=SERIES))
    extra = phase_report_extra(volume, tmp_path)
    assert extra == {"series_instance_uid": pseudonym_uid(SERIES),
                     "volume_notes": [f"chose series [0] {pseudonym_uid(SERIES)}: axial CT, 72 image(s)"]}
