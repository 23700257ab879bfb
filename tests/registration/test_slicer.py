"""Files for 3D Slicer: markups against Slicer's schema, ``.tfm`` files read by
SimpleITK (an independent reader), the LPS model against the heart-frame model.

The case is the shared sample phantom's session registered to the phantom's
analytic heart (as in ``test_pipeline.py``), written and read back as a model
folder, so every file here is the one ``heartreg register`` writes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from modeling.model import read_model
from modeling.slicer import (
    SlicerFileError,
    read_itk_transform,
    read_markups,
    write_itk_transform,
    write_markups,
)
from registration.pipeline import register_session
from registration.report import write_registration
from registration.session import read_session
from tests.heartreg.small_case import small_case

SCHEMA = Path("/work/shared/slicer/markups-schema-v1.0.3.json")
EXAMPLE_TFM = Path("/work/shared/slicer/example-affine.tfm")


#: a part of the shared sample session and a coarse sweep keep the two registrations
#: (CSV and PLUS) quick; the files' checks do not depend on the registration's accuracy.
N_POINTS = 12
PHASE_STEP = 0.05


@pytest.fixture(scope="module")
def registered(sample_case, tmp_path_factory):
    case, truth = sample_case
    root = tmp_path_factory.mktemp("slicer")
    model_dir, session_dir = small_case(case, truth, root, grid=60, points=N_POINTS)
    model = read_model(model_dir)
    session = read_session(session_dir)
    result = register_session(model, session, phase_step=PHASE_STEP)
    out = root / "registration"
    paths = write_registration(result, out, model=model, view=False, fiducials_probe_mm=session.fiducials_probe_mm)
    return {"model_dir": model_dir, "model": model, "session": session, "result": result, "out": out,
            "paths": paths}


def _sitk_map(path, points):
    sitk = pytest.importorskip("SimpleITK")
    tx = sitk.ReadTransform(str(path))
    return np.array([tx.TransformPoint([float(x) for x in p]) for p in points])


def test_markups_validate_against_slicers_schema(registered):
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SCHEMA.read_text())
    files = [registered["model_dir"] / "fiducials_ct.mrk.json",
             registered["out"] / "fiducials_touched.mrk.json",
             registered["out"] / "points_registered.mrk.json"]
    for f in files:
        doc = json.loads(f.read_text())
        jsonschema.validate(doc, schema)
        m = doc["markups"][0]
        assert m["type"] == "Fiducial" and m["coordinateSystem"] == "LPS" and m["coordinateUnits"] == "mm"
        assert all(cp["positionStatus"] == "defined" for cp in m["controlPoints"])
    # what is written is read back, in the same order
    ct = read_markups(files[0])
    np.testing.assert_array_equal(ct.points_lps_mm, registered["model"].fiducials_patient_mm)
    assert ct.labels == tuple(f"CT-{k}" for k in range(1, 10))
    touched = read_markups(files[1])
    np.testing.assert_array_equal(touched.points_lps_mm, registered["session"].fiducials_probe_mm)
    pts = read_markups(files[2])
    np.testing.assert_array_equal(pts.points_lps_mm, registered["result"].points_probe_mm)


def test_tfm_read_by_simpleitk_moves_ct_fiducials_onto_touched_ones(registered):
    result, model, session = registered["result"], registered["model"], registered["session"]
    ct = read_markups(registered["model_dir"] / "fiducials_ct.mrk.json").points_lps_mm
    touched = read_markups(registered["out"] / "fiducials_touched.mrk.json").points_lps_mm
    # ITK resamples: the file of node ProbeToPatient maps patient (CT) points to probe points.
    moved = _sitk_map(registered["out"] / "ProbeToPatient_fiducial.tfm", ct)
    d = np.linalg.norm(moved - touched, axis=1)
    # T0 is the least-squares fit of exactly these pairs: its RMS is the FRE and each
    # residual is the result's (to float64 rounding of the repr-written parameters)
    assert np.sqrt(np.mean(d**2)) <= result.fre_mm + 1e-9
    np.testing.assert_allclose(d, result.fiducial_residuals_mm, atol=1e-9)
    # the final registration (the phantom's staples shifted on the skin: they need not
    # align): SimpleITK maps through T_probe_from_patient = inv(T_patient_from_heart @ T)
    T_probe_from_patient = np.linalg.inv(model.T_patient_from_heart @ result.T_heart_from_probe)
    np.testing.assert_allclose(_sitk_map(registered["out"] / "ProbeToPatient.tfm", ct),
                               ct @ T_probe_from_patient[:3, :3].T + T_probe_from_patient[:3, 3], atol=1e-9)
    # every transform of the result, as heartreg reads it back: the to-parent matrix
    for suffix, T in (("", result.T_heart_from_probe), ("_fiducial", result.T0_heart_from_probe),
                      ("_static", result.static.T_static_heart_from_probe)):
        np.testing.assert_allclose(read_itk_transform(registered["out"] / f"ProbeToHeart{suffix}.tfm"), T,
                                   atol=1e-12)
        np.testing.assert_allclose(read_itk_transform(registered["out"] / f"ProbeToPatient{suffix}.tfm"),
                                   model.T_patient_from_heart @ T, atol=1e-9)
    assert session.fiducials_probe_mm.shape == (9, 3)


def test_lps_model_agrees_with_heart_frame_model(registered):
    trimesh = pytest.importorskip("trimesh")
    model_dir, model = registered["model_dir"], registered["model"]
    raw = (model_dir / "heart_lps.stl").read_bytes()
    assert b"SPACE=LPS" in raw[:80] and not raw.startswith(b"solid")
    lps = trimesh.load(model_dir / "heart_lps.stl", process=False)
    heart = model.mesh  # heart.ply, float64
    # triangle by triangle: the LPS mesh mapped by T_heart_from_patient is the heart-frame mesh
    tri_lps = np.asarray(lps.triangles)
    T = model.T_heart_from_patient
    tri_heart = tri_lps @ T[:3, :3].T + T[:3, 3]
    # STL stores float32: ~1e-5 relative, 2e-3 mm at 150 mm from the origin
    np.testing.assert_allclose(tri_heart, heart.vertices[heart.faces], atol=5e-3)
    # the model's node file: SimpleITK (resampling direction) maps patient points into the heart frame
    sample = tri_lps[::50, 0]
    np.testing.assert_allclose(_sitk_map(model_dir / "HeartToPatient.tfm", sample),
                               sample @ T[:3, :3].T + T[:3, 3], atol=1e-9)


def test_ras_markups_and_slicers_example_transform(tmp_path):
    # a file Slicer saved in RAS reads back in LPS (x and y negated)
    doc = {"@schema": "x", "markups": [{"type": "Fiducial", "coordinateSystem": "RAS",
                                         "controlPoints": [{"label": "a", "position": [1.0, 2.0, 3.0]}]}]}
    f = tmp_path / "ras.mrk.json"
    f.write_text(json.dumps(doc))
    np.testing.assert_array_equal(read_markups(f).points_lps_mm, [[-1.0, -2.0, 3.0]])
    # points listed but not placed (positionStatus undefined or preview, with or without a position) are not read
    doc["markups"][0]["controlPoints"] = [{"label": "u", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"},
                                          {"label": "p", "positionStatus": "preview"},
                                          {"label": "a", "position": [1.0, 2.0, 3.0], "positionStatus": "defined"}]
    f.write_text(json.dumps(doc))
    assert read_markups(f).labels == ("a",)
    # Slicer's example: a 30 deg rotation about x; its to-parent is the stored matrix's inverse
    T = read_itk_transform(EXAMPLE_TFM)
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, c, s], [0, -s, c]], atol=1e-12)
    # round trip of a centred transform written by ITK's convention (x -> A (x - c) + c + t)
    g = tmp_path / "centred.tfm"
    g.write_text("#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
                 "Parameters: 0 -1 0 1 0 0 0 0 1 1 2 3\nFixedParameters: 10 0 0\n")
    stored = np.linalg.inv(read_itk_transform(g))
    np.testing.assert_allclose(stored[:3, 3], _sitk_map(g, [[0.0, 0.0, 0.0]])[0], atol=1e-12)


def test_skipped_points_of_a_slicer_list_are_not_read(tmp_path):
    # Slicer 5 writes a point skipped while placing as positionStatus "missing" with "position": ""
    # (and an unplaced one as "undefined", also with ""); the placed point is what --seed takes
    orientation = [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0]
    points = [{"id": str(k), "label": label, "description": "", "associatedNodeID": "", "position": position,
               "orientation": orientation, "selected": True, "locked": False, "visibility": True,
               "positionStatus": status}
              for k, (label, position, status) in enumerate([("skipped", "", "missing"),
                                                             ("placed", [-517.25, -0.5, 122.75], "defined"),
                                                             ("editing", "", "undefined")], start=1)]
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
                      "Resources/Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": "Fiducial", "coordinateSystem": "RAS", "coordinateUnits": "mm",
                        "controlPoints": points}]}
    f = tmp_path / "seed.mrk.json"
    f.write_text(json.dumps(doc))
    m = read_markups(f)
    assert m.labels == ("placed",)
    np.testing.assert_array_equal(m.points_lps_mm, [[517.25, 0.5, 122.75]])


def test_bad_slicer_files(tmp_path):
    f = tmp_path / "two.tfm"
    f.write_text("#Insight Transform File V1.0\n#Transform 0\nTransform: CompositeTransform_double_3_3\n"
                 "#Transform 1\nTransform: AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 1 0 0 0\n"
                 "FixedParameters: 0 0 0\n")
    with pytest.raises(SlicerFileError, match="holds 2 transforms"):
        read_itk_transform(f)
    f.write_text("#Insight Transform File V1.0\nTransform: BSplineTransform_double_3_3\nParameters: 1\n")
    with pytest.raises(SlicerFileError, match="not a 3-D affine"):
        read_itk_transform(f)
    f.write_text("hello")
    with pytest.raises(SlicerFileError, match="not an ITK transform file"):
        read_itk_transform(f)
    with pytest.raises(ValueError, match="rigid"):
        write_itk_transform(tmp_path / "s.tfm", np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        write_markups(tmp_path / "a.mrk.json", np.zeros((3, 2)), labels="abc", name="x")
    with pytest.raises(ValueError, match="must end in .mrk.json"):
        write_markups(tmp_path / "a.json", np.zeros((1, 3)), labels="a", name="x")
    g = tmp_path / "b.mrk.json"
    g.write_text('{"markups": [{"type": "Line"}]}')
    with pytest.raises(SlicerFileError, match="no fiducial list"):
        read_markups(g)


def test_plus_session_gives_the_same_registration_as_the_csv_session(registered, tmp_path):
    """The phantom's PLUS sequence file, read back, gives registration.json byte for
    byte as the CSV session, apart from the line that names the pose source."""
    from heartreg.phantom.plus import write_plus_session

    plus_dir = write_plus_session(registered["session"].path, tmp_path / "session_plus")
    session = read_session(plus_dir)
    assert session.pose_source == "PLUS sequence" and not session.notes
    for a, b in zip(registered["session"].points, session.points):
        np.testing.assert_array_equal(a.T_probe_from_robot, b.T_probe_from_robot)  # to the last bit
    result = register_session(registered["model"], session, phase_step=PHASE_STEP)
    write_registration(result, tmp_path / "reg", model=registered["model"], view=False)
    csv_lines = (registered["out"] / "registration.json").read_text().splitlines()
    plus_lines = (tmp_path / "reg" / "registration.json").read_text().splitlines()
    differ = [(a, b) for a, b in zip(csv_lines, plus_lines) if a != b]
    assert len(csv_lines) == len(plus_lines)
    assert differ == [('  "session_pose_source": "csv"', '  "session_pose_source": "PLUS sequence"')]


def test_slicers_legacy_fcsv_point_lists_are_read(tmp_path):
    """``.fcsv``, the point list Slicer 4 wrote (and 5 still writes on request), found in many labs' datasets:
    read for ``--seed`` and ``--fiducials`` beside ``.mrk.json``.  Slicer 4.4 numbered the coordinate system
    (0 RAS, 1 LPS), 4.11 names it, 5 adds each point's status and 'auto-created' flag after the named
    columns (a point listed but not placed has status 0, 1 or 3)."""
    columns = "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
    files = {
        "v44.fcsv": "# Markups fiducial file version = 4.4\n# CoordinateSystem = 0\n" + columns
        + "vtkMRMLMarkupsFiducialNode_0,10.5,-20,30,0,0,0,1,1,1,0,F-1,,vtkMRMLScalarVolumeNode1\n"
        + "vtkMRMLMarkupsFiducialNode_1,1,2,3,0,0,0,1,1,1,0,F-2,a note,\n",
        "v411.fcsv": "# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n" + columns
        + "1,-10.5,20,30,0,0,0,1,1,1,0,F-1,,\n2,-1,-2,3,0,0,0,1,1,1,0,F-2,a note,\n",
        "v54.fcsv": "# Markups fiducial file version = 5.4\n# CoordinateSystem = RAS\n" + columns
        + "1,10.5,-20,30,0,0,0,1,1,1,0,F-1,,,2,0\n9,7,7,7,0,0,0,1,1,1,0,F-9,,,3,0\n"
        + "2,1,2,3,0,0,0,1,1,1,0,F-2,a note,,2,0\n",
        # a label or note with commas is quoted (a review: a plain split shifted the columns, and the Slicer 5
        # status read off the wrong cell left the point out without a word)
        "quoted.fcsv": "# Markups fiducial file version = 5.6\n# CoordinateSystem = LPS\n" + columns
        + '1,-10.5,20,30,0,0,0,1,1,1,0,"F-1, row 1",,,2,0\n2,-1,-2,3,0,0,0,1,1,1,0,F-2,"a note, ""quoted""",,2,0\n',
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        m = read_markups(tmp_path / name)
        np.testing.assert_array_equal(m.points_lps_mm, [[-10.5, 20.0, 30.0], [-1.0, -2.0, 3.0]]), name
        if name == "quoted.fcsv":
            assert m.labels == ("F-1, row 1", "F-2") and m.descriptions == ("", 'a note, "quoted"')
        else:
            assert m.labels == ("F-1", "F-2") and m.descriptions == ("", "a note"), name
    (tmp_path / "bad.fcsv").write_text("# CoordinateSystem = LPS\n1,abc,2,3,0,0,0,1,1,1,0,F-1,,\n")
    with pytest.raises(SlicerFileError, match=r"bad.fcsv: line 2 has no x, y, z of finite numbers"):
        read_markups(tmp_path / "bad.fcsv")
    (tmp_path / "ijk.fcsv").write_text("# CoordinateSystem = 2\n1,1,2,3,0,0,0,1,1,1,0,F-1,,\n")
    with pytest.raises(SlicerFileError, match="CoordinateSystem '2' is neither LPS nor RAS"):
        read_markups(tmp_path / "ijk.fcsv")
    with pytest.raises(SlicerFileError, match="does not exist"):
        read_markups(tmp_path / "none.fcsv")
