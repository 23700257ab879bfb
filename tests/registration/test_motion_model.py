"""Tests of registration/motion_model.py against the phantom's analytic motion."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from heartreg.phantom import layout
from registration.motion_model import (
    CoverageWarning,
    Harmonics,
    MotionModelError,
    design_matrix,
    fit_motion_model,
    predict_positions,
)
from registration.transforms import invert

from .conftest import simulate_traces, spread_uv

NOISE_MM = 0.3
NOISE_DEG = 0.2


@pytest.fixture(scope="module")
def fitted(trial1_heart, trial1_config):
    rng = np.random.default_rng(11)
    uv = spread_uv(12)
    traces, truth = simulate_traces(
        trial1_heart, trial1_config, uv, rng=rng, rate_hz=100.0, noise_mm=NOISE_MM, noise_deg=NOISE_DEG
    )
    models = [fit_motion_model(*trace) for trace in traces]
    return uv, traces, models


def test_design_matrix_columns_follow_the_paper():
    h = Harmonics()
    assert h.n_terms == 1 + 2 * 4 + 2 * 5 + 4 * 2 * 1 == 27
    X = design_matrix([0.1], [0.3], h)[0]
    pc, pr = 0.1, 0.3
    assert X[0] == 1.0
    assert X[1] == pytest.approx(np.sin(2 * np.pi * pr)) and X[2] == pytest.approx(np.cos(2 * np.pi * pr))
    assert X[7] == pytest.approx(np.sin(2 * np.pi * 4 * pr))
    assert X[9] == pytest.approx(np.sin(2 * np.pi * pc))
    assert X[17] == pytest.approx(np.sin(2 * np.pi * 5 * pc))
    assert X[19] == pytest.approx(np.sin(2 * np.pi * (pc - pr)))
    assert X[22] == pytest.approx(np.cos(2 * np.pi * (pc + pr)))
    assert X[25] == pytest.approx(np.sin(2 * np.pi * (2 * pc + pr)))


def test_residuals_are_at_the_tracker_noise(fitted):
    # The phantom's motion is (nearly) inside the model's span, so the residual
    # is the injected white noise: RMS per axis ~ 0.3 mm (slightly less: 27 of
    # 3000 degrees of freedom are fitted), never more than 1.2 x.
    _, _, models = fitted
    for m in models:
        assert np.all(m.residual_rms_mm <= 1.2 * NOISE_MM)
        assert np.all(m.residual_rms_mm >= 0.8 * NOISE_MM)
        # the rotation noise is 0.2 deg per axis: the angle RMS is sqrt(3) x that
        assert m.residual_rms_deg <= 1.2 * np.sqrt(3) * NOISE_DEG
        assert m.condition_number < 3.0
        assert m.n_samples == 3000 and m.n_dropped == 0


def test_predicted_positions_and_normals_match_the_surface(fitted, trial1_heart):
    uv, _, models = fitted
    T_probe_from_patient = invert(layout.T_patient_from_probe())
    pairs = np.array([[0.65, 0.3], [0.1, 0.0], [0.3, 0.5], [0.9, 0.8], [0.5, 0.15]])
    for (u, v), m in zip(uv, models):
        pos, R = trial1_heart.surface_frames(np.full(5, u), np.full(5, v), pairs[:, 0], pairs[:, 1])
        true_pos = pos @ T_probe_from_patient[:3, :3].T + T_probe_from_patient[:3, 3]
        true_n = R[:, :, 2] @ T_probe_from_patient[:3, :3].T
        pred = m.predict_position(pairs[:, 0], pairs[:, 1])
        assert np.abs(pred - true_pos).max() < 0.5
        angle = np.degrees(np.arccos(np.clip(np.sum(m.predict_normal(pairs[:, 0], pairs[:, 1]) * true_n, 1), -1, 1)))
        assert angle.max() < 2.0
        T = m.predict(pairs[:, 0], pairs[:, 1])
        np.testing.assert_allclose(T[:, :3, 3], pred)
        np.testing.assert_allclose(np.linalg.det(T[:, :3, :3]), 1.0)
    stacked = predict_positions(models, pairs[:, 0], pairs[:, 1])
    assert stacked.shape == (5, len(models), 3)
    np.testing.assert_allclose(stacked[:, 3], models[3].predict_position(pairs[:, 0], pairs[:, 1]))


def test_nan_phases_are_dropped_and_counted(fitted):
    _, traces, _ = fitted
    pc, pr, T = (np.array(a, copy=True) for a in traces[0])
    pc[:40] = np.nan
    pr[-10:] = np.nan
    m = fit_motion_model(pc, pr, T)
    assert m.n_dropped == 50 and m.n_samples == T.shape[0] - 50


def test_uncovered_phases_warn(fitted):
    _, traces, _ = fitted
    pc, pr, T = traces[0]
    keep = pr < 0.6  # respiration phases 0.6..1 never seen
    with pytest.warns(CoverageWarning, match="respiration phase leaves 4 of 10 bins empty"):
        fit_motion_model(pc[keep], pr[keep], T[keep])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_motion_model(pc, pr, T)  # full coverage: silent


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match=r"T_probe_from_robot must have shape \(5, 4, 4\)"):
        fit_motion_model(np.zeros(5), np.zeros(5), np.zeros((5, 3, 3)))
    with pytest.raises(MotionModelError, match="cannot fit 27 Fourier terms"):
        fit_motion_model(np.linspace(0, 0.9, 10), np.linspace(0, 0.9, 10), np.tile(np.eye(4), (10, 1, 1)))
    with pytest.raises(ValueError, match="fractions of a cycle"):
        fit_motion_model(np.full(30, 1.5), np.zeros(30), np.tile(np.eye(4), (30, 1, 1)))


def _on_blas_threads(n_threads, fn):
    from threadpoolctl import threadpool_limits

    with threadpool_limits(n_threads, user_api="blas"):
        return fn()


def test_motion_model_fit_is_the_same_bits_on_one_and_two_threads():
    # 3000 samples x 59 terms: the size at which OpenBLAS's threaded A.T @ B sums in another order
    rng = np.random.default_rng(4)
    n = 3000
    phase_c, phase_r = rng.random(n), rng.random(n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = rng.normal(size=(n, 3))
    T[:, :3, :3] = Rotation.from_rotvec(0.05 * rng.normal(size=(n, 3))).as_matrix()

    def fit():
        m = fit_motion_model(phase_c, phase_r, T, harmonics=Harmonics(5, 4, 5, 2))
        return m.coef_translation, m.coef_rotation, m.residual_rms_mm, m.predict(phase_c[:200], phase_r[:200])

    for one, two in zip(_on_blas_threads(1, fit), _on_blas_threads(2, fit)):
        assert np.array_equal(one, two)
