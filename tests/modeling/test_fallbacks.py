"""A step that cannot do its job falls back, warns, and says so in model.json.

The failures are forced (a trim that leaves an open surface, a fiducial search
that finds no air around the body) on the phantom's sample CT, so the
fallbacks are tested whatever the data; the real-CT tests meet the same
fallbacks on real data (no markers, unknown phase).
"""

from __future__ import annotations

import numpy as np
import pytest

import modeling.build
import modeling.fiducials
from imaging import load_study
from modeling import FiducialError, MeshError, find_fiducials, segment_heart
from modeling.build import ModelingWarning, build_heart_model


def _fail(exc):
    def raiser(*args, **kwargs):
        raise exc

    return raiser


def test_trim_and_fiducial_search_fall_back(sample_case, monkeypatch):
    """Also: a model without fiducials says it cannot be registered (it said 'registration will need them from
    elsewhere', and register refuses it); a frame fit that did not converge is a warning (it was none)."""
    import modeling.model

    case, truth = sample_case
    volume = load_study(case / "ct")
    monkeypatch.setattr(modeling.build, "trim_vessel_stubs", _fail(MeshError("left an open surface")))
    monkeypatch.setattr(modeling.fiducials, "find_fiducials", _fail(FiducialError("no air around the body")))
    fit = modeling.model.fit_heart_frame
    monkeypatch.setattr(modeling.model, "fit_heart_frame", lambda *a, **k: fit(*a, **k, max_iterations=1))
    with pytest.warns(ModelingWarning) as caught:
        build = build_heart_model(volume, cardiac_phase=truth["cardiac_phase"], cardiac_phase_source="truth",
                                  expected_fiducials="auto", target_faces=4000)
    messages = [str(w.message) for w in caught]
    assert any(m.startswith("vessel stub trim skipped, surface kept as segmented: left an open surface") for m in messages)
    assert any(m.startswith("fiducial search skipped: no air around the body; the model has no fiducials and "
                            "cannot be registered ('heartreg register' starts from the CT's skin staples")
               for m in messages)
    assert not build.model.frame.converged
    assert any(m.startswith("the heart frame's fit did not converge (1 iterations") and "unreliable" in m
               for m in messages)
    assert set(messages) <= set(build.model.parameters["warnings"])
    assert len(build.model.fiducials_patient_mm) == 0 and build.model.mesh.n_faces > 0
    # a count asked for is insisted on: no fallback
    with pytest.raises(FiducialError, match="no air around the body"):
        build_heart_model(volume, cardiac_phase=truth["cardiac_phase"], cardiac_phase_source="truth",
                          expected_fiducials=9, target_faces=4000)


def test_fiducials_given_in_a_markups_file_are_taken_as_they_are(sample_case, sample_outputs, tmp_path, capsys):
    """The model's own ``fiducials_ct.mrk.json``, checked and corrected in 3D Slicer (one staple moved 2 mm, the
    file saved in RAS), given back with ``--fiducials FILE``: the model carries those points as they are, not a
    search's (a CT whose staples the search misses, or whose markers are no metal, had no way to a model that
    can be registered).  The markups file lies inside the model folder: the command refuses to replace it."""
    import json

    from heartreg.cli import main
    from modeling.model import read_model

    case, _ = sample_case
    found = read_model(sample_outputs / "model").fiducials_patient_mm
    doc = json.loads((sample_outputs / "model" / "fiducials_ct.mrk.json").read_text())
    markups = doc["markups"][0]
    assert markups["coordinateSystem"] == "LPS"
    markups["coordinateSystem"] = "RAS"
    for cp in markups["controlPoints"]:
        cp["position"] = [-cp["position"][0], -cp["position"][1], cp["position"][2]]
    markups["controlPoints"][4]["position"][2] += 2.0  # the middle staple, 2 mm superior
    given = tmp_path / "staples.mrk.json"
    given.write_text(json.dumps(doc))
    out = tmp_path / "model"
    assert main(["model", str(case / "ct"), "-o", str(out), "--fiducials", str(given), "--faces", "4000", "-q"]) == 0
    assert "fiducials: 9 given (patient LPS), not searched" in capsys.readouterr().out
    model = read_model(out)
    expected = found.copy()
    expected[4, 2] += 2.0
    np.testing.assert_allclose(model.fiducials_patient_mm, expected, atol=1e-6)
    assert model.parameters["fiducials_given"] is True
    inside = out / "staples.mrk.json"
    inside.write_text(given.read_text())
    assert main(["model", str(case / "ct"), "-o", str(out), "--overwrite", "--fiducials", str(inside), "-q"]) == 1
    assert "contains the input" in capsys.readouterr().err and inside.is_file()
    # points in another frame (a tracker's, 600 mm away) are no skin markers of this CT
    for cp in markups["controlPoints"]:
        cp["position"][2] += 600.0
    given.write_text(json.dumps(doc))
    assert main(["model", str(case / "ct"), "-o", str(tmp_path / "far"), "--fiducials", str(given), "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "given fiducial 1 (" in err[0] and "lies outside the CT (9 of 9 such)" in err[0], err


def test_vessel_cut_skipped_when_nothing_is_heart_thick():
    """A 50 mm ball of tissue around a contrast pool: thinner than the heart ball asked for."""
    k, j, i = np.mgrid[:40, :40, :40]
    r = np.sqrt((k - 20) ** 2 + (j - 20) ** 2 + (i - 20) ** 2) * 1.5  # mm, 1.5 mm voxels
    hu = np.where(r < 25, 60, -1000).astype(np.int16)
    hu[r < 15] = 400
    T = np.diag([1.5, 1.5, 1.5, 1.0])
    seg = segment_heart(hu, T, heart_radius_mm=30.0, min_volume_ml=10.0)
    assert any(n.startswith("vessel cut skipped: no part of the heart region is thicker than 60 mm") for n in seg.notes)
    assert seg.volume_ml == pytest.approx(4 / 3 * np.pi * 25**3 / 1000, rel=0.1)  # the ball, kept whole


def test_only_markers_on_the_skin_are_fiducials():
    """A synthetic chest (a 30 mm radius cylinder of soft tissue, 1 mm voxels):
    a staple on the skin is found; metal floating 5 mm above the skin and a
    bone-like rod reaching the skin from inside are not."""
    k, j, i = np.mgrid[:60, :80, :80]
    hu = np.where((j - 40) ** 2 + (i - 40) ** 2 < 30**2, 40, -1000).astype(np.int16)
    hu[30, 10:12, 38:44] = 3000  # staple: 6 x 2 x 1 mm on the anterior skin (LPS y = j: low j is anterior)
    hu[45, 4:6, 38:44] = 3000  # the same metal 5 mm above the skin, in the air
    hu[14:17, 10:35, 39:42] = 1200  # a rod from the skin 25 mm into the body
    T = np.eye(4)
    found = find_fiducials(hu, T, expected=None)
    np.testing.assert_allclose(found.centres_patient_mm, [[40.5, 10.5, 30.0]], atol=0.5)  # the staple's centroid
    notes = " ".join(found.notes)
    assert "not touching the body (it lies in the air)" in notes
    assert "dense tissue continues beneath the skin" in notes
    with pytest.raises(FiducialError, match=r"found 1 metal marker\(s\) on the skin, expected 9"):
        find_fiducials(hu, T, expected=9)


def test_a_decimation_that_breaks_the_surface_keeps_more_faces(sample_case, monkeypatch):
    """Where decimating to the faces asked for breaks the surface, the model keeps twice as many (and so on),
    and says so."""
    case, truth = sample_case
    volume = load_study(case / "ct")
    real = modeling.build.decimate

    def decimate(mesh, target_faces):
        if target_faces < 8000:
            raise MeshError(f"decimation to {target_faces} faces broke the surface")
        return real(mesh, target_faces)

    monkeypatch.setattr(modeling.build, "decimate", decimate)
    with pytest.warns(ModelingWarning, match="decimation to 4000 faces broke the surface; the model keeps"):
        build = build_heart_model(volume, cardiac_phase=truth["cardiac_phase"], cardiac_phase_source="truth",
                                  expected_fiducials="auto", target_faces=4000)
    assert 7000 < build.model.mesh.n_faces <= 8000
    assert any(w.startswith("decimation to 4000 faces broke the surface") for w in build.model.parameters["warnings"])
