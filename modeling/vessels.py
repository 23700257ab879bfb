"""Trim the great-vessel stubs off a whole-heart surface.

The segmentation cuts the aorta and pulmonary arteries with a morphological
opening, which leaves a stub of a few millimetres over each vessel's mouth.  The
epicardium is everywhere a *myocardium* boundary: just inside it the CT shows
muscle (~100 HU).  Just inside a stub's surface it shows the vessel's
contrast-filled lumen.  So:

1. sample the HU inside every vertex along its inward normal, deeper than a
   great vessel's wall (1-2 mm) but reading no tissue deeper than the
   thinnest myocardium (the atria, ``wall_mm`` = 2.5 mm): the probe sits
   ``wall_mm`` less half a voxel along the normal deep, since a voxel's value
   mixes in what lies half a voxel beyond its centre (on a 2 mm CT 1.3-1.5 mm,
   on a 0.5 mm CT 2.2 mm.  A fixed 1.5 mm found the lumen under a 2 mm aortic
   wall on a coarse CT through its partial volume only, and missed it on a
   fine one: the full-size phantom kept its aortic root's wall as heart);
2. vertices over contrast blood (> ``blood_hu``), or over less enhanced
   venous blood (> ``vein_hu``) already at half that depth, grown by
   ``grow_rings`` rings of neighbours, are the stubs: their faces are removed.
   A surface with a great vessel's lumen traced down to its valve
   (:mod:`modeling.greatvessels`) just *outside* it is no vessel's
   wall: it is the cut the segmentation made there on purpose (the lumen's
   floor at the valve, the walls of the aortic root's well), and stays:
   trimmed, the well lost its floor and was lidded at its rim, 14 mm above
   the valve on the anatomical phantom;
3. the holes left at the vessels' mouths are closed with new faces spanning
   each mouth's rim (the epicardium across a mouth is nearly flat: the base);
   decimating afterwards (as :func:`modeling.build.build_heart_model` does)
   blends the patches into the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hrcore.geometry import apply_to_points
from modeling.coarse import centroid, mask_box, sample_ct
from modeling.distance import distance_mm
from modeling.mesh import Mesh, MeshError, check_mesh, vertex_normals

__all__ = ["APEX_LAI_LPS", "MAX_REMOVED", "VesselTrim", "base_direction", "over_lumen", "trim_vessel_stubs"]

#: Largest fraction of the surface's faces a stub trim may remove.  The stubs of the great vessels are a
#: small part of the heart's surface: 4.6-4.9 % on the spheroid phantom (sample size, four presets),
#: 17.6-18.2 % on the anatomical phantom (eight vessels' mouths; sample and full size, a 200 mm field of
#: view, a stent).  A trim reading a real heart's chamber blood under its 1.5-2 mm atrial and right
#: ventricular walls as lumen flags far more: 39-82 % on ``shared/realct`` and TotalSegmentator's aortic
#: CTA, as read and resampled (0.7 x 0.7 x 2.5 mm: 47-48 %, blood dimmed towards a venous phase: 39 %), and
#: such a trim took 20-25 % of the heart's volume (Dice against the reference 0.87 -> 0.71-0.78).  It is
#: refused, with a warning, above this fraction; the former bound, half, let those through, and 0.3 a trim of
#: 29.8 % on ``shared/realct`` with its right heart washed out (a saline chaser), which cut the left atrium's
#: thin walls flat (the model's mesh Dice 0.890 against the segmentation's 0.908; skipped, 0.907).
MAX_REMOVED = 0.25
#: A vertex is over a traced lumen when the lumen lies this far outside it: two voxels of the
#: segmentation's grid at its nominal 2 mm (``segment_heart``'s ``coarse_mm``), past the partial volume
#: of the lumen's edge.
LUMEN_PROBE_MM = 4.0


@dataclass(frozen=True)
class VesselTrim:
    """The trimmed mesh and what was removed."""

    mesh: Mesh
    n_removed_faces: int
    n_patch_faces: int


def trim_vessel_stubs(
    mesh: Mesh,
    hu,
    T_patient_from_voxel,
    *,
    wall_mm: float = 2.5,
    blood_hu: float = 225.0,
    vein_hu: float = 140.0,
    grow_rings: int = 2,
    max_removed: float = MAX_REMOVED,
    lumen=None,
    T_patient_from_lumen=None,
) -> VesselTrim:
    """Remove the parts of ``mesh`` that cover contrast-filled vessel lumen.

    Parameters
    ----------
    mesh : Mesh
        Closed surface in the patient frame (from :func:`modeling.surface.mask_to_mesh`).
    hu : (n_slices, n_rows, n_cols) array
        The CT volume, indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64
    wall_mm : float
        The thinnest myocardium (atria, 2.5-3 mm; a great vessel's wall is 1-2
        mm): the HU is sampled this far inside each vertex less half a voxel
        along its normal (the voxel's partial volume reaches that far), so that
        a stub is found at any resolution and a chamber at none.
    blood_hu : float
        HU above which the sample is contrast blood.
    vein_hu : float
        Less enhanced blood (a vena cava's inflow, 140-200 HU; enhanced
        myocardium ~100-130 HU) counts when the HU at half the depth reads it
        too: only a vein's wall (~1 mm) is that thin over it, never myocardium.
    grow_rings : int
        Rings of neighbouring vertices removed with each stub vertex.
    max_removed : float
        Largest fraction of the faces a trim may remove (:data:`MAX_REMOVED`).
    lumen : bool array, optional
        The great vessels' lumen the segmentation traced to their valves and
        took out inside the heart's body
        (:attr:`modeling.segment.HeartSegmentation.vessel_lumen`): a surface
        over it is the cut at the valve.  Where a lumen was cut at the body's
        edge instead (a vessel open to its chamber, the phantom's stubs), the
        stub's end is trimmed with its sides.  Vertices over it are no stub;
        the rings grown around a stub next to them may still take some (sparing
        those too left ragged rims: full-size anatomical phantom p95 0.57 ->
        0.61 mm, largest error 3.0 -> 4.9 mm).
    T_patient_from_lumen : (4, 4) float64, optional
        Its voxel -> patient transform.

    Returns
    -------
    VesselTrim
        The input mesh unchanged when nothing covers blood.

    Raises
    ------
    MeshError
        If the trim would remove more than ``max_removed`` of the faces, or the
        trimmed and closed surface is not watertight.
    """
    import pymeshlab

    v = np.asarray(mesh.vertices, dtype=float)
    f = np.asarray(mesh.faces)
    normals = vertex_normals(v, f)
    T = np.asarray(T_patient_from_voxel, dtype=float)
    spacing = np.linalg.norm(T[:3, :3], axis=0)  # (i, j, k) mm
    axes = T[:3, :3] / spacing  # unit voxel axes in the patient frame
    half_voxel = 0.5 * np.linalg.norm((normals @ axes) * spacing, axis=1)  # half the voxel's extent along the normal
    depth_mm = np.maximum(wall_mm - half_voxel, 0.5 * wall_mm)
    inside = np.concatenate([v - depth_mm[:, None] * normals, v - 0.5 * depth_mm[:, None] * normals])
    deep, shallow = np.split(sample_ct(hu, T, inside), 2)
    flagged = deep > blood_hu
    flagged |= (deep > vein_hu) & (shallow > vein_hu)  # venous blood under a vein's ~1 mm wall
    if lumen is not None:  # the traced lumen's own cut stays
        flagged &= ~over_lumen(v, normals, lumen, T_patient_from_lumen)
    if not flagged.any():
        return VesselTrim(mesh, 0, 0)
    for _ in range(grow_rings):
        touched = flagged[f].any(axis=1)
        flagged[f[touched].ravel()] = True
    keep = ~flagged[f].any(axis=1)
    n_removed = int((~keep).sum())
    if n_removed > max_removed * len(f):
        raise MeshError(
            f"it would remove {n_removed / len(f):.0%} of the surface's faces (at most {max_removed:.0%}): it reads "
            f"the chambers' blood under thin walls as vessel lumen; pass trim_vessels=False (--keep-vessels) to keep "
            f"the stubs without this warning"
        )

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f[keep].astype(np.int32)))
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_remove_connected_component_by_face_number(mincomponentsize=max(10, int(0.05 * keep.sum())))
    n_before = ms.current_mesh().face_number()
    # no hole refinement: it costs tens of seconds on a full-resolution mesh
    ms.meshing_close_holes(maxholesize=100000, selfintersection=False)
    n_patch = ms.current_mesh().face_number() - n_before
    m = ms.current_mesh()
    trimmed = Mesh(m.vertex_matrix(), m.face_matrix().astype(np.int64))
    check = check_mesh(trimmed)
    if not check.ok:
        raise MeshError(
            f"trimming {n_removed} faces over vessel lumen left an open surface ({check}); "
            "pass trim_vessels=False (--keep-vessels) to keep the stubs"
        )
    return VesselTrim(trimmed, n_removed, int(n_patch))


def over_lumen(vertices, normals, lumen, T_patient_from_lumen, *, probe_mm: float = LUMEN_PROBE_MM) -> np.ndarray:
    """(n,) bool: vertices with a traced lumen ``probe_mm`` outside them along their normals.

    ``lumen`` is :attr:`modeling.segment.HeartSegmentation.vessel_lumen`, indexed
    ``[k, j, i]`` (points outside its grid are not over it).
    """
    points = np.asarray(vertices, dtype=float) + probe_mm * np.asarray(normals, dtype=float)
    kji = np.rint(apply_to_points(np.linalg.inv(T_patient_from_lumen), points)).astype(np.int64)[:, ::-1]
    ok = np.all((kji >= 0) & (kji < np.asarray(lumen.shape)), axis=1)
    out = np.zeros(len(points), bool)
    out[ok] = np.asarray(lumen)[tuple(kji[ok].T)]
    return out


#: Contrast blood (HU) just outside a heart mask marks a vessel's mouth.
MOUTH_BLOOD_HU = 150.0
#: How far outside the mask (mm) the vessels' mouths are looked for.
MOUTH_REACH_MM = 4.0
#: Coarsest grid spacing (mm) the base direction is found on.
MOUTH_GRID_MM = 1.0
#: The usual direction of the apex in LPS: patient left, anterior, inferior.
APEX_LAI_LPS = np.array([1.0, -1.0, -1.0]) / np.sqrt(3.0)


def base_direction(mask, hu, T_patient_from_voxel, *, blood_hu: float = MOUTH_BLOOD_HU,
                   reach_mm: float = MOUTH_REACH_MM, min_ml: float = 1.0):
    """Direction from the heart's centre to where the great vessels leave it.

    The aorta, pulmonary trunk, venae cavae and pulmonary veins all join the
    heart at its base; outside a heart mask they are contrast-filled tubes.  The
    blood voxels in a shell ``reach_mm`` thick just outside ``mask`` are their
    mouths: the unit vector from the mask's centroid to theirs points from the
    apex towards the base.

    Parameters
    ----------
    mask : (n_slices, n_rows, n_cols) bool
        The heart, on the grid of ``hu``.
    hu : (n_slices, n_rows, n_cols) array
    T_patient_from_voxel : (4, 4) float64
    blood_hu : float
        Lower HU of contrast blood (metal and bone, far from the heart's
        surface, hardly weigh on the centroid).
    reach_mm : float
    min_ml : float
        Fewer mouth voxels than this volume give no answer.

    Returns
    -------
    (3,) float64 unit vector, patient frame, or None
        None when no contrast blood touches the mask (a non-contrast CT).
    """
    mask = np.asarray(mask, dtype=bool)
    T = np.asarray(T_patient_from_voxel, dtype=float)
    spacing_kji = np.linalg.norm(T[:3, :3], axis=0)[::-1]
    box = mask_box(mask, np.ceil(reach_mm / spacing_kji).astype(int) + 1)
    if box is None:
        return None
    # a direction needs no sub-millimetre grid: every ``step``-th voxel (at most
    # MOUTH_GRID_MM apart) keeps the distance transform small on a fine CT
    step = np.maximum(1, np.floor(MOUTH_GRID_MM / spacing_kji)).astype(int)
    box = tuple(slice(b.start, b.stop, int(st)) for b, st in zip(box, step))
    sub = mask[box]
    spacing = spacing_kji * step
    shell = (distance_mm(~sub, spacing) <= reach_mm) & ~sub
    mouths = shell & (np.asarray(hu[box]) > blood_hu)
    voxel_ml = abs(np.linalg.det(T[:3, :3])) * float(np.prod(step)) / 1000.0
    if mouths.sum() * voxel_ml < min_ml:
        return None
    kji_delta = (centroid(mouths) - centroid(sub)) * step
    d = T[:3, :3] @ kji_delta[::-1]
    n = np.linalg.norm(d)
    return None if n < 1e-6 else d / n
