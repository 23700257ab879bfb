"""The model on a real chest CT *without contrast*: ``CTChest4.nrrd`` of the slicerio package.

128 x 128 x 34 voxels of 3 x 3 x 10 mm, no reference mask: a coarse smoke case.
Without contrast there is no blood pool to start from (the largest 200-650 HU
component is the skeleton); the segmentation must say so and start from the
soft tissue between the lungs.  The CT is converted to NIfTI (LPS -> RAS) and
read through :func:`imaging.volume_file.read_nifti_volume`, as a user's file would be.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from imaging.volume_file import read_nifti_volume
from modeling.build import ModelingWarning, build_heart_model
from modeling.segment import segment_heart
from modeling.vessels import APEX_LAI_LPS
from hrcore.geometry import apply_to_points
from tests.data.fetch_real_cts import paths as real_cts
from tests.modeling.realct import mesh_to_mask

nrrd = pytest.importorskip("nrrd")
slicerio = pytest.importorskip("slicerio")
CTCHEST4 = Path(slicerio.__file__).parent / "data" / "CTChest4.nrrd"
pytestmark = pytest.mark.skipif(not CTCHEST4.is_file(), reason="slicerio's CTChest4.nrrd is missing")


@pytest.fixture(scope="module")
def chest4(tmp_path_factory):
    """(volume, segmentation, build, ModelingWarning messages): the CLI's defaults."""
    data, header = nrrd.read(str(CTCHEST4))
    assert header["space"] == "left-posterior-superior"
    A = np.eye(4)
    A[:3, :3] = np.asarray(header["space directions"], float).T
    A[:3, 3] = header["space origin"]
    path = tmp_path_factory.mktemp("chest4") / "ct.nii.gz"
    nib.save(nib.Nifti1Image(data.astype(np.int16), np.diag([-1.0, -1.0, 1.0, 1.0]) @ A), str(path))
    volume = read_nifti_volume(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build = build_heart_model(volume, cardiac_phase=None, cardiac_phase_source="a NIfTI volume has no slice clock",
                                  expected_fiducials="auto", target_faces=4000)
    seg = segment_heart(volume.hu, volume.T_patient_from_voxel)  # 2 s: its seed and volume
    return volume, seg, build, [str(w.message) for w in caught if issubclass(w.category, ModelingWarning)]


def test_no_contrast_seeds_between_the_lungs(chest4):
    volume, seg, build, caught = chest4
    notes = " ".join(build.notes)
    assert "no contrast blood pool" in notes and "between the lungs" in notes
    # 10 mm slices, 3 mm pixels: the surface stays the mesh's (shape-based between the slices)
    assert "surface kept as meshed, not moved onto the CT's edge: voxels of 3 x 3 x 10 mm" in notes
    assert build.model.parameters["refined_to_edge_hu"] is None
    assert build.model.parameters["segmentation"]["contrast"] is False
    T = volume.T_patient_from_voxel
    i, j, k = np.rint(np.linalg.solve(T[:3, :3], seg.seed_patient_mm - T[:3, 3])).astype(int)
    # the seed is soft tissue (blood and myocardium without contrast, 0-100 HU), not the spine (round 1's
    # start: bone marrow at 200-650 HU)
    assert 0 <= volume.hu[k, j, i] <= 100
    # ... at least 40 mm in front of the vertebral bodies (bone of the seed's slice, behind the seed's row)
    bone_j = np.flatnonzero((volume.hu[k, :, max(i - 5, 0) : i + 6] > 300).any(axis=1))
    bone_y = T[1, 1] * bone_j + T[1, 3]
    assert np.max(bone_y) > seg.seed_patient_mm[1] + 40.0
    # the model is made (no abort); its odd findings are warnings
    assert any("cannot form 3 equal rows" in w or "no skin markers" in w for w in caught)
    assert any("no contrast vessels leave the heart" in w for w in caught)


def test_heart_volume_and_apex(chest4):
    """Issue 9: an adult heart's volume, the apex towards patient left-anterior-inferior.

    Measured 474 ml, apex . LAI 0.98.  The soft tissue between the lungs holds the heart, the liver's dome
    beneath the diaphragm and the great vessels above it.  The liver is parted first (328 ml: tissue below the
    heart body and farther than 30 mm from it, flooded up to the diaphragm's dimmest layer); the vessels are then
    one branch, thick for 25 mm (the atria), cut there.  Before the liver was parted it was a second branch, cut
    10 mm from the body (447 ml); cut 10 mm from the body both, the atria went with the vessels (362 ml, the
    lower ventricles, apex to the right).
    """
    _, seg, build, caught = chest4
    assert 400.0 <= seg.volume_ml <= 1100.0  # issue 9: an adult heart with the 10 mm slices' partial volume
    notes = " ".join(seg.notes)
    assert "soft tissue below the heart parted from it" in notes and "cut 25 mm from it" in notes
    apex = -build.model.frame.axes_patient[:, 2]
    assert apex @ APEX_LAI_LPS > 0.7
    # no contrast lumen to trim stubs over (it trimmed the calcified rings and bone it took for lumen)
    assert any("vessel stub trim skipped: the CT has no contrast blood" in w for w in caught)


def test_the_nrrd_file_as_it_is(chest4, tmp_path, capsys):
    """3D Slicer's own format: ``heartreg model CTChest4.nrrd`` reads it directly, as the NIfTI copy."""
    import json

    from heartreg.cli import main
    from imaging.volume_file import read_volume_file

    volume = chest4[0]
    direct = read_volume_file(CTCHEST4)
    assert np.array_equal(direct.hu, volume.hu)
    np.testing.assert_allclose(direct.T_patient_from_voxel, volume.T_patient_from_voxel, atol=1e-4)
    out = tmp_path / "model"
    assert main(["model", str(CTCHEST4), "-o", str(out), "-q", "--faces", "4000"]) == 0
    payload = json.loads((out / "model.json").read_text())
    assert payload["cardiac_phase"] is None and payload["cardiac_phase_source"] == "an NRRD volume has no slice clock"
    assert str(CTCHEST4.parent) not in json.dumps(payload)  # no folder path in the model
    assert main(["model", str(CTCHEST4), "-o", str(tmp_path / "m2"), "-q", "--qrs", "r.csv"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--qrs and --series apply to DICOM studies, not to the NRRD file" in err[0]


# ---- pyradiomics' lung2: a full-field chest CT without contrast, 5 mm slices (tests/data/fetch_real_cts.py)

LUNG2 = real_cts()["lung2_image.nrrd"]
#: Points read off the CT by eye (LPS mm): the middle of the right atrium and of the left ventricle on the same
#: slice, and the liver's dome 65 mm lower, under the right lung.
LUNG2_RIGHT_ATRIUM = (-35.7, -196.0, -235.0)
LUNG2_LEFT_VENTRICLE = (36.4, -205.4, -235.0)
LUNG2_LIVER = (-60.8, -199.1, -300.0)


@pytest.mark.skipif(not LUNG2.is_file(), reason="pyradiomics' lung2_image.nrrd was not fetched (offline)")
def test_full_chest_without_contrast(tmp_path):
    """The whole chest and the liver, no contrast: the heart with its right atrium, without the liver.

    Before (measured): 379 ml, no right atrium, apex along patient right-anterior (warned): the liver's dome,
    joined to the heart across the diaphragm, and the right atrium formed one branch of the heart body, cut
    10 mm from it.  Now the liver is parted at the diaphragm (391 ml) and the right atrium, a branch that rounds
    off 15 mm past its thick part, is kept: 486 ml, apex towards left-anterior-inferior.
    """
    from imaging.volume_file import read_volume_file
    from modeling.mesh import check_mesh

    volume = read_volume_file(LUNG2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build = build_heart_model(volume, cardiac_phase=None, cardiac_phase_source="an NRRD volume has no slice clock",
                                  expected_fiducials="auto", target_faces=8000)
    messages = [str(w.message) for w in caught if issubclass(w.category, ModelingWarning)]
    notes = " ".join(build.notes)
    assert "no contrast blood pool" in notes and "soft tissue below the heart parted from it" in notes
    mesh = build.model.mesh_patient()
    volume_ml = check_mesh(mesh).volume_mm3 / 1000.0
    assert 400.0 <= volume_ml <= 1100.0, volume_ml
    T = volume.T_patient_from_voxel
    solid = mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, T)
    i, j, k = np.rint(apply_to_points(np.linalg.inv(T), [LUNG2_RIGHT_ATRIUM, LUNG2_LEFT_VENTRICLE, LUNG2_LIVER])).astype(int).T
    inside = solid[k, j, i]
    assert inside.tolist() == [True, True, False]
    apex = -build.model.frame.axes_patient[:, 2]
    assert apex @ APEX_LAI_LPS > 0.7, apex
    assert not any("not towards patient left-anterior-inferior" in m for m in messages)



# ---- pyradiomics' lung1: no contrast, the scan from the neck down to the heart's lower wall

LUNG1 = real_cts()["lung1_image.nrrd"]
#: The middle of the left atrium and of the left ventricle (LPS mm, read off the CT by eye).
LUNG1_LEFT_ATRIUM = (27.9, -114.0, -717.5)
LUNG1_LEFT_VENTRICLE = (42.2, -153.9, -747.5)


@pytest.fixture(scope="module")
def lung1():
    """(segmentation, the two points' voxel indices (k, j, i) as arrays)."""
    from imaging.volume_file import read_volume_file

    if not LUNG1.is_file():
        pytest.skip("pyradiomics' lung1_image.nrrd was not fetched (offline)")
    volume = read_volume_file(LUNG1)
    T = volume.T_patient_from_voxel
    i, j, k = np.rint(apply_to_points(np.linalg.inv(T), [LUNG1_LEFT_ATRIUM, LUNG1_LEFT_VENTRICLE])).astype(int).T
    return segment_heart(volume.hu, T), (k, j, i)


def test_ventricles_without_contrast(lung1):
    seg, (k, j, i) = lung1
    assert seg.parameters["contrast"] is False and seg.mask[k[1], j[1], i[1]]


def test_a_heart_cut_one_slice_short_of_the_edge_is_warned(lung1):
    """The scan ends below the heart's lower wall; the mask stops one 5 mm slice short of the edge
    (0 voxels on it, 17 cm² one slice in) and the model ends flat there: warned as cut by the field of view
    (it was not: only the edge layer counted)."""
    from modeling.build import _cut_by_field_of_view, _volume_cause
    from imaging.volume_file import read_volume_file

    seg, _ = lung1
    assert not seg.mask[0].any() and seg.mask[1].sum() > 4000
    T = read_volume_file(LUNG1).T_patient_from_voxel
    assert _cut_by_field_of_view(seg.mask, T).startswith("inferior side, 17 cm²")
    two_short = np.concatenate([np.zeros_like(seg.mask[:1]), seg.mask])  # a slice more below: rounded off inside
    assert _cut_by_field_of_view(two_short, T) == ""
    # the small volume's hint names the likeliest cause
    cut, not_cut = _cut_by_field_of_view(seg.mask, T), _cut_by_field_of_view(two_short, T)
    assert _volume_cause(seg.volume_ml, seg.parameters, cut) == "a heart cut by the field of view"
    assert _volume_cause(seg.volume_ml, seg.parameters, not_cut) == "a CT without contrast"
    assert _volume_cause(seg.volume_ml, {"contrast": True}, not_cut).startswith("chambers parted by noise")


@pytest.mark.xfail(strict=True, reason="known limit without contrast: fat planes around the aortic root and in the "
                   "atrioventricular grooves divide the heart's base into lobes 25-35 mm across on 5 mm slices, "
                   "which the 28 mm opening against bridges removes with the vessels (measured 166 ml, the "
                   "ventricles only; the volume warned as unusual)")
def test_heart_base_divided_by_fat(lung1):
    seg, (k, j, i) = lung1
    assert seg.volume_ml >= 250.0 and seg.mask[k[0], j[0], i[0]], seg.volume_ml


@pytest.mark.skipif(not LUNG2.is_file(), reason="pyradiomics' lung2_image.nrrd was not fetched (offline)")
def test_seeded_without_contrast():
    """``--seed`` in a CT without contrast takes the same path as the automatic seed (measured: the same 488 ml).

    Before, a given seed left the segmentation in its contrast path: no liver parted, tissue up to 1500 HU,
    no restriction to the space between the lungs (2048 ml, the liver's dome inside).
    """
    from imaging.volume_file import read_volume_file

    volume = read_volume_file(LUNG2)
    T = volume.T_patient_from_voxel
    seeded = segment_heart(volume.hu, T, seed_patient_mm=LUNG2_LEFT_VENTRICLE)
    assert seeded.parameters["contrast"] is False
    assert "soft tissue below the heart parted from it" in " ".join(seeded.notes)
    i, j, k = np.rint(apply_to_points(np.linalg.inv(T), [LUNG2_RIGHT_ATRIUM, LUNG2_LIVER])).astype(int).T
    assert seeded.mask[k, j, i].tolist() == [True, False]
    assert 400.0 <= seeded.volume_ml <= 1100.0


def test_stored_with_the_slices_along_another_axis(chest4):
    """The same CT stored sagittally (the slice axis last in the array): the same heart.

    The seed between the lungs takes the lungs' hull in axial planes, whichever array axis runs along the
    patient's height (before: the hull was taken in the array's first-axis planes, sagittal here: 371 ml
    instead of 474).
    """
    volume, seg, _, _ = chest4
    T = volume.T_patient_from_voxel.copy()
    T[:3, :3] = T[:3, [2, 1, 0]]
    stored = segment_heart(np.ascontiguousarray(volume.hu.transpose(2, 1, 0)), T)
    assert np.array_equal(stored.mask.transpose(2, 1, 0), seg.mask)
