"""ATE with evo against hand-computed cases, and the drifting odometry's noise model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.trajectory_error import (
    OdometryDrift,
    absolute_trajectory_error,
    drifting_odometry,
    read_tum,
    trajectory_from_matrices,
    tum_text,
)


def translations(points: list[list[float]]) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(points), 1, 1))
    poses[:, :3, 3] = points
    return poses


SQUARE = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]


def test_ate_of_a_shifted_trajectory_is_zero_after_alignment() -> None:
    stamps = np.arange(4.0)
    reference = trajectory_from_matrices(stamps, translations(SQUARE))
    shifted = trajectory_from_matrices(stamps, translations([[x + 5, y - 2, z + 1] for x, y, z in SQUARE]))
    assert absolute_trajectory_error(reference, shifted).rmse_m == pytest.approx(0.0, abs=1e-9)


def test_ate_hand_computed() -> None:
    """Two of four corners pushed up by +h and two down by -h: the best SE(3) alignment cannot remove an
    alternating offset whose mean is zero and which no rotation explains, so RMSE = h."""
    h = 0.1
    stamps = np.arange(4.0)
    reference = trajectory_from_matrices(stamps, translations(SQUARE))
    bumped = translations([[0.0, 0.0, h], [1.0, 0.0, -h], [1.0, 1.0, h], [0.0, 1.0, -h]])
    result = absolute_trajectory_error(reference, trajectory_from_matrices(stamps, bumped))
    assert result.matched == 4
    assert result.rmse_m == pytest.approx(h, rel=1e-6)


def test_sim3_alignment_removes_a_scale_error_se3_cannot() -> None:
    stamps = np.arange(4.0)
    reference = trajectory_from_matrices(stamps, translations(SQUARE))
    doubled = trajectory_from_matrices(stamps, translations([[2 * x, 2 * y, 2 * z] for x, y, z in SQUARE]))
    assert absolute_trajectory_error(reference, doubled, correct_scale=True).rmse_m == pytest.approx(0.0, abs=1e-9)
    # SE(3): the doubled square's corners are sqrt(0.5) from its centre instead of 0.5*sqrt(0.5)... off by that.
    assert absolute_trajectory_error(reference, doubled).rmse_m == pytest.approx(np.sqrt(0.5), rel=1e-6)


def test_tum_round_trip_and_bad_files(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    path.write_text(tum_text(np.arange(4.0) + 0.5, translations(SQUARE)))
    trajectory = read_tum(path)
    np.testing.assert_allclose(trajectory.positions_xyz, SQUARE)
    with pytest.raises(DataError, match="does not exist"):
        read_tum(tmp_path / "missing.tum")
    (tmp_path / "bad.tum").write_text("1 2 3\n")
    with pytest.raises(DataError, match=r"bad\.tum"):
        read_tum(tmp_path / "bad.tum")
    far = trajectory_from_matrices(np.arange(4.0) + 100, translations(SQUARE))
    with pytest.raises(DataError):
        absolute_trajectory_error(trajectory, far)


def test_drifting_odometry_is_seeded_and_drifts_as_stated() -> None:
    straight = translations([[float(i), 0.0, 0.0] for i in range(101)])  # 100 m along x, body z up
    drift = OdometryDrift(scale_noise=0.0, yaw_noise_deg=0.0, yaw_drift_deg_per_m=0.0, scale_bias=0.02)
    odometry = drifting_odometry(straight, np.array([0.0, 0.0, 1.0]), drift)
    assert odometry[-1][0, 3] == pytest.approx(102.0)  # 2 % too long
    turning = drifting_odometry(straight, np.array([0.0, 0.0, 1.0]),
                                OdometryDrift(scale_bias=0.0, scale_noise=0.0, yaw_noise_deg=0.0))
    heading = np.degrees(np.arctan2(turning[-1][1, 0], turning[-1][0, 0]))
    assert heading == pytest.approx(10.0)  # 0.1 degree per metre over 100 m, about the up axis
    noisy_a = drifting_odometry(straight, np.array([0.0, 0.0, 1.0]), OdometryDrift(seed=3))
    noisy_b = drifting_odometry(straight, np.array([0.0, 0.0, 1.0]), OdometryDrift(seed=3))
    np.testing.assert_array_equal(noisy_a, noisy_b)
    np.testing.assert_array_equal(noisy_a[0], straight[0])


def test_at_stamps_keeps_the_poses_at_the_given_stamps() -> None:
    from aefabmap_ros.evaluation.trajectory_error import at_stamps, trajectory_from_matrices

    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = np.arange(5)
    trajectory = trajectory_from_matrices(np.array([0.0, 0.1, 0.2, 0.3, 0.4]), poses)
    selected = at_stamps(trajectory, np.array([0.3, 0.1001, 7.0]))
    assert selected.timestamps.tolist() == [0.1, 0.3]
    assert selected.positions_xyz[:, 0].tolist() == [1.0, 3.0]
    assert at_stamps(trajectory, np.array([0.2])).timestamps.tolist() == [0.2]
    assert trajectory.num_poses == 5  # the original is left alone
