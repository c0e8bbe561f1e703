"""aefabmap_view: watch the loop-closure suite live in Foxglove, over the Foxglove WebSocket protocol.

Serves the closure pictures (closure_view_node), the pose graph's markers and path (pose_graph_node),
the closures, candidates and place posteriors as channels of their ROS 2 types (CDR, as they travel), on
ws://HOST:PORT. In Foxglove: Open connection -> Foxglove WebSocket -> ws://localhost:8765, then
Layouts -> Import from file -> aefabmap_ros/config/foxglove_layout.json (the same layout opens a
recording of the run).

A ROS topic is subscribed only while a client subscribes to its channel, so nobody watching costs
nothing: no message is received, and closure_view_node, seeing no subscriber, draws nothing.
"""

from __future__ import annotations

import argparse
import queue
import sys
import time
from typing import Any

import foxglove
from foxglove.websocket import ServerListener

from aefabmap_ros.cli.common import ArgumentParser, ros_message_class, run_cli, with_ros
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io.bag_messages import get_typestore
from aefabmap_ros.nodes.launch_table import VIEW_TOPICS

DEFAULT_PORT = 8765
# How long a new client's subscription may wait for its ROS subscription; also how often an idle server wakes.
SPIN_PERIOD_S = 0.2


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_view", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1; 0.0.0.0 to be reached from other machines)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0: any free)")
    parser.add_argument("--topic", action="append", default=[], metavar="NAME=TYPE",
                        help="also serve this topic, e.g. image=sensor_msgs/msg/Image (repeatable)")
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0 = never)")
    return parser


def served_topics(extra: list[str]) -> dict[str, str]:
    """The view's topics plus ``NAME=TYPE`` extras, by name without a leading '/'."""
    topics = dict(VIEW_TOPICS)
    for entry in extra:
        name, separator, msgtype = entry.partition("=")
        if not separator or not name.strip("/ ") or msgtype.count("/") != 2:
            raise ConfigError(f"--topic {entry!r} must be NAME=PACKAGE/msg/TYPE, e.g. image=sensor_msgs/msg/Image")
        topics[name.strip("/ ")] = msgtype.strip()
    return topics


def ros2msg_schema(msgtype: str) -> foxglove.Schema:
    """The Foxglove schema of a ROS 2 type: its .msg text with every nested definition (what a bag stores)."""
    try:
        definition, _ = get_typestore().generate_msgdef(msgtype, ros_version=2)
    except Exception as exc:  # rosbags' own error types for an unknown message type
        raise ConfigError(f"unknown message type {msgtype!r}: {exc}") from exc
    return foxglove.Schema(name=msgtype, encoding="ros2msg", data=definition.encode())


class TopicBridge(ServerListener):
    """Foxglove channels fed from ROS subscriptions that exist only while a client subscribes.

    The server calls ``on_subscribe`` / ``on_unsubscribe`` on its own thread; the ROS side changes only in
    :meth:`apply`, called between spins on the ROS thread.
    """

    def __init__(self, node: Any, topics: dict[str, str]) -> None:
        self._node = node
        self._types = {f"/{name}": msgtype for name, msgtype in topics.items()}
        # The suite's own topics are reliable; another (a camera's) may be best effort, which only a best-effort
        # subscription matches.
        self._best_effort = {f"/{name}" for name in topics if name not in VIEW_TOPICS}
        self.channels = {topic: foxglove.Channel(topic, schema=ros2msg_schema(msgtype), message_encoding="cdr")
                         for topic, msgtype in self._types.items()}
        self._requests: queue.SimpleQueue[tuple[str, int]] = queue.SimpleQueue()
        self._clients: dict[str, int] = {}
        self._subscriptions: dict[str, Any] = {}
        self.forwarded: dict[str, int] = dict.fromkeys(self.channels, 0)

    def on_subscribe(self, _client: Any, channel: Any) -> None:
        self._requests.put((channel.topic, 1))

    def on_unsubscribe(self, _client: Any, channel: Any) -> None:
        self._requests.put((channel.topic, -1))

    def apply(self) -> None:
        """Subscribe to a topic when its first client came, unsubscribe when its last one left."""
        while not self._requests.empty():
            topic, change = self._requests.get()
            if topic not in self.channels:
                continue
            self._clients[topic] = max(0, self._clients.get(topic, 0) + change)
            if self._clients[topic] and topic not in self._subscriptions:
                self._subscriptions[topic] = self._subscribe(topic)
            elif not self._clients[topic] and topic in self._subscriptions:
                self._node.destroy_subscription(self._subscriptions.pop(topic))

    def _subscribe(self, topic: str) -> Any:
        from rclpy.qos import qos_profile_sensor_data

        from aefabmap_ros.nodes.common import RESULT_QOS

        channel = self.channels[topic]

        def forward(data: bytes) -> None:
            channel.log(data, log_time=time.time_ns())
            self.forwarded[topic] += 1

        return self._node.create_subscription(ros_message_class(self._types[topic]), topic, forward,
                                              qos_profile_sensor_data if topic in self._best_effort else RESULT_QOS,
                                              raw=True)


def serve(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    node = rclpy.create_node("aefabmap_view")
    bridge = TopicBridge(node, served_topics(args.topic))
    try:
        server = foxglove.start_server(name="aefabmap", host=args.host, port=args.port, server_listener=bridge)
    except RuntimeError as exc:  # the SDK's FoxgloveError, e.g. the port is taken
        node.destroy_node()
        raise ConfigError(f"cannot serve on {args.host}:{args.port}: {exc}") from exc
    print(f"[view] serving {len(bridge.channels)} topics on ws://{args.host}:{server.port} (Foxglove: Open "
          "connection -> Foxglove WebSocket; layout aefabmap_ros/config/foxglove_layout.json)",
          file=sys.stderr, flush=True)
    started = time.monotonic()
    try:
        while rclpy.ok() and not (args.duration > 0 and time.monotonic() - started >= args.duration):
            bridge.apply()
            rclpy.spin_once(node, timeout_sec=SPIN_PERIOD_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        server.stop()
        node.destroy_node()
    listing = ", ".join(f"{topic}: {count}" for topic, count in bridge.forwarded.items() if count)
    print(f"[view] stopped; forwarded {listing or 'nothing'}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, with_ros(serve))


if __name__ == "__main__":
    raise SystemExit(main())
