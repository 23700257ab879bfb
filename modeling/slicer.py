"""3D Slicer's file formats: markups ``.mrk.json`` (and the legacy ``.fcsv``, read) and ITK ``.tfm`` files.

Both are written in **LPS** and say so, so Slicer (whose scene is RAS) converts
on reading, as it does for DICOM:

- a markups file (schema ``markups-schema-v1.0.3``) holds one fiducial list with
  ``coordinateSystem: "LPS"``, ``coordinateUnits: "mm"``;
- an ITK text transform file holds one ``AffineTransform_double_3_3`` in the
  *resampling* direction (from the fixed to the moving space): the inverse of
  the "to parent" matrix that Slicer shows for the transform node it makes.
  :func:`write_itk_transform` takes the to-parent transform ``T_parent_from_child``
  and writes its inverse; :func:`read_itk_transform` gives it back.

Names follow SlicerIGT: a transform file ``ProbeToPatient.tfm`` makes a node
that moves data in the probe frame into the patient frame (its to-parent is
``T_patient_from_probe``); ``sitk.ReadTransform`` of the same file maps patient
points to probe points (``T_probe_from_patient``), as ITK's resampling does.
Every writer writes atomically; every reader gives back what was written.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError
from hrcore.geometry import check_transform, invert
from imaging.files import write_text_atomic

__all__ = [
    "MARKUPS_SCHEMA",
    "Markups",
    "SlicerFileError",
    "read_itk_transform",
    "read_markups",
    "write_itk_transform",
    "write_markups",
]

MARKUPS_SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
    "Resources/Schema/markups-schema-v1.0.3.json#"
)
#: LPS <-> RAS: negate x and y (its own inverse).
_FLIP = np.diag([-1.0, -1.0, 1.0])
_ITK_MAGIC = "#Insight Transform File V1.0"
#: ITK transform types whose parameters are 9 matrix entries (row-major) and a translation.
_AFFINE_TYPES = ("AffineTransform", "MatrixOffsetTransformBase")


class SlicerFileError(HeartregError, ValueError):
    """A markups or transform file that is not what 3D Slicer writes."""


@dataclass(frozen=True, eq=False)
class Markups:
    """One fiducial list as read from a ``.mrk.json`` file.

    Attributes
    ----------
    name : str
        The list's name (Slicer's node name).
    labels : tuple of str
        One label per control point.
    points_lps_mm : (n, 3) float64, mm
        Control point positions in LPS (converted from RAS if the file was RAS).
    descriptions : tuple of str
        One per control point (may be empty strings).
    """

    name: str
    labels: tuple[str, ...]
    points_lps_mm: np.ndarray
    descriptions: tuple[str, ...]

    def __post_init__(self):
        pts = np.array(self.points_lps_mm, dtype=np.float64).reshape(-1, 3)
        pts.setflags(write=False)
        object.__setattr__(self, "points_lps_mm", pts)


def write_markups(
    path,
    points_mm,
    *,
    labels,
    name: str,
    descriptions=None,
    color=(0.9, 0.2, 0.2),
) -> Path:
    """Write a Slicer fiducial list (``.mrk.json``), coordinates in LPS mm.

    Parameters
    ----------
    path : str or Path
        Output file; its name must end in ``.mrk.json``.
    points_mm : (n, 3) float, mm
        Positions in an LPS-handed frame (the patient frame, or a tracker frame
        Slicer is to show through a transform of the same convention).
    labels : sequence of str
        One label per point (shown next to it in Slicer).
    name : str
        The list's node name.
    descriptions : sequence of str, optional
        One per point.
    color : (3,) float in [0, 1]
        Display colour of the points.

    Returns
    -------
    Path
    """
    path = Path(path)
    if not path.name.endswith(".mrk.json"):
        raise ValueError(f"a markups file name must end in .mrk.json, got {path.name}")
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_mm must have shape (n, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points_mm contains NaN or infinity")
    labels = [str(x) for x in labels]
    if len(labels) != len(pts):
        raise ValueError(f"labels must give one label per point: {len(labels)} labels, {len(pts)} points")
    descriptions = [""] * len(pts) if descriptions is None else [str(d) for d in descriptions]
    if len(descriptions) != len(pts):
        raise ValueError(f"descriptions must give one per point: {len(descriptions)} for {len(pts)} points")
    points = [
        {
            "id": str(k + 1),
            "label": label,
            "description": desc,
            "associatedNodeID": "",
            "position": [float(x) for x in p],
            "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0],
            "selected": True,
            "locked": True,
            "visibility": True,
            "positionStatus": "defined",
        }
        for k, (label, desc, p) in enumerate(zip(labels, descriptions, pts))
    ]
    doc = {
        "@schema": MARKUPS_SCHEMA,
        "markups": [
            {
                "type": "Fiducial",
                "name": str(name),
                "coordinateSystem": "LPS",
                "coordinateUnits": "mm",
                "locked": True,
                "fixedNumberOfControlPoints": False,
                "labelFormat": "%N-%d",
                "lastUsedControlPointNumber": len(points),
                "controlPoints": points,
                "measurements": [],
                "display": {
                    "visibility": True,
                    "opacity": 1.0,
                    "color": [float(c) for c in color],
                    "selectedColor": [float(c) for c in color],
                    "propertiesLabelVisibility": False,
                    "pointLabelsVisibility": True,
                    "textScale": 3.0,
                    "glyphType": "Sphere3D",
                    "glyphScale": 2.0,
                    "glyphSize": 4.0,
                    "useGlyphScale": False,
                },
            }
        ],
    }
    write_text_atomic(path, json.dumps(doc, indent=2, allow_nan=False) + "\n")
    return path


#: ``positionStatus`` of a markups control point that is not placed: the schema's ``undefined`` and
#: ``preview``, and ``missing`` (a point skipped while placing, Slicer 5, written with ``"position": ""``).
UNPLACED = ("undefined", "preview", "missing")


def read_markups(path) -> Markups:
    """Read the first fiducial list of a ``.mrk.json`` file (LPS or RAS) as LPS.

    Only placed points are read: a control point whose ``positionStatus`` is
    ``undefined``, ``preview`` or ``missing`` (listed in Slicer but not yet
    placed, being placed, or skipped) is left out.  Slicer's legacy point
    list, ``.fcsv``, is read too (:func:`_read_fcsv`).

    Raises
    ------
    SlicerFileError
        Unreadable JSON, no fiducial list, units other than mm, or a control
        point without three finite coordinates.
    """
    path = Path(path)
    if path.exists() and not path.is_file():  # a named pipe would block the read
        raise SlicerFileError(f"markups file {path} is not a regular file (a folder, named pipe or device)")
    if path.name.lower().endswith(".fcsv"):
        return _read_fcsv(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SlicerFileError(f"markups file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SlicerFileError(f"{path} is not a readable JSON markups file ({exc})") from None
    lists = doc.get("markups") if isinstance(doc, dict) else None
    fiducials = [m for m in lists or [] if isinstance(m, dict) and m.get("type") == "Fiducial"]
    if not fiducials:
        raise SlicerFileError(f"{path} holds no fiducial list ('markups' with type 'Fiducial'); save a point list from Slicer")
    m = fiducials[0]
    system = m.get("coordinateSystem", "LPS")
    if system not in ("LPS", "RAS"):
        raise SlicerFileError(f"{path}: coordinateSystem {system!r} is neither 'LPS' nor 'RAS'")
    units = m.get("coordinateUnits", "mm")
    if units not in ("mm", ["mm", "UCUM", "millimeter"]):
        raise SlicerFileError(f"{path}: coordinateUnits {units!r}; heartreg reads millimetres only")
    labels, descriptions, pts = [], [], []
    for k, cp in enumerate(m.get("controlPoints") or []):
        if isinstance(cp, dict) and cp.get("positionStatus") in UNPLACED:
            continue
        pos = cp.get("position") if isinstance(cp, dict) else None
        if not (isinstance(pos, list) and len(pos) == 3 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in pos
        )):
            raise SlicerFileError(f"{path}: controlPoints[{k}] has no position of 3 finite numbers")
        labels.append(str(cp.get("label", "")))
        descriptions.append(str(cp.get("description", "")))
        pts.append(pos)
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if system == "RAS":
        pts = pts @ _FLIP
    return Markups(name=str(m.get("name", "")), labels=tuple(labels), points_lps_mm=pts,
                   descriptions=tuple(descriptions))


#: ``.fcsv``'s coordinate systems: a name, or Slicer 4's number (0 RAS, 1 LPS); no line: RAS.
_FCSV_SYSTEMS = {"RAS": "RAS", "0": "RAS", "LPS": "LPS", "1": "LPS"}
#: the columns of a ``.fcsv`` point without a ``# columns`` line (Slicer 4.6 and later write it).
_FCSV_COLUMNS = "id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID".split(",")
#: Slicer 5's ``positionStatus`` written after the named columns: 2 is a placed point.
_FCSV_PLACED = "2"


def _read_fcsv(path: Path) -> Markups:
    """Slicer's legacy point list (``.fcsv``): ``#`` header lines (``CoordinateSystem``, ``columns``), then
    one comma-separated line per point; Slicer 5 adds the point's status and whether it was made automatically
    after the named columns, and only placed points (status 2) are read."""
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except FileNotFoundError:
        raise SlicerFileError(f"markups file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SlicerFileError(f"{path} is not a readable .fcsv markups file ({exc})") from None
    system, columns = "RAS", _FCSV_COLUMNS
    labels, descriptions, pts = [], [], []
    for n, line in enumerate(lines, 1):
        if line.startswith("#"):
            key, _, value = (part.strip() for part in line[1:].partition("="))
            if key == "CoordinateSystem":
                if value not in _FCSV_SYSTEMS:
                    raise SlicerFileError(f"{path}: CoordinateSystem {value!r} is neither LPS nor RAS")
                system = _FCSV_SYSTEMS[value]
            elif key == "columns":
                columns = [c.strip() for c in value.split(",")]
            continue
        if not line.strip():
            continue
        cells = next(csv.reader([line]))  # a label or note holding commas is quoted
        try:
            xyz = [float(cells[columns.index(c)]) for c in "xyz"]
        except (ValueError, IndexError):
            raise SlicerFileError(f"{path}: line {n} has no x, y, z of finite numbers") from None
        if not all(math.isfinite(v) for v in xyz):
            raise SlicerFileError(f"{path}: line {n} has no x, y, z of finite numbers")
        if len(cells) >= len(columns) + 2 and cells[len(columns)].strip() != _FCSV_PLACED:
            continue  # Slicer 5: listed but not placed
        named = dict(zip(columns, cells))
        labels.append(named.get("label", ""))
        descriptions.append(named.get("desc", ""))
        pts.append(xyz)
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if system == "RAS":
        pts = pts @ _FLIP
    return Markups(name=path.name[: -len(".fcsv")], labels=tuple(labels), points_lps_mm=pts,
                   descriptions=tuple(descriptions))


def write_itk_transform(path, T_parent_from_child, *, note: str = "") -> Path:
    """Write a rigid transform as an ITK text transform file, as Slicer reads it.

    Parameters
    ----------
    path : str or Path
        Output ``.tfm`` (or ``.txt``) file.
    T_parent_from_child : (4, 4) float64
        The to-parent transform of the Slicer node, LPS, mm: it maps points of
        the child frame into the parent frame (e.g. ``T_patient_from_probe`` for
        ``ProbeToPatient.tfm``).  The file stores its inverse, the resampling
        direction ITK expects.
    note : str
        One line written as a comment under the magic line.

    Returns
    -------
    Path
    """
    T = check_transform(T_parent_from_child, name="T_parent_from_child", rigid=True)
    if "\n" in note or "\r" in note:
        raise ValueError("note must be a single line")
    inv = invert(T)
    params = [*inv[:3, :3].ravel(), *inv[:3, 3]]
    lines = [_ITK_MAGIC]
    if note:
        lines.append(f"# {note}")
    lines += [
        "#Transform 0",
        "Transform: AffineTransform_double_3_3",
        "Parameters: " + " ".join(repr(float(x)) for x in params),
        "FixedParameters: 0 0 0",
    ]
    write_text_atomic(path, "\n".join(lines) + "\n")
    return Path(path)


def read_itk_transform(path) -> np.ndarray:
    """Read a single affine ITK text transform file and return its to-parent matrix.

    Parameters
    ----------
    path : str or Path
        A ``.tfm``/``.txt`` file written by Slicer, ITK or :func:`write_itk_transform`.

    Returns
    -------
    (4, 4) float64
        ``T_parent_from_child``: the inverse of the stored (resampling) transform,
        with the centre (``FixedParameters``) folded into the translation.

    Raises
    ------
    SlicerFileError
        Not an ITK transform file, more than one transform, a non-affine type,
        or malformed parameters.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except FileNotFoundError:
        raise SlicerFileError(f"transform file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SlicerFileError(f"{path} is not a text ITK transform file ({exc})") from None
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if not lines or not lines[0].startswith("#Insight Transform File"):
        raise SlicerFileError(f"{path} is not an ITK transform file (no '{_ITK_MAGIC}' line)")
    fields: dict[str, list[str]] = {}
    for ln in lines[1:]:
        if ln.startswith("#") or ":" not in ln:
            continue
        key, value = ln.split(":", 1)
        fields.setdefault(key.strip(), []).append(value.strip())
    types = fields.get("Transform", [])
    if len(types) != 1:
        raise SlicerFileError(
            f"{path} holds {len(types)} transforms; heartreg reads one linear transform "
            "(harden or export a single transform node from Slicer)"
        )
    kind = types[0]
    if not any(kind.startswith(t + "_") for t in _AFFINE_TYPES) or not kind.endswith("_3_3"):
        raise SlicerFileError(f"{path}: transform type {kind!r} is not a 3-D affine transform")
    try:
        params = np.array(fields["Parameters"][0].split(), dtype=np.float64)
        fixed = np.array(fields.get("FixedParameters", ["0 0 0"])[0].split(), dtype=np.float64)
    except (KeyError, ValueError) as exc:
        raise SlicerFileError(f"{path}: Parameters/FixedParameters are missing or not numbers ({exc})") from None
    if params.shape != (12,) or fixed.shape != (3,) or not np.all(np.isfinite(params)):
        raise SlicerFileError(
            f"{path}: expected 12 finite Parameters and 3 FixedParameters, got {params.size} and {fixed.size}"
        )
    A = params[:9].reshape(3, 3)
    stored = np.eye(4)
    stored[:3, :3] = A
    stored[:3, 3] = params[9:] + fixed - A @ fixed  # x -> A (x - c) + c + t
    try:
        return np.linalg.inv(stored)
    except np.linalg.LinAlgError:
        raise SlicerFileError(f"{path}: the transform is singular") from None
