"""The model command on a second real contrast CT: TotalSegmentator's aortic CTA.

An early-arterial aortic CTA of the whole chest (233 x 167 x 191 voxels,
1.5 mm, NIfTI in LPS, not gated, no skin markers) from TotalSegmentator's
source archive (``tests/data/fetch_real_cts.py``), with TotalSegmentator's own
masks of its aorta, its aortic annulus and its sinotubular junction.  No heart
mask ships with it; what the masks give is where the aorta leaves the heart,
the check of issue 9's "great vessels cut at their origin" on real anatomy.
The four chambers' points and the ascending aorta's were read off the CT by eye.

Measured (``heartreg model ct.nii.gz``, default options): 703 ml; the annulus
57 % inside the surface, the sinotubular junction (20 mm up the lumen) 0 %, the
aorta farther than 2.1 mm from the annulus nowhere; apex . LAI 0.91; the
pulmonary trunk and the right pulmonary artery outside (until session 11 the
model kept the trunk up to its bifurcation: 734 ml, apex . LAI 0.94; no
pulmonary lobe reaches this field of view's edge, the arteries end in the lungs).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from skimage.graph import MCP_Geometric

from heartreg.cli import main
from hrcore.geometry import apply_to_points
from imaging.volume_file import read_volume_file
from modeling import read_model
from modeling.labelmap import mask_on_grid, read_label_map
from modeling.mesh import check_mesh
from modeling.segment import segment_heart
from modeling.vessels import APEX_LAI_LPS
from tests.data.fetch_real_cts import paths as real_cts
from tests.modeling.realct import mesh_to_mask

AORTIC_CTA = real_cts()["ts_aorta/ct.nii.gz"].parent
pytestmark = pytest.mark.skipif(
    not all(path.is_file() for name, path in real_cts().items() if name.startswith("ts_aorta/")),
    reason="TotalSegmentator's aortic CTA was not fetched whole (offline)")

#: Read off the CT by eye (LPS mm): the middle of each chamber on a four-chamber slice (z 630.2) and of
#: the left atrium at the aortic valve's level (z 667.7); the ascending aorta 21 mm above that level.
INSIDE = {
    "right atrium": (-35.0, -178.0, 630.2),
    "right ventricle": (10.0, -215.0, 630.2),
    "left ventricle": (40.0, -175.0, 630.2),
    "left atrium": (0.0, -150.0, 667.7),
}
ASCENDING_AORTA = (5.0, -190.0, 688.7)
#: The pulmonary trunk where it curves back to its bifurcation, and the right pulmonary artery behind the
#: ascending aorta (read off the CT by eye, LPS mm): vessel beyond the pulmonary valve, not heart.
PULMONARY_ARTERY = {"pulmonary trunk": (38.0, -185.0, 692.0), "right pulmonary artery": (0.0, -158.0, 698.0)}


@pytest.fixture(scope="module")
def cta():
    """The CT as read: every model is judged on its grid."""
    return read_volume_file(AORTIC_CTA / "ct.nii.gz")


@pytest.fixture(scope="module")
def cta_model(tmp_path_factory, cta):
    out = tmp_path_factory.mktemp("aortic_cta") / "model"
    rc = main(["model", str(AORTIC_CTA / "ct.nii.gz"), "-o", str(out), "-q"])
    model = read_model(out)
    return rc, out, model, _solid(model.mesh_patient(), cta)


def _solid(mesh, volume):
    return mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, volume.T_patient_from_voxel)


def _at(mask, T, points) -> list[bool]:
    """``mask``'s value at each LPS point (mm), on the grid of ``T``."""
    i, j, k = np.rint(apply_to_points(np.linalg.inv(T), list(points))).astype(int).T
    return mask[k, j, i].tolist()


def _aorta_labels(shape, T):
    """TotalSegmentator's aorta farther than 10 mm up its lumen from the annulus, the annulus, the
    sinotubular junction (on the grid of ``shape``, ``T``), and the grid's voxel volume (mm³)."""
    aorta, annulus, junction = (mask_on_grid(read_label_map(AORTIC_CTA / f"{n}.nii.gz"), shape, T)
                                for n in ("aorta", "annulus", "sinotubular_junction"))
    spacing = tuple(np.linalg.norm(np.asarray(T, dtype=float)[:3, :3], axis=0)[::-1])
    along, _ = MCP_Geometric(np.where(aorta | annulus | junction, 1.0, np.inf),
                             sampling=spacing).find_costs(np.argwhere(annulus))
    return aorta & np.isfinite(along) & (along > 10.0), annulus, junction, float(np.prod(spacing))


def _slices_from_600_mm(cta, stop):
    """The CT's slices 40 (600 mm) to ``stop`` (exclusive): the HU and their voxel-to-patient transform."""
    T = np.asarray(cta.T_patient_from_voxel, dtype=float).copy()
    T[:3, 3] = T[:3, :3] @ [0, 0, 40] + T[:3, 3]
    return np.ascontiguousarray(cta.hu[40:stop]), T


def _model_of(tmp_path, data, affine):
    """``heartreg model`` of a NIfTI made of ``data`` and ``affine`` (8000 faces): the model."""
    import nibabel as nib

    path = tmp_path / "ct.nii.gz"
    nib.save(nib.Nifti1Image(data, affine), str(path))
    assert main(["model", str(path), "-o", str(tmp_path / "model"), "-q", "--faces", "8000"]) == 0
    return read_model(tmp_path / "model")


def test_model_of_the_whole_heart(cta_model, cta):
    rc, out, model, solid = cta_model
    assert rc == 0
    volume_ml = check_mesh(model.mesh_patient()).volume_mm3 / 1000.0
    assert 550.0 <= volume_ml <= 950.0, volume_ml
    inside = _at(solid, cta.T_patient_from_voxel, [*INSIDE.values(), ASCENDING_AORTA, *PULMONARY_ARTERY.values()])
    assert dict(zip([*INSIDE, "ascending aorta", *PULMONARY_ARTERY], inside)) == {
        **dict.fromkeys(INSIDE, True), "ascending aorta": False, **dict.fromkeys(PULMONARY_ARTERY, False)}
    apex = -model.frame.axes_patient[:, 2]
    assert apex @ APEX_LAI_LPS > 0.8, apex
    saved = json.loads((out / "model.json").read_text())
    assert saved["fiducials_patient_mm"] == [] and saved["cardiac_phase"] is None  # no markers, no gating


def test_aorta_cut_at_its_valve(cta_model, cta):
    """The surface crosses the aortic annulus and leaves out the aorta beyond it: of the aorta's lumen
    farther than 10 mm from the annulus (along the lumen), at most 1 % is inside; at least a quarter of
    the annulus is inside (the cut is not below it, in the outflow tract) and at most a tenth of the
    sinotubular junction (the root is not kept)."""
    solid = cta_model[-1]
    far, annulus, junction, voxel_mm3 = _aorta_labels(cta.shape, cta.T_patient_from_voxel)
    assert far.sum() * voxel_mm3 > 200e3  # the aorta is there to be cut: > 200 ml of it beyond 10 mm
    assert (far & solid).sum() <= 0.01 * far.sum()
    assert (annulus & solid).sum() >= 0.25 * annulus.sum()
    assert (junction & solid).sum() <= 0.10 * junction.sum()


#: Liver, 25 mm below the heart's lowest point (LPS mm, read off the CT by eye).
LIVER = (-40.0, -190.0, 574.7)


@pytest.mark.parametrize("averaged", [True, False], ids=["averaged", "every-third"])
def test_thick_slices_keep_the_liver_out(tmp_path, cta, averaged):
    """The same CT on 4.5 mm slices, as a routine chest CT is reconstructed: averaged three by three, or
    every third 1.5 mm slice kept (noisier).  The diaphragm blurs into the heart's and the liver's tissue,
    and contrast refluxed into the inferior vena cava and the liver's veins joins them to the blood pool.

    Measured before the heart's seeds were limited to the pool near its chambers
    (``modeling.seed._heart_seeds``), the liver marked by blood that is no mere speck: 1095 ml with a lobe
    of liver, apex . LAI 0.37 (averaged); 850 ml with a lobe of liver (every third).  Now 806 and 701 ml
    without it (the full CT: 734 ml); 780 and 668 ml since the pulmonary trunk is cut (session 11; the full
    CT: 703 ml)."""
    import nibabel as nib

    image = nib.load(AORTIC_CTA / "ct.nii.gz")
    data = np.asanyarray(image.dataobj)
    n = data.shape[2] // 3 * 3
    groups = data[:, :, :n].reshape(*data.shape[:2], n // 3, 3)
    thick = groups.mean(axis=3).round().astype(np.int16) if averaged else groups[..., 1]
    affine = image.affine.copy()
    affine[:3, 3] += affine[:3, 2]  # the centre of each group of three slices
    affine[:3, 2] *= 3
    model = _model_of(tmp_path, thick, affine)
    mesh = model.mesh_patient()
    volume_ml = check_mesh(mesh).volume_mm3 / 1000.0
    assert 550.0 <= volume_ml <= 950.0, volume_ml
    assert _at(_solid(mesh, cta), cta.T_patient_from_voxel, [*INSIDE.values(), LIVER]) == [True] * len(INSIDE) + [False]
    assert -model.frame.axes_patient[:, 2] @ APEX_LAI_LPS > 0.8


def test_thick_slices_cut_just_below_the_heart_keep_the_liver_dome_out(cta):
    """4.5 mm slices (averaged three by three) from 15 mm below the heart: the CT shows the liver's dome alone,
    and in its slices the lungs' bases wrap around it, so it lies between the lungs.  Sparing all solid tissue
    between the lungs (for a right heart washed out by a saline chaser, ``modeling.seed.split_solid_organs``)
    kept 331 ml of liver (1238 ml, a review); with the tissue just under a lung's base not spared, 979 ml
    (before the sparing 908; the same CT whole on 4.5 mm slices 824, on its 1.5 mm slices 707)."""
    k0 = 30
    n = (cta.shape[0] - k0) // 3 * 3
    thick = cta.hu[k0:k0 + n].reshape(n // 3, 3, *cta.shape[1:]).mean(axis=1).round().astype(np.int16)
    T = cta.T_patient_from_voxel.copy()
    T[:3, 3] += T[:3, :3] @ [0.0, 0.0, k0 + 1.0]  # the centre of each group of three slices
    T[:3, 2] *= 3
    seg = segment_heart(thick, T)
    assert seg.volume_ml <= 1000.0, seg.volume_ml
    assert _at(seg.mask, T, INSIDE.values()) == [True] * len(INSIDE)


def test_a_field_of_view_through_the_right_ventricle(tmp_path, cta):
    """The CT cropped as a cardiac reconstruction might be (600-748 mm in height, 195 x 203 mm across): its
    lower edge cuts through the right ventricle's thin crescent.  There the crescent is a lobe of the blood
    pool 10.6 mm in radius, as narrow and as compact on the edge as a vessel leaving the field of view; it
    was traced as one and 39 ml of ventricle removed (690 ml, the right-ventricle point outside, measured).
    A lobe whose footprint on the edge lies mostly inside the heart's body (91 % here; every vessel leaving
    the real CTs' edges: 0 %) is now a chamber cut by the edge: 742 ml, all four points inside, the cut
    warned (710 ml since the pulmonary trunk is cut, session 11)."""
    import nibabel as nib

    image = nib.load(AORTIC_CTA / "ct.nii.gz")
    crop = (slice(50, 180), slice(15, 150), slice(40, 140))
    affine = image.affine.copy()
    affine[:3, 3] = (image.affine @ [50, 15, 40, 1])[:3]
    model = _model_of(tmp_path, np.asanyarray(image.dataobj)[crop], affine)
    mesh = model.mesh_patient()
    assert 600.0 <= check_mesh(mesh).volume_mm3 / 1000.0 <= 900.0
    inside = _at(_solid(mesh, cta), cta.T_patient_from_voxel, INSIDE.values())
    assert all(inside), dict(zip(INSIDE, inside))
    warned = json.loads((tmp_path / "model" / "model.json").read_text())["parameters"]["warnings"]
    assert any("cut by the CT's field of view" in w and "inferior side" in w for w in warned), warned


def test_a_top_edge_through_the_pulmonary_bifurcation(cta):
    """The CT cropped 600-707 mm in height, as a cardiac CT's range may start at the carina: its top edge cuts
    the pulmonary bifurcation and the trunk, whose lobe (12.1 mm) opens without a narrowing into the outflow
    tract's (13.2 mm, 1.09 times, 86 % inside the heart's body).  The 1.1 widening allowed for an aortic sinus
    lets the trace on through the outflow tract into the right ventricle: 676 ml, the right-ventricle point
    lost (measured; the same before session 11).  Tried in session 11: into lobes mostly inside the heart's
    body, a widening of 1.05 only: 763 ml, all four chambers in, the real CTs and the phantom unchanged, but on
    ``shared/realct`` averaged to 3 mm voxels the aorta's lobes inside the body (radii 13.7 -> 14.7 mm: one
    step of the distance map there) were no longer traced (791 -> 847 ml, Dice 0.868 -> 0.839): reverted.
    Also left: 28.6 ml of ascending aorta stay, its lobe on this edge lying half inside the heart's body.

    Passing since session 15: the blood pool's speckles (cavities of one or two voxels, the CT's noise above
    the pool's upper 650 HU; ``modeling.seed._with_speckles``) are blood, and the outflow tract's lobe measures
    13.6 mm, 1.12 times the trunk's: the trace stops there (764 ml, all four chambers in; 717 ml cropped at
    108, 716 ml at 116).  The margin over the 1.1 widening is small."""
    hu, T = _slices_from_600_mm(cta, 112)
    seg = segment_heart(hu, T)
    inside = _at(seg.mask, T, INSIDE.values())
    assert all(inside), dict(zip(INSIDE, inside))
    assert 600.0 <= seg.volume_ml <= 850.0, seg.volume_ml


def test_a_top_edge_just_above_the_aortic_root(cta):
    """The CT cropped 600-716 mm in height: its top edge runs through the ascending aorta 35 mm above the
    sinotubular junction, where the aorta's stub is too short for the vessel cut at the heart body's root.
    Its lobe on the edge then lies inside the opened region, and judged against that region it was taken for
    a chamber cut by the edge and kept (35 ml of aorta more than 10 mm up the lumen, measured); judged against the
    heart body (the part holding the ventricles' ball, which no vessel stub does) it is a vessel leaving:
    none of the aorta farther than 10 mm up the lumen from the annulus is inside, and the four chambers are."""
    hu, T = _slices_from_600_mm(cta, 118)
    mask = segment_heart(hu, T).mask
    far, _, _, voxel_mm3 = _aorta_labels(hu.shape, T)
    assert far.sum() * voxel_mm3 > 20e3  # 20 ml of ascending aorta above the root, up to the edge
    assert (far & mask).sum() <= 0.01 * far.sum(), (far & mask).sum() * voxel_mm3 / 1000.0
    inside = _at(mask, T, INSIDE.values())
    assert all(inside), dict(zip(INSIDE, inside))
