"""A node under test fed through its ROS topics, and what it made of each message: counted by name, silent, fatal.

The probe is a second node on the same executor: it publishes on the node's input topics and keeps what the
node publishes; the executor is spun by the test's own thread, so a callback's exception that escapes the
node's guard reaches the test (in a launched node it would end the process: "fatal"). A message is judged by
the node's drop counters (``dropped_<reason>``), the one thing besides its topics that every node keeps.
"""

from __future__ import annotations

import builtins
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

# Deep enough that no message of a burst is pushed out of a queue before the node takes it.
PROBE_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
# Waiting, not timing: a message answered by nothing for this long is taken as silently accepted.
ANSWER_WAIT_S = 10.0
# Names a drop gets from node_callback's guard when an exception no validation foresaw escaped the callback.
_UNFORESEEN = {name for name in dir(builtins) if isinstance(getattr(builtins, name), type)
               and issubclass(getattr(builtins, name), BaseException)} | {"error"}  # cv2.error


@dataclass
class Verdicts:
    """Per malformed kind: how often it was counted under an expected name, under another name, not at all, or
    stopped the node."""

    counted: Counter[str] = field(default_factory=Counter)
    misnamed: Counter[str] = field(default_factory=Counter)
    silent: Counter[str] = field(default_factory=Counter)
    fatal: Counter[str] = field(default_factory=Counter)
    names: dict[str, set[str]] = field(default_factory=dict)  # kind -> the drop names seen

    def kinds(self) -> set[str]:
        return set(self.counted) | set(self.misnamed) | set(self.silent) | set(self.fatal)

    def failures(self) -> dict[str, str]:
        """Kind -> what went wrong, for the kinds not always counted under an expected name."""
        wrong = {}
        for kind in sorted(self.kinds()):
            if self.misnamed[kind] or self.silent[kind] or self.fatal[kind]:
                wrong[kind] = (f"misnamed {self.misnamed[kind]} (as {sorted(self.names.get(kind, set()))}), "
                               f"silent {self.silent[kind]}, fatal {self.fatal[kind]}")
        return wrong


def drop_increase(before: Mapping[str, int], after: Mapping[str, int]) -> set[str]:
    """The ``dropped_*`` counters that grew (without the prefix); DDS's own loss counters are not a verdict."""
    return {key.removeprefix("dropped_") for key, value in after.items()
            if key.startswith("dropped_") and key != "dropped_before_callback" and value > before.get(key, 0)}


def is_foreseen(reason: str) -> bool:
    """A reason a validation gave, not the type of an exception that escaped one (``dropped_IndexError``)."""
    return reason not in _UNFORESEEN


class TopicProbe:
    def __init__(self, node: Any, inputs: Mapping[str, Any], outputs: Mapping[str, Any],
                 answer_wait_s: float = ANSWER_WAIT_S) -> None:
        """``inputs``/``outputs``: topic -> message type the node subscribes to / publishes; ``answer_wait_s``:
        how long a malformed message may go unanswered before it is taken as silently accepted."""
        self.node = node
        self.answer_wait_s = answer_wait_s
        self.probe = Node(f"probe_of_{node.get_name()}")
        self.publishers = {topic: self.probe.create_publisher(kind, topic, PROBE_QOS) for topic, kind in inputs.items()}
        self.received: dict[str, list[Any]] = {topic: [] for topic in outputs}
        for topic, kind in outputs.items():
            self.probe.create_subscription(kind, topic, self.received[topic].append, PROBE_QOS)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(node)
        self.executor.add_node(self.probe)

    def close(self) -> None:
        self.executor.shutdown()
        self.probe.destroy_node()

    def counts(self) -> dict[str, int]:
        return dict(self.node.counter.counts)

    def spin_until(self, done: Callable[[], bool], seconds: float) -> bool:
        """Spin until ``done()``; an exception out of a callback propagates (the node's guard let it through)."""
        deadline = time.monotonic() + seconds
        while not done():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def wait_connected(self, seconds: float = 30.0) -> None:
        """Until every input has the node as a subscriber and every output the node as a publisher (a message
        sent before discovery matched them is lost)."""
        def connected() -> bool:
            return (all(p.get_subscription_count() > 0 for p in self.publishers.values())
                    and all(self.probe.count_publishers(topic) > 0 for topic in self.received))
        if not self.spin_until(connected, seconds):
            raise AssertionError(f"{self.node.get_name()}: topics not connected within {seconds} s")

    def publish_and_wait(self, topic: str, message: Any, answered: Callable[[], bool],
                         seconds: float = 30.0) -> bool:
        self.publishers[topic].publish(message)
        return self.spin_until(answered, seconds)

    def judge(self, kind: str, topic: str, message: Any, expected: set[str], verdicts: Verdicts) -> None:
        """Publish one malformed message and record the node's verdict on it."""
        before = self.counts()
        self.publishers[topic].publish(message)
        try:
            self.spin_until(lambda: bool(drop_increase(before, self.counts())), self.answer_wait_s)
        except Exception as exc:  # escaped the node's guard: in its own process, the end of it
            verdicts.fatal[kind] += 1
            verdicts.names.setdefault(kind, set()).add(f"raised {type(exc).__name__}: {exc}")
            return
        reasons = drop_increase(before, self.counts())
        verdicts.names.setdefault(kind, set()).update(reasons)
        if not reasons:
            verdicts.silent[kind] += 1
        elif reasons <= expected and all(is_foreseen(reason) for reason in reasons):
            verdicts.counted[kind] += 1
        else:
            verdicts.misnamed[kind] += 1
