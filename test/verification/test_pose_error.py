"""A measured relative pose's error against a pair with a known answer."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.verification.pose_error import OUTSIDE_COVARIANCE_CHI2, error_mahalanobis2, relative_pose_error


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


def test_the_error_under_the_pose_covariance_is_a_mahalanobis_distance() -> None:
    """A pose 2 cm off along z and 0.5 degrees off about x, with standard deviations 1 cm and 0.25 degrees:
    2^2 + 2^2 = 8; a covariance that is not one gives NaN; 22.46 is chi-square's 99.9 % point for 6 dof."""
    from scipy.stats import chi2

    truth = np.eye(4)
    truth[:3, 3] = [0.0, 0.0, 3.0]
    measured = truth.copy()
    measured[:3, :3] = Rotation.from_euler("x", 0.5, degrees=True).as_matrix()
    measured[:3, 3] += [0.0, 0.0, 0.02]
    covariance = np.diag([0.01 ** 2] * 3 + [np.radians(0.25) ** 2] * 3)
    assert error_mahalanobis2(truth, measured, covariance) == pytest.approx(8.0, rel=1e-6)
    assert np.isnan(error_mahalanobis2(truth, measured, np.zeros((6, 6))))
    assert np.isnan(error_mahalanobis2(truth, measured, np.full((6, 6), np.nan)))
    assert abs(OUTSIDE_COVARIANCE_CHI2 - chi2.ppf(0.999, 6)) < 0.01
    query = np.eye(4)
    assert relative_pose_error(query, truth, measured, covariance).mahalanobis2 == pytest.approx(8.0, rel=1e-6)
    assert np.isnan(relative_pose_error(query, truth, measured).mahalanobis2)
