"""What a place recognizer keeps per robot: the session it is in, its belief, its consistency chain, the
places its session made and how many frames it has seen.

Several robots share one map of places, but each has its own view of time: the motion model predicts
where *this* robot is from where it was a frame ago, a loop closure is consistent when *this* robot's
recent frames agree, a keyframe is decided against *this* robot's last place, and the places too recent to
be revisits are *this* session's. Another robot's places, and an earlier session's, are ordinary hypotheses.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.consistency import TemporalConsistency
from aefabmap_ros.fabmap.place_table import PlaceTable
from aefabmap_ros.fabmap.posterior import motion_log_prior, posterior
from aefabmap_ros.fabmap.recognition import jaccard
from aefabmap_ros.fabmap.sessions import Session

PlaceWords = Callable[[int], np.ndarray]  # place id -> its sorted unique word ids


class RobotTrack:
    """One robot's session on the map and the state its frames carry from one to the next."""

    def __init__(self, session: Session, config: FabMapConfig) -> None:
        self.session = session
        self.previous_posterior: np.ndarray | None = None  # over [new, every place at that time]
        self.consistency = TemporalConsistency(
            config.consistency_matches, config.island_seconds, max_skipped=config.consistency_skips,
            window_seconds=config.consistency_window_seconds,
        )
        self.places: list[int] = []  # place ids this session made, oldest first
        self.frames_seen = 0  # frames of this session so far
        self.last_place_frame = -1  # frames_seen when the session's newest place was made

    @property
    def robot(self) -> str:
        return self.session.robot

    @property
    def last_place(self) -> int:
        """The session's newest place, -1 before its first."""
        return self.places[-1] if self.places else -1

    def observe_frame(self) -> None:
        """Count one frame of this robot (informative or not), after it was recognised."""
        self.frames_seen += 1

    def made_place(self, place_id: int) -> None:
        """This robot's current frame made ``place_id`` (call before ``observe_frame``)."""
        self.places.append(place_id)
        self.last_place_frame = self.frames_seen

    def frames_since_last_place(self) -> int:
        """Frames of this robot between its newest place's frame and the current one."""
        return self.frames_seen - self.last_place_frame

    def posterior(self, config: FabMapConfig, new_ll: float, place_ll: np.ndarray, included: np.ndarray) -> np.ndarray:
        """Posterior over [new place, included places] from this robot's motion prior; kept (over every place)
        for the robot's next frame."""
        num_places = place_ll.size
        hypotheses = np.concatenate([[new_ll], place_ll[included]])
        log_prior = None
        if config.motion_model:
            full_prior = motion_log_prior(self.previous_posterior, num_places, config.p_new, config.motion_bias)
            log_prior = full_prior[np.concatenate([[0], included + 1])]
        p = posterior(hypotheses / config.likelihood_temperature, log_prior, config.smoothing)
        previous = np.zeros(num_places + 1)
        previous[0] = p[0]
        previous[included + 1] = p[1:]
        self.previous_posterior = previous
        return p

    def linked_places(self, words: np.ndarray, place_words: PlaceWords, min_overlap: float) -> list[int]:
        """The session's newest run of places that each overlap the query by >= ``min_overlap``."""
        linked: list[int] = []
        for place in reversed(self.places):
            if jaccard(words, place_words(place)) < min_overlap:
                break
            linked.append(place)
        return linked

    def is_keyframe(self, config: FabMapConfig, words: np.ndarray, stamp_ns: int, place_words: PlaceWords,
                    last_place_stamp_ns: int) -> bool:
        """Whether the current frame makes a place: the session's first informative frame, else enough frames
        after its last place and either enough time or little enough overlap with it (the module doc of
        fabmap/recognizer.py)."""
        if not self.places:
            return True
        since = self.frames_since_last_place()
        if since < config.keyframe_min_frames:
            return False
        if config.keyframe_max_frames > 0 and since >= config.keyframe_max_frames:
            return True
        seconds = (stamp_ns - last_place_stamp_ns) / 1e9
        if config.keyframe_max_seconds > 0.0 and seconds >= config.keyframe_max_seconds:
            return True
        return jaccard(words, place_words(self.last_place)) <= config.keyframe_max_overlap

    @classmethod
    def continuing(cls, places: PlaceTable, config: FabMapConfig, next_query_id: int,
                   previous_posterior: np.ndarray | None) -> RobotTrack:
        """The track of a saved map's last session, as if the recognizer had never stopped: the session's
        frames are the query ids from its first to ``next_query_id`` (exact for a map of one robot)."""
        session = places.sessions.current
        track = cls(session, config)
        track.previous_posterior = previous_posterior
        own = np.flatnonzero(places.session_numbers == session.number)
        track.places = [int(place) for place in own]
        track.frames_seen = next_query_id - session.first_query_id
        if track.places:
            track.last_place_frame = int(places.frames[own[-1]]) - session.first_query_id
        return track
