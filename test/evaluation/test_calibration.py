"""Reliability diagram and ECE against hand-computed bins."""

import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.calibration import reliability


def test_bins_by_hand():
    confidence = np.array([0.05, 0.15, 0.55, 0.6, 0.95, 1.0, 0.995])
    correct = np.array([False, True, True, False, True, True, False])
    result = reliability(confidence, correct, (0.0, 0.5, 0.9, 1.0))
    np.testing.assert_array_equal(result.counts, [2, 2, 3])
    np.testing.assert_allclose(result.mean_confidence, [0.1, 0.575, (0.95 + 1.0 + 0.995) / 3])
    np.testing.assert_allclose(result.accuracy, [0.5, 0.5, 2 / 3])
    expected = (2 * 0.4 + 2 * 0.075 + 3 * abs((0.95 + 1.0 + 0.995) / 3 - 2 / 3)) / 7
    assert result.expected_calibration_error == pytest.approx(expected)
    assert result.as_dict()["counts"] == [2, 2, 3]


def test_a_perfectly_calibrated_detector_has_zero_error_and_empty_bins_are_nan():
    result = reliability(np.array([1.0, 1.0, 0.0]), np.array([True, True, False]), (0.0, 0.5, 1.0))
    assert result.expected_calibration_error == 0.0
    empty = reliability(np.array([0.2]), np.array([True]), (0.0, 0.5, 1.0))
    assert np.isnan(empty.accuracy[1]) and empty.as_dict()["accuracy"] == [1.0, None]


def test_bad_input():
    with pytest.raises(DataError, match="two"):
        reliability(np.zeros(3), np.zeros(2, bool))
    with pytest.raises(DataError, match="increase strictly"):
        reliability(np.zeros(1), np.zeros(1, bool), (0.0, 0.0, 1.0))
    with pytest.raises(DataError, match=r"must lie in \[0.0, 1.0\]"):
        reliability(np.array([1.5]), np.array([True]))
