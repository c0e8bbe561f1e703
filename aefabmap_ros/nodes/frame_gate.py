"""A one-frame mailbox between a subscription callback and the worker that processes frames.

A live camera does not wait for us: when frames arrive faster than the pipeline takes them, a
queue in front of it only grows the delay from image to result. The gate holds at most one frame,
the newest; a frame that arrives while the previous one is still waiting replaces it and is counted
as dropped, so the worker always starts on the freshest frame and nothing queues up.

Every stage that can be the slowest has one (feature_node for images, quantizer_node for features):
a gate only at the first stage would let frames it passed queue up in front of a slower second one.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

ItemT = TypeVar("ItemT")


class LatestFrameGate(Generic[ItemT]):
    """Thread-safe: ``offer`` from the receiving thread, ``take`` from the worker."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._waiting: ItemT | None = None
        self._closed = False
        self.dropped = 0

    def offer(self, item: ItemT) -> bool:
        """Hand over a frame; False when it replaced one the worker had not taken (that one is dropped)."""
        return self.swap(item) is None

    def swap(self, item: ItemT) -> ItemT | None:
        """Hand over a frame; returns the one it replaced (dropped), None when none was waiting."""
        with self._condition:
            replaced = self._waiting
            if replaced is not None:
                self.dropped += 1
            self._waiting = item
            self._condition.notify()
            return replaced

    def take(self, timeout_s: float | None = None) -> ItemT | None:
        """The waiting frame (removed from the gate), waiting up to ``timeout_s``; None if none came
        or the gate was closed."""
        with self._condition:
            self._condition.wait_for(lambda: self._waiting is not None or self._closed, timeout_s)
            item, self._waiting = self._waiting, None
            return None if self._closed else item

    def close(self) -> None:
        """Wake the worker for good: every later ``take`` returns None."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()


class LatestFrameWorker(Generic[ItemT]):
    """A worker thread that processes the newest frame offered to it, through a ``LatestFrameGate``.

    ``offer`` returns at once (the subscription callback is never held up); a frame still waiting
    when a newer one is offered is dropped, and ``offer`` returns False so the node can count it.
    """

    def __init__(self, process: Callable[[ItemT], None], name: str) -> None:
        self.gate: LatestFrameGate[ItemT] = LatestFrameGate()
        self._process = process
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def offer(self, item: ItemT) -> bool:
        """Hand over a frame; False when it replaced one the worker had not taken (that one is dropped)."""
        return self.gate.offer(item)

    def swap(self, item: ItemT) -> ItemT | None:
        """Hand over a frame; returns the one it replaced (dropped), None when none was waiting."""
        return self.gate.swap(item)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Finish the frame in hand (one still waiting is not processed), then end the thread."""
        self.gate.close()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=timeout_s)

    def _run(self) -> None:
        while (item := self.gate.take()) is not None:
            self._process(item)


class FrameHandOff(Generic[ItemT]):
    """How a node's subscription callback passes each message on: processed in the callback itself
    (every message, in order: bag replay), or, with ``newest_only``, through a ``LatestFrameWorker``
    (a live camera: a message still waiting when a newer one arrives is dropped)."""

    def __init__(self, process: Callable[[ItemT], None], name: str, *, newest_only: bool,
                 on_replaced: Callable[[ItemT], None] | None = None) -> None:
        self._process = process
        self._on_replaced = on_replaced  # told of each message dropped for a newer one
        self.worker: LatestFrameWorker[ItemT] | None = LatestFrameWorker(process, name) if newest_only else None

    def submit(self, item: ItemT) -> bool:
        """Process or hand over ``item``; False when it replaced one still waiting (that one is dropped)."""
        if self.worker is None:
            self._process(item)
            return True
        replaced = self.worker.swap(item)
        if replaced is not None and self._on_replaced is not None:
            self._on_replaced(replaced)
        return replaced is None

    def stop(self) -> None:
        """Finish the frame in hand (one still waiting is not processed); nothing to do without a worker."""
        if self.worker is not None:
            self.worker.stop()


class DetectionRate:
    """Which frames are processed at ``rate_hz`` at most (0 = every frame), decided by the frames' stamps.

    A loop-closure front end does not need every frame of a 30 Hz camera: neighbouring frames see the same
    scene, and a pipeline that tries to process them all on a small computer drops at random wherever it
    is busy. Deciding by stamp makes the choice the same in a lossless replay and live, whatever the load.
    A frame is taken when it is at least 90 % of a period after the last one taken, so a camera's timing
    jitter does not push every other frame out (30 Hz at 10 Hz takes every third frame, not every fourth);
    a stamp earlier than the last one taken (a bag looped, a clock reset) starts afresh.
    """

    def __init__(self, rate_hz: float) -> None:
        if not rate_hz >= 0:
            raise ValueError(f"detection rate {rate_hz} Hz must be >= 0")
        self.min_interval_ns = round(0.9e9 / rate_hz) if rate_hz > 0 else 0
        self._last_ns: int | None = None

    def take(self, stamp_ns: int) -> bool:
        """True when the frame stamped ``stamp_ns`` is to be processed (and it becomes the last one taken)."""
        last = self._last_ns
        if last is not None and last <= stamp_ns < last + self.min_interval_ns:
            return False
        self._last_ns = stamp_ns
        return True
