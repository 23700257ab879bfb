"""The phantom's own geometry (heartreg/phantom/geometry.py) agrees with hrcore's.

The phantom does not share the tested packages' code; the two copies of the 4x4
basics must still give the same numbers.
"""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import hrcore.geometry as hr
from heartreg.phantom import geometry as ph

seeds = st.integers(min_value=0, max_value=2**32 - 1)


@settings(max_examples=40, deadline=None)
@given(seeds)
def test_the_two_copies_agree_on_random_inputs(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 12))
    R = Rotation.random(4, random_state=rng).as_matrix()
    t = rng.uniform(-300, 300, (4, 3))
    T = ph.poses(R, t)
    hr.check_transform(T, stack=True, rigid=True)
    points = rng.normal(0, 80, (n, 3))

    np.testing.assert_allclose(ph.apply(T[0], points), hr.apply_to_points(T[0], points), atol=1e-9)
    np.testing.assert_allclose(ph.invert(T), hr.invert(T), atol=1e-12)
    target = ph.apply(T[1], points) + rng.normal(0, 2.0, (n, 3))
    np.testing.assert_allclose(ph.kabsch(points, target), hr.kabsch(points, target), atol=1e-9)
    mirrored = points * [1.0, 1.0, -1.0]  # the reflection guard of both
    np.testing.assert_allclose(ph.kabsch(points, mirrored), hr.kabsch(points, mirrored), atol=1e-9)
    a = rng.normal(size=(n, 3))
    f_ph, f_hr = ph.frozen(a), hr.frozen(a, float)
    np.testing.assert_array_equal(f_ph, f_hr)
    assert not f_ph.flags.writeable and not f_hr.flags.writeable
