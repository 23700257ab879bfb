"""phi_R* estimators on synthetic evidence whose answer is known: the shape
estimator and its bootstrap interval, the traced staples' fit over the breath,
and the paper's eq. 10 with its fiducial bootstrap."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from registration.temporal import (
    TemporalError,
    estimate_phase,
    fiducial_curve,
    paper_phase,
)

PHASES = np.linspace(0.0, 1.0, 101)


def _wrap(d):
    return (np.asarray(d) + 0.5) % 1.0 - 0.5


def _identity_sweep(m):
    return np.broadcast_to(np.eye(4), (m, 4, 4)).copy()


def _distances(rng, phase_true, *, n=60, noise_mm=0.2, signal_mm=2.0):
    """Per-point distances after ICP: noise, plus a misfit that grows away from phase_true."""
    eps = rng.standard_normal((1, n))  # each point's own (phase-independent) error
    a = rng.uniform(0.0, signal_mm, (1, n))
    jitter = 0.05 * rng.standard_normal((PHASES.size, n))  # ICP's small phase-to-phase noise
    misfit = a * np.sin(np.pi * _wrap(PHASES - phase_true))[:, None]
    return np.sqrt((noise_mm * (eps + jitter)) ** 2 + misfit**2)


def test_shape_estimate_recovers_the_phase_and_its_interval_covers_it():
    rng = np.random.default_rng(1)
    vertices = rng.normal(0, 40, (500, 3))
    for phase_true in (0.05, 0.62, 0.97):
        est = estimate_phase(PHASES, _distances(rng, phase_true), _identity_sweep(101), vertices)
        # the misfit's minimum is exactly at the truth; 0.02 allows for the 0.05 mm jitter
        assert abs(_wrap(est.respiration_phase - phase_true)) <= 0.02
        assert est.contains(phase_true) and est.decided
        assert est.width < 0.15
        assert est.interval_offsets[0] <= 0 <= est.interval_offsets[1]
        assert est.transform_mm == 0.0 and est.transform_deg == 0.0  # every phase has the same T
        assert est.evidence == ("heart",) and est.cost.min() == 0.0


def test_flat_evidence_is_undecided_and_a_stated_breath_hold_decides():
    rng = np.random.default_rng(2)
    d = 0.2 * np.abs(rng.standard_normal((101, 60)))  # no phase carries more evidence than another
    vertices = rng.normal(0, 40, (200, 3))
    est = estimate_phase(PHASES, d, _identity_sweep(101), vertices)
    assert not est.decided and est.width > 0.3
    assert "cannot decide" in est.summary()
    held = estimate_phase(PHASES, d, _identity_sweep(101), vertices, breath_hold_phase=0.4, breath_hold_sd=0.02)
    # the prior (sd 0.02) against the flat term's chance wiggles (a few chi-square units)
    assert held.decided and held.contains(0.4) and abs(_wrap(held.respiration_phase - 0.4)) <= 0.1
    assert "breath_hold" in held.evidence


def test_transform_uncertainty_is_the_spread_of_T_over_the_interval():
    rng = np.random.default_rng(3)
    Ts = _identity_sweep(101)
    Ts[:, 2, 3] = 10.0 * np.sin(2 * np.pi * PHASES)  # the registration moves 10 mm over the breath
    vertices = rng.normal(0, 40, (300, 3))
    est = estimate_phase(PHASES, _distances(rng, 0.3, signal_mm=0.6), Ts, vertices)
    inside = (_wrap(PHASES - est.respiration_phase) >= est.interval_offsets[0] - 1e-9) & (
        _wrap(PHASES - est.respiration_phase) <= est.interval_offsets[1] + 1e-9)
    z = Ts[inside, 2, 3] - Ts[est.index, 2, 3]
    # a pure translation moves every vertex by the same amount: the largest over the interval
    assert inside.sum() >= 2 and est.transform_mm == pytest.approx(np.abs(z).max(), abs=1e-9)
    assert est.transform_deg == 0.0


def _staples():
    x, z = np.meshgrid([-40.0, 0.0, 40.0], [50.0, 10.0, -30.0])
    return np.stack([x.ravel(), -95 + 0.002 * x.ravel() ** 2, z.ravel()], axis=1)


def _breathing(phase):
    """Non-rigid chest motion (mm): the lower rows move more, and later."""
    rows = np.repeat([0.7, 1.0, 1.3], 3)
    lag = np.repeat([0.0, 0.08, 0.16], 3)
    g = 0.5 - 0.5 * np.cos(2 * np.pi * (phase[:, None] - lag))
    out = np.zeros(phase.shape + (9, 3))
    out[..., 1] = -6.0 * rows * g
    return out


def _trace(rng, phase_true, T_source_from_map, *, hold_fraction=1.2, noise_mm=0.2):
    target = _staples() + _breathing(np.array([phase_true]))[0]
    labels, phase = [], []
    start = 0.0
    for k in range(1, 10):
        ph = (start + np.arange(0, hold_fraction, 0.01)) % 1.0
        labels.append(np.full(ph.size, k))
        phase.append(ph)
        start += 0.37
    labels, phase = np.concatenate(labels), np.concatenate(phase)
    staples = _staples()[None] + _breathing(phase)
    held = staples[np.arange(labels.size), labels - 1]
    tip = held @ T_source_from_map[:3, :3].T + T_source_from_map[:3, 3] + noise_mm * rng.standard_normal(held.shape)
    return labels, tip, phase, target


def test_traced_staples_find_the_phase_at_which_the_chest_had_the_ct_shape():
    rng = np.random.default_rng(4)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [20, -10, 35], degrees=True).as_matrix()
    T[:3, 3] = [30.0, -150.0, 80.0]
    for phase_true in (0.25, 0.7):
        labels, tip, phase, target = _trace(rng, phase_true, T)
        curve = fiducial_curve(labels, tip, phase, target, PHASES)
        best = int(np.argmin(curve.sse_mm2))
        # 0.2 mm tracker noise over ~120 samples per staple: the shape is known to
        # ~0.02 mm, the phase to about a percent of the breath
        assert abs(_wrap(PHASES[best] - phase_true)) <= 0.02
        at_truth = int(round(phase_true * 100))
        # at the true phase the rigid fit is T's inverse up to the noise (0.2 mm / sqrt(9 staples))
        np.testing.assert_allclose(curve.T0_heart_from_probe[at_truth][:3, :3], np.linalg.inv(T)[:3, :3], atol=0.005)
        np.testing.assert_allclose(curve.T0_heart_from_probe[at_truth][:3, 3], np.linalg.inv(T)[:3, 3], atol=0.3)
        assert np.all(curve.trace_rms_mm < 0.45)  # 0.2 mm per axis: 0.35 mm in 3-D
        assert curve.residuals_mm[best].max() < 0.3


def test_a_staple_held_for_half_a_breath_is_refused():
    rng = np.random.default_rng(5)
    labels, tip, phase, target = _trace(rng, 0.3, np.eye(4), hold_fraction=0.45)
    with pytest.raises(TemporalError, match="staple 1 is held over .* of 4 quarters of the breath"):
        fiducial_curve(labels, tip, phase, target, PHASES)


def test_paper_eq10_picks_the_registration_closest_to_T0():
    rng = np.random.default_rng(6)
    staples_map = _staples()
    T_true = np.eye(4)
    T_true[:3, 3] = [5.0, -3.0, 2.0]
    Ts = np.repeat(T_true[None], 101, axis=0)
    path = 8.0 * np.sin(2 * np.pi * (PHASES - 0.42))  # the heart's respiratory path, z
    Ts[:, 2, 3] += path
    source = (staples_map - T_true[:3, 3]) + 0.3 * rng.standard_normal((9, 3))
    est = paper_phase(PHASES, Ts, source, staples_map, np.zeros(3), rng.normal(0, 40, (100, 3)))
    # T0 is T_true up to 0.3 mm touch noise; |path| < 0.5 mm only within ~0.01 of 0.42
    assert abs(_wrap(est.respiration_phase - 0.42)) <= 0.02 and est.contains(0.42)
    # a T0 error of 4 mm along the path moves the minimum where the path makes up for it
    shifted = source - np.array([0.0, 0.0, 4.0])
    biased = paper_phase(PHASES, Ts, shifted, staples_map, np.zeros(3), rng.normal(0, 40, (100, 3)))
    # 8 sin(2 pi (phi - 0.42)) = 4 twice a cycle: 0.42 + 1/12 and 0.42 + 5/12
    expected = 0.42 + np.array([1.0, 5.0]) / 12
    assert np.abs(_wrap(biased.respiration_phase - expected)).min() <= 0.02
    assert not biased.contains(0.42)  # resampling the staples cannot reveal a shift of them all


def test_errors_shared_by_neighbouring_points_widen_the_interval():
    # 12 patches of 5 points; each patch's misfit is least at its own phase
    # (0.5 + a shared error of sd 0.04, as a patch of mesh error would pull it).
    # Counted as 60 independent points the interval is too narrow; with where
    # the points lie (spatial blocks, the sandwich) it widens to cover the truth.
    vertices = np.random.default_rng(0).normal(0, 40, (200, 3))
    covered = {"independent": 0, "blocks": 0}
    for seed in range(8):
        rng = np.random.default_rng(seed)
        centres = rng.normal(0, 40, (12, 3))
        points = np.repeat(centres, 5, axis=0) + rng.normal(0, 1.0, (60, 3))
        pull = np.repeat(0.04 * rng.standard_normal(12), 5)
        misfit = 2.0 * np.sin(np.pi * _wrap(PHASES[:, None] - 0.5 - pull))
        d = np.sqrt(0.2**2 + misfit**2)
        plain = estimate_phase(PHASES, d, _identity_sweep(101), vertices)
        blocks = estimate_phase(PHASES, d, _identity_sweep(101), vertices, points_mm=points)
        assert blocks.respiration_phase == plain.respiration_phase and blocks.width >= plain.width
        covered["independent"] += plain.contains(0.5)
        covered["blocks"] += blocks.contains(0.5)
    assert covered["blocks"] >= 7 and covered["independent"] <= 4


def _fiducial_residuals(rng, phase_true, *, noise_mm=0.5, signal_mm=3.0):
    """A traced-staple term (FiducialCurve) whose residuals grow away from phase_true."""
    from registration.fiducial_curve import FiducialCurve

    eps = rng.standard_normal((1, 9))
    a = rng.uniform(0.5 * signal_mm, signal_mm, (1, 9))
    r = np.sqrt((noise_mm * eps) ** 2 + (a * np.sin(np.pi * _wrap(PHASES - phase_true))[:, None]) ** 2)
    m = PHASES.size
    return FiducialCurve(phases=PHASES, positions_probe_mm=np.zeros((m, 9, 3)), T0_heart_from_probe=_identity_sweep(m),
                         residuals_mm=r, sse_mm2=(r**2).sum(axis=1), trace_rms_mm=np.full(9, 0.3),
                         n_samples=np.full(9, 100))


def test_terms_that_disagree_widen_the_interval_to_hold_both():
    from registration.temporal import disagreement

    rng = np.random.default_rng(5)
    vertices = rng.normal(0, 40, (200, 3))
    agree = estimate_phase(PHASES, _distances(rng, 0.30, signal_mm=1.0), _identity_sweep(101), vertices,
                           fiducials=_fiducial_residuals(rng, 0.30))
    # the chest says 0.42, the heart 0.30: each term alone is sure, so one of them is biased
    apart = estimate_phase(PHASES, _distances(rng, 0.30, signal_mm=1.0), _identity_sweep(101), vertices,
                           fiducials=_fiducial_residuals(rng, 0.42))
    ratio = [disagreement(e.cost_heart + e.cost_fiducial, [e.cost_heart, e.cost_fiducial]) for e in (agree, apart)]
    assert ratio[0] < 3.0 < 20.0 < ratio[1]  # consistent: about chi-square 1; apart: far beyond
    assert agree.contains(0.30) and agree.width < 0.06
    assert apart.contains(0.30) and apart.contains(0.42) and apart.width > 2 * agree.width
    assert disagreement(agree.cost, [agree.cost]) == 1.0  # one term cannot disagree with itself
    # the estimate carries its ratio (registration.json) and says what would decide it
    assert apart.disagreement == pytest.approx(ratio[1]) and agree.disagreement == pytest.approx(ratio[0])
    assert type(apart).from_dict(apart.to_dict()).disagreement == apart.disagreement
    legacy = {k: v for k, v in apart.to_dict().items() if k != "disagreement"}  # written before the ratio
    assert type(apart).from_dict(legacy).disagreement == 1.0
    assert "the heart and the staples' trace disagree" in dataclasses.replace(apart, decided=False).summary()


def test_the_advice_on_an_undecided_phase_follows_the_evidence_used():
    """An audit that had traced the staples and stated the breath-hold phase (0.9, against data at 0.11) was
    told to 'trace the staples over a breath (session format 2) or state the breath-hold phase'; eq. 10, which
    reads neither, was told the same."""
    rng = np.random.default_rng(5)
    vertices = rng.normal(0, 40, (200, 3))
    heart, trace = _distances(rng, 0.30, signal_mm=1.0), _fiducial_residuals(rng, 0.30)

    def advice(**evidence):
        est = estimate_phase(PHASES, heart, _identity_sweep(101), vertices, **evidence)
        return est, dataclasses.replace(est, decided=False).summary()

    _, text = advice()  # the heart alone: either would help
    assert text.endswith("trace the staples over a breath (session format 2) or state the breath-hold phase "
                         "(--breath-hold-phase)")
    traced, text = advice(fiducials=trace)
    assert "trace the staples" not in text and text.endswith("state the breath-hold phase (--breath-hold-phase)")
    wrong, text = advice(fiducials=trace, breath_hold_phase=0.9)
    assert text.endswith("the stated breath-hold phase 0.90 disagrees with the data; check it or leave it out "
                         "(--breath-hold-phase)")
    assert type(wrong).from_dict(wrong.to_dict()).breath_hold_phase == 0.9  # registration.json keeps it
    assert type(wrong).from_dict({k: v for k, v in wrong.to_dict().items() if k != "breath_hold_phase"}
                                 ).breath_hold_phase is None  # written before it
    _, text = advice(fiducials=trace, breath_hold_phase=0.3)  # all three agree: only more points are left
    assert "trace the staples" not in text and "state the" not in text and "record more points" in text
    eq10 = dataclasses.replace(traced, method="eq10", evidence=("fiducials",), decided=False)
    assert "trace the staples" not in eq10.summary() and "the shape estimator (--estimator shape)" in eq10.summary()


def test_the_interval_reads_as_it_is_wrapping_or_whole():
    """An audit read eq. 10's ``[0.79, 0.78]`` (all but 0.01 of the cycle) as a narrow interval."""
    rng = np.random.default_rng(1)
    est = estimate_phase(PHASES, _distances(rng, 0.5), _identity_sweep(101), rng.normal(0, 40, (200, 3)))
    lo, hi = est.interval
    assert est.interval_text() == f"[{lo:.2f}, {hi:.2f}]" and f"interval [{lo:.2f}, {hi:.2f}];" in est.summary()
    wraps = dataclasses.replace(est, interval=np.array([0.95, 0.05]), interval_offsets=np.array([-0.05, 0.05]))
    assert wraps.interval_text() == "[0.95, 0.05] through 0"
    whole = dataclasses.replace(est, interval=np.array([0.79, 0.78]), interval_offsets=np.array([-0.5, 0.49]),
                                decided=False)
    assert whole.interval_text() == "the whole cycle" and "interval the whole cycle; " in whole.summary()


def test_a_rigid_fit_of_few_points_claims_no_certainty():
    """Eight points fit rigidly with 2 degrees of freedom left: their residual (2-7 um, as in an audit's
    8-point phantom session) is no measure of the noise, and taken as one it made misfits of hundredths of a
    mm look impossible (here a 0.05 wide interval; the audit's [0.17, 0.18] with the truth at 0.30).  The
    heart term's noise is at least HEART_NOISE_FLOOR_MM."""
    from registration.temporal import HEART_NOISE_FLOOR_MM

    rng = np.random.default_rng(3)
    d = _distances(rng, 0.3, n=8, noise_mm=0.002, signal_mm=0.08)
    est = estimate_phase(PHASES, d, _identity_sweep(101), rng.normal(0, 40, (200, 3)))
    assert est.width >= 0.1 and est.contains(0.3), (est.width, est.interval)
    # a hundred points' ordinary noise (0.15 mm, above the floor) decides as before
    assert HEART_NOISE_FLOOR_MM < 0.15
