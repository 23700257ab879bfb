"""From an imaging Volume to a HeartModel: the modeling stage end to end.

    mask (automatic segmentation, or an external label map on any grid)
      -> surface mesh (patient mm) -> chest fiducials -> heart-centric frame
      -> HeartModel (mesh in the heart frame)

Each stage's wall time is recorded in the result, so a user (and ``bench/``)
sees where the time goes.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from hrcore.memory import release_free_memory
from hrcore.redact import pseudonym_uid, pseudonymize_uids
from modeling.coarse import mask_box
from modeling.edge import edge_refinable, refine_to_edge
from modeling.fiducials import Fiducials, check_given_fiducials, fiducial_stage
from modeling.frame import SETTLED_DEG
from modeling.labelmap import LabelMapError, label_map_kind, mask_on_grid, on_air, other_frame, read_label_map
from modeling.mesh import vertex_normals
from modeling.metal import metal_in_chest, metal_near_heart
from modeling.model import HeartModel, make_heart_model
from modeling.options import AUTO, MIN_HEART_ML, ModelOptions
from modeling.segment import SegmentationError, segment_heart
from modeling.surface import MeshError, decimate, mask_to_mesh
from modeling.vessels import APEX_LAI_LPS, MOUTH_REACH_MM, base_direction, over_lumen, trim_vessel_stubs

__all__ = ["AUTO", "MIN_HEART_ML", "ModelBuild", "ModelOptions", "ModelingWarning", "build_heart_model"]

#: A CT spanning less than this (mm) along any of its axes cannot hold a heart (an adult's is 100-150 mm long).
MIN_SPAN_MM = 40.0
#: Voxels longer than this (mm) along any axis cannot outline a heart: slicerio's CTChest4 (10 mm slices) still
#: gives a coarse model; two images 62 mm apart gave a "watertight" model of one slab.
MAX_VOXEL_MM = 12.5

#: Whole-heart volumes (ml) of adults; an automatic segmentation outside this range is flagged.
HEART_ML = (250.0, 1500.0)
#: Largest rightward component (LPS -x) of a unit apex direction not warned about: a heart
#: whose apex points straight down (as the phantom's, or a vertical heart) is usual too.
APEX_RIGHT_MAX = 0.25
#: The vessels' mouths must lie this far along the long axis (|cosine|) to say which end is the base.
BASE_HINT_MIN_COSINE = 0.2
#: The surface is meshed on a grid of about this spacing (mm) where the CT is finer (blocks of
#: whole voxels, their filled fraction): a 20k-face model's edges are ~2.5 mm long, and on the
#: full-size phantom (0.49 x 0.49 x 0.625 mm) this grid is more accurate than the CT's own
#: (mean 0.036 vs 0.063 mm, p95 0.09 vs 0.15 mm from the true epicardium) with a quarter of the faces to smooth,
#: trim and decimate.
MESH_GRID_MM = 1.0


class ModelingWarning(UserWarning):
    """A modeling step fell back (no markers, trim skipped, unusual anatomy); the model is still made."""


@dataclass(frozen=True)
class ModelBuild:
    """A built model and how it was made.

    Attributes
    ----------
    model : HeartModel
    fiducials : Fiducials
    mask_source : str
        ``"automatic segmentation"`` or the label map's file and label.
    timings_s : dict of str to float
        Wall time per stage.
    notes : tuple of str
        What each step did, fallbacks included (also in ``model.json``,
        ``parameters.notes``; fallbacks also in ``parameters.warnings``).
    mask, T_patient_from_mask : (k, j, i) bool array and (4, 4) float64
        The mask that was meshed, on the CT's grid within its box
        (:func:`modeling.labelmap.write_mask` writes it beside the model).
    """

    model: HeartModel
    fiducials: Fiducials
    mask_source: str
    timings_s: dict = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    mask: np.ndarray | None = None
    T_patient_from_mask: np.ndarray | None = None


#: the share of an external label that may lie outside the CT before a note says so.
OUTSIDE_NOTE_FRACTION = 0.05


#: A given mask's pieces apart from its largest are said when they hold this much (ml) or more.
MIN_PIECES_ML = 1.0


def _other_pieces(mask, T) -> str:
    """What a mask holds besides its largest connected piece (26-connected), in words; "" if nothing.
    The surface keeps the largest piece only (:func:`modeling.surface.mask_to_mesh`)."""
    labels, n = ndimage.label(mask, structure=np.ones((3, 3, 3), bool))
    if n < 2:
        return ""
    sizes = np.bincount(labels.ravel())[1:]
    voxel_ml = abs(float(np.linalg.det(T[:3, :3]))) / 1000.0
    rest = float(sizes.sum() - sizes.max()) * voxel_ml
    if rest < MIN_PIECES_ML:  # specks of a segmentation's edge
        return ""
    return (f"the mask holds {n} separate pieces, {rest:.1f} ml of it outside the largest ({sizes.max() * voxel_ml:.0f} "
            "ml), which is left out")


def _check_mask_volume(mask, T, source: str, min_ml: float, *, external, notes: list, source_ml=None) -> float:
    """Refuse a mask far smaller than a heart; note a label map partly outside the CT; its volume, ml.

    ``external``: the label map's path (named in the refusal, a console line, not in ``notes``, which
    are written), or None for the automatic segmentation."""
    ml = float(np.count_nonzero(mask)) * abs(float(np.linalg.det(T[:3, :3]))) / 1000.0
    if ml < min_ml:
        error = LabelMapError if external else SegmentationError
        hint = "check --label or the label map" if external else "give a heart mask with --mask"
        raise error(f"{external or source}: the mask holds {ml:.1f} ml, far less than a heart ({min_ml:g} ml or more); {hint}")
    if source_ml and ml < (1.0 - OUTSIDE_NOTE_FRACTION) * source_ml:
        notes.append(
            f"{source}: {100 * (1 - ml / source_ml):.0f} % of the label ({source_ml:.0f} ml) lies outside "
            f"the CT; the model covers {ml:.0f} ml"
        )
    return ml


#: Mask on a face of the volume (mm²) above which the heart counts as cut by the field of view.
FOV_CUT_MM2 = 100.0
_SIDES = (("patient's left", "patient's right"), ("posterior", "anterior"), ("superior", "inferior"))


def _cut_by_field_of_view(mask, T) -> str:
    """Where the mask lies on the volume's faces: '' if nowhere (more than FOV_CUT_MM2), else the patient sides.

    A face's area is the larger of the mask's outermost layer and the one inside it: the segmentation's
    openings may thin the heart's last layer away at the edge (pyradiomics' lung1, 5 mm slices: 0 voxels on
    the edge, 17 cm² one slice in), and the model then ends flat one voxel short of it.
    """
    spacing = np.linalg.norm(T[:3, :3], axis=0)  # i, j, k
    cuts = []
    for col in range(3):  # voxel axis i, j, k = array axis 2, 1, 0
        axis = 2 - col
        face_mm2 = float(np.prod(np.delete(spacing, col)))
        layers = min(2, mask.shape[axis])
        for end, sign in ((0, -1.0), (-1, 1.0)):
            at = range(layers) if end == 0 else range(-1, -layers - 1, -1)
            area = max(float(np.count_nonzero(np.take(mask, i, axis=axis))) for i in at) * face_mm2
            if area > FOV_CUT_MM2:
                outward = sign * T[:3, col] / spacing[col]  # LPS
                d = int(np.argmax(np.abs(outward)))
                cuts.append(f"{_SIDES[d][0 if outward[d] > 0 else 1]} side, {area / 100.0:.0f} cm² on the edge")
    return "; ".join(cuts)


def _volume_cause(mask_ml, seg_params, cut: str) -> str:
    """The likeliest reason an automatic mask is not heart-sized, for the warning's hint (``cut``: where the
    field of view cuts it, :func:`_cut_by_field_of_view`)."""
    if mask_ml > HEART_ML[1]:
        return "tissue beyond the heart taken in: the liver, the great vessels"
    if cut:
        return "a heart cut by the field of view"
    if seg_params.get("contrast") is False:
        return "a CT without contrast"
    return "chambers parted by noise or metal artefacts"


def _along(hint, long_axis) -> bool:
    """Whether a direction towards the base lies along the long axis enough to sign it (BASE_HINT_MIN_COSINE)."""
    return hint is not None and abs(float(hint @ long_axis)) >= BASE_HINT_MIN_COSINE


def _decimate_or_keep_more(mesh, target_faces: int, fallback):
    """Decimate to ``target_faces``; where that breaks the surface, to twice as many, and so on (with a warning)."""
    faces = int(target_faces)
    while True:
        try:
            out = decimate(mesh, faces)
        except MeshError:
            if 2 * faces >= len(mesh.faces):
                raise
            faces *= 2
            continue
        if faces != target_faces:
            fallback(f"decimation to {target_faces} faces broke the surface; the model keeps {len(out.faces)} faces")
        return out


def _crop_mask(mask, T, margin_mm: float):
    """The mask's bounding box grown by ``margin_mm`` (+ 2 voxels), as a copy.

    Returns
    -------
    mask : bool array, the box of ``mask``
    box : tuple of slice, (k, j, i)
    T_box : (4, 4) float64
        ``T_patient_from_voxel`` of the box's voxels.
    """
    spacing_kji = np.linalg.norm(T[:3, :3], axis=0)[::-1]
    box = mask_box(mask, np.ceil(margin_mm / spacing_kji).astype(int) + 2)
    T_box = T.copy()
    T_box[:3, 3] = T[:3, :3] @ np.array([box[2].start, box[1].start, box[0].start], float) + T[:3, 3]
    return mask[box].copy(), box, T_box


def build_heart_model(
    volume,
    *,
    cardiac_phase: float | None,
    cardiac_phase_source: str,
    slice_phases=None,
    mask_path=None,
    label: int | str | None = None,
    options: ModelOptions | None = None,
    progress=None,
    **overrides,
) -> ModelBuild:
    """Build the heart model of ``volume``.

    Parameters
    ----------
    volume : imaging.Volume
    cardiac_phase, cardiac_phase_source : float or None, str
        The volume's phase phi_C* and where it came from (imaging's PhaseReport);
        None with the reason when the CT is not gated (the phase is then unknown
        and registration asks for it).
    slice_phases : SlicePhases, optional
        The volume's cardiac phase slice by slice
        (:meth:`modeling.slice_phases.SlicePhases.from_report`); kept in the
        model so that registration predicts each point at its slices' phase.
    mask_path : path, optional
        An external label map (NIfTI, NRRD, DICOM SEG, or a TotalSegmentator
        output folder) instead of the automatic segmentation; resampled onto the
        volume's grid through both affines and meshed as given.
    label : int or str, optional
        The label of the heart in ``mask_path``, by value or by name (needed if
        it holds several).
    options : ModelOptions, optional
        How the model is built (:class:`modeling.options.ModelOptions`: faces,
        fiducials, vessel trim, ...); default: its defaults.
    **overrides
        Fields of :class:`ModelOptions` replaced for this call, e.g.
        ``target_faces=5000``.
    progress : callable, optional
        Called with a stage name as each stage starts (e.g. to advance a bar).

    Raises
    ------
    LabelMapError, SegmentationError
        A mask far smaller than a heart (the message gives its volume in ml), or
        a CT too small to hold one (a single slice).

    Examples
    --------
    The whole chain on the sample study (a few seconds, hence skipped here):

    >>> from imaging import compute_phase_report, load_study
    >>> from modeling import ModelOptions, build_heart_model
    >>> volume = load_study("sample_dicom/ct")
    >>> report = compute_phase_report(volume)
    >>> build = build_heart_model(volume, cardiac_phase=report.volume_cardiac_phase,  # doctest: +SKIP
    ...                           cardiac_phase_source=report.source, options=ModelOptions(target_faces=5000))
    >>> build.model.mesh.n_faces <= 5000  # doctest: +SKIP
    True
    """
    opts = ModelOptions.of(options, **overrides)
    target_faces, expected_fiducials, fiducial_rows = opts.target_faces, opts.expected_fiducials, opts.fiducial_rows
    segmentation, trim_vessels = opts.segmentation, opts.trim_vessels
    min_heart_ml = opts.min_heart_ml
    T = np.asarray(volume.T_patient_from_voxel, dtype=float)
    span_mm = np.asarray(volume.hu.shape[::-1]) * np.linalg.norm(T[:3, :3], axis=0)  # along i, j, k
    if span_mm.min() < MIN_SPAN_MM:
        axis = ("its columns", "its rows", "its slices")[int(np.argmin(span_mm))]
        raise SegmentationError(
            f"the CT spans only {span_mm.min():.0f} mm along {axis} ({' x '.join(map(str, volume.hu.shape))} voxels); "
            f"a heart model needs a 3-D CT of the whole heart (at least {MIN_SPAN_MM:.0f} mm each way)"
        )
    voxel_mm = np.linalg.norm(T[:3, :3], axis=0)
    if voxel_mm.max() > MAX_VOXEL_MM:
        axis = ("columns", "rows", "slices")[int(np.argmax(voxel_mm))]
        raise SegmentationError(
            f"the CT's {axis} lie {voxel_mm.max():.1f} mm apart ({' x '.join(map(str, volume.hu.shape))} voxels); "
            f"a heart model needs them at most {MAX_VOXEL_MM:g} mm apart: give a CT reconstructed on thinner slices"
        )
    timings: dict[str, float] = {}
    notes: list[str] = []

    def stage(name):
        if progress is not None:
            progress(name)
        timings[name] = time.perf_counter()

    def done(name):
        # each stage's arrays are garbage now: give the heap they leave back, so the
        # next stage's peak does not sit on top of it
        release_free_memory()
        timings[name] = time.perf_counter() - timings[name]

    def fallback(message: str) -> None:
        warnings.warn(message, ModelingWarning, stacklevel=3)
        fallbacks.append(message)
        notes.append(message)

    fallbacks: list[str] = []
    if opts.fiducials_mm is not None:  # given points in another frame: said before the segmentation's seconds
        check_given_fiducials(opts.fiducials_mm, volume.hu.shape, T)
    stage("mask")
    if mask_path is not None:
        label_map = read_label_map(mask_path, structure=label if isinstance(label, str) else None)
        mask = mask_on_grid(label_map, volume.shape, T, label=label)
        lumen = T_lumen = None
        mask_source = f"label map ({label_map_kind(label_map.source)})" + (f", label {label}" if label is not None else "")
        seg_params = {}
        if elsewhere := other_frame(label_map, volume) or on_air(mask, volume.hu):
            fallback(f"{mask_source}: {elsewhere}")
    else:
        try:
            seg = segment_heart(volume.hu, T, **(segmentation or {}))
        except SegmentationError as exc:  # a lead's streaks part the blood pool: say so, not only the contrast
            raise SegmentationError(f"{exc}{metal_in_chest(volume.hu, T, refusal=str(exc))}") from exc
        mask, lumen, T_lumen = seg.mask, seg.vessel_lumen, seg.T_patient_from_lumen
        mask_source = "automatic segmentation"
        seg_params = seg.parameters
        for note in seg.notes:
            if note.startswith("vessel cut skipped"):
                fallback(note)
            else:
                notes.append(note)
    mask_ml = _check_mask_volume(mask, T, mask_source, min_heart_ml, external=mask_path, notes=notes,
                                 source_ml=label_map.volume_ml(label) if mask_path is not None else None)
    cut = _cut_by_field_of_view(mask, T)
    if not HEART_ML[0] <= mask_ml <= HEART_ML[1]:
        fallback(
            f"{mask_source}: the mask holds {mask_ml:.0f} ml, outside a heart's usual {HEART_ML[0]:.0f}-"
            f"{HEART_ML[1]:.0f} ml; " + ("it is meshed as given: check --label or the label map" if mask_path is not None
                                         else f"check the model ({_volume_cause(mask_ml, seg_params, cut)}? "
                                              "give --mask or a seed point)")
        )
    if mask_path is not None:
        pieces = _other_pieces(mask, T)
        if pieces:
            fallback(f"{mask_source}: {pieces}; the largest is meshed (a heart is one piece: check the mask for a "
                     "missing slice, or remove what is not heart)")
    if cut:
        fallback(f"the heart is cut by the CT's field of view ({cut}): the model ends flat there and misses what "
                 "lies beyond; reconstruct a wider field of view if that side matters")
    if metal := metal_near_heart(volume.hu, mask, T):
        fallback(metal)
    if trim_vessels is None:
        trim_vessels = mask_path is None
        pool_hu, arterial_hu = seg_params.get("pool_hu"), seg_params.get("blood_hu", [None])[0]
        if trim_vessels and seg_params.get("contrast") is False:
            trim_vessels = False
            fallback(
                "vessel stub trim skipped: the CT has no contrast blood, and the trim finds a vessel's mouth by "
                "its contrast lumen (--trim-vessels to trim anyway)"
            )
        elif trim_vessels and pool_hu is not None and pool_hu < arterial_hu:
            trim_vessels = False
            fallback(
                f"vessel stub trim skipped: the blood is dim (pool above {pool_hu:.0f} HU, a venous phase), and "
                f"the trim tells a vessel's lumen from a chamber's blood by an arterial phase's HU; the traced "
                f"vessel lumens are out of the mask already (--trim-vessels to trim anyway)"
            )
    # from here on the mask's box only: a full-size mask holds ~50 MB of huge pages where the heart is
    mask, box, T_box = _crop_mask(mask, T, MOUTH_REACH_MM)
    seg = None
    done("mask")

    stage("mesh")
    # the automatic segmentation has filled its cavities already (coarse.fill_holes before its largest
    # component): labelling the box's background again (~0.1 s, an int32 box) would change nothing
    fill_cavities = mask_path is not None
    # mesh densely, trim the stubs there (the patches get fine faces too), then decimate
    dense = mask_to_mesh(mask, T_box, target_faces=max(int(target_faces), 400_000), grid_mm=MESH_GRID_MM,
                         fill_cavities=fill_cavities)
    release_free_memory()
    if trim_vessels:
        try:
            trim = trim_vessel_stubs(dense, volume.hu, T, lumen=lumen, T_patient_from_lumen=T_lumen)
            release_free_memory()
        except MeshError as exc:
            fallback(f"vessel stub trim skipped, surface kept as segmented: {exc}")
        else:
            if trim.n_removed_faces:
                notes.append(
                    f"vessel stubs trimmed: {trim.n_removed_faces} of {len(dense.faces)} faces over "
                    f"contrast lumen removed, mouths closed with {trim.n_patch_faces} faces"
                )
            dense = trim.mesh
    mesh = _decimate_or_keep_more(dense, target_faces, fallback)
    edge_hu = None
    if mask_path is None and not edge_refinable(T):
        spacing = np.linalg.norm(T[:3, :3], axis=0)  # i, j, k
        notes.append("surface kept as meshed, not moved onto the CT's edge: voxels of "
                     + " x ".join(f"{s:.2g}" for s in spacing) + " mm, coarser than the move's 2.5 mm "
                     "(their blur and thick slices place the edge less well than the mesh)")
    elif mask_path is None:  # the automatic mask's threshold, to sub-voxel accuracy (an external mask is kept as given)
        edge_hu = float(seg_params["hu_low"])
        over, lumen_mm = None, 0.0
        if lumen is not None:  # the traced lumen cut at its valve: its surface moves to the blood's edge
            over = over_lumen(mesh.vertices, vertex_normals(mesh.vertices, mesh.faces), lumen, T_lumen)
            lumen_mm = float(np.linalg.norm(T_lumen[:3, :3], axis=0).max())  # its grid's spacing
        mesh, refined = refine_to_edge(mesh, volume.hu, T, edge_hu, over_blood=over,
                                       blood_level=seg_params.get("pool_hu"), blood_reach_mm=lumen_mm)
        notes.append(f"surface moved to the CT's {edge_hu:g} HU edge"
                     + ("" if over is None or not over.any() else
                        f" ({seg_params['pool_hu']:g} HU, the blood's, at the {int(over.sum())} vertices over a "
                        "vessel's lumen cut at its valve)")
                     + f" at {refined:.0%} of its vertices (sub-voxel)")
    done("mesh")

    stage("fiducials")
    fiducials = fiducial_stage(volume.hu, T, opts, fallback)
    notes.extend(fiducials.notes)
    done("fiducials")

    stage("frame")
    base_hint = base_direction(mask, volume.hu[box], T_box)
    meshed, mask = mask, None  # the box's mask goes out with the model (written beside it: heart_mask.nii.gz)
    v = mesh.vertices - mesh.vertices.mean(axis=0)
    long_axis = np.linalg.svd(v, full_matrices=False)[2][0]
    base_rule = "great vessels" if _along(base_hint, long_axis) else "usual orientation"
    if base_rule == "usual orientation":
        # a real heart's two ends differ too little in width to tell them apart (pyradiomics' lung2 without
        # contrast: 0.6-1.4 mm of median radius over 140 mm, its sign flipping with the face count)
        base_hint = -APEX_LAI_LPS
        if _along(base_hint, long_axis):
            fallback("no contrast vessels leave the heart along its long axis: the apex taken at the end towards "
                     "the patient's left-anterior-inferior, as usual (a mirrored heart, dextrocardia, would be missed)")
        else:
            base_rule, base_hint = "cross-section", None
            fallback("no contrast vessels leave the heart along its long axis, and the long axis lies across the "
                     "usual apex direction: apex and base told apart by the cross-sections' width")
    series = volume.series
    source = {
        "series_instance_uid": pseudonym_uid(series.series_instance_uid),  # PS3.15: the UIDs identify the study
        "study_instance_uid": pseudonym_uid(series.study_instance_uid),
        "modality": series.modality,
        "manufacturer": series.manufacturer,
        "n_slices": int(volume.shape[0]),
        "shape_kji": [int(s) for s in volume.shape],
        "spacing_mm": [float(s) for s in volume.spacing_mm],
        "kind": mask_source,
        **({"series_choice": pseudonymize_uids(volume.selection)} if volume.selection else {}),  # UIDs: as above
    }
    parameters = {
        "target_faces": int(target_faces),
        "expected_fiducials": expected_fiducials if opts.fiducials_mm is None else len(opts.fiducials_mm),
        "fiducials_given": opts.fiducials_mm is not None,
        "fiducial_rows": int(fiducial_rows),
        "segmentation": seg_params,
        "trim_vessels": bool(trim_vessels),
        "mesh_grid_mm": MESH_GRID_MM,
        "refined_to_edge_hu": edge_hu,
        "base_from_great_vessels": base_rule == "great vessels",
    }
    if cardiac_phase is None:
        fallback(f"cardiac phase unknown ({cardiac_phase_source}); give it to 'heartreg register' with --cardiac-phase")
    model = make_heart_model(
        mesh,
        cardiac_phase=None if cardiac_phase is None else float(cardiac_phase),
        cardiac_phase_source=str(cardiac_phase_source),
        fiducials_patient_mm=fiducials.centres_patient_mm if len(fiducials.centres_patient_mm) else None,
        fiducial_rows=fiducial_rows,
        source=source,
        parameters=parameters,
        base_hint=base_hint,
        slice_phases=slice_phases,
    )
    apex = -model.frame.axes_patient[:, 2]
    if apex[0] < -APEX_RIGHT_MAX or apex @ APEX_LAI_LPS <= 0:  # to the patient's right, or away from L-A-I
        fallback(f"the apex points {np.round(apex, 2).tolist()} (LPS), not towards patient left-anterior-inferior "
                 "as usual: check the model (dextrocardia, or a segmentation error)")
    if frame_warning := model.frame.convergence_warning():
        fallback(frame_warning)
    elif model.frame.cycle and model.frame.axis_change_deg >= SETTLED_DEG:
        notes.append(f"heart frame: the long axis's fit cycled among {model.frame.cycle} axes up to "
                     f"{model.frame.axis_change_deg:.1f} deg apart (the slabs' ellipses it accepts change with it); "
                     "the frame's axis is their mean")
    notes.append(
        {"great vessels": "heart frame: base where the great vessels leave",
         "usual orientation": "heart frame: apex towards the patient's left-anterior-inferior (no vessel told the base)",
         "cross-section": "heart frame: base at the broader end"}[base_rule]
    )
    model = replace(model, parameters={**dict(model.parameters), "notes": list(notes), "warnings": list(fallbacks)})
    done("frame")
    return ModelBuild(model, fiducials, mask_source, timings, tuple(notes), meshed, T_box)
