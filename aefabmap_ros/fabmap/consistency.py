"""Temporal consistency of loop-closure matches (DLoopDetector's and iBoW-LCD's islands, by time).

One match of one frame is weak evidence on dense video: FAB-MAP's posterior over many similar
places can spike on a look-alike for a single frame. A real revisit lasts: the next frames match
the same stretch of the map again. So a match is *consistent* only when ``min_matches`` recent
informative frames (this one included, which must have matched) matched places that chain within
``island_seconds`` of each other in map time (the stamps of the matched places), walking back from
this frame's match. A frame is recent when it is among the last ``min_matches + max_skipped``
informative frames, or when its own stamp is at most ``window_seconds`` from this frame's
(DLoopDetector's "maximum distance between queries"): whichever reaches further back.

The skips exist because along a real revisit the posterior flickers: at 30 Hz a frame between
matching ones often falls below the match threshold or onto a look-alike, and requiring
*consecutive* frames then throws a revisit away. A count of frames suits a low frame rate; at
video rate the flicker lasts a fraction of a second, many frames, so there the time window is what
reaches back (and it does not shrink when a busy pipeline drops frames). With ``max_skipped = 0``
and no window the rule is the strict one: every one of the last ``min_matches`` frames matched.

Why map time and not place ids: place ids of a map built from video are dense in some stretches
(the camera moved) and sparse in others (it stood still); stamps measure the same "neighbourhood of
the map" whatever the motion was. ``island_seconds`` has to allow for the two traversals running at
different speeds: between two query frames ``dt`` apart the matched places may move by ``dt``
times the speed ratio, plus the jitter of which of several similar places wins.

Frames with too few words to be recognised are not observed at all: a blank frame says nothing
either way.
"""

from __future__ import annotations

import itertools
from collections import deque

from aefabmap_ros.errors import ConfigError


class TemporalConsistency:
    """Chain of the recent matches: (query stamp, matched place stamp or ``None`` for no match)."""

    def __init__(self, min_matches: int, island_seconds: float, *, max_skipped: int = 0,
                 window_seconds: float = 0.0) -> None:
        if isinstance(min_matches, bool) or not isinstance(min_matches, int) or min_matches < 1:
            raise ConfigError(f"min_matches = {min_matches!r}: must be an integer >= 1")
        if not island_seconds >= 0.0:
            raise ConfigError(f"island_seconds = {island_seconds!r}: must be >= 0")
        if isinstance(max_skipped, bool) or not isinstance(max_skipped, int) or max_skipped < 0:
            raise ConfigError(f"max_skipped = {max_skipped!r}: must be an integer >= 0")
        if not window_seconds >= 0.0:
            raise ConfigError(f"window_seconds = {window_seconds!r}: must be >= 0")
        self.min_matches = min_matches
        self._island_ns = island_seconds * 1e9
        self._window_ns = window_seconds * 1e9
        self._frames_kept = min_matches + max_skipped
        self._recent: deque[tuple[int, int | None]] = deque()

    def observe(self, query_stamp_ns: int, matched_stamp_ns: int | None) -> bool:
        """Record one informative frame's match (None: no match); True when it is consistent."""
        self._recent.append((query_stamp_ns, matched_stamp_ns))
        # Forget frames outside both reaches. Distance, not age: stamps that jump back (a bag replayed
        # again into a live node) must not pin old frames in memory.
        while len(self._recent) > self._frames_kept and not self._in_window(self._recent[0][0]):
            self._recent.popleft()
        return self.is_consistent()

    def __len__(self) -> int:
        """Frames held: the last ``min_matches + max_skipped`` and those within the window."""
        return len(self._recent)

    def _in_window(self, query_stamp_ns: int) -> bool:
        return abs(self._recent[-1][0] - query_stamp_ns) <= self._window_ns

    def is_consistent(self) -> bool:
        if not self._recent or self._recent[-1][1] is None:
            return False
        # Walk back from this frame's match; a match joins the chain when it lies within the island of
        # the last one joined. Frames without a match, or matching elsewhere, are passed over.
        anchor = self._recent[-1][1]
        joined = 1
        for back, (query_stamp, stamp) in enumerate(itertools.islice(reversed(self._recent), 1, None), start=2):
            recent = back <= self._frames_kept or self._in_window(query_stamp)
            if recent and stamp is not None and abs(anchor - stamp) <= self._island_ns:
                anchor = stamp
                joined += 1
        return joined >= self.min_matches

    def reset(self) -> None:
        self._recent.clear()
