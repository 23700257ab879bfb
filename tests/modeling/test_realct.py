"""The model command on a real chest CT (``shared/realct``, README there).

The CT (an ungated aortic CTA, 1.5 mm voxels, cropped around the heart, a stent
graft in the descending aorta, no skin markers) is written by the test as a
plain DICOM series and also read as NIfTI.  Reference: ``heart.nii.gz``,
TotalSegmentator's heart on a grid shifted by whole voxels (resampled through
both affines, exactly).  Measured facts about that reference, which bound what
any epicardial surface can score against it:

- it *includes* the pulmonary trunk and its branches (91 % of
  ``pulmonary_artery.nii.gz``, 44 ml of its 669 ml), which heartreg cuts at the
  pulmonary valve as the issue asks: ~6 % of the reference is therefore missed
  by design (until session 11 the model kept the trunk up to its bifurcation,
  17 ml of ``pulmonary_artery.nii.gz``; see the last point below);
- its boundary lies about one voxel inside the myocardium's outer edge.  HU
  profile across it (median of each 6-connected voxel layer, pulmonary artery
  left out): inside -2: 411, -1: 241, outside +1: 104 (myocardium), +2: 35,
  +3: 6.  The automatic mask's own layers: -2: 146, -1: 91, +1: 0, +2: 3 --
  its edge is at the fat/myocardium half-way level (``hu_low`` 0 HU, fat about
  -100, myocardium about 100), i.e. on the epicardium; the reference's edge is
  one layer further in.  Of the 118 ml the automatic mask has outside the
  reference, 53 ml lie in the first outside layer and 79 ml within two; the
  rest is the aortic root (inside the heart's envelope, left out of the
  reference) and the tissue around the left atrium's roof.  Inside the
  reference and not in the automatic mask: 72 ml, 40 of them pulmonary artery,
  most of the rest the right atrium's roof and the right ventricular outflow
  tract lost with the superior vena cava and the pulmonary trunk (the vessel
  cut decides per branch).

Further measurements (session seg9, voxel masks on the CT grid, ``overlap``):

- the reference behaves like the usual whole-heart atlas convention (chamber
  blood pools plus the left-ventricular myocardium; inferred from its
  profiles, not documented by its maker): where the heart borders fat, HU profiles along the reference's
  outward normal give, at the left-ventricular wall, 96 / 15 / -37 HU at
  0 / +1 / +2 voxels (the fat/myocardium half-way level ~20 HU lies about half
  a voxel outside its edge), but at thin walls (right ventricle, atria) 470 /
  196 / 43 / -32 HU at 0 / +1 / +2 / +3 voxels: its edge is the blood
  pool's, the 2-4 mm wall is left out.  An epicardial surface includes that
  wall;
- with the pulmonary artery cut at its valve no surface can meet the issue's
  p95 against this reference: the reference less its own pulmonary artery
  (dilated by 2 voxels, opened, largest part; "r2") scores Dice 0.946, MSD
  2.2 mm, p95 19.5 mm against the whole reference; less the artery and one
  voxel of its wall, largest part (session 29): 0.962 / 1.68 / 16.8 mm, the
  set difference alone 0.966 / 0.21 / 1.5 mm only because it keeps the
  artery's wall as a one-voxel sleeve.  Against r2, the reference
  grown by one or two layers of its wall tissue (> 0 HU, < 250 HU) still
  scores Dice 0.95-0.98, MSD 0.5-1.05 mm, p95 1.5-3 mm: the targets are
  reachable against the reference less its pulmonary artery;
- of today's automatic mask's 136 ml outside r2 (22 ml inside r2 missed),
  removing only the contrast-blood part (vessel lumens: the pulmonary-vein
  antrum above the left atrium, the aortic root, the inferior vena cava) and
  2 voxels around it gives Dice 0.948, MSD 1.30 mm, p95 5.6 mm against r2;
  removing too the non-blood part deeper than one voxel and adding the
  missed blood (right atrial roof, outflow tract) gives 0.985 / 0.45 / 1.5.
  The vessel lumens, not the boundary's HU level, are the first error;
- a wave-front vessel tracer (contrast blood > 200 HU on a 3 mm grid,
  fronts started where blood leaves the field of view, a front frozen where
  its inscribed radius exceeds ``growth`` times its last 20 mm's median)
  is brittle here: growth 1.4-1.5 traces the aortae, pulmonary trunk and
  caval/pulmonary veins (200 ml, no chamber flooded) but stops at the
  sinotubular junction: about 25 mm of aortic root (CT slices 51-67) stay
  below its end; 1.6 floods the chambers (686 ml).
  Of what 1.4-1.5 traces, 16 ml lie in the automatic mask outside r2 and
  14 ml inside it; removing it with the tissue closer to it than to the
  remaining blood (up to 6 mm) leaves Dice 0.885 against ``ref & ~pa``.  Softening the
  current cut (``vessel_root_mm`` 6 or 10, ``heart_radius_mm`` 18 or 22)
  trades the right atrial roof against the aortic root: full reference
  Dice 0.861-0.863, ``ref & ~pa`` 0.875-0.885, no gain either (without the lobe trace
  below; with it, 10 mm gains);
- where that wrong lumen lies: a watershed of the blood pool's distance
  map (peaks >= 4 mm, 7.5 mm apart) splits it into lobes.  The aortic root
  is a lobe of its own (inscribed radius 14 mm) between the ascending aorta
  (saddle 13 mm, the sinotubular junction) and the left ventricle (saddle
  9 mm, the annulus): a valve-level cut exists, but the root holds only
  8 ml of the automatic mask's 55 ml of wrong blood, and removing it with
  up to 3 mm of its wall gains Dice 0.885 -> 0.890 against ``ref & ~pa``.
  30 ml lie in the left atrium's own lobe (radius 24 mm; its upper part,
  slices 67-78, where the pulmonary veins enter) and 8 ml in the right
  atrium's: the reference cuts these atria where no narrowing of the blood
  pool marks a vessel's mouth.  Most of the oracle gain above is that
  atrial roof and 81 ml of non-blood tissue (mostly thin walls).
- that lobe trace is now the segmentation's last step
  (``modeling.greatvessels``: lobes at the field of view's edge no wider
  than 20 mm, continued across saddles >= 0.8 of the narrower radius into
  lobes at most 1.1 times the narrowest on the way, removed with 3 mm of
  wall), and the tissue-level cut keeps 10 mm of the vessels instead of 3
  (it took the right atrium's roof and the outflow tract).  Model mesh
  through ``heartreg model``, before -> after: full reference Dice
  0.862 -> 0.879, MSD 4.0 -> 3.3 mm, p95 14.2 -> 10.6 mm; ``ref & ~pa``
  0.884 -> 0.892, 3.21 -> 2.76 mm, 9.2 -> 7.5 mm; frame 12.6 -> 11.0 deg
  from the mask model's (the trace alone, with the 3 mm cut: 0.869 / 3.8 /
  14.2 and 0.892 / 2.98 / 8.6, 12.9 deg).  On the masks the trace holds
  for widen ratios 1.1-1.35, saddle ratios 0.7-0.9, peak spacings 6-10 mm
  (no chamber is reached; 1.15-1.25 take 30 ml more lumen: ``ref & ~pa``
  0.895 on the mask, but the full reference's p95 rises to 15 mm).
- where the 0.948 oracle's gain lies (session seg9c, segmentation mask,
  ``ref & ~pa``): of the automatic mask's blood outside it, most lies in
  the reference's first two layers (its edge sits inside the blood pool
  at thin walls).  Removing the outside blood only where it lies deeper than
  d voxels outside the reference (then 2 voxels around, outside it):
  d = 0: 0.955 / 1.15 / 5.2; 1: 0.933 / 1.71 / 5.6; 2: 0.917 / 2.16 / 6.0;
  3: 0.907 / 2.36 / 6.2; 4: 0.900 / 2.49 / 6.2 (today 0.892 / 2.61 / 7.35).
  So the real vessel lumens (deeper than 4.5 mm) are worth ~0.015 Dice and
  ~1 mm of p95; the rest is the reference's convention at thin walls.  Of
  the left atrium's lobe (radius 24 mm, 156 ml) 43 ml lie outside the
  reference: 16 ml within 3 mm of its edge, 18 ml deeper than 6 mm (the
  pulmonary veins' antrum: a funnel with no distance-map peak of its own,
  so the watershed gives it to the atrium).  Tissue of the mask outside the
  reference is no farther from the chambers' blood than tissue inside
  (left ventricular wall up to 10 mm): no wall-thickness cut separates them;
  the vessel walls' ``wall_mm`` 3 -> 9 gains 0.001;
- tried and not kept (seg9c): a funnel rule (blood of a lobe wider than any
  vessel, in no ball of 0.4-0.6 times its radius, reached from the traced
  lumen, is a vein's mouth) gives the model mesh full reference 0.879 ->
  0.884, MSD 3.32 -> 3.24 mm, p95 10.6 -> 10.6; ``ref & ~pa`` 0.892 ->
  0.898, 2.76 -> 2.64 mm, 7.5 -> 7.0 mm (stable for ratios 0.4-0.6), but it
  takes 2 % of the spheroid phantom's heart near its vessels
  (test_build's volume bound; within reach of the lumen only, 2.0 %): on
  the branch seg9c as commits e1bc161 and 04261fa, reverted.  In that
  phantom (its vessels start inside the blood pool and leave through the
  base cap) the rule reaches the pool's cap from the pulmonary trunk: of
  the 7.5 ml it removes, 7.2 ml lie inside the true epicardium (6.3 ml
  deeper than 2 mm), i.e. it cuts chamber blood with no valve or junction;
  keeping only the funnel deeper than 3 / 6 mm beyond the chamber's thick
  body, or thicker than 3-6 mm, spares the phantom (mask -1.1 / -0.5 %)
  but loses the real CT's gain too (mask ``ref & ~pa`` 0.894 / 0.893):
  what the rule gains here is mostly shallow, the atrium's rim next to the
  veins, not a deep antrum.  A gentler tissue-level cut with the trace
  (``vessel_root_mm`` 15 / 20 / 30) raises the full reference (mask Dice
  0.884 / 0.888 / 0.889, p95 9.0 / 8.5 / 8.7 mm: it keeps the pulmonary
  trunk's root the reference holds) and lowers ``ref & ~pa`` (0.889 /
  0.885 / 0.881): the missed blood inside ``ref & ~pa`` (14 ml: the right
  atrium's roof at the superior vena cava, the outflow tract, 3 ml low
  behind the right atrium) goes with the tissue-level steps, before the trace.  Murray's law
  at a branching (the trunk as wide as the cube root of its branches'
  cubed radii) with ``widen_ratio`` 1.1 traces nothing more here; 1.2
  floods 50 ml of chamber, 1.3 150 ml (the pulmonary branches taper, the
  trunk is 1.1-1.3 times wider than the lobe feeding it);
- the branch rule (session 9): a branch of the heart body is now cut where
  its thick (atrial) stretch ends, not at its first thin shell, and kept
  whole when it rounds off within 25 mm of that stretch (a right atrium
  without contrast).  Here the one cut branch (the right atrium's roof and
  the superior vena cava: 16.8 / 17.3 / 17.9 mm thick in its first three
  shells) is cut 15 mm from the body instead of 10: the model's mesh
  0.879 / 3.3 / 10.6 -> 0.884 / 3.2 / 9.6 against the reference, ``ref &
  ~pa`` 0.892 / 2.76 / 7.5 -> 0.889 / 2.73 / 7.5, the frame 1.2 -> 2.1 deg
  from the mask model's;
- the heart's seeds (session 10): in the solid-organ watershed only the
  pool near the chambers' lumen seeds the heart, and specks of blood (noise
  on thin slices) no longer break the liver's marker
  (``modeling.seed._heart_seeds``, ``split_solid_organs``; for thick
  slices of TotalSegmentator's aortic CTA, ``test_aortic_cta.py``).  Here:
  0.884 / 3.2 / 9.6 -> 0.887 / 3.1 / 9.2, ``ref & ~pa`` 0.889 / 2.73 / 7.5
  -> 0.891 / 2.67 / 7.5; the venous-phase variant unchanged;
- the pulmonary trunk (session 11): the trace started only where blood
  leaves the field of view, and followed a vessel only into lobes at most
  1.1 times as wide as its narrowest so far.  Here the pulmonary branches
  leave the crop with lobes of 7.5-9.6 mm radius, the bifurcation's lobe is
  10.7 mm and the trunk's 12.1 mm: the trace stopped at the branches and the
  model kept the trunk and the bifurcation (17 ml of
  ``pulmonary_artery.nii.gz``; on TotalSegmentator's whole-chest aortic CTA,
  the same patient, no pulmonary lobe reaches the edge at all).  Now lobes
  outside the heart body reaching 50 mm beyond it start a vessel too, the
  trace steps into lobes outside the body of a vessel's radius (at most 1.4
  times its narrowest: a bifurcation's parent), and a vessel
  lobe open to a chamber's (the trunk's lobe runs on into the outflow tract:
  the valve leaves no saddle) is vessel only outside the body
  (``modeling.greatvessels``, steps 4-6).  The model's mesh: full reference
  0.887 / 3.1 / 9.2 -> 0.870 / 3.7 / 15.2 (the reference's own pulmonary
  artery now lies outside), ``ref & ~pa`` 0.891 / 2.67 / 7.5 -> 0.899 /
  2.78 / 7.6, the pulmonary artery inside the model 17.1 -> 0.0 ml; of the
  31.6 ml removed, 17.1 ml are ``pulmonary_artery.nii.gz``, 6.3 ml lie
  outside the reference and 8.9 ml in ``ref & ~pa``, the outflow tract
  between the body's edge and where TotalSegmentator starts its pulmonary
  artery (a few mm below it; taking the trunk's lobe whole took 12.4 ml).
  The frame is 5.2 deg from the reference's mask model (1.2 before), 3.8 deg
  from the mask model of the reference less its pulmonary artery, which is
  itself 3.6 deg from the reference's: the pulmonary artery alone turns the
  reference's frame that much;
- the frame (session seg9, round 2): with every accepted slab ellipse on the
  long axis, the automatic and the mask model were 11.0 deg apart, the
  reference with and without its pulmonary artery 9.9 deg; the mask model's
  line ran through two pulmonary-trunk slabs beyond five rejected base slabs.
  Through the longest run of adjacent slabs only: 1.2 and 3.7 deg (the
  automatic model vs the reference less its pulmonary artery 17.7 -> 3.4).
  Other rules tried, every pair within 5 deg for none: only the slabs within
  0.5-0.8 of the length from the apex (8.9-31 deg), dropping centres farther
  than 3, 5 or 8 mm from the line (0.6-19 deg).
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import warnings

import nibabel as nib
import numpy as np
import pytest

from heartreg.cli import main
from hrcore.geometry import apply_to_points
from imaging import load_study
from imaging.volume_file import read_nifti_volume
from modeling import read_model
from modeling.build import ModelingWarning, build_heart_model
from modeling.fiducials import FiducialError, find_fiducials
from modeling.labelmap import LabelMapError, mask_on_grid, read_label_map
from modeling.mesh import check_mesh
from modeling.segment import SegmentationError, segment_heart
from modeling.vessels import APEX_LAI_LPS, base_direction

from tests.data.fetch_real_cts import paths as real_cts

from .realct import LEAD_KJI, REALCT, mesh_to_mask, overlap, principal_axis, right_heart_blood, write_ct_series

pytestmark = pytest.mark.skipif(not REALCT.is_dir(), reason=f"real CT folder {REALCT} is missing")

SPACING = (1.5, 1.5, 1.5)


def _angle_deg(a, b, *, signed=False) -> float:
    c = float(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c if signed else abs(c), -1.0, 1.0))))


@pytest.fixture(scope="module")
def realct(tmp_path_factory):
    """(NIfTI volume, DICOM study folder, reference mask on the CT's grid)."""
    volume = read_nifti_volume(REALCT / "ct_cropped.nii.gz")
    study = write_ct_series(volume.hu, volume.T_patient_from_voxel, tmp_path_factory.mktemp("realct") / "study")
    reference = mask_on_grid(read_label_map(REALCT / "heart.nii.gz"), volume.shape, volume.T_patient_from_voxel)
    return volume, study, reference


@pytest.fixture(scope="module")
def as_read(realct):
    """``segment_heart`` of the CT as read (the tests that compare against it share one run)."""
    volume = realct[0]
    return segment_heart(volume.hu, volume.T_patient_from_voxel)


@pytest.fixture(scope="module")
def artery(realct):
    """TotalSegmentator's pulmonary artery on the CT's grid."""
    volume = realct[0]
    return mask_on_grid(read_label_map(REALCT / "pulmonary_artery.nii.gz"), volume.shape, volume.T_patient_from_voxel)


@pytest.fixture(scope="module")
def heart_less_artery(realct, artery):
    """The reference less its pulmonary artery, on the CT's grid: the anatomy the model keeps."""
    return realct[2] & ~artery


def _run_model(args):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(args)
    return rc, [str(w.message) for w in caught if issubclass(w.category, ModelingWarning)]


@pytest.fixture(scope="module")
def auto_model(realct, tmp_path_factory):
    """``heartreg model STUDY -o OUT`` with no options on the DICOM series."""
    _, study, _ = realct
    out = tmp_path_factory.mktemp("auto") / "model"
    rc, caught = _run_model(["model", str(study), "-o", str(out), "-q"])
    return rc, caught, out


@pytest.fixture(scope="module")
def mask_model(realct, tmp_path_factory):
    """``heartreg model CT.nii.gz --mask heart.nii.gz`` (the NIfTI CT as input)."""
    out = tmp_path_factory.mktemp("mask") / "model"
    rc, caught = _run_model(
        ["model", str(REALCT / "ct_cropped.nii.gz"), "-o", str(out), "-q", "--mask", str(REALCT / "heart.nii.gz")]
    )
    return rc, caught, out


def _metrics(model_dir, volume, reference):
    model = read_model(model_dir)
    mesh = model.mesh_patient()
    mask = mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, volume.T_patient_from_voxel)
    return model, overlap(mask, reference, SPACING)


def test_nifti_and_dicom_give_the_same_volume(realct):
    volume, study, _ = realct
    dicom = load_study(study)
    np.testing.assert_array_equal(dicom.hu, volume.hu)
    np.testing.assert_allclose(dicom.T_patient_from_voxel, volume.T_patient_from_voxel, atol=1e-4)
    assert any("RAS" in n and "LPS" in n for n in volume.notes)
    assert all(s.acquisition_time_s is None for s in volume.slices)  # no slice clock


def test_model_with_no_options(realct, auto_model, heart_less_artery):
    volume, _, reference = realct
    rc, caught, out = auto_model
    assert rc == 0
    payload = json.loads((out / "model.json").read_text())
    # ungated: the phase is unknown, said in model.json and warned
    assert payload["cardiac_phase"] is None and "no ECG gating" in payload["cardiac_phase_source"]
    # no skin markers in this scan (contrast vessels, sternum, an ECG clip in the air are not markers)
    assert payload["fiducials_patient_mm"] == []
    # it said "registration will need them from elsewhere", and 'heartreg register' refuses a model without them
    for message in ("cardiac phase unknown", "no skin markers found: the model has no fiducials and cannot be "
                    "registered ('heartreg register' starts from the CT's skin staples, touched in surgery); make it "
                    "from a CT that shows the staples"):
        assert any(message in w for w in caught), message
        assert any(message in w for w in payload["parameters"]["warnings"]), message
    model, m = _metrics(out, volume, reference)
    # Measured 0.879 / 3.6 mm / 14.8 mm (0.873 / 3.5 / 13.6 before session 22; 0.870 / 3.7 / 15.2 before session 20 kept the outflow tract up to the
    # pulmonary valve): the reference holds the pulmonary artery, which the model cuts at its
    # valve since session 11 (0.887 / 3.1 / 9.2 with the trunk kept; the reference less its own pulmonary
    # artery scores p95 19.5 mm against it).  The bounds a few % looser; the fair comparison, against the
    # reference less its pulmonary artery, is test_against_the_reference_less_its_pulmonary_artery, the
    # issue's targets are in test_issue_targets.
    assert m["dice"] >= 0.85 and m["msd_mm"] <= 4.0 and m["p95_mm"] <= 17.0, m
    # the long axis follows the principal axis of the reference less its pulmonary artery, the anatomy the model
    # keeps (measured 10.5 deg, 11.4 before session 22, 9.5 before session 20 kept the outflow tract up to the pulmonary valve: the frame's line runs through the ventricular slabs, the principal axis leans
    # towards the atria; with the artery the reference's axis leans towards it too: 14.6 deg from the model's,
    # 12.6 while the model kept the pulmonary trunk)
    z = model.frame.axes_patient[:, 2]
    angle = _angle_deg(z, principal_axis(heart_less_artery, volume.T_patient_from_voxel))
    assert angle <= 15.0, angle
    apex = -z  # towards patient left, anterior, inferior (LPS: +x, -y, -z)
    assert apex[0] > 0 and apex[1] < 0 and apex[2] < 0 and apex @ APEX_LAI_LPS > 0.7
    assert payload["parameters"]["base_from_great_vessels"] is True
    assert "great vessels cut at their root" in " ".join(payload["parameters"]["notes"])


def test_model_from_reference_mask(realct, mask_model, auto_model):
    volume, _, reference = realct
    rc, _, out = mask_model
    assert rc == 0
    payload = json.loads((out / "model.json").read_text())
    assert payload["parameters"]["trim_vessels"] is False  # a given mask is meshed as it is
    assert "a NIfTI volume has no slice clock" in payload["cardiac_phase_source"]
    assert str(REALCT) not in json.dumps(payload)  # no folder path in the model
    model, m = _metrics(out, volume, reference)
    # meshing a blocky 1.5 mm mask: only the smoothing of its staircase differs (measured 0.993)
    assert m["dice"] >= 0.98 and m["msd_mm"] <= 0.5, m
    apex = -model.frame.axes_patient[:, 2]
    assert apex @ APEX_LAI_LPS > 0.7


def test_the_meshed_mask_goes_beside_the_model_for_slicer(realct, auto_model, mask_model, heart_less_artery):
    """``heart_mask.nii.gz``: the mask the model meshed, a NIfTI label map in RAS (3D Slicer's Segment Editor
    opens it over the CT; corrected, it comes back through ``--mask``).  On the real CT it lies where the mesh
    lies (the mesh's own mask measured Dice 0.879 against the reference, this one 0.88) and holds its volume
    (the mesh, moved onto the CT's edge and trimmed at the vessels' mouths, 704 ml; the mask 700 ml); an
    external mask goes out as it was meshed."""
    volume, _, reference = realct
    for model_dir, dice in ((auto_model[2], 0.86), (mask_model[2], 0.99)):
        image = nib.load(str(model_dir / "heart_mask.nii.gz"))
        assert image.header.get_data_dtype() == np.uint8 and int(image.header["sform_code"]) == 1
        mask = mask_on_grid(read_label_map(model_dir / "heart_mask.nii.gz"), volume.shape, volume.T_patient_from_voxel)
        assert overlap(mask, reference, SPACING)["dice"] >= dice, model_dir
        mesh = read_model(model_dir).mesh_patient()
        ml = float(mask.sum()) * float(np.prod(SPACING)) / 1000.0
        assert abs(ml / (check_mesh(mesh).volume_mm3 / 1000.0) - 1.0) < 0.03, (ml, model_dir)


def test_a_mask_off_the_heart_is_said(realct, mask_model, tmp_path):
    """The reference heart mask moved 40 mm to the patient's left (as if drawn on another scan or placed in
    another frame) lies a third on lung: it is meshed as given, with a warning, in model.json too (an audit:
    only "pieces" and "field of view" warnings came, Dice 0.35); the reference in place is not warned."""
    assert not any("air or lung" in w for w in mask_model[1])
    ref = nib.load(str(REALCT / "heart.nii.gz"))
    moved = ref.affine.copy()
    moved[0, 3] -= 40.0  # RAS: 40 mm towards the patient's left
    nib.save(nib.Nifti1Image(np.asanyarray(ref.dataobj), moved), str(tmp_path / "moved.nii.gz"))
    with pytest.warns(ModelingWarning, match=r"label map \(NIfTI\): (\d+)% of its voxels lie on air or lung in this CT "
                                             r"\(below -300 HU; a heart holds none\): is it drawn on another scan"):
        build = build_heart_model(realct[0], cardiac_phase=None, cardiac_phase_source="none", target_faces=4000,
                                  mask_path=tmp_path / "moved.nii.gz")
    said = next(w for w in build.model.parameters["warnings"] if "air or lung" in w)
    assert 25 <= int(re.search(r"(\d+)% of its voxels", said)[1]) <= 45, said  # measured 38 %


@pytest.fixture(scope="module")
def mask_model_less_artery(heart_less_artery, tmp_path_factory):
    """``heartreg model CT.nii.gz --mask M``, M the reference less TotalSegmentator's pulmonary artery."""
    folder = tmp_path_factory.mktemp("mask_less_artery")
    ct = nib.load(str(REALCT / "ct_cropped.nii.gz"))  # the CT's grid, in the CT's (i, j, k) order
    nib.save(nib.Nifti1Image(heart_less_artery.transpose(2, 1, 0).astype(np.uint8), ct.affine),
             str(folder / "heart.nii.gz"))
    rc, _ = _run_model(["model", str(REALCT / "ct_cropped.nii.gz"), "-o", str(folder / "model"), "-q",
                        "--mask", str(folder / "heart.nii.gz")])
    assert rc == 0
    return folder / "model"


def test_frame_from_mesh_and_mask_agree(auto_model, mask_model_less_artery):
    """Issue 9: the same frame within 5 deg from the automatic mesh and from the reference mask, the reference
    less its pulmonary artery (the anatomy the automatic model keeps: it cuts the artery at its valve).

    Measured 4.2 deg (z, same apex->base sign) and 6.3 deg (x); 3.8 and 5.0-5.2 before session 20 kept the
    outflow tract up to the pulmonary valve.  Against the reference with its pulmonary
    artery 5.2 deg (1.2 deg while the model kept the pulmonary trunk, before session 11): the artery alone
    turns the reference's frame by 3.6 deg.  Before the line was fitted through the longest run of adjacent
    slabs only, 11.0 deg from the reference: its pulmonary trunk (two narrow slabs beyond a gap at the base)
    and the automatic model's base tilted it.
    """
    auto, given = read_model(auto_model[2]), read_model(mask_model_less_artery)
    a, g = auto.frame.axes_patient, given.frame.axes_patient
    assert _angle_deg(a[:, 2], g[:, 2], signed=True) <= 5.0
    assert _angle_deg(a[:, 0], g[:, 0], signed=True) <= 10.0


@pytest.mark.xfail(strict=True, reason="issue 9's surface targets are not reached yet (measured Dice 0.879, MSD "
                   "3.6 mm, p95 14.8 mm); see the module docstring for why part of the gap is the reference "
                   "(against it less its pulmonary artery: Dice 0.906, MSD 2.6 mm, p95 7.0 mm); its MSD and p95 cannot be met "
                   "with the pulmonary artery cut at its valve (the best such surface: 1.7-2.4 mm, p95 14-17 mm; "
                   "test_what_the_artery_cut_costs_against_the_whole_reference)")
def test_issue_targets(realct, auto_model):
    volume, _, reference = realct
    _, m = _metrics(auto_model[2], volume, reference)
    assert m["dice"] >= 0.92 and m["msd_mm"] <= 1.5 and m["p95_mm"] <= 5.0, m


def test_what_the_artery_cut_costs_against_the_whole_reference(realct, artery):
    """Why test_issue_targets stays an xfail: the best surface that cuts the pulmonary artery, as the issue
    asks, cannot meet its MSD and p95 against the whole reference, which keeps the trunk and its branches.

    That surface, idealised from the reference itself: the reference less the artery and one voxel of the
    artery's wall, its largest part, then grown by one or two layers of wall tissue (0-250 HU: an epicardial
    surface at the thin walls, where the reference's edge is the blood pool's).  Measured (session 29):
    cut 0.962 / 1.68 / 16.8 mm; grown 0.930 / 2.32 / 16.4 and 0.913 / 2.41 / 14.3 mm against the whole
    reference; against it less its artery 0.962 / 1.18 / 2.1 and 0.943 / 1.39 / 3.0 mm, where the model
    scores 0.906 / 2.65 / 7.0 (test below).  The plain set difference ``reference & ~artery`` scores 0.966 /
    0.21 / 1.5 mm only because it keeps the artery's wall as a one-voxel sleeve, a shape no heart has."""
    from scipy import ndimage

    volume, _, reference = realct
    cross = ndimage.generate_binary_structure(3, 1)
    wall = ndimage.binary_dilation(artery, cross)
    labels, _ = ndimage.label(reference & ~wall)
    cut = labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1
    grown = cut.copy()
    for _ in range(2):
        grown |= ndimage.binary_dilation(grown, cross) & (volume.hu > 0) & (volume.hu < 250) & ~wall
    for mask in (cut, grown):
        whole, less = overlap(mask, reference, SPACING), overlap(mask, reference & ~artery, SPACING)
        assert whole["p95_mm"] > 10.0 and whole["msd_mm"] > 1.5, whole  # the issue's 5 mm and 1.5 mm: out of reach
        assert less["p95_mm"] <= 3.0 and less["msd_mm"] <= 1.5 and less["dice"] >= 0.94, less  # within reach


def test_against_the_reference_less_its_pulmonary_artery(realct, auto_model, artery, heart_less_artery):
    """The issue cuts the great vessels at their valves, the reference keeps the pulmonary artery."""
    volume = realct[0]
    T = volume.T_patient_from_voxel
    model, m = _metrics(auto_model[2], volume, heart_less_artery)
    # measured 0.906 / 2.65 mm / 7.04 mm (0.901 / 2.70 / 7.35 before session 22 parted the fat planes blurred above
    # 0 HU, modeling.planes; 0.897 / 2.79 / 7.6 before session 20 kept the outflow tract up to the
    # pulmonary valve; 0.898 / 2.76 / 7.6 before the aortic root's wall inside the heart's body
    # was kept, session 14: the reference leaves it out; 0.891 / 2.67 / 7.5 with the pulmonary trunk kept, before
    # session 11; before
    # the vessels were traced to their valves: 0.884 / 3.21 / 9.2);
    # the rest is mostly the atrial roofs and the thin walls (module docstring)
    assert m["dice"] >= 0.89 and m["msd_mm"] <= 2.9 and m["p95_mm"] <= 8.5, m
    # the pulmonary trunk and its bifurcation are cut off (measured 0.8 ml of the artery inside, 0.2 before session 22,
    # 0.0 before session 20;
    # 17.1 ml before session 11)
    mesh = model.mesh_patient()
    inside_ml = (artery & mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, T)).sum() * np.prod(SPACING) / 1000
    assert inside_ml <= 2.0, inside_ml


PULMONARY_VALVE = {name: real_cts()[f"ts_pulmonary/{name}.nii.gz"] for name in ("annulus", "sinotubular_junction")}


@pytest.mark.skipif(not all(p.is_file() for p in PULMONARY_VALVE.values()),
                    reason="TotalSegmentator's pulmonary landmarks were not fetched (offline)")
def test_the_outflow_tract_reaches_the_pulmonary_valve(realct, auto_model):
    """The pulmonary trunk is cut at its valve, not at the heart body's edge below it.

    TotalSegmentator's pulmonary report (made from this CT) marks the valve's annulus and the sinotubular
    junction.  Along the annulus's normal through its centre (towards the junction), the model's top lies
    2.2 mm below the annulus (TotalSegmentator starts its pulmonary artery 1.5-4.8 mm below it); 17.2 mm
    below before session 20, when the trunk's lobe was cut where it left the heart body, through the
    right ventricle's infundibulum (``modeling.greatvessels``, step 7).
    """
    volume = realct[0]
    T = volume.T_patient_from_voxel
    model = read_model(auto_model[2])
    mesh = model.mesh_patient()
    mask = mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, T)
    landmark = {name: mask_on_grid(read_label_map(path), volume.shape, T) for name, path in PULMONARY_VALVE.items()}
    points = apply_to_points(T, np.argwhere(landmark["annulus"])[:, ::-1].astype(float))
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre)[2][2]
    junction = apply_to_points(T, np.argwhere(landmark["sinotubular_junction"])[:, ::-1].astype(float)).mean(axis=0)
    normal *= np.sign((junction - centre) @ normal)
    along = np.arange(-30.0, 10.0, 0.25)
    kji = np.rint(apply_to_points(np.linalg.inv(T), centre + along[:, None] * normal)[:, ::-1]).astype(int)
    top = along[mask[tuple(kji.T)]].max()
    assert -6.0 <= top <= 3.0, top
    assert (mask & landmark["sinotubular_junction"]).sum() <= 0.1 * landmark["sinotubular_junction"].sum()


def test_fiducials_insisted_on(realct):
    volume, _, _ = realct
    with pytest.raises(FiducialError, match=r"found 0 metal marker\(s\) on the skin, expected 9"):
        find_fiducials(volume.hu, volume.T_patient_from_voxel, expected=9)
    notes = " ".join(find_fiducials(volume.hu, volume.T_patient_from_voxel, expected=None).notes)
    assert "continues beneath the skin" in notes and "edge of the field of view" in notes


def test_totalsegmentator_outputs(realct, tmp_path):
    volume, _, reference = realct
    T = volume.T_patient_from_voxel
    # its segmentations/ folder, given as the folder or as the one above it
    seg = tmp_path / "ts" / "segmentations"
    seg.mkdir(parents=True)
    shutil.copy(REALCT / "heart.nii.gz", seg / "heart.nii.gz")
    shutil.copy(REALCT / "pulmonary_artery.nii.gz", seg / "pulmonary_artery.nii.gz")
    for path in (seg, seg.parent):
        assert np.array_equal(mask_on_grid(read_label_map(path), volume.shape, T), reference)
        # a structure chosen by its name (--label), as --help suggests: each file's label 1 carries it
        by_name = read_label_map(path, structure="Heart.nii.gz")
        assert np.array_equal(mask_on_grid(by_name, volume.shape, T, label="heart"), reference)
        artery = mask_on_grid(read_label_map(path, structure="pulmonary_artery"), volume.shape, T,
                              label="pulmonary_artery")
        assert artery.sum() > 0 and not np.array_equal(artery, reference)
    with pytest.raises(LabelMapError, match="without heart.nii.gz"):
        read_label_map(tmp_path)
    with pytest.raises(LabelMapError, match=r"without aorta.nii.gz .*--label NAME"):
        read_label_map(seg, structure="aorta")
    # its multi-label file (--ml): the label table in a Caret XML header extension
    ct = nib.load(str(REALCT / "ct_cropped.nii.gz"))
    labels = np.zeros(ct.shape, np.uint8)
    labels[reference.transpose(2, 1, 0)] = 51
    labels[np.asarray(nib.load(str(REALCT / "pulmonary_artery.nii.gz")).dataobj) > 0] = 52
    image = nib.Nifti1Image(labels, ct.affine)
    xml = ('<?xml version="1.0" encoding="UTF-8"?><CaretExtension><VolumeInformation Index="0"><LabelTable>'
           '<Label Key="51" Red="1" Green="0" Blue="0" Alpha="1"><![CDATA[heart]]></Label>'
           '<Label Key="52" Red="0" Green="0" Blue="1" Alpha="1"><![CDATA[pulmonary_artery]]></Label>'
           '</LabelTable></VolumeInformation></CaretExtension>')
    image.header.extensions.append(nib.nifti1.Nifti1Extension(0, xml.encode()))
    ml = tmp_path / "total.nii.gz"
    nib.save(image, str(ml))
    label_map = read_label_map(ml)
    assert label_map.names == {51: "heart", 52: "pulmonary_artery"}
    heart = mask_on_grid(label_map, volume.shape, T, label="Heart")
    assert np.array_equal(heart, reference & ~np.asarray(labels.transpose(2, 1, 0) == 52))
    with pytest.raises(LabelMapError, match="'aorta' is not named"):
        mask_on_grid(label_map, volume.shape, T, label="aorta")
    with pytest.raises(LabelMapError, match="several labels"):
        mask_on_grid(label_map, volume.shape, T)


def test_base_direction(realct):
    volume, _, reference = realct
    T = volume.T_patient_from_voxel
    base = base_direction(reference, volume.hu, T)
    assert -base @ APEX_LAI_LPS > 0.8  # measured 0.99: the vessels leave at the base
    # a CT without contrast: no vessel mouths, no answer
    assert base_direction(reference, np.zeros(volume.shape, np.int16), T) is None


def test_mirrored_heart_warns(realct, tmp_path):
    """A mirror image (dextrocardia): the apex points right; a warning, not an error."""
    volume, _, reference = realct
    mirrored = dataclasses.replace(volume, hu=np.ascontiguousarray(volume.hu[:, :, ::-1]))
    mask = tmp_path / "mirrored.nii.gz"
    nib.save(nib.Nifti1Image(reference[:, :, ::-1].transpose(2, 1, 0).astype(np.uint8),
                             np.diag([-1.0, -1.0, 1.0, 1.0]) @ volume.T_patient_from_voxel), str(mask))
    with pytest.warns(ModelingWarning, match="not towards patient left-anterior-inferior"):
        build = build_heart_model(mirrored, cardiac_phase=None, cardiac_phase_source="test",
                                  mask_path=mask, expected_fiducials=None, target_faces=4000)
    assert -build.model.frame.axes_patient[:, 2][0] < 0  # the apex points to the patient's right
    assert any("left-anterior-inferior" in w for w in build.model.parameters["warnings"])


def test_register_asks_for_the_phase(mask_model, tmp_path, capsys):
    out = mask_model[2]
    session = tmp_path / "session"  # never read: the phase is asked for first
    session.mkdir()
    assert main(["register", str(out), str(session), "-o", str(tmp_path / "reg"), "-q"]) == 1
    err = capsys.readouterr().err
    assert "cardiac phase of model" in err and "--cardiac-phase" in err and len(err.strip().splitlines()) == 1
    assert main(["register", str(out), str(session), "-o", str(tmp_path / "reg"), "-q", "--cardiac-phase", "1.5"]) == 1
    assert "--cardiac-phase must be a phase in [0, 1)" in capsys.readouterr().err



def test_venous_phase(realct, heart_less_artery, as_read):
    """Contrast timing: the real CT's blood dimmed to a venous phase (median 180 HU) is still a blood pool.

    HU above 60 are scaled towards soft tissue so that the blood's median (486 HU) becomes 180, rounded to
    integers as a DICOM file stores them; myocardium (~120 HU) becomes ~75.  No chamber then reaches the
    arterial 200 HU, and this cropped field of view has no two whole lungs to seed between: before the pool's
    lower bound stepped down, the model failed.  Two more steps read an arterial phase's HU and are fitted to
    it: the vessel tracer took the left atrium, cut by the field of view's edge with a 20 mm lumen, for a
    vessel (Dice 0.806; vessels now start at most 17 mm wide), and the stub trim took the chambers' dim blood
    under thin walls for vessel lumen (Dice 0.795 with both; now skipped with a warning at weak contrast).
    Measured against the reference less its pulmonary artery 0.895 / 2.7 mm / 7.5 mm (segmentation) and
    0.896 / 2.8 / 7.6 (the model's mesh; 0.897 / 2.6 / 7.3 and 0.898 / 2.7 / 7.6 before the aortic root's
    wall inside the heart's body was kept, session 14); before the pulmonary trunk was cut (session 11) 0.892 / 2.5 / 6.9
    and 0.892 / 2.6 / 7.3 (against the whole reference 0.884 / 3.0 / 9.1 and 0.884 / 3.1 / 9.6 then, 0.868 /
    3.5 / 14.2 and 0.868 / 3.7 / 15.0 now: the reference holds the artery).
    """
    volume, _, reference = realct
    hu = volume.hu.astype(np.float32)
    blood = float(np.median(hu[reference & (hu > 200)]))
    dim = np.rint(np.where(hu > 60, 60 + (hu - 60) * (180 - 60) / (blood - 60), hu)).astype(np.int16)
    seg = segment_heart(dim, volume.T_patient_from_voxel)
    assert seg.parameters["contrast"] is True and seg.parameters["pool_hu"] == 150.0
    assert "weak contrast" in " ".join(seg.notes)
    m = overlap(seg.mask, heart_less_artery, SPACING)
    assert m["dice"] >= 0.88 and m["msd_mm"] <= 3.0, m
    # the arterial CT keeps its pool at 200 HU
    assert as_read.parameters["pool_hu"] == 200.0
    with pytest.warns(ModelingWarning, match="vessel stub trim skipped: the blood is dim"):
        build = build_heart_model(dataclasses.replace(volume, hu=dim), cardiac_phase=None,
                                  cardiac_phase_source="test", expected_fiducials="auto")
    assert build.model.parameters["trim_vessels"] is False
    mesh = build.model.mesh_patient()
    m = overlap(mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, volume.T_patient_from_voxel),
                heart_less_artery, SPACING)
    assert m["dice"] >= 0.88 and m["msd_mm"] <= 3.0, m
    assert -build.model.frame.axes_patient[:, 2] @ APEX_LAI_LPS > 0.7


def test_a_washed_out_right_heart_stays(realct, artery, heart_less_artery):
    """Contrast timing: the right heart's blood washed out by a saline chaser (coronary CTA's usual look: the
    left heart bright, the right at 100-200 HU), here the right atrium, ventricle, pulmonary artery and caval
    veins of the real CT (:func:`right_heart_blood`) dimmed to 100 HU, the left heart as it is.  The right
    heart is then thick tissue far from the blood, as a liver is; it lies between the lungs, the liver below
    them.  Measured 693 ml, Dice 0.908 against the reference less its pulmonary artery (the CT as read 0.906);
    before, 434 ml and 0.705: the right heart went with the chest wall (``modeling.seed.split_solid_organs``)."""
    volume = realct[0]
    hu = volume.hu.astype(np.float32)
    right = right_heart_blood(hu, artery)
    dim = np.rint(np.where(right, 60 + (hu - 60) * (100 - 60) / (np.median(hu[right]) - 60), hu)).astype(np.int16)
    seg = segment_heart(dim, volume.T_patient_from_voxel)
    m = overlap(seg.mask, heart_less_artery, SPACING)
    assert 620 <= seg.volume_ml <= 780 and m["dice"] >= 0.88 and m["p95_mm"] <= 8.5, (seg.volume_ml, m)


@pytest.mark.parametrize("left_hu", [100])  # 150: test_a_frame_fit_that_cycles_takes_the_mean_axis
def test_a_pulmonary_cta_timing(realct, artery, heart_less_artery, left_hu):
    """Contrast timing the other way: a pulmonary CTA (a CT for pulmonary embolism, the commonest contrast
    chest CT) is timed for the pulmonary arteries: the right heart bright, the left heart and the aorta still
    dim.  Here the real CT's left atrium, ventricle and aorta (its blood apart from :func:`right_heart_blood`)
    dimmed to 150 or 100 HU.  The right atrium and ventricle alone hold a 13 mm ball on the coarse grid:
    with a chamber's ball of 15 mm (before session 29) no pool was found and there was no model ("no
    heart-sized region"); now measured 695 / 691 ml, Dice 0.885 / 0.885, p95 8.1 mm against the reference
    less its pulmonary artery (the dim left heart is tissue the region keeps)."""
    volume = realct[0]
    seg = segment_heart(_pulmonary_cta(volume.hu, artery, left_hu), volume.T_patient_from_voxel)
    m = overlap(seg.mask, heart_less_artery, SPACING)
    assert 620 <= seg.volume_ml <= 780 and m["dice"] >= 0.87 and m["p95_mm"] <= 9.0, (seg.volume_ml, m)


@pytest.mark.parametrize("blood_hu", [750, 900])  # 600 (measured in the docstring) passes between
def test_bright_contrast_at_low_kv(realct, heart_less_artery, blood_hu):
    """Iodine brighter than a 120 kV CTA's: at 70-80 kV (low-dose cardiac CT, children) or in a dual-energy CT's
    40-50 keV image blood reads 700-1200 HU.  Here every HU above 100 of the real CT stretched so that the
    heart's blood (median 496 HU) reads 600, 750 or 900 (bone brightens too).  The pool was blood below 650 HU:
    at 600 it broke apart (Dice 0.863), from 750 on there was no model; now its upper bound follows the blood's
    own level (``modeling.seed.blood_ceiling_hu``): measured 696 / 710 / 697 ml, Dice 0.902 / 0.899 / 0.880,
    p95 7.0 / 7.0 / 9.5 mm against the reference less its pulmonary artery (as read 0.906); limit: at 1100 HU
    874 ml, 0.789."""
    volume, _, reference = realct
    hu = volume.hu.astype(np.float32)
    level = np.median(hu[(hu > 250) & reference])
    bright = np.where(hu > 100, 100 + (hu - 100) * (blood_hu - 100) / (level - 100), hu)
    seg = segment_heart(np.rint(np.clip(bright, -1024, 3071)).astype(np.int16), volume.T_patient_from_voxel)
    m = overlap(seg.mask, heart_less_artery, SPACING)
    assert 620 <= seg.volume_ml <= 780 and m["dice"] >= 0.87 and m["p95_mm"] <= 10.0, (seg.volume_ml, m)
    assert seg.parameters["blood_hu"][1] > 650.0  # the pool reaches above 120 kV's bound


def test_a_sharp_kernel(realct, heart_less_artery):
    """A sharp reconstruction kernel (a stent or lung kernel, the series a user may pick from a study): edges
    enhanced (the CT plus its difference from a 1.5 mm Gaussian blur, overshoot of 100-200 HU at the blood's
    edge) and noise amplified (100 HU).  The noise's extra smoothing (``modeling.seed.NOISE_HU``) takes the
    overshoot too, once the noise is measured: before session 29 it was measured only in a pool found at the
    light smoothing, which the overshoot and the noise parted in 3 of 5 noise draws (no model, "no heart-sized
    region" or "the blood-pool seed does not touch any tissue"); now the pool is looked for again smoothed over
    1.2 mm (``modeling.seed.NOISE_PROBE_MM``) to measure it, and the grid smoothed at least as much: measured
    631-672 ml, Dice 0.902-0.910, p95 6.2-7.5 mm against the reference less its pulmonary artery in the five
    draws (at 150 HU 0.896-0.906; white noise of 150 HU alone 0.896-0.898).  Limit, not a scanner's: the same enhancement without the noise, 149 ml,
    Dice 0.31 (the blood's rim above the pool's 650 HU, the chambers' lobes thin as vessels)."""
    from scipy import ndimage

    volume = realct[0]
    hu = volume.hu.astype(np.float32)
    sharp = 2.0 * hu - ndimage.gaussian_filter(hu, 1.0) + np.random.default_rng(0).normal(0.0, 100.0, hu.shape)
    seg = segment_heart(np.rint(np.clip(sharp, -1024, 3071)).astype(np.int16), volume.T_patient_from_voxel)
    m = overlap(seg.mask, heart_less_artery, SPACING)
    assert 580 <= seg.volume_ml <= 780 and m["dice"] >= 0.87 and m["p95_mm"] <= 9.5, (seg.volume_ml, m)


def _pulmonary_cta(hu, artery, left_hu) -> np.ndarray:
    """The real CT's left atrium, ventricle and aorta (its blood apart from :func:`right_heart_blood`) dimmed
    to ``left_hu``, as stored (int16)."""
    from scipy import ndimage

    hu = np.asarray(hu, np.float32)
    right = right_heart_blood(hu, artery)
    left = ndimage.binary_dilation((ndimage.gaussian_filter(hu, 0.7) > 180.0) & ~right) & (hu > 100) & ~right
    return np.rint(np.where(left, 60 + (hu - 60) * (left_hu - 60) / (np.median(hu[left]) - 60), hu)).astype(np.int16)


def test_a_frame_fit_that_cycles_takes_the_mean_axis(realct, artery, heart_less_artery, auto_model):
    """The pulmonary CTA's model (left heart at 150 HU): the frame's axis fit came back to an axis it had (a
    cycle of 3 axes up to 6.9 deg apart: which slabs are accepted, and which run of them is the longest, changes
    with the axis) and stopped after 20 iterations on whichever it had reached, warned as unreliable.  Now the
    axis is the cycle's mean, not warned, noted; measured 6.4 deg from the CT as read's frame."""
    volume = realct[0]
    build = build_heart_model(dataclasses.replace(volume, hu=_pulmonary_cta(volume.hu, artery, 150)),
                              cardiac_phase=None, cardiac_phase_source="test", expected_fiducials=None)
    mesh = build.model.mesh_patient()  # the model, as test_a_pulmonary_cta_timing's segmentation (measured 0.884, 8.6 mm)
    m = overlap(mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, volume.T_patient_from_voxel), heart_less_artery,
                SPACING)
    assert m["dice"] >= 0.87 and m["p95_mm"] <= 9.5, m
    frame = build.model.frame
    assert frame.cycle >= 2 and frame.axis_change_deg <= 10.0 and frame.convergence_warning() is None
    assert not any("heart frame's fit" in w for w in build.model.parameters["warnings"])
    assert any("cycled among" in n for n in build.notes)
    z, z_read = frame.axes_patient[:, 2], read_model(auto_model[2]).frame.axes_patient[:, 2]
    assert _angle_deg(z, z_read) <= 10.0


def test_thick_voxels(realct):
    """A coarser reconstruction: the real CT averaged to 3 mm voxels, as routine chest CTs are read.

    At 3 mm the diaphragm and the fat over it blur into the tissue range and the liver joins the heart over a
    broad front (before: 1145 ml, Dice 0.699, p95 51 mm).  The liver is tissue thicker than any heart wall and
    far from blood: parted at the diaphragm (measured 791 ml, Dice 0.868, MSD 3.3 mm, p95 11.3 mm; the 1.5 mm
    CT: 0.884 / 3.0 / 9.0).  The descending aorta (its lumen a stent graft) joins the left atrium here into a
    branch thick for 45 mm: longer than an atrium, it is cut at its first thin shell.  Session 22, the fat
    planes blurred above 0 HU parted (modeling.planes): 800 -> 732 ml, Dice 0.863 -> 0.883, p95 11.8 -> 8.1 mm
    (22 ml of the pulmonary artery still kept, 29 before).
    """
    volume, _, reference = realct
    n = np.array(volume.shape) // 2 * 2
    hu = volume.hu[: n[0], : n[1], : n[2]].astype(np.float32)
    hu = hu.reshape(n[0] // 2, 2, n[1] // 2, 2, n[2] // 2, 2).mean(axis=(1, 3, 5))
    T = volume.T_patient_from_voxel.copy()
    T[:3, 3] += T[:3, :3] @ [0.5, 0.5, 0.5]
    T[:3, :3] *= 2
    seg = segment_heart(hu, T)
    assert "parted from the heart" in " ".join(seg.notes)
    mask = np.zeros(volume.shape, bool)
    mask[: n[0], : n[1], : n[2]] = seg.mask.repeat(2, 0).repeat(2, 1).repeat(2, 2)
    m = overlap(mask, reference, SPACING)
    assert 650 <= seg.volume_ml <= 850 and m["dice"] >= 0.87 and m["p95_mm"] <= 10.0, m


def test_no_contrast_in_a_tight_field_of_view(realct, artery):
    """A calcium-scoring-like scan: the real CT without contrast, its field of view cutting both lungs.

    Within 18 mm of the heart and pulmonary artery the HU above 60 are pressed to ~40 (blood and myocardium
    without contrast, 40-60 HU), bone farther out is kept, and noise of 15 HU is added.  With no pool the seed
    is the soft tissue between the lungs; the lungs, cut by the field of view, touch the volume's sides like
    room air, and were refused as lungs (the model failed).  They are told from room air by their density
    (median -798 HU against air's -1000).  Measured: segmentation 708 ml, Dice 0.872, 3.4 mm, p95 11.4 mm; the
    model's mesh 0.871 / 3.5 / 11.8, apex . LAI 0.91.
    """
    from scipy import ndimage

    volume, _, reference = realct
    hu = volume.hu.astype(np.float32)
    near = ndimage.binary_dilation(reference | artery, iterations=12)
    plain = np.where(hu > 60, 40 + (hu - 60) * 0.03, hu)
    plain = np.where(~near & (hu > 150), hu, plain) + np.random.default_rng(1).normal(0, 15, hu.shape)
    plain = np.rint(plain).astype(np.int16)
    with pytest.warns(ModelingWarning):
        build = build_heart_model(dataclasses.replace(volume, hu=plain), cardiac_phase=None,
                                  cardiac_phase_source="test", expected_fiducials="auto")
    notes = " ".join(build.notes)
    assert "no contrast blood pool" in notes and "between the lungs" in notes
    mesh = build.model.mesh_patient()
    m = overlap(mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, volume.T_patient_from_voxel), reference, SPACING)
    assert m["dice"] >= 0.85 and m["msd_mm"] <= 4.0, m
    assert -build.model.frame.axes_patient[:, 2] @ APEX_LAI_LPS > 0.7


def test_model_over_its_ct(realct, auto_model):
    """``model_ct.png``: the surface's outline on planes of the CT, where a user checks a real model first.

    The outline runs on the epicardium: the CT under it is the fat/myocardium edge the segmentation put it on
    (``hu_low`` 0 HU; measured median 45 HU over the six planes' outline points, the CT sampled bilinearly at
    the segments' midpoints), and it follows the reference mask's boundary (measured median 2.1 mm from it: the
    reference's edge lies a voxel inside the myocardium and leaves out the thin walls; module docstring).
    """
    from PIL import Image
    from scipy import ndimage

    from modeling.ct_overlay import AXIAL_LEVELS, ct_panels

    volume, _, reference = realct
    model = read_model(auto_model[2])
    mesh = model.mesh_patient()
    panels = ct_panels(volume.hu, volume.T_patient_from_voxel, mesh.vertices, mesh.faces)
    assert [p.title.split(",")[0].split(" ")[0] for p in panels] == ["axial"] * len(AXIAL_LEVELS) + ["coronal",
                                                                                                     "sagittal"]
    T_inv = np.linalg.inv(volume.T_patient_from_voxel)
    to_ref = ndimage.distance_transform_edt(~(reference & ~ndimage.binary_erosion(reference)), sampling=SPACING)
    hu_at, ref_at = [], []
    for p in panels:
        assert len(p.outline) > 40 and max(p.image.shape) <= 361 and p.image.dtype == np.float32
        # the outline's midpoints on the panel's image (bilinear) and in the CT's voxels
        mid = p.outline.mean(axis=1)
        a0, a1, b0, b1 = p.extent
        rows = (mid[:, 1] - b0) / (b1 - b0) * p.image.shape[0] - 0.5
        cols = (mid[:, 0] - a0) / (a1 - a0) * p.image.shape[1] - 0.5
        hu_at.append(ndimage.map_coordinates(p.image, [rows, cols], order=1))
        kji = (p.to_patient(mid) @ T_inv[:3, :3].T + T_inv[:3, 3])[:, ::-1]
        ref_at.append(ndimage.map_coordinates(to_ref, kji.T, order=1))
    hu_at, ref_at = np.concatenate(hu_at), np.concatenate(ref_at)
    assert -60 <= np.median(hu_at) <= 120, np.median(hu_at)
    assert np.median(ref_at) <= 3.0, np.median(ref_at)
    image = np.asarray(Image.open(auto_model[2] / "model_ct.png").convert("L"), dtype=float)
    assert image.shape[0] > 500 and image.shape[1] > 900 and image.std() > 20  # the CLI drew it



def test_storage_order_does_not_matter(realct, as_read):
    """The same anatomy stored with its rows, columns and slices reversed (a feet-first, differently oriented
    scan) gives the same segmentation, voxel for voxel once turned back."""
    volume, _, _ = realct
    T = volume.T_patient_from_voxel
    n = np.array(volume.shape[::-1]) - 1  # (i, j, k) of the last voxel
    flip = np.diag([-1.0, -1.0, -1.0, 1.0])
    flip[:3, 3] = n
    flipped = segment_heart(volume.hu[::-1, ::-1, ::-1], T @ flip)
    assert np.array_equal(flipped.mask[::-1, ::-1, ::-1], as_read.mask)  # measured: identical (Dice 1.0)


def test_heart_cut_by_the_field_of_view(realct, heart_less_artery):
    """The real CT cropped 40 mm on the patient's left: the model is made, with a warning naming the side.

    (The whole CT, the phantoms and their tight field of view leave no mask voxel on the volume's faces.)
    The edge cuts the left ventricle: its blood pool's lobes there were traced as vessels leaving the field
    of view and the ventricle removed with them (425 ml, Dice 0.646 against the reference within the crop,
    measured); a lobe lying mostly inside the heart's body on the edge is now a chamber cut by it (690 ml,
    Dice 0.883; 0.888 against the reference less its pulmonary artery).  With the pulmonary trunk cut
    (session 11): 658 ml, 0.896 against the reference less its artery (0.865 against the whole reference).
    """
    volume, _, _ = realct
    cropped = dataclasses.replace(volume, hu=np.ascontiguousarray(volume.hu[:, :, :95]))
    assert overlap(segment_heart(cropped.hu, volume.T_patient_from_voxel).mask, heart_less_artery[:, :, :95],
                   SPACING)["dice"] >= 0.88
    with pytest.warns(ModelingWarning, match=r"cut by the CT's field of view \(patient's left side, 4\d cm² on the edge\)"):
        build = build_heart_model(cropped, cardiac_phase=None, cardiac_phase_source="test", expected_fiducials=None,
                                  target_faces=4000)
    warned = build.model.parameters["warnings"]
    assert any("field of view" in w for w in warned)
    # decimating this cut surface to 4000 faces left faces wound backwards after the clean-up (it broke the
    # surface, and the model kept twice as many) until session 15: the clean-up now winds them alike, outward
    assert not any("decimation" in w for w in warned), warned
    assert build.model.mesh.faces.shape[0] <= 4000


@pytest.mark.parametrize("kind", ["0.7 x 0.7 x 2.5 mm voxels", "blood half-way to a venous phase"])
def test_a_trim_reading_chamber_walls_is_refused(realct, heart_less_artery, tmp_path, kind):
    """Clinical reconstructions of the real CT: its stub trim reads the chambers' blood under the atria's and
    the right ventricle's thin walls as vessel lumen, and is refused as on the CT as read (63 % of the faces).

    Resampled (linear) to 0.7 x 0.7 x 2.5 mm voxels, a routine chest CT's, the trim flagged 48 % of the faces;
    with the blood within 12 mm of the heart dimmed half-way to 40 HU (its pool still above the arterial
    200 HU) 39 %.  Under the former bound (half the faces) both ran and took a quarter of the heart
    (measured 525 and 551 ml, Dice 0.705 and 0.775 against the whole reference; the robustness sweep of
    session 15, ``/work/scratch/s15h``).  A trim that would remove more than 25 % is refused: the phantoms'
    stubs take 5-18 %.  Measured now: 793 / 705 ml; against the reference less its pulmonary artery
    Dice 0.849 / 0.899, MSD 4.1 / 2.7 mm (as read 0.897 / 2.8 mm).  The resampled CT's remaining loss is
    not the trim's: with its 2.5 mm slices the tissue behind the left atrium joins the heart (the model
    reaches the field of view's posterior edge, warned).
    """
    from scipy import ndimage

    volume, _, reference = realct
    hu, T = volume.hu.astype(np.float32), volume.T_patient_from_voxel.copy()
    if kind.startswith("0.7"):
        factors = np.array([1.5 / 2.5, 1.5 / 0.7, 1.5 / 0.7])  # (k, j, i)
        hu = ndimage.zoom(hu, factors, order=1)
        T[:3, :3] *= ((np.array(volume.shape) - 1) / (np.array(hu.shape) - 1))[::-1]  # columns i, j, k
    else:
        near = ndimage.binary_dilation(reference, iterations=8)
        hu = np.where(near & (hu > 100), 40 + (hu - 40) * 0.5, hu)
    image = nib.Nifti1Image(np.rint(hu).astype(np.int16).transpose(2, 1, 0), np.diag([-1.0, -1.0, 1.0, 1.0]) @ T)
    nib.save(image, tmp_path / "ct.nii.gz")
    rc, caught = _run_model(["model", str(tmp_path / "ct.nii.gz"), "-o", str(tmp_path / "model"), "-q"])
    assert rc == 0
    assert any(re.search(r"vessel stub trim skipped.*would remove (3\d|4\d)% .*at most 25%", w) for w in caught), caught
    model, m = _metrics(tmp_path / "model", volume, heart_less_artery)
    assert 650.0 <= check_mesh(model.mesh_patient()).volume_mm3 / 1000.0 <= 850.0
    assert m["dice"] >= 0.83 and m["msd_mm"] <= 4.5, m
    assert -model.frame.axes_patient[:, 2] @ APEX_LAI_LPS > 0.8


@pytest.mark.parametrize("sd_hu", [50.0, 100.0])
def test_noise(realct, heart_less_artery, sd_hu):
    """The real CT with white noise of 50 or 100 HU standard deviation added (low-dose scans'): the same heart.

    Noise above the blood pool's upper bound (650 HU) left speckled holes in the pool, the left atrium's
    inscribed radius fell from 24 mm to 16-18, and the vessel trace took its lobes at the field of view's edge
    for vessels leaving it: with this draw at 50 HU 426 ml were left (with 40 HU of noise, another draw: 29 lobes,
    368 ml of "lumen", 469 ml, Dice 0.760 against the whole reference; session 15's robustness sweep).  The
    pool's cavities are now blood (session 15: 606 ml, Dice 0.877, MSD 3.2 mm against the reference less its
    pulmonary artery at 50 HU), and the coarse grid is smoothed more as the blood's noise rises above 40 HU
    (session 19; a helper's sweep had the model collapse from 60 HU on: 70 HU 357 ml, 100 HU 145 ml).
    Measured: 50 HU 704 ml, Dice 0.898, MSD 2.6 mm; 100 HU 727 ml, 0.890, 2.7 mm (the CT as read: 707 ml, 0.898,
    2.7 mm); the noise read from the blood 64 and 108 HU.
    """
    volume, _, _ = realct
    noise = np.random.default_rng(1).normal(0.0, sd_hu, volume.shape)
    seg = segment_heart(np.rint(volume.hu + noise).astype(np.int16), volume.T_patient_from_voxel)
    m = overlap(seg.mask, heart_less_artery, SPACING)
    assert 620.0 <= seg.volume_ml <= 800.0 and m["dice"] >= 0.87 and m["msd_mm"] <= 3.0, (seg.volume_ml, m)
    assert any(n.startswith("noisy CT (the blood's noise") for n in seg.notes)


def test_a_mask_in_two_pieces_is_said(realct, tmp_path):
    """The reference with one slice cleared (two pieces, 381 and 277 ml): the model meshes the larger and
    says how much it left out (before session 16 half the heart went without a word)."""
    volume, _, reference = realct
    split = reference.copy()
    split[:, :, 60] = False
    ct = nib.load(str(REALCT / "ct_cropped.nii.gz"))
    nib.save(nib.Nifti1Image(split.transpose(2, 1, 0).astype(np.uint8), ct.affine), str(tmp_path / "split.nii.gz"))
    with pytest.warns(ModelingWarning, match=r"the mask holds 2 separate pieces, 277.4 ml of it outside the "
                                             r"largest \(381 ml\), which is left out"):
        build = build_heart_model(volume, cardiac_phase=None, cardiac_phase_source="none", target_faces=4000,
                                  mask_path=tmp_path / "split.nii.gz")
    assert any("separate pieces" in w for w in build.model.parameters["warnings"])  # and in model.json


def _streaked(tmp_path, slices, change, lead: bool = False) -> object:
    """The real CT with three lines through the heart's centre in each of ``slices`` (a session-19 hunt's),
    each line's voxels changed by ``change`` (HU -> HU), and with ``lead`` a lead's wire (:func:`_with_lead`),
    read back as a volume."""
    ct = nib.load(str(REALCT / "ct_cropped.nii.gz"))
    data = np.asanyarray(ct.dataobj).astype(np.int32)  # [i, j, k], RAS
    t = np.linspace(-80, 80, 400)
    for k in slices:
        for angle in np.linspace(0.3, 0.3 + np.pi, 3, endpoint=False):
            i = np.rint(61 + t * np.cos(angle + k * 0.05)).astype(int)
            j = np.rint(51 + t * np.sin(angle + k * 0.05)).astype(int)
            ok = (i >= 0) & (i < data.shape[0]) & (j >= 0) & (j < data.shape[1])
            data[i[ok], j[ok], k] = change(data[i[ok], j[ok], k])
    if lead:
        _with_lead(data)
    nib.save(nib.Nifti1Image(data.clip(-1024, 3071).astype(np.int16), ct.affine), str(tmp_path / "streaks.nii.gz"))
    return read_nifti_volume(tmp_path / "streaks.nii.gz")


def _with_lead(data) -> None:
    """Paint a pacing lead's wire (3071 HU, one voxel thick) along ``LEAD_KJI`` into ``data[i, j, k]``."""
    points = np.asarray(LEAD_KJI, float)
    for a, b in zip(points[:-1], points[1:]):
        for t in np.linspace(0.0, 1.0, int(4 * np.linalg.norm(b - a)) + 1):
            k, j, i = np.rint(a + t * (b - a)).astype(int)
            data[i, j, k] = 3071


def test_a_lead_beside_the_heart_is_said(tmp_path, auto_model):
    """A pacing lead's wire (3071 HU, one voxel thick) from the superior vena cava through the right atrium to the
    right ventricle's apex: the model is built and warned of it, in model.json too, since a real lead's streaks
    can part or shrink the chambers (``modeling.metal``; ``bench/realct_robustness.py``'s simulated scans: a
    harsh one lost 140 ml of the right heart without a word).  The CT as read is not warned: its stent graft,
    sternal wires and the dense contrast in its superior vena cava lie farther than 5 mm from the heart."""
    assert not any("metal in or beside the heart" in w for w in auto_model[1])
    ct = nib.load(str(REALCT / "ct_cropped.nii.gz"))
    data = np.asanyarray(ct.dataobj).astype(np.int16)  # [i, j, k]
    _with_lead(data)
    nib.save(nib.Nifti1Image(data, ct.affine), str(tmp_path / "lead.nii.gz"))
    volume = read_nifti_volume(tmp_path / "lead.nii.gz")
    with pytest.warns(ModelingWarning, match=r"metal in or beside the heart \((\d+) mm\^3 above 3000 HU within 5 mm "
                                             r"of it: a pacing or defibrillator lead\?\)") as caught:
        build = build_heart_model(volume, cardiac_phase=None, cardiac_phase_source="none", target_faces=4000)
    said = next(str(w.message) for w in caught if "metal in or beside" in str(w.message))
    assert 200 <= float(re.search(r"\((\d+) mm", said)[1]) <= 800, said  # the wire: 135 voxels, 456 mm^3
    assert said in build.model.parameters["warnings"]
    assert 650 <= build.model.mesh.volume_mm3 / 1000 <= 760  # one voxel's wire parts nothing (thin metal)


@pytest.mark.parametrize("slices", [range(50, 60, 2), range(30, 90, 6)])
def test_metal_lines_through_the_heart_part_nothing(tmp_path, heart_less_artery, slices):
    """Lines of metal (3000 HU, one voxel thick) in five slices 3 mm apart, or every 9 mm: above any tissue's
    HU they were neither tissue nor blood, parted the chambers and left no room for the heart body's ball:
    415 and 207 ml of 707 (Dice 0.70 and 0.43 against the reference), the apex reversed, no warning.  Thin
    metal now takes its surroundings' level (``modeling.coarse.without_thin_metal``): measured 709 and 708 ml,
    Dice 0.898, as the CT as read."""
    volume = _streaked(tmp_path, slices, lambda hu: np.full_like(hu, 3000))
    seg = segment_heart(volume.hu, volume.T_patient_from_voxel)
    m = overlap(seg.mask, heart_less_artery, SPACING)
    assert 680.0 <= seg.volume_ml <= 740.0 and m["dice"] >= 0.89, (seg.volume_ml, m)


def test_a_seed_in_contrast_blood_finds_its_pool(tmp_path):
    """Dark streaks (-600 HU lines through the heart every 9 mm, as beside metal) part the blood pool so that no
    piece holds a chamber's ball: the automatic seed finds no pool and the segmentation fails, and the seed it
    suggests was refused as "not in heart tissue (510 HU outside 0..150)": a seed in contrast blood went down the
    path of a CT without contrast.  Now the blood connected to the seed is the pool (measured: a model of
    263 ml: the streaks still part the chambers, a limit of the segmentation's ball openings; the CT without
    them, seeded there, 708 ml).  Since session 29 a pool need hold only a 13 mm ball (a pulmonary CTA's right
    heart), and the streaked pool holds one: the automatic path then makes a poor model (385 ml, Dice 0.67
    against the reference less its artery, warned "vessel cut skipped"); with the earlier 15 mm the pool is
    now found smoothed for the streaks' noise (720 ml, 0.882).  The test asks for a ball no pool holds (40 mm,
    ``min_pool_radius_mm``), which the streaks used to make of 15 mm, for the path it tests (measured 385 ml)."""
    volume = _streaked(tmp_path, range(30, 90, 6), lambda hu: hu - 600)
    with pytest.raises(SegmentationError, match="no heart-sized region"):
        segment_heart(volume.hu, volume.T_patient_from_voxel, min_pool_radius_mm=40.0)
    seed = (40.0, -190.0, 630.0)  # LPS mm, in the left ventricle's blood
    seg = segment_heart(volume.hu, volume.T_patient_from_voxel, seed_patient_mm=seed, min_pool_radius_mm=40.0)
    assert "blood pool: the contrast blood around the given point (above 200 HU)" in seg.notes
    assert seg.parameters["contrast"] is True and seg.volume_ml >= 200.0, seg.volume_ml


def test_a_refusal_says_a_lead_may_be_why(tmp_path):
    """Streaks part the blood pool (dark lines every 9 mm) and a lead's wire runs through the right heart: the
    refusal names the lead as a likely cause, which 'no blood pool was found: with contrast too weak...' did
    not (a simulated defibrillator lead's scan gave only that); without the wire it says nothing of metal.  With
    a ball no pool holds (40 mm), as these streaks left none of 15 mm before session 29
    (:func:`test_a_seed_in_contrast_blood_finds_its_pool`)."""
    with pytest.raises(SegmentationError, match=r"no heart-sized region.*; the CT holds metal \(a piece 1[0-9]{2} mm "
                                                r"long above 3000 HU: a pacing or defibrillator lead\?\)"):
        build_heart_model(_streaked(tmp_path, range(30, 90, 6), lambda hu: hu - 600, lead=True), cardiac_phase=None,
                          cardiac_phase_source="none", target_faces=4000, segmentation={"min_pool_radius_mm": 40.0})
    # without the wire nothing is said of metal (the CT's stent graft and sternal wires are no lead), nor after
    # a refusal a lead cannot cause
    from modeling.metal import metal_in_chest

    plain = _streaked(tmp_path, range(30, 90, 6), lambda hu: hu - 600)
    assert metal_in_chest(plain.hu, plain.T_patient_from_voxel, refusal="no heart-sized region: ...") == ""
    wired = _streaked(tmp_path, range(30, 90, 6), lambda hu: hu - 600, lead=True)
    assert metal_in_chest(wired.hu, wired.T_patient_from_voxel, refusal="seed point lies outside the volume") == ""


@pytest.mark.parametrize("spacing_mm", [1.0, 2.0])
def test_the_same_ct_at_finer_or_coarser_voxels(realct, artery, heart_less_artery, spacing_mm):
    """The CT resampled (linear) to 1 mm isotropic voxels, as a sub-millimetre CTA reaches the segmentation,
    or to 2 mm, gives the same heart: Dice >= 0.88 against the reference less its pulmonary artery, at most
    2 ml of the artery kept.

    Until session 22 it did not (a strict xfail at 1 mm): thin fat planes between the heart, the ascending
    aorta, the pulmonary trunk and the tissue behind the left atrium blur into the tissue range, the heart's
    region runs on into them and the heart body (the ball opening) covers the ascending aorta and the
    pulmonary trunk's root, so the vessel trace does not enter them.  Segmentation Dice (as read / 2 mm /
    1 mm / 0.75 mm / 1 x 0.5 x 0.5 mm / 3 mm slices) 0.901 / 0.853 / 0.845 / 0.862 / 0.837 / 0.880, 0.2 /
    0 / 17 / 10 / 20 / 0.1 ml of artery; at 2 mm 68 ml of the posterior mediastinum (oesophagus, the
    descending aorta's surroundings) joined the left atrium and the model reached the field of view's
    posterior edge.  Now the region is parted also at the planes' remains, valleys of the HU found by
    their shape (:mod:`modeling.planes`): as read 0.908, 2 mm 0.895, 1 mm 0.888, 0.75 mm 0.909, artery
    0.7 / 0 / 0.1 / 2.0 ml (the mesh through ``heartreg model``: ``bench/realct_robustness.py``).

    Tried before and not kept (session 21): a finer coarse grid (``coarse_mm`` 1.0 or 1.5 at 1 mm: 0.843 /
    0.845); coarse tissue joining the heart's region only above 30 HU (0.903 / 0.892 / 0.879 / 0.891 /
    0.884 / 0.893, but the phantoms' noise leaves single coarse voxels of 20-30 HU inside the myocardium and
    the opening takes a dent around each: spheroid sample 465 -> 436 ml); the same parting only where more
    than two of a voxel's 26 neighbours are weak (the descending aorta joined the left atrium again at 1 mm,
    ``test_thick_voxels`` fell to 0.848).  The valleys' shape tells a plane from a speck where the HU level
    alone cannot, and only sheets of 30 mm² or more part anything: the spheroid sample keeps its 465 ml."""
    from scipy import ndimage

    volume = realct[0]
    T = volume.T_patient_from_voxel
    fine = ndimage.zoom(volume.hu.astype(np.float32), SPACING[0] / spacing_mm, order=1)
    T_fine = T.copy()
    T_fine[:3, :3] *= ((np.array(volume.shape) - 1) / (np.array(fine.shape) - 1))[::-1]  # the same corners
    seg = segment_heart(np.rint(fine), T_fine)
    # back on the CT's grid: the fine voxel nearest each CT voxel's centre
    centres = np.indices(volume.shape).reshape(3, -1)[::-1].T.astype(float)
    at = apply_to_points(np.linalg.inv(T_fine) @ T, centres)[:, ::-1]
    kji = np.clip(np.rint(at).astype(int), 0, np.array(fine.shape) - 1)
    mask = seg.mask[tuple(kji.T)].reshape(volume.shape)
    m = overlap(mask, heart_less_artery, SPACING)
    artery_ml = (mask & artery).sum() * np.prod(SPACING) / 1000.0
    assert m["dice"] >= 0.88 and artery_ml <= 2.0, (m, artery_ml)
