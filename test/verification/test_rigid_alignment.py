"""The robust rigid alignment of matched 3-D points against a known motion."""

from __future__ import annotations

import numpy as np

from aefabmap_ros.verification.rigid_alignment import rigid_alignment
from test.verification.test_relative_pose import rotation_about


def test_rigid_alignment_recovers_a_known_motion_despite_outliers() -> None:
    """60 place points moved by a known motion, 20 of them replaced by points off it by metres: the motion to
    1e-9 and exactly the 40 true matches as inliers."""
    rng = np.random.default_rng(5)
    place = np.column_stack([rng.uniform(-5, 5, 60), rng.uniform(-2, 2, 60), rng.uniform(3, 20, 60)])
    rotation, translation = rotation_about([0.2, 1.0, 0.1], 25.0), np.array([0.8, -0.1, 2.5])
    query = place @ rotation.T + translation
    wrong = rng.choice(60, 20, replace=False)
    query[wrong] += rng.uniform(2.0, 6.0, (20, 3)) * rng.choice([-1.0, 1.0], (20, 3))
    found = rigid_alignment(place, query)
    assert found is not None
    found_rotation, found_translation, inliers = found
    np.testing.assert_allclose(found_rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(found_translation, translation, atol=1e-9)
    expected = np.ones(60, bool)
    expected[wrong] = False
    np.testing.assert_array_equal(inliers, expected)
    assert rigid_alignment(place[:7], query[:7]) is None  # too few for any redundancy
