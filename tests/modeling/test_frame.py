"""modeling.frame: the recursive ellipse-fit heart frame against known axes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from heartreg.phantom import config
from modeling.frame import FrameError, fit_heart_frame
from modeling.slab_ellipses import _fit_line, _fit_slabs

from .conftest import WOOD_PRESETS, heart_of


def _angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.mark.parametrize("preset", WOOD_PRESETS)
def test_phantom_axes_and_euler(preset, phantom_meshes):
    """Phantom at phi_C = 0.65, 1 mm voxels, 20k faces.

    Measured: z within 0.16 deg, x within 0.51 deg (the heartbeat's twist and
    angle-dependent radial contraction at 0.65 turn the cross-sections' minor
    axes slightly), Euler angles within 0.5 deg (gamma, about z, takes the x
    error). Tolerances: the brief's 2 deg (z) and 5 deg (x); 1.5 deg (Euler).
    """
    frame = fit_heart_frame(phantom_meshes[preset].vertices)
    truth = heart_of(preset).axes_patient
    fitted = frame.axes_patient
    assert frame.converged and frame.axis_change_deg < 0.01
    assert frame.base_rule == "cross-section"
    assert _angle_deg(fitted[:, 2], truth[:, 2]) < 2.0
    assert _angle_deg(fitted[:, 0], truth[:, 0]) < 5.0
    assert np.allclose(np.cross(fitted[:, 2], fitted[:, 0]), fitted[:, 1])
    assert np.allclose(fitted @ fitted.T, np.eye(3), atol=1e-12)
    expected = np.asarray(config.PRESETS[preset].euler_xyz_deg)
    assert np.abs(np.asarray(frame.euler_xyz_deg) - expected).max() < 1.5
    # origin on the true axis (within 0.5 mm) halfway along the heart's extent
    h = heart_of(preset)
    o_heart = h.T_heart_from_patient[:3, :3] @ frame.origin_patient_mm + h.T_heart_from_patient[:3, 3]
    assert np.hypot(o_heart[0], o_heart[1]) < 0.5
    assert len(frame.ellipses) >= 8
    heights = [e.height_mm for e in frame.ellipses]
    assert heights == sorted(heights)
    # the ellipse minor axes lie along x (within 10 deg) and their semi-axes
    # follow the phantom's 38 x 45 mm cross-section at the widest slab
    widest = max(frame.ellipses, key=lambda e: e.semi_major_mm)
    assert 40.0 < widest.semi_major_mm < 47.0 and 34.0 < widest.semi_minor_mm < 40.0


def _ellipsoid(semi=(20.0, 30.0, 60.0), n_u=64, n_v=48):
    """Lat-long ellipsoid vertices, symmetric under x -> -x, y -> -y, z -> -z."""
    u = (np.arange(n_u) + 0.5) / n_u * 2 * np.pi
    v = (np.arange(n_v) + 0.5) / n_v * np.pi
    uu, vv = np.meshgrid(u, v, indexing="ij")
    pts = np.stack(
        [np.sin(vv) * np.cos(uu), np.sin(vv) * np.sin(uu), np.cos(vv)], axis=-1
    ).reshape(-1, 3)
    return pts * np.asarray(semi)


def test_elongated_ellipsoid_gives_exact_axes():
    R = Rotation.from_euler("XYZ", [-20.0, 10.0, -60.0], degrees=True).as_matrix()
    origin = np.array([15.0, -10.0, 40.0])
    v = _ellipsoid() @ R.T + origin
    # a symmetric ellipsoid has no base: the hint fixes the sign of z
    frame = fit_heart_frame(v, base_hint=R[:, 2])
    assert frame.base_rule == "hint"
    fitted = frame.axes_patient
    assert R[:, 0] @ np.array([0.0, -1.0, 0.0]) > 0  # the construction is anterior
    for c in range(3):
        assert _angle_deg(fitted[:, c], R[:, c]) < 1e-6
    assert np.allclose(frame.origin_patient_mm, origin, atol=1e-9)
    assert np.allclose(frame.euler_xyz_deg, [-20.0, 10.0, -60.0], atol=1e-6)
    flipped = fit_heart_frame(v, base_hint=-R[:, 2])
    assert np.allclose(flipped.axes_patient[:, 2], -R[:, 2])


def test_a_fit_that_did_not_converge_says_its_axes_are_unreliable():
    """CTChest4's 'tissue' (a whole chest) gave '20 iterations, last change 43.362 deg' in model.json and no
    warning: the frame says so (build_heart_model's warning, tests/modeling/test_fallbacks.py)."""
    v = _ellipsoid()
    tilted = Rotation.from_euler("X", 20.0, degrees=True).apply([0.0, 0.0, 1.0])
    frame = fit_heart_frame(v, base_hint=[0.0, 0.0, 1.0], initial_axis=tilted, max_iterations=1)
    assert not frame.converged and frame.axis_change_deg > 5.0
    text = frame.convergence_warning()
    assert text.startswith(f"the heart frame's fit did not converge (1 iterations, the long axis still moved "
                           f"{frame.axis_change_deg:.1f} deg in the last): the frame's axes")
    assert "unreliable" in text
    assert fit_heart_frame(v, base_hint=[0.0, 0.0, 1.0]).convergence_warning() is None


def test_a_fit_that_settled_into_a_tiny_cycle_is_not_warned():
    """slicerio's CTChest4 (10 mm slices): the axis alternated between two directions 0.029 deg apart from the
    third iteration on, and the model warned 'did not converge ... moved 0.0 deg ... unreliable'.  A fit stopped
    while moving less than SETTLED_DEG is not warned; model.json keeps converged false and the last change."""
    from modeling.frame import SETTLED_DEG

    v = _ellipsoid()
    tilted = Rotation.from_euler("X", 0.3, degrees=True).apply([0.0, 0.0, 1.0])
    frame = fit_heart_frame(v, base_hint=[0.0, 0.0, 1.0], initial_axis=tilted, max_iterations=1)
    assert not frame.converged and 0.01 < frame.axis_change_deg < SETTLED_DEG, frame.axis_change_deg
    assert frame.convergence_warning() is None


def test_pointed_end_is_apex():
    """Egg: pointed prolate half (apex) below a flat-topped half (base)."""
    v = _ellipsoid((20.0, 30.0, 60.0))
    base_half = v[:, 2] > 0
    v[base_half, 2] *= 0.5  # a short, blunt base
    R = Rotation.from_euler("XYZ", [-25.0, 14.0, -55.0], degrees=True).as_matrix()
    frame = fit_heart_frame(v @ R.T)
    assert frame.base_rule == "cross-section"
    assert _angle_deg(frame.axes_patient[:, 2], R[:, 2]) < 0.5


def test_stub_beyond_a_gap_does_not_tilt_the_axis():
    """A vessel stub past the base, off the axis, with an empty slab between: only the body's run of slabs counts."""
    body = _ellipsoid((20.0, 30.0, 60.0))
    a, h = np.meshgrid(np.linspace(0, 2 * np.pi, 40, endpoint=False), np.linspace(72.0, 100.0, 30), indexing="ij")
    stub = np.stack([25.0 + 8.0 * np.cos(a), 8.0 * np.sin(a), h], axis=-1).reshape(-1, 3)
    v = np.concatenate([body, stub])
    frame = fit_heart_frame(v, base_hint=[0.0, 0.0, 1.0])
    assert _angle_deg(frame.axes_patient[:, 2], np.array([0.0, 0.0, 1.0])) < 0.5
    assert max(e.height_mm for e in frame.ellipses) < 60.0 - frame.origin_patient_mm[2]  # no stub ellipse
    # every accepted slab on the line, the stub tilts it
    slabs, _ = _fit_slabs(v, frame.axes_patient[:, 2], 10.0, 30)
    assert _angle_deg(_fit_line([s["centre"] for s in slabs])[1], np.array([0.0, 0.0, 1.0])) > 3.0


@settings(max_examples=15, deadline=None)
@given(
    rotvec=st.tuples(*[st.floats(-np.pi / 2, np.pi / 2)] * 3),
    shift=st.tuples(*[st.floats(-200.0, 200.0)] * 3),
)
def test_invariant_to_rigid_motion(rotvec, shift, phantom_meshes):
    """Moving the vertices moves the frame with them.  Only x's sign may
    differ: it follows the patient's anterior direction, which does not move."""
    v = phantom_meshes["wood2018-trial2"].vertices
    ref = fit_heart_frame(v)
    R = Rotation.from_rotvec(rotvec).as_matrix()
    moved = fit_heart_frame(v @ R.T + np.asarray(shift))
    a, b = R @ ref.axes_patient, moved.axes_patient
    # 1e-5 deg: arccos of a cosine one float64 ulp below 1 is already 8.5e-7 deg (1.2e-6 was seen)
    assert _angle_deg(a[:, 2], b[:, 2]) < 1e-5
    assert abs(abs(a[:, 0] @ b[:, 0]) - 1.0) < 1e-10
    assert np.allclose(R @ ref.origin_patient_mm + np.asarray(shift), moved.origin_patient_mm, atol=1e-6)
    assert moved.iterations == ref.iterations


def test_input_errors():
    v = _ellipsoid()
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        fit_heart_frame(v[:, :2])
    with pytest.raises(FrameError, match="at least 100"):
        fit_heart_frame(v[:50])
    with pytest.raises(FrameError, match="reduce slab_mm"):
        fit_heart_frame(v, slab_mm=100.0)
    with pytest.raises(ValueError, match="perpendicular"):
        fit_heart_frame(v, base_hint=[1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="initial_axis"):
        fit_heart_frame(v, initial_axis=[0.0, 0.0, 0.0])
