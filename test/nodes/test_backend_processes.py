"""pose_graph_node as its own process, fed as in the demo: a bag's odometry replayed with
``aefabmap_replay --with /odom`` and a loop closure on ``loop_closures``; it writes its TUM trajectory
on shutdown and puts map -> odom on /tf (tf2_msgs built by setup.sh)."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_ros.io import bags  # noqa: E402
from aefabmap_ros.io.messages import time_from_ns  # noqa: E402
from aefabmap_ros.nodes.pose_graph_node import gtsam_to_pose  # noqa: E402
from test.core.test_pose_graph import drifting_odometry, square_truth, stamp  # noqa: E402
from test.ros_processes import LoggedProcess  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.usefixtures("ros_context")]


def _odometry_bag(path: Path, odometry: list[Any]) -> None:
    """A tiny image per frame and the frame's odometry, as aefabmap_synth writes them."""
    with bags.BagWriter(path) as writer:
        writer.add_topic("/cam", bags.IMAGE_TYPE)
        writer.add_topic("/odom", bags.ODOMETRY_TYPE)
        for index, pose in enumerate(odometry):
            writer.write("/odom", stamp(index), bags.make_odometry_message(pose.matrix(), stamp(index)))
            writer.write("/cam", stamp(index), bags.make_image_message(np.zeros((4, 4), np.uint8), stamp(index)))


def test_replayed_odometry_and_a_closure_reach_the_backend_process(tmp_path: Path) -> None:
    from tf2_msgs.msg import TFMessage

    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    bag, trajectory = tmp_path / "bag", tmp_path / "keyframes.tum"
    _odometry_bag(bag, odometry)
    node = rclpy.create_node("backend_test")
    transforms: list[Any] = []
    node.create_subscription(TFMessage, "/tf", transforms.append, 10)
    closures = node.create_publisher(msg.LoopClosure, "loop_closures", 10)
    try:
        with LoggedProcess(tmp_path / "backend.log", "aefabmap_ros.nodes.pose_graph_node", "--ros-args",
                           "-p", f"trajectory_file:={trajectory}") as backend:
            backend.wait_for_log("pose graph (example backend)", timeout_s=90)
            with LoggedProcess(tmp_path / "replay.log", "aefabmap_ros.cli.replay", bag, "--topic", "/cam",
                               "--with", "/odom=1", "--rate", "0", "--wait-subscribers", "0", "--quiet") as replay:
                assert replay.wait(timeout_s=120) == 0, replay.log()
            closure = msg.LoopClosure(query_id=end, matched_place_id=0, pose_available=True,
                                      translation_metric=True, pose=gtsam_to_pose(truth[end].between(truth[0])))
            closure.header.stamp, closure.matched_stamp = time_from_ns(stamp(end)), time_from_ns(stamp(0))
            closure.pose_covariance = list(np.diag([0.02**2] * 3 + [0.005**2] * 3).reshape(36))
            deadline = time.monotonic() + 60
            while closures.get_subscription_count() == 0 and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.1)
            closures.publish(closure)
            deadline = time.monotonic() + 60
            while not transforms and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.1)
            assert backend.stop(signal.SIGINT) == 0, backend.log()
    finally:
        node.destroy_node()
    assert transforms, "no map -> odom on /tf"
    assert transforms[0].transforms[0].child_frame_id == "odom"
    log = (tmp_path / "backend.log").read_text()
    # Added: both endpoints lie in the odometry received, so its first sample (frame 0) was not lost to discovery.
    assert "added=1" in log, log
    rows = np.loadtxt(trajectory)
    assert rows.shape == (2, 8)  # the first odometry pose (the anchor) and the loop's end
    end_error = np.linalg.norm(rows[-1, 1:4] - truth[end].translation())
    assert end_error < 0.1 * np.linalg.norm(odometry[end].translation() - truth[end].translation())
