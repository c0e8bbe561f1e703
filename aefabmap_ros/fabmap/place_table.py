"""What a map knows of each place besides its words: the stamp and query id of the frame that made it, the
session it was made in, and its frame's index within that session; and the session table.

The words live in the FAB-MAP engine's inverted index; this table is the rest of a place, kept as columns
(one growable array each) so that a million places cost 28 bytes each here and are masked in one pass.
"""

from __future__ import annotations

import numpy as np

from aefabmap_ros.fabmap.index import GrowableArray
from aefabmap_ros.fabmap.sessions import Session, SessionTable


class PlaceTable:
    """The places' stamps, frames and sessions, and the map's sessions."""

    def __init__(self, sessions: SessionTable | None = None) -> None:
        self.sessions = sessions if sessions is not None else SessionTable()
        self._stamps_ns = GrowableArray(np.int64, 64)  # (P,) stamp of each place's frame
        self._frames = GrowableArray(np.int64, 64)  # (P,) query id of each place's frame
        self._sessions = GrowableArray(np.int32, 64)  # (P,) session each place was made in
        # (P,) the index of each place's frame among its session's frames (RobotTrack.frames_seen then): how
        # many frames ago its robot made it, whatever other robots sent in between. Not saved: it is the
        # query id less the session's first query id, exact for a session of one robot alone on the map,
        # which is the only one a reloaded map continues.
        self._session_frames = GrowableArray(np.int64, 64)

    def __len__(self) -> int:
        return len(self._stamps_ns)

    @property
    def stamps_ns(self) -> np.ndarray:
        return self._stamps_ns.view()

    @property
    def frames(self) -> np.ndarray:
        return self._frames.view()

    @property
    def session_numbers(self) -> np.ndarray:
        return self._sessions.view()

    @property
    def session_frames(self) -> np.ndarray:
        return self._session_frames.view()

    def session_of(self, place_id: int) -> Session:
        return self.sessions[int(self._sessions.view()[place_id])]

    def add(self, stamps_ns: np.ndarray, frames: np.ndarray, session: int, session_frames: np.ndarray) -> None:
        """Append places made in ``session`` (parallel arrays, one entry a place)."""
        self._stamps_ns.extend(np.asarray(stamps_ns, dtype=np.int64))
        self._frames.extend(np.asarray(frames, dtype=np.int64))
        self._sessions.extend(np.full(len(stamps_ns), session, dtype=np.int32))
        self._session_frames.extend(np.asarray(session_frames, dtype=np.int64))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The map file's place and session columns (copies)."""
        return {"place_stamps_ns": self.stamps_ns.copy(), "place_frames": self.frames.copy(),
                "place_sessions": self.session_numbers.copy(), **self.sessions.to_arrays()}

    @classmethod
    def from_arrays(cls, state: dict[str, np.ndarray]) -> PlaceTable:
        """The table of a map file's columns (``map_file.read_map`` checked them)."""
        table = cls(SessionTable.from_arrays(state["session_robots"], state["session_first_queries"]))
        frames = state["place_frames"].astype(np.int64)
        numbers = state["place_sessions"].astype(np.int32)
        first_queries = np.array([session.first_query_id for session in table.sessions], dtype=np.int64)
        table._stamps_ns.extend(state["place_stamps_ns"].astype(np.int64))
        table._frames.extend(frames)
        table._sessions.extend(numbers)
        table._session_frames.extend(frames - first_queries[numbers] if numbers.size else frames)
        return table

    def too_recent(self, session: Session, frames_seen: int, stamp_ns: int, recent_frames: int,
                   recent_seconds: float) -> np.ndarray:
        """(P,) bool: places of ``session`` made by its last ``recent_frames`` frames (its robot has seen
        ``frames_seen`` before this one) or stamped less than ``recent_seconds`` before ``stamp_ns``."""
        own: np.ndarray = self.session_numbers == session.number
        recent = np.zeros(own.size, dtype=bool)
        if recent_frames > 0:
            recent |= frames_seen - self.session_frames <= recent_frames
        if recent_seconds > 0.0:
            recent |= (stamp_ns - self.stamps_ns) < recent_seconds * 1e9
        return own & recent
