"""The phantom's gated CT study: DICOM files read back against the phantom's truth.

Tests read the files with pydicom only (not heartreg.imaging), so they check the
writer independently of the readers that will be tested against it.
"""

from __future__ import annotations

import dataclasses
import json
from datetime import datetime
from pathlib import Path

import numpy as np
import pydicom
import pytest
from scipy.ndimage import map_coordinates

from heartreg.phantom import ct as ct_module
from heartreg.phantom.chest import build_chest
from heartreg.phantom.chest_render import render_slice
from heartreg.phantom.config import PRESETS, SIZES, config_from_dict, make_config
from heartreg.phantom.acquisition import _streams, plan_acquisition
from heartreg.phantom.ct import CTStudyExistsError, write_ct_study
from heartreg.phantom.dicom_ct import GE_ACQU_CREATOR, GE_CARDIAC_CREATOR
from heartreg.phantom.layout import FIDUCIAL_SIZE_MM, fiducials_patient_mm, make_heart
from heartreg.phantom.signals import phase_from_events

SEED = 3


def _quiet(config):
    """The same case without CT or ECG noise (and without ECG wander)."""
    noise = dataclasses.replace(config.noise, ct_noise_hu=0.0, ecg_noise_mv=0.0, ecg_wander_mv=0.0)
    return dataclasses.replace(config, noise=noise)


def _tm(text: str) -> float:
    return int(text[0:2]) * 3600 + int(text[2:4]) * 60 + float(text[4:])


def _read(study_dir: Path):
    """CT datasets sorted by position along the normal, and the ECG dataset."""
    cts, ecgs = [], []
    for f in (study_dir / "ct").iterdir():
        ds = pydicom.dcmread(f)
        (ecgs if ds.Modality == "ECG" else cts).append(ds)
    normal = np.cross(*np.reshape([float(v) for v in cts[0].ImageOrientationPatient], (2, 3)))
    cts.sort(key=lambda d: float(np.dot(normal, [float(v) for v in d.ImagePositionPatient])))
    return cts, ecgs


def _hu(ds) -> np.ndarray:
    return ds.pixel_array.astype(float) * float(ds.RescaleSlope) + float(ds.RescaleIntercept)


def _grid(ds):
    x0, y0, _ = (float(v) for v in ds.ImagePositionPatient)
    dr, dc = (float(v) for v in ds.PixelSpacing)  # row spacing (along y), column spacing (along x)
    return x0 + dc * np.arange(ds.Columns), y0 + dr * np.arange(ds.Rows)


@pytest.fixture(scope="module")
def quiet_study(tmp_path_factory):
    config = _quiet(make_config("default"))
    out = tmp_path_factory.mktemp("quiet")
    truth = write_ct_study(out, config, size="sample", seed=SEED)
    cts, ecgs = _read(out)
    return config, out, truth, cts, ecgs


@pytest.fixture(scope="module")
def noisy_study(tmp_path_factory):
    config = make_config("default")
    out = tmp_path_factory.mktemp("noisy")
    truth = write_ct_study(out, config, size="sample", seed=SEED)
    cts, ecgs = _read(out)
    return config, out, truth, cts, ecgs


# ----------------------------------------------------------------- geometry
def test_geometry_tags_match_truth(quiet_study):
    _, _, truth, cts, _ = quiet_study
    g = SIZES["sample"]
    assert len(cts) == g.n_slices
    z = np.array([float(d.ImagePositionPatient[2]) for d in cts])
    np.testing.assert_allclose(z, truth.slice_position_mm, atol=1e-4)
    np.testing.assert_allclose(np.diff(z), g.slice_mm, atol=1e-4)
    for d in cts:
        assert [float(v) for v in d.ImageOrientationPatient] == [1, 0, 0, 0, 1, 0]
        assert [float(v) for v in d.PixelSpacing] == [g.pixel_mm, g.pixel_mm]
        assert float(d.SliceThickness) == float(d.SpacingBetweenSlices) == g.slice_mm
        assert (d.Rows, d.Columns) == (g.n_rows, g.n_cols)
        assert d.PixelRepresentation == 1 and d.BitsStored == 16 and float(d.RescaleIntercept) == -1024
        assert d.file_meta.TransferSyntaxUID == pydicom.uid.ExplicitVRLittleEndian
        assert d.FrameOfReferenceUID == truth.frame_of_reference_uid
        assert d.SeriesInstanceUID == truth.series_instance_uid
    # FOV centred on x = y = 0; truth affine = the one the files define
    x, y = _grid(cts[0])
    assert abs(x[0] + x[-1]) < 1e-3 and abs(y[0] + y[-1]) < 1e-3
    T = np.eye(4)
    T[:3, 0] = [g.pixel_mm, 0, 0]
    T[:3, 1] = [0, g.pixel_mm, 0]
    T[:3, 2] = [0, 0, z[1] - z[0]]
    T[:3, 3] = [float(v) for v in cts[0].ImagePositionPatient]
    np.testing.assert_allclose(truth.T_patient_from_voxel, T, atol=1e-6)
    assert [d.SOPInstanceUID for d in cts] == list(truth.slice_sop_instance_uid)


def test_pixels_are_the_rendered_chest(quiet_study):
    """Noise-free: stored HU equal chest.render_slice at the file's grid and the
    slice's truth phase, up to rounding to integer HU (0.5 HU)."""
    config, _, truth, cts, _ = quiet_study
    chest = build_chest(make_heart(config))
    for k, ds in enumerate(cts):
        x, y = _grid(ds)
        expected = render_slice(
            chest, z_mm=float(ds.ImagePositionPatient[2]), phase_c=float(truth.slice_cardiac_phase[k]),
            xs_mm=x, ys_mm=y,
        )
        np.testing.assert_allclose(_hu(ds), expected, atol=0.5 + 1e-3)


def test_noise_is_seeded_gaussian_ct_noise(noisy_study):
    """Residual against the noise-free render: mean 0 and sigma = ct_noise_hu
    (16k pixels per slice: sigma within 3 %, mean within 1 HU)."""
    config, _, truth, cts, _ = noisy_study
    chest = build_chest(make_heart(config))
    for k in (5, 36, 60):
        ds = cts[k]
        x, y = _grid(ds)
        clean = render_slice(chest, z_mm=float(ds.ImagePositionPatient[2]),
                             phase_c=float(truth.slice_cardiac_phase[k]), xs_mm=x, ys_mm=y)
        r = _hu(ds) - clean
        assert abs(r.mean()) < 1.0
        assert abs(r.std() / config.noise.ct_noise_hu - 1) < 0.03


def test_epicardium_midpoint_lies_on_the_true_surface(quiet_study):
    """Heart surface points (heart.surface_points at each slice's own phase and the
    breath-hold phase) that lie in a slice are where the noise-free image crosses
    the fat/myocardium midpoint (0 HU), within half a pixel, measured along the
    in-plane normal.  Points where the great vessels join the base are skipped."""
    config, _, truth, cts, _ = quiet_study
    heart = make_heart(config)
    chest = build_chest(heart)
    pixel = SIZES["sample"].pixel_mm
    u, v = np.meshgrid(np.linspace(0, 1, 240, endpoint=False), np.linspace(0.005, 0.995, 300))
    u, v = u.ravel(), v.ravel()
    errors = []
    for k, ds in enumerate(cts):
        z = float(ds.ImagePositionPatient[2])
        if k % 3 or not chest.heart_lo_mm[2] + 2 < z < chest.heart_hi_mm[2] - 2:
            continue
        phase = float(truth.slice_cardiac_phase[k])
        p = heart.surface_points(u, v, phase, heart.image_resp_phase)
        near = np.abs(p[:, 2] - z) < 0.1
        p, n = heart.surface_frames(u[near], v[near], phase, heart.image_resp_phase)
        n = n[..., 2]
        n_xy = n[:, :2] / np.linalg.norm(n[:, :2], axis=1, keepdims=True)
        keep = (np.linalg.norm(n[:, :2], axis=1) > 0.5) & (chest.vessel_distance_mm(p) > 4.0)
        hu = _hu(ds)
        x, y = _grid(ds)
        t = np.linspace(-2.5, 2.5, 501)
        for q, d in zip(p[keep], n_xy[keep]):
            line = q[:2] + t[:, None] * d
            vals = map_coordinates(hu, [(line[:, 1] - y[0]) / pixel, (line[:, 0] - x[0]) / pixel], order=1)
            s = np.sign(vals - 0.0)
            idx = np.nonzero(s[:-1] != s[1:])[0]
            assert idx.size, f"no fat/myocardium crossing near {q}"
            i = idx[np.argmin(np.abs(t[idx]))]
            t0 = t[i] + (t[i + 1] - t[i]) * (0 - vals[i]) / (vals[i + 1] - vals[i])
            errors.append(t0)
    errors = np.abs(errors)
    print(f"{errors.size} points, max {errors.max():.3f} mm, rms {np.sqrt(np.mean(errors**2)):.3f} mm")
    assert len(errors) > 300
    assert errors.max() < 0.5 * pixel, f"max {errors.max():.3f} mm"


# -------------------------------------------------------------------- timing
def _acq_time(ds) -> float:
    return _tm(ds.AcquisitionTime)


def test_private_ge_clocks_and_phases(quiet_study):
    _, out, truth, cts, _ = quiet_study
    origins = []
    for ds in cts:
        acqu = ds.private_block(0x0019, GE_ACQU_CREATOR)
        cardiac = ds.private_block(0x0049, GE_CARDIAC_CREATOR)
        assert acqu[0x24].VR == "DS" and cardiac[0x0C].VR == "FD"
        assert ds[0x0019, 0x0010].value == GE_ACQU_CREATOR
        origins.append(_acq_time(ds) - float(acqu[0x24].value))
        r_ms = np.asarray(cardiac[0x0C].value, dtype=float)
        np.testing.assert_allclose(r_ms / 1000.0 + truth.scan_origin_s, truth.r_peaks_s, atol=2e-6)
        assert ds.ContentTime == ds.AcquisitionTime and "." in ds.AcquisitionTime
        assert ds.CardiacSynchronizationTechnique == "PROSPECTIVE"
        assert 0 < float(ds.TriggerTime) < 60000.0 / int(ds.HeartRate) * 1.5
    np.testing.assert_allclose(origins, truth.scan_origin_s, atol=2e-6)
    times = np.array([_acq_time(d) for d in cts])
    np.testing.assert_allclose(times, truth.slice_time_s, atol=1e-6)
    # the phase a reader gets from the files is the phase each slice was rendered at
    qrs = np.loadtxt(out / "qrs.csv", skiprows=1)
    np.testing.assert_allclose(phase_from_events(times, qrs), truth.slice_cardiac_phase, atol=1e-6)
    assert truth.cardiac_phase == pytest.approx(np.mean(truth.slice_cardiac_phase))
    # phases differ slightly within a stack (row offsets), by at most 40 ms / RR
    rr = np.diff(truth.r_peaks_s).min()
    for j in np.unique(truth.slice_stack):
        ph = truth.slice_cardiac_phase[truth.slice_stack == j]
        if np.ptp(ph) < 0.5:  # no wrap inside this stack
            assert 0 < np.ptp(ph) <= 0.040 / rr + 1e-6


def test_qrs_csv_equals_truth(quiet_study):
    _, out, truth, _, _ = quiet_study
    lines = (out / "qrs.csv").read_text().splitlines()
    assert lines[0] == "time_s"
    np.testing.assert_allclose([float(s) for s in lines[1:]], truth.r_peaks_s, atol=1e-6)
    # every slice lies between covered R-peaks
    assert truth.r_peaks_s[0] < truth.slice_time_s.min() and truth.slice_time_s.max() < truth.r_peaks_s[-1]


def _ecg_samples(ds):
    item = ds.WaveformSequence[0]
    start = datetime.strptime(ds.AcquisitionDateTime, "%Y%m%d%H%M%S.%f")
    start_s = start.hour * 3600 + start.minute * 60 + start.second + start.microsecond * 1e-6
    start_s += float(item.MultiplexGroupTimeOffset) / 1000.0
    fs = float(item.SamplingFrequency)
    mv = ds.waveform_array(0)[:, 0]
    return start_s + np.arange(mv.size) / fs, mv, fs


@pytest.mark.parametrize("which, tol_samples", [("quiet", 1), ("noisy", 3)])
def test_ecg_waveform_r_peaks_at_truth(which, tol_samples, quiet_study, noisy_study):
    """The R-wave maximum is at each truth R-peak: within one sample without noise
    (wander and mains slopes shift it < 1 ms); with 0.03 mV noise against the R
    wave's curvature (~10^4 mV/s^2) within 3 samples (6 ms)."""
    _, _, truth, cts, ecgs = quiet_study if which == "quiet" else noisy_study
    assert len(ecgs) == 1
    ds = ecgs[0]
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.9.1.2"
    assert ds.StudyInstanceUID == cts[0].StudyInstanceUID
    assert ds.SeriesInstanceUID not in {d.SeriesInstanceUID for d in cts}
    ch = ds.WaveformSequence[0].ChannelDefinitionSequence[0]
    assert ch.ChannelSensitivityUnitsSequence[0].CodeValue == "mV"
    assert ch.ChannelSensitivityUnitsSequence[0].CodingSchemeDesignator == "UCUM"
    t, mv, fs = _ecg_samples(ds)
    assert t[0] < truth.slice_time_s.min() and t[-1] > truth.slice_time_s.max()
    for r in truth.r_peaks_s:
        assert t[0] < r < t[-1]
        win = np.nonzero(np.abs(t - r) < 0.05)[0]
        i = win[np.argmax(mv[win])]
        assert abs(t[i] - r) <= tol_samples / fs + 1e-6
        assert 0.8 < mv[i] < 1.8  # R wave of 1.25 mV: the values are mV


def test_phases_scatter_like_a_gated_scan():
    """Across presets and seeds: slice phases centre on the 0.6-0.8 diastolic window
    around the 0.7 target, and ectopic beats sometimes throw a stack far off or wrap
    it past 1 (a jump), as in the paper's Fig. 4."""
    all_phases, jumps = [], 0
    for config in PRESETS.values():
        for seed in range(8):
            plan = plan_acquisition(config, size="sample", seed=seed)
            ph = plan.slice_cardiac_phase
            assert np.all((ph >= 0) & (ph < 1))
            all_phases.append(ph)
            order = np.argsort(plan.slice_instance_number)
            jumps += int(np.any(np.abs(np.diff(ph[order])) > 0.2))
            # instance numbers follow time, not position
            inst = plan.slice_instance_number
            assert not (np.all(np.diff(inst) > 0) or np.all(np.diff(inst) < 0))
            assert np.all(np.diff(plan.slice_time_s[order]) >= 0)
    ph = np.concatenate(all_phases)
    assert 0.62 < np.median(ph) < 0.75
    assert np.mean((ph > 0.6) & (ph < 0.8)) > 0.8
    assert jumps >= 3


@pytest.mark.parametrize("size", sorted(SIZES))
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_scan_covers_heart_and_fiducials(size, preset):
    plan = plan_acquisition(PRESETS[preset], size=size, seed=0)
    g = SIZES[size]
    lo = plan.slice_position_mm[0] - 0.5 * g.slice_mm
    hi = plan.slice_position_mm[-1] + 0.5 * g.slice_mm
    chest = build_chest(make_heart(PRESETS[preset]))
    f = fiducials_patient_mm()
    assert lo + 5 < chest.heart_lo_mm[2] and chest.heart_hi_mm[2] < hi - 5
    assert lo + 5 < f[:, 2].min() - FIDUCIAL_SIZE_MM[1] and f[:, 2].max() + FIDUCIAL_SIZE_MM[1] < hi - 5
    half_fov = 0.5 * g.n_cols * g.pixel_mm
    assert np.all(np.abs(f[:, :2]) < half_fov - 10)


# -------------------------------------------------------------- files, errors
def test_identity_is_synthetic_and_names_do_not_follow_order(quiet_study):
    _, _, truth, cts, ecgs = quiet_study
    for ds in cts + ecgs:
        assert "PatientBirthDate" not in ds
        assert str(ds.PatientName) == "PHANTOM^HEARTREG"
        assert ds.PatientID == f"PHANTOM-{SEED}"
        assert ds.StudyDate == "20000101"
        assert ds.Manufacturer == "GE MEDICAL SYSTEMS"
    assert list(cts[0].ImageType) == ["ORIGINAL", "PRIMARY", "AXIAL"]
    names = list(truth.slice_file)
    assert names != sorted(names) and names != sorted(names, reverse=True)
    inst = [d.InstanceNumber for d in cts]
    assert inst != sorted(inst) and inst != sorted(inst, reverse=True)
    assert sorted(inst) == list(range(1, len(cts) + 1))


def test_truth_to_dict_is_json_ready(quiet_study):
    _, _, truth, _, _ = quiet_study
    d = json.loads(json.dumps(truth.to_dict()))
    assert d["cardiac_phase"] == truth.cardiac_phase
    assert d["slice_cardiac_phase"] == truth.slice_cardiac_phase.tolist()
    assert d["r_peaks_s"] == truth.r_peaks_s.tolist()
    np.testing.assert_array_equal(d["fiducials_patient_mm"], fiducials_patient_mm())
    assert d["geometry"]["n_slices"] == 72


def _all_bytes(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_other_seed_differs(tmp_path, quiet_study):
    config, out, _, _, _ = quiet_study
    write_ct_study(tmp_path / "a", config, size="sample", seed=SEED)
    assert _all_bytes(tmp_path / "a") == _all_bytes(out)
    write_ct_study(tmp_path / "b", config, size="sample", seed=SEED + 1)
    a, b = _all_bytes(tmp_path / "a"), _all_bytes(tmp_path / "b")
    assert set(a) != set(b)
    assert sorted(a.values())[0] != sorted(b.values())[0]


def test_invalid_arguments(tmp_path):
    config = make_config("default")
    with pytest.raises(ValueError, match="unknown size 'huge'.*full, sample"):
        write_ct_study(tmp_path, config, size="huge")
    with pytest.raises(ValueError, match="seed must be a non-negative integer"):
        write_ct_study(tmp_path, config, seed=-1)
    with pytest.raises(TypeError, match="config must be a PhantomConfig"):
        write_ct_study(tmp_path, {"name": "x"})
    (tmp_path / "ct").mkdir()
    (tmp_path / "ct" / "old.dcm").write_bytes(b"x")
    with pytest.raises(CTStudyExistsError, match="already holds 1 entries; remove it"):
        write_ct_study(tmp_path, config)
    assert isinstance(CTStudyExistsError("x"), FileExistsError)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["ct", "old.dcm"]
    chest = build_chest(make_heart(config))
    with pytest.raises(ValueError, match=r"phase_c must be a cardiac phase in \[0, 1\)"):
        render_slice(chest, z_mm=0.0, phase_c=1.2, xs_mm=[0.0, 1.0], ys_mm=[0.0, 1.0])
    with pytest.raises(ValueError, match="rng must be a numpy.random.Generator"):
        render_slice(chest, z_mm=0.0, phase_c=0.5, xs_mm=[0.0, 1.0], ys_mm=[0.0, 1.0], noise_hu=5.0)


def test_failure_leaves_no_half_written_study(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = ct_module.render_slice

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 10:
            raise OSError("disk full (simulated)")
        return real(*args, **kwargs)

    monkeypatch.setattr(ct_module, "render_slice", failing)
    with pytest.raises(OSError, match="simulated"):
        write_ct_study(tmp_path, make_config("default"), size="sample", seed=0)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_full_size_study(full_case):
    """512 x 512 x 288 (the suite's shared full-size case): geometry, timing and
    pixels of a few slices against truth, the CT noise drawn again from its seed."""
    case, truth = full_case
    config = config_from_dict(truth["config"])
    g = SIZES["full"]
    files = [f for f in (case / "ct").iterdir() if f.name != truth["ecg_file"]]
    assert len(files) == g.n_slices
    chest = build_chest(make_heart(config), anatomy=config.anatomy, phase_c=config.gating_target_phase)
    noise_seeds = _streams(truth["seed"])[2].spawn(g.n_slices)
    for k in (0, 100, 200, 287):
        ds = pydicom.dcmread(case / "ct" / truth["slice_file"][k])
        assert float(ds.ImagePositionPatient[2]) == pytest.approx(truth["slice_position_mm"][k], abs=1e-4)
        assert _tm(ds.AcquisitionTime) == pytest.approx(truth["slice_time_s"][k], abs=1e-6)
        x, y = _grid(ds)
        expected = render_slice(chest, z_mm=truth["slice_position_mm"][k], phase_c=truth["slice_cardiac_phase"][k],
                                xs_mm=x, ys_mm=y, rng=np.random.default_rng(noise_seeds[k]),
                                noise_hu=config.noise.ct_noise_hu)
        np.testing.assert_allclose(_hu(ds), expected, atol=0.5 + 1e-3)
