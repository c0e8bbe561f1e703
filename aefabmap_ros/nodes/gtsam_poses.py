"""Poses of ROS messages as gtsam ``Pose3``, for the nodes that feed a pose graph or the odometry gate
(pose_graph_node, verifier_node).

Apart from ``messages`` so that the detection nodes (feature, quantizer, FAB-MAP), which a robot may run
without the example backend, do not need gtsam installed.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np
from geometry_msgs.msg import Pose
from scipy.spatial.transform import Rotation

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.verification.relative_pose import pose_message_to_matrix


def pose_to_gtsam(pose: Any) -> gtsam.Pose3:
    """A geometry_msgs/Pose as a gtsam Pose3 (one ``messages.message_pose_problem`` accepted: scipy raises on
    the rest)."""
    return gtsam.Pose3(np.asarray(pose_message_to_matrix(pose), dtype=np.float64))


def gtsam_to_poses(poses: Sequence[gtsam.Pose3]) -> list[Pose]:
    """Pose3s as geometry_msgs/Pose. The rotations go through scipy in one call: converted one at a time, its
    checks of each matrix cost more than the rest of a message, and a backend republishes every keyframe."""
    if not poses:
        return []
    quaternions = Rotation.from_matrix(np.stack([pose.rotation().matrix() for pose in poses])).as_quat()
    messages = []
    for pose3, (qx, qy, qz, qw) in zip(poses, quaternions.tolist(), strict=True):
        message = Pose()
        x, y, z = pose3.translation().tolist()
        message.position.x, message.position.y, message.position.z = x, y, z
        message.orientation.x, message.orientation.y, message.orientation.z, message.orientation.w = qx, qy, qz, qw
        messages.append(message)
    return messages


def gtsam_to_pose(pose: gtsam.Pose3) -> Pose:
    return gtsam_to_poses([pose])[0]


def loop_closure_pose(message: Any) -> tuple[gtsam.Pose3, np.ndarray]:
    """A LoopClosure's relative pose (the place camera in the query camera's frame) and its 6x6 covariance
    (ROS order x y z rot), as the backend and the odometry gate take them; meaningful when pose_available."""
    return pose_to_gtsam(message.pose), np.asarray(message.pose_covariance, dtype=np.float64).reshape(6, 6)


def extrinsic_to_gtsam(values: list[float]) -> gtsam.Pose3:
    """[x, y, z, qx, qy, qz, qw] -> Pose3; ConfigError unless 7 finite numbers with a non-zero quaternion."""
    array = np.asarray(values, dtype=np.float64)
    if array.shape != (7,) or not np.isfinite(array).all() or np.linalg.norm(array[3:]) < 1e-9:
        raise ConfigError(f"base_to_camera must be [x, y, z, qx, qy, qz, qw] with a non-zero quaternion, got {values}")
    rotation = Rotation.from_quat(array[3:] / np.linalg.norm(array[3:])).as_matrix()
    return gtsam.Pose3(gtsam.Rot3(rotation), array[:3])
