"""QRS detection (imaging/ecg.py) against the phantom's R-peak truth.

The phantom's ECG (heartreg.phantom.signals.synthesize_ecg) has its clean R
maxima exactly at the true R-peak times (Q and S are mirror images about R), so
the detected times can be compared with the truth directly.  A detection
matches a true beat within 50 ms (a QRS half-width); beats are scored as in
the MIT-BIH tradition: sensitivity = TP / (TP + FN), positive predictivity
= TP / (TP + FP).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from heartreg.phantom.signals import phase_from_events, r_peak_times, synthesize_ecg
from imaging.ecg import EDGE_MARGIN_S, RPeaks, SignalError, cardiac_phase, detect_r_peaks

MATCH_TOL_S = 0.050
START_S = 36_000.0  # 10:00:00 on the AcquisitionTime clock


def phantom_ecg(seed, *, rate_hz, heart_rate_hz, duration_s, inverted=False,
                noise_mv=0.05, wander_mv=0.3, ectopic_probability=0.06, start_s=START_S):
    """(truth R-peaks (s), ECG (mV)) of a phantom record."""
    rng = np.random.default_rng(seed)
    r = r_peak_times(rng, start_s=start_s, end_s=start_s + duration_s, heart_rate_hz=heart_rate_hz,
                     hrv_fraction=0.05, ectopic_probability=ectopic_probability, resp_rate_hz=0.2)
    ecg = synthesize_ecg(rng, r, start_s=start_s, duration_s=duration_s, rate_hz=rate_hz,
                         noise_mv=noise_mv, wander_mv=wander_mv)
    return r, (-ecg if inverted else ecg)


def match(truth_s, detected_s, tol_s=MATCH_TOL_S):
    """Greedy one-to-one matching: (true positives, unmatched detections, errors (s))."""
    used = np.zeros(len(detected_s), dtype=bool)
    errors = []
    for t in truth_s:
        i = np.searchsorted(detected_s, t)
        cands = [c for c in (i - 1, i) if 0 <= c < len(detected_s) and not used[c]]
        if not cands:
            continue
        c = min(cands, key=lambda c: abs(detected_s[c] - t))
        if abs(detected_s[c] - t) <= tol_s:
            used[c] = True
            errors.append(detected_s[c] - t)
    return len(errors), int(np.count_nonzero(~used)), np.asarray(errors)


def complete_beats(truth_s, n_samples, rate_hz, start_s=START_S, margin_s=EDGE_MARGIN_S):
    """True R-peaks whose whole QRS lies inside the record (R maximum at least
    EDGE_MARGIN_S = 50 ms, half a QRS complex, from either end)."""
    end = start_s + (n_samples - 1) / rate_hz
    return truth_s[(truth_s >= start_s + margin_s) & (truth_s <= end - margin_s)]


@pytest.mark.parametrize("rate_hz", [100.0, 250.0, 1000.0])
def test_detection_accuracy_against_phantom_truth(rate_hz):
    """Se and +P >= 99.5 % and sub-sample R-peak times at 60-180 bpm, incl. ectopics and an inverted lead.

    Per rate: 6 records x 120 s (60, 120, 180 bpm, each upright and inverted),
    noise 0.05 mV, baseline wander 0.3 mV, 6 % ectopic beats (28 % early): about
    1,440 beats.  The R-peak error is bounded by noise on the parabola vertex
    and by the parabola's bias on a Gaussian R wave (largest at 100 Hz, where R
    spans ~2 samples): measured median 0.2-0.4 ms, max ~2 ms.
    """
    tp = fn = fp = 0
    errors = []
    ectopic_found = 0
    for k, (hr, inverted) in enumerate([(1.0, False), (2.0, True), (3.0, False),
                                        (1.0, True), (2.0, False), (3.0, True)]):
        truth, ecg = phantom_ecg(100 + k, rate_hz=rate_hz, heart_rate_hz=hr, duration_s=120.0,
                                 inverted=inverted)
        peaks = detect_r_peaks(ecg, rate_hz, start_s=START_S)
        assert peaks.polarity == (-1 if inverted else 1)
        inside = complete_beats(truth, ecg.size, rate_hz)
        t, _, e = match(inside, peaks.times_s)
        _, extra, _ = match(truth, peaks.times_s)  # a detection matching no true beat at all
        tp, fn, fp = tp + t, fn + inside.size - t, fp + extra
        errors.append(e)
        # ectopic beats: RR < 80 % of the previous RR
        rr = np.diff(truth)
        early = truth[1:][np.r_[False, rr[1:] < 0.8 * rr[:-1]]]
        early = complete_beats(early, ecg.size, rate_hz)
        ectopic_found += match(early, peaks.times_s)[0]
        assert match(early, peaks.times_s)[0] == early.size
    err = np.abs(np.concatenate(errors))
    sensitivity, ppv = tp / (tp + fn), tp / (tp + fp)
    assert tp > 1400
    assert ectopic_found > 30
    assert sensitivity >= 0.995 and ppv >= 0.995, (sensitivity, ppv)
    sample_s = 1.0 / rate_hz
    assert np.median(err) <= sample_s  # the requirement
    assert np.median(err) <= 0.5e-3  # what the sub-sample refinement gives
    assert err.max() <= 3e-3


def test_short_record_of_10_s():
    """A 10 s, 100 Hz record (the shortest the paper-like pipeline sees): every complete beat."""
    truth, ecg = phantom_ecg(7, rate_hz=100.0, heart_rate_hz=1.2, duration_s=10.0)
    peaks = detect_r_peaks(ecg, 100.0, start_s=START_S)
    inside = complete_beats(truth, ecg.size, 100.0)
    tp, extra, err = match(inside, peaks.times_s)
    assert tp == inside.size >= 10
    assert extra == 0
    assert np.abs(err).max() <= 3e-3


RATE_DROP_HZ = 250.0


def rate_drop_ecg(fast_s, slow_s, *, noise_mv):
    """(beat times, ECG) of 140 s at RATE_DROP_HZ: a beat every ``fast_s`` for 20 s, then every ``slow_s`` (the last
    1 s before the end), each a narrow R (12 ms) with a tall narrow T wave (0.5 of it, 25 ms, 0.28 s after it),
    under white noise of ``noise_mv`` (seed 0)."""
    n_fast = int(20.0 / fast_s)
    beats = np.concatenate([0.5 + fast_s * np.arange(n_fast),
                            0.5 + fast_s * n_fast + slow_s * np.arange(int(118 / slow_s))])
    beats = beats[beats < 139.0]
    t = np.arange(int(140.0 * RATE_DROP_HZ)) / RATE_DROP_HZ
    ecg = np.zeros_like(t)
    for b in beats:
        ecg += np.exp(-0.5 * ((t - b) / 0.012) ** 2) + 0.5 * np.exp(-0.5 * ((t - b - 0.28) / 0.025) ** 2)
    return beats, ecg + noise_mv * np.random.default_rng(0).standard_normal(t.size)


def test_a_rhythm_slowed_for_good_is_learnt_anew():
    """Beats every 0.45 s for 20 s, then every 1.1 s (a 2:1 block, say), each with a tall T wave (0.5 of the R,
    0.28 s after it): every slow interval is past the fast rhythm's search-back limit, a "pause" left out of the
    regular R-R, and the limits come from the last 64 intervals only, so after 64 slow beats they are learnt anew
    from 60 bpm.  Kept since every regular interval was (a session-21 speed-up, found by its review), the limit
    stayed at the fast rhythm's 0.83 s and a T wave passed for a beat."""
    beats, ecg = rate_drop_ecg(0.45, 1.1, noise_mv=0.0)
    found = detect_r_peaks(ecg, RATE_DROP_HZ).times_s
    tp, extra, err = match(beats, found)
    assert tp == beats.size and extra == 0, (tp, beats.size, extra)
    assert np.abs(err).max() <= 5e-3


@pytest.mark.parametrize(("fast_s", "slow_s"), [(0.5, 1.0), (0.45, 1.1)])
def test_tall_t_waves_after_the_rate_drops_are_no_beats(fast_s, slow_s):
    """The rate halves after 20 s; every beat has a tall, narrow T wave (0.5 of the R, 25 ms, 0.28 s after it) and
    0.1 mV of white noise lies over all.  Each slow interval was past the fast rhythm's search-back limit, and
    the search-back took the T wave in it for a missed beat (72 / 36 T waves in 140 s; neurokit2 2 false, 39 / 29
    missed): it now applies the T-wave rule as every peak does, and 8 pauses in a row as steady as a rhythm are
    the slower rhythm (its limit at once, not after 64 beats)."""
    beats, ecg = rate_drop_ecg(fast_s, slow_s, noise_mv=0.1)
    tp, extra, _ = match(beats, detect_r_peaks(ecg, RATE_DROP_HZ).times_s)
    assert tp == beats.size and extra <= 1, (tp, beats.size, extra)


def test_wide_premature_beats_before_a_pause_are_found():
    """Narrow beats (8 ms, 1.5 mV) every 0.6 s, every sixth a wide premature beat (a Gaussian of 35 ms, 1.2 mV,
    0.45 s after the last, then a 0.75 s pause) under 0.01 mV of noise.  Its QRS-band energy is a tenth of the
    narrow beats' (MIT-BIH 208's wide premature beats: a tenth to a quarter), below half of threshold 1, and
    the search-back across the pause missed them (neurokit2 finds them all).  A peak that stands out
    of its neighbours (4 x their median energy) and is at least 0.4 as large as the QRS complexes now passes at
    a quarter of threshold 1.  Wider still (a
    Gaussian of 45 ms: a twenty-fifth of the energy) they are missed (README, Limits)."""
    fs, t = 360.0, np.arange(int(60.0 * 360.0)) / 360.0
    ecg, beats, wide, b = np.zeros_like(t), [], [], 0.5
    for k in range(1, 200):
        if b > 59.0:
            break
        if k % 6 == 0:
            b -= 0.15  # premature
            ecg += 1.2 * np.exp(-0.5 * ((t - b) / 0.035) ** 2) - 0.4 * np.exp(-0.5 * ((t - b - 0.3) / 0.08) ** 2)
            wide.append(b)
        else:
            ecg += 1.5 * np.exp(-0.5 * ((t - b) / 0.008) ** 2) + 0.25 * np.exp(-0.5 * ((t - b - 0.28) / 0.05) ** 2)
        beats.append(b)
        b += 0.75 if k % 6 == 0 else 0.6
    ecg += 0.01 * np.random.default_rng(0).standard_normal(t.size)
    tp, extra, _ = match(np.array(beats), detect_r_peaks(ecg, fs).times_s, tol_s=0.1)
    assert len(wide) == 16 and tp == len(beats) and extra == 0, (tp, len(beats), extra)


@pytest.mark.parametrize("p_width_s", [0.012, 0.015])
def test_blocked_p_waves_in_pauses_are_no_beats(p_width_s):
    """Sinus beats (R 1 mV, 10 ms) every 0.8 s, every eighth followed by a 2 s pause holding a blocked P wave
    (0.3 mV, sharp, 0.45 s after the R) under 0.005 mV of noise: the P wave stands out of the quiet pause and
    its QRS-band energy passes a quarter of threshold 1, so the rule for wide premature beats took all 15 (the
    session-22 review); it is no beat, being 0.3 of the QRS complexes' size, below ``qrs_classify.QRS_SIZE_RATIO``
    (0.4)."""
    fs = 360.0
    t = np.arange(int(120 * fs)) / fs
    ecg, beats, b = np.zeros_like(t), [], 0.5
    for k in range(1, 200):
        if b > 119.0:
            break
        ecg += 0.1 * np.exp(-0.5 * ((t - b + 0.16) / 0.025) ** 2) + np.exp(-0.5 * ((t - b) / 0.010) ** 2)
        ecg += 0.3 * np.exp(-0.5 * ((t - b - 0.3) / 0.05) ** 2)
        beats.append(b)
        if k % 8 == 0:
            ecg += 0.3 * np.exp(-0.5 * ((t - b - 0.45) / p_width_s) ** 2)
        b += 2.0 if k % 8 == 0 else 0.8
    ecg += 0.005 * np.random.default_rng(0).standard_normal(t.size)
    tp, extra, _ = match(np.array(beats), detect_r_peaks(ecg, fs).times_s, tol_s=0.1)
    assert tp == len(beats) and extra == 0, (tp, len(beats), extra)


@pytest.mark.parametrize("rate_hz", [100.0, 1000.0])
@pytest.mark.parametrize("edge_s", [0.06, 0.10])
def test_edge_beats_are_found_when_complete(rate_hz, edge_s):
    """A beat whose R maximum is 60 or 100 ms inside either end is found; a cut one is not invented."""
    truth, ecg_long = phantom_ecg(3, rate_hz=rate_hz, heart_rate_hz=1.4, duration_s=30.0)
    first = truth[np.searchsorted(truth, START_S + 2.0)]
    last = truth[np.searchsorted(truth, START_S + 20.0)]
    i0 = int(round((first - edge_s - START_S) * rate_hz))
    i1 = int(round((last + edge_s - START_S) * rate_hz)) + 1
    ecg = ecg_long[i0:i1]
    start = START_S + i0 / rate_hz
    peaks = detect_r_peaks(ecg, rate_hz, start_s=start)
    assert abs(peaks.times_s[0] - first) < 3e-3
    assert abs(peaks.times_s[-1] - last) < 3e-3
    inside = truth[(truth >= first) & (truth <= last)]
    tp, extra, _ = match(inside, peaks.times_s)
    assert tp == inside.size and extra == 0


@pytest.mark.parametrize("rate_hz", [100.0, 360.0])
def test_beats_within_the_edge_margin_are_left_out(rate_hz):
    """R maxima 40 ms inside either end (QRS cut in half): neither is reported (issue 10)."""
    truth, ecg_long = phantom_ecg(3, rate_hz=rate_hz, heart_rate_hz=1.4, duration_s=30.0)
    first = truth[np.searchsorted(truth, START_S + 2.0)]
    last = truth[np.searchsorted(truth, START_S + 20.0)]
    i0 = int(round((first - 0.04 - START_S) * rate_hz))
    i1 = int(round((last + 0.04 - START_S) * rate_hz)) + 1
    peaks = detect_r_peaks(ecg_long[i0:i1], rate_hz, start_s=START_S + i0 / rate_hz)
    inside = truth[(truth > first) & (truth < last)]
    assert peaks.times_s.size == inside.size
    np.testing.assert_allclose(peaks.times_s, inside, atol=3e-3)


def test_beat_cut_by_the_record_start_is_not_reported():
    """An R maximum 5 ms before the first sample: the first reported beat is the next one."""
    rate_hz = 250.0
    truth, ecg_long = phantom_ecg(4, rate_hz=rate_hz, heart_rate_hz=1.2, duration_s=20.0)
    r = truth[np.searchsorted(truth, START_S + 2.0)]
    i0 = int(np.ceil((r + 0.005 - START_S) * rate_hz))
    peaks = detect_r_peaks(ecg_long[i0:], rate_hz, start_s=START_S + i0 / rate_hz)
    nxt = truth[np.searchsorted(truth, r, side="right")]
    assert abs(peaks.times_s[0] - nxt) < 3e-3


def test_result_is_a_frozen_read_only_value():
    truth, ecg = phantom_ecg(5, rate_hz=250.0, heart_rate_hz=1.0, duration_s=12.0)
    peaks = detect_r_peaks(ecg, 250.0, start_s=START_S)
    assert isinstance(peaks, RPeaks) and len(peaks) == peaks.times_s.size
    assert peaks.times_s.dtype == np.float64 and peaks.indices.dtype == np.int64
    assert np.all(np.diff(peaks.times_s) > 0)
    np.testing.assert_allclose(peaks.times_s, START_S + peaks.indices / 250.0, atol=0.5 / 250.0)
    np.testing.assert_allclose(peaks.amplitudes_mv, 1.3, atol=0.25)  # R 1.25 mV - Q/S + noise
    with pytest.raises(ValueError):
        peaks.times_s[0] = 0.0
    with pytest.raises(AttributeError):
        peaks.rate_hz = 1.0


def test_cardiac_phase_of_detected_peaks_matches_truth():
    """Phase from detected R-peaks vs phase from the true ones: same coverage, |error| < 0.01."""
    truth, ecg = phantom_ecg(8, rate_hz=100.0, heart_rate_hz=1.3, duration_s=30.0)
    peaks = detect_r_peaks(ecg, 100.0, start_s=START_S)
    t = START_S + np.arange(ecg.size) / 100.0
    phase = cardiac_phase(t, peaks)
    true = phase_from_events(t, truth)
    both = np.isfinite(phase)
    assert np.all(np.isfinite(true[both]))
    assert np.all(np.isnan(phase[t < peaks.times_s[0]])) and np.all(np.isnan(phase[t >= peaks.times_s[-1]]))
    d = np.abs((phase[both] - true[both] + 0.5) % 1.0 - 0.5)
    assert np.median(d) < 1e-3 and d.max() < 0.01


@pytest.mark.parametrize(
    "signal, rate, match_",
    [
        (None, 100.0, "signal_mv is None"),
        (np.zeros(0), 100.0, "empty"),
        (np.zeros((2, 1000)), 100.0, r"shape \(n,\)"),
        (np.r_[np.sin(np.arange(1000.0)), np.nan], 100.0, "NaN"),
        (np.full(1000, 0.4), 100.0, "constant"),
        (1e-4 * np.random.default_rng(0).standard_normal(1000), 100.0, "flat"),
        (np.sin(np.arange(150.0)), 100.0, "at least 2 s"),
        (np.sin(np.arange(1000.0)), 20.0, "rate_hz must be at least"),
        (np.sin(np.arange(1000.0)), "fast", "rate_hz must be a number"),
        ("abc", 100.0, "signal_mv must be numbers"),  # numpy's own ValueError before session 15
        (np.sin(np.arange(1000.0)).astype(complex), 100.0, "complex"),  # its imaginary part was dropped
        # 30 s of noise (a floating electrode): ~3500 "beats" per 30 min before session 16
        (np.random.default_rng(0).normal(0.0, 1.0, 30 * 360), 360.0, "no QRS complexes that stand out of its noise"),
    ],
)
def test_bad_signals_are_refused_clearly(signal, rate, match_):
    with pytest.raises(SignalError, match=match_):
        detect_r_peaks(signal, rate)


def test_bad_options_are_refused_clearly():
    _, ecg = phantom_ecg(1, rate_hz=100.0, heart_rate_hz=1.0, duration_s=5.0)
    with pytest.raises(SignalError, match="polarity"):
        detect_r_peaks(ecg, 100.0, polarity=2)
    with pytest.raises(SignalError, match="refractory_s"):
        detect_r_peaks(ecg, 100.0, refractory_s=0.0)
    with pytest.raises(SignalError, match="start_s"):
        detect_r_peaks(ecg, 100.0, start_s=np.nan)
    # a bare TypeError from float(), or from deep inside, before session 15
    with pytest.raises(SignalError, match="start_s must be a number"):
        detect_r_peaks(ecg, 100.0, start_s=None)
    with pytest.raises(SignalError, match="refractory_s must be a number"):
        detect_r_peaks(ecg, 100.0, refractory_s=None)
    with pytest.raises(SignalError, match="polarity"):
        detect_r_peaks(ecg, 100.0, polarity=np.array([1]))
    assert len(detect_r_peaks(ecg, 100.0, polarity=np.int64(1))) == len(detect_r_peaks(ecg, 100.0, polarity=1))
    assert issubclass(SignalError, ValueError)


def test_cardiac_phase_needs_two_increasing_r_peaks():
    with pytest.raises(SignalError, match="at least two"):
        cardiac_phase([0.5], [1.0])
    with pytest.raises(SignalError, match="strictly increasing"):
        cardiac_phase([0.5], [1.0, 1.0, 2.0])
    with pytest.raises(SignalError, match="NaN"):
        cardiac_phase([0.5], [1.0, np.nan])


increasing_peaks = st.lists(
    st.floats(0.25, 2.0), min_size=1, max_size=30
).flatmap(lambda rr: st.floats(-100.0, 100.0).map(lambda t0: t0 + np.cumsum([0.0, *rr])))


@settings(max_examples=200, deadline=None)
@given(peaks=increasing_peaks, u=st.lists(st.floats(-0.2, 1.2), min_size=1, max_size=50))
def test_cardiac_phase_properties(peaks, u):
    """Phase in [0, 1) inside, NaN outside, 0 at each R-peak, increasing within a beat, = phantom truth."""
    span = peaks[-1] - peaks[0]
    t = np.sort(peaks[0] + np.asarray(u) * span)
    phase = cardiac_phase(t, peaks)
    inside = (t >= peaks[0]) & (t < peaks[-1])
    assert np.all(np.isnan(phase[~inside]))
    assert np.all((phase[inside] >= 0.0) & (phase[inside] < 1.0))
    np.testing.assert_allclose(cardiac_phase(peaks[:-1], peaks), 0.0, atol=1e-12)
    beat = np.searchsorted(peaks, t, side="right")
    for b in np.unique(beat[inside]):
        assert np.all(np.diff(phase[beat == b]) >= 0)
    np.testing.assert_allclose(phase[inside], phase_from_events(t, peaks)[inside], atol=1e-12)
