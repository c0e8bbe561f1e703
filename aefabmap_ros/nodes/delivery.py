"""Messages a subscription never got, counted from the gaps in the publisher's sequence numbers.

DDS drops messages before any callback runs: a best-effort sample lost on the way, or one
overwritten in the reader's KEEP_LAST queue while the node was busy (the queue holds ``depth``
messages; the next one pushes the oldest out). Neither reaches the node, so no callback can count
it -- but every message carries its writer's *publication sequence number* (1, 2, 3, ... per
publisher), and the numbers missing between two received messages are exactly the ones lost.

What this cannot see (documented where the counts are reported):
- messages lost after the last one received (no later number reveals the gap);
- messages published before the subscription matched (never meant for it; not counted);
- losses while more than one publisher is matched: the numbers of two publishers interleave and the
  message info rclpy gives has no publisher id to tell them apart, so such messages are not judged.
"""

from __future__ import annotations

# rmw's RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED: the middleware does not number its messages.
SEQUENCE_NUMBER_UNSUPPORTED = 2**64 - 1


class SequenceGaps:
    """Counts the publication sequence numbers skipped between consecutive messages of one publisher.

    Not thread-safe: feed it from one subscription's callback (a node's callbacks do not overlap).
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self.missed = 0  # messages lost between received ones, in total
        self.unjudged = 0  # messages received while the gap could not be judged (see the module docstring)

    def observe(self, sequence: int, publishers: int) -> int:
        """One received message with its ``sequence`` number while ``publishers`` are matched; returns how
        many messages were lost just before it (0 when that cannot be told)."""
        if sequence == SEQUENCE_NUMBER_UNSUPPORTED or sequence <= 0 or publishers != 1:
            self._last = None  # the next numbered message from a single publisher starts afresh
            self.unjudged += 1
            return 0
        last, self._last = self._last, sequence
        if last is None or sequence <= last:
            # The first message, or a publisher that restarted (it numbers from 1 again): nothing to compare.
            return 0
        lost = sequence - last - 1
        self.missed += lost
        return lost
