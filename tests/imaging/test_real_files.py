"""Reading real files nobody here wrote: pydicom-data's CT files and pydicom's DICOMDIR folders.

Each file is read by ``imaging.load_study`` and compared with pydicom's own
decoding (with python-gdcm for JPEG Lossless) mapped to HU by the file's
rescale, exactly (stored integers, integer rescale: no tolerance is needed).
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.data import get_testdata_file
from pydicom.pixels import get_decoder
from pydicom.uid import DeflatedExplicitVRLittleEndian, JPEGLosslessSV1

from imaging import SeriesError, list_series, load_study

data_store = pytest.importorskip("data_store")
DATA = Path(data_store.__file__).parent / "data"
DICOMDIR_TESTS = Path(pydicom.__file__).parent / "data" / "test_files" / "dicomdirtests"
SAMPLE = Path(__file__).resolve().parents[2] / "sample_dicom" / "ct"


def _study(tmp_path, *names) -> Path:
    folder = tmp_path / "study"
    folder.mkdir(parents=True)
    for name in names:
        shutil.copy(DATA / name, folder / name)
    return folder


def _hu(ds) -> np.ndarray:
    return ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)


def _load(folder, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # single-slice studies warn that they are one slice
        return load_study(folder, **kw)


def test_jpeg_lossless_sv1_bad_sequence_read_with_gdcm(tmp_path):
    """pydicom's real ``bad_sequence.dcm`` (JPEG Lossless process 14 SV1, the
    commonest compressed CT in archives): decoded out of the box by python-gdcm (BSD)."""
    ds = pydicom.dcmread(DATA / "bad_sequence.dcm")
    assert ds.file_meta.TransferSyntaxUID == JPEGLosslessSV1
    assert "gdcm" in get_decoder(JPEGLosslessSV1).available_plugins
    volume = _load(_study(tmp_path, "bad_sequence.dcm"))
    assert volume.hu.shape == (1, 512, 512)
    np.testing.assert_array_equal(volume.hu[0], _hu(ds))


def test_693_set_same_image_in_three_syntaxes(tmp_path):
    """693_UNCR (uncompressed) and 693_J2KR (JPEG 2000 lossless) give the same HU;
    693_UNCI is the lossy version (differs).  All three in one folder share one
    position: the series is refused with the files named."""
    uncr = _load(_study(tmp_path / "a", "693_UNCR.dcm"))
    j2kr = _load(_study(tmp_path / "b", "693_J2KR.dcm"))
    unci = _load(_study(tmp_path / "c", "693_UNCI.dcm"))
    np.testing.assert_array_equal(uncr.hu, j2kr.hu)
    np.testing.assert_array_equal(uncr.hu[0], _hu(pydicom.dcmread(DATA / "693_UNCR.dcm")))
    assert np.abs(unci.hu.astype(float) - uncr.hu).max() > 0
    both = _study(tmp_path / "d", "693_UNCR.dcm", "693_J2KR.dcm", "693_UNCI.dcm")
    with pytest.raises(SeriesError, match=r"repeated slice positions.*693_"):
        _load(both)


def test_enhanced_ct_two_frames(tmp_path):
    """eCT_Supplemental.dcm: Enhanced CT, 2 frames 10 mm apart, per-frame positions."""
    ds = pydicom.dcmread(DATA / "eCT_Supplemental.dcm")
    volume = _load(_study(tmp_path, "eCT_Supplemental.dcm"))
    assert volume.hu.shape == (2, 512, 512)
    assert [s.position_mm for s in volume.slices] == pytest.approx([149.0, 159.0])
    t = ds.SharedFunctionalGroupsSequence[0].PixelValueTransformationSequence[0]
    expected = ds.pixel_array * float(t.RescaleSlope) + float(t.RescaleIntercept)
    iop = np.asarray(ds.SharedFunctionalGroupsSequence[0].PlaneOrientationSequence[0].ImageOrientationPatient, float)
    normal = np.cross(iop[:3], iop[3:])
    along = [float(np.dot(f.PlanePositionSequence[0].ImagePositionPatient, normal))
             for f in ds.PerFrameFunctionalGroupsSequence]  # slices are ordered along the normal
    np.testing.assert_array_equal(volume.hu, expected[np.argsort(along)])


def test_dicomdir_folders(tmp_path):
    """pydicom's DICOMDIR test folders (CT, MR, CR; DICOMDIR files of several
    encodings beside the images): every series listed, the DICOMDIR files not
    taken for images, and the automatic choice is the gated CT stack."""
    series = list_series(DICOMDIR_TESTS)
    assert len(series) == 25
    assert sum(s.kind == "volume" for s in series) == 2
    volume = _load(DICOMDIR_TESTS)
    assert volume.series.description == "SmartScore - Gated 0.5 sec"
    assert volume.hu.shape == (5, 16, 16)
    files = sorted({s.file for s in volume.slices}, key=str)
    ds = pydicom.dcmread(files[0])
    k = [Path(s.file) for s in volume.slices].index(Path(files[0]))
    np.testing.assert_array_equal(volume.hu[k], _hu(ds))
    # the DICOMDIR file itself, as a viewer's "open" dialog gives it: the files beside it (before session 15,
    # "no DICOM images found under .../DICOMDIR")
    assert list_series(DICOMDIR_TESTS / "DICOMDIR") == series


def test_deflated_explicit_vr_is_read(tmp_path):
    """Deflated Explicit VR Little Endian (the whole dataset zlib-compressed): read,
    with the same HU as the uncompressed original (it used to fail with an
    AttributeError text)."""
    sources = []
    for f in sorted(SAMPLE.iterdir()):
        ds = pydicom.dcmread(f, stop_before_pixels=True)
        if ds.Modality == "CT":
            sources.append((float(ds.ImagePositionPatient[2]), f))
    sources = [f for _, f in sorted(sources)]  # four neighbouring slices
    folder = tmp_path / "deflated"
    folder.mkdir()
    plain = tmp_path / "plain"
    plain.mkdir()
    for f in sources[:4]:
        shutil.copy(f, plain / f.name)
        ds = pydicom.dcmread(f)
        ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
        ds.save_as(folder / f.name, enforce_file_format=True)
        assert pydicom.dcmread(folder / f.name).file_meta.TransferSyntaxUID == DeflatedExplicitVRLittleEndian
    np.testing.assert_array_equal(_load(folder).hu, _load(plain).hu)


def test_jpeg_lossless_process_14_read_with_gdcm(tmp_path):
    """JPEG Lossless process 14 (not SV1): 693_UNCR re-encoded by python-gdcm reads
    back to the same HU as the uncompressed original."""
    gdcm = pytest.importorskip("gdcm")
    reader = gdcm.ImageReader()
    reader.SetFileName(str(DATA / "693_UNCR.dcm"))
    assert reader.Read()
    change = gdcm.ImageChangeTransferSyntax()
    change.SetTransferSyntax(gdcm.TransferSyntax(gdcm.TransferSyntax.JPEGLosslessProcess14))
    change.SetInput(reader.GetImage())
    assert change.Change()
    folder = tmp_path / "p14"
    folder.mkdir()
    writer = gdcm.ImageWriter()
    writer.SetFileName(str(folder / "693_P14.dcm"))
    writer.SetFile(reader.GetFile())
    writer.SetImage(change.GetOutput())
    assert writer.Write()
    assert pydicom.dcmread(folder / "693_P14.dcm").file_meta.TransferSyntaxUID == "1.2.840.10008.1.2.4.57"
    np.testing.assert_array_equal(_load(folder).hu, _load(_study(tmp_path / "u", "693_UNCR.dcm")).hu)


# ---- TotalSegmentator's example DICOM series (tests/data/fetch_real_cts.py)

def _ts_entry(name):
    from tests.data.fetch_real_cts import paths

    path = paths()[name]
    if not path.exists():
        pytest.skip(f"TotalSegmentator's {name} was not fetched (offline)")
    return path


#: TotalSegmentator's class numbers (its ``map_to_binary.py``, task "total")
_TS_LABELS = {"spleen": 1, "liver": 5, "colon": 20, "vertebrae_T12": 32, "humerus_left": 69, "humerus_right": 70}


def test_anonymised_jpeg2000_series_with_blanked_uids():
    """A real series as an anonymiser left it: 20 JPEG 2000 slices whose
    SOPInstanceUID and SeriesInstanceUID are empty (read as one slice before).

    Every slice is read and equals pydicom's own decoding.  Against the
    segmentation TotalSegmentator wrote on this series (through another reader,
    NIfTI RAS): each of its voxel centres, taken to LPS by its affine, is one of
    our voxel centres, and what it labels is what our HU show there (bone in its
    humeri and vertebra, gas in its colon, air outside the body), on the side
    the label names (left humerus and spleen at +x, right humerus and liver at -x)."""
    import nibabel as nib

    folder = _ts_entry("ts_dicom")
    volume = _load(folder)
    assert volume.hu.shape == (20, 512, 512)
    T = np.asarray(volume.T_patient_from_voxel, dtype=float)
    by_z = {round(float(pydicom.dcmread(f).ImagePositionPatient[2]), 3): f for f in folder.iterdir()}
    for k in (0, 7, 19):
        z = round(float((T @ [0, 0, k, 1])[2]), 3)
        np.testing.assert_array_equal(volume.hu[k], _hu(pydicom.dcmread(by_z[z])))

    seg = nib.load(_ts_entry("ts_dicom_seg.nii.gz"))
    labels = np.asarray(seg.dataobj)
    theirs = np.argwhere(np.ones(labels.shape, bool))[::7]
    lps = (np.diag([-1.0, -1.0, 1.0, 1.0]) @ seg.affine @ np.c_[theirs, np.ones(len(theirs))].T).T[:, :3]
    ijk = np.linalg.solve(T[:3, :3], (lps - T[:3, 3]).T).T
    np.testing.assert_allclose(ijk, np.round(ijk), atol=1e-3)  # the same voxel centres
    i, j, k = np.round(ijk).astype(int).T
    assert (i.min(), j.min(), k.min(), i.max(), j.max(), k.max()) == (0, 0, 0, 511, 511, 19)
    hu, label = volume.hu[k, j, i], labels[tuple(theirs.T)]

    def median_hu(name):
        return float(np.median(hu[label == _TS_LABELS[name]]))

    assert np.median(hu[label == 0]) < -900
    assert median_hu("colon") < -300
    assert min(median_hu("humerus_left"), median_hu("humerus_right"), median_hu("vertebrae_T12")) > 150
    for name, side in (("humerus_left", 1), ("spleen", 1), ("humerus_right", -1), ("liver", -1)):
        assert side * np.median(lps[label == _TS_LABELS[name], 0]) > 30, name


def _padded_series(folder, *, signed: bool, compress_second: bool = False):
    """Three copies of ``CT_small.dcm`` 2.5 mm apart with their corner 10 x 10 pixels set to the
    (0028,0120) Pixel Padding Value: -2000 in signed data, 63536 in unsigned data (the same bits)."""
    from pydicom.uid import JPEG2000Lossless, generate_uid

    folder.mkdir()
    series_uid, paths = generate_uid(), []
    for k in range(3):
        ds = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
        stored = ds.pixel_array.astype(np.int32)
        if not signed:  # the same HU as unsigned data: stored + 1024, rescaled by intercept -2048
            stored += 1024
            ds.PixelRepresentation, ds.RescaleIntercept = 0, -2048
        stored[:10, :10] = -2000 if signed else 63536
        ds.PixelData = stored.astype(np.int16 if signed else np.uint16).tobytes()
        del ds.PixelPaddingValue
        ds.add_new(0x00280120, "SS" if signed else "US", -2000 if signed else 63536)
        ds.SeriesInstanceUID, ds.SOPInstanceUID = series_uid, generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.ImagePositionPatient = [float(v) for v in ds.ImagePositionPatient[:2]] + [2.5 * k]
        if compress_second and k == 1:
            ds.compress(JPEG2000Lossless)
        ds.save_as(folder / f"IM{k}", enforce_file_format=True)
        paths.append(folder / f"IM{k}")
    return paths


@pytest.mark.parametrize("compress_second", [False, True])
def test_unsigned_pixel_padding_value_is_air_not_62512_hu(tmp_path, compress_second):
    """Unsigned CT whose corners hold Pixel Padding Value 63536 (GE writes it so): rescaled they were
    63536 - 2048 = 61488 HU, brighter than any bone, and the volume went float32.  Padding is air now
    (-1024 HU), read from the file or through a decoder; every other pixel is pydicom's HU exactly."""
    paths = _padded_series(tmp_path / "u", signed=False, compress_second=compress_second)
    volume = _load(tmp_path / "u")
    assert volume.hu.dtype == np.int16
    for k, path in enumerate(paths):
        ds = pydicom.dcmread(path)
        expected = _hu(ds)
        assert expected[0, 0] == 61488
        expected[:10, :10] = -1024
        np.testing.assert_array_equal(volume.hu[k], expected)
    assert ("pixels at (0028,0120) Pixel Padding Value 63536 (outside the reconstructed field of view) taken as "
            "at most -1024 (air)") in volume.notes


def test_signed_pixel_padding_below_air_kept_as_written(tmp_path):
    """Signed padding -2000 rescales to -3024 HU, already below air: kept as pydicom (and ITK, dcm2niix)
    give it, without a note."""
    paths = _padded_series(tmp_path / "s", signed=True)
    volume = _load(tmp_path / "s")
    for k, path in enumerate(paths):
        np.testing.assert_array_equal(volume.hu[k], _hu(pydicom.dcmread(path)))
    assert volume.hu[0, 0, 0] == -3024
    assert not any("Padding" in n for n in volume.notes)
