"""Subscriptions to a robot's sensor topics that connect to whatever its drivers publish.

Camera, depth and odometry drivers often publish with the sensor-data profile (best effort); a bag
replay, or a driver configured for it, publishes reliable. A reliable subscription never matches a
best-effort publisher, and the middleware's only sign is one generic warning at start-up: the node
then runs without that input. Each sensor input here therefore has a policy (``sensor_qos`` /
``image_qos``):

- ``auto`` (default): subscribe reliable, so that a reliable publisher (a lossless bag replay)
  delivers every message, and switch to best effort -- which matches publishers of either kind --
  as soon as a best-effort publisher is seen on the topic, saying so once by name. This is how
  ``ros2 bag record`` adapts to the QoS offered.
- ``best_effort`` (alias ``sensor_data``): best effort from the start.
- ``reliable``: reliable only; a best-effort publisher is reported once, by name, as unmatched.

The topic's publishers are looked at every ``CHECK_PERIOD_S``. A topic that has had no message
``silent_after_s`` after start-up, or that loses many of its messages on the way (counted from the
gaps in the publisher's numbering), is reported once, by name, with what the node does without it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.common import CALLBACKS, DropCounter, counted_subscription

SENSOR_QOS_POLICIES = ("auto", "best_effort", "sensor_data", "reliable")
CHECK_PERIOD_S = 0.5
# A topic that lost at least this many messages, and more than this share of them, is reported once.
LOSS_REPORT_MIN = 10
LOSS_REPORT_SHARE = 0.1
SILENT_AFTER_S = 5.0


def check_sensor_qos(policy: str, parameter: str) -> str:
    """The policy's canonical name (``sensor_data`` is ``best_effort``); a ConfigError names a bad one."""
    if policy not in SENSOR_QOS_POLICIES:
        raise ConfigError(f"parameter {parameter}={policy!r} must be one of {', '.join(SENSOR_QOS_POLICIES)}")
    return "best_effort" if policy == "sensor_data" else policy


def sensor_profile(best_effort: bool, depth: int) -> QoSProfile:
    """KEEP_LAST ``depth``, volatile; best effort or reliable."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, durability=DurabilityPolicy.VOLATILE,
                      reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE)


def should_switch_to_best_effort(policy: str, subscribed_best_effort: bool, offered_best_effort: list[bool]) -> bool:
    """``auto`` moves a reliable subscription to best effort once any publisher offers only best effort."""
    return policy == "auto" and not subscribed_best_effort and any(offered_best_effort)


class SensorInput:
    """One sensor topic's subscription with its QoS policy, counted drops and start-up diagnostics.

    ``without_it`` says, in the node's words, what is lost while the topic is silent (e.g. "closures get
    no metric pose"); it is logged with the topic's name when that happens.
    """

    def __init__(self, node: Node, message_type: Any, topic: str, callback: Callable[[Any], None], *,
                 policy: str, depth: int, counter: DropCounter, without_it: str,
                 silent_after_s: float = SILENT_AFTER_S, drain: bool = True) -> None:
        self._node = node
        self._message_type = message_type
        self._callback = callback
        self._depth = depth
        self._counter = counter
        self._without_it = without_it
        # Every waiting message per callback: a sensor stream (30-200 Hz) beside a node's slow callbacks would
        # otherwise queue up, one message taken per executor round, and overflow.
        self._drain = drain
        self.policy = policy
        self.topic = node.resolve_topic_name(topic)
        self.best_effort = policy == "best_effort"
        self.received = 0
        self.lost = 0  # messages that never reached the node, from the gaps in the publisher's numbering
        self._silent_after_s = silent_after_s
        self._started = time.monotonic()
        self._reported: set[str] = set()
        self.subscription = self._subscribe()
        self._timer = node.create_timer(CHECK_PERIOD_S, self._check)

    def _subscribe(self) -> Any:
        return counted_subscription(self._node, self._message_type, self.topic, self._on_message,
                                    sensor_profile(self.best_effort, self._depth), self._counter,
                                    on_incompatible_qos=self._on_incompatible_qos, on_lost=self._on_lost,
                                    drain=self._drain)

    def _on_lost(self, count: int) -> None:
        self.lost += count

    def _on_message(self, message: Any) -> None:
        self.received += 1
        self._callback(message)

    def _on_incompatible_qos(self, _info: Any) -> None:
        # Counted here; the switch (or the report) follows at the next check, outside DDS's event callback.
        self._counter.counts[f"incompatible_publishers_{self._short_name()}"] += 1

    def _short_name(self) -> str:
        return self.topic.strip("/").replace("/", "_") or "root"

    def _check(self) -> None:
        if not CALLBACKS.enter():  # shutting down
            return
        try:
            self._look_at_publishers()
        finally:
            CALLBACKS.leave()

    def _look_at_publishers(self) -> None:
        publishers = self._node.get_publishers_info_by_topic(self.topic)
        offered_best_effort = [p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers]
        if should_switch_to_best_effort(self.policy, self.best_effort, offered_best_effort):
            self._node.destroy_subscription(self.subscription)
            self.best_effort = True
            self.subscription = self._subscribe()
            self._node.get_logger().info(
                f"{self.topic}: a publisher offers best effort (a driver's sensor-data QoS); subscribed best effort, "
                "which receives from reliable publishers too")
        elif self.policy == "reliable" and any(offered_best_effort):
            self._report_once("unmatched", f"{self.topic}: {sum(offered_best_effort)} publisher(s) offer best effort, "
                              "which this reliable subscription never receives (set the node's sensor QoS to auto or "
                              f"best_effort); without it {self._without_it}")
        if self.lost >= LOSS_REPORT_MIN and self.lost > LOSS_REPORT_SHARE * (self.lost + self.received):
            self._report_once("lossy", f"{self.lost} of {self.lost + self.received} messages on {self.topic} never "
                              "reached the node. A best-effort publisher's messages over 512 KiB (a 640x480 depth or "
                              "colour image) leave Fast DDS's default shared memory for UDP fragments and are mostly "
                              "lost: start the driver with FASTRTPS_DEFAULT_PROFILES_FILE=<aefabmap_ros>/config/"
                              f"fastdds_large_messages.xml. Without them {self._without_it}")
        if self.received == 0 and time.monotonic() - self._started >= self._silent_after_s:
            waited = f"{self._silent_after_s:g} s"
            if not publishers:
                self._report_once("silent", f"no publisher on {self.topic} after {waited}: {self._without_it}")
            else:
                self._report_once("silent", f"{len(publishers)} publisher(s) on {self.topic} but no message after "
                                  f"{waited}: {self._without_it}")

    def _report_once(self, kind: str, text: str) -> None:
        if kind not in self._reported:
            self._reported.add(kind)
            self._node.get_logger().warning(text)

    def summary(self) -> str:
        """One phrase for the node's shutdown summary."""
        qos = "best effort" if self.best_effort else "reliable"
        return f"{self.topic}: {self.received} received, {self.lost} lost on the way ({qos})"
