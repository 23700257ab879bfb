"""DICOM ECG waveforms (imaging/waveform.py), and QRS detection on them.

Two sources: pydicom's real 12-lead file ``waveform_ecg.dcm`` (Mortara el250,
10 s at 1000 Hz, 12 leads in microvolts, 10 beats annotated), and General ECG
files written here from the phantom's ECG, whose R-peak times are known on the
AcquisitionTime clock.
"""

from __future__ import annotations

import copy

import numpy as np
import pydicom
import pytest
from pydicom.data import get_testdata_file
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from heartreg.phantom.signals import r_peak_times, synthesize_ecg
from imaging.ecg import detect_r_peaks
from imaging.waveform import EcgRecord, WaveformError, read_ecg_waveform

MORTARA = get_testdata_file("waveform_ecg.dcm")
GENERAL_ECG = "1.2.840.10008.5.1.4.1.1.9.1.2"


@pytest.fixture(scope="module")
def mortara():
    return pydicom.dcmread(MORTARA)


def test_mortara_file_is_read_as_lead_ii_on_the_acquisition_clock():
    rec = read_ecg_waveform(MORTARA)
    assert isinstance(rec, EcgRecord)
    assert rec.channel_label == "Lead II" and rec.channel_index == 1 and len(rec.channel_labels) == 12
    assert rec.group_index == 0  # the ORIGINAL rhythm strip, not the DERIVED median beat
    assert rec.rate_hz == 1000.0 and rec.signal_mv.shape == (10000,)
    # AcquisitionDateTime 20130125105919 -> 10:59:19; MultiplexGroupTimeOffset 0
    assert rec.start_time_s == 10 * 3600 + 59 * 60 + 19
    assert rec.clock_source.startswith("(0008,002A) AcquisitionDateTime")
    assert rec.notes == ()
    # microvolts (Channel Sensitivity Units "uV") to mV: R waves of about 1 mV
    assert 0.9 < rec.signal_mv.max() < 1.3
    np.testing.assert_allclose(rec.time_s[[0, -1]], rec.start_time_s + np.array([0.0, 9.999]))


def test_mortara_annotated_beats_are_the_ten_rhythm_fiducial_points():
    """The file annotates 10 QRS fiducial points (SCP-ECG 5.7.1-3) at 1-based sample
    positions 527 ... 9370 of the rhythm strip, and one more at 501: the median
    beat's trigger sample, wrongly referenced to the rhythm group.  The 10 are kept."""
    rec = read_ecg_waveform(MORTARA)
    positions = np.array([527, 1526, 2507, 3489, 4485, 5468, 6442, 7444, 8417, 9370])
    np.testing.assert_allclose(rec.annotated_r_peaks_s, rec.start_time_s + (positions - 1) / 1000.0)


def test_every_annotated_beat_of_the_real_file_is_detected_within_5_ms():
    """Reference: the file's QRS fiducial points.  They lie within 2 ms of the lead II
    maxima (checked here too, on the raw samples), so they are R-peak times to the
    tolerance used.  Every one is found within 5 ms, with no other detection."""
    rec = read_ecg_waveform(MORTARA)
    peaks = detect_r_peaks(rec.signal_mv, rec.rate_hz, start_s=rec.start_time_s)
    ref = rec.annotated_r_peaks_s
    assert len(peaks) == ref.size == 10
    assert peaks.polarity == 1
    np.testing.assert_allclose(peaks.times_s, ref, atol=5e-3)
    # the reference is an R maximum: the raw lead II maximum within +-60 ms
    idx = np.round((ref - rec.start_time_s) * rec.rate_hz).astype(int)
    raw_max = np.array([i - 60 + np.argmax(rec.signal_mv[i - 60 : i + 61]) for i in idx])
    np.testing.assert_allclose(raw_max, idx, atol=2)


@pytest.mark.parametrize("lead", range(12))
def test_all_twelve_leads_give_the_ten_beats(lead):
    """Upright and inverted leads (aVR, V1, V2 are negative) give the same 10 beats.
    The R maximum differs between leads by the QRS loop's projection (<= 15 ms here)."""
    rec = read_ecg_waveform(MORTARA, channel=lead)
    peaks = detect_r_peaks(rec.signal_mv, rec.rate_hz, start_s=rec.start_time_s)
    assert len(peaks) == 10
    np.testing.assert_allclose(peaks.times_s, rec.annotated_r_peaks_s, atol=15e-3)


def test_channel_by_name_and_errors(mortara):
    assert read_ecg_waveform(mortara, channel="V5").channel_label == "Lead V5"
    assert read_ecg_waveform(mortara, channel="lead avr").channel_label == "Lead aVR"
    with pytest.raises(WaveformError, match="no lead named 'X7'.*Lead II"):
        read_ecg_waveform(mortara, channel="X7")
    with pytest.raises(WaveformError, match=r"channel must be in \[0, 12\)"):
        read_ecg_waveform(mortara, channel=12)
    with pytest.raises(WaveformError, match="group must be an index"):
        read_ecg_waveform(mortara, group=5)
    median = read_ecg_waveform(mortara, group=1)
    assert median.signal_mv.shape == (1200,) and median.annotated_r_peaks_s.size == 0


def test_clock_fallbacks_are_said(mortara):
    ds = copy.deepcopy(mortara)
    ds.WaveformSequence[0].MultiplexGroupTimeOffset = "250"
    rec = read_ecg_waveform(ds)
    assert rec.start_time_s == 39559.25
    del ds.AcquisitionDateTime
    ds.AcquisitionTime = "105920.5"
    rec = read_ecg_waveform(ds)
    assert rec.start_time_s == 39560.75
    assert "AcquisitionTime" in rec.clock_source and "fallback" in rec.clock_source
    assert any("fallback" in n for n in rec.notes)
    del ds.AcquisitionTime
    rec = read_ecg_waveform(ds)
    assert rec.start_time_s == 39559.25 and "ContentTime" in rec.clock_source
    del ds.ContentTime
    with pytest.raises(WaveformError, match="cannot be placed on the study clock"):
        read_ecg_waveform(ds)


def general_ecg(channels_mv, labels, *, rate_hz, acquisition_dt, offset_ms=0.0, units="uV"):
    """A General ECG Waveform Storage dataset with one multiplex group (int16 samples)."""
    scale = {"uV": 1000.0, "mV": 1.0}[units]
    sensitivity = 2.5 if units == "uV" else 0.0025
    samples = np.round(np.column_stack(channels_mv) * scale / sensitivity).astype("<i2")
    ds = Dataset()
    ds.SOPClassUID = GENERAL_ECG
    ds.SOPInstanceUID = generate_uid()
    ds.Modality = "ECG"
    ds.AcquisitionDateTime = acquisition_dt
    group = Dataset()
    group.MultiplexGroupTimeOffset = f"{offset_ms:g}"
    group.WaveformOriginality = "ORIGINAL"
    group.NumberOfWaveformChannels = samples.shape[1]
    group.NumberOfWaveformSamples = samples.shape[0]
    group.SamplingFrequency = f"{rate_hz:g}"
    group.WaveformBitsAllocated = 16
    group.WaveformSampleInterpretation = "SS"
    defs = []
    for label in labels:
        ch = Dataset()
        src = Dataset()
        src.CodeValue, src.CodingSchemeDesignator, src.CodeMeaning = {
            "II": ("5.6.3-9-2", "SCPECG", "Lead II"),
            "I": ("5.6.3-9-1", "SCPECG", "Lead I (Einthoven)"),
            "V1": ("5.6.3-9-3", "SCPECG", "Lead V1"),
        }[label]
        ch.ChannelSourceSequence = Sequence([src])
        ch.ChannelSensitivity = f"{sensitivity:g}"
        unit = Dataset()
        unit.CodeValue, unit.CodingSchemeDesignator, unit.CodeMeaning = units, "UCUM", units
        ch.ChannelSensitivityUnitsSequence = Sequence([unit])
        ch.ChannelSensitivityCorrectionFactor = "1"
        ch.ChannelBaseline = "0"
        ch.WaveformBitsStored = 16
        defs.append(ch)
    group.ChannelDefinitionSequence = Sequence(defs)
    group.WaveformData = samples.tobytes()
    ds.WaveformSequence = Sequence([group])
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    return ds


@pytest.mark.parametrize("labels, chosen", [(("ECG V1", "ECG II"), 1), (("V1", "Lead II (mV)"), 1),
                                            (("ECG1", "ECG2"), 0), (("V1", "III"), 0)])
def test_lead_ii_is_found_by_its_label_alone(tmp_path, labels, chosen):
    """A vendor's file without the leads' codes, labelled "ECG II": the first channel (here an inverted V1) was
    taken (an ECG audit); a label naming lead II is enough, and without one the first channel stays."""
    ecg = np.sin(np.linspace(0.0, 20.0, 500))
    ds = general_ecg([-0.6 * ecg, ecg], ["V1", "II"], rate_hz=250.0, acquisition_dt="20240301140507.25")
    for ch, label in zip(ds.WaveformSequence[0].ChannelDefinitionSequence, labels):
        del ch.ChannelSourceSequence
        ch.ChannelLabel = label
    ds.save_as(tmp_path / "ecg.dcm", enforce_file_format=True)
    rec = read_ecg_waveform(tmp_path / "ecg.dcm")
    assert (rec.channel_index, rec.channel_label) == (chosen, labels[chosen])


@pytest.mark.parametrize("rate_hz, units", [(250.0, "uV"), (500.0, "mV")])
def test_phantom_ecg_file_round_trip_on_the_study_clock(tmp_path, rate_hz, units):
    """Phantom ECG written as General ECG (lead II second, after an inverted V1): read back,
    lead II chosen, its R-peaks found on the AcquisitionTime clock within 3 ms of truth."""
    rng = np.random.default_rng(11)
    t0 = 14 * 3600 + 5 * 60 + 7.25 + 0.120  # AcquisitionDateTime + 120 ms group offset
    truth = r_peak_times(rng, start_s=t0, end_s=t0 + 20.0, heart_rate_hz=1.4, hrv_fraction=0.05,
                         ectopic_probability=0.05, resp_rate_hz=0.2)
    ecg = synthesize_ecg(rng, truth, start_s=t0, duration_s=20.0, rate_hz=rate_hz, noise_mv=0.03,
                         wander_mv=0.2)
    ds = general_ecg([-0.6 * ecg, ecg], ["V1", "II"], rate_hz=rate_hz,
                     acquisition_dt="20240301140507.25", offset_ms=120.0, units=units)
    path = tmp_path / "ecg.dcm"
    ds.save_as(path, enforce_file_format=True)
    rec = read_ecg_waveform(path)
    assert rec.channel_label == "Lead II" and rec.source == str(path)
    assert rec.start_time_s == pytest.approx(t0, abs=1e-9)
    assert rec.annotated_r_peaks_s.size == 0
    np.testing.assert_allclose(rec.signal_mv, ecg, atol=0.002)  # int16 quantisation
    peaks = detect_r_peaks(rec.signal_mv, rec.rate_hz, start_s=rec.start_time_s)
    inside = truth[(truth > t0 + 0.03) & (truth < t0 + 19.97)]
    assert len(peaks) == inside.size
    np.testing.assert_allclose(peaks.times_s, inside, atol=3e-3)
    # no lead II: the first channel, here an inverted lead, still gives the beats
    ds1 = general_ecg([-0.6 * ecg], ["V1"], rate_hz=rate_hz, acquisition_dt="20240301140507.25",
                      offset_ms=120.0, units=units)
    rec1 = read_ecg_waveform(ds1)
    assert rec1.channel_label == "Lead V1" and rec1.source == "<Dataset>"
    p1 = detect_r_peaks(rec1.signal_mv, rec1.rate_hz, start_s=rec1.start_time_s)
    assert p1.polarity == -1
    np.testing.assert_allclose(p1.times_s, inside, atol=3e-3)


def test_not_an_ecg_or_not_dicom_is_refused_naming_the_file(tmp_path, mortara):
    ct = get_testdata_file("CT_small.dcm")
    with pytest.raises(WaveformError, match=r"CT_small\.dcm is not an ECG waveform \(CT Image Storage"):
        read_ecg_waveform(ct)
    text = tmp_path / "notes.txt"
    text.write_text("not dicom at all")
    with pytest.raises(WaveformError, match=r"notes\.txt is not a DICOM file.*force=True"):
        read_ecg_waveform(text)
    with pytest.raises(WaveformError, match="cannot be read"):
        read_ecg_waveform(tmp_path / "missing.dcm")
    ds = copy.deepcopy(mortara)
    del ds.WaveformSequence
    with pytest.raises(WaveformError, match=r"no \(5400,0100\) Waveform Sequence"):
        read_ecg_waveform(ds)
    with pytest.raises(WaveformError, match="path or a pydicom Dataset"):
        read_ecg_waveform(42)
