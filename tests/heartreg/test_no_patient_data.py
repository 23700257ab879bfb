"""No path, folder name or patient tag in any output of any command (issue 10).

A phantom study is copied into a folder named like a patient, every DICOM file
gets (0010,0010) *Patient's Name*, (0010,0020) *Patient ID* and (0010,0030)
*Patient's Birth Date*, and a *Series Description* that names the patient (free
text), and the GE R-peak stamps are removed so that the study is timed by its ECG
waveform (the source whose absolute path used to leak into ``phases.json`` and
``model.json``).  Then ``phases``, ``model``, ``register`` and ``pipeline`` run (the
session cut to its first 8 points: a registration in seconds), ``phases`` also with
an R-peak file and on the folder above the patient's (a duplicate image in a
subfolder: its note names the file), ``model`` with a mask whose file names carry the patient's name
(exports often do), and every file they wrote is searched, as bytes and with the
compressed text chunks of PNG files inflated, for the name, the ID, the birth date
(both spellings), the folder name and the temporary path, and, with what they
printed, for the study's DICOM UIDs (DICOM PS3.15: outputs carry their pseudonyms,
``hrcore.redact.pseudonym_uid``).
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pydicom
import pytest

from heartreg.cli import main
from hrcore.redact import pseudonym_uid
from tests.heartreg.small_case import first_points

NAME = "DOE^JANE"
PATIENT_ID = "PID8675309"
BIRTH = "19610412"
FOLDER = "DOE_JANE_PID8675309"


def _patient_case(case_dir: Path, root: Path) -> Path:
    """``root/FOLDER`` holding ct/ (tags set, GE stamps removed) and session/ (its first 8 points)."""
    folder = root / FOLDER
    (folder / "ct").mkdir(parents=True)
    for f in sorted((case_dir / "ct").iterdir()):
        ds = pydicom.dcmread(f)
        if ds.Modality != "ECG":
            ds.remove_private_tags()
        ds.PatientName = NAME
        ds.PatientID = PATIENT_ID
        ds.PatientBirthDate = BIRTH
        ds.SeriesDescription = f"CTA {FOLDER}"
        ds.save_as(folder / "ct" / f.name)
    (folder / "export").mkdir()  # a second copy of one image, in a subfolder: a note names it
    (folder / "export" / "IM0001.dcm").write_bytes(next((folder / "ct").iterdir()).read_bytes())
    first_points(case_dir / "session", folder / "session", 8)  # 8 points: a registration in seconds
    (folder / f"{FOLDER}_qrs.csv").write_bytes((case_dir / "qrs.csv").read_bytes())
    return folder


def _patient_mask(ct: Path, path: Path) -> Path:
    """A NIfTI mask on the CT's grid (a 40 mm ball at its centre), written to ``path``."""
    import nibabel as nib
    import numpy as np

    from imaging import load_study

    volume = load_study(ct)
    k, j, i = np.indices(volume.shape)
    c = (np.array(volume.shape) - 1) / 2
    T = volume.T_patient_from_voxel
    mm = np.sqrt(((np.stack([i - c[2], j - c[1], k - c[0]], axis=-1) @ T[:3, :3].T) ** 2).sum(axis=-1))
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ T
    nib.save(nib.Nifti1Image((mm < 40).astype(np.uint8).transpose(2, 1, 0), ras), str(path))
    return path


def _png_texts(data: bytes) -> bytes:
    """The text chunks of a PNG (tEXt, zTXt, iTXt), inflated where compressed."""
    out = []
    pos = 8
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        if kind == b"tEXt":
            out.append(body)
        elif kind == b"zTXt":
            key, _, rest = body.partition(b"\0")
            out += [key, zlib.decompress(rest[1:])]
        elif kind == b"iTXt":
            key, _, rest = body.partition(b"\0")
            compressed, rest = rest[0], rest[2:]
            _, _, rest = rest.partition(b"\0")  # language
            _, _, text = rest.partition(b"\0")  # translated keyword
            out += [key, zlib.decompress(text) if compressed else text]
        pos += 12 + length
    return b"\n".join(out)


def _leaks(out_root: Path, needles: list[str]) -> list[str]:
    found = []
    files = [p for p in out_root.rglob("*") if p.is_file()]
    assert files, f"nothing written under {out_root}"
    for path in files:
        data = path.read_bytes()
        if path.suffix.lower() == ".png":
            data += _png_texts(data)
        for needle in needles:
            if needle.encode() in data:
                found.append(f"{path.relative_to(out_root)}: {needle}")
    return found


def _study_uids(ct: Path) -> dict[str, str]:
    """Every instance UID of the study's files (study, series, frame of reference, image), as pydicom reads them."""
    uids = {}
    for f in sorted(ct.iterdir()):
        ds = pydicom.dcmread(f, stop_before_pixels=True)
        for tag in ("StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID", "SOPInstanceUID"):
            if tag in ds:
                uids[str(ds[tag].value)] = f"{tag} of a {ds.Modality} file"
    return uids


def test_no_patient_data_in_any_output(sample_case, tmp_path, capsys):
    case, _ = sample_case
    folder = _patient_case(case, tmp_path / "studies")
    out = tmp_path / "outputs"
    ct, session = folder / "ct", folder / "session"
    assert main(["phases", str(ct), "-o", str(out / "phases"), "-q"]) == 0
    assert main(["phases", str(ct), "--qrs", str(folder / f"{FOLDER}_qrs.csv"), "-o", str(out / "phases_qrs"),
                 "-q"]) == 0
    # given the folder above the patient's: the duplicate's note names neither the file nor its folders (a file
    # name can name the patient too: it named the file until session 16)
    assert main(["phases", str(folder.parent), "-o", str(out / "phases_root"), "-q"]) == 0
    written = (out / "phases_root" / "phases.json").read_text()
    assert "duplicate image(s) (same SOPInstanceUID) ignored: a file" in written and "IM0001.dcm" not in written
    mask = _patient_mask(ct, folder / f"{FOLDER}_heart.nii.gz")
    assert main(["model", str(ct), "--mask", str(mask), "-o", str(out / "model_mask"), "-q"]) == 0
    # the pipeline writes what the model command does (the same writers); register reads its model folder
    assert main(["pipeline", str(ct), str(session), "-o", str(out / "pipeline"), "-q", "--step", "0.05"]) == 0
    assert main(["register", str(out / "pipeline" / "model"), str(session), "-o", str(out / "register"), "-q",
                 "--step", "0.05", "--no-view"]) == 0
    # the study was timed by its ECG waveform, the second run by the R-peak file; each named by what it is
    assert '"source": "ECG waveform (' in (out / "phases" / "phases.json").read_text()
    assert '"source": "R-peak file given with --qrs (R-peak times)' in (out / "phases_qrs" / "phases.json").read_text()
    assert '"kind": "label map (NIfTI)"' in (out / "model_mask" / "model.json").read_text()
    needles = [NAME, NAME.replace("^", " "), PATIENT_ID, BIRTH, "1961-04-12", FOLDER, str(tmp_path),
               str(tmp_path.resolve())]
    assert _leaks(out, needles) == []
    # the study's UIDs: in no file written nor anything printed (the summaries name the series by its pseudonym)
    uids = _study_uids(ct)
    ct_file = pydicom.dcmread(next(f for f in sorted(ct.iterdir()) if pydicom.dcmread(f).Modality == "CT"))
    study, series = str(ct_file.StudyInstanceUID), str(ct_file.SeriesInstanceUID)
    assert {uids[study], uids[series]} == {"StudyInstanceUID of a CT file", "SeriesInstanceUID of a CT file"}
    assert len(uids) > 70  # each image's SOPInstanceUID, the ECG's series
    assert [f"{hit} ({uids[hit.split(': ')[1]]})" for hit in _leaks(out, list(uids))] == []
    printed = capsys.readouterr()
    assert [uids[u] for u in uids if u in printed.out or u in printed.err] == []
    assert f"slices of series {pseudonym_uid(series)}\n" in printed.out
    assert f"heart model of series {pseudonym_uid(series)} written to" in printed.out
    for model_json in (out / "model_mask" / "model.json", out / "pipeline" / "model" / "model.json"):
        source = json.loads(model_json.read_text())["source"]
        assert (source["series_instance_uid"], source["study_instance_uid"]) == (pseudonym_uid(series),
                                                                                pseudonym_uid(study))
        # how the series was chosen, named by its pseudonym (the UID search above finds no original in it)
        assert source["series_choice"].startswith(f"chose series [0] {pseudonym_uid(series)}: axial CT"), source
    # the same series in the phase report: one can still tell a model and its phases belong together
    for phases_json in (out / "phases" / "phases.json", out / "pipeline" / "phases" / "phases.json"):
        written = json.loads(phases_json.read_text())
        assert written["series_instance_uid"] == pseudonym_uid(series)
        assert f"chose series [0] {pseudonym_uid(series)}: axial CT" in written["volume_notes"][0]
    # the listing a user picks a series from shows the study's own UIDs, and --series takes them
    assert main(["phases", str(ct), "--list-series"]) == 0
    assert f"[0] {series} ({pseudonym_uid(series)})  CT" in capsys.readouterr().out  # and the pseudonym printed
    assert main(["phases", str(ct), "--series", series, "-o", str(tmp_path / "chosen"), "-q"]) == 0
    assert json.loads((tmp_path / "chosen" / "phases.json").read_text())["series_instance_uid"] == pseudonym_uid(series)


def test_warnings_and_refusals_print_pseudonyms(sample_case, tmp_path, capsys):
    """What the readers say on the terminal names a series by its pseudonym, as the outputs do: two equally good
    copies of the CT series (a re-export) are warned of, an unknown --series is refused with the series held,
    and --series takes the pseudonym printed (an audit found both lines printing the study's raw UIDs)."""
    case, _ = sample_case
    study = tmp_path / "study"
    study.mkdir()
    uids = {}
    for copy in ("a", "b"):
        series_uid = pydicom.uid.generate_uid()
        for f in sorted((case / "ct").iterdir()):
            ds = pydicom.dcmread(f)
            if ds.Modality != "CT":
                continue
            ds.SeriesInstanceUID = series_uid
            ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = pydicom.uid.generate_uid()
            ds.save_as(study / f"{copy}_{f.name}")
            uids.update({str(ds.StudyInstanceUID): "study", series_uid: f"series {copy}"})
    # as a user runs it (in-process, pytest would take the warnings before the command's printer does)
    run = subprocess.run([sys.executable, "-m", "heartreg", "model", str(study), "-o", str(tmp_path / "model"), "-q"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "2 CT series are equally good candidates ([0], [1]); used [0] 2.25." in run.stderr
    assert [uids[u] for u in uids if u in run.stdout + run.stderr] == []
    assert main(["model", str(study), "--series", "1.2.3.4.5.6", "-o", str(tmp_path / "other"), "-q"]) == 1
    refused = capsys.readouterr().err
    assert "error: no series has the UID given; the study holds: [0] 2.25." in refused
    assert [uids[u] for u in uids if u in refused] == []
    second = next(u for u, what in uids.items() if what == "series b")
    assert main(["model", str(study), "--series", pseudonym_uid(second), "-o", str(tmp_path / "b"), "-q"]) == 0
    source = json.loads((tmp_path / "b" / "model.json").read_text())["source"]
    assert source["series_instance_uid"] == pseudonym_uid(second)


@pytest.mark.parametrize("needle", [FOLDER, PATIENT_ID])
def test_the_search_finds_a_leak(tmp_path, needle):
    """The search above is not blind: a PNG with the folder in a compressed text
    chunk and a JSON with the ID are both caught."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(1, 1))
    fig.savefig(tmp_path / "a.png", metadata={"Description": f"/data/{needle}/ct" * 200})
    plt.close(fig)
    assert _leaks(tmp_path, [needle]) == ["a.png: " + needle]
