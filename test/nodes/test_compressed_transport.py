"""Compressed image bags through the separate-process feature node, as a camera's bag is replayed.

image_transport's convention: the compressed stream of ``image`` is ``<resolved image topic>/compressed``;
aefabmap_replay publishes a bag's CompressedImage topic there, and feature_node listens there by default.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_ros.io import bag_messages, bags  # noqa: E402
from aefabmap_ros.stamps import stamp_to_ns  # noqa: E402
from test.ros_processes import LoggedProcess  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.usefixtures("ros_context")]

FRAMES = 4


def _frames() -> list[tuple[int, np.ndarray]]:
    """Textured grey images (blocky noise, blurred) on which SIFT finds plenty of keypoints."""
    rng = np.random.default_rng(7)
    frames = []
    for index in range(FRAMES):
        blocks = rng.integers(0, 256, (15, 20), dtype=np.uint8)
        image = cv2.GaussianBlur(cv2.resize(blocks, (160, 120), interpolation=cv2.INTER_NEAREST), (3, 3), 0)
        frames.append(((index + 1) * 100_000_000, image))
    return frames


def _compressed_bag(path: Path, topic: str, frames: list[tuple[int, np.ndarray]]) -> None:
    """The frames as lossless PNG sensor_msgs/CompressedImage, as image_transport's png mode records them."""
    compressed_type = bag_messages.get_typestore().types[bag_messages.COMPRESSED_IMAGE_TYPE]
    with bags.BagWriter(path) as writer:
        writer.add_topic(topic, bag_messages.COMPRESSED_IMAGE_TYPE)
        for stamp_ns, image in frames:
            ok, png = cv2.imencode(".png", image)
            assert ok
            message = compressed_type(header=bag_messages.make_header(stamp_ns), format="mono8; png compressed mono8",
                                      data=png.reshape(-1))
            writer.write(topic, stamp_ns, message)


def _feature_node(tmp_path: Path, name: str, *ros_args: str) -> LoggedProcess:
    return LoggedProcess(tmp_path / f"{name}.log", "aefabmap_ros.nodes.feature_node", "--ros-args",
                         "-p", "image_qos:=reliable", "-p", "drop_when_busy:=false", "-p", "queue_depth:=50", *ros_args)


def _replay(tmp_path: Path, name: str, bag: Path, *args: str) -> LoggedProcess:
    return LoggedProcess(tmp_path / f"{name}.log", "aefabmap_ros.cli.replay", bag, "--topic", "/cam",
                         "--rate", "0", "--quiet", "--wait-timeout", "60", *args)


def _features_through(tmp_path: Path, name: str, bag: Path, remap: tuple[str, ...] = (),
                      replay_args: tuple[str, ...] = ()) -> dict[int, dict[str, np.ndarray]]:
    """Replay ``bag`` into a feature_node process; its Features by stamp (keypoints and descriptors)."""
    from aefabmap_msgs.msg import Features

    received: dict[int, dict[str, np.ndarray]] = {}

    def keep(message: Any) -> None:
        received[stamp_to_ns(message.header.stamp)] = {
            field: np.asarray(getattr(message, field)).copy()
            for field in ("x", "y", "size", "angle", "response", "float_descriptors")
        }

    node = rclpy.create_node(f"collect_{name}")
    subscription = node.create_subscription(Features, "aefabmap/features", keep, 50)
    try:
        with _feature_node(tmp_path, f"{name}_feature", *remap) as feature_node:
            feature_node.wait_for_log("extracting", timeout_s=90)
            deadline = time.monotonic() + 60
            while subscription.get_publisher_count() == 0 and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.1)
            with _replay(tmp_path, f"{name}_replay", bag, *replay_args) as replay:
                assert replay.wait(timeout_s=120) == 0, replay.log() + feature_node.log()
            deadline = time.monotonic() + 60
            while len(received) < FRAMES and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        node.destroy_node()
    return received


def test_compressed_bag_gives_the_raw_bags_features(tmp_path: Path) -> None:
    frames = _frames()
    raw_bag, compressed_bag = tmp_path / "raw", tmp_path / "compressed"
    bags.write_image_bag(raw_bag, "/cam", frames)
    _compressed_bag(compressed_bag, "/cam", frames)
    from_raw = _features_through(tmp_path, "raw", raw_bag)
    from_compressed = _features_through(tmp_path, "compressed", compressed_bag)
    assert sorted(from_raw) == [stamp for stamp, _ in frames]
    assert sorted(from_compressed) == sorted(from_raw)
    for stamp, features in from_raw.items():
        assert len(features["x"]) > 20
        for field, values in features.items():
            np.testing.assert_array_equal(from_compressed[stamp][field], values, err_msg=f"{stamp} {field}")


def test_remapping_image_moves_the_compressed_subscription_with_it(tmp_path: Path) -> None:
    """`-r image:=/camera/image_raw` listens on /camera/image_raw/compressed, where replay publishes the bag's
    CompressedImage topic when told the raw image topic."""
    frames = _frames()
    compressed_bag = tmp_path / "compressed"
    _compressed_bag(compressed_bag, "/cam", frames)
    received = _features_through(tmp_path, "remapped", compressed_bag, remap=("-r", "image:=/camera/image_raw"),
                                 replay_args=("--out-topic", "/camera/image_raw"))
    assert sorted(received) == [stamp for stamp, _ in frames]


def test_replay_names_a_subscriber_of_another_type(tmp_path: Path) -> None:
    """A raw Image bag sent where only a CompressedImage subscriber listens: the error says why nothing connects."""
    from sensor_msgs.msg import CompressedImage

    raw_bag = tmp_path / "raw"
    bags.write_image_bag(raw_bag, "/cam", _frames()[:1])
    node = rclpy.create_node("compressed_listener")
    node.create_subscription(CompressedImage, "/elsewhere/image", lambda _message: None, 10)
    try:
        with _replay(tmp_path, "mismatch", raw_bag, "--out-topic", "/elsewhere/image", "--wait-timeout", "5") as replay:
            while replay.process.poll() is None:
                rclpy.spin_once(node, timeout_sec=0.1)
            assert replay.wait(timeout_s=5) == 1
    finally:
        node.destroy_node()
    log = replay.log()
    assert "ERROR: no subscriber on /elsewhere/image" in log, log
    assert "subscriber(s) of type sensor_msgs/CompressedImage" in log and "sensor_msgs/Image" in log, log
