"""imaging.nifti: a NIfTI CT volume as a Volume in LPS, without a slice clock."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest

from imaging import SeriesError
from imaging.nifti import is_nifti_path, read_nifti_volume


def _save(path, data, affine):
    nib.save(nib.Nifti1Image(data, affine), str(path))
    return path


@pytest.mark.parametrize("ras_diag", [(-1.5, -1.5, 1.5), (1.0, 2.0, 3.0), (-0.8, 0.8, 2.5)])
def test_voxels_land_where_nibabel_puts_them(tmp_path, ras_diag):
    """Every voxel's LPS position is its RAS position (nibabel) with x and y negated."""
    rng = np.random.default_rng(0)
    data = rng.integers(-1000, 2000, size=(7, 6, 5)).astype(np.int16)  # [i, j, k]
    affine = np.diag([*ras_diag, 1.0])
    affine[:3, 3] = [10.0, -20.0, 30.0]
    volume = read_nifti_volume(_save(tmp_path / "ct.nii.gz", data, affine))
    T = volume.T_patient_from_voxel
    assert np.linalg.det(T[:3, :3]) > 0  # right-handed, as a DICOM stack
    assert volume.hu.dtype == np.int16 and volume.hu.shape == (5, 6, 7)
    for i, j, k in [(0, 0, 0), (6, 5, 4), (3, 1, 2)]:
        ras = affine[:3, :3] @ [i, j, k] + affine[:3, 3]
        lps = ras * [-1, -1, 1]
        kk, jj, ii = np.round(np.linalg.solve(T[:3, :3], lps - T[:3, 3])[::-1]).astype(int)
        assert volume.hu[kk, jj, ii] == data[i, j, k]
    assert "converted to LPS" in volume.notes[0]
    assert all(s.acquisition_time_s is None for s in volume.slices)
    # the same file, the same identity
    assert read_nifti_volume(tmp_path / "ct.nii.gz").series == volume.series


def test_bad_files(tmp_path):
    assert is_nifti_path("a/b.NII.GZ") and not is_nifti_path("a/b.nrrd")
    with pytest.raises(SeriesError, match="does not exist"):
        read_nifti_volume(tmp_path / "none.nii.gz")
    with pytest.raises(SeriesError, match="3-D volume"):
        read_nifti_volume(_save(tmp_path / "4d.nii.gz", np.zeros((3, 3, 3, 2), np.int16), np.eye(4)))
    sheared = np.eye(4)
    sheared[0, 1] = 0.5
    with pytest.raises(SeriesError, match="not orthogonal"):
        read_nifti_volume(_save(tmp_path / "shear.nii.gz", np.zeros((3, 3, 3), np.int16), sheared))
    (tmp_path / "junk.nii").write_bytes(b"not a nifti")
    with pytest.raises(SeriesError, match="cannot read NIfTI"):
        read_nifti_volume(tmp_path / "junk.nii")
