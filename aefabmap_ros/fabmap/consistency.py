"""Temporal consistency of loop-closure matches (DLoopDetector's and iBoW-LCD's islands, by time).

One match of one frame is weak evidence on dense video: FAB-MAP's posterior over many similar
places can spike on a look-alike for a single frame. A real revisit lasts: the next frames match
the same stretch of the map again. So a match is *consistent* only when each of the last
``min_matches`` informative frames (this one included) matched a place, and each two consecutive
matches lie within ``island_seconds`` of each other in map time (the stamps of the matched places).

Why map time and not place ids: place ids of a map built from video are dense in some stretches
(the camera moved) and sparse in others (it stood still); stamps measure the same "neighbourhood of
the map" whatever the motion was. ``island_seconds`` has to allow for the two traversals running at
different speeds: between two query frames ``dt`` apart the matched places may move by ``dt``
times the speed ratio, plus the jitter of which of several similar places wins.

An informative frame without a match breaks the chain. Frames with too few words to be recognised
are not observed at all: a blank frame says nothing either way.
"""

from __future__ import annotations

import itertools
from collections import deque

from aefabmap_ros.errors import ConfigError


class TemporalConsistency:
    """Chain of the last matches (matched place stamps, ``None`` for a frame without a match)."""

    def __init__(self, min_matches: int, island_seconds: float) -> None:
        if isinstance(min_matches, bool) or not isinstance(min_matches, int) or min_matches < 1:
            raise ConfigError(f"min_matches = {min_matches!r}: must be an integer >= 1")
        if not island_seconds >= 0.0:
            raise ConfigError(f"island_seconds = {island_seconds!r}: must be >= 0")
        self.min_matches = min_matches
        self._island_ns = island_seconds * 1e9
        self._recent: deque[int | None] = deque(maxlen=min_matches)

    def observe(self, matched_stamp_ns: int | None) -> bool:
        """Record one informative frame's match (None: no match); True when it is consistent."""
        self._recent.append(matched_stamp_ns)
        return self.is_consistent()

    def is_consistent(self) -> bool:
        chain = list(self._recent)
        if len(chain) < self.min_matches or any(stamp is None for stamp in chain):
            return False
        stamps = [int(stamp) for stamp in chain if stamp is not None]
        return all(abs(later - earlier) <= self._island_ns for earlier, later in itertools.pairwise(stamps))

    def reset(self) -> None:
        self._recent.clear()
