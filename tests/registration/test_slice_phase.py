"""Each point at the cardiac phase of the CT slices it lies on (registration.slice_phase)."""

from __future__ import annotations

import numpy as np
import pytest

from registration.motion_model import fit_motion_model, predict_positions
from registration.slice_phase import SlicePhases, point_cardiac_phases, predict_at_point_phases
from registration.transforms import invert

from .conftest import simulate_traces, spread_uv


def _patchwork():
    """Three stacks of four 2.5 mm slices: 0.63, then one imaged early (0.49), then one wrapping 0.97 -> 0.01."""
    pos = -15.0 + 2.5 * np.arange(12)
    phases = np.r_[np.full(4, 0.63), np.full(4, 0.49), [0.97, 0.99, 0.01, 0.03]]
    return SlicePhases(pos[::-1], phases[::-1], [0.0, 0.0, 2.0])  # any order, any normal length


def test_point_phases_follow_the_slices_through_any_map_frame():
    slices = _patchwork()
    assert np.allclose(slices.normal_patient, [0, 0, 1]) and np.all(np.diff(slices.positions_mm) > 0)
    T_map_from_patient = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    T_map_from_patient[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]] @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    T_map_from_patient[:3, 3] = [5.0, -20.0, 40.0]
    z = np.array([-14.0, -7.5, -6.25, -2.5, 8.75, 13.75, -40.0, 40.0])
    patient = np.column_stack([np.full(z.size, 12.0), np.full(z.size, -3.0), z])
    points_map = patient @ T_map_from_patient[:3, :3].T + T_map_from_patient[:3, 3]
    got = point_cardiac_phases(points_map, T_map_from_patient, slices)
    # inside a stack its phase; halfway between stacks the mean; the wrap through 0 interpolates through 0;
    # beyond the scanned range the end slices'
    want = [0.63, 0.63, 0.56, 0.49, 0.0, 0.03, 0.63, 0.03]
    assert np.allclose(np.abs((got - want + 0.5) % 1.0 - 0.5), 0.0, atol=1e-9)
    assert slices.spread > 0.3  # the stacks disagree by a third of a beat


def test_points_predicted_at_their_own_phase(trial1_heart, trial1_config):
    rng = np.random.default_rng(3)
    uv = spread_uv(4, seed=2)
    traces, _ = simulate_traces(trial1_heart, trial1_config, uv, rng=rng, noise_mm=0.05, noise_deg=0.05)
    models = [fit_motion_model(pc, pr, T) for pc, pr, T in traces]
    own = np.array([0.63, 0.49, 0.2, 0.9])
    phases_r = np.array([0.0, 0.35, 0.8])
    got = predict_at_point_phases(models, own, phases_r)
    assert got.shape == (3, 4, 3)
    for i, pc in enumerate(own):
        assert np.allclose(got[:, i], predict_positions(models, np.full(3, pc), phases_r)[:, i], atol=1e-9)
    # and it is the heart there: the truth at each point's own phase, in the probe frame
    from heartreg.phantom import layout

    T_probe_from_patient = invert(layout.T_patient_from_probe())
    truth = trial1_heart.surface_points(np.repeat(uv[None, :, 0], 3, 0), np.repeat(uv[None, :, 1], 3, 0),
                                        own[None], phases_r[:, None])
    truth = truth @ T_probe_from_patient[:3, :3].T + T_probe_from_patient[:3, 3]
    assert np.sqrt(np.mean(np.sum((got - truth) ** 2, axis=-1))) < 0.3
    with pytest.raises(ValueError, match="point_phases_c"):
        predict_at_point_phases(models, own[:3], phases_r)
    with pytest.raises(ValueError, match="same shape"):
        SlicePhases([0.0, 1.0], [0.5], [0, 0, 1])
