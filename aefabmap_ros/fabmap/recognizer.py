"""Online place recognition with FAB-MAP 2: data association, place policies, sessions, map persistence.

One :class:`PlaceRecognizer` holds one map of places, shared by every robot that feeds it. Every call of
:meth:`PlaceRecognizer.process` is one frame of one robot and gets the next query id (0, 1, 2, ...), also
frames without words. Frames with fewer than ``min_words`` distinct words stop there: they carry almost no
evidence, and FAB-MAP would match a blank frame to any earlier blank frame with certainty (see
:data:`aefabmap_ros.fabmap.config.DEFAULT_MIN_WORDS`); they get no posterior and no place, and the motion
model continues from the robot's last informative frame. Every other frame:

1. FAB-MAP 2 log-likelihoods of every stored place and of the new place.
2. Hypotheses: "new" plus the stored places except those too recent to be a revisit: places the robot's
   current session made from its last ``exclude_recent_frames`` frames, stamped less than
   ``exclude_recent_seconds`` before the query, or (``exclude_linked_overlap``) in the session's newest run
   of places whose words still overlap the query's. Places of other robots and of earlier sessions are
   never too recent. Excluded places are no hypotheses at all (the posterior sums to one over the rest).
3. Prior: uniform, or openFABMAP's motion model from the robot's previous posterior (see
   :func:`aefabmap_ros.fabmap.posterior.motion_log_prior`; excluded places count as probability 0
   there). The log-likelihoods are divided by ``likelihood_temperature`` (calibration), then
   smoothing p <- s p + (1 - s) / n over the n hypotheses.
4. Data association: the frame matches the best place when its posterior exceeds ``match_threshold``.
   The match is a loop closure once it is temporally consistent: the robot's last ``consistency_matches``
   informative frames matched places within ``island_seconds`` of each other
   (:mod:`aefabmap_ros.fabmap.consistency`).
5. Place addition (places, not frames): policy "all" adds every frame, "new_only" only unmatched
   frames; in both cases only keyframes are added: at least ``keyframe_min_frames`` of the robot's frames
   after its session's last place and a Jaccard word overlap with it of at most ``keyframe_max_overlap``,
   or, when ``keyframe_max_frames`` / ``keyframe_max_seconds`` > 0, once that many frames / seconds have
   passed (whatever the overlap). A session's first informative frame is always a keyframe. A frame that
   adds no place belongs to its session's newest place (``Recognition.current_place_id``).

Sessions (:mod:`aefabmap_ros.fabmap.sessions`, per-robot state in :mod:`aefabmap_ros.fabmap.robot_track`):
a recognizer starts session 0 of its ``robot``; another robot's first frame starts a session of that robot;
a map loaded from disk continues in a new session, and :meth:`PlaceRecognizer.start_session` starts one on
request (a robot relocated). A new session starts with the motion model's first prior (the robot may be
anywhere) and a fresh consistency chain. Every place and candidate carries its session and robot.

Place ids are 0, 1, 2, ... in the order places are added (so with one robot, policy "all", default
keyframing and ``min_words = 0``, place id == query id, as in openFABMAP's golden run).

New-place samples that are the query itself: pass ``exclude_sample=<sample index>`` to
:meth:`PlaceRecognizer.process` (identity by index, not by comparing word sets).

The map (places' words, stamps, frames, sessions, counters, last posterior) is saved atomically as an
``.npz`` tied to the model's vocabulary id (:mod:`aefabmap_ros.fabmap.map_file`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.engines import make_engine
from aefabmap_ros.fabmap.map_file import ConfigDifferences, config_differences, read_map, write_map
from aefabmap_ros.fabmap.observation import as_word_ids
from aefabmap_ros.fabmap.place_table import PlaceTable
from aefabmap_ros.fabmap.posterior import top_k_indices
from aefabmap_ros.fabmap.recognition import Candidate, Recognition, jaccard
from aefabmap_ros.fabmap.robot_track import RobotTrack
from aefabmap_ros.fabmap.sessions import Session, SessionTable, check_robot_name

__all__ = ["RUNTIME_SETTINGS", "Candidate", "PlaceRecognizer", "Recognition", "jaccard"]

# Settings read afresh for every frame (nothing is built from them at start-up), so they can change
# while the recognizer runs; the others shape the engine or the consistency chain, built once.
RUNTIME_SETTINGS = frozenset({
    "match_threshold", "likelihood_temperature", "top_k", "min_words", "add_policy",
    "exclude_recent_frames", "exclude_recent_seconds", "keyframe_max_overlap", "keyframe_max_seconds",
})


class PlaceRecognizer:
    """FAB-MAP 2 place recognizer over a growing map of places (see module doc for the policies)."""

    def __init__(self, tree: ChowLiuTree, new_place_samples: sp.csr_matrix | None, config: FabMapConfig,
                 vocabulary_id: str, robot: str = "") -> None:
        if not isinstance(vocabulary_id, str) or not vocabulary_id:
            raise DataError(f"vocabulary_id must be a non-empty string, got {vocabulary_id!r}")
        self.config = config
        self.vocabulary_id = vocabulary_id
        self.robot = check_robot_name(robot)  # the robot of frames that name none
        self._engine = make_engine(tree, new_place_samples, config, "fabmap2")
        self._reset()

    def _reset(self) -> None:
        self._engine.clear()
        self._places = PlaceTable()
        self._next_query_id = 0
        self._tracks: dict[str, RobotTrack] = {}
        self.start_session()

    # -- read-only views ----------------------------------------------------------------------

    @property
    def vocabulary_size(self) -> int:
        return self._engine.model.vocabulary_size

    @property
    def num_places(self) -> int:
        return self._engine.num_places

    @property
    def num_queries(self) -> int:
        return self._next_query_id

    @property
    def sessions(self) -> SessionTable:
        return self._places.sessions

    @property
    def current_session(self) -> Session:
        """The session of this recognizer's own robot."""
        return self._tracks[self.robot].session

    def session_of(self, robot: str) -> Session | None:
        """The current session of ``robot``, None before its first frame."""
        track = self._tracks.get(robot)
        return None if track is None else track.session

    @property
    def place_sessions(self) -> np.ndarray:
        """(P,) int32 session of each place (a copy)."""
        return self._places.session_numbers.copy()

    def place_words(self, place_id: int) -> np.ndarray:
        return self._engine.places.place_words(self._known(place_id))

    def place_stamp_ns(self, place_id: int) -> int:
        return int(self._places.stamps_ns[self._known(place_id)])

    def _known(self, place_id: int) -> int:
        if not 0 <= place_id < self.num_places:
            raise DataError(f"place id {place_id} out of range [0, {self.num_places})")
        return place_id

    @property
    def place_stamps_ns(self) -> np.ndarray:
        """(P,) int64 stamp of each place's frame (a copy)."""
        return self._places.stamps_ns.copy()

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the place index (word lists, postings, defaults)."""
        return self._engine.places.nbytes + 28 * self.num_places

    def reconfigure(self, changes: Mapping[str, Any]) -> None:
        """Change settings of :data:`RUNTIME_SETTINGS` from the next frame on (validated as a whole);
        ConfigError for any other setting or a bad value, and then nothing changes."""
        self.config = _reconfigured(self.config, changes)

    # -- sessions -------------------------------------------------------------------------------

    def start_session(self, robot: str | None = None) -> Session:
        """Begin a new session of ``robot`` (default: this recognizer's) from its next frame on.

        A session that has seen no frame yet is reused rather than followed by an empty one, so a node
        restarted twice without images adds one session, not two.
        """
        robot = self.robot if robot is None else check_robot_name(robot)
        track, sessions = self._tracks.get(robot), self._places.sessions
        if track is not None and track.frames_seen == 0:
            session = track.session
        elif track is None and len(sessions) and sessions.current.robot == robot \
                and sessions.current.first_query_id == self._next_query_id:
            session = sessions.current  # a reloaded map's last session, which never saw a frame
        else:
            session = sessions.start(robot, self._next_query_id)
        self._tracks[robot] = RobotTrack(session, self.config)
        return session

    def _track(self, robot: str | None) -> RobotTrack:
        robot = self.robot if robot is None else check_robot_name(robot)
        if robot not in self._tracks:  # a robot's first frame on this map starts its session
            self.start_session(robot)
        return self._tracks[robot]

    # -- processing ---------------------------------------------------------------------------

    def process(self, word_ids: np.ndarray, stamp_ns: int, exclude_sample: int | None = None,
                robot: str | None = None) -> Recognition:
        """Recognise one frame of ``robot`` (default: this recognizer's) from its sorted unique word ids
        (unsorted/duplicates are normalised).

        Raises DataError for ids outside [0, V), non-integer ids, a non-integer stamp or a bad robot name.
        """
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
            raise DataError(f"stamp_ns must be an integer (nanoseconds), got {stamp_ns!r}")
        stamp_ns = int(stamp_ns)
        words = as_word_ids(word_ids, self.vocabulary_size)
        track = self._track(robot)
        query_id = self._next_query_id
        self._next_query_id += 1
        try:
            if words.size < self.config.min_words:
                # No evidence: the belief stays as it was (the motion model continues from the last
                # informative frame) and the frame neither matches nor becomes a place.
                return Recognition(
                    query_id=query_id, stamp_ns=stamp_ns, assigned_place_id=-1, is_new_place=False,
                    new_place_probability=float("nan"), candidates=(), loop_closure=None,
                    new_place_log_likelihood=float("nan"), informative=False, current_place_id=track.last_place,
                    session=track.session.number, robot=track.robot)
            return self._recognise(words, stamp_ns, query_id, track, exclude_sample)
        finally:
            track.observe_frame()

    def _recognise(self, words: np.ndarray, stamp_ns: int, query_id: int, track: RobotTrack,
                   exclude_sample: int | None) -> Recognition:
        new_ll, place_ll = self._engine.log_likelihoods(words, exclude_sample)
        included = np.flatnonzero(self._included(track, stamp_ns, words))
        p = track.posterior(self.config, new_ll, place_ll, included)
        place_p = p[1:]
        # Best first, ties: older place first (``included`` is increasing); O(k P), not a full sort.
        order = top_k_indices(place_p, max(self.config.top_k, 1))
        candidates = tuple(self._candidate(int(included[k]), place_p[k], place_ll) for k in order[: self.config.top_k])
        match = None
        if order.size and place_p[order[0]] > self.config.match_threshold:
            match = self._candidate(int(included[order[0]]), place_p[order[0]], place_ll)
        consistent = track.consistency.observe(stamp_ns, None if match is None else match.stamp_ns)
        wants_place = self.config.add_policy == "all" or match is None
        added = self._add_if_keyframe(words, query_id, stamp_ns, track) if wants_place else -1
        return Recognition(
            query_id=query_id, stamp_ns=stamp_ns, assigned_place_id=match.place_id if match is not None else added,
            is_new_place=match is None, new_place_probability=float(p[0]), candidates=candidates,
            loop_closure=match if consistent else None, added_place_id=added,
            new_place_log_likelihood=float(new_ll), match=match, current_place_id=track.last_place,
            hypothesis_place_ids=included, hypothesis_probabilities=place_p,
            session=track.session.number, robot=track.robot)

    def _candidate(self, place_id: int, probability: float, place_ll: np.ndarray) -> Candidate:
        session = self._places.session_of(place_id)
        return Candidate(place_id=place_id, stamp_ns=int(self._places.stamps_ns[place_id]),
                         probability=float(probability), log_likelihood=float(place_ll[place_id]),
                         session=session.number, robot=session.robot)

    def _add_if_keyframe(self, words: np.ndarray, query_id: int, stamp_ns: int, track: RobotTrack) -> int:
        """The id of the place this frame adds when it is a keyframe of its robot, else -1."""
        last_stamp_ns = int(self._places.stamps_ns[track.last_place]) if track.places else 0
        if not track.is_keyframe(self.config, words, stamp_ns, self._engine.places.place_words, last_stamp_ns):
            return -1
        added = self._engine.add(words)
        self._places.add(np.array([stamp_ns]), np.array([query_id]), track.session.number,
                         np.array([track.frames_seen]))
        track.made_place(added)
        return added

    def _included(self, track: RobotTrack, stamp_ns: int, words: np.ndarray) -> np.ndarray:
        """(P,) bool: places that are hypotheses for this query: all but the robot's session's recent ones."""
        recent = self._places.too_recent(track.session, track.frames_seen, stamp_ns, self.config.exclude_recent_frames,
                                         self.config.exclude_recent_seconds)
        if self.config.exclude_linked_overlap > 0.0:
            linked = track.linked_places(words, self._engine.places.place_words, self.config.exclude_linked_overlap)
            recent[linked] = True
        return ~recent

    def add_places(self, places: sp.csr_matrix, stamps_ns: np.ndarray) -> None:
        """Bulk-add places of this recognizer's robot without recognising them (e.g. a map built offline):
        (P, V) binary rows. Each place counts as one processed frame (its query id is its frame)."""
        matrix, stamps = _place_rows(places, stamps_ns, self.vocabulary_size)
        track = self._track(None)
        first_place, first = self.num_places, self._next_query_id
        self._engine.places.add_many(matrix.indptr.astype(np.int64), matrix.indices)
        count = matrix.shape[0]
        self._places.add(stamps, np.arange(first, first + count), track.session.number,
                         np.arange(count) + track.frames_seen)
        for offset in range(matrix.shape[0]):
            track.made_place(first_place + offset)
            track.observe_frame()
        self._next_query_id += matrix.shape[0]

    # -- persistence --------------------------------------------------------------------------

    def save_map(self, path: Path) -> None:
        """Write the map atomically (temporary file in the same directory, then os.replace)."""
        indptr, indices = self._engine.places.word_csr()
        previous = self._tracks[self.robot].previous_posterior
        arrays = {
            "vocabulary_id": np.array(self.vocabulary_id),
            "vocabulary_size": np.array(self.vocabulary_size, dtype=np.int64),
            "word_indptr": indptr,
            "word_indices": indices,  # uint16 when the vocabulary fits, else int32: as the index stores them
            "next_query_id": np.array(self._next_query_id, dtype=np.int64),
            "previous_posterior": np.zeros(0) if previous is None else previous,
            "has_previous_posterior": np.array(previous is not None),
            "config_json": np.array(json.dumps(asdict(self.config), sort_keys=True)),
            **self._places.to_arrays(),
        }
        write_map(path, arrays)

    def load_map(self, path: Path, new_session: bool = True) -> ConfigDifferences:
        """Replace the map by the one saved at ``path``; returns the settings it was made with that
        differ from this recognizer's (:func:`config_differences`), for the caller to report.

        With ``new_session`` (a node starting on a saved map), later frames of every robot belong to new
        sessions; without it, this recognizer's robot continues the map's last session (its belief and
        consistency chain as saved: a map of one robot goes on as if never stopped).

        Raises VocabularyMismatchError (naming both ids) if it belongs to another vocabulary,
        ModelError if it is missing, corrupt or of another format version. Other settings do not
        refuse a map: places are stored as word sets, which only the vocabulary gives a meaning to;
        the settings change how later frames are matched and added, not what the places are.
        """
        state = read_map(Path(path), self.vocabulary_id, self.vocabulary_size)
        self._reset()
        self._engine.places.add_many(state["word_indptr"], state["word_indices"])
        self._places = PlaceTable.from_arrays(state)
        self._next_query_id = int(state["next_query_id"])
        self._tracks = {}
        if new_session:
            self.start_session()
        else:  # the map's last session goes on, with the belief it was saved with
            previous = state["previous_posterior"] if bool(state["has_previous_posterior"]) else None
            track = RobotTrack.continuing(self._places, self.config, self._next_query_id, previous)
            self.robot, self._tracks[track.robot] = track.robot, track
        if "config_json" not in state:  # written by a version that did not record its settings
            return {"config_json": (None, "not recorded in the map")}
        return config_differences(str(state["config_json"]), self.config)


def _place_rows(places: sp.csr_matrix, stamps_ns: np.ndarray, vocabulary_size: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """Places given as (P, V) rows, binarised with sorted indices, and their (P,) integer stamps; DataError
    for other shapes or types."""
    matrix = sp.csr_matrix(places)
    if matrix.ndim != 2 or matrix.shape[1] != vocabulary_size:
        raise DataError(f"places have shape {matrix.shape}, expected (P, {vocabulary_size})")
    stamps = np.asarray(stamps_ns)
    if stamps.shape != (matrix.shape[0],) or not np.issubdtype(stamps.dtype, np.integer):
        raise DataError(f"stamps_ns must be ({matrix.shape[0]},) integers, got {stamps.shape} {stamps.dtype}")
    matrix = sp.csr_matrix(matrix > 0)
    matrix.sort_indices()
    return matrix, stamps


def _reconfigured(config: FabMapConfig, changes: Mapping[str, Any]) -> FabMapConfig:
    """``config`` with ``changes`` of :data:`RUNTIME_SETTINGS`; ConfigError for any other setting or a bad value."""
    fixed = sorted(set(changes) - RUNTIME_SETTINGS)
    if fixed:
        raise ConfigError(f"{', '.join(fixed)} cannot change while the recognizer runs "
                          f"(only {', '.join(sorted(RUNTIME_SETTINGS))} can)")
    return replace(config, **changes)
