"""QRS detection (imaging/ecg.py) on real ECG: eight MIT-BIH Arrhythmia Database records.

The records and their reference beats are in ``../shared/ecg/mitdb`` beside the
repository checkout (see its README); the test is skipped when that folder is
missing.  Scoring follows ANSI/AAMI EC57: a detection matches a reference beat
within +-150 ms, one to one; sensitivity, positive predictivity and F1 over the
whole record and from 5:00 on (the learning period left out).

The bar (issue 10): F1 >= 99.5 % over the eight records together, and on each
record at least what neurokit2's default detector reaches on it in the same run
(``nk.ecg_peaks(signal, sampling_rate=fs)``, method "neurokit", on the record as
given to ours), except 108 (large complexes of both polarities, much noise)
where >= 95 % is asked.  (After ``nk.ecg_clean`` neurokit2 does better on 104,
99.78 % against our 99.69 % over the whole record, and worse on the others;
README, accuracy table.)

Timing: a reference annotation at sample ``i`` is at ``i / fs`` s on the
record's clock, the clock of ``detect_r_peaks(..., start_s=0)``; the timing
error of a matched beat is detection time minus annotation time.  The median
|error| over all matched beats must be <= 3 ms (about one sample at 360 Hz);
the annotations mark the major local extremum of the QRS, which is what our
sub-sample refinement places the R-peak on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imaging.ecg import MIN_QRS_CONTRAST, detect_r_peaks

RECORDS = ("100", "102", "104", "105", "106", "108", "116", "119")
TOL_S = 0.150  # EC57 matching window
LATE_S = 300.0  # 5:00: the second score leaves out the learning period
F1_ALL = 0.995
F1_108 = 0.95
MEDIAN_ERROR_S = 3e-3


def _mitdb_dir() -> Path | None:
    repo = Path(__file__).resolve().parents[2]
    # the shared folder beside the checkout (a worktree sits one level deeper)
    for base in (repo.parent, repo.parent.parent):
        folder = base / "shared" / "ecg" / "mitdb"
        if all((folder / f"{r}.npz").is_file() for r in RECORDS):
            return folder
    return None


MITDB = _mitdb_dir()
pytestmark = pytest.mark.skipif(MITDB is None, reason="../shared/ecg/mitdb (MIT-BIH records) not found")


def match_beats(detected_s, reference_s, tol_s=TOL_S):
    """One-to-one matching of two sorted beat lists within ``tol_s``.

    Each reference beat, in time order, takes the nearest still unmatched
    detection within ``tol_s`` (beats are >= 200 ms apart and the window is
    +-150 ms, so at most two detections compete for one beat).

    Returns
    -------
    det_matched : (n_det,) bool
    errors_s : (n_ref,) float, detection minus reference time, NaN if unmatched
    """
    detected_s = np.asarray(detected_s, dtype=float)
    used = np.zeros(detected_s.size, dtype=bool)
    errors = np.full(len(reference_s), np.nan)
    for k, r in enumerate(reference_s):
        i = int(np.searchsorted(detected_s, r))
        best = None
        for c in (i - 1, i, i + 1):
            near = 0 <= c < detected_s.size and not used[c] and abs(detected_s[c] - r) <= tol_s
            if near and (best is None or abs(detected_s[c] - r) < abs(detected_s[best] - r)):
                best = c
        if best is not None:
            used[best] = True
            errors[k] = detected_s[best] - r
    return used, errors


def f1(tp, fp, fn) -> float:
    return 2 * tp / (2 * tp + fp + fn)


def _load(record):
    z = np.load(MITDB / f"{record}.npz")
    fs = float(z["fs_hz"])
    return z["ecg_uv"] / 1000.0, fs, z["r_peak_samples"] / fs


def _scores(detected_s, reference_s):
    """(whole record, from 5:00 on), each (tp, fp, fn, errors of the matched beats (s)).

    One matching over the whole record; the second score counts the reference
    beats and the detections from 5:00 on.
    """
    used, errors = match_beats(detected_s, reference_s)
    out = []
    for t0 in (-np.inf, LATE_S):
        ref_in, det_in = reference_s >= t0, detected_s >= t0
        hit = ref_in & np.isfinite(errors)
        out.append((int(hit.sum()), int((det_in & ~used).sum()), int((ref_in & ~hit).sum()), errors[hit]))
    return tuple(out)


@pytest.fixture(scope="session")
def mitdb_results():
    """Our detections and neurokit2's on every record, computed once per session."""
    nk = pytest.importorskip("neurokit2")
    out = {}
    for record in RECORDS:
        x, fs, ref = _load(record)
        ours = detect_r_peaks(x, fs).times_s
        _, info = nk.ecg_peaks(x, sampling_rate=fs)
        out[record] = (ref, ours, np.asarray(info["ECG_R_Peaks"], dtype=float) / fs)
    return out


def test_f1_over_the_eight_records_and_timing(mitdb_results):
    """F1 >= 99.5 % over all beats of the eight records, whole and from 5:00; median |error| <= 3 ms."""
    whole = np.zeros(3)
    late = np.zeros(3)
    errors = []
    for ref, ours, _ in mitdb_results.values():
        (tp, fp, fn, e), (tp5, fp5, fn5, _) = _scores(ours, ref)
        whole += (tp, fp, fn)
        late += (tp5, fp5, fn5)
        errors.append(e)
    assert f1(*whole) >= F1_ALL, whole
    assert f1(*late) >= F1_ALL, late
    err = np.abs(np.concatenate(errors))
    assert np.median(err) <= MEDIAN_ERROR_S, np.median(err)


@pytest.mark.parametrize("record", RECORDS)
def test_each_record_at_least_neurokit2(mitdb_results, record):
    """Per record, whole and from 5:00: F1 >= neurokit2's default on it (108: >= 95 %)."""
    ref, ours, theirs = mitdb_results[record]
    mine = _scores(ours, ref)
    for part in (0, 1):
        f_ours = f1(*mine[part][:3])
        if record == "108":
            assert f_ours >= F1_108, (part, f_ours)
            continue
        f_nk = f1(*_scores(theirs, ref)[part][:3])
        assert f_ours >= f_nk - 1e-12, (part, f_ours, f_nk)


def test_108_both_polarities_and_no_beats_at_the_edges(mitdb_results):
    """108's large complexes of both polarities: >= 95 % with R-peaks on the right wave
    (median |error| <= 5 ms, where refinement onto the wrong wave gave errors of tens of
    ms); and on every record no beat within 50 ms of either end."""
    ref, ours, _ = mitdb_results["108"]
    (tp, fp, fn, e), _ = _scores(ours, ref)
    assert f1(tp, fp, fn) >= F1_108
    assert np.median(np.abs(e)) <= 5e-3
    for record, (_, det, _) in mitdb_results.items():
        x, fs, _ = _load(record)
        assert det[0] >= 0.05 and det[-1] <= (x.size - 1) / fs - 0.05, record


def test_recovers_after_a_large_transient():
    """A 4 s, 20x-amplitude artefact inserted into record 100: the detector follows
    the beats again within 3 s after it (the Pan-Tompkins threshold used to lock for
    minutes, issue 10)."""
    x, fs, ref = _load("100")
    x = x[: int(120 * fs)].copy()
    ref = ref[ref < 119.5]
    t = np.arange(x.size) / fs
    burst = (t >= 40.0) & (t < 44.0)
    x[burst] += 20.0 * np.sin(2 * np.pi * 7.0 * t[burst])
    det = detect_r_peaks(x, fs).times_s
    used, errors = match_beats(det, ref)
    for part_ref, part_det in ((ref < 40.0, det < 40.0), (ref >= 47.0, det >= 47.0)):
        assert np.all(np.isfinite(errors[part_ref])) and np.all(used[part_det])


@pytest.mark.parametrize("record", ["105", "108"])
def test_every_30_s_of_the_noisiest_records_is_an_ecg(record):
    """The noise check never refuses a real lead: every 30 s window of the two noisiest records (muscle noise,
    motion, large P waves) stands out of its noise by more than MIN_QRS_CONTRAST (measured 6.8 and up over
    all eight records; 30 s of noise reaches 3.9)."""
    x, fs, _ = _load(record)
    n = int(30 * fs)
    contrast = [detect_r_peaks(x[s:s + n], fs).qrs_contrast for s in range(0, x.size - n + 1, n)]
    assert min(contrast) >= 1.3 * MIN_QRS_CONTRAST, min(contrast)


def test_a_clipped_r_is_put_mid_plateau():
    """An amplifier saturating at 1.5 mV flattens the tall beats of record 119 (5.6 % of its samples): their
    R-peak goes to the middle of the clipped run.  Measured: 0.7 % of matched beats more than 20 ms from the
    annotation (0.1 % unclipped, neurokit2 0.1 %); before session 16, 19.3 % (the filtered signal's maximum
    wandered to the plateau's end, 30-44 ms late)."""
    x, fs, ref = _load("119")
    used, errors = match_beats(detect_r_peaks(np.clip(x, -1.5, 1.5), fs).times_s, ref)
    errors = errors[np.isfinite(errors)]
    assert errors.size >= 0.99 * ref.size
    assert np.mean(np.abs(errors) > 0.020) <= 0.02, np.mean(np.abs(errors) > 0.020)


def _with_pauses(record, minutes=10.0, seed=0):
    """The record's first minutes with pauses cut in: every 12-25 beats, 2-4 beats are replaced by copies of
    the record's own baseline between beats (the previous beat's T-P segment), from just after the dropped
    first beat's P wave to after the last one's T wave.  A pause as after a blocked beat or a sinus arrest
    (MIT-BIH 232 and 231 have them), each 2-4 RR intervals long; returns the signal, its rate and the
    remaining reference beats (s)."""
    x, fs, ref = _load(record)
    x = x[: int(minutes * 60 * fs)].copy()
    beats = np.rint(ref * fs).astype(int)
    beats = beats[beats < x.size - int(fs)]
    keep = np.ones(beats.size, bool)
    rng = np.random.default_rng(seed)
    b = 10
    while b < beats.size - 10:
        m = int(rng.integers(2, 5))
        lo, hi = beats[b] - int(0.12 * fs), beats[b + m - 1] + int(0.45 * fs)
        baseline = x[beats[b - 1] + int(0.45 * fs): beats[b] - int(0.22 * fs)]
        if baseline.size >= int(0.1 * fs):
            fill = np.tile(baseline, (hi - lo) // baseline.size + 2)[: hi - lo]
            fill += x[lo - 1] - fill[0]  # continuous at both ends
            fill += np.linspace(0.0, 1.0, hi - lo) * (x[hi] - fill[-1])
            x[lo:hi] = fill
            keep[b: b + m] = False
            b += int(rng.integers(12, 25))
        else:
            b += 15
    return x, fs, beats[keep] / fs


@pytest.mark.parametrize("record", ["100", "102", "106", "116", "119"])
def test_pauses_take_no_p_wave_and_lose_no_beat(record):
    """Pauses of 2-4 beats cut into ten minutes of a record (:func:`_with_pauses`).  The P wave left before
    each pause is no beat: search-back takes only a peak as steep as a QRS; and a pause is no part of the
    rhythm the detector learns.  Measured false / missed beats on 100, 102, 106, 116, 119: 1/0, 1/0, 1/0, 1/0,
    6/0 (neurokit2's default on the same signals 3/1, 1/0, 20/0, 1/0, 47/0); before session 20 53/0, 23/0,
    60/0, 28/1 and 43/44 (after a pause the stretched rhythm made 119's bigeminy PVCs "too early")."""
    x, fs, ref = _with_pauses(record)
    used, errors = match_beats(detect_r_peaks(x, fs).times_s, ref)
    false_beats, missed = int((~used).sum()), int(np.isnan(errors).sum())
    assert missed <= 1, missed
    assert false_beats <= 8, false_beats


def _irregular(record, minutes=10.0, mean_rr_s=0.6, cv=0.3, min_rr_s=0.4):
    """The record's beats at the irregular intervals of atrial fibrillation: each QRS (R +-100 ms) as
    recorded, the rest of every interval (T wave, T-P, P) resampled to a new R-R drawn independently from a
    gamma distribution (mean ``mean_rr_s``, coefficient of variation ``cv``, at least ``min_rr_s``).  None of
    the eight records is in fibrillation (201, 202, 203, 210, 219, 221 and 222 of the database are); returns
    the signal, its rate and the new beats (s)."""
    x, fs, ref = _load(record)
    beats = np.rint(ref * fs).astype(int)
    q = int(0.1 * fs)
    beats = beats[(beats > q) & (beats < x.size - q)]
    rng = np.random.default_rng(int(record))
    parts, new = [x[: beats[0] + q]], [beats[0]]
    for a, b in zip(beats[:-1], beats[1:]):
        rr_s = max(min_rr_s, rng.gamma(1.0 / cv**2, mean_rr_s * cv**2))
        gap, n = x[a + q: b - q], int(round(rr_s * fs)) - 2 * q
        parts.append(np.interp(np.linspace(0.0, gap.size - 1.0, n), np.arange(gap.size), gap))
        new.append(new[-1] + n + 2 * q)
        parts.append(x[b - q: b + q])
        if new[-1] > minutes * 60 * fs:
            break
    return np.concatenate(parts), fs, np.asarray(new) / fs


@pytest.mark.parametrize("record", RECORDS)
def test_an_irregular_rhythm_loses_no_beat(record):
    """Ten minutes of each record re-timed as atrial fibrillation (:func:`_irregular`: 100 beats/min, R-R
    0.4-1.6 s, coefficient of variation 0.3).  Pan-Tompkins' rules learn a regular R-R: an early beat, a
    long gap and the search-back are all read against it.  Measured F1 100 / 99.95 / 99.30 / 100 / 99.95 /
    99.80 / 100 / 99.95 % on 100, 102, 104, 105, 106, 108, 116, 119 (neurokit2's default on the same signals
    99.90 / 100 / 97.09 / 99.90 / 99.85 / 96.11 / 100 / 99.90 %)."""
    x, fs, ref = _irregular(record)
    detected = detect_r_peaks(x, fs).times_s
    used, errors = match_beats(detected, ref)
    tp = int(np.isfinite(errors).sum())
    assert f1(tp, int((~used).sum()), ref.size - tp) >= (0.99 if record == "104" else 0.995)


def _qrs_shape(x, b, half):
    """The QRS window ``x[b - half : b + half + 1]`` less the straight line between its ends (zero at both)."""
    q = x[b - half: b + half + 1]
    return q - np.linspace(q[0], q[-1], q.size)


def _stretched(q, before, after):
    """``q`` (its middle sample the R) resampled ``before`` times longer left of the R, ``after`` right of it;
    returns the new shape and the R's index in it."""
    c = q.size // 2
    left = np.interp(np.linspace(0.0, c, int(round(c * before)) + 1), np.arange(c + 1), q[: c + 1])
    right = np.interp(np.linspace(c, q.size - 1.0, int(round(c * after)) + 1), np.arange(c, q.size), q[c:])
    return np.concatenate([left, right[1:]]), left.size - 1


def _qrs_beats(x, fs, ref, half):
    """Reference beats (samples) with a whole QRS window (R +- half) inside the record, not overlapping."""
    beats = np.rint(ref * fs).astype(int)
    beats = beats[(beats > 3 * half) & (beats < x.size - 3 * half)]
    return beats[np.concatenate([[True], np.diff(beats) > 2 * half + 1])]


#: Bundle branch block shapes of :func:`_bundle_branch_block`: (stretch before the R, after it, echo delay (s)).
BBB_SHAPES = {"rbbb": (1.0, 2.5, 0.0), "notch": (1.2, 1.2, 0.045), "lbbb": (2.0, 1.5, 0.0),
              "x1.5": (1.5, 1.5, 0.0), "x1.8": (1.8, 1.8, 0.0), "x2.2": (2.2, 2.2, 0.0)}


def _bundle_branch_block(record, shape):
    """The whole record with every QRS widened as in bundle branch block, the rest of each beat as recorded
    (each R-R longer by the widening; the reference beats moved with it).  Each QRS window, R +- 60 ms, less the
    line between its ends, is stretched (:data:`BBB_SHAPES`): "rbbb", its part after the R 2.5 times (a broad
    slurred terminal part, as in right bundle branch block: QRS 80 -> 140 ms); "lbbb", before the R 2 times and
    after it 1.5 (a slurred upstroke); "x1.5" .. "x2.2" uniformly; "notch", 1.2 times and added to itself 45 ms
    later (0.75 and 0.65 of it: a notched RSR' complex, 130-140 ms).  MIT-BIH 109, 111, 207, 214 (left) and
    118, 124, 212, 231 (right) are in bundle branch block; none of the eight is.  Returns the signal, its rate
    and the beats (s)."""
    x, fs, ref = _load(record)
    half = int(round(0.060 * fs))
    beats = _qrs_beats(x, fs, ref, half)
    parts, new, at = [x[: beats[0] - half]], [], beats[0] - half
    for i, b in enumerate(beats):
        before, after, echo_s = BBB_SHAPES[shape]
        wide, r = _stretched(_qrs_shape(x, b, half), before, after)
        if echo_s:
            lag = int(round(echo_s * fs))
            wide = np.concatenate([0.75 * wide, np.zeros(lag)]) + np.concatenate([np.zeros(lag), 0.65 * wide])
        parts.append(wide + np.linspace(x[b - half], x[b + half], wide.size))
        new.append(at + r)
        rest = x[b + half + 1: beats[i + 1] - half if i + 1 < beats.size else x.size]
        parts.append(rest)
        at += wide.size + rest.size
    return np.concatenate(parts), fs, np.asarray(new) / fs


@pytest.mark.parametrize("shape", ["notch", "rbbb"])
def test_bundle_branch_block_loses_no_beat(shape):
    """Record 106 with every QRS widened as in bundle branch block (:func:`_bundle_branch_block`); its premature
    ventricular beats (a fifth of its beats, often in runs), wide already, become 150-250 ms wide, of low QRS-band
    energy.  Measured F1 99.78 / 99.90 % (missed / false 9 / 0 and 3 / 1) for notch / rbbb; neurokit2's default
    on the same signals 99.36 / 99.31 % (14 / 12, 10 / 18); before the standing-out rule ran as the peaks come
    (``qrs_classify._Classifier._standing_out_qrs``) 98.93 / 99.15 % (43 / 0, 33 / 1).  The eight records so
    widened: README, accuracy table."""
    x, fs, ref = _bundle_branch_block("106", shape)
    used, errors = match_beats(detect_r_peaks(x, fs).times_s, ref)
    tp = int(np.isfinite(errors).sum())
    assert f1(tp, int((~used).sum()), ref.size - tp) >= 0.995
    assert ref.size - tp <= 15, ref.size - tp


def _premature(record, every=2, width_s=0.150, size=1.0, coupling=0.7, minutes=10.0, run=1):
    """The record's first minutes with every ``every``-th beat (and the ``run - 1`` after it: couplets) made a
    wide premature ventricular one: its QRS window (R +- 60 ms, less the line between its ends) stretched to
    ``width_s`` (of a 90 ms QRS), times ``-size`` (the opposite polarity), ``coupling`` of the R-R after the
    beat before it, with a broad T wave
    opposite to its largest deflection (0.35 of it, 70 ms, ~300 ms after it); the next beat keeps its time
    (a full compensatory pause).  Before it the record goes on as recorded (cut where it starts); after it the
    replaced beat's ST-T, T-P and the next P wave are resampled into the pause.  MIT-BIH 200, 203, 208, 233 have
    such beats by the thousand (208: a tenth to a quarter of the narrow beats' QRS-band energy); returns the
    signal, its rate and the beats (s)."""
    x, fs, ref = _load(record)
    x = x[: int(minutes * 60 * fs)]
    half = int(round(0.060 * fs))
    beats = _qrs_beats(x, fs, ref[ref < minutes * 60 - 0.5], half)
    factor = width_s / 0.090
    # (time, source beat, premature?): a premature beat early after the beat before it; the next narrow one as
    # long after the last narrow one as in the record
    plan, narrow = [(beats[0], 0, False)], (beats[0], 0)
    for i in range(1, beats.size):
        if i % every < run and i >= every and i + run - i % every < beats.size:
            plan.append((plan[-1][0] + int(round(coupling * (beats[i] - beats[i - 1]))), i, True))
        else:
            plan.append((narrow[0] + beats[i] - beats[narrow[1]], i, False))
            narrow = plan[-1][:2]
    parts, times, at = [x[: beats[0] - half]], [], beats[0] - half
    t_sd, t_at = int(0.07 * fs), int(0.28 * fs + 0.5 * half * factor)
    t_waves = []
    for k, (t, i, early) in enumerate(plan):
        b = beats[i]
        if early:
            shape, r = _stretched(_qrs_shape(x, b, half), factor, factor)
            shape = -size * shape
        else:
            shape, r = x[b - half: b + half + 1], half
        if k:
            j = beats[plan[k - 1][1]] + half + 1  # after the last complex: as recorded, or resampled into the pause
            n = t - r - at
            gap = x[j: j + n] if early else np.interp(np.linspace(j, b - half - 1, n), np.arange(x.size), x)
            parts.append(gap)
            at += n
        if early:
            t_waves.append((at + r, -0.35 * shape[np.argmax(np.abs(shape))]))
            shape = shape + np.linspace(parts[-1][-1], x[b + half + 1], shape.size)
        parts.append(shape)
        times.append(at + r)
        at += shape.size
    parts.append(x[beats[plan[-1][1]] + half + 1:])
    y = np.concatenate(parts)
    n = np.arange(y.size)
    for r, height in t_waves:
        lo, hi = max(0, r + t_at - 4 * t_sd), min(y.size, r + t_at + 4 * t_sd)
        y[lo:hi] += height * np.exp(-0.5 * ((n[lo:hi] - r - t_at) / t_sd) ** 2)
    return y, fs, np.asarray(times) / fs


@pytest.mark.parametrize("width_s, size", [(0.150, 1.0), (0.120, 0.5), (0.120, 2.0)])
def test_wide_premature_beats_in_a_bigeminy_are_found(width_s, size):
    """Ten minutes of each record with every second beat a wide premature one (:func:`_premature`: 150 ms and the
    size of the record's QRS; 120 ms and half of it; 120 ms and twice it; inverted).  One class of beats has far
    less QRS-band energy than the other (the wide ones; in the last, the narrow ones).  Measured F1 over the
    eight records 99.42 / 98.98 / 99.59 %, the worst record 97.42 / 95.57 / 98.79 % (104, paced: 33 / 47 / 10
    false beats); neurokit2's default on the same signals 98.02 / 95.85 / 99.44 %, worst 95.19 / 92.26 / 98.45 %
    (104; with twice the size it beats us on 100, 102, 105, 116, 119 by 1-7 beats); before the standing-out rule
    ran as the peaks come 95.05 / 89.98 / 95.67 %, worst 67.51 (105) / 66.67 (105) / 70.70 % (100): the weaker
    class was never taken, the regular R-R became twice the true one, so the search-back never ran, and the
    early-beat rule rejected the weaker beats above threshold 1."""
    tp = fp = fn = 0
    for record in RECORDS:
        x, fs, ref = _premature(record, width_s=width_s, size=size)
        used, errors = match_beats(detect_r_peaks(x, fs).times_s, ref)
        hit = int(np.isfinite(errors).sum())
        assert f1(hit, int((~used).sum()), ref.size - hit) >= 0.95, record
        tp, fp, fn = tp + hit, fp + int((~used).sum()), fn + ref.size - hit
    assert f1(tp, fp, fn) >= 0.985, (tp, fp, fn)


@pytest.mark.parametrize("where", ["mid", "start"])
def test_a_lead_gone_to_noise_gives_no_beats(where):
    """Five minutes of each record with a stretch of 50 uV noise and no ECG: 20 s from 1:00 (an electrode
    floating) or the first 10 s (put on late).  Measured false / missed beats over the eight records: mid
    33 / 2 (0 on five records; 104: 7, 106: 2, 108: 24), start 13 / 1; before session 20, 187 / 3 and 131 / 2
    (about a beat a second in the noise: once no beat came for the search-back limit the threshold decayed
    to the noise, and the first noise peak taken became the signal level; at the start the levels were
    learnt from the first 8 s alone).  A peak after the rhythm is lost must stand out of the peaks around
    it, and the first levels are medians over the first minute."""
    false_beats = missed = 0
    for record in RECORDS:
        x, fs, ref = _load(record)
        n = int(300 * fs)
        x, ref = x[:n].copy(), ref[ref < 299.9]
        a, b = (int(60 * fs), int(80 * fs)) if where == "mid" else (0, int(10 * fs))
        x[a:b] = np.median(x) + np.random.default_rng(0).normal(0.0, 0.05, b - a)
        ref = ref[(ref < a / fs - 0.05) | (ref > b / fs + 0.05)]
        used, errors = match_beats(detect_r_peaks(x, fs).times_s, ref)
        false_beats += int((~used).sum())
        missed += int(np.isnan(errors).sum())
    assert false_beats <= (50 if where == "mid" else 20) and missed <= 5, (false_beats, missed)


def test_pacing_spikes_between_beats_are_no_beats():
    """A 5 mV one-sample spike halfway between every two beats (asynchronous pacing, recorded unfiltered),
    five minutes of each record: F1 >= 0.98 on every record (measured 0.988-1.000; before session 20's 4 ms
    running median ahead of the detection 0.43 / 0.63 / 0.63 / 0.74 on 108 / 102 / 104 / 106, neurokit2
    0.64 on 108)."""
    for record in RECORDS:
        x, fs, ref = _load(record)
        x, ref = x[: int(300 * fs)].copy(), ref[ref < 299.9]
        for mid in 0.5 * (ref[:-1] + ref[1:]):
            x[int(mid * fs)] += 5.0
        used, errors = match_beats(detect_r_peaks(x, fs).times_s, ref)
        tp = int(np.isfinite(errors).sum())
        assert f1(tp, int((~used).sum()), ref.size - tp) >= 0.98, record


def test_tall_t_waves_are_no_beats():
    """MIT-BIH 119 with every T wave (180-450 ms after each beat) 2.5 times as large about its baseline: 0.65 of
    the QRS's size, as peaked T waves or leads V2-V3 show them.  A tall T wave is as steep, in proportion, as a
    QRS: when wide premature beats came to be taken as the peaks come (session 29) 150 of them were beats, 230-300
    ms after each true one; none is now (that rule stays out of the T-wave window), nor before it.  Over the
    eight records so altered: 245 false beats, F1 98.93 % (before the rule 241, 98.93 %; with it in the T-wave
    window 407, 98.47 %)."""
    x, fs, ref = _load("119")
    x = x.copy()
    for s in np.rint(ref * fs).astype(int):
        lo, hi = s + int(0.18 * fs), s + int(0.45 * fs)
        if hi < x.size:
            base = np.linspace(x[lo], x[hi], hi - lo)
            x[lo:hi] = base + 2.5 * (x[lo:hi] - base)
    used, errors = match_beats(detect_r_peaks(x, fs).times_s, ref)
    assert int((~used).sum()) <= 3 and int(np.isnan(errors).sum()) <= 3
