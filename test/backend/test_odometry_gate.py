"""The odometry gate on straight-line odometry: a closed-form Mahalanobis distance, aliasing refused."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.odometry_gate import OdometryGate
from aefabmap_ros.backend.pose_graph import PoseGraphConfig
from aefabmap_ros.verification.gate import GateResult

SECOND = 1_000_000_000
CONFIG = PoseGraphConfig()
# ROS order (x, y, z, rot x, rot y, rot z): 1 cm and 1 mrad.
CLOSURE_COVARIANCE = np.diag([0.01 ** 2] * 3 + [0.001 ** 2] * 3)


def _straight_gate(base_to_camera: gtsam.Pose3 | None = None) -> OdometryGate:
    """Odometry of a robot driving 1 m/s along x for 10 s, one sample per second."""
    gate = OdometryGate(CONFIG, base_to_camera or gtsam.Pose3())
    for second in range(11):
        assert gate.add_odometry(second * SECOND, gtsam.Pose3(gtsam.Rot3(), np.array([float(second), 0.0, 0.0])))
    return gate


def test_the_disagreement_is_the_closed_form_mahalanobis_distance():
    gate = _straight_gate()
    # The place (t = 0 s) is 10 m behind the query (t = 10 s); the closure says 9.5 m.
    closure = gtsam.Pose3(gtsam.Rot3(), np.array([-9.5, 0.0, 0.0]))
    result, distance = gate.check(10 * SECOND, 0, closure, CLOSURE_COVARIANCE)
    # Residual 0.5 m along x; variance = closure 0.01^2 + floor 0.05^2 + drift (2 % of 10 m)^2.
    assert distance == pytest.approx(0.5 ** 2 / (0.01 ** 2 + 0.05 ** 2 + 0.2 ** 2), rel=1e-9)
    assert result is GateResult.CONSISTENT


def test_a_look_alike_place_is_refused_and_the_true_one_passes():
    gate = _straight_gate()
    truth = gtsam.Pose3(gtsam.Rot3(), np.array([-10.0, 0.0, 0.0]))
    result, distance = gate.check(10 * SECOND, 0, truth, CLOSURE_COVARIANCE)
    assert result is GateResult.CONSISTENT and distance == pytest.approx(0.0, abs=1e-12)
    # Aliasing: the images say "the same spot, turned 90 degrees"; odometry says 10 m back, same heading.
    aliased = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([0.3, 0.0, 0.0]))
    result, distance = gate.check(10 * SECOND, 0, aliased, CLOSURE_COVARIANCE)
    assert result is GateResult.INCONSISTENT and distance > CONFIG.gate_chi2


def test_stamps_outside_the_odometry_are_not_judged():
    gate = _straight_gate()
    closure = gtsam.Pose3(gtsam.Rot3(), np.array([-11.0, 0.0, 0.0]))
    result, distance = gate.check(11 * SECOND, 0, closure, CLOSURE_COVARIANCE)  # odometry ends at 10 s: not yet
    assert result is GateResult.NOT_YET and np.isnan(distance)
    result, distance = gate.check(10 * SECOND, -SECOND, closure, CLOSURE_COVARIANCE)  # before it began: never
    assert result is GateResult.NO_ODOMETRY and np.isnan(distance)
    assert not gate.reaches(11 * SECOND, 0) and gate.reaches(10 * SECOND, -SECOND)  # what NOT_YET is decided by
    assert not OdometryGate(CONFIG, gtsam.Pose3()).active and gate.active
    assert not gate.add_odometry(10 * SECOND, gtsam.Pose3())  # not after the last sample: ignored


def test_a_camera_mounted_off_the_base_is_judged_in_the_base_frame():
    # The camera looks to the robot's left (yawed 90 degrees) from 0.5 m ahead of the base.
    base_to_camera = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([0.5, 0.0, 0.0]))
    gate = _straight_gate(base_to_camera)
    base_truth = gtsam.Pose3(gtsam.Rot3(), np.array([-10.0, 0.0, 0.0]))
    camera_truth = base_to_camera.inverse().compose(base_truth).compose(base_to_camera)
    assert gate.check(10 * SECOND, 0, camera_truth, CLOSURE_COVARIANCE)[0] is GateResult.CONSISTENT
    # The base-frame pose read as if it were the camera's is 10 m off to the side: refused.
    assert gate.check(10 * SECOND, 0, base_truth, CLOSURE_COVARIANCE)[0] is GateResult.INCONSISTENT


def test_odometry_at_the_int32_limit_and_out_of_order() -> None:
    """Stamps up to the last ROS time (sec 2**31 - 1, nanosec 999999999) interpolate; out of order is refused."""
    last_ns = (2**31 - 1) * SECOND + 999_999_999
    gate = OdometryGate(CONFIG, gtsam.Pose3())
    for second in range(11):
        assert gate.add_odometry(last_ns - (10 - second) * SECOND,
                                 gtsam.Pose3(gtsam.Rot3(), np.array([float(second), 0.0, 0.0])))
    assert not gate.add_odometry(last_ns - 5 * SECOND, gtsam.Pose3())  # out of order: ignored
    truth = gtsam.Pose3(gtsam.Rot3(), np.array([-9.5, 0.0, 0.0]))  # from 10 s to 0.5 s: interpolated
    result, distance = gate.check(last_ns, last_ns - 10 * SECOND + SECOND // 2, truth, CLOSURE_COVARIANCE)
    assert result is GateResult.CONSISTENT and distance == pytest.approx(0.0, abs=1e-9)
