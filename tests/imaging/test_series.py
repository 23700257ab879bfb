"""Tests for imaging.series / imaging.volume / imaging.discover (load_study, list_series).

Fixtures are tiny CT series written by ``dicom_factory`` whose pixels hold
round(x + 2y + 3z) of their own LPS position, so the affine is checked voxel by voxel.
Tolerances: 0 HU where no interpolation happens; 1 HU where the loader interpolates
linearly (the pattern is linear, so interpolation is exact up to the factory's
rounding to whole HU: at most 0.5 on each of two samples).
"""

from __future__ import annotations

import re

import shutil
import warnings

import numpy as np
import pydicom
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydicom.data import get_testdata_file
from pydicom.encaps import encapsulate
from pydicom.uid import JPEG2000Lossless, JPEGLSLossless, RLELossless
from scipy.spatial.transform import Rotation

from imaging.grouping import StudyError, StudyWarning
from imaging.pixels import DecoderUnavailableError
from imaging.series import list_series, load_study
from imaging.volume import SeriesError, SliceInfo, Volume

from . import dicom_factory as fac


def voxel_positions(vol: Volume) -> np.ndarray:
    """(k, j, i, 3) LPS positions of every voxel of vol.hu through its affine."""
    nk, nj, ni = vol.hu.shape
    k, j, i = np.mgrid[0:nk, 0:nj, 0:ni]
    ijk = np.stack([i, j, k], axis=-1).reshape(-1, 3)
    return vol.voxel_to_patient(ijk).reshape(nk, nj, ni, 3)


def pattern_error(vol: Volume, mask=None) -> float:
    err = np.abs(vol.hu.astype(np.float64) - fac.pattern_hu(voxel_positions(vol)))
    return float(err[mask].max() if mask is not None else err.max())


def quiet_load(path, **kw) -> Volume:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StudyWarning)
        return load_study(path, **kw)


@pytest.fixture
def axial(tmp_path):
    fac.write_ct_series(tmp_path / "axial")
    return tmp_path / "axial"


# ------------------------------------------------------------ basic geometry


def test_axial_series_matches_pattern_voxel_by_voxel(axial):
    vol = load_study(axial)
    assert vol.hu.shape == (20, 32, 32)
    assert vol.hu.dtype == np.int16
    assert not vol.resampled
    np.testing.assert_allclose(vol.spacing_mm, [1.0, 1.0, 2.0])
    np.testing.assert_allclose(vol.T_patient_from_voxel[:3, 3], [-16, -16, -20])
    assert pattern_error(vol) == 0
    assert [s.k for s in vol.slices] == list(range(20))
    assert np.all(np.diff([s.position_mm for s in vol.slices]) > 0)
    assert any("chose series" in n and "axial CT, 20 image(s)" in n for n in vol.notes)


def test_volume_is_frozen_and_read_only(axial):
    vol = load_study(axial)
    with pytest.raises(AttributeError):
        vol.notes = ()
    with pytest.raises(ValueError):
        vol.hu[0, 0, 0] = 1
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        vol.voxel_to_patient(np.zeros((2, 4)))
    p = vol.voxel_to_patient([[3, 4, 5]])
    np.testing.assert_allclose(vol.patient_to_voxel(p), [[3, 4, 5]])


def test_no_patient_identity_in_the_result(axial):
    vol = load_study(axial)
    text = repr(vol) + repr(vol.series) + repr(vol.slices) + " ".join(vol.notes)
    assert fac.PATIENT_NAME.split("^")[0] not in text
    assert fac.PATIENT_ID not in text
    assert "19700101" not in text


def test_slice_times_and_ge_private_tags(axial):
    vol = load_study(axial)
    s3 = vol.slices[3]
    assert s3.mid_scan_time_s == pytest.approx(0.5 + 3 * fac.SLICE_DT_S)
    # sub-second AcquisitionTime on the seconds-after-midnight clock
    assert s3.acquisition_time_s == pytest.approx(fac.SCAN_ORIGIN_S + 0.5 + 3 * fac.SLICE_DT_S)
    rp = vol.series.rpeak_timestamps_ms
    assert rp is not None and rp[:3] == (-1000.0, -150.0, 700.0)


def test_ge_private_tags_as_un_bytes(tmp_path):
    fac.write_ct_series(tmp_path, n_slices=4, ge_private="UN")
    vol = load_study(tmp_path)
    assert vol.slices[2].mid_scan_time_s == pytest.approx(0.5 + 2 * fac.SLICE_DT_S)
    assert vol.series.rpeak_timestamps_ms[:2] == (-1000.0, -150.0)


def test_ge_private_tags_implicit_vr(tmp_path):
    files = fac.write_ct_series(tmp_path, n_slices=3)
    for f in files:
        ds = pydicom.dcmread(f)
        ds.file_meta.TransferSyntaxUID = pydicom.uid.ImplicitVRLittleEndian
        ds.save_as(f, enforce_file_format=True)
    vol = load_study(tmp_path)
    assert vol.slices[1].mid_scan_time_s == pytest.approx(0.5 + fac.SLICE_DT_S)
    assert vol.series.rpeak_timestamps_ms[:2] == (-1000.0, -150.0)


def test_raw_dataset_without_preamble_or_file_meta(tmp_path):
    """Old exports: implicit VR, no 128-byte preamble, no file meta."""
    files = fac.write_ct_series(tmp_path, n_slices=3)
    for f in files:
        ds = pydicom.dcmread(f)
        ds.preamble = None
        del ds.file_meta
        pydicom.dcmwrite(f, ds, enforce_file_format=False, implicit_vr=True, little_endian=True)
    vol = load_study(tmp_path)
    assert pattern_error(vol) == 0
    assert vol.slices[1].mid_scan_time_s == pytest.approx(0.5 + fac.SLICE_DT_S)
    assert vol.series.rpeak_timestamps_ms[:2] == (-1000.0, -150.0)


def test_non_image_series_is_listed_not_chosen(tmp_path, axial):
    ds = pydicom.dcmread(axial / "slice_000.dcm", stop_before_pixels=True)
    for kw in ("Rows", "Columns", "ImagePositionPatient", "ImageOrientationPatient"):
        delattr(ds, kw)
    ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.9.1.2"  # General ECG Waveform Storage
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID
    ds.SeriesInstanceUID = pydicom.uid.generate_uid()
    ds.Modality = "ECG"
    ds.save_as(axial / "ecg.dcm", enforce_file_format=True)
    summary = list_series(axial)
    ecg = [s for s in summary if s.modality == "ECG"]
    assert len(ecg) == 1 and ecg[0].kind == "non-image" and ecg[0].files[0].endswith("ecg.dcm")
    assert load_study(axial).hu.shape == (20, 32, 32)
    with pytest.raises(SeriesError, match="cannot be loaded as a volume: no image"):
        load_study(axial, series=ecg[0].index)


def test_images_of_the_series_left_out_of_its_stack_are_warned(tmp_path, axial):
    """Eight images of the same series in another orientation (a reformat exported into the series) form a
    part of their own; the stack used leaves them out, now with a warning (only --list-series showed them:
    review of session 22)."""
    for k in range(12, 20):
        ds = pydicom.dcmread(axial / f"slice_{k:03d}.dcm")
        ds.ImageOrientationPatient = [1, 0, 0, 0, 0, -1]  # coronal
        ds.save_as(axial / f"slice_{k:03d}.dcm")
    with pytest.warns(StudyWarning, match=r"is used without 8 of its own image\(s\) that do not stack with it: "
                                          r"\[\d\] coronal 8 file\(s\); choose another part with --series"):
        volume = load_study(axial)
    assert volume.hu.shape[0] == 12


def test_a_folder_that_cannot_be_opened_is_warned_not_named_in_notes(tmp_path, axial, monkeypatch):
    """A sub-folder of the study without read permission was passed over without a word by os.walk: the
    volume came out short of its slices (review of session 22).  Warned, naming it; the notes that outputs
    keep name no folder (a folder name may name the patient)."""
    import os

    hidden = axial / "SMITH_JOHN"
    hidden.mkdir()
    for k in range(15, 20):
        shutil.move(str(axial / f"slice_{k:03d}.dcm"), hidden)
    real = os.scandir

    def scandir(path="."):
        if os.fspath(path).endswith("SMITH_JOHN"):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real(path)

    monkeypatch.setattr(os, "scandir", scandir)
    with pytest.warns(StudyWarning, match=r"SMITH_JOHN: folder that cannot be opened \(Permission denied\)"):
        volume = load_study(axial)
    assert volume.hu.shape[0] == 15
    assert any("skipped a folder that cannot be opened (Permission denied)" in n for n in volume.notes)
    assert not any("SMITH" in n for n in volume.notes)


def test_pydicom_warnings_name_their_file(axial):
    """pydicom's warnings about a file's values named no file ('warning: Invalid value for VR IS: '1A'' and
    nothing else: review of session 22); they are said once per message with the file(s) they came from."""
    shutil.copy(get_testdata_file("badVR.dcm"), axial / "odd.dcm")
    with pytest.warns(UserWarning, match=r"odd.dcm: Invalid value for VR IS: '1A'"):
        assert load_study(axial).hu.shape == (20, 32, 32)


def test_a_series_exported_twice_over_is_read_once(axial):
    """Every image twice, the copies with new SOPInstanceUIDs (an export run twice into one folder): each
    position's repeats are the same image again (InstanceNumber, times), so one of each is kept, warned.
    Before, the series was 'unusable' and no --series could load it (review of session 22)."""
    for f in sorted(axial.glob("slice_*.dcm")):
        ds = pydicom.dcmread(f)
        ds.SOPInstanceUID = pydicom.uid.generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.save_as(axial / f"copy_{f.name}")
    with pytest.warns(StudyWarning, match=r"20 image\(s\) repeat the position of another and were ignored"):
        volume = load_study(axial)
    assert volume.hu.shape == (20, 32, 32)


# ------------------------------------------------------------- ordering


def test_shuffled_names_and_reversed_instance_numbers_give_same_volume(tmp_path, axial):
    ref = load_study(axial)
    uid = pydicom.dcmread(axial / "slice_000.dcm").SeriesInstanceUID
    for seed in range(3):
        folder = tmp_path / f"shuffled{seed}"
        fac.write_ct_series(folder, names="shuffled", seed=seed, reverse_instance=seed % 2 == 0,
                            series_uid=uid)
        vol = load_study(folder)
        np.testing.assert_array_equal(vol.hu, ref.hu)
        np.testing.assert_array_equal(vol.T_patient_from_voxel, ref.T_patient_from_voxel)
        assert [s.position_mm for s in vol.slices] == [s.position_mm for s in ref.slices]
    rev = load_study(tmp_path / "shuffled0")
    assert rev.slices[0].instance_number == 20  # InstanceNumber is informative only


# ------------------------------------------------------------- selection


@pytest.fixture
def mixed(tmp_path):
    study = pydicom.uid.generate_uid()
    fac.write_ct_series(tmp_path / "ct", n_slices=20, series_number=2, study_uid=study)
    fac.write_ct_series(tmp_path / "loc", n_slices=2, rows=40, cols=24, iop=fac.CORONAL,
                        series_number=1, image_type=("ORIGINAL", "PRIMARY", "LOCALIZER"),
                        description="Scout")
    fac.write_ct_series(tmp_path / "cor", n_slices=25, iop=fac.CORONAL, series_number=3,
                        description="Coronal MPR", origin=(-16, -30, 16))
    (tmp_path / "notes.txt").write_text("not dicom")
    (tmp_path / "DICOMDIR").write_bytes(b"\0" * 200)
    return tmp_path


def test_list_series_shows_every_group(mixed):
    summary = list_series(mixed)
    assert [s.index for s in summary] == [0, 1, 2]
    by_desc = {s.description: s for s in summary}
    assert by_desc["Scout"].kind == "localizer"
    assert by_desc["Cardiac 0.625 mm"].orientation == "axial"
    assert by_desc["Coronal MPR"].orientation == "coronal"
    assert by_desc["Coronal MPR"].n_slices == 25


def test_automatic_choice_is_axial_ct_not_localizer(mixed):
    vol = load_study(mixed)
    assert vol.series.description == "Cardiac 0.625 mm"
    assert vol.hu.shape == (20, 32, 32)
    assert any("localizer(s) ignored" in n for n in vol.notes)
    assert any("1 non-DICOM file(s) ignored" in n for n in vol.notes)
    assert any("DICOMDIR ignored" in n for n in vol.notes)
    # how it was chosen, for model.json (modeling.build writes it with the UIDs' pseudonyms): the chosen series
    # by its place in the listing, the other CT candidate and the localizer passed over
    cor = next(s for s in list_series(mixed) if s.description == "Coronal MPR")
    assert vol.selection.startswith(f"chose series [{vol_index(mixed, vol)}] {vol.series.series_instance_uid}: "
                                    "axial CT, 20 image(s)"), vol.selection
    assert f"1 other CT candidate(s) [{cor.index}] coronal 25" in vol.selection
    assert "localizer(s) ignored" in vol.selection and vol.selection in vol.notes
    assert load_study(mixed, series=cor.index).selection == f"series [{cor.index}] {cor.uid} chosen by the caller"


def vol_index(study, volume) -> int:
    return next(s.index for s in list_series(study) if s.uid == volume.series.series_instance_uid)


def test_series_selectable_by_index_and_uid(mixed):
    summary = {s.description: s for s in list_series(mixed)}
    cor = summary["Coronal MPR"]
    by_index = load_study(mixed, series=cor.index)
    by_uid = load_study(mixed, series=cor.uid)
    assert by_index.hu.shape == by_uid.hu.shape == (25, 32, 32)
    assert pattern_error(by_uid) == 0  # coronal: k along -y, affine still right
    assert np.linalg.det(by_uid.T_patient_from_voxel[:3, :3]) > 0
    loc = load_study(mixed, series=summary["Scout"])
    assert loc.hu.shape == (2, 40, 24)


def test_unknown_series_lists_choices(mixed):
    with pytest.raises(SeriesError, match=r"(?s)no series has the UID given.*\[0\].*\[2\]") as err:
        load_study(mixed, series="1.2.3.4")
    assert "Scout" not in str(err.value)  # the descriptions (free text) are for --list-series only
    with pytest.raises(SeriesError, match="not found"):
        load_study(mixed, series=17)
    with pytest.raises(TypeError, match="series must be"):
        load_study(mixed, series=2.5)


def test_two_cardiac_phases_in_one_series_are_split(tmp_path):
    uid = pydicom.uid.generate_uid()
    for pct in (40.0, 70.0):
        def tag(ds, k, pct=pct):
            ds.NominalPercentageOfCardiacPhase = pct
        fac.write_ct_series(tmp_path / f"p{pct:g}", n_slices=8, series_uid=uid, extra=tag)
    summary = list_series(tmp_path)
    assert [s.subset for s in summary] == [
        "NominalPercentageOfCardiacPhase=40", "NominalPercentageOfCardiacPhase=70"]
    assert all(s.kind == "volume" and s.n_slices == 8 for s in summary)
    with pytest.raises(SeriesError, match=r"split into 2 groups; pass series=<index>"):
        load_study(tmp_path, series=uid)
    vol = load_study(tmp_path, series=1)
    assert vol.series.subset == "NominalPercentageOfCardiacPhase=70"
    assert {s.nominal_cardiac_percent for s in vol.slices} == {70.0}


def test_list_series_shows_the_phase_of_each_part(tmp_path, capsys):
    """A multi-phase series (0 %, 40 %, 70 % in one SeriesInstanceUID): --list-series showed three alike lines
    and the automatic choice (the lowest) named the others by size only (a new user's audit); each part now
    shows its NominalPercentageOfCardiacPhase, or its TriggerTime when it has no percentage."""
    from heartreg.cli import main

    uid = pydicom.uid.generate_uid()
    for pct in (0.0, 40.0, 70.0):
        def tag(ds, k, pct=pct):
            ds.NominalPercentageOfCardiacPhase = pct
            ds.TriggerTime = 8.5 * pct
        fac.write_ct_series(tmp_path / "study" / f"p{pct:g}", n_slices=8, series_uid=uid, extra=tag)
    assert [s.cardiac for s in list_series(tmp_path / "study")] == ["phase 0 %", "phase 40 %", "phase 70 %"]
    assert main(["phases", str(tmp_path / "study"), "--list-series"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [re.search(r"volume  (phase \d+ %) - series repeats", line).group(1) for line in lines] == [
        "phase 0 %", "phase 40 %", "phase 70 %"]
    with pytest.warns(StudyWarning, match=r"\[1\] axial 8 file\(s\) phase 40 %, \[2\] axial 8 file\(s\) phase 70 %"):
        volume = load_study(tmp_path / "study")
    assert any(re.search(r"other CT candidate\(s\) \[1\] axial 8 phase 40 %, \[2\] axial 8 phase 70 %", n)
               for n in volume.notes), volume.notes
    # TriggerTime alone: one value, or the range of a retrospective series
    fac.write_ct_series(tmp_path / "tt", n_slices=4, extra=lambda ds, k: setattr(ds, "TriggerTime", 560))
    fac.write_ct_series(tmp_path / "tr", n_slices=4, extra=lambda ds, k: setattr(ds, "TriggerTime", 100 * k))
    assert list_series(tmp_path / "tt")[0].cardiac == "TriggerTime 560 ms"
    assert list_series(tmp_path / "tr")[0].cardiac == "TriggerTime 0-300 ms"
    assert list_series(tmp_path / "study" / "p0")[0].cardiac == "phase 0 %"
    fac.write_ct_series(tmp_path / "none", n_slices=4)
    assert list_series(tmp_path / "none")[0].cardiac == ""


def test_duplicate_copies_are_kept_once(tmp_path, axial):
    shutil.copytree(axial, tmp_path / "copy")
    vol = load_study(tmp_path)
    assert vol.hu.shape == (20, 32, 32)
    assert any("duplicate image(s)" in n for n in vol.notes)


@pytest.mark.parametrize("blank_meta", [False, True])
def test_blanked_uids_keep_every_slice(tmp_path, axial, blank_meta):
    """An anonymiser that empties SOPInstanceUID and SeriesInstanceUID (as in
    TotalSegmentator's example DICOM series) must not merge the slices into one:
    the file meta's MediaStorageSOPInstanceUID stands in, and images with no UID
    at all are never taken for copies of each other."""
    reference = load_study(axial)
    for path in sorted(axial.iterdir()):
        ds = pydicom.dcmread(path)
        ds.SOPInstanceUID = ""
        ds.SeriesInstanceUID = ""
        if blank_meta:
            ds.file_meta.MediaStorageSOPInstanceUID = ""
        ds.save_as(path)
    vol = load_study(axial)
    assert vol.hu.shape == (20, 32, 32)
    np.testing.assert_array_equal(vol.hu, reference.hu)
    assert not any("duplicate" in n for n in vol.notes)


# ------------------------------------------------------------- irregular stacks


def test_missing_slice_is_resampled(tmp_path):
    fac.write_ct_series(tmp_path, skip=(7,))
    with pytest.warns(StudyWarning, match="missing slice"):
        vol = load_study(tmp_path)
    assert vol.resampled and vol.hu.dtype == np.float32
    assert vol.hu.shape == (20, 32, 32)
    assert len(vol.slices) == 19 and vol.slices[7].k == pytest.approx(8.0)
    assert pattern_error(vol) == 0  # 2 mm steps: the pattern is exact at slice 7
    assert any("1 missing slice(s)" in n and "2.000 mm" in n for n in vol.notes)


def test_resampling_notes_name_files_without_their_folder(tmp_path):
    """The notes of a missing slice, of uneven spacing and of a sheared stack are
    printed as warnings: they name the files, not the study's folders (a folder can
    be named after the patient; the grouping's notes did so already).  Until this
    audit they gave the full path, e.g. 'largest between /data/DOE_JANE/ct/slice_006.dcm
    and ...'."""
    folder = tmp_path / "DOE_JANE_PID123"
    fac.write_ct_series(folder / "missing", skip=(7,))
    z = 2.0 * np.arange(20)
    z[5:] += 0.6
    fac.write_ct_series(folder / "uneven", positions=[(-16.0, -16.0, -20.0 + v) for v in z])
    fac.write_ct_series(folder / "tilted", shear_mm=(0.0, 0.7, 0.0))
    for sub, what, named in [("missing", "missing slice", "slice_006.dcm and slice_008.dcm"),
                             ("uneven", "uneven slice spacing", "slice_004.dcm and slice_005.dcm"),
                             ("tilted", "sheared stack", "(file slice_019.dcm)")]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            vol = load_study(folder / sub)
        note = next(n for n in vol.notes if what in n)
        assert named in note, note
        printed = " ".join(str(w.message) for w in caught)
        assert what in printed and "DOE_JANE" not in printed and str(tmp_path) not in printed


def test_missing_slice_refused_when_resampling_off(tmp_path):
    fac.write_ct_series(tmp_path, skip=(7,))
    with pytest.raises(SeriesError, match="not a regular orthogonal stack.*missing slice"):
        load_study(tmp_path, resample=False)


def test_uneven_spacing_is_resampled_at_median(tmp_path):
    z = 2.0 * np.arange(20)
    z[5] += 0.6
    z[12:] += 0.8
    pos = [(-16.0, -16.0, -20.0 + dz) for dz in z]
    fac.write_ct_series(tmp_path, positions=pos)
    vol = quiet_load(tmp_path)
    assert vol.resampled
    assert vol.spacing_mm[2] == pytest.approx(2.0)
    assert vol.hu.shape[0] == int(np.floor((z[-1] - z[0]) / 2.0)) + 1
    assert pattern_error(vol) <= 1.0
    assert any("uneven slice spacing" in n for n in vol.notes)


def test_slice_thickness_differing_from_spacing_is_noted(tmp_path):
    fac.write_ct_series(tmp_path, n_slices=5, slice_thickness=1.25)
    vol = load_study(tmp_path)
    assert any("SliceThickness 1.25 mm differs from the slice spacing 2.000 mm (gaps between"
               in n for n in vol.notes)


def _spacing_on_odd_slices(value):
    def extra(ds, k):
        if k % 2:
            ds.PixelSpacing = value
    return extra


def test_pixel_spacing_differing_by_rounding_is_one_spacing(tmp_path):
    """PixelSpacing 1.5 beside 1.500001 (exporters round DS values differently) was refused as 'PixelSpacing
    differs between images' (a new user's audit): equal within 1e-4 of the value, the median used."""
    fac.write_ct_series(tmp_path, pixel_spacing=(1.5, 1.5), extra=_spacing_on_odd_slices(["1.500001", "1.5"]))
    vol = load_study(tmp_path)
    assert vol.hu.shape == (20, 32, 32) and not vol.resampled
    assert vol.spacing_mm[0] == 1.5 and vol.spacing_mm[1] == pytest.approx(1.5000005)
    assert pattern_error(vol) <= 1.0  # round(x + 2y + 3z) at 1 um per 32 pixels: a rounding step at most


def test_pixel_spacing_that_really_differs_is_refused(tmp_path):
    fac.write_ct_series(tmp_path, pixel_spacing=(1.5, 1.5), extra=_spacing_on_odd_slices(["1.5", "1.51"]))
    with pytest.raises(SeriesError, match=r"PixelSpacing differs between images .* by more than 0\.0001 of its "
                                          r"value; pass series=\.\.\. \(--series\)"):
        load_study(tmp_path)


def test_wild_gap_is_refused_naming_files(tmp_path):
    fac.write_ct_series(tmp_path, skip=(8, 9, 10, 11))
    with pytest.raises(SeriesError, match=r"gap of 10\.000 mm.*slice_007\.dcm.*slice_012\.dcm"):
        load_study(tmp_path)


def test_gantry_tilt_resampled_to_orthogonal_grid(tmp_path):
    # 0.7 mm posterior shift per 2 mm slice: a ~19 degree tilt, sub-pixel shifts
    fac.write_ct_series(tmp_path, shear_mm=(0.0, 0.7, 0.0), extra=lambda ds, k: setattr(
        ds, "GantryDetectorTilt", 19.3))
    with pytest.warns(StudyWarning, match="sheared stack"):
        vol = load_study(tmp_path)
    T = vol.T_patient_from_voxel[:3, :3]
    np.testing.assert_allclose(T.T @ T, np.diag(vol.spacing_mm ** 2), atol=1e-12)  # orthogonal
    # voxels inside every acquired slice match the pattern; outside ones are air
    y = voxel_positions(vol)[..., 1]
    k = np.arange(20)[:, None, None]
    inside = (y >= -16 + 0.7 * k) & (y <= -16 + 31 + 0.7 * k)
    assert inside.sum() >= 0.95 * 20 * 32 * 32  # the grid holds every acquired slice
    assert pattern_error(vol, inside) <= 1.0
    # more than one pixel anterior of the acquired slice (within one pixel the
    # slice's edge values are kept, so that its edge pixels are interpolated exactly)
    before = y < -16 + 0.7 * k - 1.0 - 1e-6
    assert before.sum() > 1000 and np.all(vol.hu[before] == -1024)
    assert any("GantryDetectorTilt 19.3 deg" in n for n in vol.notes)


def test_gantry_tilt_refused_when_resampling_off(tmp_path):
    fac.write_ct_series(tmp_path, shear_mm=(0.0, 0.7, 0.0))
    with pytest.raises(SeriesError, match="sheared stack.*slice_019.dcm"):
        load_study(tmp_path, resample=False)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1))
def test_oblique_orientation_exact_through_affine(tmp_path_factory, seed):
    R = Rotation.random(random_state=seed).as_matrix()
    iop = tuple(R[:, 0]) + tuple(R[:, 1])
    folder = tmp_path_factory.mktemp("oblique")
    fac.write_ct_series(folder, n_slices=6, rows=12, cols=10, iop=iop,
                        pixel_spacing=(0.8, 0.6), spacing_mm=1.5, origin=(3.0, -7.0, 11.0))
    vol = load_study(folder)
    assert not vol.resampled  # oblique but orthogonal: no interpolation
    np.testing.assert_allclose(vol.spacing_mm, [0.6, 0.8, 1.5], rtol=1e-5)
    # pattern rounded from IPP/IOP written with 6 decimals: exact but for ties
    err = np.abs(vol.hu - fac.pattern_hu(voxel_positions(vol)))
    assert err.max() <= 1 and np.mean(err == 0) > 0.99


# ------------------------------------------------------------- pixel encodings


def test_enhanced_multiframe_equals_single_frame(tmp_path, axial):
    ref = load_study(axial)
    order = list(np.random.default_rng(3).permutation(20))
    fac.write_enhanced_ct(tmp_path / "enh" / "multi.dcm", frame_order=order)
    vol = load_study(tmp_path / "enh")
    np.testing.assert_array_equal(vol.hu, ref.hu)
    np.testing.assert_allclose(vol.T_patient_from_voxel, ref.T_patient_from_voxel)
    assert [s.frame for s in vol.slices] == [order.index(k) for k in range(20)]
    assert vol.slices[4].acquisition_time_s == pytest.approx(
        fac.SCAN_ORIGIN_S + 0.5 + 4 * fac.SLICE_DT_S)
    assert vol.slices[4].nominal_cardiac_percent == 70.0
    assert vol.slices[4].trigger_time_ms == 600.0
    assert vol.slices[4].nominal_interval_ms == 850.0


@pytest.mark.parametrize("syntax", [RLELossless, JPEG2000Lossless, JPEGLSLossless], ids=["rle", "j2k", "jpegls"])
def test_compressed_copies_give_identical_hu(tmp_path, axial, syntax):
    ref = load_study(axial)
    fac.write_ct_series(tmp_path / "c", transfer_syntax=syntax)
    assert pydicom.dcmread(tmp_path / "c" / "slice_000.dcm").file_meta.TransferSyntaxUID == syntax
    vol = load_study(tmp_path / "c")
    np.testing.assert_array_equal(vol.hu, ref.hu)


def test_syntax_without_decoder_names_the_package(tmp_path, monkeypatch):
    """JPEG Lossless (process 14) needs python-gdcm, which heartreg does not install
    (the licence-safe decoders are openjpeg, RLE and CharLS): on a machine without
    it (simulated: pydicom's JPEG Lossless decoder offers no plugin) the message
    names the package."""
    from pydicom.pixels.decoders.base import Decoder
    from pydicom.uid import JPEGLosslessSV1

    plugins = Decoder.available_plugins
    monkeypatch.setattr(Decoder, "available_plugins",
                        property(lambda self: () if self.UID == JPEGLosslessSV1 else plugins.fget(self)))
    files = fac.write_ct_series(tmp_path, n_slices=2)
    for f in files:
        ds = pydicom.dcmread(f)
        ds.PixelData = encapsulate([b"\xff\xd8\xff\xc3" + b"\0" * 64])
        ds["PixelData"].VR = "OB"
        ds.file_meta.TransferSyntaxUID = JPEGLosslessSV1
        ds.save_as(f, enforce_file_format=True)
    with pytest.raises(DecoderUnavailableError, match=r"slice_000.dcm.*install python-gdcm"):
        load_study(tmp_path)


def test_twelve_bit_jpeg_extended_names_its_syntax_not_a_corrupt_file(tmp_path):
    """A valid JPEG Extended file of 12-bit samples (older CT exports; written here by
    python-gdcm): pydicom's gdcm and pillow plugins decode 8-bit JPEG Extended only and
    heartreg does not use the GPL libjpeg, so nothing installed reads it.  The line names
    the syntax and the converters; it used to say "cannot decode pixel data (RuntimeError:
    ...); the file may be truncated or corrupt: remove it or re-export the series"."""
    gdcm = pytest.importorskip("gdcm")

    def twelve_bits(ds, k):
        ds.BitsStored, ds.HighBit = 12, 11

    files = fac.write_ct_series(tmp_path, n_slices=2, extra=twelve_bits)
    for f in files:
        reader = gdcm.ImageReader()
        reader.SetFileName(str(f))
        assert reader.Read()
        change = gdcm.ImageChangeTransferSyntax()
        change.SetTransferSyntax(gdcm.TransferSyntax(gdcm.TransferSyntax.JPEGExtendedProcess2_4))
        change.SetInput(reader.GetImage())
        assert change.Change()
        writer = gdcm.ImageWriter()
        writer.SetFileName(str(f))
        writer.SetFile(reader.GetFile())
        writer.SetImage(change.GetOutput())
        assert writer.Write()
    ds = pydicom.dcmread(files[0])
    assert (ds.file_meta.TransferSyntaxUID, ds.BitsStored) == ("1.2.840.10008.1.2.4.51", 12)
    with pytest.raises(DecoderUnavailableError) as err:
        load_study(tmp_path)
    text = str(err.value)
    assert "slice_000.dcm: transfer syntax 1.2.840.10008.1.2.4.51 (JPEG Extended" in text
    assert "12-bit samples" in text and "dcmdjpeg" in text and "gdcmconv --raw" in text
    assert "corrupt" not in text and "\n" not in text


# ------------------------------------------------------------- bad input


def test_truncated_file_skipped_with_warning(tmp_path):
    files = fac.write_ct_series(tmp_path)
    fac.truncate(files[19], 500)
    with pytest.warns(StudyWarning, match=r"slice_019\.dcm: Pixel Data holds"):
        vol = load_study(tmp_path)
    assert vol.hu.shape == (19, 32, 32)
    assert any("skipped unreadable DICOM file" in n and "slice_019" in n for n in vol.notes)


def test_truncated_compressed_file_skipped(tmp_path):
    files = fac.write_ct_series(tmp_path, n_slices=5, transfer_syntax=RLELossless)
    fac.truncate(files[0], 100)
    with pytest.warns(StudyWarning, match=r"slice_000\.dcm: .*truncated"):
        vol = load_study(tmp_path)
    assert len(vol.slices) == 4


def test_missing_rescale_tags_assumed_identity(tmp_path):
    fac.write_ct_series(tmp_path, n_slices=5, rescale=None)
    with pytest.warns(StudyWarning, match="lack RescaleSlope/RescaleIntercept"):
        vol = load_study(tmp_path)
    assert vol.hu.dtype == np.int16
    assert pattern_error(vol) == 0


def test_one_image_without_rescale_takes_the_series_own(tmp_path):
    """One image of a series lacking RescaleSlope/RescaleIntercept was read with slope 1, intercept 0: 1024 HU
    brighter than its neighbours, and a model was built from it (session 15's sweep).  It takes the series'
    common rescale, and the warning says so."""
    files = fac.write_ct_series(tmp_path, n_slices=5)
    expected = load_study(tmp_path).hu
    ds = pydicom.dcmread(files[2])
    del ds.RescaleSlope, ds.RescaleIntercept
    ds.save_as(files[2])
    with pytest.warns(StudyWarning, match=r"1 image\(s\) lack RescaleSlope/RescaleIntercept \(.*\): the series' "
                                          r"other images' slope 1 and intercept -1024 taken"):
        vol = load_study(tmp_path)
    np.testing.assert_array_equal(vol.hu, expected)


def test_the_series_rescale_holds_while_resampling(tmp_path):
    """The same image without rescale in a series with a missing slice (resampled): the resampling reads the
    frames that carry the series' rescale (a merge once left them out of the plan: that image 1024 HU off)."""
    files = fac.write_ct_series(tmp_path, n_slices=8, skip=(5,))
    with pytest.warns(StudyWarning, match="missing slice"):
        expected = load_study(tmp_path).hu
    ds = pydicom.dcmread(files[2])
    del ds.RescaleSlope, ds.RescaleIntercept
    ds.save_as(files[2])
    with pytest.warns(StudyWarning, match=r"lack RescaleSlope/RescaleIntercept"):
        vol = load_study(tmp_path)
    assert vol.resampled
    np.testing.assert_array_equal(vol.hu, expected)


@pytest.mark.parametrize("tag", ["ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing"])
def test_an_image_that_cannot_be_placed_is_left_out_by_name(tmp_path, tag):
    """One image of 8 lacking ImagePositionPatient made the whole series "unusable" (and --series could not
    choose it); one lacking ImageOrientationPatient went out unnamed, seen only as a gap (session 15's sweep).
    Any of the three is left out with a warning naming its file and what it lacks; the gap is filled."""
    files = fac.write_ct_series(tmp_path, n_slices=8)
    ds = pydicom.dcmread(files[3])
    delattr(ds, tag)
    ds.save_as(files[3])
    with pytest.warns(StudyWarning, match=rf"1 image\(s\) without {tag} left out: {files[3].name}"):
        vol = load_study(tmp_path)
    assert vol.hu.shape[0] == 8 and len(vol.slices) == 7 and vol.resampled
    # every image without it: no volume, and the error says what they lack
    for f in files:
        ds = pydicom.dcmread(f)
        if hasattr(ds, tag):
            delattr(ds, tag)
            ds.save_as(f)
    with pytest.raises(SeriesError, match=rf"no {tag}"):
        load_study(tmp_path)


def test_an_image_of_another_size_is_named(tmp_path):
    """One slice of 8 at another size left the stack unnamed, seen only as a gap (session 15's sweep)."""
    files = fac.write_ct_series(tmp_path, n_slices=8)
    small = tmp_path / "small"
    fac.write_ct_series(small, n_slices=8, rows=16, cols=16)
    ds = pydicom.dcmread(sorted(small.glob("*.dcm"))[3])
    ref = pydicom.dcmread(files[3])
    ds.SeriesInstanceUID, ds.StudyInstanceUID, ds.FrameOfReferenceUID = (
        ref.SeriesInstanceUID, ref.StudyInstanceUID, ref.FrameOfReferenceUID)
    ds.ImagePositionPatient = ref.ImagePositionPatient
    files[3].unlink()
    ds.save_as(tmp_path / "odd.dcm")
    import shutil

    shutil.rmtree(small)
    with pytest.warns(StudyWarning, match=r"1 image\(s\) of another size than its 32x32 left out of its stack: odd.dcm"):
        vol = load_study(tmp_path)
    assert vol.hu.shape[0] == 8 and len(vol.slices) == 7


def test_a_series_chosen_that_is_not_ct_is_warned(tmp_path):
    """--series chose an MR series and a heart model was built from it with no word (session 15's sweep)."""
    files = fac.write_ct_series(tmp_path, n_slices=6)
    for f in files:
        ds = pydicom.dcmread(f)
        ds.Modality = "MR"
        ds.save_as(f)
    with pytest.raises(SeriesError, match="no CT image stack found"):
        load_study(tmp_path)
    with pytest.warns(StudyWarning, match=r"series \[0\] .* is MR, not CT: its values are not Hounsfield units"):
        load_study(tmp_path, series=0)


@pytest.mark.parametrize("tag, value, named", [
    ("PixelSpacing", [-1.0, -1.0], r"\(0028,0030\) Pixel Spacing is \(-1, -1\) mm, not a plausible value"),
    ("ImageOrientationPatient", [0.0] * 6, r"\(0020,0037\) Image Orientation \(Patient\) is \(0, 0, 0, 0, 0, 0\)"),
    ("ImageOrientationPatient", [1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
     r"\(0020,0037\) Image Orientation \(Patient\) is \(1, 0, 0, 1, 0, 0\)"),
])
def test_a_series_of_unreadable_geometry_says_why(tmp_path, tag, value, named):
    """Every image with an impossible geometry: the error named --series (which could not help) or blamed
    "repeated slice positions" (an orientation of zeros); it now gives a file and what is wrong with it."""
    files = fac.write_ct_series(tmp_path, n_slices=4)
    for f in files:
        ds = pydicom.dcmread(f)
        setattr(ds, tag, value)
        ds.save_as(f)
    with pytest.warns(StudyWarning), pytest.raises(
            StudyError, match=r"no readable DICOM image under .*: 4 DICOM file\(s\) cannot be read, e.g. "
                              r".*slice_\d+\.dcm: " + named):
        load_study(tmp_path)
    for f in fac.write_ct_series(tmp_path / "mr", n_slices=3):  # another, readable series: no CT still
        ds = pydicom.dcmread(f)
        ds.Modality = "MR"
        ds.save_as(f)
    with pytest.warns(StudyWarning), pytest.raises(  # the MR series can still be chosen: both are said
            SeriesError, match=r"no CT image stack found automatically \(4 DICOM file\(s\) cannot be read, e.g. "
                               r".*slice_\d+\.dcm: " + named + r".*\); choose one with --series"):
        load_study(tmp_path)


def test_fractional_slope_gives_float32(tmp_path):
    fac.write_ct_series(tmp_path, n_slices=4, rescale=(0.5, -1024.0))
    vol = load_study(tmp_path)
    assert vol.hu.dtype == np.float32
    assert pattern_error(vol) == 0


def test_folder_without_dicom_is_a_clear_error(tmp_path):
    (tmp_path / "a.txt").write_text("hello")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.bin").write_bytes(b"\x00" * 300)
    with pytest.raises(StudyError, match=r"no DICOM images found.*2 file\(s\) examined: 2 not DICOM"):
        load_study(tmp_path)
    with pytest.raises(StudyError, match="no DICOM images"):
        list_series(tmp_path / "sub")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_study(tmp_path / "nowhere")


# ------------------------------------------------------------- real data


def test_pydicom_ct_small_loads_as_one_slice():
    path = get_testdata_file("CT_small.dcm")
    ds = pydicom.dcmread(path)
    vol = load_study(path)
    assert vol.hu.shape == (1, 128, 128)
    expected = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    np.testing.assert_array_equal(vol.hu[0], expected)
    ipp = np.array(ds.ImagePositionPatient, dtype=float)
    dr, dc = (float(v) for v in ds.PixelSpacing)
    np.testing.assert_allclose(vol.voxel_to_patient([0, 0, 0]), ipp)
    np.testing.assert_allclose(vol.voxel_to_patient([5, 7, 0]), ipp + [5 * dc, 7 * dr, 0])
    assert vol.spacing_mm[2] == pytest.approx(float(ds.SliceThickness))
    assert isinstance(vol.slices[0], SliceInfo)
    assert vol.slices[0].mid_scan_time_s is not None  # GE private (0019,xx24)
    assert vol.series.manufacturer == "GE MEDICAL SYSTEMS"


# ------------------------------------------------ pixel layouts and header values


def _garbage_high_bits(bits_stored, pixel_representation):
    """BitsStored < BitsAllocated, with random values in the unused high bits."""
    rng = np.random.default_rng(7)

    def edit(ds, k):
        arr = np.frombuffer(ds.PixelData, "<u2") & ((1 << bits_stored) - 1)
        noise = rng.integers(0, 1 << (16 - bits_stored), arr.shape, dtype=np.uint16)
        ds.BitsStored, ds.HighBit = bits_stored, bits_stored - 1
        ds.PixelRepresentation = pixel_representation
        ds.PixelData = (arr | (noise << bits_stored)).astype("<u2").tobytes()

    return edit


def _eight_bit(pixel_representation):
    def edit(ds, k):
        arr = (np.frombuffer(ds.PixelData, "<u2") % 256).astype(np.uint8)
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
        ds.PixelRepresentation = pixel_representation
        ds.PixelData = arr.tobytes()

    return edit


def _thirty_two_bit(ds, k):
    arr = np.frombuffer(ds.PixelData, "<u2").astype("<u4") * 3
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 32, 32, 31
    ds.PixelData = arr.tobytes()


def _overflow_slice_2(ds, k):
    if k == 2:
        arr = np.frombuffer(ds.PixelData, "<u2").copy()
        arr[0] = 65000  # 65000 - 1024 HU does not fit int16
        ds.PixelData = arr.tobytes()


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(extra=_garbage_high_bits(12, 1)),
        dict(extra=_garbage_high_bits(12, 0)),
        dict(extra=_eight_bit(0)),
        dict(extra=_eight_bit(1)),
        dict(extra=_thirty_two_bit),
        dict(rescale=(2.0, -2048.0)),
        dict(rescale=(-1.0, 1024.0)),
        dict(rescale=None),
        dict(extra=_overflow_slice_2),
    ],
    ids=["12bit-signed", "12bit-unsigned", "8bit", "8bit-signed", "32bit", "slope2",
         "slope-neg", "no-rescale", "int16-overflow"],
)
def test_uncompressed_layouts_equal_pydicom_decoding(tmp_path, kwargs):
    """Uncompressed slices are read straight from the files: same HU as pydicom gives."""
    files = fac.write_ct_series(tmp_path, n_slices=5, **kwargs)
    vol = quiet_load(tmp_path)
    expected = []
    for f in files:
        ds = pydicom.dcmread(f)
        slope, intercept = float(ds.get("RescaleSlope", 1)), float(ds.get("RescaleIntercept", 0))
        expected.append(ds.pixel_array.astype(np.float64) * slope + intercept)
    np.testing.assert_array_equal(vol.hu, np.stack(expected))
    overflow = kwargs.get("extra") is _overflow_slice_2
    assert vol.hu.dtype == (np.float32 if overflow else np.int16)
    assert any("exceed int16" in n for n in vol.notes) == overflow


def test_big_endian_slices_are_decoded_by_pydicom(tmp_path):
    files = fac.write_ct_series(tmp_path, n_slices=3)
    for f in files:
        ds = pydicom.dcmread(f)
        ds.PixelData = ds.pixel_array.astype(">u2").tobytes()
        ds.file_meta.TransferSyntaxUID = pydicom.uid.ExplicitVRBigEndian
        pydicom.dcmwrite(f, ds, little_endian=False, implicit_vr=False)
    vol = load_study(tmp_path)
    assert pattern_error(vol) == 0


def test_header_values_beyond_plain_ascii(tmp_path):
    """Latin-1 text, and the GE block behind another vendor's private block."""

    def edit(ds, k):
        ds.SpecificCharacterSet = "ISO_IR 100"
        ds.SeriesDescription = "Cardiaque gaté"
        for tag in [t for t in ds.keys() if t.group == 0x0019]:
            del ds[tag]
        ds.private_block(0x0019, "OTHER_VENDOR", create=True).add_new(0x24, "DS", "99")
        acq = ds.private_block(0x0019, "GEMS_ACQU_01", create=True)
        acq.add_new(0x24, "DS", f"{0.5 + k * fac.SLICE_DT_S:.6f}")

    fac.write_ct_series(tmp_path, n_slices=3, extra=edit)
    vol = load_study(tmp_path)
    assert vol.series.description == "Cardiaque gaté"
    assert [s.mid_scan_time_s for s in vol.slices] == pytest.approx(
        [0.5 + k * fac.SLICE_DT_S for k in range(3)]
    )


def test_single_valued_image_type_localizer_is_recognised(tmp_path):
    """ImageType with one value ('LOCALIZER') must not be split into letters."""
    import pydicom

    from imaging.dicom_values import _upper_values

    assert _upper_values("LOCALIZER") == ("LOCALIZER",)
    assert _upper_values(pydicom.multival.MultiValue(str, ["ORIGINAL", "primary"])) == ("ORIGINAL", "PRIMARY")
    assert _upper_values(None) == ()


def test_a_stray_repeated_position_is_dropped_not_split(tmp_path):
    """One image resent at another's position (with its own AcquisitionNumber) must
    not split the series into fragments: the repeat is dropped with a warning that
    names both files, and the hole it leaves is resampled."""
    z = 2.0 * np.arange(20)
    z[11] = z[10]

    def acquisition_number(ds, k):
        ds.AcquisitionNumber = 1 + k // 4  # step-and-shoot: one number per stack

    fac.write_ct_series(tmp_path, positions=[(-16.0, -16.0, -20.0 + v) for v in z], extra=acquisition_number)
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vol = load_study(tmp_path)
    messages = [str(w.message) for w in caught if issubclass(w.category, StudyWarning)]
    assert any(re.search(r"repeat the position of another.*slice_011.dcm repeats .*slice_010.dcm", m) for m in messages)
    assert any("1 missing slice(s)" in m for m in messages)  # the hole it leaves
    assert vol.hu.shape[0] == 20 and len(vol.slices) == 19
    assert vol.resampled
    # the same image resent under the same file name into another folder (two exports merged): said so, not
    # "slice_011.dcm repeats slice_011.dcm"
    (tmp_path / "resent").mkdir()
    (tmp_path / "slice_011.dcm").rename(tmp_path / "resent" / "slice_011.dcm")
    (tmp_path / "slice_010.dcm").rename(tmp_path / "slice_011.dcm")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_study(tmp_path)
    assert any(re.search(r"slice_011.dcm repeats the file of that name in another folder", str(w.message))
               for w in caught), [str(w.message) for w in caught]


def test_zero_rescale_slope_is_a_clear_error(tmp_path):
    from imaging.pixels import PixelDataError

    with np.errstate(divide="ignore", invalid="ignore"):  # the factory divides by the slope
        fac.write_ct_series(tmp_path, rescale=(0.0, -1024.0))
    with pytest.raises(PixelDataError, match=r"slice_0\d\d.dcm: \(0028,1053\) Rescale Slope 0.0"):
        load_study(tmp_path)


def test_a_huge_rescale_slope_is_a_clear_error(tmp_path):
    """A slope of 1e30 overflowed numpy's integer arithmetic: a 24-line traceback, exit 70 (session 15's sweep)."""
    from imaging.pixels import PixelDataError

    fac.write_ct_series(tmp_path)
    for path in sorted(tmp_path.glob("*.dcm"))[:1]:
        ds = pydicom.dcmread(path)
        ds.RescaleSlope = 1e30
        ds.save_as(path)
    with pytest.raises(PixelDataError, match=r"\(0028,1053\) Rescale Slope 1e\+30 .* cannot map stored values to HU"):
        load_study(tmp_path)


def test_tilted_series_keeps_every_acquired_pixel(tmp_path):
    """Issue 10: a tilt of 1.3 mm per 2 mm slice (33 deg) over 20 slices moves the
    last slice 24.7 mm (77 % of its width): the grid is widened to every slice's
    pixels (no acquired pixel dropped), said in the note, and the volume, sampled
    at each acquired slice's own pixel centres (trilinear), gives that slice's
    values.  The pattern is linear in y and z over most of the slice, so linear
    resampling is exact there; within a pixel of the content's kinks and edges
    the two linear interpolations differ: tolerance 1 HU for 99 % of pixels and
    the pattern's step per pixel at most."""
    from scipy import ndimage

    files = fac.write_ct_series(tmp_path, shear_mm=(0.0, 1.3, 0.0))
    with pytest.warns(StudyWarning, match="widened to the bounding box"):
        vol = load_study(tmp_path)
    assert vol.hu.shape[1] == 32 + 25  # 24.7 px of shift: 25 more rows
    note = next(n for n in vol.notes if "sheared stack" in n)
    assert "57 x 32 pixels" in note and "extended by 0 / 25 rows" in note
    T_voxel_from_patient = np.linalg.inv(vol.T_patient_from_voxel)
    errors = []
    for f in files:
        ds = pydicom.dcmread(f)
        hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        j, i = np.mgrid[0 : ds.Rows, 0 : ds.Columns]
        ipp = np.asarray(ds.ImagePositionPatient, float)
        r, c = np.asarray(ds.ImageOrientationPatient[:3], float), np.asarray(ds.ImageOrientationPatient[3:], float)
        dr, dc = (float(v) for v in ds.PixelSpacing)
        p = ipp + i[..., None] * dc * r + j[..., None] * dr * c
        v = np.c_[p.reshape(-1, 3), np.ones(p[..., 0].size)] @ T_voxel_from_patient.T
        ijk = v[:, :3]
        # every acquired pixel centre lies inside the volume's grid
        assert np.all(ijk >= -1e-6) and np.all(ijk <= np.array(vol.hu.shape[::-1]) - 1 + 1e-6)
        sampled = ndimage.map_coordinates(vol.hu.astype(np.float64), ijk[:, ::-1].T, order=1, mode="nearest")
        errors.append(np.abs(sampled - hu.ravel()))
    err = np.concatenate(errors)
    assert np.percentile(err, 99) <= 1.0, np.percentile(err, 99)
    step = np.abs(np.diff(fac.pattern_hu(np.stack(np.meshgrid(np.zeros(1), np.arange(-40, 40, 1.0), np.zeros(1)), -1).reshape(-1, 3)))).max()
    assert err.max() <= step + 1e-6


def test_of_two_reconstructions_alike_the_smoother_is_taken(tmp_path):
    """A scan exported twice, as a soft-tissue and as a lung (sharp, noisy) reconstruction, the lung one under the
    lower series index: the soft one is loaded, and the warning says why (the lower index was taken before, and
    a lung kernel's copy of the real CT gave a model 1.3 % smaller); --series still takes the other."""
    rng = np.random.default_rng(3)
    study = pydicom.uid.generate_uid()

    def sharp(ds, k):
        stored = np.frombuffer(ds.PixelData, np.uint16).astype(np.int32)
        ds.PixelData = np.clip(stored + rng.normal(0.0, 40.0, stored.shape).round(), 0, 4095).astype(np.uint16).tobytes()

    fac.write_ct_series(tmp_path / "lung", series_number=2, study_uid=study, extra=sharp)
    fac.write_ct_series(tmp_path / "soft", series_number=3, study_uid=study)
    with pytest.warns(StudyWarning, match=r"equally good candidates \(\[1\], \[0\]\); used \[1\] .*, the smoothest "
                                          r"\(neighbouring voxels in soft tissue differ by a median \d+ HU in \[1\], "
                                          r"\d+ HU in \[0\]: a softer reconstruction kernel\)"):
        volume = load_study(tmp_path)
    soft = load_study(tmp_path / "soft")
    np.testing.assert_array_equal(volume.hu, soft.hu)
    listed = {s.index: s for s in list_series(tmp_path)}
    assert listed[0].description == listed[1].description  # nothing but the pixels tells them apart here
    assert not np.array_equal(load_study(tmp_path, series=0).hu, soft.hu)


def test_phases_of_a_gated_study_are_not_told_apart_by_texture(tmp_path):
    """Two phases of a gated study, alike in size (each its own series, the noisier first): no texture decides
    between them (it would choose a phase by its image's noise), the lower index is taken as before."""
    rng = np.random.default_rng(4)
    study = pydicom.uid.generate_uid()

    def phase(pct, noise):
        def tag(ds, k):
            ds.NominalPercentageOfCardiacPhase = pct
            if noise:
                stored = np.frombuffer(ds.PixelData, np.uint16).astype(np.int32)
                ds.PixelData = np.clip(stored + rng.normal(0.0, 40.0, stored.shape).round(), 0,
                                       4095).astype(np.uint16).tobytes()
        return tag

    fac.write_ct_series(tmp_path / "p40", series_number=2, study_uid=study, extra=phase(40.0, True))
    fac.write_ct_series(tmp_path / "p70", series_number=3, study_uid=study, extra=phase(70.0, False))
    with pytest.warns(StudyWarning, match=r"equally good candidates \(\[0\], \[1\]\); used \[0\] [\d.]+: choose"):
        volume = load_study(tmp_path)
    np.testing.assert_array_equal(volume.hu, load_study(tmp_path / "p40").hu)
