"""run_nodes' shutdown: a stop signal lets running callbacks finish before the nodes close and save;
a failed final save is the exit code; node callbacks survive any exception."""

from __future__ import annotations

import os
import signal
import time
from typing import Any, ClassVar

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.node import Node  # noqa: E402

from aefabmap_ros.nodes.common import DropCounter, node_callback, run_nodes  # noqa: E402
from test.reliability import Recorder  # noqa: E402

pytestmark = pytest.mark.ros


class TwoStepNode(Node):
    """Updates its state in two steps per tick, like PlaceRecognizer.process (add a place, then its
    stamp); the first tick sends this process ``signal_to_send`` between the steps and, in a pool
    thread, takes a while to reach the second step. close() records whether the state was whole."""

    closed_states: ClassVar[list[tuple[int, int]]] = []

    def __init__(self, name: str, signal_to_send: int | None, pause_s: float) -> None:
        super().__init__(name)
        self.counter = DropCounter(self)
        self.first_steps = 0
        self.second_steps = 0
        self.signal_to_send = signal_to_send
        self.pause_s = pause_s
        self.create_timer(0.01, self._tick)

    @node_callback
    def _tick(self) -> None:
        self.first_steps += 1
        if self.signal_to_send is not None:
            signal_to_send, self.signal_to_send = self.signal_to_send, None
            os.kill(os.getpid(), signal_to_send)
            time.sleep(self.pause_s)  # the old handler raised here, or closed the node meanwhile
        self.second_steps += 1

    def close(self) -> bool:
        TwoStepNode.closed_states.append((self.first_steps, self.second_steps))
        return True


class IdleNode(Node):
    def __init__(self) -> None:
        super().__init__("idle_node")
        self.counter = DropCounter(self)

    def close(self) -> bool:
        return True


@pytest.mark.parametrize("threads", ["single", "multi"])
@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_lets_the_running_callback_finish_before_the_nodes_close(threads: str,
                                                                                stop_signal: int) -> None:
    TwoStepNode.closed_states.clear()
    factories: list[Any] = [lambda: TwoStepNode("two_step_node", stop_signal, pause_s=0.5)]
    if threads == "multi":  # two nodes: the multi-threaded executor, callbacks in pool threads
        factories.append(IdleNode)
    assert run_nodes(factories) == 0
    ((first, second),) = TwoStepNode.closed_states
    assert first >= 1 and first == second, "the node closed (and would have saved) between the two steps"


class SignalledDuringCloseNode(IdleNode):
    """Its close (the final save) is interrupted by another stop signal half-way."""

    saved: ClassVar[list[bool]] = []

    def __init__(self) -> None:
        super().__init__()
        self.create_timer(0.01, lambda: os.kill(os.getpid(), signal.SIGTERM))

    def close(self) -> bool:
        os.kill(os.getpid(), signal.SIGINT)  # e.g. an impatient second Ctrl-C
        time.sleep(0.2)  # signals are handled between bytecodes: give it every chance to interrupt
        SignalledDuringCloseNode.saved.append(True)
        return True


def test_a_second_stop_signal_during_the_final_save_does_not_cut_it_short() -> None:
    SignalledDuringCloseNode.saved.clear()
    before = signal.getsignal(signal.SIGINT)
    assert run_nodes([SignalledDuringCloseNode]) == 0
    assert SignalledDuringCloseNode.saved == [True]
    # The handlers are restored afterwards (pytest's own SIGINT handling works again).
    assert signal.getsignal(signal.SIGINT) is before


class FailingSaveNode(IdleNode):
    def __init__(self) -> None:
        super().__init__()
        self.create_timer(0.01, lambda: os.kill(os.getpid(), signal.SIGTERM))

    def close(self) -> bool:
        return False  # as PeriodicSave.final_save when the disk is full


def test_a_failed_final_save_makes_the_exit_code_1() -> None:
    assert run_nodes([FailingSaveNode]) == 1
    assert run_nodes([FailingSaveNode, IdleNode]) == 1


class RaisingNode(IdleNode):
    def __init__(self) -> None:
        super().__init__()
        self.handled: list[int] = []

    @node_callback
    def on_message(self, value: int) -> None:
        if value == 1:
            raise RuntimeError("a torch kernel failed")
        if value == 2:
            raise IndexError("index 4 is out of bounds for axis 1 with size 2")
        self.handled.append(value)


@pytest.mark.reliability
def test_any_exception_in_a_node_callback_is_counted_and_dropped(reliability: Recorder) -> None:
    rclpy.init()
    try:
        node = RaisingNode()
        try:
            for value in (0, 1, 2, 3):
                node.on_message(value)
            assert node.handled == [0, 3]
            assert node.counter.counts["dropped_RuntimeError"] == 1
            assert node.counter.counts["dropped_IndexError"] == 1
            reliability.bad_inputs("any node (an exception in its callback)", tried=2,
                                   survived=node.counter.counts["dropped_RuntimeError"]
                                   + node.counter.counts["dropped_IndexError"])
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_the_callbacks_handed_to_the_pool_are_finished_before_the_executor_shuts_down() -> None:
    """rclpy's shutdown leaves them queued, to run on destroyed nodes ("exception was never retrieved");
    run_nodes waits for them first."""
    import threading

    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.executors import MultiThreadedExecutor
    from std_msgs.msg import Header

    from aefabmap_ros.nodes.common import finish_handed_over_callbacks, pipeline_qos

    rclpy.init()
    try:
        release, taken = threading.Event(), []
        node = Node("pool_node")
        group = ReentrantCallbackGroup()  # four callbacks at once, where the pool has two threads
        topics = [f"pool_topic_{index}" for index in range(4)]
        publishers = [node.create_publisher(Header, topic, pipeline_qos(10)) for topic in topics]
        def held_until_released(message: Header) -> None:
            release.wait(10)
            taken.append(message)

        for topic in topics:
            node.create_subscription(Header, topic, held_until_released, pipeline_qos(10), callback_group=group)
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        deadline = time.monotonic() + 20
        while any(p.get_subscription_count() == 0 for p in publishers) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        for publisher in publishers:
            publisher.publish(Header())
        handed = 0
        while handed < 4 and time.monotonic() < deadline:  # each ready message goes to the pool, whose two
            executor.spin_once(timeout_sec=0.05)         # threads wait on `release`: two callbacks queue
            handed = len(executor._futures)  # the pool's tasks (private: what the test must see)
        assert handed == 4 and not taken
        threading.Timer(0.3, release.set).start()
        finish_handed_over_callbacks(executor)
        assert len(taken) == 4  # every queued callback ran, while its node was still alive
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
