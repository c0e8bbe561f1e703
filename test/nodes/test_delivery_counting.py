"""Messages DDS drops before a callback (reader queue overwritten while busy) are counted by the nodes."""

from __future__ import annotations

from typing import Any

import pytest

from aefabmap_ros.backend.odometry_gate import OdometryGate

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from aefabmap_ros.nodes.feature_node import FeatureNode  # noqa: E402
from test.reliability import Recorder  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]

DEPTH = 2
BURST = 30


def _spin_until(executor: SingleThreadedExecutor, done: Any, attempts: int = 600) -> None:
    for _ in range(attempts):
        if done():
            return
        executor.spin_once(timeout_sec=0.05)
    raise AssertionError("condition not reached")


def _image(sec: int) -> Image:
    image = Image(height=64, width=64, encoding="mono8", step=64, data=bytes(64 * 64))
    image.header.stamp = Time(sec=sec)
    return image


@pytest.mark.reliability
@pytest.mark.parametrize("qos_kind", ["reliable", "sensor_data"])
def test_feature_node_counts_images_its_reader_queue_overwrote(qos_kind: str, reliability: Recorder) -> None:
    """A burst sent while the node takes nothing overflows its queue of DEPTH: every image is then either
    processed, dropped at the door (camera QoS), or counted as lost before the callback."""
    node = FeatureNode(parameter_overrides=[
        Parameter("image_qos", value=qos_kind), Parameter("queue_depth", value=DEPTH),
        Parameter("drop_when_busy", value=qos_kind == "sensor_data"),
        Parameter("subscribe_compressed", value=False)])
    camera = rclpy.create_node("test_camera")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    counts = node.counter.counts

    def accounted() -> int:
        return counts["processed"] + counts["dropped_busy"] + counts["dropped_before_callback"]

    try:
        qos = qos_profile_sensor_data if qos_kind == "sensor_data" else 100
        publisher = camera.create_publisher(Image, "image", qos)
        _spin_until(executor, lambda: publisher.get_subscription_count() > 0)
        sec = 1
        while accounted() == 0:  # a first image, so the node knows where the camera's numbering stands
            publisher.publish(_image(sec))
            sec += 1
            executor.spin_once(timeout_sec=0.2)
        for _ in range(10):
            executor.spin_once(timeout_sec=0.05)
        before = accounted()
        for _ in range(BURST):  # the node takes nothing meanwhile: its queue keeps the last DEPTH images
            publisher.publish(_image(sec))
            sec += 1
        published = BURST
        for attempt in range(400):
            executor.spin_once(timeout_sec=0.05)
            if accounted() - before == published:
                break
            if attempt % 40 == 39:  # a loss after the last image shows only once another one follows
                publisher.publish(_image(sec))
                sec += 1
                published += 1
        assert accounted() - before == published, dict(counts)
        assert counts["dropped_before_callback"] >= BURST - DEPTH
        reliability.drops(f"feature_node, {qos_kind} QoS, {published} images sent into a queue of {DEPTH} "
                          f"while it took none ({accounted() - before} accounted for)", counts)
    finally:
        executor.shutdown()
        node.destroy_node()
        camera.destroy_node()


ODOMETRY_BURST = 1000  # 10 s of 100 Hz odometry


@pytest.mark.reliability
def test_verifier_node_keeps_a_burst_of_odometry_it_was_too_busy_to_take(reliability: Recorder) -> None:
    """A verifier busy for seconds (a long verification, a store being saved) still gets every odometry
    message sent meanwhile: the odometry gate interpolates between them, so a lost one widens its gaps."""
    from nav_msgs.msg import Odometry

    from aefabmap_ros.nodes.verifier_node import VerifierNode

    node = VerifierNode(parameter_overrides=[Parameter("odometry_gate", value=True)])
    robot = rclpy.create_node("test_robot")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        publisher = robot.create_publisher(Odometry, "odom", ODOMETRY_BURST)
        _spin_until(executor, lambda: publisher.get_subscription_count() > 0)
        for index in range(ODOMETRY_BURST):  # the node takes nothing meanwhile
            message = Odometry()
            message.header.stamp = Time(sec=1 + index // 100, nanosec=(index % 100) * 10_000_000)  # 100 Hz
            message.pose.pose.orientation.w = 1.0
            message.pose.pose.position.x = 0.01 * index
            publisher.publish(message)
        gate = node.chain.odometry.gate
        assert isinstance(gate, OdometryGate)
        _spin_until(executor, lambda: len(gate.odometry) == ODOMETRY_BURST, attempts=ODOMETRY_BURST + 400)
        assert node.counter.counts.get("dropped_before_callback", 0) == 0
        reliability.drops(f"verifier_node, {ODOMETRY_BURST} odometry messages sent while it took none",
                          node.counter.counts)
    finally:
        executor.shutdown()
        node.destroy_node()
        robot.destroy_node()
