"""One session of the pose graph: a run of a robot's front end, named (robot, session number) as LoopClosure
names it, with its own odometry frame, odometry buffer and chain of keyframes.

Each session's keyframes are kept in stamp order; a closure endpoint within ``SAME_KEYFRAME_NS`` of a keyframe
is that keyframe (a place seen again by a later closure reuses it). How sessions are named, anchored and
joined is the pose graph's (backend/pose_graph.py); a session only records which graph it is part of.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

from aefabmap_ros.backend.graph_types import Keyframe, SessionId
from aefabmap_ros.backend.odometry import OdometryBuffer

# Two stamps this close (ns) are the same keyframe: a place seen again by a later closure reuses it.
SAME_KEYFRAME_NS = 1_000_000


def odometry_buffer(max_odometry: int) -> OdometryBuffer:
    """A session's odometry buffer: decimated when full, not forgotten from the start, since a later session
    may close a loop to any stamp of it."""
    return OdometryBuffer(max_odometry, decimate=True)


@dataclass
class Session:
    """One run of a robot's front end: its odometry (one odometry frame) and its keyframes, by stamp.

    ``root`` names the session whose prior holds the graph this one is part of: itself until a closure joins
    it to another graph. Sessions whose root is the graph's ``anchor`` are joined (in the map frame)."""

    id: SessionId
    odometry: OdometryBuffer
    root: SessionId
    keyframes: list[Keyframe] = field(default_factory=list)

    def index_of(self, stamp_ns: int) -> int:
        """Where a keyframe at ``stamp_ns`` goes in the stamp-ordered chain (before any keyframe at that stamp)."""
        return bisect.bisect_left([keyframe.stamp_ns for keyframe in self.keyframes], stamp_ns)

    def find_keyframe(self, stamp_ns: int) -> Keyframe | None:
        """The keyframe within ``SAME_KEYFRAME_NS`` of ``stamp_ns`` (the earlier of two), None if there is none."""
        index = self.index_of(stamp_ns)
        for candidate in (index - 1, index):
            if (0 <= candidate < len(self.keyframes)
                    and abs(self.keyframes[candidate].stamp_ns - stamp_ns) <= SAME_KEYFRAME_NS):
                return self.keyframes[candidate]
        return None
