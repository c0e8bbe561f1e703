"""The frame gate keeps only the newest frame and counts the ones it replaced."""

from __future__ import annotations

import threading

from aefabmap_ros.nodes.frame_gate import LatestFrameGate, LatestFrameWorker


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


def test_the_worker_finishes_the_frame_in_hand_on_stop_but_not_the_one_waiting() -> None:
    holding, release = threading.Event(), threading.Event()
    processed: list[int] = []

    def slow(frame: int) -> None:
        holding.set()
        release.wait()
        processed.append(frame)

    worker: LatestFrameWorker[int] = LatestFrameWorker(slow, "test_worker")
    assert worker.offer(1)
    assert holding.wait(timeout=30)
    assert worker.offer(2)  # waits behind frame 1
    assert not worker.offer(3)  # replaces 2
    close = worker.gate.close

    def close_then_release() -> None:  # frame 1 ends only after stop() closed the gate: no race with frame 3
        close()
        release.set()

    worker.gate.close = close_then_release  # type: ignore[method-assign]
    worker.stop()
    assert processed == [1]  # 1 was finished; 3 was still waiting when the worker was told to stop
    assert worker.gate.dropped == 1
