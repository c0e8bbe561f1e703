"""ROS time stamps as integer nanoseconds, the one unit the package computes with."""

from __future__ import annotations

from typing import Any


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (rclpy or rosbags: anything with ``sec``, ``nanosec``) -> nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
