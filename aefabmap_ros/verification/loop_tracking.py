"""Loop tracking: after a verified loop closure, the next frames are verified near its place.

FAB-MAP's posterior along a revisit flickers on dense video: the true place is among a frame's
top candidates far more often than it is the confident, temporally consistent match that becomes a
loop-closure candidate (on the dense synthetic video: 1,902 revisiting frames had a true place among
their top 5 hypotheses, 1,117 were closed). Once the robot is known -- geometrically -- to be
revisiting a stretch of the map, the question for the next frames is no longer "which of all places
is this?" but "is this still that stretch?": the map's time order answers where to look, and the
geometric check decides, with the same thresholds as every other closure.

This is what ORB-SLAM does after a relocalisation (it tracks the local map around the matched
keyframe) and what DLoopDetector's islands do across frames, with the evidence of appearance and
geometry kept separate: a tracked closure is one of the frame's own top FAB-MAP candidates, lying
within ``island_seconds`` (map time) of the last verified place, and accepted by the verifier. A
frame with no such candidate, or whose candidates all fail, publishes nothing; ``track_seconds``
after the last verified closure the track ends, and only a new temporally consistent detection
starts another. So tracking adds closures only inside revisits that appearance and geometry have
already confirmed; it cannot open one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

from aefabmap_ros.errors import ConfigError

PlaceT = TypeVar("PlaceT")


class LoopTrack:
    """The last verified loop closure (query stamp, matched place stamp) and the window it opens."""

    def __init__(self, track_seconds: float, island_seconds: float) -> None:
        for name, value in (("track_seconds", track_seconds), ("island_seconds", island_seconds)):
            if not value >= 0.0:
                raise ConfigError(f"{name} = {value!r}: must be >= 0")
        self._track_ns = track_seconds * 1e9
        self._island_ns = island_seconds * 1e9
        self._last: tuple[int, int] | None = None

    @property
    def enabled(self) -> bool:
        return self._track_ns > 0.0

    def accept(self, query_ns: int, place_ns: int) -> None:
        """A closure of the query stamped ``query_ns`` to the place stamped ``place_ns`` was verified."""
        if self._last is None or query_ns >= self._last[0]:
            self._last = (query_ns, place_ns)

    def is_active(self, query_ns: int) -> bool:
        """True while ``query_ns`` is at most ``track_seconds`` after the last verified closure."""
        return self._last is not None and 0 < query_ns - self._last[0] <= self._track_ns

    def near(self, query_ns: int, candidates: Sequence[PlaceT], place_ns: Callable[[PlaceT], int]) -> list[PlaceT]:
        """The query's candidates (best first) within ``island_seconds`` of the tracked place; [] when inactive."""
        if self._last is None or not self.is_active(query_ns):
            return []
        tracked_ns = self._last[1]
        return [candidate for candidate in candidates if abs(place_ns(candidate) - tracked_ns) <= self._island_ns]

    def reset(self) -> None:
        self._last = None
