"""From an imaging Volume to a HeartModel: the modeling stage end to end.

    mask (automatic segmentation, or an external label map on any grid)
      -> surface mesh (patient mm) -> chest fiducials -> heart-centric frame
      -> HeartModel (mesh in the heart frame)

Each stage's wall time is recorded in the result, so a user (and ``bench/``)
sees where the time goes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from modeling.fiducials import Fiducials, find_fiducials
from modeling.labelmap import LabelMapError, mask_on_grid, read_label_map
from modeling.model import HeartModel, make_heart_model
from modeling.segment import SegmentationError, segment_heart
from modeling.surface import decimate, mask_to_mesh
from modeling.vessels import trim_vessel_stubs

__all__ = ["ModelBuild", "build_heart_model"]


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
    """

    model: HeartModel
    fiducials: Fiducials
    mask_source: str
    timings_s: dict = field(default_factory=dict)
    notes: tuple[str, ...] = ()


#: an adult heart (epicardial surface) holds some 300-1000 ml; a mask below this is not one.
MIN_HEART_ML = 100.0
#: the share of an external label that may lie outside the CT before a note says so.
OUTSIDE_NOTE_FRACTION = 0.05


def _label_ml(label_map, label) -> float:
    values = label_map.labels
    chosen = values == label if label is not None else values != 0
    return float(chosen.sum()) * abs(float(np.linalg.det(label_map.T_patient_from_voxel[:3, :3]))) / 1000.0


def _check_mask_volume(mask, T, source: str, min_ml: float, *, external: bool, notes: list, source_ml=None):
    """Refuse a mask far smaller than a heart; note a label map partly outside the CT."""
    ml = float(mask.sum()) * abs(float(np.linalg.det(T[:3, :3]))) / 1000.0
    if ml < min_ml:
        error = LabelMapError if external else SegmentationError
        hint = "check --label or the label map" if external else "give a heart mask with --mask"
        raise error(f"{source}: the mask holds {ml:.1f} ml, far less than a heart ({min_ml:g} ml or more); {hint}")
    if source_ml and ml < (1.0 - OUTSIDE_NOTE_FRACTION) * source_ml:
        notes.append(
            f"{source}: {100 * (1 - ml / source_ml):.0f} % of the label ({source_ml:.0f} ml) lies outside "
            f"the CT; the model covers {ml:.0f} ml"
        )


def build_heart_model(
    volume,
    *,
    cardiac_phase: float,
    cardiac_phase_source: str,
    mask_path=None,
    label: int | None = None,
    target_faces: int = 20000,
    expected_fiducials: int | None = 9,
    fiducial_rows: int = 3,
    fiducial_floor_hu: float | None = None,
    segmentation: dict | None = None,
    trim_vessels: bool = True,
    min_heart_ml: float = MIN_HEART_ML,
    progress=None,
) -> ModelBuild:
    """Build the heart model of ``volume``.

    Parameters
    ----------
    volume : imaging.Volume
    cardiac_phase, cardiac_phase_source : float, str
        The volume's phase phi_C* and where it came from (imaging's PhaseReport).
    mask_path : path, optional
        An external label map (NIfTI, NRRD or DICOM SEG) instead of the automatic
        segmentation; resampled onto the volume's grid through both affines.
    label : int, optional
        The label of the heart in ``mask_path`` (needed if it holds several).
    target_faces : int
        Faces of the decimated mesh.
    expected_fiducials : int or None
        Skin fiducials expected (None: no fiducials are looked for).
    fiducial_rows : int
        Rows of the fiducial grid (for their order).
    fiducial_floor_hu : float, optional
        HU above which fiducial excess density counts (default: modeling.fiducials.FLOOR_HU).
    segmentation : dict, optional
        Keyword arguments of :func:`modeling.segment.segment_heart`.
    trim_vessels : bool
        Remove the great-vessel stubs the segmentation leaves over the vessels'
        mouths and close the surface across them (:mod:`modeling.vessels`).
    min_heart_ml : float, ml
        A mask smaller than this is refused: it is not a heart (see
        :data:`MIN_HEART_ML`).
    progress : callable, optional
        Called with a stage name as each stage starts (e.g. to advance a bar).

    Raises
    ------
    LabelMapError, SegmentationError
        A mask far smaller than a heart (the message gives its volume in ml).
    """
    if target_faces < 100:
        raise ValueError(f"target_faces must be at least 100, got {target_faces}")
    T = np.asarray(volume.T_patient_from_voxel, dtype=float)
    timings: dict[str, float] = {}
    notes: list[str] = []

    def stage(name):
        if progress is not None:
            progress(name)
        timings[name] = time.perf_counter()

    def done(name):
        timings[name] = time.perf_counter() - timings[name]

    stage("mask")
    if mask_path is not None:
        label_map = read_label_map(mask_path)
        mask = mask_on_grid(label_map, volume.shape, T, label=label)
        mask_source = f"label map {label_map.source}" + (f", label {label}" if label is not None else "")
        seg_params = {}
    else:
        seg = segment_heart(volume.hu, T, **(segmentation or {}))
        mask = seg.mask
        mask_source = "automatic segmentation"
        seg_params = seg.parameters
        notes.extend(seg.notes)
    _check_mask_volume(mask, T, mask_source, min_heart_ml, external=mask_path is not None, notes=notes,
                       source_ml=_label_ml(label_map, label) if mask_path is not None else None)
    done("mask")

    stage("mesh")
    if trim_vessels:
        # trim at full resolution, then decimate: the patches get fine faces too
        dense = mask_to_mesh(mask, T, target_faces=max(int(target_faces), 400_000))
        trim = trim_vessel_stubs(dense, volume.hu, T)
        mesh = decimate(trim.mesh, target_faces)
        if trim.n_removed_faces:
            notes.append(
                f"vessel stubs trimmed: {trim.n_removed_faces} of {len(dense.faces)} faces over "
                f"contrast lumen removed, mouths closed with {trim.n_patch_faces} faces"
            )
    else:
        mesh = mask_to_mesh(mask, T, target_faces=target_faces)
    done("mesh")

    stage("fiducials")
    if expected_fiducials is None:
        fiducials = Fiducials(np.zeros((0, 3)), np.zeros(0))
    else:
        kwargs = {} if fiducial_floor_hu is None else {"floor_hu": fiducial_floor_hu}
        fiducials = find_fiducials(volume.hu, T, expected=expected_fiducials, n_rows=fiducial_rows, **kwargs)
        notes.extend(fiducials.notes)
    done("fiducials")

    stage("frame")
    series = volume.series
    source = {
        "series_instance_uid": series.series_instance_uid,
        "study_instance_uid": series.study_instance_uid,
        "modality": series.modality,
        "manufacturer": series.manufacturer,
        "n_slices": int(volume.shape[0]),
        "shape_kji": [int(s) for s in volume.shape],
        "spacing_mm": [float(s) for s in volume.spacing_mm],
        "kind": mask_source,
    }
    parameters = {
        "target_faces": int(target_faces),
        "expected_fiducials": expected_fiducials,
        "fiducial_rows": int(fiducial_rows),
        "segmentation": seg_params,
        "trim_vessels": bool(trim_vessels),
    }
    model = make_heart_model(
        mesh,
        cardiac_phase=float(cardiac_phase),
        cardiac_phase_source=str(cardiac_phase_source),
        fiducials_patient_mm=fiducials.centres_patient_mm if len(fiducials.centres_patient_mm) else None,
        fiducial_rows=fiducial_rows,
        source=source,
        parameters=parameters,
    )
    done("frame")
    return ModelBuild(model, fiducials, mask_source, timings, tuple(notes))
