"""The frame gate keeps only the newest frame and counts the ones it replaced."""

from __future__ import annotations

import threading

from aefabmap_ros.nodes.frame_gate import LatestFrameGate


def test_a_waiting_frame_is_replaced_by_a_newer_one_and_counted() -> None:
    gate: LatestFrameGate[int] = LatestFrameGate()
    assert gate.offer(1)
    assert not gate.offer(2)
    assert not gate.offer(3)
    assert gate.dropped == 2
    assert gate.take(timeout_s=0) == 3  # the newest, never the stale ones
    assert gate.take(timeout_s=0) is None  # nothing queued behind it
    assert gate.offer(4)  # taken frames are not drops
    assert gate.dropped == 2


def test_take_waits_for_a_frame_from_another_thread_and_close_wakes_it() -> None:
    gate: LatestFrameGate[str] = LatestFrameGate()
    got: list[str | None] = []
    worker = threading.Thread(target=lambda: got.append(gate.take()))
    worker.start()
    gate.offer("frame")
    worker.join()
    assert got == ["frame"]
    closer = threading.Thread(target=lambda: got.append(gate.take()))
    closer.start()
    gate.close()
    closer.join()
    assert got == ["frame", None]
    gate.offer("late")
    assert gate.take(timeout_s=0) is None
