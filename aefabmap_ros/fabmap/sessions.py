"""Sessions of a map: which run of which robot made each place.

A session is one run of a robot's detection front end on a map. A map holds the sessions in the order they
started, numbered 0, 1, 2, ...; each place records the session it was made in. A SLAM backend keeps one
odometry frame per session (a restarted robot's odometry starts again at the identity), so a closure must say
which session its two images belong to: the session number and robot travel with every place.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from aefabmap_ros.errors import DataError


@dataclass(frozen=True)
class Session:
    """One run of one robot on the map."""

    number: int  # index in the map's session table
    robot: str  # '' = the map's only robot
    first_query_id: int  # the map's query count when the session started: its frames' query ids are later


def check_robot_name(robot: str) -> str:
    """The robot name, refused when it is not a plain string (it keys graphs and namespaces)."""
    if not isinstance(robot, str) or any(character in robot for character in "\n\r\t"):
        raise DataError(f"a robot name must be a one-line string, got {robot!r}")
    return robot


class SessionTable:
    """The sessions of a map, in the order they started; the last one is current."""

    def __init__(self, sessions: list[Session] | None = None) -> None:
        self._sessions: list[Session] = list(sessions or [])

    def __len__(self) -> int:
        return len(self._sessions)

    def __iter__(self) -> Iterator[Session]:
        return iter(self._sessions)

    def __getitem__(self, number: int) -> Session:
        if not 0 <= number < len(self._sessions):
            raise DataError(f"session {number} out of range [0, {len(self._sessions)})")
        return self._sessions[number]

    @property
    def current(self) -> Session:
        if not self._sessions:
            raise DataError("the map has no session yet")
        return self._sessions[-1]

    def start(self, robot: str, first_query_id: int) -> Session:
        """Append a session of ``robot`` whose first frame will get ``first_query_id``."""
        session = Session(len(self._sessions), check_robot_name(robot), int(first_query_id))
        self._sessions.append(session)
        return session

    def robots(self) -> list[str]:
        """Every robot of the map, in the order it first appears."""
        return list(dict.fromkeys(session.robot for session in self._sessions))

    # -- arrays (the map file's columns) -----------------------------------------------------------

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "session_robots": np.array([session.robot for session in self._sessions], dtype=np.str_),
            "session_first_queries": np.array([session.first_query_id for session in self._sessions],
                                              dtype=np.int64),
        }

    @classmethod
    def from_arrays(cls, robots: np.ndarray, first_queries: np.ndarray) -> SessionTable:
        """The table of a map file's columns; DataError when they do not describe sessions."""
        robots, first_queries = np.asarray(robots), np.asarray(first_queries)
        if robots.ndim != 1 or first_queries.shape != robots.shape:
            raise DataError(f"session columns differ in shape: robots {robots.shape}, first queries "
                            f"{first_queries.shape}")
        if not np.issubdtype(first_queries.dtype, np.integer) or (robots.size and robots.dtype.kind != "U"):
            raise DataError("session columns have the wrong types")
        if np.any(np.diff(first_queries) < 0) or (first_queries.size and first_queries[0] < 0):
            raise DataError("sessions' first query ids are not increasing")
        return cls([Session(number, check_robot_name(str(robot)), int(first))
                    for number, (robot, first) in enumerate(zip(robots, first_queries, strict=True))])
