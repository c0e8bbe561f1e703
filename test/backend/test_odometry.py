"""Odometry interpolated by stamp, and a camera-frame closure moved into the base frame, against hand-made
poses."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.odometry import OdometryBuffer, closure_in_base_frame

SECOND = 1_000_000_000


def test_odometry_is_interpolated_between_samples() -> None:
    buffer = OdometryBuffer(max_samples=10)
    buffer.add(SECOND, gtsam.Pose3())
    buffer.add(3 * SECOND, gtsam.Pose3(gtsam.Rot3.Yaw(0.4), np.array([2.0, 0.0, 0.0])))
    middle = buffer.pose_at(2 * SECOND)
    assert middle is not None
    assert middle[0].rotation().yaw() == pytest.approx(0.2)
    assert middle[1] == pytest.approx(1.0)  # half of the 2 m travelled
    assert buffer.pose_at(4 * SECOND) is None and buffer.pose_at(0) is None


def test_closure_in_base_frame_conjugates_pose_and_moves_covariance() -> None:
    """Camera 1 m ahead of the base, turned 90 degrees about z: the base-frame closure is T_bc T_cc T_bc^-1, and
    an uncertainty along the camera's x (translation) becomes one along the base's y."""
    base_to_camera = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([1.0, 0.0, 0.0]))
    bases = (gtsam.Pose3(gtsam.Rot3.Yaw(0.3), np.array([2.0, 1.0, 0.0])),
             gtsam.Pose3(gtsam.Rot3.Yaw(-0.4), np.zeros(3)))
    cameras = [base.compose(base_to_camera) for base in bases]
    covariance = np.diag([4.0, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])  # ROS order: x y z rot
    pose, moved = closure_in_base_frame(cameras[0].between(cameras[1]), covariance, base_to_camera)
    assert pose.equals(bases[0].between(bases[1]), 1e-9)
    assert moved[1, 1] == pytest.approx(4.0, rel=1e-6) and moved[0, 0] < 0.01
    assert np.allclose(moved, moved.T)
    same, unchanged = closure_in_base_frame(cameras[0].between(cameras[1]), covariance, gtsam.Pose3())
    assert same.equals(cameras[0].between(cameras[1]), 1e-12) and np.allclose(unchanged, covariance)
