"""The place map of a ``PlaceRecognizer`` on disk: places' word sets, stamps, frames and sessions, the
session table, counters and last posterior in a versioned ``.npz`` written atomically, tied to the model's
vocabulary id and recording the settings it was made with.

Format 2 adds the sessions (``place_sessions``, ``session_robots``, ``session_first_queries``). A format-1
map (written before maps kept sessions) reads as one session of robot '' holding every place.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.errors import DataError, ModelError, VocabularyMismatchError
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.sessions import SessionTable
from aefabmap_ros.io.npz_files import read_versioned_npz, write_npz_atomically

MAP_FORMAT_VERSION = 2
_MAP_KEYS = ("vocabulary_id", "vocabulary_size", "word_indptr", "word_indices", "place_stamps_ns", "place_frames",
             "next_query_id", "previous_posterior", "has_previous_posterior")
_SESSION_KEYS = ("place_sessions", "session_robots", "session_first_queries")
_CHECK_CHUNK_ROWS = 65_536

ConfigDifferences = dict[str, tuple[Any, Any]]  # setting -> (value the map was made with, value now)


def config_differences(saved_json: str, config: FabMapConfig) -> ConfigDifferences:
    """The settings of ``config`` that differ from those a map was saved with (its ``config_json``).

    A setting the saved map does not name (an older version) or names but ``config`` lacks (a newer
    one) differs too, with None on the missing side; an unreadable ``config_json`` is one difference
    named ``config_json``.
    """
    try:
        saved = json.loads(saved_json)
    except json.JSONDecodeError:
        saved = None
    if not isinstance(saved, dict):
        return {"config_json": (saved_json, "unreadable")}
    current = asdict(config)
    return {key: (saved.get(key), current.get(key)) for key in sorted(saved.keys() | current.keys())
            if saved.get(key) != current.get(key)}


def write_map(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a map's arrays (``_MAP_KEYS``, ``_SESSION_KEYS`` and ``config_json``) with the format version,
    atomically."""
    missing = [key for key in (*_MAP_KEYS, *_SESSION_KEYS) if key not in arrays]
    if missing:
        raise ModelError(f"map for {path} lacks {missing}")
    write_npz_atomically(path, {"format_version": np.array(MAP_FORMAT_VERSION, dtype=np.int64), **arrays})


def read_map(path: Path, vocabulary_id: str, vocabulary_size: int) -> dict[str, np.ndarray]:
    """A map's arrays, checked: VocabularyMismatchError for another vocabulary, ModelError when missing,
    corrupt or of another format version."""
    # The word ids are read with an eighth to spare: the index adopts them and grows into that room online.
    arrays = read_versioned_npz(path, "map file", "place map", _MAP_KEYS, (1, MAP_FORMAT_VERSION),
                                room={"word_indices": 0.125})
    if int(arrays["format_version"]) == 1:
        arrays = _with_one_session(arrays)
    return _validated_state(path, arrays, vocabulary_id, vocabulary_size)


def read_map_unchecked_vocabulary(path: Path) -> dict[str, np.ndarray]:
    """A map's arrays, checked as ``read_map`` does against the vocabulary the map itself names (for tools
    that read a map without its model)."""
    arrays = read_versioned_npz(path, "map file", "place map", _MAP_KEYS, (1, MAP_FORMAT_VERSION))
    if int(arrays["format_version"]) == 1:
        arrays = _with_one_session(arrays)
    return _validated_state(path, arrays, str(arrays["vocabulary_id"]), int(arrays["vocabulary_size"]))


def _with_one_session(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A format-1 map's arrays with the session columns it lacks: one session of robot '' from query 0."""
    n_places = max(int(np.asarray(arrays["word_indptr"]).size) - 1, 0)
    return {**arrays, "place_sessions": np.zeros(n_places, dtype=np.int32),
            "session_robots": np.array([""], dtype=np.str_), "session_first_queries": np.zeros(1, dtype=np.int64)}


def _unsorted_within_rows(indptr: np.ndarray, indices: np.ndarray) -> bool:
    """True if some CSR row's indices are not strictly increasing (vectorised, a chunk of rows at a time so that
    a million-place map needs no temporaries of its size)."""
    rows = indptr.size - 1
    for first in range(0, rows, _CHECK_CHUNK_ROWS):
        end = min(first + _CHECK_CHUNK_ROWS, rows)
        chunk = indices[indptr[first]:indptr[end]].astype(np.int64)
        not_increasing = np.diff(chunk) <= 0
        crossings = indptr[first + 1:end] - indptr[first] - 1  # positions comparing a row's last with the next's
        crossings = crossings[(crossings >= 0) & (crossings < not_increasing.size)]
        not_increasing[crossings] = False
        if np.any(not_increasing):
            return True
    return False


def _validated_state(path: Path, arrays: dict[str, np.ndarray], vocabulary_id: str, vocabulary_size: int
                     ) -> dict[str, np.ndarray]:
    map_vocabulary_id = str(arrays["vocabulary_id"])
    if map_vocabulary_id != vocabulary_id:
        raise VocabularyMismatchError(
            f"map file {path} belongs to vocabulary {map_vocabulary_id!r}, "
            f"but the loaded model is vocabulary {vocabulary_id!r}"
        )
    if int(arrays["vocabulary_size"]) != vocabulary_size:
        raise VocabularyMismatchError(
            f"map file {path} has {int(arrays['vocabulary_size'])} words, the model {vocabulary_size}"
        )
    indptr = arrays["word_indptr"].astype(np.int64)
    indices = arrays["word_indices"]  # any integer type, kept (a million places' uint16 ids are 600 MB)
    n_places = indptr.size - 1
    stamps, frames = arrays["place_stamps_ns"], arrays["place_frames"]
    previous = arrays["previous_posterior"].astype(np.float64)
    problems = []
    if n_places < 0 or indptr[0] != 0 or np.any(np.diff(indptr) < 0) or indptr[-1] != indices.size:
        problems.append("inconsistent word_indptr")
    elif not np.issubdtype(indices.dtype, np.integer):
        problems.append(f"word ids of type {indices.dtype}, not integers")
    elif indices.size and (int(indices.min()) < 0 or int(indices.max()) >= vocabulary_size):
        problems.append("word ids out of range")
    elif _unsorted_within_rows(indptr, indices):
        problems.append("word ids not sorted unique per place")
    if stamps.shape != (max(n_places, 0),) or frames.shape != (max(n_places, 0),):
        problems.append("stamps/frames do not match the number of places")
    if bool(arrays["has_previous_posterior"]) and previous.size > max(n_places, 0) + 1:
        problems.append("previous posterior longer than the map")
    problems.extend(_session_problems(arrays, max(n_places, 0)))
    if problems:
        raise ModelError(f"corrupt map file {path}: {'; '.join(problems)}")
    arrays = dict(arrays)
    arrays["word_indptr"], arrays["word_indices"], arrays["previous_posterior"] = indptr, indices, previous
    arrays["place_sessions"] = arrays["place_sessions"].astype(np.int32)
    return arrays


def _session_problems(arrays: dict[str, np.ndarray], n_places: int) -> list[str]:
    """What is wrong with a map's session columns: the table readable and every place in one of its sessions
    (several robots' sessions run at once, so their places interleave)."""
    try:
        table = SessionTable.from_arrays(arrays["session_robots"], arrays["session_first_queries"])
    except DataError as exc:
        return [str(exc)]
    sessions = np.asarray(arrays["place_sessions"])
    if sessions.shape != (n_places,) or not np.issubdtype(sessions.dtype, np.integer):
        return [f"place_sessions has shape {sessions.shape}, expected ({n_places},) integers"]
    if n_places and (len(table) == 0 or sessions.min() < 0 or sessions.max() >= len(table)):
        return [f"place sessions outside the {len(table)} sessions of the table"]
    return []
