"""External label maps (a segmentation from 3D Slicer, TotalSegmentator, ...).

A label map is read with its own affine and resampled onto the CT volume's grid
through both affines (nearest label), so it may come on any grid, in any
orientation.  Formats: NIfTI (``.nii``, ``.nii.gz``, through nibabel; RAS on
disk), NRRD (``.nrrd`` through :mod:`imaging.nrrd`) and DICOM SEG (through :mod:`imaging.seg`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points
from imaging.files import gzip_damage
from imaging.nrrd import NrrdError, is_nrrd_path, read_nrrd
from imaging.volume_file import degenerate_affine, load_nifti, nifti_lps_affine, nifti_misnamed, nifti_unoriented

__all__ = ["LabelMapError", "LabelMap", "MASK_FILE", "label_map_kind", "read_label_map", "mask_on_grid", "on_air",
           "other_frame", "write_mask"]

#: the model's mask beside its mesh (``heartreg model``, ``pipeline``): what was meshed, for 3D Slicer's Segment
#: Editor and back through ``--mask``.
MASK_FILE = "heart_mask.nii.gz"


class LabelMapError(HeartregError, ValueError):
    """A label map that cannot be read or used."""


@dataclass(frozen=True)
class LabelMap:
    """Integer labels on their own grid.

    Attributes
    ----------
    labels : (n_k, n_j, n_i) int array
        Indexed ``[k, j, i]`` like :class:`imaging.Volume`; ``(n_layers, n_k,
        n_j, n_i)`` for a 3D Slicer segmentation whose segments overlap (one
        label layer each), whose segments are then chosen by name.
    T_patient_from_voxel : (4, 4) float64
        ``(i, j, k, 1)`` to patient LPS mm.
    source : str
    names : dict
        Label value to name, where the file says (one layer).
    segments : dict
        A Slicer segmentation's segments: name to ``(layer, label value)``.
    """

    labels: np.ndarray
    T_patient_from_voxel: np.ndarray
    source: str
    names: dict
    segments: dict = field(default_factory=dict)
    #: a NIfTI header without orientation (qform_code and sform_code 0): placed where nibabel guesses
    unoriented: bool = False
    #: a DICOM SEG's Frame of Reference UID ('' for other files, which carry none)
    frame_of_reference_uid: str = ""

    def __post_init__(self):
        if problem := degenerate_affine(self.T_patient_from_voxel):  # else: "made on another study?"
            raise LabelMapError(f"label map {self.source}: {problem}; write it again with its CT's geometry")

    def select(self, label=None) -> tuple[np.ndarray, str]:
        """The voxels of one label, ``[k, j, i]`` bool, and how it is called in messages.

        ``label``: a value or a name (case-insensitive); None for the only
        label there is.

        Raises
        ------
        LabelMapError
            Empty, unknown label, several labels and no choice.
        """
        if self.labels.ndim == 4:
            by_name = {name.lower(): where for name, where in self.segments.items()}
            known = ", ".join(list(self.segments)[:20]) or "none"
            if label is None and len(self.segments) == 1:
                label = next(iter(self.segments))
            if not self.segments:
                raise LabelMapError(
                    f"{self.source} holds {self.labels.shape[0]} overlapping layers and no segment names; export "
                    "the heart alone (or as a label map) from 3D Slicer"
                )
            if isinstance(label, (int, np.integer)):  # a label value: the segment of that value, if only one
                of_value = [name for name, (_, value) in self.segments.items() if value == label]
                label = of_value[0] if len(of_value) == 1 else label
            if not isinstance(label, str) or label.lower() not in by_name:
                raise LabelMapError(
                    f"{self.source} is a segmentation of {self.labels.shape[0]} overlapping layers: choose a "
                    f"segment by name with --label NAME (segments: {known})"
                )
            layer, value = by_name[label.lower()]
            if not 0 <= layer < self.labels.shape[0]:
                raise LabelMapError(f"{self.source}: segment {label!r} is in layer {layer}, but the file holds "
                                    f"{self.labels.shape[0]} layers")
            chosen = self.labels[layer] == value
            if not chosen.any():
                raise LabelMapError(f"segment {label!r} of {self.source} is empty (no voxel of label {value} in "
                                    f"layer {layer})")
            return chosen, f"segment {label!r}"
        values = np.unique(self.labels)
        values = values[values != 0]
        if values.size == 0:
            raise LabelMapError(f"label map {self.source} is empty (all zero)")
        if isinstance(label, str):
            by_name = {name.lower(): value for value, name in self.names.items()}
            if label.lower() not in by_name:
                known = ", ".join(sorted(self.names.values())[:20]) or "none"
                raise LabelMapError(
                    f"label {label!r} is not named in {self.source} (names: {known}); give --label N or a name it has"
                )
            label = int(by_name[label.lower()])
        if label is None:
            if values.size > 1:
                named = ", ".join(f"{v}{' (' + self.names[v] + ')' if v in self.names else ''}" for v in values[:20])
                # a probability map stored in percent or in bytes (0-100, 0-255): many values, none named
                ramp = not self.names and values.size > 20 and values[-1] <= 255
                raise LabelMapError(
                    f"label map {self.source} holds several labels ({named}{', ...' if values.size > 20 else ''}); "
                    "choose one with --label N" + ("; or is it a probability map (in percent or 0-255)? threshold it "
                                                   "to a 0/1 mask first" if ramp else "")
                )
            label = int(values[0])
        elif label not in values:
            raise LabelMapError(
                f"label {label} is not in {self.source}; it holds {', '.join(str(v) for v in values[:20])}"
            )
        return self.labels == label, f"label {label}"

    def volume_ml(self, label=None) -> float:
        """The volume of one label (as :meth:`select` chooses it) on the label map's own grid, ml."""
        chosen, _ = self.select(label)
        return float(np.count_nonzero(chosen)) * abs(float(np.linalg.det(self.T_patient_from_voxel[:3, :3]))) / 1000.0


def _read_nifti(path: Path) -> LabelMap:
    if misnamed := nifti_misnamed(path):
        raise LabelMapError(f"NIfTI label map {path} {misnamed}")
    damage = gzip_damage(path)
    if damage:
        raise LabelMapError(f"NIfTI label map {path} is damaged ({damage}): copy it again from its source")
    try:
        img, data, _ = load_nifti(path)  # nibabel's mends of the header not printed
    except Exception as exc:  # nibabel raises many types for bad files
        raise LabelMapError(f"cannot read NIfTI label map {path}: {exc}") from None
    if data.ndim != 3:
        raise LabelMapError(f"label map {path} must be 3-D, got shape {data.shape}")
    T, conflict = nifti_lps_affine(img)
    if conflict:
        raise LabelMapError(f"NIfTI label map {path}: {conflict}")
    names = _caret_label_names(img)
    labels = _whole_labels(data, path)
    unoriented = nifti_unoriented(img)
    return LabelMap(np.ascontiguousarray(labels.transpose(2, 1, 0)), T, str(path), names, unoriented=unoriented)


#: Largest distance of a float label map's value from a whole number (float rounding of a saved label).
WHOLE_TOL = 1e-3
#: A float map whose values all stay below this is one structure's mask, rounded (cut at 0.5): a binary mask
#: resampled with linear or cubic interpolation (-0.1 to 1.35 with scipy's cubic spline), a probability map.
#: Fractional values in a map reaching it are labels of several structures that no rounding names (3.7).
ONE_MASK_BELOW = 1.5


def _whole_labels(data, path) -> np.ndarray:
    """A label map's voxels as int32 labels, NaN or infinite ones no label; a float map is rounded.

    A value that rounds to a negative label is refused, and so is a fractional value in a map of several labels
    (reaching :data:`ONE_MASK_BELOW`), in one line naming the file and the value.  A float map (a probability
    map, a mask resampled by interpolation, labels saved as float) is common in NIfTI and NRRD alike; a NaN cast
    to int would be label -2147483648.
    """
    if np.issubdtype(data.dtype, np.floating):
        finite = np.isfinite(data)
        if not finite.any():
            raise LabelMapError(f"label map {path} holds no number (NaN or infinite everywhere)")
        data = np.where(finite, data, 0.0)  # NaN or inf is no label (it was cast to -2147483648)
    labels = np.round(data).astype(np.int32)
    low = int(labels.min())
    if low < 0:  # a label is a whole number >= 0 (0 the background): -1 is no label of any mask
        n = int(np.count_nonzero(labels < 0))
        hint = ("is it the CT, not a mask? give the mask's file" if low <= -100 else
                "write the mask again with 0 outside and 1 (or a label of its own) for the heart")
        raise LabelMapError(f"label map {path} holds the negative value {float(data.min()):.6g} ({n} voxel(s)); "
                            f"labels are whole numbers >= 0 (0 the background): {hint}")
    if np.issubdtype(data.dtype, np.floating):
        off = np.abs(data - labels) > WHOLE_TOL
        if off.any() and not labels.any():  # a probability map below 0.5 everywhere
            raise LabelMapError(f"label map {path} holds no whole-number label: its values ({float(data.min()):g} to "
                                f"{float(data.max()):g}) round to 0 (a probability map? threshold it at 0.5 first)")
        if off.any() and data.max() >= ONE_MASK_BELOW:  # rounding 3.7 to label 4 names no structure
            value = float(data[off][0])
            raise LabelMapError(f"label map {path} holds the value {value:.6g}, not a whole-number label "
                                f"({int(np.count_nonzero(off))} such voxel(s)): labels are whole numbers >= 0; "
                                "resample the label map with nearest neighbour")
    return labels


def _caret_label_names(img) -> dict:
    """Label names from a NIfTI header extension holding a Caret XML label table.

    TotalSegmentator's multi-label output (``--ml``) stores its class names so:
    ``<Label Key="51" ...><![CDATA[heart]]></Label>``.
    """
    import xml.etree.ElementTree as ET

    names = {}
    for ext in getattr(img.header, "extensions", ()):
        try:
            root = ET.fromstring(ext.get_content().decode("utf-8", "replace").strip())
        except (ET.ParseError, AttributeError, ValueError):
            continue
        for node in root.iter("Label"):
            key = node.get("Key")
            if key is not None and key.lstrip("-").isdigit() and node.text:
                names[int(key)] = node.text.strip()
    return names


#: TotalSegmentator's file for the whole heart in its ``segmentations/`` folder.
TOTALSEG_HEART = "heart.nii.gz"


def _read_nrrd(path: Path) -> LabelMap:
    """An NRRD label map; a 3D Slicer segmentation (``.seg.nrrd``) with its segments' names and layers."""
    try:
        data, T, fields = read_nrrd(path)
    except NrrdError as exc:
        raise LabelMapError(f"label map: {exc}") from None
    segments = {}
    layered = data.ndim == 4
    for n in range(10_000):
        if f"segment{n}_name" not in fields and f"segment{n}_id" not in fields:
            break
        name = fields.get(f"segment{n}_name") or fields.get(f"segment{n}_id")
        # without Layer and LabelValue fields (Slicer before 4.11): one layer per segment, each of label 1
        try:
            where = (int(fields.get(f"segment{n}_layer", n if layered else 0)),
                     int(fields.get(f"segment{n}_labelvalue", 1 if layered else n + 1)))
        except ValueError:
            raise LabelMapError(f"{path}: segment {n} ({name!r}) has a bad layer or label value") from None
        segments[name] = where
    names = {value: name for name, (layer, value) in segments.items() if layer == 0} if data.ndim == 3 else {}
    return LabelMap(_whole_labels(data, path), T, str(path), names, segments)


def label_map_kind(source) -> str:
    """What a label map file is, for outputs: not its name, which can name the patient."""
    name = Path(source).name.lower()
    if name.endswith(".seg.nrrd"):
        return "3D Slicer segmentation"
    if name.endswith(".nrrd"):
        return "NRRD"
    if name.endswith((".nii", ".nii.gz")):
        return "NIfTI"
    return "DICOM SEG"


def read_label_map(path, structure: str | None = None) -> LabelMap:
    """Read a label map (NIfTI, NRRD or DICOM SEG) with its affine.

    ``path`` may also be a TotalSegmentator output folder: the folder holding
    ``heart.nii.gz`` (one file per structure), or the folder above it with a
    ``segmentations/`` sub-folder; ``structure`` (e.g. ``"heart"``, the
    default) names the file, and its label 1 carries that name.  A multi-label
    NIfTI keeps the names of its labels (TotalSegmentator ``--ml``), so a label
    can be chosen by name.
    """
    path = Path(path)
    if not path.exists():
        raise LabelMapError(f"label map {path} does not exist")
    if path.is_dir():
        name = str(structure or "").strip().lower().removesuffix(".gz").removesuffix(".nii")  # its files are lower case
        file = f"{name}.nii.gz" if name else TOTALSEG_HEART
        for candidate in (path / file, path / "segmentations" / file):
            if candidate.is_file():
                found = _read_nifti(candidate)
                return dataclasses.replace(found, names=found.names or {1: file[: -len(".nii.gz")]})
        raise LabelMapError(
            f"{path} is a folder without {file} (or segmentations/{file}); "
            "give a structure of the folder with --label NAME, or the label map file itself with --mask FILE"
        )
    if not path.is_file():  # a named pipe would block the read
        raise LabelMapError(f"label map {path} is not a regular file (a named pipe or device); give the mask's file")
    name = path.name.lower()
    if name.endswith((".nii", ".nii.gz")):
        return _read_nifti(path)
    if is_nrrd_path(name):  # a detached .nhdr is refused by the reader, by name
        return _read_nrrd(path)
    from imaging.seg import read_dicom_seg

    try:
        labels, T, names, frame, layer_of = read_dicom_seg(path)
    except ValueError as exc:
        raise LabelMapError(
            f"{path} is neither NIfTI (.nii/.nii.gz), NRRD (.nrrd) nor a DICOM SEG: {exc}; give the heart's label "
            "map in one of these (an RT structure set: export it as a labelmap, e.g. from 3D Slicer)"
        ) from None
    segments = {}
    if labels.ndim == 4:  # overlapping segments, one layer each where they overlap: chosen by name or number
        segments = {(names.get(v) or f"segment {v}"): (n, v) for v, n in sorted(layer_of.items())}
    return LabelMap(labels, T, str(path), names, segments, frame_of_reference_uid=frame)


#: HU below which a voxel is air or lung, which no heart holds; and the share of a mask's voxels there from which
#: the mask is said to lie elsewhere (``shared/realct``'s reference: 0 %; moved 10 / 20 / 40 mm: 4-8 / 13-18 /
#: 26-38 %).
AIR_HU, MAX_AIR_SHARE = -300.0, 0.10


def on_air(mask, hu) -> str:
    """What to say of a mask lying partly on air or lung in the CT ('' otherwise): a mask drawn on another scan,
    another phase's reconstruction or in another patient frame overlaps the CT but not its heart."""
    share = float(np.count_nonzero(np.asarray(hu)[mask] < AIR_HU)) / max(int(np.count_nonzero(mask)), 1)
    if share <= MAX_AIR_SHARE:
        return ""
    return (f"{share:.0%} of its voxels lie on air or lung in this CT (below {AIR_HU:.0f} HU; a heart holds none): "
            "is it drawn on another scan, or placed in another frame? check the model over the CT (model_ct.png)")


def other_frame(label_map: LabelMap, volume) -> str:
    """What to say of a DICOM SEG drawn in another frame of reference than a DICOM CT's (another study or
    acquisition), '' otherwise: its patient coordinates need not be the CT's, though it may overlap the CT
    anyway.  A volume file (NIfTI, NRRD) has no frame of reference to compare."""
    from_dicom = bool(volume.slices) and bool(volume.slices[0].sop_instance_uid)
    ct_frame = volume.series.frame_of_reference_uid
    if not (label_map.frame_of_reference_uid and from_dicom and ct_frame  # a CT without one: nothing to compare
            and label_map.frame_of_reference_uid != ct_frame):
        return ""
    return ("drawn in another frame of reference than the CT's (another study or acquisition?): it is placed by its "
            "patient coordinates, which need not be this CT's; check the model lies on this heart")


def _no_overlap(label, label_map) -> LabelMapError:
    why = ("its header has no orientation (qform_code and sform_code 0), so it cannot be placed: write it with the "
           "CT's affine" if label_map.unoriented else "was it made on another study?")
    return LabelMapError(f"{label} of {label_map.source} does not overlap the CT volume; {why}")


def mask_on_grid(label_map: LabelMap, shape, T_patient_from_voxel, *, label: int | None = None) -> np.ndarray:
    """Resample one label of ``label_map`` onto a volume grid (nearest neighbour).

    Parameters
    ----------
    label_map : LabelMap
    shape : (3,) int
        The volume's ``(n_slices, n_rows, n_cols)``.
    T_patient_from_voxel : (4, 4) float64
        The volume's affine.
    label : int or str, optional
        Which label, by value or by name (case-insensitive, from the file's
        label table); by default the only non-zero label (several -> error
        listing them).

    Returns
    -------
    (n_slices, n_rows, n_cols) bool

    Raises
    ------
    LabelMapError
        Empty label map, unknown label, several labels without a choice, or no
        overlap with the volume.
    """
    src, label = label_map.select(label)

    T_vol = np.asarray(T_patient_from_voxel, dtype=float)
    # bounding box of the label in the volume's voxel coordinates
    kji = np.argwhere(src)
    lo, hi = kji.min(axis=0), kji.max(axis=0)
    corners = np.array([[i, j, k] for k in (lo[0] - 1, hi[0] + 1) for j in (lo[1] - 1, hi[1] + 1) for i in (lo[2] - 1, hi[2] + 1)], float)
    ijk = apply_to_points(np.linalg.inv(T_vol) @ label_map.T_patient_from_voxel, corners)
    shape = tuple(int(s) for s in shape)
    box_lo = np.clip(np.floor(ijk.min(axis=0)).astype(int), 0, np.array(shape[::-1]) - 1)
    box_hi = np.clip(np.ceil(ijk.max(axis=0)).astype(int) + 1, 0, np.array(shape[::-1]))
    mask = np.zeros(shape, bool)
    if np.any(box_hi <= box_lo):
        raise _no_overlap(label, label_map)
    ii, jj, kk = np.meshgrid(*(np.arange(a, b) for a, b in zip(box_lo, box_hi)), indexing="ij")
    pts = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1).astype(float)
    T_src_from_vol = np.linalg.inv(label_map.T_patient_from_voxel) @ T_vol
    src_ijk = apply_to_points(T_src_from_vol, pts)
    # nearest voxel, rounded here: map_coordinates (order 0, mode "constant") took a point a rounding error
    # below the map's first slice for outside it, and a label map cropped to its label (a SEG, whose first frame
    # is the label's first slice; a Slicer segment's extent) lost that slice
    nearest = np.rint(src_ijk[:, ::-1]).astype(np.int64)  # (k, j, i)
    inside = np.all((nearest >= 0) & (nearest < np.array(src.shape)), axis=1)
    values = np.zeros(len(nearest), bool)
    values[inside] = src[tuple(nearest[inside].T)]
    sub = values.reshape(ii.shape).transpose(2, 1, 0)  # (k, j, i)
    mask[box_lo[2] : box_hi[2], box_lo[1] : box_hi[1], box_lo[0] : box_hi[0]] = sub
    if not mask.any():
        raise _no_overlap(label, label_map)
    return mask


def write_mask(path, mask, T_patient_from_voxel) -> Path:
    """Write a heart mask as a gzipped NIfTI label map (1 heart, 0 not; uint8), atomically.

    ``mask`` is indexed ``[k, j, i]`` and ``T_patient_from_voxel`` maps ``(i, j, k)`` to patient LPS
    mm; the file's sform and qform (code 1, scanner) both hold it in RAS, as NIfTI's.  3D Slicer loads
    it as a segmentation or a label map over the CT; :func:`read_label_map` reads it back to the same
    voxels.  The bytes depend on the mask alone (the gzip stream stamps no time).
    """
    import gzip

    import nibabel as nib

    from imaging.files import atomic_path

    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ np.asarray(T_patient_from_voxel, dtype=np.float64)
    mask = np.asarray(mask)
    voxels = mask.view(np.uint8) if mask.dtype == bool else mask.astype(np.uint8)
    # (i, j, k) as a view: nibabel writes it in Fortran order, the (k, j, i) array's own, with no copy
    image = nib.Nifti1Image(voxels.transpose(2, 1, 0), affine)
    image.set_qform(affine, code=1)
    image.set_sform(affine, code=1)
    image.header.set_xyzt_units("mm")
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(gzip.compress(image.to_bytes(), compresslevel=6, mtime=0))
    return path
