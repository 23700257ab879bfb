"""The localiser's interpolation and the causal phase, against analytic truth.

Synthetic motion models whose point motion is an affine map of the mean
position (``x(phi) = x_bar + M(phi) x_bar + c(phi)``) give a displacement
field from any phase to the image phase that is affine in the current
position, so weighted linear least squares (without the ridge) must move
*any* robot position, not only the registered points', exactly.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.icp import SurfaceIndex
from registration.localise import LocaliseError, Localiser
from registration.motion_model import Harmonics, MotionModel, design_matrix
from registration.online import CausalPhase

H = Harmonics(cardiac=2, respiratory=1, coupled_cardiac=1, coupled_respiratory=1)


def _affine_models(rng, n=40):
    k = H.n_terms
    M = 0.02 * rng.standard_normal((k, 3, 3))  # per regressor column: a small linear map
    M[0] = 0.0  # column 0 (the constant) is the mean position itself
    c = 2.0 * rng.standard_normal((k, 3))
    c[0] = 0.0
    means = rng.uniform(-40.0, 40.0, (n, 3))
    models = [
        MotionModel(harmonics=H, coef_translation=np.einsum("kij,j->ki", M, x) + c,
                    coef_rotation=np.zeros((k, 3)), mean_position_mm=x, mean_rotation=np.eye(3),
                    residual_rms_mm=np.zeros(3), residual_rms_3d_mm=0.0, residual_rms_deg=0.0,
                    condition_number=1.0, n_samples=1000)
        for x in means
    ]
    return models, M, c


def _cube():
    import trimesh

    box = trimesh.creation.box(extents=(200.0, 200.0, 200.0))
    return SurfaceIndex(np.asarray(box.vertices), np.asarray(box.faces))


def test_an_affine_motion_is_interpolated_exactly_anywhere():
    rng = np.random.default_rng(3)
    models, M, c = _affine_models(rng)
    loc = Localiser(models, np.eye(4), 0.7, 0.3, _cube(), ridge_mm2=0.0)
    X_star = design_matrix([0.7], [0.3], H)[0]
    m = 50
    pc, pr = rng.uniform(0, 1, m), rng.uniform(0, 1, m)
    robot_bar = rng.uniform(-30.0, 30.0, (m, 3))  # places that are not registered points
    T = np.tile(np.eye(4), (m, 1, 1))
    X = design_matrix(pc, pr, H)
    T[:, :3, 3] = robot_bar + np.einsum("mk,kij,mj->mi", X, M, robot_bar) + X @ c
    truth = robot_bar + np.einsum("k,kij,mj->mi", X_star, M, robot_bar) + X_star @ c
    batch = loc.locate(T, pc, pr)
    np.testing.assert_allclose(batch.position_mm, truth, atol=1e-9)
    one = loc.locate(T[:1], pc[:1], pr[:1])  # the single-sample path: same maths
    np.testing.assert_allclose(one.position_mm[0], truth[0], atol=1e-9)
    # a NaN phase gives no place, not a guess
    none = loc.locate(T[:2], np.array([np.nan, pc[1]]), pr[:2])
    assert np.isnan(none.position_mm[0]).all() and np.allclose(none.position_mm[1], truth[1])


def test_single_sample_nearest_point_is_the_exact_one_near_and_far():
    """The live path's escalating search (32, 512 sites, then all) gives the
    batch path's exact closest point, close to the surface and far from it."""
    import trimesh

    rng = np.random.default_rng(5)
    models, _, _ = _affine_models(rng)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=50.0)  # 20 480 faces
    loc = Localiser(models, np.eye(4), 0.7, 0.3, (np.asarray(sphere.vertices), np.asarray(sphere.faces)))
    d = rng.standard_normal((60, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radii = np.concatenate([rng.uniform(45.0, 55.0, 20), rng.uniform(60.0, 90.0, 20), rng.uniform(0.0, 30.0, 20)])
    from registration.icp import closest_points

    for q in d * radii[:, None]:
        cp, normal = loc._nearest_one(q)
        ref = closest_points(loc.surface, q[None])
        assert np.linalg.norm(cp - q) == pytest.approx(np.linalg.norm(ref.points[0] - q), abs=1e-9)
        np.testing.assert_allclose(cp, ref.points[0], atol=1e-6)


def test_localiser_refuses_too_few_points():
    rng = np.random.default_rng(0)
    models, _, _ = _affine_models(rng, n=3)
    with pytest.raises(LocaliseError, match="at least 4 registered points"):
        Localiser(models, np.eye(4), 0.7, 0.3, _cube())


@settings(max_examples=50, deadline=None)
@given(period=st.floats(0.3, 2.0), start=st.floats(0.0, 1e5), frac=st.floats(0.001, 0.999))
def test_causal_phase_within_a_regular_rhythm(period, start, frac):
    # events every `period`: after three of them the phase is the elapsed fraction (away
    # from the cycle boundary, where rounding may put it on either side)
    ph = CausalPhase()
    for k in range(3):
        ph.add_event(start + k * period)
    value, predicted = ph.phase(start + 2 * period + frac * period)
    assert value == pytest.approx(frac, abs=1e-6) and not predicted
    # past the expected next event: the next cycle, flagged as predicted
    value, predicted = ph.phase(start + 3 * period + frac * period)
    assert value == pytest.approx(frac, abs=1e-6) and predicted
    # past max_gap_periods (2.5): undefined
    assert np.isnan(ph.phase(start + 2 * period + 2.6 * period)[0])
