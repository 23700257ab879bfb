"""Helpers for the tests on real CTs: the shared data, a DICOM writer, metrics.

The real chest CT of ``shared/realct`` (README there) comes as NIfTI; the tests
write it as a plain DICOM series (one CT Image Storage file per slice, no ECG,
no gating) with pydicom, as a scanner without cardiac gating would.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid
from scipy import ndimage

#: ``shared/`` beside the checkout (CI clones the repository next to it); a
#: git worktree in ``wt/NAME`` finds it one level higher.
_ROOT = Path(__file__).resolve().parents[2]
SHARED = next((p for p in (_ROOT.parent / "shared", _ROOT.parent.parent / "shared") if p.is_dir()),
              _ROOT.parent / "shared")
REALCT = SHARED / "realct"


def write_ct_series(hu, T_patient_from_voxel, out_dir) -> Path:
    """Write ``hu[k, j, i]`` (LPS affine, orthogonal axes) as one DICOM file per slice.

    No ECG, no trigger times; every slice has the same AcquisitionTime, as an
    ungated helical scan reconstructed at once.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    T = np.asarray(T_patient_from_voxel, dtype=float)
    spacing = np.linalg.norm(T[:3, :3], axis=0)
    r, c = T[:3, 0] / spacing[0], T[:3, 1] / spacing[1]
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    hu = np.asarray(hu)
    for k in range(hu.shape[0]):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(out / f"ct{k:04d}.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.Modality, ds.SeriesNumber, ds.InstanceNumber = "CT", 1, k + 1
        ds.AcquisitionTime = ds.ContentTime = "120000"
        ds.ImagePositionPatient = [float(x) for x in T[:3, :3] @ [0.0, 0.0, k] + T[:3, 3]]
        ds.ImageOrientationPatient = [float(x) for x in (*r, *c)]
        ds.PixelSpacing = [float(spacing[1]), float(spacing[0])]
        ds.SliceThickness = float(spacing[2])
        ds.Rows, ds.Columns = hu.shape[1], hu.shape[2]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = 0, 1, "HU"
        ds.PixelData = np.ascontiguousarray(hu[k], dtype="<i2").tobytes()
        pydicom.dcmwrite(ds.filename, ds, enforce_file_format=True)
    return out


def mesh_to_mask(vertices_patient, faces, shape_kji, T_patient_from_voxel) -> np.ndarray:
    """Voxel centres inside a closed mesh (VTK stencil; the grid must be axis-aligned in LPS)."""
    import vtk
    from vtk.util.numpy_support import (
        numpy_to_vtk,
        numpy_to_vtkIdTypeArray,
        vtk_to_numpy,
    )

    T = np.asarray(T_patient_from_voxel, dtype=float)
    if not np.allclose(T[:3, :3], np.diag(np.diag(T[:3, :3]))) or np.any(np.diag(T[:3, :3]) <= 0):
        raise ValueError("mesh_to_mask needs a grid whose axes are +x, +y, +z of LPS")
    pts = vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(vertices_patient, dtype=float), deep=True))
    f = np.asarray(faces, dtype=np.int64)
    cells = vtk.vtkCellArray()
    offsets = numpy_to_vtkIdTypeArray(np.arange(0, 3 * len(f) + 1, 3, dtype=np.int64), deep=True)
    cells.SetData(offsets, numpy_to_vtkIdTypeArray(f.ravel(), deep=True))
    poly = vtk.vtkPolyData()
    poly.SetPoints(pts)
    poly.SetPolys(cells)
    image = vtk.vtkImageData()
    image.SetDimensions(shape_kji[2], shape_kji[1], shape_kji[0])
    image.SetSpacing(*np.diag(T[:3, :3]))
    image.SetOrigin(*T[:3, 3])
    image.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 1)
    image.GetPointData().GetScalars().Fill(1)
    stencil = vtk.vtkPolyDataToImageStencil()
    stencil.SetInputData(poly)
    stencil.SetOutputOrigin(image.GetOrigin())
    stencil.SetOutputSpacing(image.GetSpacing())
    stencil.SetOutputWholeExtent(image.GetExtent())
    stencil.Update()
    apply = vtk.vtkImageStencil()
    apply.SetInputData(image)
    apply.SetStencilConnection(stencil.GetOutputPort())
    apply.ReverseStencilOff()
    apply.SetBackgroundValue(0)
    apply.Update()
    return vtk_to_numpy(apply.GetOutput().GetPointData().GetScalars()).reshape(shape_kji).astype(bool)


def overlap(mask, reference, spacing_kji) -> dict:
    """Dice and symmetric surface distances (mm) between two masks on one grid.

    Surface voxels are the mask voxels with a 6-neighbour outside; each side's
    surface voxels are measured to the other's by Euclidean distance transform.
    """
    def surface(m):
        return m & ~ndimage.binary_erosion(m)

    # the distances between the two surfaces lie within their joint box (a voxel of margin): the same numbers
    box = ndimage.find_objects((mask | reference).astype(np.uint8))
    box = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in box[0]) if box else ()
    a, b = surface(mask[box]), surface(reference[box])
    d_ab = ndimage.distance_transform_edt(~b, sampling=spacing_kji)[a]
    d_ba = ndimage.distance_transform_edt(~a, sampling=spacing_kji)[b]
    d = np.concatenate([d_ab, d_ba])
    return {
        "dice": float(2 * (mask & reference).sum() / (mask.sum() + reference.sum())),
        "msd_mm": float(d.mean()),
        "p95_mm": float(np.percentile(d, 95)),
    }


def principal_axis(mask, T_patient_from_voxel) -> np.ndarray:
    """Unit principal axis (largest variance) of a mask's voxel centres, patient frame."""
    T = np.asarray(T_patient_from_voxel, dtype=float)
    p = np.argwhere(mask)[:, ::-1] @ T[:3, :3].T + T[:3, 3]
    return np.linalg.svd(p - p.mean(axis=0), full_matrices=False)[2][0]


#: A pacing lead's course in ``ct_cropped.nii.gz`` (voxel k, j, i), picked on its slices: down the superior vena
#: cava from the field of view's top, through the right atrium and the tricuspid valve to the right ventricle's apex.
LEAD_KJI = ((111, 55, 30), (95, 56, 30), (75, 52, 31), (62, 47, 31), (52, 40, 36), (44, 32, 45), (35, 23, 60),
            (27, 20, 72))


#: The left ventricle's and the left atrium's lumen in ``ct_cropped.nii.gz`` (voxel k, j, i), picked on their slices.
LEFT_HEART_KJI = ((30, 50, 85), (60, 80, 60))


def right_heart_blood(hu, artery) -> np.ndarray:
    """The contrast blood of the right heart in ``ct_cropped.nii.gz``: the blood pool (above 180 HU, lightly
    smoothed) split by a watershed of its depth between markers in the right heart (TotalSegmentator's
    pulmonary artery, the lead's course through the caval vein, atrium and ventricle: :data:`LEAD_KJI`) and in
    the left (:data:`LEFT_HEART_KJI`), with its one-voxel rim: the right atrium, ventricle, pulmonary artery
    and caval veins (356 ml), apart from the left atrium, ventricle and aorta."""
    from scipy import ndimage
    from skimage.segmentation import watershed

    pool = ndimage.gaussian_filter(np.asarray(hu, np.float32), 0.7) > 180.0
    markers = np.zeros(pool.shape, np.int32)
    markers[ndimage.binary_erosion(artery) & pool] = 1
    for kji in LEAD_KJI:
        near = tuple(slice(c - 1, c + 2) for c in kji)
        markers[near][pool[near]] = 1
    for kji in LEFT_HEART_KJI:
        markers[tuple(slice(c - 2, c + 3) for c in kji)] = 2
    side = watershed(-ndimage.distance_transform_edt(pool), markers, mask=pool)
    return ndimage.binary_dilation(side == 1) & (np.asarray(hu) > 100)
