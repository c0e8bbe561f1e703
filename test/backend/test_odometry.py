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
    """Camera 1 m ahead of the base, turned 90 degrees about z: the base-frame closure is T_bc T_cc T_bc^-1,
    and its covariance is the spread of the base-frame closures (gtsam's right perturbation) that errors drawn
    from the message's covariance (in the query camera's axes: t + dt, Exp(dtheta) R) make (Monte Carlo)."""
    base_to_camera = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([1.0, 0.0, 0.0]))
    bases = (gtsam.Pose3(gtsam.Rot3.Yaw(0.3), np.array([2.0, 1.0, 0.0])),
             gtsam.Pose3(gtsam.Rot3.RzRyRx(0.2, -0.3, -0.9), np.array([0.5, -1.0, 0.3])))
    cameras = [base.compose(base_to_camera) for base in bases]
    closure = cameras[0].between(cameras[1])
    rng = np.random.default_rng(3)
    mixing = rng.normal(0.0, 1.0, (6, 6)) * np.array([0.04, 0.04, 0.04, 0.01, 0.01, 0.01])[:, None]
    covariance = mixing @ mixing.T + np.diag([0.02 ** 2] * 3 + [0.005 ** 2] * 3)  # ROS order: x y z rot
    for extrinsic in (base_to_camera, gtsam.Pose3()):
        pose, moved = closure_in_base_frame(closure, covariance, extrinsic)
        truth = bases[0].between(bases[1]) if extrinsic is base_to_camera else closure
        assert pose.equals(truth, 1e-9)
        assert np.allclose(moved, moved.T)
        tangents = []
        for error in rng.multivariate_normal(np.zeros(6), covariance, 20_000):
            camera_frame = gtsam.Pose3(gtsam.Rot3.Expmap(error[3:]).compose(closure.rotation()),
                                       closure.translation() + error[:3])
            base_frame = extrinsic.compose(camera_frame).compose(extrinsic.inverse())
            tangents.append(gtsam.Pose3.Logmap(pose.between(base_frame)))
        sampled = np.cov(np.asarray(tangents)[:, [3, 4, 5, 0, 1, 2]].T)  # gtsam (rot, trans) -> ROS order
        assert np.linalg.norm(moved - sampled) <= 0.04 * np.linalg.norm(sampled)
