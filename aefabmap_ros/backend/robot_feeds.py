"""Which session each robot's odometry goes to: the pose graph's per-robot feed bookkeeping.

A pose graph may take the odometry of several robots (a base station), each in its own odometry frame. Per
robot it keeps the robot's *current* session -- the one its odometry goes to, the newest named for it -- and,
until a session of the robot is named, the odometry that came before (``unnamed``): a backend started while the
robot runs cannot know the session its odometry is of until a closure or a posterior names it, and that
odometry is the first named session's.

A robot is *followed* once its odometry came, a session of it was started, or ``follow`` named it: only then
does a closure's query session become the robot's current one (a closure naming a robot whose odometry this
graph never takes names a session it will never have). Sessions themselves, their odometry buffers and
keyframes, are the graph's (backend/sessions.py); the closures waiting for odometry are the pose graph's.
"""

from __future__ import annotations

from dataclasses import dataclass

from aefabmap_ros.backend.graph_types import SessionId
from aefabmap_ros.backend.odometry import OdometryBuffer
from aefabmap_ros.backend.sessions import Session, odometry_buffer


@dataclass
class RobotFeed:
    """One robot's odometry input: its current session (None until one is named) and the odometry before it."""

    unnamed: OdometryBuffer
    current: SessionId | None = None


class RobotFeeds:
    """Every followed robot's feed, by robot name (module docstring)."""

    def __init__(self, max_odometry: int) -> None:
        self.max_odometry = max_odometry
        self._feeds: dict[str, RobotFeed] = {}

    def follow(self, robot: str) -> RobotFeed:
        """The robot's feed, made empty (no session, no odometry) the first time it is asked for."""
        feed = self._feeds.get(robot)
        if feed is None:
            feed = self._feeds[robot] = RobotFeed(odometry_buffer(self.max_odometry))
        return feed

    def follows(self, robot: str) -> bool:
        return robot in self._feeds

    @property
    def robots(self) -> list[str]:
        """The followed robots, in the order they were first followed."""
        return list(self._feeds)

    def current(self, robot: str) -> SessionId | None:
        """The session the robot's odometry goes to; None before one is named (or for a robot not followed)."""
        feed = self._feeds.get(robot)
        return None if feed is None else feed.current

    def is_current(self, session_id: SessionId) -> bool:
        """Whether the session is its robot's current one: its odometry is still coming."""
        return self.current(session_id[0]) == session_id

    def buffer(self, robot: str, sessions: dict[SessionId, Session]) -> OdometryBuffer:
        """The buffer the robot's next odometry goes into: its current session's, else the unnamed one."""
        feed = self.follow(robot)
        return feed.unnamed if feed.current is None else sessions[feed.current].odometry

    def start(self, session_id: SessionId, sessions: dict[SessionId, Session], first_stamp_ns: int | None) -> int:
        """Make ``session_id`` its robot's current session, made in ``sessions`` if new; the number of samples that
        could not be added (out of order) is returned.

        The robot's first session named takes the odometry that came before (it was this run's); a reloaded
        session continues with it (only the backend restarted: same odometry frame). A session named later is a
        new run whose odometry restarted: an empty buffer, or, given the stamp of its first frame, the previous
        session's samples from that stamp on, which came after the change."""
        feed = self.follow(session_id[0])
        rejected = 0
        if feed.current is None:
            buffer, feed.unnamed = feed.unnamed, odometry_buffer(self.max_odometry)
            existing = sessions.get(session_id)
            if existing is None:
                sessions[session_id] = Session(session_id, buffer, root=session_id)
            else:
                for stamp_ns, pose, _ in zip(*buffer.samples(), strict=True):
                    rejected += not existing.odometry.add(stamp_ns, pose)
        else:
            previous = sessions[feed.current].odometry
            moved = previous.split_from(first_stamp_ns) if first_stamp_ns is not None else ([], [])
            if session_id not in sessions:
                sessions[session_id] = Session(session_id, odometry_buffer(self.max_odometry), root=session_id)
            for stamp_ns, pose in zip(*moved, strict=True):
                sessions[session_id].odometry.add(stamp_ns, pose)
        feed.current = session_id
        return rejected
