"""What every node of the suite shares: parameters from config dataclasses, QoS, counters, main().

Configs are the core's frozen dataclasses; each field becomes a ROS parameter carrying the field's
description, so `ros2 param describe` documents the same thing the YAML and the CLIs use, and the
dataclass's own validation is the single check of every value.
"""

from __future__ import annotations

import dataclasses
import signal
import sys
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import Executor, ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions

from aefabmap_ros.core.errors import AefabmapError, ConfigError

ConfigT = TypeVar("ConfigT")
LOG_THROTTLE_S = 5.0

# Results are few and must not be lost: reliable, and deep enough for a slow backend to catch up.
RESULT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def pipeline_qos(depth: int) -> QoSProfile:
    """Between our own nodes: reliable, so a replayed bag is processed frame for frame."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def image_qos(kind: str, depth: int) -> QoSProfile:
    """``sensor_data`` (best effort, what cameras publish) or ``reliable`` (lossless bag replay)."""
    if kind == "sensor_data":
        profile = qos_profile_sensor_data
        return QoSProfile(history=profile.history, depth=depth, reliability=profile.reliability,
                          durability=profile.durability)
    if kind == "reliable":
        return pipeline_qos(depth)
    raise ConfigError(f"parameter image_qos={kind!r} must be 'sensor_data' or 'reliable'")


def declare_parameter(node: Node, name: str, default: Any, description: str) -> Any:
    """Declare one typed parameter and return its value; a value of the wrong type is a ConfigError."""
    try:
        node.declare_parameter(name, default, ParameterDescriptor(description=description))
    except Exception as exc:  # rclpy's InvalidParameterTypeException and friends
        raise ConfigError(f"parameter {name!r}: {exc}") from exc
    value = node.get_parameter(name).value
    # YAML writes 1 for 1.0; accept an int where a float is declared rather than fail start-up.
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    return value


def declare_config(node: Node, config_type: type[ConfigT], prefix: str = "") -> ConfigT:
    """Declare every field of a frozen config dataclass as a parameter and build the config from them."""
    if not dataclasses.is_dataclass(config_type):
        raise TypeError(f"{config_type!r} is not a dataclass")
    defaults: Any = config_type()
    values = {}
    for field in dataclasses.fields(config_type):
        values[field.name] = declare_parameter(
            node, prefix + field.name, getattr(defaults, field.name), field.metadata.get("description", "")
        )
    try:
        return config_type(**values)
    except ConfigError as exc:
        raise ConfigError(f"{node.get_name()}: {exc}") from exc


def report_when_connected(node: Node, subscription: Any, what: str, period_s: float = 0.1) -> None:
    """Log ``receiving <what> from N publisher(s)`` once the subscription has a matched publisher.

    A message sent before its subscription is matched (DDS discovery takes seconds on a loaded
    machine) is lost: a launcher or a test waits for this line before it feeds the first image.
    """
    timer: Any = None

    def check() -> None:
        publishers = subscription.get_publisher_count()
        if publishers > 0:
            node.get_logger().info(f"receiving {what} from {publishers} publisher(s)")
            timer.cancel()

    timer = node.create_timer(period_s, check)


class DropCounter:
    """Counts inputs by outcome and logs every drop, throttled, so a bad stream never floods the log."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self.counts: Counter[str] = Counter()

    def ok(self, what: str = "processed") -> None:
        self.counts[what] += 1

    def drop(self, reason: str, detail: str) -> None:
        self.counts[f"dropped_{reason}"] += 1
        self._node.get_logger().warning(
            f"dropped input ({reason}, {self.counts[f'dropped_{reason}']} so far): {detail}",
            throttle_duration_sec=LOG_THROTTLE_S,
        )

    def summary(self) -> str:
        return ", ".join(f"{key}={value}" for key, value in sorted(self.counts.items())) or "no input"


class PeriodicSave:
    """A node's state file: saved when it changed, every ``period_s`` and at shutdown (``save_if_changed``).

    ``path`` None keeps the state in memory only. A failed save is logged (throttled) and retried at
    the next period; the old file stays whole (the savers write atomically).
    """

    def __init__(self, node: Node, path: Path | None, save: Callable[[Path], None], what: str,
                 period_s: float) -> None:
        self._node = node
        self.path = path
        self._save = save
        self._what = what
        self.unsaved_changes = False
        if path is not None and period_s > 0:
            node.create_timer(period_s, self.save_if_changed)

    def mark_changed(self) -> None:
        self.unsaved_changes = True

    def save_if_changed(self) -> None:
        if self.path is None or not self.unsaved_changes:
            return
        try:
            self._save(self.path)
            self.unsaved_changes = False
        except (AefabmapError, OSError) as exc:
            self._node.get_logger().error(f"cannot save {self._what} to {self.path}: {exc}",
                                          throttle_duration_sec=30.0)


class _StopSignalError(Exception):
    """Raised from our SIGINT/SIGTERM handler to leave the spin loop."""


def _raise_stop(_signum: int, _frame: FrameType | None) -> None:
    raise _StopSignalError


def run_nodes(factories: Sequence[Callable[[], Any]], args: list[str] | None = None) -> int:
    """The Jazzy ``main()`` pattern for one node or several in one process (multi-threaded executor).

    Init, build every node, spin, and always close, destroy and shut down. SIGINT and SIGTERM are
    handled here rather than by rclpy, so the context is still valid while nodes close: the FAB-MAP
    node's final map save and every node's summary log happen on a clean, live context.
    A start-up error (bad parameter, missing model) is printed as ``ERROR: ...`` and gives exit 1.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    previous = {sig: signal.signal(sig, _raise_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    nodes: list[Any] = []
    executor: Executor = (MultiThreadedExecutor(num_threads=max(2, len(factories))) if len(factories) > 1
                          else SingleThreadedExecutor())
    try:
        for factory in factories:
            nodes.append(factory())
            executor.add_node(nodes[-1])
        # Short waits so a signal is handled promptly (Python runs handlers between bytecodes only).
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, _StopSignalError, ExternalShutdownException):
        pass
    except AefabmapError as exc:
        print(f"ERROR: {exc}", file=sys.stderr)
        return 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for node in reversed(nodes):
            node.close()
        executor.shutdown()
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run_node(factory: Callable[[], Any], args: list[str] | None = None) -> int:
    return run_nodes([factory], args)
