"""What every node of the suite shares: parameters from config dataclasses, QoS, counters, main().

Configs are the core's frozen dataclasses; each field becomes a ROS parameter carrying the field's
description, so `ros2 param describe` documents the same thing the YAML and the CLIs use, and the
dataclass's own validation is the single check of every value.
"""

from __future__ import annotations

import dataclasses
import functools
import signal
import sys
import threading
from collections import Counter
from collections.abc import Callable, Collection, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import FrameType
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import Executor, ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from aefabmap_ros.errors import AefabmapError, ConfigError
from aefabmap_ros.io.config_files import coerce_like
from aefabmap_ros.nodes.delivery import SequenceGaps

ConfigT = TypeVar("ConfigT")
# Messages a draining subscription takes beyond the one its callback was given, at most per callback.
DRAIN_AT_MOST = 1000
LOG_THROTTLE_S = 5.0


def _reliable_volatile(depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


# Results are few and must not be lost: reliable, and deep enough for a slow backend to catch up.
RESULT_QOS = _reliable_volatile(100)
# Odometry comes at 50-200 Hz on a robot while a node may spend 0.1-1 s on one loop closure (verification
# of 5 candidates, an iSAM2 update): 100 messages would cover half a second of it. The odometry gate and the
# backend interpolate between consecutive messages, so each lost one widens a gap; they are ~700 bytes.
ODOMETRY_QOS = _reliable_volatile(2000)


def result_qos(depth: int) -> QoSProfile:
    """RESULT_QOS, at least ``depth`` deep: for a node that may fall behind per-frame results (place_posteriors)."""
    return _reliable_volatile(max(depth, RESULT_QOS.depth))


def pipeline_qos(depth: int) -> QoSProfile:
    """Between our own nodes: reliable, so a replayed bag is processed frame for frame."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def declare_parameter(node: Node, name: str, default: Any, description: str) -> Any:
    """Declare one typed parameter and return its value; a value of the wrong type is a ConfigError."""
    try:
        node.declare_parameter(name, default, ParameterDescriptor(description=description))
    except Exception as exc:  # rclpy's InvalidParameterTypeException and friends
        raise ConfigError(f"parameter {name!r}: {exc}") from exc
    # YAML writes 1 for 1.0; accept an int where a float is declared rather than fail start-up.
    return coerce_like(node.get_parameter(name).value, default)


def declare_config(node: Node, config_type: type[ConfigT], prefix: str = "",
                   only: Collection[str] | None = None) -> ConfigT:
    """Declare the fields of a frozen config dataclass as parameters (every field, or ``only`` those; the
    others keep their defaults) and build the config from them."""
    if not dataclasses.is_dataclass(config_type):
        raise TypeError(f"{config_type!r} is not a dataclass")
    defaults: Any = config_type()
    values = {}
    for field in dataclasses.fields(config_type):
        if only is not None and field.name not in only:
            continue
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


class CallbackGate:
    """Counts the node callbacks running now; once closed, lets no new one start.

    A multi-threaded executor runs callbacks in pool threads that ``Executor.shutdown`` does not
    wait for (rclpy Jazzy): the final save must wait here, or it saves a map halfway through an
    update. Callbacks already handed to the pool when the spin stops are skipped, not half run.
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._running = 0
        self._open = True

    def enter(self) -> bool:
        with self._condition:
            if self._open:
                self._running += 1
            return self._open

    def leave(self) -> None:
        with self._condition:
            self._running -= 1
            self._condition.notify_all()

    def close_and_wait(self) -> None:
        with self._condition:
            self._open = False
            self._condition.wait_for(lambda: self._running == 0)

    def reopen(self) -> None:
        with self._condition:
            self._open = True


CALLBACKS = CallbackGate()


def node_callback(callback: Callable[..., None]) -> Callable[..., None]:
    """Wrap a node's callback (a message's, or a timer's): no new run once shutdown began, and any
    exception is counted and dropped (``self.counter``) with a throttled log naming its type -- a
    ``cv2.error`` or a torch ``RuntimeError`` from one bad message must not take the node (and the
    launch) down."""

    @functools.wraps(callback)
    def guarded(self: Any, *message: Any, **options: Any) -> None:
        if not CALLBACKS.enter():
            return
        try:
            callback(self, *message, **options)
        except Exception as exc:  # the point: nothing a message causes stops the node
            self.counter.drop(type(exc).__name__, f"{type(exc).__name__}: {exc}")
        finally:
            CALLBACKS.leave()

    return guarded


class RuntimeParameters:
    """A node's answer to ``ros2 param set``: the ``settable`` parameters are applied by ``apply``
    (which raises ConfigError to refuse a value); every other parameter is read once at start-up,
    so a change is refused with that reason instead of being reported as a success and ignored."""

    def __init__(self, node: Node, settable: Collection[str], apply: Callable[[dict[str, Any]], None]) -> None:
        self._node = node
        self.settable = frozenset(settable)
        self._apply = apply
        node.add_on_set_parameters_callback(self._on_set)

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        fixed = sorted(p.name for p in parameters if p.name not in self.settable)
        if fixed:
            settable = ", ".join(sorted(self.settable)) or "none"
            return SetParametersResult(successful=False, reason=(
                f"{', '.join(fixed)}: read at start-up only; restart {self._node.get_name()} with the new value "
                f"(settable while running: {settable})"))
        try:
            self._apply({p.name: coerce_like(p.value, self._node.get_parameter(p.name).value) for p in parameters})
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self._node.get_logger().info(
            "parameters changed: " + ", ".join(f"{p.name}={p.value!r}" for p in parameters))
        return SetParametersResult(successful=True)


class DropCounter:
    """Counts inputs by outcome and logs every drop, throttled, so a bad stream never floods the log."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self.counts: Counter[str] = Counter()

    def ok(self, what: str = "processed") -> None:
        self.counts[what] += 1

    def drop(self, reason: str, detail: str, count: int = 1) -> None:
        self.counts[f"dropped_{reason}"] += count
        self._node.get_logger().warning(
            f"dropped input ({reason}, {self.counts[f'dropped_{reason}']} so far): {detail}",
            throttle_duration_sec=LOG_THROTTLE_S,
        )

    def summary(self) -> str:
        return ", ".join(f"{key}={value}" for key, value in sorted(self.counts.items())) or "no input"


def counted_subscription(node: Node, message_type: Any, topic: str, callback: Callable[..., None],
                         qos: QoSProfile, counter: DropCounter,
                         on_incompatible_qos: Callable[[Any], None] | None = None,
                         on_lost: Callable[[int], None] | None = None, pass_source_time: bool = False,
                         drain: bool = False) -> Any:
    """``node.create_subscription`` that also counts, on ``counter``, the messages DDS lost before the callback.

    A best-effort sample lost on the way, or one pushed out of the reader's KEEP_LAST queue while the
    node was busy, never reaches a callback; the gaps in the publisher's sequence numbers reveal them
    (``dropped_before_callback``; what they cannot reveal: nodes/delivery.py). The middleware's own
    ``message_lost`` event is counted too, as ``dds_reported_lost``, but not relied on: Fast DDS
    reported most losses between processes (10,480 of 10,503 in a soak) and none of the queue
    overwrites inside one process.
    """
    gaps = SequenceGaps()
    subscription: Any = None

    def on_message(message: Any, info: dict[str, Any]) -> None:
        handle(message, info)
        if drain:
            # A single-threaded executor takes one message of each subscription per round, and a round with a
            # verification in it outlasts a 30-200 Hz stream's period: its queue would grow by seconds. Take what
            # waits now (rclpy's executor takes messages the same way).
            for _ in range(DRAIN_AT_MOST):
                with subscription.handle:
                    taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
                if taken is None:
                    break
                handle(*taken)

    def handle(message: Any, info: dict[str, Any]) -> None:
        lost = gaps.observe(int(info["publication_sequence_number"]), subscription.get_publisher_count())
        if lost:
            counter.drop("before_callback", f"{lost} message(s) on {subscription.topic_name} never reached the node "
                         "(reader queue full while busy, or lost on the way)", count=lost)
            if on_lost is not None:
                on_lost(lost)
        if pass_source_time:  # when the publisher sent it (its wall clock, ns): the age of what waited in the queue
            callback(message, int(info["source_timestamp"]))
        else:
            callback(message)

    def on_message_lost(info: Any) -> None:
        counter.counts["dds_reported_lost"] += int(info.total_count_change)

    subscription = node.create_subscription(
        message_type, topic, on_message, qos,
        event_callbacks=SubscriptionEventCallbacks(message_lost=on_message_lost, incompatible_qos=on_incompatible_qos))
    return subscription


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
            node.create_timer(period_s, self._on_timer)

    def mark_changed(self) -> None:
        self.unsaved_changes = True

    def _on_timer(self) -> None:
        if not CALLBACKS.enter():  # shutting down: the final save follows
            return
        try:
            self.save_if_changed()
        finally:
            CALLBACKS.leave()

    def save_if_changed(self) -> None:
        """The periodic save: a failure is logged (throttled) and retried at the next period."""
        if self.path is None or not self.unsaved_changes:
            return
        try:
            self._save(self.path)
            self.unsaved_changes = False
        except (AefabmapError, OSError) as exc:
            self._node.get_logger().error(f"cannot save {self._what} to {self.path}: {exc}",
                                          throttle_duration_sec=30.0)

    def final_save(self) -> bool:
        """The save at shutdown: False (and an unthrottled error naming what is lost) when it failed."""
        if self.path is None or not self.unsaved_changes:
            return True
        try:
            self._save(self.path)
        except (AefabmapError, OSError) as exc:
            self._node.get_logger().error(
                f"FINAL SAVE FAILED: {self._what} not saved to {self.path} ({type(exc).__name__}: {exc}); "
                "the file holds the last successful save only")
            return False
        self.unsaved_changes = False
        return True


def finish_handed_over_callbacks(executor: Executor) -> None:
    """Wait for every callback a multi-threaded executor already handed to its thread pool.

    rclpy Jazzy's ``Executor.shutdown`` does not wait for them (its wait is skipped once the shutdown flag is
    set), so one still queued would run after the guard condition and the nodes are destroyed: its take or
    trigger raises InvalidHandle ("cannot use Destroyable because destruction was requested") into a task
    nobody awaits, printed at exit as "The following exception was never retrieved". Run now, the gate is
    closed and each returns at once. The pool is the executor's own (``_executor``): no public API reaches it.
    """
    pool = getattr(executor, "_executor", None)
    if isinstance(pool, ThreadPoolExecutor):
        pool.shutdown(wait=True)


def run_nodes(factories: Sequence[Callable[[], Any]], args: list[str] | None = None) -> int:
    """The Jazzy ``main()`` pattern for one node or several in one process (multi-threaded executor).

    Init, build every node, spin, and always close, destroy and shut down. SIGINT and SIGTERM only
    *request* the stop (a handler that raised would interrupt a callback at any line, e.g. between
    adding a place and recording its stamp, and that half-updated map would be saved): the spin
    ends, the callbacks still running are waited for, and only then each node closes (the FAB-MAP
    node's final save) on a live context. Further signals during the close are ignored, so a second
    SIGTERM cannot cut the final save short.
    Exit code: 0; 1 for a start-up error (printed as ``ERROR: ...``) or when a node's close reports
    that its state could not be saved.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop_requested = threading.Event()

    def request_stop(_signum: int, _frame: FrameType | None) -> None:
        stop_requested.set()

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    nodes: list[Any] = []
    executor: Executor = (MultiThreadedExecutor(num_threads=max(2, len(factories))) if len(factories) > 1
                          else SingleThreadedExecutor())
    exit_code = 0
    CALLBACKS.reopen()
    try:
        for factory in factories:
            nodes.append(factory())
            executor.add_node(nodes[-1])
        # Short waits so a stop request is seen promptly.
        while rclpy.ok() and not stop_requested.is_set():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except AefabmapError as exc:
        print(f"ERROR: {exc}", file=sys.stderr)
        exit_code = 1
    finally:
        CALLBACKS.close_and_wait()
        finish_handed_over_callbacks(executor)
        executor.shutdown()
        for node in reversed(nodes):
            if node.close() is False:
                exit_code = 1
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
        CALLBACKS.reopen()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return exit_code


def run_node(factory: Callable[[], Any], args: list[str] | None = None) -> int:
    return run_nodes([factory], args)
