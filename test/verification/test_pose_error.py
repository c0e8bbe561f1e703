"""A measured relative pose's error against a pair with a known answer."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.verification.pose_error import relative_pose_error


def test_relative_pose_error_against_a_known_pair() -> None:
    """Query at the origin, place 2 m along x turned 10 degrees about y; a measurement 1 degree and 5 cm off."""
    query = np.eye(4)[:3]
    place = np.eye(4)
    place[:3, :3] = Rotation.from_euler("y", 10, degrees=True).as_matrix()
    place[:3, 3] = [2.0, 0.0, 0.0]
    measured = place.copy()
    measured[:3, :3] = Rotation.from_euler("y", 11, degrees=True).as_matrix()
    measured[:3, 3] = [2.0, 0.05, 0.0]
    error = relative_pose_error(query, place[:3], measured)
    assert error.rotation_deg == pytest.approx(1.0, abs=1e-6)
    assert error.direction_deg == pytest.approx(np.degrees(np.arctan2(0.05, 2.0)), abs=1e-6)
    assert error.translation_m == pytest.approx(0.05, abs=1e-9)
    # A monocular (unit) translation along the true direction has no direction error.
    unit = place.copy()
    unit[:3, 3] = [1.0, 0.0, 0.0]
    assert relative_pose_error(query, place, unit).direction_deg == pytest.approx(0.0, abs=1e-6)
