"""ROS time stamps as integer nanoseconds, the one unit the package computes with."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (rclpy or rosbags: anything with ``sec``, ``nanosec``) -> nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class TransportDeduplicator:
    """Drops an image that already arrived, with the same stamp, through the other transport.

    A camera driver using image_transport publishes every frame twice, raw on ``image`` and compressed on
    ``image/compressed``; a node listening to both must process each frame once. A repeat on the same
    transport is kept: that is the sender's own stream, and dropping it would hide its bug.
    """

    def __init__(self, remembered: int = 32) -> None:
        self._transport_of: dict[int, str] = {}
        self._remembered = remembered

    def is_duplicate(self, stamp_ns: int, transport: str) -> bool:
        first = self._transport_of.get(stamp_ns)
        if first is not None:
            return first != transport
        self._transport_of[stamp_ns] = transport
        if len(self._transport_of) > self._remembered:  # dicts keep insertion order: forget the oldest
            del self._transport_of[next(iter(self._transport_of))]
        return False


def newest_stamp_up_to(stamps_ns: Sequence[int] | np.ndarray, limit_ns: int | None) -> tuple[int, list[int]]:
    """The newest of ``stamps_ns`` at or before ``limit_ns`` (-1 when none) and the indices of those after it.

    A map saved before future stamps were refused can hold a place stamped years ahead (a clock set
    wrong once): ordering later frames after it would drop every one of them as "out of order", after
    every restart. ``limit_ns`` None trusts every stamp (no clock to judge by).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    beyond = np.zeros(stamps.size, dtype=bool) if limit_ns is None else stamps > limit_ns
    trusted = stamps[~beyond]
    return (int(trusted.max()) if trusted.size else -1), np.flatnonzero(beyond).tolist()
