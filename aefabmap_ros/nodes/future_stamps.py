"""Inputs stamped far ahead of a node's clock: refused, so one wrong stamp cannot order out every later input."""

from __future__ import annotations

from rclpy.node import Node

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.common import declare_parameter


class FutureStamps:
    """Refuses stamps far ahead of the node's clock (parameter ``max_future_stamp_s``).

    Inputs must come in stamp order, so one message stamped years ahead (a clock set wrong once, a corrupt
    header) would make every later one "out of order": it is dropped instead. Under simulated time before
    the first /clock message there is no clock to judge by, and every stamp passes.
    """

    def __init__(self, node: Node, default_s: float = 600.0) -> None:
        self._node = node
        max_future_s = declare_parameter(
            node, "max_future_stamp_s", default_s,
            "Drop inputs stamped more than this ahead of the node's clock (seconds; 0 = accept any stamp).")
        if not max_future_s >= 0.0:
            raise ConfigError(f"{node.get_name()}: parameter max_future_stamp_s={max_future_s} must be >= 0")
        self.max_future_ns = int(max_future_s * 1e9)

    def limit_ns(self) -> int | None:
        """Stamps after this are in the future; None: no limit (max_future_stamp_s 0, or no clock yet)."""
        now_ns = self._node.get_clock().now().nanoseconds
        return now_ns + self.max_future_ns if self.max_future_ns and now_ns > 0 else None

    def problem(self, stamp_ns: int) -> str | None:
        """Why ``stamp_ns`` is refused as in the future; None when it is not."""
        limit_ns = self.limit_ns()
        if limit_ns is None or stamp_ns <= limit_ns:
            return None
        ahead_s = (stamp_ns - limit_ns + self.max_future_ns) / 1e9
        return (f"stamp {stamp_ns} ns is {ahead_s:.0f} s ahead of the node's clock "
                f"(max_future_stamp_s {self.max_future_ns / 1e9:g})")
