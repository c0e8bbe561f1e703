"""A one-frame mailbox between a camera callback and the worker that processes frames.

A live camera does not wait for us: when frames arrive faster than the pipeline takes them, a
queue in front of it only grows the delay from image to result. The gate holds at most one frame,
the newest; a frame that arrives while the previous one is still waiting replaces it and is counted
as dropped, so the worker always starts on the freshest frame and nothing queues up.
"""

from __future__ import annotations

import threading
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
        with self._condition:
            replaced = self._waiting is not None
            if replaced:
                self.dropped += 1
            self._waiting = item
            self._condition.notify()
            return not replaced

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
