"""Online place recognition with FAB-MAP 2: data association, place policies, map persistence.

One :class:`PlaceRecognizer` per camera. Every call of :meth:`PlaceRecognizer.process` is one
frame and gets the next query id (0, 1, 2, ...), also frames without words. Frames with fewer
than ``min_words`` distinct words stop there: they carry almost no evidence, and FAB-MAP would
match a blank frame to any earlier blank frame with certainty (see
:data:`aefabmap_ros.fabmap.config.DEFAULT_MIN_WORDS`); they get no posterior and no place, and the
motion model continues from the last informative frame. Every other frame:

1. FAB-MAP 2 log-likelihoods of every stored place and of the new place.
2. Hypotheses: "new" plus the stored places except the recent ones: places created from the
   last ``exclude_recent_frames`` frames (query_id - place's frame <= N), stamped less than
   ``exclude_recent_seconds`` before the query, or (``exclude_linked_overlap``) in the newest run
   of places whose words still overlap the query's. Excluded places are not hypotheses at all
   (they get no probability mass, the posterior sums to one over the remaining hypotheses).
3. Prior: uniform, or openFABMAP's motion model from the previous frame's posterior (see
   :func:`aefabmap_ros.fabmap.posterior.motion_log_prior`; excluded places count as probability 0
   there). The log-likelihoods are divided by ``likelihood_temperature`` (calibration), then
   smoothing p <- s p + (1 - s) / n over the n hypotheses.
4. Data association: the frame matches the best place when its posterior exceeds
   ``match_threshold``. The match is a loop closure once it is temporally consistent: the last
   ``consistency_matches`` informative frames matched places within ``island_seconds`` of each
   other (:mod:`aefabmap_ros.fabmap.consistency`; the chain starts afresh after a restart).
5. Place addition (places, not frames): policy "all" adds every frame, "new_only" only unmatched
   frames; in both cases only keyframes are added: at least ``keyframe_min_frames`` frames after
   the last added place and a Jaccard word overlap with it of at most ``keyframe_max_overlap``,
   or, when ``keyframe_max_frames`` / ``keyframe_max_seconds`` > 0, once that many frames / seconds
   have passed (whatever the overlap). A frame that adds no place belongs to the current place
   (``Recognition.current_place_id``).

Sessions (:mod:`aefabmap_ros.fabmap.sessions`): a recognizer starts session 0 of its ``robot``; a map
loaded from disk continues in a new session, and :meth:`PlaceRecognizer.start_session` starts one on
request (a robot relocated). Every place and every candidate carries its session and robot. A new session
starts with a uniform prior (the robot may be anywhere), a fresh consistency chain, and its first
informative frame makes a place. The recency exclusions of step 2 apply to places of the current session
only: a robot restarted where it stopped sees the last places of the earlier session, and that is the
closure that joins the two sessions' graphs.

Place ids are 0, 1, 2, ... in the order places are added (so with policy "all", default
keyframing and ``min_words = 0``, place id == query id, as in openFABMAP's golden run).

New-place samples that are the query itself: pass ``exclude_sample=<sample index>`` to
:meth:`PlaceRecognizer.process` (identity by index, not by comparing word sets).

The map (places' words, stamps, frames, counters, last posterior) is saved atomically as an
``.npz`` tied to the model's vocabulary id (:mod:`aefabmap_ros.fabmap.map_file`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.consistency import TemporalConsistency
from aefabmap_ros.fabmap.engines import make_engine
from aefabmap_ros.fabmap.index import GrowableArray
from aefabmap_ros.fabmap.map_file import ConfigDifferences, config_differences, read_map, write_map
from aefabmap_ros.fabmap.observation import as_word_ids
from aefabmap_ros.fabmap.posterior import motion_log_prior, posterior, top_k_indices
from aefabmap_ros.fabmap.sessions import Session, SessionTable, check_robot_name


@dataclass(frozen=True)
class Candidate:
    """A known place as a hypothesis for the query."""

    place_id: int
    stamp_ns: int  # stamp of the frame the place was created from
    probability: float
    log_likelihood: float  # FAB-MAP 2 scale: relative to a place without words
    session: int = 0  # session the place was made in
    robot: str = ""  # robot of that session


@dataclass(frozen=True)
class Recognition:
    """The outcome of one frame."""

    query_id: int
    stamp_ns: int
    assigned_place_id: int  # matched place, else the place created from this frame, else -1
    is_new_place: bool  # no known place exceeded the match threshold
    new_place_probability: float
    candidates: tuple[Candidate, ...]  # top-K places by posterior, best first
    loop_closure: Candidate | None  # the match, once it is temporally consistent (see consistency_matches)
    added_place_id: int = -1  # place created from this frame, -1 if none (policy / keyframing)
    new_place_log_likelihood: float = 0.0
    # False: fewer than ``min_words`` words; nothing was decided (no candidates, no place, and
    # ``new_place_probability`` is nan).
    informative: bool = True
    match: Candidate | None = None  # best place above match_threshold, consistent or not
    # The place of the map this frame belongs to: the one it created, else the current (last added)
    # place it joined because the scene had not changed; -1 while the map is empty.
    current_place_id: int = -1
    # Every hypothesis of the posterior: (H,) place ids (increasing) and their probabilities (arrays:
    # left out of ==, which compares the decision).
    hypothesis_place_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), compare=False)
    hypothesis_probabilities: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False)
    session: int = 0  # session of the query frame
    robot: str = ""  # robot of that session


def jaccard(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∩ b| / |a ∪ b| of two sorted unique word-id arrays; 1.0 for two empty sets."""
    union = a.size + b.size
    if union == 0:
        return 1.0
    common = np.intersect1d(a, b, assume_unique=True).size
    return common / (union - common)


# Settings read afresh for every frame (nothing is built from them at start-up), so they can change
# while the recognizer runs; the others shape the engine or the consistency chain, built once.
RUNTIME_SETTINGS = frozenset({
    "match_threshold", "likelihood_temperature", "top_k", "min_words", "add_policy",
    "exclude_recent_frames", "exclude_recent_seconds", "keyframe_max_overlap", "keyframe_max_seconds",
})

class PlaceRecognizer:
    """FAB-MAP 2 place recognizer over a growing map of places (see module doc for the policies)."""

    def __init__(
        self,
        tree: ChowLiuTree,
        new_place_samples: sp.csr_matrix | None,
        config: FabMapConfig,
        vocabulary_id: str,
        robot: str = "",
    ) -> None:
        if not isinstance(vocabulary_id, str) or not vocabulary_id:
            raise DataError(f"vocabulary_id must be a non-empty string, got {vocabulary_id!r}")
        self.config = config
        self.vocabulary_id = vocabulary_id
        self.robot = check_robot_name(robot)
        self._engine = make_engine(tree, new_place_samples, config, "fabmap2")
        self._reset()

    def _reset(self) -> None:
        self._engine.clear()
        self._place_stamps_ns = GrowableArray(np.int64, 64)  # (P,) stamp of each place's frame
        self._place_frames = GrowableArray(np.int64, 64)  # (P,) query id of each place's frame
        self._place_sessions = GrowableArray(np.int32, 64)  # (P,) session each place was made in
        self._next_query_id = 0
        self._sessions = SessionTable()
        self._sessions.start(self.robot, 0)
        self._begin_session_state()

    def _begin_session_state(self) -> None:
        """What a session starts afresh: the belief, the consistency chain, and a place at its first frame."""
        self._previous_posterior: np.ndarray | None = None  # over [new, every place at that time]
        self._consistency = TemporalConsistency(
            self.config.consistency_matches, self.config.island_seconds, max_skipped=self.config.consistency_skips,
            window_seconds=self.config.consistency_window_seconds,
        )
        self._session_has_place = False

    def start_session(self, robot: str | None = None) -> Session:
        """Begin a new session (of ``robot``, default this recognizer's) from the next frame on.

        A session that has seen no frame yet is reused rather than followed by an empty one, so a node
        restarted twice without images adds one session, not two.
        """
        robot = self.robot if robot is None else check_robot_name(robot)
        current = self._sessions.current
        if current.first_query_id == self._next_query_id and current.robot == robot:
            self._begin_session_state()
            return current
        session = self._sessions.start(robot, self._next_query_id)
        self.robot = robot
        self._begin_session_state()
        return session

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
        return self._sessions

    @property
    def current_session(self) -> Session:
        return self._sessions.current

    @property
    def place_sessions(self) -> np.ndarray:
        """(P,) int32 session of each place (a copy)."""
        return self._place_sessions.view().copy()

    def place_words(self, place_id: int) -> np.ndarray:
        if not 0 <= place_id < self.num_places:
            raise DataError(f"place id {place_id} out of range [0, {self.num_places})")
        return self._engine.places.place_words(place_id)

    def place_stamp_ns(self, place_id: int) -> int:
        if not 0 <= place_id < self.num_places:
            raise DataError(f"place id {place_id} out of range [0, {self.num_places})")
        return int(self._place_stamps_ns.view()[place_id])

    @property
    def place_stamps_ns(self) -> np.ndarray:
        """(P,) int64 stamp of each place's frame (a copy)."""
        return self._place_stamps_ns.view().copy()

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the place index (word lists, postings, defaults)."""
        return self._engine.places.nbytes + 16 * self.num_places

    def reconfigure(self, changes: Mapping[str, Any]) -> None:
        """Change settings of :data:`RUNTIME_SETTINGS` from the next frame on (validated as a whole);
        ConfigError for any other setting or a bad value, and then nothing changes."""
        fixed = sorted(set(changes) - RUNTIME_SETTINGS)
        if fixed:
            raise ConfigError(f"{', '.join(fixed)} cannot change while the recognizer runs "
                              f"(only {', '.join(sorted(RUNTIME_SETTINGS))} can)")
        self.config = replace(self.config, **changes)

    # -- processing ---------------------------------------------------------------------------

    def process(self, word_ids: np.ndarray, stamp_ns: int, exclude_sample: int | None = None) -> Recognition:
        """Recognise one frame (sorted unique word ids; unsorted/duplicates are normalised).

        Raises DataError for ids outside [0, V), non-integer ids or a non-integer stamp.
        """
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
            raise DataError(f"stamp_ns must be an integer (nanoseconds), got {stamp_ns!r}")
        stamp_ns = int(stamp_ns)
        words = as_word_ids(word_ids, self.vocabulary_size)
        query_id = self._next_query_id
        self._next_query_id += 1
        session = self._sessions.current
        if words.size < self.config.min_words:
            # No evidence: the belief stays as it was (the motion model continues from the last
            # informative frame) and the frame neither matches nor becomes a place.
            return Recognition(
                query_id=query_id, stamp_ns=stamp_ns, assigned_place_id=-1, is_new_place=False,
                new_place_probability=float("nan"), candidates=(), loop_closure=None,
                new_place_log_likelihood=float("nan"), informative=False, current_place_id=self.num_places - 1,
                session=session.number, robot=session.robot,
            )

        new_ll, place_ll = self._engine.log_likelihoods(words, exclude_sample)
        included = np.flatnonzero(self._included(query_id, stamp_ns, words))
        p = self._posterior(new_ll, place_ll, included)
        place_p = p[1:]
        # Best first, ties: older place first (``included`` is increasing); O(k P), not a full sort.
        order = top_k_indices(place_p, max(self.config.top_k, 1))
        candidates = tuple(self._candidate(int(included[k]), place_p[k], place_ll) for k in order[: self.config.top_k])
        match = None
        if order.size and place_p[order[0]] > self.config.match_threshold:
            match = self._candidate(int(included[order[0]]), place_p[order[0]], place_ll)
        consistent = self._consistency.observe(stamp_ns, None if match is None else match.stamp_ns)
        loop_closure = match if consistent else None
        wants_place = self.config.add_policy == "all" or match is None
        added = self._add_if_keyframe(words, query_id, stamp_ns) if wants_place else -1
        assigned = match.place_id if match is not None else added
        return Recognition(
            query_id=query_id,
            stamp_ns=stamp_ns,
            assigned_place_id=assigned,
            is_new_place=match is None,
            new_place_probability=float(p[0]),
            candidates=candidates,
            loop_closure=loop_closure,
            added_place_id=added,
            new_place_log_likelihood=float(new_ll),
            match=match,
            current_place_id=self.num_places - 1,
            hypothesis_place_ids=included,
            hypothesis_probabilities=place_p,
            session=session.number,
            robot=session.robot,
        )

    def _posterior(self, new_ll: float, place_ll: np.ndarray, included: np.ndarray) -> np.ndarray:
        """Posterior over [new place, included places]; kept (over every place) for the next frame's prior."""
        hypotheses = np.concatenate([[new_ll], place_ll[included]])
        log_prior = None
        if self.config.motion_model:
            full_prior = motion_log_prior(
                self._previous_posterior, self.num_places, self.config.p_new, self.config.motion_bias
            )
            log_prior = full_prior[np.concatenate([[0], included + 1])]
        p = posterior(hypotheses / self.config.likelihood_temperature, log_prior, self.config.smoothing)
        previous = np.zeros(self.num_places + 1)
        previous[0] = p[0]
        previous[included + 1] = p[1:]
        self._previous_posterior = previous
        return p

    def _candidate(self, place_id: int, probability: float, place_ll: np.ndarray) -> Candidate:
        session = self._sessions[int(self._place_sessions.view()[place_id])]
        return Candidate(place_id=place_id, stamp_ns=int(self._place_stamps_ns.view()[place_id]),
                         probability=float(probability), log_likelihood=float(place_ll[place_id]),
                         session=session.number, robot=session.robot)

    def _add_if_keyframe(self, words: np.ndarray, query_id: int, stamp_ns: int) -> int:
        """The id of the place this frame adds when it is a keyframe, else -1."""
        if not self._is_keyframe(words, query_id, stamp_ns):
            return -1
        added = self._engine.add(words)
        self._place_stamps_ns.extend(np.array([stamp_ns], dtype=np.int64))
        self._place_frames.extend(np.array([query_id], dtype=np.int64))
        self._place_sessions.extend(np.array([self._sessions.current.number], dtype=np.int32))
        self._session_has_place = True
        return added

    def _included(self, query_id: int, stamp_ns: int, words: np.ndarray) -> np.ndarray:
        """(P,) bool: places that are hypotheses for this query (not too recent; places of earlier sessions
        are never too recent)."""
        frames = self._place_frames.view()
        keep = np.ones(frames.size, dtype=bool)
        if self.config.exclude_linked_overlap > 0.0:
            keep[self._linked_places(words) :] = False
        if self.config.exclude_recent_frames > 0:
            keep &= query_id - frames > self.config.exclude_recent_frames
        if self.config.exclude_recent_seconds > 0.0:
            stamps = self._place_stamps_ns.view()
            window_ns = self.config.exclude_recent_seconds * 1e9
            keep &= (stamp_ns - stamps) >= window_ns
        keep |= self._place_sessions.view() != self._sessions.current.number
        return keep

    def _linked_places(self, words: np.ndarray) -> int:
        """First place of the newest run of places that each overlap the query by >= exclude_linked_overlap."""
        first, places = self.num_places, self._engine.places
        if not self._session_has_place:  # the newest places are another session's: none is linked
            return first
        while first > 0 and jaccard(words, places.place_words(first - 1)) >= self.config.exclude_linked_overlap:
            first -= 1
        return first

    def _is_keyframe(self, words: np.ndarray, query_id: int, stamp_ns: int) -> bool:
        if not self._session_has_place:  # a session's first informative frame makes its first place
            return True
        since = query_id - int(self._place_frames.view()[-1])
        if since < self.config.keyframe_min_frames:
            return False
        if self.config.keyframe_max_frames > 0 and since >= self.config.keyframe_max_frames:
            return True
        seconds = (stamp_ns - int(self._place_stamps_ns.view()[-1])) / 1e9
        if self.config.keyframe_max_seconds > 0.0 and seconds >= self.config.keyframe_max_seconds:
            return True
        return jaccard(words, self._engine.places.place_words(self.num_places - 1)) <= self.config.keyframe_max_overlap

    def add_places(self, places: sp.csr_matrix, stamps_ns: np.ndarray) -> None:
        """Bulk-add places without recognising them (e.g. a map built offline): (P, V) binary rows.

        Each place counts as one processed frame (its query id is its frame).
        """
        matrix = sp.csr_matrix(places)
        if matrix.ndim != 2 or matrix.shape[1] != self.vocabulary_size:
            raise DataError(f"places have shape {matrix.shape}, expected (P, {self.vocabulary_size})")
        stamps = np.asarray(stamps_ns)
        if stamps.shape != (matrix.shape[0],) or not np.issubdtype(stamps.dtype, np.integer):
            raise DataError(f"stamps_ns must be ({matrix.shape[0]},) integers, got {stamps.shape} {stamps.dtype}")
        matrix = sp.csr_matrix(matrix > 0)
        matrix.sort_indices()
        self._engine.places.add_many(matrix.indptr.astype(np.int64), matrix.indices)
        first = self._next_query_id
        self._place_frames.extend(np.arange(first, first + matrix.shape[0], dtype=np.int64))
        self._place_stamps_ns.extend(stamps.astype(np.int64))
        self._place_sessions.extend(np.full(matrix.shape[0], self._sessions.current.number, dtype=np.int32))
        self._session_has_place = self._session_has_place or matrix.shape[0] > 0
        self._next_query_id += matrix.shape[0]

    # -- persistence --------------------------------------------------------------------------

    def save_map(self, path: Path) -> None:
        """Write the map atomically (temporary file in the same directory, then os.replace)."""
        indptr, indices = self._engine.places.word_csr()
        arrays = {
            "vocabulary_id": np.array(self.vocabulary_id),
            "vocabulary_size": np.array(self.vocabulary_size, dtype=np.int64),
            "word_indptr": indptr,
            "word_indices": indices,
            "place_stamps_ns": self._place_stamps_ns.view().copy(),
            "place_frames": self._place_frames.view().copy(),
            "next_query_id": np.array(self._next_query_id, dtype=np.int64),
            "previous_posterior": (
                np.zeros(0) if self._previous_posterior is None else self._previous_posterior
            ),
            "has_previous_posterior": np.array(self._previous_posterior is not None),
            "config_json": np.array(json.dumps(asdict(self.config), sort_keys=True)),
            "place_sessions": self._place_sessions.view().copy(),
            **self._sessions.to_arrays(),
        }
        write_map(path, arrays)

    def load_map(self, path: Path, new_session: bool = True) -> ConfigDifferences:
        """Replace the map by the one saved at ``path``; returns the settings it was made with that
        differ from this recognizer's (:func:`config_differences`), for the caller to report.

        With ``new_session`` (a node starting on a saved map), later frames belong to a new session of
        this recognizer's robot; without it they continue the map's last session (its belief and
        consistency chain as saved).

        Raises VocabularyMismatchError (naming both ids) if it belongs to another vocabulary,
        ModelError if it is missing, corrupt or of another format version. Other settings do not
        refuse a map: places are stored as word sets, which only the vocabulary gives a meaning to;
        the settings change how later frames are matched and added, not what the places are.
        """
        state = read_map(Path(path), self.vocabulary_id, self.vocabulary_size)
        self._reset()
        self._engine.places.add_many(state["word_indptr"], state["word_indices"])
        self._place_stamps_ns.extend(state["place_stamps_ns"].astype(np.int64))
        self._place_frames.extend(state["place_frames"].astype(np.int64))
        self._place_sessions.extend(state["place_sessions"].astype(np.int32))
        self._next_query_id = int(state["next_query_id"])
        self._sessions = SessionTable.from_arrays(state["session_robots"], state["session_first_queries"])
        if new_session:
            self.start_session()
        else:
            self.robot = self._sessions.current.robot
            self._previous_posterior = (state["previous_posterior"] if bool(state["has_previous_posterior"])
                                        else None)
            sessions = self._place_sessions.view()
            self._session_has_place = bool(sessions.size and sessions[-1] == self._sessions.current.number)
        if "config_json" not in state:  # written by a version that did not record its settings
            return {"config_json": (None, "not recorded in the map")}
        return config_differences(str(state["config_json"]), self.config)
