"""modeling.model (HeartModel folder round trip) and modeling.render."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import trimesh

from heartreg.phantom import layout
from modeling.model import (
    HeartModel,
    ModelError,
    make_heart_model,
    read_model,
    write_model,
)
from modeling.fiducials import order_fiducials
from modeling.render import RenderError, render_model_png
from modeling.mesh import check_mesh

from .conftest import heart_of

P = "wood2018-trial1"


@pytest.fixture(scope="module")
def model(phantom_meshes):
    rng = np.random.default_rng(7)
    fid = layout.fiducials_patient_mm()
    return make_heart_model(
        phantom_meshes[P],
        cardiac_phase=0.65,
        cardiac_phase_source="phantom truth",
        fiducials_patient_mm=fid[rng.permutation(len(fid))],
        source={"series_instance_uid": "1.2.826.0.1.3680043.8.498.1", "kind": "phantom"},
        parameters={"target_faces": 20000, "voxel_mm": 1.0},
    )


def test_model_contents(model, phantom_meshes):
    assert np.array_equal(model.fiducials_patient_mm, layout.fiducials_patient_mm())
    assert check_mesh(model.mesh).ok
    # the heart-frame mesh is the patient mesh moved: same volume, centred axis
    assert model.mesh.volume_mm3 == pytest.approx(phantom_meshes[P].volume_mm3, rel=1e-9)
    back = model.mesh_patient()
    assert np.allclose(back.vertices, phantom_meshes[P].vertices, atol=1e-9)
    assert np.allclose(model.T_heart_from_patient[:3, :3] @ heart_of(P).axes_patient[:, 2], [0, 0, 1], atol=0.01)


def test_round_trip(model, tmp_path):
    out = write_model(model, tmp_path / "m")
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["heart.ply", "heart.stl", "model.json", "heart_lps.stl", "HeartToPatient.tfm", "fiducials_ct.mrk.json"]
    )
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no temporary folder left
    again = read_model(out)
    assert again == model
    meta = json.loads((out / "model.json").read_text())
    for key in (
        "T_heart_from_patient", "euler_xyz_deg", "cardiac_phase", "cardiac_phase_source",
        "fiducials_heart_mm", "fiducials_patient_mm", "n_faces", "watertight", "ellipses",
        "parameters", "version", "frame_conventions",
    ):
        assert key in meta
    assert meta["watertight"] is True and meta["n_faces"] == model.mesh.n_faces
    # other tools see the same mesh
    tm = trimesh.load(out / "heart.ply", process=False)
    assert np.array_equal(tm.vertices, model.mesh.vertices)
    assert tm.is_watertight and tm.volume > 0
    import pyvista as pv

    assert np.allclose(pv.read(out / "heart.ply").points, model.mesh.vertices, atol=0)
    stl = trimesh.load(out / "heart.stl")
    assert stl.volume == pytest.approx(model.mesh.volume_mm3, rel=1e-4)
    # heart-frame points mapped back coincide with the patient-frame fiducials
    fh = np.asarray(meta["fiducials_heart_mm"])
    T = np.linalg.inv(np.asarray(meta["T_heart_from_patient"]))
    assert np.allclose(fh @ T[:3, :3].T + T[:3, 3], model.fiducials_patient_mm, atol=1e-9)
    # same bytes every time (determinism), and idempotent on an identical folder
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    write_model(model, out)
    assert before == {p.name: p.read_bytes() for p in out.iterdir()}


def test_refuses_to_overwrite_other_folder(model, tmp_path):
    other = tmp_path / "busy"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    for overwrite in (False, True):  # a folder of other files is never replaced (overwrite=True did, before session 15)
        with pytest.raises(FileExistsError, match="holds other files .* and no model.json"):
            write_model(model, other, overwrite=overwrite)
    assert sorted(p.name for p in other.iterdir()) == ["notes.txt"]
    (tmp_path / "empty").mkdir()
    write_model(model, tmp_path / "empty")
    # an earlier model: refused unless overwrite=True, then replaced
    earlier = tmp_path / "earlier"
    write_model(dataclasses.replace(model, cardiac_phase=0.1), earlier)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_model(model, earlier)
    write_model(model, earlier, overwrite=True)
    assert read_model(earlier) == model


def test_read_errors(model, tmp_path):
    with pytest.raises(ModelError, match="does not exist"):
        read_model(tmp_path / "nowhere")
    out = write_model(model, tmp_path / "m")
    (out / "heart.ply").write_bytes((out / "heart.ply").read_bytes()[:1000])
    with pytest.raises(ModelError, match="truncated"):
        read_model(out)
    out = write_model(model, tmp_path / "m2")
    (out / "model.json").write_text("{not json")
    with pytest.raises(ModelError, match="not readable JSON"):
        read_model(out)
    out = write_model(model, tmp_path / "m3")
    meta = json.loads((out / "model.json").read_text())
    del meta["ellipses"]
    (out / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="incomplete or corrupt"):
        read_model(out)
    del meta["fiducials_heart_mm"]  # was read as none, then said to 'disagree with T_heart_from_patient'
    meta["ellipses"] = json.loads((write_model(model, tmp_path / "m5") / "model.json").read_text())["ellipses"]
    (out / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match=r"incomplete or corrupt \(no field 'fiducials_heart_mm'\)"):
        read_model(out)
    meta["format_version"] = str(meta["format_version"])  # "has format_version '2'; reads version 2" (an audit)
    (out / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match=r"has format_version the text '\d+'; this heartreg reads the number \d+$"):
        read_model(out)
    del meta["format_version"]  # said "has format_version None"
    (out / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match=r"model.json has no format_version; this heartreg reads the number \d+$"):
        read_model(out)
    out = write_model(model, tmp_path / "m4")
    (out / "heart.ply").unlink()
    with pytest.raises(ModelError, match="no heart.ply"):
        read_model(out)


def test_no_patient_data_and_input_checks(model):
    import dataclasses

    with pytest.raises(ValueError, match="not allowed"):
        dataclasses.replace(model, source={"PatientName": "Doe^John"})
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        dataclasses.replace(model, cardiac_phase=1.2)
    with pytest.raises(ValueError, match="cardiac_phase_source"):
        dataclasses.replace(model, cardiac_phase_source="")
    assert isinstance(model, HeartModel)


def test_older_model_with_the_study_uids_reads(model, tmp_path):
    """Models written before the pseudonyms (hrcore.redact.pseudonym_uid) carry the study's UIDs: read as they are."""
    out = write_model(model, tmp_path / "m")
    meta = json.loads((out / "model.json").read_text())
    meta["source"]["study_instance_uid"] = "1.2.826.0.1.3680043.8.498.2"
    (out / "model.json").write_text(json.dumps(meta))
    assert dict(read_model(out).source) == {"series_instance_uid": "1.2.826.0.1.3680043.8.498.1",
                                            "study_instance_uid": "1.2.826.0.1.3680043.8.498.2", "kind": "phantom"}


def test_order_fiducials():
    truth = layout.fiducials_patient_mm()
    shuffled = truth[np.random.default_rng(3).permutation(9)]
    assert np.array_equal(shuffled[order_fiducials(shuffled)], truth)
    with pytest.raises(ValueError, match="equal rows"):
        order_fiducials(truth[:8])


def test_render_png(model, tmp_path, monkeypatch):
    import modeling.render as render

    monkeypatch.setattr(render, "offscreen_available", lambda: False)  # the model picture needs no OpenGL
    from PIL import Image

    path = render_model_png(model, tmp_path / "view.png", size=(600, 400))
    img = np.asarray(Image.open(path).convert("RGB")).astype(float)
    assert img.shape == (400, 600, 3)
    # mesh colour (reddish, blended with white) covers a plausible part of the picture
    reddish = (img[..., 0] - img[..., 2] > 40) & (img[..., 0] > 150)
    assert 0.03 < reddish.mean() < 0.6
    assert img.std() > 10
    # no wasted half: the two views are cut to what they show, so each quarter of the
    # width and the upper and lower halves all carry drawing or text
    ink = np.any(img < 200, axis=2)
    assert all(ink[:, k * 150:(k + 1) * 150].mean() > 0.03 for k in range(4))
    assert ink[:200].mean() > 0.03 and ink[200:].mean() > 0.03
    rows = np.flatnonzero(reddish.any(axis=1))
    assert rows[-1] - rows[0] > 0.5 * img.shape[0]  # the heart fills most of the height
    with pytest.raises(ValueError, match=".png"):
        render_model_png(model, tmp_path / "view.jpg")


def test_render_error_is_clear(model, tmp_path, monkeypatch):
    import modeling.render as render

    monkeypatch.setattr(render, "offscreen_available", lambda: False)
    with pytest.raises(RenderError, match="libosmesa6"):  # a VTK drawing (modeling.render.render_panel)
        render.render_png(lambda size: np.zeros((size[1], size[0], 3), np.uint8), tmp_path / "v.png",
                          size=(100, 100), what="a view")
    assert not (tmp_path / "v.png").exists()


def test_slice_phases_round_trip_and_older_files(model, tmp_path):
    import dataclasses

    from modeling.slice_phases import SlicePhases

    slices = SlicePhases(-40.0 + 2.5 * np.arange(8), [0.63] * 4 + [0.49] * 4, [0.0, 0.0, 1.0])
    with_slices = dataclasses.replace(model, slice_phases=slices)
    assert with_slices != model and model.slice_phases is None
    out = write_model(with_slices, tmp_path / "m")
    meta = json.loads((out / "model.json").read_text())
    assert meta["slice_phases"]["phases"] == [0.63] * 4 + [0.49] * 4
    assert read_model(out) == with_slices
    # a model.json written before the field (or by a CT without a slice clock) reads as None
    del meta["slice_phases"]
    (out / "model.json").write_text(json.dumps(meta))
    assert read_model(out).slice_phases is None
    meta["slice_phases"] = {"positions_mm": [0.0, 1.0], "phases": [0.5]}
    (out / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="slice_phases|normal_patient|same shape"):
        read_model(out)
    with pytest.raises(TypeError, match="slice_phases"):
        dataclasses.replace(model, slice_phases={"phases": [0.5]})
