"""verifier_node's sensor and FAB-MAP inputs: each malformed kind is counted by its name and changes nothing,
and the valid message after it is processed as if it had never come."""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.odometry_gate import OdometryGate

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_ros.nodes.verifier_node import VerifierNode  # noqa: E402
from test.nodes.captured import Captured  # noqa: E402
from test.nodes.test_nodes_inprocess import _features_message, _image, _params  # noqa: E402
from test.nodes.test_verifier_node import (  # noqa: E402
    _camera_info,
    _closure,
    _odometry,
    _place_depth_image,
    _posterior,
)
from test.verification.test_geometric import _rotation_y, _two_views  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]
SECOND = 1_000_000_000


def _small_depth(sec: int) -> Any:
    """A 320x240 32FC1 depth image: half the size of the 640x480 images the features came from."""
    return _image(np.full((240, 320), 2.0, np.float32).tobytes(), "32FC1", 240, 320, 320 * 4, sec=sec)


def _only_drops(counts: Any, *names: str) -> bool:
    return {key for key in counts if key.startswith("dropped_")} <= {f"dropped_{name}" for name in names}


def test_a_depth_image_of_another_size_is_dropped_in_either_order() -> None:
    """Depth after its features (checked before decoding) and before any features (checked when they come):
    no wrong depths are kept; the right-size depth image then gives the metric pose."""
    query, place, _ = _two_views(seed=21)
    node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0, depth_topic="depth"))
    try:
        assert node.store.depths is not None
        verified = Captured(node.publisher)
        node._on_depth(_small_depth(1))  # before any features: the image size is not known yet, it waits
        node._on_features(_features_message(place, 1))
        assert node.counter.counts["dropped_depth_size_mismatch"] == 1 and SECOND not in node.store.depths
        assert len(node.store) == 1  # the features themselves are kept
        node._on_depth(_small_depth(1))  # after the features: refused at once
        assert node.counter.counts["dropped_depth_size_mismatch"] == 2 and SECOND not in node.store.depths
        node._on_camera_info(_camera_info())
        node._on_depth(_place_depth_image(1))  # 640x480: kept
        assert SECOND in node.store.depths
        node._on_features(_features_message(query, 3))
        node._on_loop_closure(_closure(3, 1, query_id=10))
        node._on_depth(_place_depth_image(4))  # a later frame's: the query's will not come, it goes on without it
        (closure,) = verified.messages
        assert closure.pose_available and closure.translation_metric
        assert _only_drops(node.counter.counts, "depth_size_mismatch")
    finally:
        node.destroy_node()


@pytest.mark.parametrize("k", [
    [0.0] * 9,  # an uncalibrated camera
    [0.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0],  # fx 0
    [-500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0],
    [500.0, 0.0, 320.0, 0.0, float("nan"), 240.0, 0.0, 0.0, 1.0],
    [float("inf"), 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0],
])
def test_a_camera_info_without_usable_intrinsics_keeps_the_previous_ones(k: list[float]) -> None:
    query, place, _ = _two_views(seed=21)
    node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0))
    try:
        verified = Captured(node.publisher)
        node._on_camera_info(_camera_info())
        camera = node.chain.pairs.camera
        broken = _camera_info()
        broken.k = k
        node._on_camera_info(broken)
        assert node.counter.counts["dropped_bad_camera_info"] == 1 and node.chain.pairs.camera is camera
        node._on_features(_features_message(place, 1))
        node._on_features(_features_message(query, 3))
        node._on_loop_closure(_closure(3, 1, query_id=10))
        node._on_depth(_place_depth_image(4))  # a later frame's: the query's will not come, it goes on without it
        (closure,) = verified.messages
        assert closure.pose_available and node.counter.counts["pose_ok"] == 1
        assert _only_drops(node.counter.counts, "bad_camera_info")
    finally:
        node.destroy_node()


def test_a_posterior_whose_arrays_differ_in_length_is_dropped() -> None:
    query, place, _ = _two_views(seed=24)
    node = VerifierNode(parameter_overrides=_params(max_pending=2))  # candidates 5: closures wait for posteriors
    try:
        verified = Captured(node.publisher)
        node._on_features(_features_message(place, 1))
        node._on_features(_features_message(query, 4))
        node._on_loop_closure(_closure(4, 1, query_id=40))
        broken = _posterior(4, [1, 2])
        broken.probabilities = [0.9]
        node._on_posterior(broken)
        assert node.counter.counts["dropped_bad_posterior"] == 1 and not verified.messages
        assert len(node.chain.pending) == 1 and not node.chain.posteriors
        node._on_posterior(_posterior(4, [1]))
        (closure,) = verified.messages
        assert closure.query_id == 40 and closure.inliers >= 100
        assert _only_drops(node.counter.counts, "bad_posterior")
    finally:
        node.destroy_node()


def test_the_odometry_gate_never_takes_a_nan() -> None:
    """Odometry with a NaN or a zero quaternion, a stamp that is not a ROS time: dropped before the gate, which
    then judges the closure on the valid odometry alone (a closure whose own pose is broken: test_odometry_wait.py)."""
    query, place, _ = _two_views(seed=21)
    rotation, translation = _rotation_y(0.15), np.array([0.8, 0.1, 0.3])
    place_in_query = gtsam.Pose3(gtsam.Rot3(rotation.T), -rotation.T @ translation)
    node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0))
    try:
        assert node.chain.odometry.gate is not None
        verified = Captured(node.publisher)
        node._on_camera_info(_camera_info())
        for sec, features in ((1, place), (3, query)):
            node._on_features(_features_message(features, sec))
        for sec, pose in ((1, place_in_query), (2, place_in_query), (3, gtsam.Pose3())):
            for kind in ("nan", "zero", "nanosec"):
                broken = _odometry(sec, pose)
                if kind == "nan":
                    broken.pose.pose.position.z = float("nan")
                elif kind == "zero":
                    orientation = broken.pose.pose.orientation
                    orientation.x = orientation.y = orientation.z = orientation.w = 0.0
                else:
                    broken.header.stamp.nanosec = 1_000_000_000
                node._on_odometry(broken)
            node._on_odometry(_odometry(sec, pose))
        gate = node.chain.odometry.gate
        assert isinstance(gate, OdometryGate)
        assert node.counter.counts["dropped_bad_odometry"] == 9 and len(gate.odometry) == 3
        node._on_loop_closure(_closure(3, 1, query_id=31))
        (closure,) = verified.messages
        assert closure.query_id == 31
        assert _only_drops(node.counter.counts, "bad_odometry")
    finally:
        node.destroy_node()
