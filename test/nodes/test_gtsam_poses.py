"""Message poses as gtsam Pose3, against hand-made rotations: a quarter turn about z is x -> y."""

import math
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.gtsam_poses import extrinsic_to_gtsam, loop_closure_pose, pose_to_gtsam

QUARTER_TURN_ABOUT_Z = (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))  # x y z w


def _pose(position, quaternion):
    x, y, z = position
    qx, qy, qz, qw = quaternion
    return SimpleNamespace(position=SimpleNamespace(x=x, y=y, z=z),
                           orientation=SimpleNamespace(x=qx, y=qy, z=qz, w=qw))


def test_a_message_pose_is_the_same_transform():
    pose = pose_to_gtsam(_pose((1.0, 2.0, 3.0), QUARTER_TURN_ABOUT_Z))
    np.testing.assert_allclose(pose.translation(), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(pose.rotation().matrix() @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pose.transformFrom(np.array([1.0, 0.0, 0.0])), [1.0, 3.0, 3.0], atol=1e-12)


def test_a_loop_closure_gives_its_pose_and_its_covariance_as_6x6():
    covariance = np.arange(36, dtype=np.float64)
    message = SimpleNamespace(pose=_pose((0.5, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), pose_covariance=covariance.tolist())
    pose, matrix = loop_closure_pose(message)
    assert pose.equals(gtsam.Pose3(gtsam.Rot3(), np.array([0.5, 0.0, 0.0])), 1e-12)
    assert matrix.shape == (6, 6) and matrix[1, 0] == 6.0  # row-major, as ROS stores it


def test_an_extrinsic_is_normalised_and_a_bad_one_refused():
    pose = extrinsic_to_gtsam([1.0, 0.0, 0.5, *(2.0 * value for value in QUARTER_TURN_ABOUT_Z)])  # norm 2
    np.testing.assert_allclose(pose.rotation().matrix() @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pose.translation(), [1.0, 0.0, 0.5])
    for values in ([0.0] * 7, [0.0] * 6, [math.nan, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]):
        with pytest.raises(ConfigError, match="base_to_camera must be"):
            extrinsic_to_gtsam(values)
