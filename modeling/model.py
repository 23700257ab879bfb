"""The heart model: mesh in the heart frame, the frame fit, phase and fiducials.

Folder layout written by :func:`write_model` (format ``heartreg-model`` 1)::

    MODEL_DIR/
        heart.ply    binary PLY, float64 vertices, heart frame, mm, outward normals
        heart.stl    binary STL, float32, same surface (header: SPACE=LPS FRAME=heart)
        model.json   transform, Euler angles, ellipses, phase (and each slice's), fiducials, parameters

and, for 3D Slicer (:mod:`modeling.slicer`; ``docs/slicer.md``)::

        heart_lps.stl          the surface in the patient frame (LPS, SPACE=LPS header)
        HeartToPatient.tfm     ITK transform; its Slicer node moves heart.stl onto heart_lps.stl
        fiducials_ct.mrk.json  the CT's fiducials, patient LPS (when any were found)

The folder carries no patient-identifying data: ``source`` accepts only the
keys in :data:`SOURCE_KEYS` (series and study instance UIDs, modality,
geometry), never names, IDs or dates; the models heartreg builds hold the UIDs'
pseudonyms (:func:`hrcore.redact.pseudonym_uid`), older ones the UIDs.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

import numpy as np

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points
from hrcore.output import staged_output
from imaging.files import umask_mode
from modeling.fiducials import order_fiducials
from modeling.frame import HeartFrame, fit_heart_frame
from modeling.mesh import Mesh, MeshError, check_mesh, transform_mesh
from modeling.mesh_io import read_ply, write_mesh
from modeling.slab_ellipses import SlabEllipse
from modeling.slice_phases import SlicePhases
from modeling.slicer import write_itk_transform, write_markups

__all__ = [
    "ModelError",
    "HeartModel",
    "make_heart_model",
    "write_model",
    "write_slicer_files",
    "read_model",
    "SOURCE_KEYS",
    "FORMAT",
    "FORMAT_VERSION",
]

FORMAT = "heartreg-model"
FORMAT_VERSION = 1
#: Keys allowed in ``HeartModel.source``: series identity without patient data.
SOURCE_KEYS = frozenset(
    {
        "series_instance_uid",
        "study_instance_uid",
        "modality",
        "manufacturer",
        "n_slices",
        "shape_kji",
        "spacing_mm",
        "kind",
        "series_choice",
    }
)
MESH_FILES = ("heart.ply", "heart.stl")
JSON_FILE = "model.json"
#: 3D Slicer's files (see :func:`write_slicer_files`).
SLICER_MESH_FILE = "heart_lps.stl"
SLICER_TRANSFORM_FILE = "HeartToPatient.tfm"
SLICER_FIDUCIALS_FILE = "fiducials_ct.mrk.json"
#: Fiducials in model.json must agree with the transform to this tolerance.
FIDUCIAL_TOL_MM = 1e-6

FRAME_CONVENTIONS = (
    "Units mm. patient: DICOM LPS (+x left, +y posterior, +z superior). heart: "
    "z from apex to base along the least-squares line through the centres of "
    "ellipses fitted to the mesh vertices in slabs along z (recursively, Wood et "
    "al. 2018 sec. 2.2.3); x the eccentricity-weighted mean of the ellipses' minor "
    "axes, signed anterior (x . (0,-1,0) > 0); y = z cross x; origin on the axis "
    "halfway between the vertices' extreme heights. p_heart = T_heart_from_patient "
    "@ p_patient (4x4, row-major). euler_xyz_deg: intrinsic X-Y-Z angles of "
    "R = Rx(a) Ry(b) Rz(g) whose columns are the heart axes in patient "
    "coordinates. Fiducials ordered rows superior to inferior, within a row "
    "patient right to left (increasing LPS x). Mesh files are in the heart "
    "frame; their 'SPACE=LPS' token only tells 3D Slicer not to flip axes."
)


class ModelError(HeartregError, ValueError):
    """A heart model folder is missing, incomplete or inconsistent."""


def _default_version() -> str:
    try:
        from importlib.metadata import version

        return version("heartreg")
    except Exception:  # noqa: BLE001 - not installed: still write a model
        return "0+unknown"


def _readonly_mapping(d: Mapping, name: str) -> Mapping:
    try:
        text = json.dumps(dict(d), sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be JSON-serialisable with finite numbers: {exc}") from exc
    return MappingProxyType(json.loads(text))


@dataclass(frozen=True, eq=False)
class HeartModel:
    """Heart surface in the heart-centric frame, with what made it.

    Attributes
    ----------
    mesh : Mesh
        Epicardial surface, heart frame, mm, outward normals, watertight.
    frame : HeartFrame
        The fit that defines the heart frame (``frame.T_heart_from_patient``).
    cardiac_phase : float or None
        Image cardiac phase phi_C* in [0, 1); None when unknown (a CT without
        ECG gating: ``model.json`` says ``null`` and registration asks for it).
    cardiac_phase_source : str
        Where phi_C* came from (e.g. "GE RpeakTimeStamps"), or why it is unknown; from imaging.
    fiducials_patient_mm : (n, 3) float64
        Fiducial centroids, patient frame, in the documented order (may be (0, 3)).
    source : Mapping
        Series identity, keys from :data:`SOURCE_KEYS` only.
    parameters : Mapping
        Parameters that produced the model (JSON values).
    version : str
        heartreg version.
    slice_phases : SlicePhases or None
        The CT's cardiac phase slice by slice (:mod:`modeling.slice_phases`);
        None when unknown (a CT without a slice clock, a model written before).
    """

    mesh: Mesh
    frame: HeartFrame
    cardiac_phase: float | None
    cardiac_phase_source: str
    fiducials_patient_mm: np.ndarray
    source: Mapping = field(default_factory=dict)
    parameters: Mapping = field(default_factory=dict)
    version: str = field(default_factory=_default_version)
    slice_phases: SlicePhases | None = None

    def __post_init__(self):
        if not isinstance(self.mesh, Mesh):
            raise TypeError(f"mesh must be a Mesh, got {type(self.mesh).__name__}")
        if not isinstance(self.frame, HeartFrame):
            raise TypeError(f"frame must be a HeartFrame, got {type(self.frame).__name__}")
        phase = None if self.cardiac_phase is None else float(self.cardiac_phase)
        if phase is not None and not (math.isfinite(phase) and 0.0 <= phase < 1.0):
            raise ValueError(f"cardiac_phase must be a phase in [0, 1) or None (unknown), got {self.cardiac_phase}")
        if not isinstance(self.cardiac_phase_source, str) or not self.cardiac_phase_source:
            raise ValueError("cardiac_phase_source must be a non-empty string saying where phi_C came from")
        if self.slice_phases is not None and not isinstance(self.slice_phases, SlicePhases):
            raise TypeError(f"slice_phases must be a SlicePhases or None, got {type(self.slice_phases).__name__}")
        fid = np.array(self.fiducials_patient_mm, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(fid)):
            raise ValueError("fiducials_patient_mm contains NaN or infinity")
        fid.setflags(write=False)
        unknown = set(self.source) - SOURCE_KEYS
        if unknown:
            raise ValueError(
                f"source keys {sorted(unknown)} are not allowed (patient data must not enter "
                f"a model); use only {sorted(SOURCE_KEYS)}"
            )
        object.__setattr__(self, "cardiac_phase", phase)
        object.__setattr__(self, "fiducials_patient_mm", fid)
        object.__setattr__(self, "source", _readonly_mapping(self.source, "source"))
        object.__setattr__(self, "parameters", _readonly_mapping(self.parameters, "parameters"))

    def __eq__(self, other):
        if not isinstance(other, HeartModel):
            return NotImplemented
        return (
            self.mesh == other.mesh
            and self.frame == other.frame
            and self.cardiac_phase == other.cardiac_phase
            and self.cardiac_phase_source == other.cardiac_phase_source
            and np.array_equal(self.fiducials_patient_mm, other.fiducials_patient_mm)
            and dict(self.source) == dict(other.source)
            and dict(self.parameters) == dict(other.parameters)
            and self.version == other.version
            and self.slice_phases == other.slice_phases
        )

    __hash__ = None

    @property
    def T_heart_from_patient(self) -> np.ndarray:
        return self.frame.T_heart_from_patient

    @property
    def T_patient_from_heart(self) -> np.ndarray:
        return self.frame.T_patient_from_heart

    @property
    def euler_xyz_deg(self) -> tuple:
        return self.frame.euler_xyz_deg

    @property
    def fiducials_heart_mm(self) -> np.ndarray:
        """(n, 3) float64 fiducials in the heart frame, same order."""
        return apply_to_points(self.T_heart_from_patient, self.fiducials_patient_mm)

    def mesh_patient(self) -> Mesh:
        """The surface mapped back to the patient frame."""
        return transform_mesh(self.T_patient_from_heart, self.mesh)


def make_heart_model(
    mesh_patient: Mesh,
    *,
    cardiac_phase: float | None,
    cardiac_phase_source: str,
    fiducials_patient_mm=None,
    fiducial_rows: int = 3,
    source: Mapping | None = None,
    parameters: Mapping | None = None,
    slab_mm: float = 10.0,
    base_hint=None,
    slice_phases: SlicePhases | None = None,
) -> HeartModel:
    """Fit the heart frame to a patient-frame mesh and build the model.

    Parameters
    ----------
    mesh_patient : Mesh
        Surface from :func:`modeling.surface.mask_to_mesh`, patient mm.
    cardiac_phase, cardiac_phase_source : float or None, str
        phi_C* of the volume and its source, from imaging (None: unknown, and why).
    fiducials_patient_mm : (n, 3) float, optional
        Fiducial centroids, any order; sorted with :func:`order_fiducials`.
    fiducial_rows : int
        Rows of the fiducial grid.
    source, parameters : Mapping, optional
    slab_mm, base_hint
        Passed to :func:`modeling.frame.fit_heart_frame`.

    Examples
    --------
    >>> import numpy as np
    >>> from modeling import make_heart_model, mask_to_mesh
    >>> k, j, i = np.mgrid[:50, :40, :40]
    >>> mask = ((k - 25) / 22) ** 2 + ((j - 20) / 14) ** 2 + ((i - 20) / 12) ** 2 < 1
    >>> mesh = mask_to_mesh(mask, np.diag([2.0, 2.0, 2.0, 1.0]), target_faces=2000)
    >>> model = make_heart_model(mesh, cardiac_phase=0.7, cardiac_phase_source="example", base_hint=[0, 0, 1])
    >>> model.cardiac_phase, model.mesh.n_faces == mesh.n_faces
    (0.7, True)
    """
    if not isinstance(mesh_patient, Mesh):
        raise TypeError(f"mesh_patient must be a Mesh, got {type(mesh_patient).__name__}")
    frame = fit_heart_frame(mesh_patient.vertices, slab_mm=slab_mm, base_hint=base_hint)
    fid = np.zeros((0, 3))
    if fiducials_patient_mm is not None and len(fiducials_patient_mm):
        fid = np.asarray(fiducials_patient_mm, dtype=np.float64)
        fid = fid[order_fiducials(fid, n_rows=fiducial_rows)]
    params = {"slab_mm": float(slab_mm)}
    params.update(dict(parameters or {}))
    return HeartModel(
        mesh=transform_mesh(frame.T_heart_from_patient, mesh_patient),
        frame=frame,
        cardiac_phase=cardiac_phase,
        cardiac_phase_source=cardiac_phase_source,
        fiducials_patient_mm=fid,
        source=dict(source or {}),
        parameters=params,
        slice_phases=slice_phases,
    )


# ------------------------------------------------------------------------- I/O
def _model_json(model: HeartModel) -> dict:
    check = check_mesh(model.mesh)
    fr = model.frame
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "version": model.version,
        "frame_conventions": FRAME_CONVENTIONS,
        "T_heart_from_patient": fr.T_heart_from_patient.tolist(),
        "euler_xyz_deg": list(fr.euler_xyz_deg),
        "cardiac_phase": model.cardiac_phase,
        "cardiac_phase_source": model.cardiac_phase_source,
        "slice_phases": None if model.slice_phases is None else model.slice_phases.to_dict(),
        "fiducials_heart_mm": model.fiducials_heart_mm.tolist(),
        "fiducials_patient_mm": model.fiducials_patient_mm.tolist(),
        "mesh_files": list(MESH_FILES),
        "n_vertices": model.mesh.n_vertices,
        "n_faces": model.mesh.n_faces,
        "watertight": check.watertight,
        "winding_consistent": check.winding_consistent,
        "volume_mm3": check.volume_mm3,
        "area_mm2": model.mesh.area_mm2,
        "frame_fit": {
            "iterations": fr.iterations,
            "axis_change_deg": fr.axis_change_deg,
            "converged": fr.converged,
            "base_rule": fr.base_rule,
            "n_rejected_slabs": fr.n_rejected_slabs,
            "cycle": fr.cycle,
        },
        "ellipses": [e.to_dict() for e in fr.ellipses],
        "source": dict(model.source),
        "parameters": dict(model.parameters),
    }


def write_model(model: HeartModel, out_dir, *, overwrite: bool = False) -> Path:
    """Write ``model`` as a folder (heart.ply, heart.stl, model.json), atomically.

    The files are written into a staging folder beside ``out_dir`` that is
    renamed into place (:func:`hrcore.output.staged_output`). An existing empty folder, or one with byte-identical content, is
    fine; another earlier model is refused unless ``overwrite=True``, and a folder of other files always.

    Returns
    -------
    Path
        ``out_dir``.

    Examples
    --------
    An ellipsoid's surface (semi-axes 24, 28 and 44 mm) as the heart:

    >>> import tempfile
    >>> import trimesh
    >>> from modeling import Mesh, make_heart_model, write_model
    >>> sphere = trimesh.creation.icosphere(subdivisions=3)
    >>> mesh = Mesh(sphere.vertices * [24.0, 28.0, 44.0], sphere.faces)
    >>> model = make_heart_model(mesh, cardiac_phase=0.7, cardiac_phase_source="example", base_hint=[0, 0, 1])
    >>> folder = write_model(model, tempfile.mkdtemp() + "/model")
    >>> sorted(p.name for p in folder.iterdir())[:3]
    [...]
    """
    if not isinstance(model, HeartModel):
        raise TypeError(f"model must be a HeartModel, got {type(model).__name__}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    existing = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if existing and JSON_FILE not in existing:  # not an earlier model: never replaced, even with overwrite
        raise FileExistsError(f"{out} holds other files ({', '.join(existing[:5])}) and no {JSON_FILE}; "
                              "choose an empty folder or a new name")
    with staged_output(out, what="model folder", overwrite=True, earlier=(JSON_FILE,)) as tmp:
        os.chmod(tmp, umask_mode(directory=True))
        note = "heart (T_heart_from_patient in model.json)"
        for name in MESH_FILES:
            write_mesh(tmp / name, model.mesh, frame_note=note)
        text = json.dumps(_model_json(model), indent=2, allow_nan=False) + "\n"
        (tmp / JSON_FILE).write_text(text, encoding="utf-8")
        write_slicer_files(model, tmp)
        same = existing == sorted(p.name for p in tmp.iterdir()) and all(
            (out / n).read_bytes() == (tmp / n).read_bytes() for n in existing
        )
        if existing and not overwrite and not same:
            raise FileExistsError(
                f"{out} holds other files ({', '.join(existing[:5])}); choose another "
                "folder or pass overwrite=True (--overwrite)"
            )
    return out


def write_slicer_files(model: HeartModel, out_dir) -> dict:
    """Write the model's files for 3D Slicer into ``out_dir`` (called by :func:`write_model`).

    - ``heart_lps.stl``: the surface in the patient frame, LPS, mm (header
      ``SPACE=LPS``: Slicer flips it into its RAS scene, where the CT is);
    - ``HeartToPatient.tfm``: the ITK file whose Slicer node has the to-parent
      ``T_patient_from_heart`` (the file holds ``T_heart_from_patient``, ITK's
      resampling direction); ``heart.stl`` under it lands on ``heart_lps.stl``;
    - ``fiducials_ct.mrk.json``: the CT's fiducials, patient LPS, labelled
      ``CT-1`` .. in the documented order (only when the model has fiducials).

    Returns
    -------
    dict of Path by name ("mesh", "transform", and "fiducials" when written).
    """
    out = Path(out_dir)
    paths = {
        "mesh": write_mesh(out / SLICER_MESH_FILE, model.mesh_patient(), frame_note="patient (DICOM LPS)"),
        "transform": write_itk_transform(
            out / SLICER_TRANSFORM_FILE, model.T_patient_from_heart,
            note="Slicer node HeartToPatient: to-parent T_patient_from_heart, LPS, mm",
        ),
    }
    fid = model.fiducials_patient_mm
    if len(fid):
        paths["fiducials"] = write_markups(
            out / SLICER_FIDUCIALS_FILE, fid, labels=[f"CT-{k}" for k in range(1, len(fid) + 1)],
            name="CT fiducials", color=(0.95, 0.75, 0.1),
            descriptions=["CT fiducial, patient frame (LPS); " + ORDER_NOTE] * len(fid),
        )
    return paths


ORDER_NOTE = "rows superior to inferior, within a row patient right to left"


def read_model(model_dir) -> HeartModel:
    """Read a folder written by :func:`write_model`.

    Raises
    ------
    ModelError
        Missing folder or files, unreadable JSON, another format, or files
        that disagree with each other.

    Examples
    --------
    A model written and read back (:func:`write_model` made it from an ellipsoid):

    >>> import tempfile
    >>> import numpy as np
    >>> import trimesh
    >>> from modeling import Mesh, make_heart_model, read_model, write_model
    >>> ico = trimesh.creation.icosphere(subdivisions=3)
    >>> model = make_heart_model(Mesh(ico.vertices * [24.0, 28.0, 44.0], ico.faces), cardiac_phase=0.7,
    ...                          cardiac_phase_source="example", base_hint=[0, 0, 1])
    >>> again = read_model(write_model(model, tempfile.mkdtemp() + "/model"))
    >>> np.allclose(again.mesh.vertices, model.mesh.vertices, atol=1e-4), again.cardiac_phase_source
    (True, 'example')
    """
    d = Path(model_dir)
    if not d.is_dir():
        raise ModelError(f"model folder {d} does not exist; run 'heartreg model' to make one")
    jpath = d / JSON_FILE
    if not jpath.is_file():
        raise ModelError(f"{d} has no {JSON_FILE}; is it a heartreg model folder?")
    try:
        meta = json.loads(jpath.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(f"{jpath} is not readable JSON ({exc}); re-create the model") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelError(f"{jpath} is not a {FORMAT} file")
    version = meta.get("format_version")
    if version != FORMAT_VERSION or not isinstance(version, int):
        kind = "the text " if isinstance(version, str) else ""  # "has '2'; reads version 2" read as a riddle
        held = "has no format_version" if version is None else f"has format_version {kind}{version!r}"
        raise ModelError(f"{jpath} {held}; this heartreg reads the number {FORMAT_VERSION}")
    ply = d / MESH_FILES[0]
    if not ply.is_file():
        raise ModelError(f"{d} has no {MESH_FILES[0]}; re-create the model")
    try:
        mesh = read_ply(ply)
        fit = meta["frame_fit"]
        fid_heart = meta["fiducials_heart_mm"]  # a missing one 'disagreed with T_heart_from_patient' (an audit)
        frame = HeartFrame(
            T_heart_from_patient=np.asarray(meta["T_heart_from_patient"], dtype=np.float64),
            euler_xyz_deg=tuple(meta["euler_xyz_deg"]),
            ellipses=tuple(SlabEllipse.from_dict(e) for e in meta["ellipses"]),
            iterations=int(fit["iterations"]),
            axis_change_deg=float(fit["axis_change_deg"]),
            converged=bool(fit["converged"]),
            base_rule=str(fit["base_rule"]),
            n_rejected_slabs=int(fit["n_rejected_slabs"]),
            cycle=int(fit.get("cycle", 0)),  # models written before session 29 have none
        )
        model = HeartModel(
            mesh=mesh,
            frame=frame,
            cardiac_phase=meta["cardiac_phase"],
            cardiac_phase_source=meta["cardiac_phase_source"],
            fiducials_patient_mm=np.asarray(meta["fiducials_patient_mm"], dtype=np.float64),
            source=meta["source"],
            parameters=meta["parameters"],
            version=str(meta["version"]),
            slice_phases=None if meta.get("slice_phases") is None else SlicePhases.from_dict(meta["slice_phases"]),
        )
    except MeshError as exc:  # the mesh reader names its file already
        raise ModelError(str(exc) if str(ply) in str(exc) else f"{ply}: {exc}") from exc
    except KeyError as exc:
        raise ModelError(f"{jpath} is incomplete or corrupt (no field {exc.args[0]!r}); re-create the model") from exc
    except (TypeError, ValueError) as exc:
        detail = " ".join(str(exc).split())[:120]
        raise ModelError(f"{jpath} is incomplete or corrupt ({detail}); re-create the model") from exc
    if mesh.n_faces != meta.get("n_faces"):
        raise ModelError(f"{ply} has {mesh.n_faces} faces, {jpath} says {meta.get('n_faces')}")
    try:
        fid_heart = np.asarray(fid_heart, dtype=np.float64).reshape(-1, 3)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{jpath}: fiducials_heart_mm must be a list of [x, y, z] mm ({exc})") from None
    if fid_heart.shape != model.fiducials_heart_mm.shape or not np.allclose(
        fid_heart, model.fiducials_heart_mm, atol=FIDUCIAL_TOL_MM
    ):
        raise ModelError(f"{jpath}: fiducials_heart_mm disagree with T_heart_from_patient")
    return model
