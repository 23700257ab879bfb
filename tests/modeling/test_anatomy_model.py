"""The automatic model of the anatomical phantom (four chambers, great vessels) against its exact epicardium.

``bench/anatomy_accuracy.py`` measures the same at full size (issue 9's targets, mean <= 0.3 mm, p95 <= 0.8
mm, every vessel cut within 5 mm of its origin); this is its sample-size slice, run on every change.  The
truth is the chambers' envelope less the arteries' lumens beyond their valves: the aortic root's lumen
leaves a 35 mm deep well in it, whose floor is the aortic valve.

Measured (seed 0, 1.95 x 1.95 x 2.5 mm voxels): mesh -> truth mean 0.17 mm, p95 0.47 mm; truth -> mesh
p95 3.0 mm; the aortic cap 3.5 mm from the mesh at most.  Before the stub trim spared the surface over a
lumen traced to its valve (session 14) the trim took the well's floor and lidded the well at its rim:
the cap 23.8 mm from the mesh, truth -> mesh p95 9.9 mm (mesh -> truth 0.17 / 0.43 mm: a lid over the
well lies close to the well's rim).  The pulmonary trunk's cap 5.0 mm from the mesh at most: its outflow
tract (12.5-13 mm in outer radius below the valve) is thinner than the bridge opening's 14 mm ball, and
the model was closed inside it, 12.0 mm below the valve, until the tract was given back up to where fat
surrounds the trunk (``modeling.outflow``).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from heartreg.phantom import heart_from_truth, make_phantom
from imaging import load_study
from modeling import build_heart_model


def _measured(out, seed):
    """The human phantom of ``seed`` (sample size) in ``out``, its automatic model and the truth to compare."""
    make_phantom(out, preset="human", size="sample", seed=seed, session=False, overwrite=True)
    truth = json.loads((out / "truth.json").read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        build = build_heart_model(load_study(out / "ct"), cardiac_phase=truth["cardiac_phase"],
                                  cardiac_phase_source="truth")
    model = build.model
    T = np.linalg.inv(model.T_heart_from_patient)
    verts = model.mesh.vertices @ T[:3, :3].T + T[:3, 3]
    heart = heart_from_truth(truth)
    e = truth["anatomy"]["epicardium"]
    pts, _ = heart.sample_surface(e["phase_c"], e["phase_r"])
    samples, _ = trimesh.sample.sample_surface_even(trimesh.Trimesh(verts, model.mesh.faces, process=False),
                                                    200_000, seed=0)
    return dict(truth=truth, build=build, verts=verts, heart=heart, phases=(e["phase_c"], e["phase_r"]),
                pts=pts, back=cKDTree(samples).query(pts)[0])


@pytest.fixture(scope="module")
def anatomy(tmp_path_factory):
    return _measured(tmp_path_factory.mktemp("anatomy_model"), 0)


@pytest.mark.parametrize("seed", [1, 4])
def test_no_chamber_is_lost_on_another_seed(tmp_path, seed):
    """Seed 4 (image phase 0.61): the right atrium's blood lay more than 20 mm from the chambers' cores that
    seed the heart against the liver (``modeling.seed.BLOOD_REACH_MM``), was flooded last and went with the
    liver: 275 ml, 20 % of the true surface farther than 5 mm from the mesh, truth -> mesh p95 24.4 mm (an
    audit).  Reaching 30 mm: 318 ml, 5.4 %, p95 5.2 mm (the rest is the pulmonary trunk's known limit;
    seed 0: 2.8 %, 3.1 mm).

    Seed 1: the liver's front climbed the inferior vena cava's stream into the right atrium (a channel of
    1 ml) and the vessel cut took the atrium: 289 ml, 17.3 %, p95 23.4 mm.  With what the heart encloses in
    its axial planes given back (``modeling.seed._enclosed``): 331 ml, 3.0 %, 3.3 mm."""
    m = _measured(tmp_path, seed)
    assert np.mean(m["back"] > 5.0) <= 0.08 and np.percentile(m["back"], 95) <= 6.5, (
        np.mean(m["back"] > 5.0), np.percentile(m["back"], 95))


def test_mesh_on_the_true_epicardium(anatomy):
    d = np.abs(anatomy["heart"].surface_distance(anatomy["verts"], *anatomy["phases"]))
    assert d.mean() <= 0.25 and np.percentile(d, 95) <= 0.6, (d.mean(), np.percentile(d, 95))
    assert np.percentile(anatomy["back"], 95) <= 3.6, np.percentile(anatomy["back"], 95)


def _cap_gap(anatomy, name):
    """The largest truth -> mesh distance over the true cap of vessel ``name``'s mouth."""
    origins = anatomy["truth"]["anatomy"]["vessel_origins"]
    pts = anatomy["pts"]
    owner = cKDTree([o["centre_patient_mm"] for o in origins]).query(pts)[1]
    index, origin = next((i, o) for i, o in enumerate(origins) if o["name"] == name)
    c, u = np.asarray(origin["centre_patient_mm"]), np.asarray(origin["direction_patient"])
    s = (pts - c) @ u
    r = np.linalg.norm((pts - c) - s[:, None] * u, axis=1)
    cap = (r <= origin["lumen_radius_mm"]) & (np.abs(s) <= 5.0) & (owner == index)
    assert cap.sum() > 100
    return float(anatomy["back"][cap].max())


def test_the_aortic_root_is_cut_at_its_valve(anatomy):
    """The true cap over the aorta's mouth (its valve, at the floor of the root's well) lies on the mesh."""
    # measured 3.5 mm (4.3 without the move onto the blood's edge over the lumen, 23.8 with the well trimmed)
    assert _cap_gap(anatomy, "aorta") <= 4.0
    note = next(n for n in anatomy["build"].notes if n.startswith("surface moved"))
    assert int(note.split(" at the ")[1].split()[0]) > 100, note  # vertices over the lumen cut at its valve


def test_the_outflow_tract_reaches_the_pulmonary_valve(anatomy):
    """The right ventricle's outflow tract, thinner than the bridge opening's ball, is kept up to its valve."""
    # measured 5.0 mm; 12.0 with the tract lost to the opening (the model closed inside it)
    assert _cap_gap(anatomy, "pulmonary_trunk") <= 6.0
    assert any(n.startswith("outflow tract(s) thinner than the bridge opening's ball") for n in anatomy["build"].notes)
