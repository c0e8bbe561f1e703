"""ROS time stamps as integer nanoseconds, the one unit the package computes with."""

from __future__ import annotations

from typing import Any


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
