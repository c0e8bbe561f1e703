"""aefabmap_record: write the suite's outputs (or any topics) to a rosbag2 bag that Foxglove opens.

Subscriptions are raw, so messages are stored as the CDR bytes that arrived, never re-encoded.
The bag appears at its path only when recording ends cleanly (Ctrl-C, --duration or --idle-timeout).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from aefabmap_ros.cli.common import ArgumentParser, ros_message_class, run_cli, with_ros
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io import bags
from aefabmap_ros.nodes.launch_table import VIEW_TOPICS

# The suite's topics and their types; other topics' types are discovered from the graph.
KNOWN_TYPES = {
    **VIEW_TOPICS,
    "loop_closures": "aefabmap_msgs/msg/LoopClosure",
    "loop_closure_candidates": "aefabmap_msgs/msg/LoopClosure",
    "place_posteriors": "aefabmap_msgs/msg/PlacePosterior",
    "aefabmap/words": "aefabmap_msgs/msg/BagOfWords",
    "aefabmap/features": "aefabmap_msgs/msg/Features",
}
# What aefabmap_eval --recording scores: the published (by default verified) closures, FAB-MAP's raw
# candidates, and the posteriors.
DEFAULT_TOPICS = ("loop_closures", "loop_closure_candidates", "place_posteriors")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_record", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", type=Path, help="bag directory to create")
    parser.add_argument("--topics", nargs="+", default=list(DEFAULT_TOPICS),
                        help=f"topics to record (default: {' '.join(DEFAULT_TOPICS)})")
    parser.add_argument("--storage", choices=sorted(bags.STORAGES), default="mcap")
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0 = no limit)")
    parser.add_argument("--idle-timeout", type=float, default=0.0,
                        help="stop once nothing arrived for this many seconds after the first message (0 = never)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    parser.add_argument("--wait-publishers", type=float, default=0.0,
                        help="before reporting 'recording', wait up to this many seconds for every topic to have "
                        "a publisher (default: 0 = don't wait)")
    return parser


def _normalise(topic: str) -> str:
    return topic.lstrip("/")


def _resolve_type(node: Any, topic: str, timeout_s: float = 5.0) -> str:
    known = KNOWN_TYPES.get(_normalise(topic))
    if known is not None:
        return known
    import rclpy

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for name, types in node.get_topic_names_and_types():
            if _normalise(name) == _normalise(topic) and types:
                return str(types[0])
        rclpy.spin_once(node, timeout_sec=0.1)
    raise ConfigError(f"cannot find the type of topic {topic!r}: nothing publishes it")


def _wait_for_publishers(node: Any, topics: list[str], timeout_s: float) -> None:
    """Give discovery time to connect us to every topic's publisher, so the first messages are kept."""
    import rclpy

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(node.count_publishers(topic) > 0 for topic in topics):
            rclpy.spin_once(node, timeout_sec=0.3)  # let the publishers' side of the match complete
            return
        rclpy.spin_once(node, timeout_sec=0.1)


def record(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    node = rclpy.create_node("aefabmap_record")
    counts: dict[str, int] = {}
    last_arrival = [0.0]
    try:
        with bags.BagWriter(args.output, storage=args.storage, overwrite=args.overwrite) as writer:
            for topic in args.topics:
                msgtype = _resolve_type(node, topic)
                # Stored under its full name (/loop_closures), as ros2 bag record stores topics.
                name = node.resolve_topic_name(topic)
                writer.add_topic(name, msgtype)
                counts[name] = 0

                def on_message(data: bytes, name: str = name) -> None:
                    writer.write(name, time.time_ns(), data)
                    counts[name] += 1
                    last_arrival[0] = time.monotonic()

                node.create_subscription(ros_message_class(msgtype), topic, on_message, 100, raw=True)
            _wait_for_publishers(node, args.topics, args.wait_publishers)
            print(f"[record] recording {' '.join(args.topics)}", file=sys.stderr, flush=True)
            started = time.monotonic()
            try:
                while rclpy.ok():
                    try:
                        rclpy.spin_once(node, timeout_sec=0.1)
                    except Exception:
                        if rclpy.ok():
                            raise
                        # Ctrl-C shut the context down between the check and the wait (rclpy raises "context is
                        # not valid"): a stop like any other, which must not throw away what was recorded.
                        break
                    now = time.monotonic()
                    if args.duration > 0 and now - started >= args.duration:
                        break
                    if args.idle_timeout > 0 and last_arrival[0] and now - last_arrival[0] >= args.idle_timeout:
                        break
            except (KeyboardInterrupt, ExternalShutdownException):
                pass
    finally:
        node.destroy_node()
    listing = ", ".join(f"{topic}: {count}" for topic, count in counts.items())
    print(f"[record] wrote {args.output} ({listing})", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, with_ros(record))


if __name__ == "__main__":
    raise SystemExit(main())
