"""Property-based fuzzing of the readers (issue 15): DICOM headers, QRS files,
session folders and model folders, mutated by truncation, random bytes and
extreme values.

The contract for every input: a result, or a HeartregError with a one-line
message -- never another exception type, never a hang.  Each example runs
under a hard time box (SIGALRM) besides hypothesis' deadline, so a hang fails
instead of blocking the suite.  Budget: max_examples modest, ~20 s in all.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hrcore.errors import HeartregError
from imaging import list_series, load_study, read_qrs_file
from modeling.model import read_model
from registration.session import read_session
from tests.heartreg.small_case import small_case, time_box

#: a reader that takes longer than this on a few-kB input is hanging, s.
TIME_BOX_S = 10
FUZZ = settings(
    max_examples=25,
    deadline=None,  # the SIGALRM box below is the hard limit; the loaded CI machine varies
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=True,  # the same examples every run: a failure is reproducible
)

EXTREMES = ["nan", "inf", "-inf", "1e30", "-1e308", "1e-320", "", " ", "0x10", "1,5", "\u00a0", "9" * 400]


def _holds_contract(read, *args):
    """Run a reader: a result, or a one-line HeartregError."""
    with time_box(TIME_BOX_S), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return read(*args)
        except HeartregError as exc:
            msg = str(exc)
            assert msg and "\n" not in msg, msg
            assert "Traceback" not in msg and "np.float64" not in msg, msg
            return exc


def _mutate(data: bytes, how: str, where: float, junk: bytes) -> bytes:
    k = int(where * len(data))
    if how == "truncate":
        return data[:k]
    if how == "overwrite":
        return data[:k] + junk + data[k + len(junk):]
    if how == "insert":
        return data[:k] + junk + data[k:]
    return junk  # "replace": random bytes only


MUTATION = st.tuples(
    st.sampled_from(["truncate", "overwrite", "insert", "replace"]),
    st.floats(0.0, 1.0),
    st.binary(min_size=1, max_size=64),
)


@pytest.fixture(scope="module")
def material(sample_case, tmp_path_factory):
    src, truth = sample_case
    root = tmp_path_factory.mktemp("fuzz")
    model, session = small_case(src, truth, root, grid=20, points=1)
    dicom = sorted((src / "ct").rglob("*"))
    slices = [p for p in dicom if p.is_file() and p.stat().st_size > 10_000][:3]
    return {"model": model, "session": session, "qrs": src / "qrs.csv", "slices": slices}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst) if src.is_dir() else shutil.copy(src, dst)
    return dst


# ------------------------------------------------------------------ QRS files
@FUZZ
@given(mutation=MUTATION, bom=st.booleans())
def test_qrs_reader_mutated_bytes(material, mutation, bom):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "qrs.csv"
        data = _mutate(material["qrs"].read_bytes(), *mutation)
        path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + data)
        _holds_contract(read_qrs_file, path)


@FUZZ
@given(values=st.lists(st.one_of(st.sampled_from(EXTREMES), st.floats().map(repr)), max_size=20))
def test_qrs_reader_extreme_values(values):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "qrs.csv"
        path.write_text("time_s\n" + "\n".join(values) + "\n")
        result = _holds_contract(read_qrs_file, path)
        if not isinstance(result, HeartregError):  # accepted: then finite and increasing
            assert (result[1:] > result[:-1]).all() and abs(result).max() <= 1e6


# ------------------------------------------------------------------ session folders
@FUZZ
@given(target=st.sampled_from(["session.json", "points/point_000.csv", "fiducials.csv"]), mutation=MUTATION)
def test_session_reader_mutated_bytes(material, target, mutation):
    with tempfile.TemporaryDirectory() as tmp:
        session = _copy(material["session"], Path(tmp) / "s")
        file = session / target
        file.write_bytes(_mutate(file.read_bytes(), *mutation))
        _holds_contract(read_session, session)


@FUZZ
@given(row=st.integers(1, 3000), col=st.integers(0, 17), value=st.sampled_from(EXTREMES))
def test_session_reader_extreme_cell(material, row, col, value):
    with tempfile.TemporaryDirectory() as tmp:
        session = _copy(material["session"], Path(tmp) / "s")
        file = session / "points" / "point_000.csv"
        lines = file.read_text().splitlines()
        row = min(row, len(lines) - 1)
        cells = lines[row].split(",")
        cells[col] = value
        lines[row] = ",".join(cells)
        file.write_text("\n".join(lines) + "\n")
        _holds_contract(read_session, session)


JSON_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(), st.text(max_size=10)),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=5), inner, max_size=4)),
    max_leaves=10,
)


@FUZZ
@given(key=st.sampled_from(["format", "version", "units", "sample_rate_hz", "points", "fiducials_file",
                            "frames", "quaternion_order"]), value=JSON_VALUES)
def test_session_reader_wrong_json_values(material, key, value):
    with tempfile.TemporaryDirectory() as tmp:
        session = _copy(material["session"], Path(tmp) / "s")
        meta = json.loads((session / "session.json").read_text())
        meta[key] = value
        (session / "session.json").write_text(json.dumps(meta))
        _holds_contract(read_session, session)


# ------------------------------------------------------------------ model folders
@FUZZ
@given(target=st.sampled_from(["model.json", "heart.ply"]), mutation=MUTATION)
def test_model_reader_mutated_bytes(material, target, mutation):
    with tempfile.TemporaryDirectory() as tmp:
        model = _copy(material["model"], Path(tmp) / "m")
        file = model / target
        file.write_bytes(_mutate(file.read_bytes(), *mutation))
        _holds_contract(read_model, model)


@FUZZ
@given(key=st.sampled_from(["T_heart_from_patient", "cardiac_phase", "fiducials_patient_mm", "ellipses",
                            "frame_fit", "n_faces", "euler_xyz_deg", "source", "parameters"]),
       value=JSON_VALUES)
def test_model_reader_wrong_json_values(material, key, value):
    with tempfile.TemporaryDirectory() as tmp:
        model = _copy(material["model"], Path(tmp) / "m")
        meta = json.loads((model / "model.json").read_text())
        meta[key] = value
        (model / "model.json").write_text(json.dumps(meta))
        _holds_contract(read_model, model)


# ------------------------------------------------------------------ DICOM headers
@FUZZ
@given(mutation=st.tuples(
    st.sampled_from(["truncate", "overwrite", "insert", "replace"]),
    st.floats(0.0, 0.1),  # the header: the first few kB of a slice
    st.binary(min_size=1, max_size=64),
))
def test_dicom_reader_mutated_header(material, mutation):
    with tempfile.TemporaryDirectory() as tmp:
        study = Path(tmp) / "study"
        study.mkdir()
        for k, src in enumerate(material["slices"]):
            data = src.read_bytes()
            (study / f"{k}.dcm").write_bytes(_mutate(data, *mutation) if k == 1 else data)
        _holds_contract(list_series, study)
        _holds_contract(load_study, study)


HEADER_VALUES = ["nan", "inf", "-inf", "1e30", "-1e30", "0", "-1", "1e-30", ""]


@FUZZ
@given(
    keyword=st.sampled_from(["ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "SliceThickness",
                             "RescaleSlope", "RescaleIntercept", "AcquisitionTime", "TriggerTime"]),
    value=st.sampled_from(HEADER_VALUES),
    all_slices=st.booleans(),
)
def test_dicom_reader_extreme_header_values(material, keyword, value, all_slices):
    """A NaN ImagePositionPatient, a zero PixelSpacing, a 1e30 slope ...: refused
    with a message naming the attribute, or read; never a Python error text."""
    import pydicom
    from pydicom import config

    with tempfile.TemporaryDirectory() as tmp:
        study = Path(tmp) / "study"
        study.mkdir()
        for k, src in enumerate(material["slices"]):
            ds = pydicom.dcmread(src)
            if all_slices or k == 1:
                vm = {"ImagePositionPatient": 3, "ImageOrientationPatient": 6, "PixelSpacing": 2}.get(keyword, 1)
                with config.disable_value_validation():
                    if keyword == "AcquisitionTime":
                        ds.AcquisitionTime = value.replace("-", "") or ""
                    else:
                        ds.data_element(keyword).value = ([value] * vm if vm > 1 else value) if keyword in ds \
                            else None
                    ds.save_as(study / f"{k}.dcm")
            else:
                shutil.copy(src, study / f"{k}.dcm")
        result = _holds_contract(load_study, study)
        if isinstance(result, HeartregError):
            assert "cannot convert" not in str(result) and "float64" not in str(result)
