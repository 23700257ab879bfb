"""External label maps: NIfTI, NRRD and DICOM SEG, resampled through both affines.

Truth: a label map whose voxels encode a known patient-space ball; after
resampling onto another grid, every voxel centre of the result must lie inside
the ball (up to one source voxel) and the ball's volume must be kept.
"""

from __future__ import annotations

import gzip

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from imaging.seg import SEG_SOP_CLASS
from modeling.labelmap import LabelMapError, mask_on_grid, read_label_map

CENTRE = np.array([10.0, -20.0, 30.0])
RADIUS = 15.0


def _ball_labels(T, shape_kji, value=3):
    k, j, i = np.indices(shape_kji)
    ijk = np.stack([i, j, k], axis=-1).reshape(-1, 3).astype(float)
    p = ijk @ T[:3, :3].T + T[:3, 3]
    inside = np.linalg.norm(p - CENTRE, axis=1) <= RADIUS
    return np.where(inside, value, 0).reshape(shape_kji).astype(np.uint8)


def _target_grid():
    """An oblique 1.5 mm grid around the ball (the 'CT')."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [10, 20, -15], degrees=True).as_matrix() * 1.5
    T[:3, 3] = CENTRE - T[:3, :3] @ np.array([15, 15, 15])
    return T, (30, 30, 30)


def _check(label_map, label=3):
    T, shape = _target_grid()
    mask = mask_on_grid(label_map, shape, T, label=label)
    k, j, i = np.nonzero(mask)
    p = np.stack([i, j, k], axis=1) @ T[:3, :3].T + T[:3, 3]
    assert np.linalg.norm(p - CENTRE, axis=1).max() <= RADIUS + 1.0  # one source voxel
    volume = mask.sum() * abs(np.linalg.det(T[:3, :3]))
    assert volume == pytest.approx(4 / 3 * np.pi * RADIUS**3, rel=0.08)


def _source_T():
    T = np.diag([0.8, 0.9, 1.1, 1.0])
    T[:3, 3] = CENTRE - 20.0
    return T, (40, 46, 52)  # (k, j, i)


def test_nrrd_lps_and_ras_gzip(tmp_path):
    T, shape = _source_T()
    labels = _ball_labels(T, shape)
    for space, flip in (("left-posterior-superior", np.eye(3)), ("right-anterior-superior", np.diag([-1.0, -1.0, 1.0]))):
        M = flip @ T[:3, :3]
        origin = flip @ T[:3, 3]
        dirs = " ".join("(" + ",".join(f"{v:.6f}" for v in M[:, c]) + ")" for c in range(3))
        header = (
            "NRRD0004\ntype: uint8\ndimension: 3\n"
            f"space: {space}\nsizes: {shape[2]} {shape[1]} {shape[0]}\n"
            f"space directions: {dirs}\nencoding: gzip\n"
            f"space origin: ({origin[0]:.6f},{origin[1]:.6f},{origin[2]:.6f})\n\n"
        )
        path = tmp_path / f"ball_{space[:4]}.nrrd"
        path.write_bytes(header.encode() + gzip.compress(labels.tobytes()))
        _check(read_label_map(path))


def _write_seg(path, T, labels, more=(), frame_uid=None):
    """A minimal binary DICOM SEG of one segment (number 3, "Heart") on the grid T; ``more``: further segments,
    ``(number, label, mask)``, which may overlap it."""
    segments = [(3, "Heart", labels > 0), *more]
    frames = [(number, k) for number, _, mask in segments for k in range(labels.shape[0]) if mask[k].any()]
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = SEG_SOP_CLASS
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID = SEG_SOP_CLASS
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality = "SEG"
    if frame_uid:
        ds.FrameOfReferenceUID = frame_uid
    ds.SegmentationType = "BINARY"
    ds.Rows, ds.Columns = labels.shape[1], labels.shape[2]
    ds.NumberOfFrames = len(frames)
    ds.SamplesPerPixel, ds.BitsAllocated, ds.BitsStored, ds.HighBit = 1, 1, 1, 0
    ds.PixelRepresentation = 0
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.SegmentSequence = []
    for number, name, _ in segments:
        seg = Dataset()
        seg.SegmentNumber = number
        seg.SegmentLabel = name
        ds.SegmentSequence.append(seg)
    shared = Dataset()
    orient = Dataset()
    spacing = np.linalg.norm(T[:3, :3], axis=0)
    orient.ImageOrientationPatient = list(T[:3, 0] / spacing[0]) + list(T[:3, 1] / spacing[1])
    measures = Dataset()
    measures.PixelSpacing = [float(spacing[1]), float(spacing[0])]
    measures.SliceThickness = float(spacing[2])
    measures.SpacingBetweenSlices = float(spacing[2])
    shared.PlaneOrientationSequence = [orient]
    shared.PixelMeasuresSequence = [measures]
    ds.SharedFunctionalGroupsSequence = [shared]
    per_frame = []
    for number, k in frames:
        item, pos, ident = Dataset(), Dataset(), Dataset()
        pos.ImagePositionPatient = [float(v) for v in T[:3, 3] + k * T[:3, 2]]
        ident.ReferencedSegmentNumber = number
        item.PlanePositionSequence = [pos]
        item.SegmentIdentificationSequence = [ident]
        per_frame.append(item)
    ds.PerFrameFunctionalGroupsSequence = per_frame
    masks = {number: mask for number, _, mask in segments}
    bits = np.packbits(np.stack([masks[number][k] for number, k in frames]).reshape(-1), bitorder="little")
    ds.PixelData = bits.tobytes() + (b"\0" if len(bits) % 2 else b"")
    ds.save_as(path, enforce_file_format=True)


def test_dicom_seg(tmp_path):
    T, shape = _source_T()
    labels = _ball_labels(T, shape)
    path = tmp_path / "seg.dcm"
    _write_seg(path, T, labels)
    label_map = read_label_map(path)
    assert label_map.names == {3: "Heart"}
    _check(label_map)


@pytest.mark.parametrize("spacing_given", [True, False])
def test_a_dicom_seg_with_frames_apart_keeps_its_slices(tmp_path, spacing_given):
    """A SEG holds no empty frames: two segments three slices apart (or a structure drawn on every third slice)
    leave gaps between its positions, whose median was taken as the slices' spacing (the segments moved and
    stretched).  Spacing Between Slices decides where given, else Slice Thickness (each where every gap is a
    whole number of it)."""
    T, shape = _source_T()
    k = np.indices(shape)[0]
    heart = (_ball_labels(T, shape) > 0) & (k % 3 == 0)  # drawn on every third slice
    _write_seg(tmp_path / "seg.dcm", T, heart.astype(np.int32), [(4, "Apart", (k == 37) & (np.indices(shape)[1] < 4))])
    if not spacing_given:
        ds = pydicom.dcmread(tmp_path / "seg.dcm")
        del ds.SharedFunctionalGroupsSequence[0].PixelMeasuresSequence[0].SpacingBetweenSlices
        ds.save_as(tmp_path / "seg.dcm")
    label_map = read_label_map(tmp_path / "seg.dcm")
    np.testing.assert_allclose(label_map.T_patient_from_voxel[:3, 2], T[:3, 2], atol=1e-6)
    assert np.array_equal(mask_on_grid(label_map, shape, T, label="Heart"), heart)  # its first slice kept too
    assert np.array_equal(mask_on_grid(label_map, shape, T, label="Apart"), (k == 37) & (np.indices(shape)[1] < 4))


def test_a_label_map_dicom_seg(tmp_path):
    """DICOM's Label Map Segmentation (1.2.840.10008.5.1.4.1.1.66.7, 2024; highdicom writes it): one frame per
    plane, each pixel its segment's number; read as a label map with its names (it was 'not Segmentation
    Storage')."""
    from imaging.seg import LABEL_MAP_SEG_SOP_CLASS

    T, shape = _source_T()
    heart = _ball_labels(T, shape) > 0
    labels = np.where(heart, 3, 0).astype(np.uint8)
    labels[:3, :3, :3] = 5  # another segment apart
    _write_seg(tmp_path / "seg.dcm", T, labels.astype(np.int32))  # its geometry and segments, as a binary SEG
    ds = pydicom.dcmread(tmp_path / "seg.dcm")
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = LABEL_MAP_SEG_SOP_CLASS
    ds.SegmentationType = "LABELMAP"
    seg = Dataset()
    seg.SegmentNumber, seg.SegmentLabel = 5, "Aorta"
    ds.SegmentSequence.append(seg)
    planes = [k for k in range(shape[0]) if labels[k].any()]
    ds.NumberOfFrames = len(planes)
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
    for item, k in zip(ds.PerFrameFunctionalGroupsSequence, planes):  # one frame per plane, no segment reference
        item.PlanePositionSequence[0].ImagePositionPatient = [float(v) for v in T[:3, 3] + k * T[:3, 2]]
        del item.SegmentIdentificationSequence
    del ds.PerFrameFunctionalGroupsSequence[len(planes):]
    ds.PixelData = labels[planes].tobytes()
    ds.save_as(tmp_path / "labelmap.dcm", enforce_file_format=True)
    label_map = read_label_map(tmp_path / "labelmap.dcm")
    assert label_map.names == {3: "Heart", 5: "Aorta"}
    _check(label_map, label="Heart")
    assert np.array_equal(mask_on_grid(label_map, shape, T, label=5), labels == 5)


def test_dicom_seg_with_overlapping_segments(tmp_path):
    """A SEG of the heart and its left ventricle (audit aud_masks): the segments were painted into one label
    volume, the later over the earlier, so ``--label Heart`` lost the ventricle's voxels without a word (the real
    CT's reference heart with a 'Left ventricle' segment over 107 ml of it: Dice 0.924 instead of 0.993)."""
    T, shape = _source_T()
    labels = _ball_labels(T, shape)
    ventricle = (labels > 0) & (np.indices(shape)[2] < shape[2] // 2)  # half of the heart
    aorta = np.zeros(shape, bool)
    aorta[:3, :3, :3] = True  # apart from both
    _write_seg(tmp_path / "seg.dcm", T, labels, [(4, "Left ventricle", ventricle), (5, "Aorta", aorta)])
    label_map = read_label_map(tmp_path / "seg.dcm")
    assert label_map.segments == {"Heart": (0, 3), "Left ventricle": (1, 4), "Aorta": (0, 5)}
    _check(label_map, label="heart")
    _check(label_map, label=3)  # by segment number too
    T_target, shape_target = _target_grid()
    assert np.array_equal(mask_on_grid(label_map, shape_target, T_target, label=4),
                          mask_on_grid(label_map, shape_target, T_target, label="left ventricle"))
    with pytest.raises(LabelMapError, match=r"choose a segment by name .*\(segments: Heart, Left ventricle, Aorta\)"):
        mask_on_grid(label_map, shape_target, T_target)


def test_nrrd_float_label_map_nan_and_probability(tmp_path):
    """A float NRRD label map (audit aud_masks): NaN outside the heart became label -2147483648 (after numpy's
    'invalid value encountered in cast'), so the map 'held several labels'; a probability map below 0.5 was
    'empty (all zero)'.  NIfTI maps had both handled already."""
    import warnings

    T, shape = _source_T()
    labels = _ball_labels(T, shape)
    dirs = " ".join("(" + ",".join(f"{v:.6f}" for v in T[:3, c]) + ")" for c in range(3))
    header = (f"NRRD0004\ntype: float\ndimension: 3\nspace: left-posterior-superior\n"
              f"sizes: {shape[2]} {shape[1]} {shape[0]}\nspace directions: {dirs}\nencoding: raw\n"
              f"space origin: ({T[0, 3]:.6f},{T[1, 3]:.6f},{T[2, 3]:.6f})\n\n").encode()
    (tmp_path / "nan.nrrd").write_bytes(header + np.where(labels > 0, 3.0, np.nan).astype("<f4").tobytes())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy warning on the console
        label_map = read_label_map(tmp_path / "nan.nrrd")
    assert set(np.unique(label_map.labels)) == {0, 3}
    _check(label_map)
    (tmp_path / "p.nrrd").write_bytes(header + np.where(labels > 0, 0.4, 0.0).astype("<f4").tobytes())
    with pytest.raises(LabelMapError, match=r"p.nrrd holds no whole-number label: its values \(0 to 0.4\) round to 0 "
                                            r"\(a probability map\? threshold it at 0.5 first\)"):
        read_label_map(tmp_path / "p.nrrd")


def test_a_dicom_seg_of_another_frame_of_reference(tmp_path):
    """A SEG drawn on another study lands by its patient coordinates, which need not be the CT's: its Frame of
    Reference UID differs from the DICOM CT's, and was never compared (audit aud_masks: meshed without a word)."""
    from imaging import load_study
    from imaging.volume_file import read_volume_file
    from modeling.labelmap import other_frame

    from .realct import write_ct_series

    T, shape = _source_T()
    labels = _ball_labels(T, shape)
    ct = load_study(write_ct_series(np.where(labels > 0, 300, -100)[::4], T @ np.diag([1.0, 1.0, 4.0, 1.0]),
                                    tmp_path / "ct"))
    found = {}
    for name, frame in (("same", ct.series.frame_of_reference_uid), ("other", generate_uid()), ("none", None)):
        _write_seg(tmp_path / f"{name}.dcm", T, labels, frame_uid=frame)
        found[name] = bool(other_frame(read_label_map(tmp_path / f"{name}.dcm"), ct))
    assert found == {"same": False, "other": True, "none": False}
    import nibabel as nib

    nib.save(nib.Nifti1Image(np.zeros((4, 4, 4), np.int16), np.eye(4)), str(tmp_path / "ct.nii.gz"))
    assert not other_frame(read_label_map(tmp_path / "other.dcm"), read_volume_file(tmp_path / "ct.nii.gz"))


def test_unknown_file_and_label(tmp_path):
    bad = tmp_path / "mask.txt"
    bad.write_text("not a label map")
    with pytest.raises(LabelMapError, match="neither NIfTI"):
        read_label_map(bad)
    with pytest.raises(LabelMapError, match="does not exist"):
        read_label_map(tmp_path / "missing.nii.gz")
    T, shape = _source_T()
    from modeling.labelmap import LabelMap

    lm = LabelMap(_ball_labels(T, shape), T, "ball", {})
    with pytest.raises(LabelMapError, match="label 5 is not in"):
        mask_on_grid(lm, (10, 10, 10), np.eye(4), label=5)
    assert pydicom.__version__  # pydicom wrote and read the SEG above


def test_a_probability_map_in_percent_is_named_as_one():
    """A map of 0-100 (a probability in percent, as some tools save it in bytes) is no label map of a few labels:
    the refusal asks whether it is a probability map to threshold (it listed 20 'labels' and said --label N);
    a label map of a few labels is refused as before."""
    from modeling.labelmap import LabelMap

    T, shape = _source_T()
    k = np.arange(shape[0])[:, None, None] * np.ones(shape)
    percent = np.rint(100.0 * k / (shape[0] - 1)).astype(np.int32)  # 0..100 along k
    with pytest.raises(LabelMapError, match=r"holds several labels \(3, 5, .*, \.\.\.\); choose one with --label N; "
                                            r"or is it a probability map \(in percent or 0-255\)\? threshold it"):
        LabelMap(percent, T, "p.nii.gz", {}).select(None)
    few = np.where(k < 3, 1, np.where(k < 6, 2, 7)).astype(np.int32)
    with pytest.raises(LabelMapError, match=r"holds several labels \(1, 2, 7\); choose one with --label N$"):
        LabelMap(few, T, "few.nii.gz", {}).select(None)


@pytest.mark.parametrize("edit", ["nan", "zero"])
def test_a_degenerate_affine_is_said(tmp_path, edit):
    """A NIfTI mask whose affine holds a NaN or zero axes was refused as 'made on another study?' (after a
    numpy warning); the CT's reader said 'degenerate affine' (review, session 22)."""
    import nibabel as nib

    T, shape = _source_T()
    img = nib.Nifti1Image(_ball_labels(T, shape).transpose(2, 1, 0).astype(np.uint8), np.diag([-1.0, -1.0, 1.0, 1.0]) @ T)
    header = img.header
    for row in ("srow_x", "srow_y", "srow_z")[: 1 if edit == "nan" else 3]:
        header[row][:3] = np.nan if edit == "nan" else 0.0
    header["sform_code"], header["qform_code"] = 1, 0
    nib.save(nib.Nifti1Image(np.asarray(img.dataobj), None, header=header), str(tmp_path / "m.nii.gz"))
    with pytest.raises(LabelMapError, match=r"m.nii.gz: degenerate affine \(voxel sizes .*\); write it again"):
        read_label_map(tmp_path / "m.nii.gz")


def test_slicer_segmentations_by_segment_name():
    """3D Slicer's ``.seg.nrrd`` (slicerio's samples on CTChest4): segments chosen by name, overlapping layers too."""
    from pathlib import Path

    slicerio = pytest.importorskip("slicerio")
    from imaging.volume_file import read_nrrd_volume

    data = Path(slicerio.__file__).parent / "data"
    ct = read_nrrd_volume(data / "CTChest4.nrrd")
    shape, T = ct.shape, ct.T_patient_from_voxel
    flat = read_label_map(data / "Segmentation.seg.nrrd")
    assert flat.labels.ndim == 3 and flat.names[6] == "left lung" and flat.segments["left lung"] == (0, 6)
    lung = mask_on_grid(flat, shape, T, label="Left Lung")
    assert np.array_equal(lung, flat.labels == 6)  # the same grid as the CT
    assert np.array_equal(mask_on_grid(flat, shape, T, label=6), lung)
    layered = read_label_map(data / "SegmentationOverlapping.seg.nrrd")
    assert layered.labels.shape == (2, *shape) and layered.segments["overlapping sphere"] == (1, 1)
    assert np.array_equal(mask_on_grid(layered, shape, T, label="left lung"), lung)
    sphere = mask_on_grid(layered, shape, T, label="overlapping sphere")
    ribs = mask_on_grid(layered, shape, T, label="ribs")
    assert sphere.any() and (sphere & ribs).any()  # they overlap: no single label map could hold both
    with pytest.raises(LabelMapError, match="overlapping layers: choose a segment by name with --label NAME"):
        mask_on_grid(layered, shape, T, label=1)
    with pytest.raises(LabelMapError, match="segments: ribs, cervical vertebral column"):
        mask_on_grid(layered, shape, T)
    with pytest.raises(LabelMapError, match="'heart' is not named"):
        mask_on_grid(flat, shape, T, label="heart")


def _seg_nrrd(path, layers, segments):
    """A 3D Slicer style layered segmentation: ``layers`` (n_layers, k, j, i) uint8, header fields per segment."""
    n, nk, nj, ni = layers.shape
    fields = "".join(f"Segment{s}_{key}:={value}\n" for s, seg in enumerate(segments) for key, value in seg.items())
    header = (
        f"NRRD0004\ntype: unsigned char\ndimension: 4\nspace: left-posterior-superior\nsizes: {n} {ni} {nj} {nk}\n"
        f"space directions: none (2,0,0) (0,2,0) (0,0,2)\nkinds: list domain domain domain\nencoding: raw\n"
        f"space origin: (0,0,0)\n{fields}\n"
    )
    path.write_bytes(header.encode() + np.ascontiguousarray(np.moveaxis(layers, 0, -1)).tobytes())
    return path


def test_slicer_segmentation_edge_cases(tmp_path):
    """An empty segment, a layer the file lacks, no names, and Slicer's older files (a layer per segment, label 1)."""
    layers = np.zeros((2, 6, 7, 8), np.uint8)
    layers[0, 1:4, 1:4, 1:4] = 1
    layers[1, 2:5, 2:5, 2:5] = 1
    shape, T = (6, 7, 8), np.diag([2.0, 2.0, 2.0, 1.0])
    old = read_label_map(_seg_nrrd(tmp_path / "old.seg.nrrd", layers, [{"Name": "heart"}, {"Name": "liver"}]))
    assert old.segments == {"heart": (0, 1), "liver": (1, 1)}
    assert np.array_equal(mask_on_grid(old, shape, T, label="liver"), layers[1].astype(bool))
    empty = read_label_map(_seg_nrrd(tmp_path / "empty.seg.nrrd", layers, [
        {"Name": "heart", "Layer": 0, "LabelValue": 1}, {"Name": "aorta", "Layer": 1, "LabelValue": 2}]))
    with pytest.raises(LabelMapError, match="segment 'aorta' of .* is empty"):
        mask_on_grid(empty, shape, T, label="aorta")
    beyond = read_label_map(_seg_nrrd(tmp_path / "beyond.seg.nrrd", layers, [{"Name": "heart", "Layer": 7}]))
    with pytest.raises(LabelMapError, match="segment 'heart' is in layer 7, but the file holds 2 layers"):
        mask_on_grid(beyond, shape, T, label="heart")
    unnamed = read_label_map(_seg_nrrd(tmp_path / "unnamed.seg.nrrd", layers, []))
    with pytest.raises(LabelMapError, match="2 overlapping layers and no segment names"):
        mask_on_grid(unnamed, shape, T, label=1)


def test_a_damaged_gzip_and_nan_voxels(tmp_path):
    """Session 16's sweep: 64 zeroed bytes inside a heart mask's .nii.gz were read by nibabel without a word
    (a third of the heart lost); a NaN background became label -2147483648."""
    import nibabel as nib

    T, shape = _source_T()
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ T  # the NIfTI affine of the LPS grid
    data = _ball_labels(T, shape).transpose(2, 1, 0).astype(np.float32)
    good = tmp_path / "ball.nii.gz"
    nib.save(nib.Nifti1Image(data, ras), str(good))
    _check(read_label_map(good))
    raw = bytearray(good.read_bytes())
    raw[len(raw) // 2:len(raw) // 2 + 64] = bytes(64)
    (tmp_path / "damaged.nii.gz").write_bytes(bytes(raw))
    with pytest.raises(LabelMapError, match=r"damaged.nii.gz is damaged \(.*\): copy it again"):
        read_label_map(tmp_path / "damaged.nii.gz")
    nan_background = np.where(data > 0, data, np.nan).astype(np.float32)
    nib.save(nib.Nifti1Image(nan_background, ras), str(tmp_path / "nan.nii.gz"))
    label_map = read_label_map(tmp_path / "nan.nii.gz")
    assert set(np.unique(label_map.labels)) == {0, 3}
    _check(label_map)
    # all NaN, and a map whose values all round to 0, were "empty (all zero)"
    nib.save(nib.Nifti1Image(np.full_like(data, np.nan), ras), str(tmp_path / "all_nan.nii.gz"))
    with pytest.raises(LabelMapError, match=r"all_nan.nii.gz holds no number \(NaN or infinite everywhere\)"):
        read_label_map(tmp_path / "all_nan.nii.gz")
    nib.save(nib.Nifti1Image(np.where(data > 0, 0.4, 0.0).astype(np.float32), ras), str(tmp_path / "p.nii.gz"))
    with pytest.raises(LabelMapError, match=r"p.nii.gz holds no whole-number label: its values \(0 to 0.4\) "
                                            r"round to 0 \(a probability map\? threshold it at 0.5 first\)"):
        read_label_map(tmp_path / "p.nii.gz")


def test_a_label_map_without_orientation_says_so(tmp_path):
    """qform_code and sform_code 0: when it lands off the CT, the error says why (it asked 'another study?')."""
    import nibabel as nib

    T, shape = _source_T()
    img = nib.Nifti1Image(_ball_labels(T, shape).transpose(2, 1, 0), np.diag([-1.0, -1.0, 1.0, 1.0]) @ T)
    img.set_qform(None, code=0)
    img.set_sform(None, code=0)
    nib.save(img, str(tmp_path / "unoriented.nii.gz"))
    label_map = read_label_map(tmp_path / "unoriented.nii.gz")
    far = np.eye(4)
    far[:3, 3] = 500.0
    with pytest.raises(LabelMapError, match=r"does not overlap the CT volume; its header has no orientation"):
        mask_on_grid(label_map, (10, 10, 10), far)


def test_a_label_map_in_metres_lands_in_mm(tmp_path):
    """xyzt_units metres: the label map's affine scaled to mm, as the CT's (it was taken as mm: 1000 x too small)."""
    import nibabel as nib

    T, shape = _source_T()
    img = nib.Nifti1Image(_ball_labels(T, shape).transpose(2, 1, 0), np.diag([-1e-3, -1e-3, 1e-3, 1.0]) @ T)
    img.header["xyzt_units"] = 1
    nib.save(img, str(tmp_path / "metres.nii.gz"))
    label_map = read_label_map(tmp_path / "metres.nii.gz")
    np.testing.assert_allclose(label_map.T_patient_from_voxel, T, atol=1e-9)
    _check(label_map)


def test_header_conflicts_and_other_nrrd_forms(tmp_path):
    """Found by session 17's sweep: a NIfTI whose sform and qform disagree was placed by its sform (nibabel),
    30 mm from where 3D Slicer (ITK: the qform) shows it, without a word; a detached ``.nhdr`` was 'not a DICOM
    file'; an int64 NRRD (a standard type) was blamed on its geometry."""
    import nibabel as nib

    T, shape = _source_T()
    labels = _ball_labels(T, shape)
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ T
    img = nib.Nifti1Image(labels.transpose(2, 1, 0), ras)
    img.set_qform(ras, code=1)
    moved = ras.copy()
    moved[2, 3] += 30.0
    img.set_sform(moved, code=2)
    nib.save(img, str(tmp_path / "two.nii.gz"))
    with pytest.raises(LabelMapError, match=r"two.nii.gz: its sform and qform place the volume up to 30.0 mm apart "
                                            r"\(sform_code 2, qform_code 1\).* write the file with one orientation"):
        read_label_map(tmp_path / "two.nii.gz")
    img.set_sform(ras, code=2)  # both set and agreeing: read
    nib.save(img, str(tmp_path / "agree.nii.gz"))
    _check(read_label_map(tmp_path / "agree.nii.gz"))
    dirs = " ".join("(" + ",".join(f"{v:.6f}" for v in T[:3, c]) + ")" for c in range(3))
    header = (f"NRRD0004\ntype: {{}}\ndimension: 3\nspace: left-posterior-superior\n"
              f"sizes: {shape[2]} {shape[1]} {shape[0]}\nspace directions: {dirs}\nencoding: raw\n"
              f"space origin: ({T[0, 3]:.6f},{T[1, 3]:.6f},{T[2, 3]:.6f})\n")
    (tmp_path / "ball64.nrrd").write_bytes(header.format("int64").encode() + b"\n" + labels.astype("<i8").tobytes())
    _check(read_label_map(tmp_path / "ball64.nrrd"))
    # a detached header (ITK's and Slicer's .nhdr) beside its data file, gzip-encoded (was refused)
    import gzip

    (tmp_path / "ball.nhdr").write_text(header.format("uint8").replace("encoding: raw", "encoding: gzip")
                                        + "data file: ball.raw.gz\n")
    (tmp_path / "ball.raw.gz").write_bytes(gzip.compress(labels.astype(np.uint8).tobytes()))
    _check(read_label_map(tmp_path / "ball.nhdr"))
    (tmp_path / "odd.nrrd").write_bytes(header.format("block").encode() + b"\n" + labels.tobytes())
    with pytest.raises(LabelMapError, match=r"odd.nrrd: voxel type 'block' is not read"):
        read_label_map(tmp_path / "odd.nrrd")


@pytest.mark.parametrize(("fill", "match"), [
    (-1.0, r"m.nii.gz holds the negative value -1 \(\d+ voxel\(s\)\); labels are whole numbers >= 0 \(0 the "
           r"background\): write the mask again"),
    (-1024.0, r"m.nii.gz holds the negative value -1024 .*: is it the CT, not a mask\?"),
    (3.7, r"m.nii.gz holds the value 3.7, not a whole-number label \(\d+ such voxel\(s\)\): labels are whole "
          r"numbers >= 0; resample the label map with nearest neighbour$"),
    (0.5, r"m.nii.gz holds no whole-number label: its values \(0 to 0.5\) round to 0"),
])
def test_negative_and_fractional_labels_are_refused_alike(tmp_path, fill, match):
    """A review: a mask of -1 or of 3.7 in the heart built a model without a word (3.7 read as label 4, -1 as a
    label of its own), while 0.5 was refused as 'no whole-number label'."""
    import nibabel as nib

    T, shape = _source_T()
    inside = _ball_labels(T, shape).transpose(2, 1, 0) > 0
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ T
    nib.save(nib.Nifti1Image(np.where(inside, fill, 0.0).astype(np.float32), ras), str(tmp_path / "m.nii.gz"))
    with pytest.raises(LabelMapError, match=match) as info:
        read_label_map(tmp_path / "m.nii.gz")
    assert "\n" not in str(info.value)
    if fill < 0:  # an integer map alike
        nib.save(nib.Nifti1Image(np.where(inside, fill, 0).astype(np.int16), ras), str(tmp_path / "m.nii.gz"))
        with pytest.raises(LabelMapError, match=match):
            read_label_map(tmp_path / "m.nii.gz")
    # a float map of whole labels (within float rounding) is read as before
    nib.save(nib.Nifti1Image(np.where(inside, 3.0000001, 0.0).astype(np.float32), ras), str(tmp_path / "ok.nii.gz"))
    assert set(np.unique(read_label_map(tmp_path / "ok.nii.gz").labels)) == {0, 3}


def test_a_soft_edged_mask_is_cut_at_half(tmp_path):
    """A mask resampled with linear interpolation (1 inside, fractions at its edge) or a probability map is cut
    at 0.5, as before the review's rule for fractional labels (which is for values above 1: 3.7)."""
    import nibabel as nib
    from scipy import ndimage

    T, shape = _source_T()
    inside = _ball_labels(T, shape).transpose(2, 1, 0) > 0
    soft = ndimage.gaussian_filter(inside.astype(np.float32), 1.0)
    nib.save(nib.Nifti1Image(soft, np.diag([-1.0, -1.0, 1.0, 1.0]) @ T), str(tmp_path / "soft.nii.gz"))
    labels = read_label_map(tmp_path / "soft.nii.gz").labels
    assert set(np.unique(labels)) == {0, 1}
    assert np.array_equal(labels, (soft > 0.5).transpose(2, 1, 0))


def test_a_mask_resampled_by_a_cubic_spline_is_rounded(tmp_path):
    """A review: a binary mask resampled with scipy's default cubic spline holds -0.1 to 1.35, and a soft mask's
    maximum may be 1.0000002 in float32; both were refused after the rule for fractional labels, and both are one
    structure's mask, rounded (the map of several labels, 3.7, stays refused)."""
    import nibabel as nib
    from scipy import ndimage

    T, shape = _source_T()
    inside = (_ball_labels(T, shape).transpose(2, 1, 0) > 0).astype(np.float32)
    cubic = ndimage.zoom(ndimage.zoom(inside, 0.5, order=3), np.array(inside.shape) / np.array(
        ndimage.zoom(inside, 0.5, order=0).shape), order=3)[: inside.shape[0], : inside.shape[1], : inside.shape[2]]
    assert cubic.min() < -0.01 and cubic.max() > 1.01
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ T
    nib.save(nib.Nifti1Image(cubic.astype(np.float32), ras), str(tmp_path / "cubic.nii.gz"))
    labels = read_label_map(tmp_path / "cubic.nii.gz").labels
    assert set(np.unique(labels)) == {0, 1}
    soft = ndimage.gaussian_filter(inside, 1.0) * np.float32(1.0000002)
    nib.save(nib.Nifti1Image(soft.astype(np.float32), ras), str(tmp_path / "soft.nii.gz"))
    assert set(np.unique(read_label_map(tmp_path / "soft.nii.gz").labels)) == {0, 1}
