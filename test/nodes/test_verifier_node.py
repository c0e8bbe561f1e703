"""verifier_node as a ROS node: its topics, parameters and store, with messages sent over ROS.

What it decides is the chain's (test/verification/test_chain.py); here the adapter around it: messages in
on its topics, closures out on loop_closures, its parameters, its saved store and its shutdown."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from aefabmap_ros.errors import ConfigError, ModelError  # noqa: E402
from aefabmap_ros.features.extraction import Features  # noqa: E402
from aefabmap_ros.nodes.common import RESULT_QOS, pipeline_qos, result_qos  # noqa: E402
from aefabmap_ros.nodes.verifier_node import VerifierNode  # noqa: E402
from test.nodes.captured import Captured  # noqa: E402
from test.nodes.test_nodes_inprocess import _dropped, _features_message, _image, _params  # noqa: E402
from test.reliability import Recorder  # noqa: E402
from test.verification.test_geometric import FOCAL, HEIGHT, WIDTH, _rotation_y, _two_views  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]
SECOND = 1_000_000_000
SIZE = (640, 480)  # _features_message's image size


def _closure(query_sec: int, place_sec: int, query_id: int) -> Any:
    closure = msg.LoopClosure(query_id=query_id, matched_place_id=place_sec, probability=0.995)
    closure.header.stamp = Time(sec=query_sec)
    closure.matched_stamp = Time(sec=place_sec)
    return closure


def _camera_info() -> CameraInfo:
    return CameraInfo(width=WIDTH, height=HEIGHT, k=[FOCAL, 0.0, WIDTH / 2, 0.0, FOCAL, HEIGHT / 2, 0.0, 0.0, 1.0],
                      d=[0.0] * 5, distortion_model="plumb_bob")


def _place_depth_image(sec: int) -> Image:
    """32FC1 depth of _two_views(seed=21)'s place camera at its shared keypoints, NaN elsewhere."""
    from test.verification.test_chain import _place_depth

    return _image(_place_depth().tobytes(), "32FC1", HEIGHT, WIDTH, WIDTH * 4, sec=sec)


def _posterior(query_sec: int, place_secs: list[int], candidate: bool = True) -> Any:
    """fabmap_node's posterior of a query (``candidate``: it also published a loop-closure candidate)."""
    posterior = msg.PlacePosterior(place_ids=place_secs, probabilities=[0.9 / 2**k for k in range(len(place_secs))],
                                   log_likelihoods=[-float(k) for k in range(len(place_secs))],
                                   loop_closure_candidate=candidate)
    posterior.header.stamp = Time(sec=query_sec)
    posterior.place_stamps = [Time(sec=sec) for sec in place_secs]
    return posterior


def _odometry(sec: int, pose: Any) -> Any:
    """nav_msgs/Odometry of the camera (its own base frame) at ``sec``; ``pose`` a gtsam Pose3."""
    from nav_msgs.msg import Odometry

    from aefabmap_ros.nodes.gtsam_poses import gtsam_to_pose

    message = Odometry()
    message.header.stamp = Time(sec=sec)
    message.pose.pose = gtsam_to_pose(pose)
    return message


def _spin_until(executor: SingleThreadedExecutor, done: Callable[[], bool], timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return done()


def test_verifier_node_publishes_verified_closures_sent_over_ros() -> None:
    """Features, camera_info, depth, candidates and their queries' posteriors on the node's topics: the true
    revisit comes out on loop_closures with its inliers and its metric pose, the aliased one does not."""
    query, place, _ = _two_views(seed=21)
    _, unrelated, _ = _two_views(seed=22)
    node = VerifierNode(parameter_overrides=_params(odometry_gate=False, depth_topic="depth"))
    peer = rclpy.create_node("verifier_test_peer")
    executor = SingleThreadedExecutor()
    try:
        assert node.publisher.topic_name == "/loop_closures"
        assert [s.topic_name for s in node.subscriptions] == [
            "/aefabmap/features", "/aefabmap/skipped_frames", "/loop_closure_candidates", "/camera_info", "/depth",
            "/place_posteriors"]
        received: list[Any] = []
        peer.create_subscription(msg.LoopClosure, "loop_closures", received.append, RESULT_QOS)
        features = peer.create_publisher(msg.Features, "aefabmap/features", pipeline_qos(100))
        candidates = peer.create_publisher(msg.LoopClosure, "loop_closure_candidates", result_qos(100))
        posteriors = peer.create_publisher(msg.PlacePosterior, "place_posteriors", result_qos(100))
        camera_info = peer.create_publisher(CameraInfo, "camera_info", RESULT_QOS)
        depth = peer.create_publisher(Image, "depth", RESULT_QOS)
        executor.add_node(node)
        executor.add_node(peer)
        publishers = (features, candidates, posteriors, camera_info, depth)
        assert _spin_until(executor, lambda: all(p.get_subscription_count() for p in publishers)
                           and peer.count_publishers("/loop_closures") > 0)
        camera_info.publish(_camera_info())
        depth.publish(_place_depth_image(1))
        for sec, view in ((1, place), (2, unrelated), (3, query), (4, query)):
            features.publish(_features_message(view, sec))
        assert _spin_until(executor, lambda: len(node.store) == 4 and node.chain.pairs.camera is not None
                           and node.store.depths is not None and SECOND in node.store.depths)
        candidates.publish(_closure(3, 2, query_id=10))  # FAB-MAP matched the unrelated place: rejected
        posteriors.publish(_posterior(3, [2, 1]))
        candidates.publish(_closure(4, 1, query_id=11))  # the true place
        posteriors.publish(_posterior(4, [1, 2]))
        assert not _spin_until(executor, lambda: bool(received), timeout_s=1.0)  # the queries wait for their depth
        depth.publish(_place_depth_image(5))  # a later frame's: theirs will not come, they go on without it
        assert _spin_until(executor, lambda: len(received) == 1 and node.counter.counts["rejected"] == 1)
        (closure,) = received
        assert (closure.query_id, closure.matched_place_id, closure.matched_stamp.sec) == (11, 1, 1)
        assert closure.inliers >= 100 and closure.pose_available and closure.translation_metric
        position = closure.pose.position
        expected = -_rotation_y(0.15).T @ np.array([0.8, 0.1, 0.3])
        assert np.linalg.norm([position.x - expected[0], position.y - expected[1], position.z - expected[2]]) <= 0.05
    finally:
        executor.shutdown()
        peer.destroy_node()
        node.destroy_node()


def test_verifier_node_refuses_bad_parameters() -> None:
    with pytest.raises(ConfigError, match="min_inliers"):
        VerifierNode(parameter_overrides=_params(min_inliers=3))
    for name, value in (("max_stored_frames", 0), ("max_store_mb", 0.0), ("max_awaiting_odometry", 0),
                        ("odometry_wait_s", -1.0), ("depth_wait_s", -1.0), ("drop_after_lag_s", 0.1)):
        with pytest.raises(ConfigError, match=name):
            VerifierNode(parameter_overrides=_params(**{name: value}))


def test_verifier_node_applies_runtime_settings_and_refuses_the_rest() -> None:
    node = VerifierNode()
    try:
        (applied,) = node.set_parameters([Parameter("min_inliers", value=40)])
        assert applied.successful and node.chain.config.min_inliers == 40
        (fixed,) = node.set_parameters([Parameter("max_stored_frames", value=5)])
        assert not fixed.successful and "read at start-up only" in fixed.reason
        (budget,) = node.set_parameters([Parameter("max_store_mb", value=1.0)])
        assert not budget.successful and node.store.max_frames == 20000 and node.store.max_bytes == 512 * 2**20
    finally:
        node.destroy_node()


@pytest.mark.reliability
def test_verifier_node_survives_descriptors_of_another_length(tmp_path: Path, reliability: Recorder) -> None:
    """A 64-d frame among 128-d ones: refused by the store (so it cannot poison a save), and the closure of the
    frames of one kind still published."""
    query, place, _ = _two_views(seed=31)
    short = Features(query.keypoints, np.ascontiguousarray(query.descriptors[:, :64]), query.descriptor_type)
    store_dir = tmp_path / "store"
    node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0, store_dir=str(store_dir),
                                                    save_period_s=0.0))
    try:
        verified = Captured(node.publisher)
        for sec, features in ((1, place), (2, short), (3, query)):
            node.chain.add_features(sec * SECOND, features, SIZE)
        node.chain.add_detection(node_detection(3, 1, query_id=5))
        assert [m.query_id for m in verified.messages] == [5]
        assert node.counter.counts["dropped_bad_features"] == 1 and len(node.store) == 2
        reliability.bad_inputs("verifier_node", tried=1, survived=_dropped(node.counter))
        assert node.close()  # the store saves
    finally:
        node.destroy_node()
    assert len(list(store_dir.glob("chunk-*.npz"))) == 1


def node_detection(query_sec: int, place_sec: int, query_id: int) -> Any:
    from aefabmap_ros.nodes.closure_messages import detection_from_message

    return detection_from_message(_closure(query_sec, place_sec, query_id))


@pytest.mark.reliability
def test_verifier_node_keeps_its_store_across_a_restart(tmp_path: Path, reliability: Recorder) -> None:
    query, place, _ = _two_views(seed=23)
    store_dir = tmp_path / "map.features"
    first = VerifierNode(parameter_overrides=_params(store_dir=str(store_dir), save_period_s=0.0))
    try:
        first.chain.add_features(SECOND, place, SIZE)
        assert first.close()  # saves on shutdown
    finally:
        first.destroy_node()
    assert len(list(store_dir.glob("chunk-*.npz"))) == 1
    second = VerifierNode(parameter_overrides=_params(store_dir=str(store_dir), candidates=1))
    try:
        verified = Captured(second.publisher)
        assert SECOND in second.store
        second.chain.add_features(2 * SECOND, query, SIZE)
        second.chain.add_detection(node_detection(2, 1, query_id=30))  # its place was seen before the restart
        assert [m.query_id for m in verified.messages] == [30]
    finally:
        second.destroy_node()
    chunk = next(store_dir.glob("chunk-*.npz"))
    chunk.write_bytes(b"corrupt")
    with pytest.raises(ModelError, match="cannot read feature store chunk"):
        VerifierNode(parameter_overrides=_params(store_dir=str(store_dir)))
    assert chunk.read_bytes() == b"corrupt"  # refused, not overwritten
    # Refused at start with the file left as it was; its frames are unreadable, nothing else is lost.
    reliability.fault("corrupt feature store chunk at start (verifier)", injected=1, survived=1, places_lost=0)
