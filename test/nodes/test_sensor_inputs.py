"""Sensor inputs connect to a best-effort driver as to a reliable replay, and say so when they cannot."""

from __future__ import annotations

import itertools
import threading
import time
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from aefabmap_ros.errors import ConfigError  # noqa: E402
from aefabmap_ros.nodes.common import DropCounter  # noqa: E402
from aefabmap_ros.nodes.feature_node import FeatureNode  # noqa: E402
from aefabmap_ros.nodes.frame_gate import DetectionRate  # noqa: E402
from aefabmap_ros.nodes.pose_graph_node import PoseGraphNode  # noqa: E402
from aefabmap_ros.nodes.sensor_inputs import (  # noqa: E402
    SensorInput,
    check_sensor_qos,
    should_switch_to_best_effort,
)
from aefabmap_ros.nodes.verifier_node import VerifierNode  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
PUBLISHER_QOS = {"reliable": RELIABLE, "best_effort": qos_profile_sensor_data}


def _spin_until(executor: SingleThreadedExecutor, done: Any, seconds: float = 20.0) -> bool:
    for _ in range(int(seconds / 0.05)):
        if done():
            return True
        _spin_for(executor, 0.05)
    return done()


def _publish_until(executor: SingleThreadedExecutor, publisher: Any, make: Any, received: Any,
                   seconds: float = 20.0) -> bool:
    """Publish a message every spin round until ``received()`` (discovery and a QoS switch take a moment)."""
    sec = 1
    for _ in range(int(seconds / 0.1)):
        if received():
            return True
        publisher.publish(make(sec))
        sec += 1
        _spin_for(executor, 0.1)
    return received()


def _spin_for(executor: SingleThreadedExecutor, seconds: float) -> None:
    """Every callback that comes due within ``seconds`` (spin_once runs one: several nodes share the executor)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)


def test_policies_and_when_auto_moves_to_best_effort() -> None:
    assert check_sensor_qos("sensor_data", "p") == "best_effort"
    assert check_sensor_qos("auto", "p") == "auto"
    with pytest.raises(ConfigError, match="parameter image_qos='fast' must be one of"):
        check_sensor_qos("fast", "image_qos")
    assert should_switch_to_best_effort("auto", False, [False, True])
    assert not should_switch_to_best_effort("auto", False, [False])  # reliable publishers: stay reliable
    assert not should_switch_to_best_effort("auto", True, [True])  # already best effort
    assert not should_switch_to_best_effort("reliable", False, [True])  # the user asked for reliable


def test_detection_rate_takes_frames_by_stamp() -> None:
    period_ns = round(1e9 / 30)
    stamps = [i * period_ns + (1_000_000 if i % 2 else -1_000_000) for i in range(1, 31)]  # 30 Hz, 1 ms jitter
    rate = DetectionRate(10.0)
    taken = [stamp for stamp in stamps if rate.take(stamp)]
    assert len(taken) == 10  # every third frame, not every fourth, despite the jitter
    assert all(b - a >= 0.09e9 for a, b in itertools.pairwise(taken))
    assert DetectionRate(10.0).take(5) and not _take_twice(DetectionRate(10.0), 5)  # a repeated stamp is skipped
    restarted = DetectionRate(10.0)
    assert restarted.take(10**9) and restarted.take(0)  # a stamp before the last one taken starts afresh
    every = DetectionRate(0.0)
    assert all(every.take(stamp) for stamp in (1, 1, 2, 3))
    with pytest.raises(ValueError, match="must be >= 0"):
        DetectionRate(-1.0)


def _take_twice(rate: DetectionRate, stamp: int) -> bool:
    rate.take(stamp)
    return rate.take(stamp)


@pytest.mark.parametrize("policy", ["auto", "best_effort", "reliable"])
@pytest.mark.parametrize("offered", ["reliable", "best_effort"])
def test_qos_matrix(policy: str, offered: str) -> None:
    """Every policy against every publisher: received, except reliable-only against a best-effort driver,
    which is reported by name instead of passing silently."""
    node = rclpy.create_node("sensor_input_test")
    driver = rclpy.create_node("fake_driver")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(driver)
    received: list[Any] = []
    counter = DropCounter(node)
    warnings: list[str] = []
    node.get_logger().warning = lambda text, **_: warnings.append(text)
    try:
        sensor = SensorInput(node, CameraInfo, "cam/camera_info", received.append, policy=policy, depth=10,
                             counter=counter, without_it="no poses", silent_after_s=1.0)
        publisher = driver.create_publisher(CameraInfo, "cam/camera_info", PUBLISHER_QOS[offered])

        def info(sec: int) -> CameraInfo:
            message = CameraInfo()
            message.header.stamp = Time(sec=sec)
            return message

        expect_delivery = not (policy == "reliable" and offered == "best_effort")
        got = _publish_until(executor, publisher, info, lambda: len(received) >= 3,
                             seconds=10.0 if expect_delivery else 3.0)
        assert got == expect_delivery
        assert sensor.best_effort == (policy == "best_effort" or (policy == "auto" and offered == "best_effort"))
        if not expect_delivery:
            _spin_until(executor, lambda: len(warnings) >= 2, seconds=5.0)
            assert any("/cam/camera_info: 1 publisher(s) offer best effort" in text and "no poses" in text
                       for text in warnings), warnings
            assert any("1 publisher(s) on /cam/camera_info but no message after 1 s: no poses" in text
                       for text in warnings), warnings
        else:
            assert not warnings
    finally:
        executor.shutdown()
        driver.destroy_node()
        node.destroy_node()


def test_a_topic_nobody_publishes_is_reported_once_by_name() -> None:
    node = rclpy.create_node("sensor_input_silent")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    warnings: list[str] = []
    node.get_logger().warning = lambda text, **_: warnings.append(text)
    try:
        SensorInput(node, Odometry, "odometry/filtered", lambda _m: None, policy="auto", depth=10,
                    counter=DropCounter(node), without_it="no gate", silent_after_s=0.5)
        _spin_until(executor, lambda: False, seconds=2.0)
        assert warnings == ["no publisher on /odometry/filtered after 0.5 s: no gate"]
    finally:
        executor.shutdown()
        node.destroy_node()


def test_a_topic_that_loses_many_messages_on_the_way_is_reported_once_with_the_cure() -> None:
    node = rclpy.create_node("sensor_input_lossy")
    warnings: list[str] = []
    node.get_logger().warning = lambda text, **_: warnings.append(text)
    try:
        sensor = SensorInput(node, Image, "camera/depth", lambda _m: None, policy="auto", depth=10,
                             counter=DropCounter(node), without_it="no metric poses")
        sensor.received = 100
        sensor._on_lost(9)  # a few: a busy moment, not worth a word
        sensor._check()
        assert warnings == []
        sensor._on_lost(50)
        sensor._check()
        sensor._check()
        assert len(warnings) == 1
        assert warnings[0].startswith("59 of 159 messages on /camera/depth never reached the node")
        assert "fastdds_large_messages.xml" in warnings[0] and warnings[0].endswith("no metric poses")
        assert sensor.summary() == "/camera/depth: 100 received, 59 lost on the way (reliable)"
    finally:
        node.destroy_node()


def _camera_info(sec: int) -> CameraInfo:
    message = CameraInfo(width=320, height=240)
    message.header.stamp = Time(sec=sec)
    message.k = [200.0, 0.0, 160.0, 0.0, 200.0, 120.0, 0.0, 0.0, 1.0]
    return message


def _odometry(sec: int) -> Odometry:
    message = Odometry()
    message.header.stamp = Time(sec=sec)
    message.pose.pose.position.x = float(sec)
    message.pose.pose.orientation.w = 1.0
    return message


def _depth(sec: int) -> Image:
    message = Image(height=4, width=4, encoding="16UC1", step=8, data=bytes(32))
    message.header.stamp = Time(sec=sec)
    return message


@pytest.mark.parametrize("offered", ["reliable", "best_effort"])
def test_every_input_of_the_verifier_and_the_backend_hears_a_driver_of_either_qos(offered: str) -> None:
    """camera_info, depth and odometry from a driver with the sensor-data profile reach the nodes as a replay's do."""
    verifier = VerifierNode(parameter_overrides=[Parameter("depth_topic", value="/camera/depth")])
    backend = PoseGraphNode()
    driver = rclpy.create_node("fake_rgbd_driver")
    executor = SingleThreadedExecutor()
    for node in (verifier, backend, driver):
        executor.add_node(node)
    qos = PUBLISHER_QOS[offered]
    try:
        camera_info = driver.create_publisher(CameraInfo, "camera_info", qos)
        assert _publish_until(executor, camera_info, _camera_info, lambda: verifier.chain.pairs.camera is not None)
        depth = driver.create_publisher(Image, "/camera/depth", qos)
        depth_input = next(i for i in verifier.inputs if i.topic == "/camera/depth")
        assert _publish_until(executor, depth, _depth, lambda: depth_input.received > 0)
        odometry = driver.create_publisher(Odometry, "odom", qos)
        verifier_odometry = next(i for i in verifier.inputs if i.topic == "/odom")
        assert _publish_until(executor, odometry, _odometry,
                              lambda: verifier_odometry.received > 0 and backend.odometry.received > 0), (
            [(i.topic, i.best_effort, i.received) for i in verifier.inputs], backend.odometry.summary(),
            verifier.counter.counts, backend.counter.counts)
        assert all(i.best_effort == (offered == "best_effort") for i in (*verifier.inputs, backend.odometry))
        assert "received" in verifier.inputs[0].summary()
    finally:
        executor.shutdown()
        driver.destroy_node()
        backend.destroy_node()
        verifier.destroy_node()


def test_feature_node_announces_the_frames_its_detection_rate_skips(monkeypatch: pytest.MonkeyPatch) -> None:
    """At 10 Hz from a 30 Hz camera: two frames in three are skipped, counted, and announced with their stamps."""
    processed: list[int] = []
    monkeypatch.setattr(FeatureNode, "_on_image", lambda _node, message: processed.append(message.header.stamp.nanosec))
    node = FeatureNode(parameter_overrides=[Parameter("detection_rate_hz", value=10.0),
                                            Parameter("drop_when_busy", value=False)])
    announced: list[Header] = []
    node.skipped_publisher.publish = announced.append
    try:
        for frame in range(9):
            image = Image()
            image.header.stamp = Time(sec=0, nanosec=round(frame * 1e9 / 30))
            node._on_frame(image)
        assert len(processed) == 3
        assert node.counter.counts["skipped_detection_rate"] == 6
        assert [h.stamp.nanosec for h in announced] == [round(f * 1e9 / 30) for f in (1, 2, 4, 5, 7, 8)]
        assert {h.frame_id for h in announced} == {"detection_rate"}
    finally:
        node.destroy_node()


def test_busy_drops_are_announced_too(monkeypatch: pytest.MonkeyPatch) -> None:
    started, release = threading.Event(), threading.Event()

    def hold(_node: Any, _message: Any) -> None:
        started.set()
        release.wait(timeout=30)

    monkeypatch.setattr(FeatureNode, "_on_image", hold)
    node = FeatureNode(parameter_overrides=[Parameter("detection_rate_hz", value=0.0)])
    announced: list[Header] = []
    node.skipped_publisher.publish = announced.append
    try:
        node._on_frame(_stamped_image(1))
        assert started.wait(timeout=30)  # the worker holds frame 1: 2 waits, 3 replaces it, 4 replaces 3
        for sec in (2, 3, 4):
            node._on_frame(_stamped_image(sec))
        assert [(h.stamp.sec, h.frame_id) for h in announced] == [(2, "busy"), (3, "busy")]
        assert node.counter.counts["dropped_busy"] == 2
    finally:
        release.set()
        node.destroy_node()


def _stamped_image(sec: int) -> Image:
    image = Image()
    image.header.stamp = Time(sec=sec)
    return image
