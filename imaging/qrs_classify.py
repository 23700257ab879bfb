"""Pan-Tompkins' sequential classification of energy peaks into QRS and noise.

:func:`imaging.ecg.detect_r_peaks` filters the ECG and finds the peaks of its
integrated energy; the classifier here walks those peaks in time order with
adaptive signal and noise levels, rejects T waves and searches back over gaps
(steps 3 to 5 of the detector described in :mod:`imaging.ecg`).
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right

import numpy as np

#: A peak this close (s) after a QRS is tested for being a T wave.
T_WAVE_WINDOW_S = 0.360
#: Search back when no QRS came for this multiple of the regular RR interval.
SEARCH_BACK_FACTOR = 1.66
#: The signal level is the median energy of this many last QRS complexes.
SPK_MEMORY = 8
#: Threshold = noise level + this fraction of (signal level - noise level).
THRESHOLD_FRACTION = 0.25
#: Half-life (s) of the signal level once no QRS came for the search-back limit.
DECAY_HALF_LIFE_S = 1.0
#: The decayed signal level stays at least this multiple of the noise level.
NOISE_FLOOR_RATIO = 4.0
#: A peak earlier than this fraction of the regular RR after the last QRS ...
EARLY_FRACTION = 0.55
#: ... is noise unless its energy is at least this fraction of the QRS level.
EARLY_ENERGY_RATIO = 0.7
#: Within this fraction of the regular RR (at most MAX_REFRACTORY_S, at least
#: the refractory period) only the larger of two peaks is a QRS (a P wave
#: before it, an artefact after it).
REFRACTORY_RR_FRACTION = 0.6
MAX_REFRACTORY_S = 0.25
#: Levels are learnt afresh from a gap this long (s) past the search-back limit.
RELEARN_AFTER_S = 1.0
#: A peak found by search-back is a QRS only if its steepest slope is at least this fraction of the
#: median of the last :data:`SPK_MEMORY` QRS complexes' (a missed QRS is still steep; a P wave
#: before a pause or a blocked beat is not: in 10 min of MIT-BIH records 100, 102, 106 and 116 with
#: pauses of 2-4 beats cut in, 17-42 P waves each were taken for beats, 1-2 with the rule; the
#: eight records whole change by 4 beats of 116).
SEARCH_BACK_SLOPE_RATIO = 0.2
#: A peak that stands out of its neighbours (NOISE_FLOOR_RATIO x their median) and is at least QRS_SIZE_RATIO as
#: large as the last QRS complexes is a beat above this fraction of threshold 1, half the search-back's usual half:
#: a wide premature beat's QRS-band energy is a tenth to a quarter of the narrow beats' (MIT-BIH 208).  It is so
#: in the search-back's gap and as the peaks come, below threshold 1 or early (:meth:`_Classifier._standing_out_qrs`).
SEARCH_BACK_STANDING_OUT = 0.25
#: ... at least this fraction as large as the last QRS complexes (median peak to peak, 0.5-40 Hz, within 75 ms): a
#: P wave is not (a sharp blocked one of 0.3 of the R, ``test_blocked_p_waves_in_pauses_are_no_beats``); the narrow
#: beats between premature ones twice their size are (0.41-0.53 of them: MIT-BIH 100 with every second beat so
#: made lost its narrow beats for its first minute at 0.5).
QRS_SIZE_RATIO = 0.4
#: Peaks within this many seconds either side of a candidate are its neighbourhood (:meth:`_Classifier.stands_out`).
STAND_OUT_S = 1.5
#: This many pauses in a row, as steady as a rhythm, are a slower rhythm, not pauses.
SLOWED_BEATS = 8


def _median(values: list[float]) -> float:
    s = sorted(values)
    m = len(s) // 2
    return s[m] if len(s) % 2 else 0.5 * (s[m - 1] + s[m])


def _steady_mean(intervals: list[int]) -> float | None:
    """Their mean if every one lies within 0.92-1.16 of it (Pan-Tompkins' regular R-R range), else None."""
    mean = sum(intervals) / len(intervals)
    return mean if 0.92 * mean <= min(intervals) and max(intervals) <= 1.16 * mean else None


class _Classifier:
    """Sequential adaptive-threshold classification of energy peaks.

    Pan-Tompkins' rules, with the signal level taken as the median of the last
    :data:`SPK_MEMORY` QRS energies instead of a running average, so that one
    large transient cannot lift the threshold above the beats that follow, and a
    search-back that repeats until the gap before the current peak is closed and
    takes only a peak as steep as a QRS.  A pause (an interval past the
    search-back limit: a sinus arrest, blocked beats) is no part of the regular
    rhythm the limits are learnt from: averaged in, it stretched the regular RR
    and the early-beat rule took a bigeminy's PVCs for noise for half a minute
    (record 119 with pauses cut in: 41 beats missed, none now).  Once no beat
    came for the search-back limit, a peak is a QRS only if it stands out of
    the peaks around it (:meth:`stands_out`), as a QRS does among T and P
    waves and noise: with the threshold decayed, a lead gone to noise (a
    floating electrode) gave about a beat a second, and the first noise peak
    taken reset the signal level to the noise's.  A peak that stands out of
    the peaks around it and is as large and as steep as a QRS is one down to a
    quarter of threshold 1, early or not, as the peaks come
    (:meth:`_standing_out_qrs`), not only in the search-back's gaps: a class of
    beats much weaker in the QRS band than the others (wide premature beats) is
    not lost for good once the rhythm is learnt without it.
    """

    def __init__(self, peaks, values, slopes, heights, rate: float, refractory: int):
        self.peaks = peaks.tolist()
        self.values = values.tolist()
        self.slopes = slopes.tolist()
        self.heights = heights.tolist()
        self.rate, self.refractory = rate, refractory
        self.t_window = T_WAVE_WINDOW_S * rate

    def run(self, spk0: float, npk0: float) -> list[int]:
        peaks, values, slopes = self.peaks, self.values, self.slopes
        self.recent = [spk0]  # energies of the last accepted QRS complexes
        self.steep: list[float] = []  # their steepest slopes
        self.tall: list[float] = []  # their sizes
        self.regular: list[int] = []  # positions in the RR list of the intervals that are no pause
        self.regular_rr: list[int] = []  # ... and those intervals, samples
        self.spk = spk0  # their median: the signal level
        self.npk = npk0
        self.limit = SEARCH_BACK_FACTOR * self.rate  # 60 bpm until two intervals are known
        self.dead = self.refractory
        qrs: list[int] = []  # indices into peaks
        rr: list[int] = []  # samples
        for j in range(len(peaks)):
            p, v = peaks[j], values[j]
            # search back in the gap before this peak, as often as beats are missing
            tried_relearning = False
            while qrs and p - peaks[qrs[-1]] > self.limit:
                found = self._search_back(qrs[-1], j)
                if found is None:
                    if tried_relearning or p - peaks[qrs[-1]] < self.limit + RELEARN_AFTER_S * self.rate:
                        break
                    tried_relearning = True
                    if self._relearn(qrs[-1], j):
                        continue
                    break
                self._accept(qrs, rr, found)
            gap = p - peaks[qrs[-1]] if qrs else 0  # samples since the last QRS
            th1 = self.threshold(gap)
            if qrs and gap < self.dead:
                if v > th1 and v > values[qrs[-1]]:  # the larger of two close peaks is the QRS
                    self._retract(qrs, rr)
                    self._accept(qrs, rr, j)
                continue
            if v > th1 and qrs and gap > self.limit and not self.stands_out(j, NOISE_FLOOR_RATIO):
                self.npk = 0.125 * v + 0.875 * self.npk  # the rhythm lost: noise unless it stands out
                continue
            if v > th1:
                if qrs and gap < EARLY_FRACTION * self.limit / SEARCH_BACK_FACTOR and v < (
                    EARLY_ENERGY_RATIO * self.spk
                ) and not self._standing_out_qrs(j, qrs[-1], th1):
                    self.npk = 0.125 * v + 0.875 * self.npk  # noise: too early for a weak beat
                    continue
                if qrs and self._t_wave(j, qrs[-1]):
                    self.npk = 0.125 * v + 0.875 * self.npk
                    continue
                if qrs and gap < self.t_window:
                    last = qrs[-1]
                    if slopes[last] < 0.5 * slopes[j] or (
                        values[last] < 0.5 * v and slopes[last] < 0.85 * slopes[j]
                    ):
                        self._retract(qrs, rr)  # the last one was a P wave before this QRS
                self._accept(qrs, rr, j)
            elif qrs and v > SEARCH_BACK_STANDING_OUT * th1 and self._standing_out_qrs(j, qrs[-1], th1):
                self._accept(qrs, rr, j)  # below threshold 1, but a QRS among its neighbours
            else:
                self.npk = 0.125 * v + 0.875 * self.npk
        self.rr = rr
        return qrs

    def stands_out(self, j: int, ratio: float) -> bool:
        """Whether peak ``j`` is ``ratio`` times the median energy of the other peaks within STAND_OUT_S of it."""
        reach = STAND_OUT_S * self.rate
        lo = bisect_left(self.peaks, self.peaks[j] - reach)
        hi = bisect_right(self.peaks, self.peaks[j] + reach)
        others = self.values[lo:j] + self.values[j + 1:hi]
        return not others or self.values[j] >= ratio * _median(others)

    def threshold(self, gap: float) -> float:
        """Threshold 1 a peak ``gap`` samples after the last QRS must pass.

        Past the search-back limit the signal level decays (half-life
        DECAY_HALF_LIFE_S), down to NOISE_FLOOR_RATIO x the noise level, so that a
        lead whose QRS complexes shrank (after a transient, a lead change) is
        followed again within seconds.
        """
        spk = self.spk
        over = gap - self.limit
        if over > 0:
            spk = max(spk * 0.5 ** (over / (DECAY_HALF_LIFE_S * self.rate)), NOISE_FLOOR_RATIO * self.npk)
        return self.npk + THRESHOLD_FRACTION * (spk - self.npk)

    def _relearn(self, last: int, j: int) -> bool:
        """Learn the levels afresh from the peaks of a long gap (last, j) without a QRS.

        After a large transient both levels can sit far above the beats that
        follow.  If the largest peak of the gap stands out from the others
        (NOISE_FLOOR_RATIO x their median, as a QRS does among T waves and
        noise), it becomes the signal level and their median the noise level.
        A gap of similar peaks (a flat or disconnected lead) teaches nothing.
        """
        gap = self.values[last + 1 : j]
        if len(gap) < 2:
            return False
        top, typical = max(gap), _median(gap)
        if top < NOISE_FLOOR_RATIO * typical or top >= self.spk:
            return False
        self.recent = [top]
        self.spk = top
        self.npk = min(self.npk, typical)
        return True

    def _search_back(self, last: int, j: int, end: float | None = None) -> int | None:
        """The largest peak in the gap (last, j) above half its threshold 1 (a quarter when it stands out of its
        neighbours and is as large as a QRS, :meth:`_standing_out`: a wide premature beat's low QRS-band energy),
        as steep as a QRS and no T wave; ``end`` (a sample) instead of peak ``j`` after the last detection."""
        peaks, values, slopes = self.peaks, self.values, self.slopes
        lo_p, hi_p = peaks[last] + self.refractory, (peaks[j] - self.refractory) if end is None else end
        best, best_v = None, 0.0
        steep = SEARCH_BACK_SLOPE_RATIO * _median(self.steep) if self.steep else 0.0
        for k in range(last + 1, j):
            if lo_p <= peaks[k] <= hi_p and values[k] > best_v and slopes[k] >= steep and not self._t_wave(k, last):
                threshold = self.threshold(peaks[k] - peaks[last])
                if values[k] > 0.5 * threshold or self._standing_out(k, threshold):
                    best, best_v = k, values[k]
        return best

    def _standing_out(self, k: int, threshold: float) -> bool:
        """Whether peak ``k`` is above :data:`SEARCH_BACK_STANDING_OUT` x ``threshold``, at least
        :data:`QRS_SIZE_RATIO` as large as the last QRS complexes and stands out of the peaks around it."""
        return (self.values[k] > SEARCH_BACK_STANDING_OUT * threshold
                and self.heights[k] >= QRS_SIZE_RATIO * _median(self.tall) and self.stands_out(k, NOISE_FLOOR_RATIO))

    def _standing_out_qrs(self, j: int, last: int, th1: float) -> bool:
        """Whether peak ``j``, below threshold 1 ``th1`` or early, is a QRS all the same, as the peaks come:
        it passes the search-back's test for a wide premature beat (:meth:`_standing_out`), is as steep as a QRS
        (:data:`SEARCH_BACK_SLOPE_RATIO`) and lies past the T-wave window after the QRS ``last``.

        Nothing within that window, steep or not (:meth:`_t_wave` lets a steep peak through): a T wave 0.65 of the QRS's size (peaked T waves,
        leads V2-V3) is proportionally steeper and passed the slope test: MIT-BIH 119 with its T waves 2.5 times
        as large gave 150 false beats, 230-300 ms after each true one (none before the rule; session 29's review).

        Without it, a class of beats whose QRS-band energy is below threshold 1 learnt from the others (wide
        premature beats in a bigeminy; narrow beats between premature ones of twice their size) was never taken:
        the regular R-R became the interval between the beats taken, twice the true one, so the search-back never
        ran, and the early-beat rule rejected those above threshold 1 (ten minutes of the eight MIT-BIH records
        with every second beat made a wide premature one, 120-150 ms, half to twice the QRS's size: F1 90.0-95.7 %
        over the eight, 67 % on 105, where neurokit2 reaches 95.9-99.4 %; now 99.0-99.6 %:
        ``tests/imaging/test_ecg_mitdb.py::test_wide_premature_beats_in_a_bigeminy_are_found``).
        """
        if self.peaks[j] - self.peaks[last] < self.t_window or not self._standing_out(j, th1):
            return False  # none in the T wave's window: a tall T wave is as steep as a QRS (below)
        return not self.steep or self.slopes[j] >= SEARCH_BACK_SLOPE_RATIO * _median(self.steep)

    def _t_wave(self, k: int, last: int) -> bool:
        """Whether peak ``k`` is a T wave after the QRS ``last``: within the T-wave window and not half as steep."""
        return self.peaks[k] - self.peaks[last] < self.t_window and self.slopes[k] < 0.5 * self.slopes[last]

    def _retract(self, qrs, rr) -> None:
        """Take back the last QRS (a P or T wave, as the steeper complex after it shows)."""
        j = qrs.pop()
        if rr:
            rr.pop()
            if self.regular and self.regular[-1] == len(rr):  # the interval taken back was no pause
                self.regular.pop()
                self.regular_rr.pop()
        if len(self.recent) > 1 and self.recent[-1] == self.values[j]:
            self.recent.pop()
            self.spk = _median(self.recent)
        if self.steep and self.steep[-1] == self.slopes[j]:
            self.steep.pop()
        self.npk = 0.125 * self.values[j] + 0.875 * self.npk
        self._update_limits(rr)

    def _accept(self, qrs, rr, j) -> None:
        if qrs:
            gap = self.peaks[j] - self.peaks[qrs[-1]]
            if gap > self.limit:  # found after the level decayed: start learning it afresh
                self.recent = []
            rr.append(gap)
            if gap <= self.limit:  # no pause
                self.regular.append(len(rr) - 1)
                self.regular_rr.append(gap)
        qrs.append(j)
        self._update_limits(rr)
        self.recent.append(self.values[j])
        self.steep.append(self.slopes[j])
        self.tall.append(self.heights[j])
        del self.recent[:-SPK_MEMORY], self.steep[:-SPK_MEMORY], self.tall[:-SPK_MEMORY]
        self.spk = _median(self.recent)

    def _update_limits(self, rr) -> None:
        self.limit = self._rr_limit(rr)
        regular_rr = self.limit / SEARCH_BACK_FACTOR
        self.dead = max(self.refractory, min(MAX_REFRACTORY_S * self.rate, REFRACTORY_RR_FRACTION * regular_rr))

    def _rr_limit(self, rr_all) -> float:
        """1.66 x the regular RR average (Pan-Tompkins RR AVERAGE2), samples: of the last 64 intervals, pauses
        left out; but :data:`SLOWED_BEATS` pauses in a row as steady as a rhythm are a slower rhythm, and theirs."""
        positions = self.regular
        last = rr_all[-SLOWED_BEATS:]
        if len(last) == SLOWED_BEATS and (not positions or positions[-1] < len(rr_all) - SLOWED_BEATS):
            slowed = _steady_mean(last)  # the last ones all pauses: as steady as a rhythm, the rhythm slowed
            if slowed is not None:
                return SEARCH_BACK_FACTOR * slowed
        first = max(bisect_left(positions, len(rr_all) - 64), len(positions) - 32)  # the last 32 of the last 64
        if len(positions) - first < 2:
            return SEARCH_BACK_FACTOR * self.rate  # 60 bpm until two intervals are known
        recent = self.regular_rr[max(first, len(positions) - 8):]
        steady = _steady_mean(recent)
        if steady is not None:
            return SEARCH_BACK_FACTOR * steady  # the last 8 are all in the range: theirs is the average below
        avg1 = sum(recent) / len(recent)
        lo, hi = 0.92 * avg1, 1.16 * avg1
        regular = []
        for r in reversed(self.regular_rr[first:]):
            if lo <= r <= hi:
                regular.append(r)
                if len(regular) == 8:
                    break
        avg = sum(regular) / len(regular) if regular else avg1
        return SEARCH_BACK_FACTOR * avg

    def best_in(self, lo_p: float, hi_p: float, threshold: float) -> int | None:
        """The largest peak above ``threshold`` with position in [lo_p, hi_p]."""
        return self._best(0, len(self.peaks), lo_p, hi_p, threshold)

    def _best(self, lo_j, hi_j, lo_p, hi_p, threshold) -> int | None:
        lo_j = max(lo_j, bisect_left(self.peaks, lo_p))
        hi_j = min(hi_j, bisect_right(self.peaks, hi_p))
        best, best_v = None, threshold
        for k in range(lo_j, hi_j):
            if self.values[k] > best_v:
                best, best_v = k, self.values[k]
        return best


def _search_edges(clf: _Classifier, qrs: list[int], n: int) -> list[int]:
    """Search back in the gaps before the first and after the last detection."""
    qrs = sorted(qrs)
    peaks = clf.peaks
    rr = np.diff([peaks[j] for j in qrs])
    limit = SEARCH_BACK_FACTOR * (float(np.median(rr)) if rr.size else clf.rate)
    while peaks[qrs[0]] > limit:
        found = clf.best_in(0, peaks[qrs[0]] - clf.refractory, 0.5 * clf.threshold(0))
        if found is None:
            break
        qrs.insert(0, found)
    while n - 1 - peaks[qrs[-1]] > limit:  # as within the record: the last beat's T wave is none (it was)
        found = clf._search_back(qrs[-1], len(peaks), end=n - 1)
        if found is None:
            break
        qrs.append(found)
    return qrs
