"""closure_view_node in this process, callbacks called directly: frames kept serialized, a picture per closure,
bad frames counted by name, refused-candidate pictures bounded by their rate."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402

from aefabmap_ros.nodes.closure_view_node import ClosureViewNode  # noqa: E402
from aefabmap_ros.nodes.messages import time_from_ns  # noqa: E402
from aefabmap_ros.visualization.match_picture import decode_jpeg, make_thumbnail  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]
RNG = np.random.default_rng(5)
POINTS = RNG.uniform([10, 10], [300, 220], size=(80, 2)).astype(np.float32)
DESCRIPTORS = RNG.integers(0, 255, size=(80, 128)).astype(np.float32)
IMAGE = RNG.integers(0, 255, size=(240, 320), dtype=np.uint8)


class Watched:
    """A publisher someone subscribes to: what the node publishes on it is kept."""

    def __init__(self, publisher: Any) -> None:
        self.messages: list[Any] = []
        publisher.publish = self.messages.append
        publisher.get_subscription_count = lambda: 1


def _frame(second: int, points: np.ndarray = POINTS, nanosec: int = 0) -> bytes:
    features = msg.Features(descriptor_type="sift", image_width=320, image_height=240, x=points[:, 0].tolist(),
                            y=points[:, 1].tolist(), size=[5.0] * len(points), angle=[0.0] * len(points),
                            response=[1.0] * len(points), descriptor_length=128,
                            float_descriptors=DESCRIPTORS.ravel().tolist())
    features.header.stamp = Time(sec=second, nanosec=nanosec)
    return bytes(serialize_message(msg.FrameView(features=features, thumbnail_jpeg=make_thumbnail(IMAGE, 320))))


def _closure(query_second: int, place_second: int) -> Any:
    closure = msg.LoopClosure(query_id=query_second, matched_place_id=place_second, probability=0.9)
    closure.header.stamp, closure.matched_stamp = time_from_ns(query_second * 10**9), time_from_ns(place_second * 10**9)
    return closure


def test_a_closure_picture_from_kept_frames_and_a_bad_frame_counted_by_name() -> None:
    node = ClosureViewNode()
    try:
        pictures = Watched(node.closure_publisher)
        node._on_frame(_frame(1))
        node._on_frame(_frame(2, POINTS + np.float32(3)))
        broken = POINTS.copy()
        broken[0, 0] = np.nan
        node._on_frame(_frame(3, broken))  # kept as it came: found bad only when a picture needs it
        node._on_frame(_frame(4, nanosec=2_000_000_000))  # not a ROS time
        assert node.counter.counts["dropped_bad_stamp"] == 1 and len(node.album.frames) == 3

        node._on_closure(_closure(2, 1))
        assert len(pictures.messages) == 1 and pictures.messages[0].header.stamp.sec == 2
        assert decode_jpeg(bytes(pictures.messages[0].data)).shape[1] == 2 * 320
        node._on_closure(_closure(3, 1))
        assert node.counter.counts["dropped_bad_frame"] == 1 and len(pictures.messages) == 1
    finally:
        node.destroy_node()


def test_refused_pictures_are_bounded_by_their_rate_closures_are_not() -> None:
    node = ClosureViewNode()
    try:
        closures, refused = Watched(node.closure_publisher), Watched(node.refused_publisher)
        for second in (1, 2, 3, 4, 5):
            node._on_frame(_frame(second))
        for query in (2, 3, 4):  # three candidates the verifier passes over ...
            node._on_candidate(_closure(query, 1))
        node._on_closure(_closure(5, 1))  # ... once a later query's closure comes
        assert len(closures.messages) == 1
        assert len(refused.messages) == 1  # at most 2 a second: the other two counted, not drawn
        assert node.counter.counts["refused_pictures_over_rate"] == 2
    finally:
        node.destroy_node()
