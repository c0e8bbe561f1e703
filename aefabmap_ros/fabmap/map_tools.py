"""Maps as data: summarise, merge and cut the arrays of a map file (:mod:`aefabmap_ros.fabmap.map_file`).

Every function takes and returns a map's arrays as :func:`~aefabmap_ros.fabmap.map_file.read_map` gives them
(checked, a format-1 map already read as one session) and works on whole columns with numpy: the cost is a
few passes over the word ids, whatever the number of places.

What the results keep true, so that a recognizer loading them behaves as if it had built them:

* Places stay in the order they were added, and the sessions in the order they started; a place's session
  number indexes the session table.
* Query ids (a place's frame, a session's first query) stay unique and increasing across the whole map and
  below ``next_query_id``: a merged map's second half is shifted after the first half's last query id.
* The last posterior is dropped: it is a belief over the places of the map it was computed on, and a
  merged or cut map has other places. A map without one starts its next session with a uniform prior,
  which is what a recognizer loading a map does anyway (a loaded map continues in a new session).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from aefabmap_ros.errors import DataError, VocabularyMismatchError

MapArrays = dict[str, np.ndarray]


@dataclass(frozen=True)
class SessionSummary:
    """One session of a map: its robot, how many places it made, and when."""

    number: int
    robot: str
    places: int
    first_query_id: int
    first_stamp_ns: int | None  # stamp of its first place, None when it made none
    last_stamp_ns: int | None  # stamp of its last place


@dataclass(frozen=True)
class MapSummary:
    """What a map holds, without its word sets."""

    vocabulary_id: str
    vocabulary_size: int
    format_version: int
    places: int
    words_stored: int  # (place, word) pairs over all places
    next_query_id: int
    has_previous_posterior: bool
    sessions: tuple[SessionSummary, ...]
    robots: tuple[str, ...]  # in the order they first appear
    file_bytes: int | None = None

    def to_json(self) -> dict[str, Any]:
        """The summary as JSON values (sessions as a list of objects)."""
        values = asdict(self)
        values["sessions"] = [asdict(session) for session in self.sessions]
        values["robots"] = list(self.robots)
        return values


def map_summary(arrays: MapArrays, file_bytes: int | None = None) -> MapSummary:
    """The summary of a map's arrays (``file_bytes``: the size of the file they came from, if any)."""
    indptr = np.asarray(arrays["word_indptr"])
    stamps = np.asarray(arrays["place_stamps_ns"], dtype=np.int64)
    place_sessions = np.asarray(arrays["place_sessions"], dtype=np.int64)
    robots = [str(robot) for robot in np.asarray(arrays["session_robots"])]
    first_queries = np.asarray(arrays["session_first_queries"], dtype=np.int64)
    numbers = np.arange(len(robots))
    # Places are in session order (a session's places follow the earlier sessions'): each session's places
    # are one run, found by binary search.
    starts = np.searchsorted(place_sessions, numbers, side="left")
    ends = np.searchsorted(place_sessions, numbers, side="right")
    sessions = tuple(
        SessionSummary(number=int(number), robot=robots[number], places=int(end - start),
                       first_query_id=int(first_queries[number]),
                       first_stamp_ns=int(stamps[start]) if end > start else None,
                       last_stamp_ns=int(stamps[end - 1]) if end > start else None)
        for number, start, end in zip(numbers, starts, ends, strict=True)
    )
    return MapSummary(
        vocabulary_id=str(arrays["vocabulary_id"]), vocabulary_size=int(arrays["vocabulary_size"]),
        format_version=int(arrays.get("format_version", 0)), places=max(indptr.size - 1, 0),
        words_stored=int(indptr[-1]) if indptr.size else 0, next_query_id=int(arrays["next_query_id"]),
        has_previous_posterior=bool(arrays["has_previous_posterior"]), sessions=sessions,
        robots=tuple(dict.fromkeys(robots)), file_bytes=file_bytes,
    )


def check_same_vocabulary(a: MapArrays, b: MapArrays, names: tuple[str, str] = ("the first map", "the second map")
                          ) -> None:
    """VocabularyMismatchError naming both maps' vocabularies unless they are one: word ids only mean the
    same word under the same vocabulary."""
    a_id, b_id = str(a["vocabulary_id"]), str(b["vocabulary_id"])
    a_size, b_size = int(a["vocabulary_size"]), int(b["vocabulary_size"])
    if a_id != b_id or a_size != b_size:
        raise VocabularyMismatchError(
            f"{names[0]} belongs to vocabulary {a_id!r} ({a_size} words), {names[1]} to {b_id!r} ({b_size} words): "
            "maps of different vocabularies cannot be merged"
        )


def merge_maps(a: MapArrays, b: MapArrays, names: tuple[str, str] = ("the first map", "the second map")
               ) -> MapArrays:
    """One map holding ``a``'s places and then ``b``'s, as if ``b``'s sessions had run after ``a``'s.

    ``b``'s sessions are renumbered after ``a``'s (their robots kept), and ``b``'s query ids (its places'
    frames, its sessions' first queries) are shifted by ``a``'s ``next_query_id``, so every query id stays
    unique and increasing; the merged map's ``next_query_id`` is the sum of both. The settings
    (``config_json``) are ``a``'s; the last posterior is dropped (see the module doc).
    VocabularyMismatchError (naming ``names``) when the maps are of different vocabularies.
    """
    check_same_vocabulary(a, b, names)
    query_offset = int(a["next_query_id"])
    a_indptr, b_indptr = np.asarray(a["word_indptr"]), np.asarray(b["word_indptr"])
    indptr = np.concatenate([a_indptr, b_indptr[1:] + a_indptr[-1]])
    merged: MapArrays = {
        "vocabulary_id": np.array(str(a["vocabulary_id"])),
        "vocabulary_size": np.array(int(a["vocabulary_size"]), dtype=np.int64),
        "word_indptr": indptr.astype(np.int64, copy=False),
        "word_indices": _concatenate(a["word_indices"], b["word_indices"]),
        "place_stamps_ns": _concatenate(a["place_stamps_ns"], b["place_stamps_ns"], np.int64),
        "place_frames": _concatenate(a["place_frames"], np.asarray(b["place_frames"], dtype=np.int64) + query_offset,
                                     np.int64),
        "place_sessions": _concatenate(a["place_sessions"],
                                       np.asarray(b["place_sessions"], dtype=np.int32) + len(a["session_robots"]),
                                       np.int32),
        "session_robots": np.concatenate([np.asarray(a["session_robots"], dtype=np.str_),
                                          np.asarray(b["session_robots"], dtype=np.str_)]),
        "session_first_queries": _concatenate(
            a["session_first_queries"], np.asarray(b["session_first_queries"], dtype=np.int64) + query_offset,
            np.int64),
        "next_query_id": np.array(query_offset + int(b["next_query_id"]), dtype=np.int64),
        **_no_previous_posterior(),
    }
    if "config_json" in a:
        merged["config_json"] = np.array(str(a["config_json"]))
    return merged


def remove_session(arrays: MapArrays, number: int) -> MapArrays:
    """The map without session ``number`` and its places; later sessions are renumbered down by one.

    Query ids are not renumbered and ``next_query_id`` is kept: the remaining places keep the frames they
    were made from, and a later session never reuses a query id the map has given out (a backend may still
    hold the removed session's frames under those ids). The last posterior is dropped (see the module doc).
    DataError for a session the map does not have.
    """
    robots = np.asarray(arrays["session_robots"], dtype=np.str_)
    if not 0 <= number < robots.size:
        have = f"sessions 0 to {robots.size - 1}" if robots.size else "no sessions"
        raise DataError(f"the map has no session {number} (it has {have})")
    indptr = np.asarray(arrays["word_indptr"], dtype=np.int64)
    place_sessions = np.asarray(arrays["place_sessions"], dtype=np.int32)
    keep = place_sessions != number
    lengths = np.diff(indptr)
    kept_lengths = lengths[keep]
    result: MapArrays = {key: value for key, value in arrays.items()
                         if key not in ("format_version", "previous_posterior", "has_previous_posterior")}
    result.update({
        "word_indptr": np.concatenate([np.zeros(1, dtype=np.int64), np.cumsum(kept_lengths, dtype=np.int64)]),
        "word_indices": np.asarray(arrays["word_indices"])[np.repeat(keep, lengths)],
        "place_stamps_ns": np.asarray(arrays["place_stamps_ns"], dtype=np.int64)[keep],
        "place_frames": np.asarray(arrays["place_frames"], dtype=np.int64)[keep],
        "place_sessions": (place_sessions[keep] - (place_sessions[keep] > number)).astype(np.int32),
        "session_robots": np.delete(robots, number),
        "session_first_queries": np.delete(np.asarray(arrays["session_first_queries"], dtype=np.int64), number),
        **_no_previous_posterior(),
    })
    return result


def _concatenate(first: np.ndarray, second: np.ndarray, dtype: type[np.generic] | None = None) -> np.ndarray:
    """``first`` then ``second`` in one array (of ``dtype``, else ``first``'s)."""
    dtype = dtype or np.asarray(first).dtype.type
    return np.concatenate([np.asarray(first, dtype=dtype), np.asarray(second, dtype=dtype)])


def _no_previous_posterior() -> MapArrays:
    return {"previous_posterior": np.zeros(0), "has_previous_posterior": np.array(False)}
