"""The live view end to end: closure_view_node and aefabmap_view as processes, a Foxglove WebSocket client.

The client connects, sees the advertised channels, subscribes to the closure pictures and receives the picture
of a closure published meanwhile (the frames and the closure from this test, as the nodes would)."""

from __future__ import annotations

import json
import re
import struct
import time

import cv2
import numpy as np
import pytest

from aefabmap_ros.nodes.launch_table import CLOSURE_PICTURES_TOPIC, FRAME_VIEWS_TOPIC, VIEW_TOPICS
from test.ros_processes import LoggedProcess

rclpy = pytest.importorskip("rclpy")
websockets_sync = pytest.importorskip("websockets.sync.client")

SUBPROTOCOL = "foxglove.sdk.v1"  # what the SDK's server speaks (the v1 protocol under the SDK's name)
MESSAGE_DATA_OPCODE = 0x01  # server -> client binary message


def _frame_view(stamp_ns: int, image: np.ndarray, points: np.ndarray, descriptors: np.ndarray) -> object:
    """What feature_node sends a viewer for one frame: its features and a JPEG of the image."""
    from aefabmap_msgs.msg import Features, FrameView

    from aefabmap_ros.nodes.messages import time_from_ns
    from aefabmap_ros.visualization.match_picture import make_thumbnail

    features = Features(descriptor_type="sift", image_width=image.shape[1], image_height=image.shape[0],
                        x=points[:, 0].tolist(), y=points[:, 1].tolist(), size=[5.0] * len(points),
                        angle=[0.0] * len(points), response=[1.0] * len(points), descriptor_length=128,
                        float_descriptors=descriptors.ravel().tolist())
    features.header.stamp = time_from_ns(stamp_ns)
    return FrameView(features=features, thumbnail_jpeg=make_thumbnail(image, image.shape[1]))


def _advertised(socket: object, wanted: str, timeout_s: float) -> dict[str, int]:
    channels: dict[str, int] = {}
    deadline = time.monotonic() + timeout_s
    while wanted not in channels and time.monotonic() < deadline:
        message = socket.recv(timeout=timeout_s)  # type: ignore[attr-defined]
        if isinstance(message, str) and json.loads(message).get("op") == "advertise":
            channels.update({c["topic"]: c["id"] for c in json.loads(message)["channels"]})
    return channels


def test_a_client_gets_the_channels_and_a_closure_picture(tmp_path):
    from aefabmap_msgs.msg import LoopClosure
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CompressedImage

    from aefabmap_ros.nodes.common import RESULT_QOS, pipeline_qos
    from aefabmap_ros.nodes.messages import time_from_ns

    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, size=(240, 320), dtype=np.uint8)
    points = rng.uniform([10, 10], [300, 220], size=(80, 2)).astype(np.float32)
    descriptors = rng.integers(0, 255, size=(80, 128)).astype(np.float32)
    moved = points + np.stack([rng.uniform(2, 15, 80), np.zeros(80)], axis=1).astype(np.float32)
    with LoggedProcess(tmp_path / "view_node.log", "aefabmap_ros.nodes.closure_view_node") as view_node, \
            LoggedProcess(tmp_path / "view.log", "aefabmap_ros.cli.view", "--port", "0") as view:
        view.wait_for_log("[view] serving", timeout_s=60)
        view_node.wait_for_log("closure pictures on", timeout_s=60)
        served = re.search(r"ws://[\d.]+:(\d+)", view.log())
        assert served is not None
        port = int(served.group(1))
        rclpy.init()
        node = rclpy.create_node("test_view_publisher")
        try:
            from aefabmap_msgs.msg import FrameView

            frames = node.create_publisher(FrameView, FRAME_VIEWS_TOPIC, pipeline_qos(100))
            closures = node.create_publisher(LoopClosure, "loop_closures", RESULT_QOS)
            with websockets_sync.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as socket:
                channels = _advertised(socket, f"/{CLOSURE_PICTURES_TOPIC}", timeout_s=30)
                assert {f"/{topic}" for topic in VIEW_TOPICS} <= set(channels)
                socket.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": 7, "channelId": channels[f"/{CLOSURE_PICTURES_TOPIC}"]}]}))
                closure = LoopClosure(query_id=1, matched_place_id=0, probability=0.99, inliers=80)
                closure.header.stamp, closure.matched_stamp = time_from_ns(2_000_000_000), time_from_ns(1_000_000_000)
                picture = None
                deadline = time.monotonic() + 60
                while picture is None and time.monotonic() < deadline:
                    # Published until the picture comes: discovery between three processes takes its time.
                    for stamp_ns, frame_points in ((1_000_000_000, points), (2_000_000_000, moved)):
                        frames.publish(_frame_view(stamp_ns, image, frame_points, descriptors))
                    rclpy.spin_once(node, timeout_sec=0.3)
                    closures.publish(closure)
                    try:
                        message = socket.recv(timeout=1.0)
                    except TimeoutError:
                        continue
                    if isinstance(message, bytes) and message[0] == MESSAGE_DATA_OPCODE:
                        subscription_id, _log_time = struct.unpack_from("<IQ", message, 1)
                        assert subscription_id == 7
                        picture = deserialize_message(message[13:], CompressedImage)
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
        assert picture is not None, f"no picture; view_node log:\n{view_node.log()[-2000:]}"
        assert picture.format == "jpeg" and picture.header.stamp.sec == 2
        decoded = cv2.imdecode(np.frombuffer(bytes(picture.data), np.uint8), cv2.IMREAD_COLOR)
        assert decoded is not None and decoded.shape[1] == 2 * 320  # the query and the place side by side


def test_a_taken_port_is_one_error_line_and_exit_1(capsys):
    import socket

    from aefabmap_ros.cli import view

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert view.main(["--port", str(port), "--duration", "1"]) == 1
    assert capsys.readouterr().err.startswith(f"ERROR: cannot serve on 127.0.0.1:{port}")


def test_a_malformed_extra_topic_is_refused_by_name(capsys):
    from aefabmap_ros.cli import view

    assert view.main(["--topic", "image"]) == 1
    assert "--topic 'image' must be NAME=PACKAGE/msg/TYPE" in capsys.readouterr().err
