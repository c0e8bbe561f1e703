"""Message poses as gtsam Pose3, against hand-made rotations: a quarter turn about z is x -> y."""

import math
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.gtsam_poses import (
    extrinsic_to_gtsam,
    gtsam_to_pose,
    gtsam_to_poses,
    loop_closure_pose,
    pose_to_gtsam,
)

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


def test_poses_converted_together_rebuild_to_the_same_gtsam_poses():
    rng = np.random.default_rng(3)
    poses = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 2.0), rng.normal(size=3) * 10.0) for _ in range(50)]
    messages = gtsam_to_poses(poses)
    assert len(messages) == 50 and gtsam_to_poses([]) == []
    for pose, message in zip(poses, messages, strict=True):
        q = message.orientation  # rebuilt by gtsam's own quaternion constructor (w, x, y, z)
        assert gtsam.Rot3.Quaternion(q.w, q.x, q.y, q.z).equals(pose.rotation(), 1e-12)
        assert abs(np.linalg.norm([q.x, q.y, q.z, q.w]) - 1.0) < 1e-12
        position = message.position
        np.testing.assert_allclose([position.x, position.y, position.z], pose.translation(), atol=1e-12)
        assert pose_to_gtsam(message).equals(pose, 1e-9)  # and back
    single = gtsam_to_pose(poses[7])
    assert single == messages[7]
