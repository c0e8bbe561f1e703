"""pose_graph_node in this process, callbacks called directly: the square loop through ROS messages."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from aefabmap_ros.nodes.messages import time_from_ns  # noqa: E402
from aefabmap_ros.nodes.pose_graph_node import PoseGraphNode, gtsam_to_pose  # noqa: E402
from test.backend.test_pose_graph import drifting_odometry, square_truth, stamp  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]


def _odometry(index: int, pose: Any) -> Odometry:
    message = Odometry()
    message.header.stamp = time_from_ns(stamp(index))
    message.pose.pose = gtsam_to_pose(pose)
    return message


def _closure(query: int, place: int, relative: Any, with_pose: bool = True) -> Any:
    closure = msg.LoopClosure(query_id=query, matched_place_id=place)
    closure.header.stamp = time_from_ns(stamp(query))
    closure.matched_stamp = time_from_ns(stamp(place))
    closure.pose_available = with_pose
    closure.pose = gtsam_to_pose(relative)
    closure.pose_covariance = list(np.diag([0.02**2] * 3 + [0.005**2] * 3).reshape(36))
    closure.translation_metric = True
    return closure


def test_pose_graph_node_closes_the_loop_and_writes_tum(tmp_path: Path) -> None:
    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    output = tmp_path / "keyframes.tum"
    node = PoseGraphNode(parameter_overrides=[Parameter("trajectory_file", value=str(output))])
    try:
        paths: list[Any] = []
        transforms: list[Any] = []
        node.path_publisher.publish = paths.append
        node.tf_publisher.publish = transforms.append
        for index, pose in enumerate(odometry):
            node._on_odometry(_odometry(index, pose))
        node._on_odometry(_odometry(3, odometry[3]))  # out of order
        node._on_loop_closure(_closure(end, 0, truth[end].between(truth[0]), with_pose=False))  # no pose
        node._on_loop_closure(_closure(end, 0, truth[end].between(truth[0])))
        node._on_loop_closure(_closure(end, -5, truth[end].between(truth[0])))  # before the odometry
        counts = node.counter.counts
        assert counts["added"] == 1
        assert counts["dropped_odometry_out_of_order"] == 1
        assert counts["dropped_no_pose"] == 1 and counts["dropped_unknown_stamp"] == 1
        (path,) = paths
        assert path.header.frame_id == "map" and len(path.poses) == 2
        last = path.poses[-1].pose.position
        end_error = np.linalg.norm(np.array([last.x, last.y, last.z]) - truth[end].translation())
        odometry_error = np.linalg.norm(odometry[end].translation() - truth[end].translation())
        assert end_error < 0.1 * odometry_error
        assert len(transforms) == 1
        node.close()
        lines = output.read_text().splitlines()
        assert len(lines) == 2 and float(lines[-1].split()[0]) == pytest.approx(stamp(end) / 1e9)
    finally:
        node.destroy_node()
