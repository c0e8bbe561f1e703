"""A robot's camera for the fleet test, and its link meter: run as ``python -m test.fleet.robot_driver``.

Publishes a recorded stretch of the synthetic town as the robot's camera would (image, aligned depth and
camera_info at ``--rate`` Hz, each frame with its own stamp) once the base station is connected and the test
says go, and meanwhile counts the serialized bytes of every message on the topics that cross the robot's
link: its words and requested features (robot -> base) and the base's feature requests (base -> robot).
Writes what it counted as JSON to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from aefabmap_msgs.msg import BagOfWords, FeatureRequest, RequestedFeatures
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image

from aefabmap_ros.nodes.messages import time_from_ns

LINK_TOPICS: dict[str, tuple[Any, str]] = {  # topic (in the robot's namespace) -> message type, direction
    "aefabmap/words": (BagOfWords, "robot_to_base"),
    "aefabmap/requested_features": (RequestedFeatures, "robot_to_base"),
    "aefabmap/feature_requests": (FeatureRequest, "base_to_robot"),
}
QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE)


class Driver(Node):
    def __init__(self, robot: str) -> None:
        super().__init__("robot_driver", namespace=f"/{robot}")
        self.image = self.create_publisher(Image, "image", QOS)
        self.depth = self.create_publisher(Image, "depth", QOS)
        self.camera_info = self.create_publisher(CameraInfo, "camera_info", QOS)
        self.counts: dict[str, dict[str, float]] = {}
        for topic, (message_type, _) in LINK_TOPICS.items():
            self.counts[topic] = {"messages": 0, "bytes": 0}
            self.create_subscription(message_type, topic, self._counter(topic), QOS, raw=True)

    def _counter(self, topic: str) -> Any:
        def count(serialized: bytes) -> None:
            self.counts[topic]["messages"] += 1
            self.counts[topic]["bytes"] += len(serialized)
        return count

    def connected(self) -> bool:
        """feature_node, the feature server and the base's fabmap and verifier nodes are all matched."""
        namespace = self.get_namespace()
        return (self.image.get_subscription_count() >= 1 and self.depth.get_subscription_count() >= 1
                and self.camera_info.get_subscription_count() >= 1
                and self.count_subscribers(f"{namespace}/aefabmap/words") >= 2
                and self.count_subscribers(f"{namespace}/aefabmap/requested_features") >= 2
                and self.count_publishers(f"{namespace}/aefabmap/feature_requests") >= 1)

    def publish_frame(self, stamp_ns: int, image: np.ndarray, depth_m: np.ndarray, k: np.ndarray) -> None:
        stamp = time_from_ns(stamp_ns)
        height, width = image.shape
        message = Image(height=height, width=width, encoding="mono8", step=width, data=image.tobytes())
        message.header.stamp, message.header.frame_id = stamp, "camera"
        millimetres = np.rint(np.nan_to_num(depth_m, nan=0.0) * 1000.0).clip(0, 65535).astype(np.uint16)
        depth = Image(height=height, width=width, encoding="16UC1", step=width * 2, data=millimetres.tobytes())
        depth.header = message.header
        info = CameraInfo(height=height, width=width, k=[float(v) for v in k.reshape(-1)],
                          distortion_model="plumb_bob", d=[0.0] * 5)
        info.header = message.header
        self.depth.publish(depth)
        self.camera_info.publish(info)
        self.image.publish(message)


def _spin_for(node: Node, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=max(0.0, min(0.01, end - time.monotonic())))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robot", required=True)
    parser.add_argument("--frames", type=Path, required=True, help="npz: images, depths, stamps_ns, camera_matrix")
    parser.add_argument("--go", type=Path, required=True, help="start publishing once this file exists")
    parser.add_argument("--delay", type=float, default=0.0, help="seconds after go before the first frame")
    parser.add_argument("--rate", type=float, default=10.0)
    parser.add_argument("--linger", type=float, default=4.0, help="seconds to keep counting after the last frame")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    data = np.load(args.frames)
    rclpy.init()
    node = Driver(args.robot)
    try:
        while not node.connected():
            _spin_for(node, 0.1)
        _spin_for(node, 1.0)
        print("[driver] ready", flush=True)
        while not args.go.exists():
            _spin_for(node, 0.05)
        node.counts = {topic: {"messages": 0, "bytes": 0} for topic in LINK_TOPICS}  # only the replay's traffic
        _spin_for(node, args.delay)
        started = time.monotonic()
        for index, stamp_ns in enumerate(data["stamps_ns"].tolist()):
            _spin_for(node, max(0.0, started + index / args.rate - time.monotonic()))
            node.publish_frame(int(stamp_ns), data["images"][index], data["depths"][index], data["camera_matrix"])
        published_s = time.monotonic() - started + 1.0 / args.rate
        _spin_for(node, args.linger)
        result = {"robot": args.robot, "frames_published": len(data["stamps_ns"]), "seconds": published_s,
                  "topics": {topic: {**node.counts[topic], "direction": LINK_TOPICS[topic][1]}
                             for topic in LINK_TOPICS}}
        args.out.write_text(json.dumps(result))
        print("[driver] done", flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
