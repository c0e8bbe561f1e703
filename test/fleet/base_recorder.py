"""The base station's results for the fleet test: run as ``python -m test.fleet.base_recorder OUT``.

Appends one JSON line per message on ``place_posteriors`` (robot, stamp, when it arrived) and ``loop_closures``
(both robots and stamps, inliers, the relative pose) to OUT, until stopped.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import rclpy
from aefabmap_msgs.msg import LoopClosure, PlacePosterior
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from aefabmap_ros.stamps import stamp_to_ns

QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def main() -> None:
    with Path(sys.argv[1]).open("a") as out:
        record(out)


def record(out: Any) -> None:
    rclpy.init()
    node = Node("base_recorder")

    def write(record: dict[str, Any]) -> None:
        out.write(json.dumps(record) + "\n")
        out.flush()

    def on_posterior(message: PlacePosterior) -> None:
        write({"kind": "posterior", "robot": message.robot, "stamp_ns": stamp_to_ns(message.header.stamp),
               "query_id": int(message.query_id), "received_s": time.monotonic()})

    def on_closure(message: LoopClosure) -> None:
        pose = message.pose
        write({"kind": "closure", "query_robot": message.query_robot, "matched_robot": message.matched_robot,
               "query_ns": stamp_to_ns(message.header.stamp), "matched_ns": stamp_to_ns(message.matched_stamp),
               "inliers": int(message.inliers), "pose_available": bool(message.pose_available),
               "translation_metric": bool(message.translation_metric),
               "translation": [pose.position.x, pose.position.y, pose.position.z],
               "rotation_xyzw": [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]})

    node.create_subscription(PlacePosterior, "place_posteriors", on_posterior, QOS)
    node.create_subscription(LoopClosure, "loop_closures", on_closure, QOS)
    print("[recorder] recording", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
