"""Where loop tracking looks for a frame's place (verification/loop_tracking.py): the frame's own top
candidates near the tracked place, then the stored frames nearest that place in time.

With several robots (docs/fleet.md) a track follows one robot's frames along one place robot's stretch of
the map: only candidates and nearby frames of the tracked place's robot are near it (another robot's frames
of the same time are elsewhere), and only those the query may be checked against (``usable``).
"""

from __future__ import annotations

from collections.abc import Callable

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.closures import Posterior
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.loop_tracking import LoopTrack
from aefabmap_ros.verification.pair_check import PairCheck
from aefabmap_ros.verification.places import Match, PlaceFilter, PlaceSessions, PlaceToVerify, ranked_places
from aefabmap_ros.verification.reranking import rerank_by_inliers


class TrackingSearch:
    """The two searches of loop tracking over one frame store."""

    def __init__(self, store: FrameStore, pairs: PairCheck, place_sessions: PlaceSessions,
                 config: Callable[[], VerificationConfig]) -> None:
        self.store = store
        self.pairs = pairs
        self.place_sessions = place_sessions
        self.config = config  # the current settings (a runtime change replaces them)

    def candidates(self, track: LoopTrack, query_ns: int, query: Features, posterior: Posterior, tried: set[int],
                   usable: PlaceFilter) -> Match | None:
        """The query's top candidates near the tracked place, best verified wins (their stamps go to ``tried``)."""
        ranked = [(rank, place) for rank, place in ranked_places(self.store, posterior, usable)
                  if place.robot == track.place_robot]
        near = track.near(query_ns, ranked, lambda item: item[1].stamp_ns)[: self.config().candidates]
        tried.update(place.stamp_ns for _, place in near)
        outcome = rerank_by_inliers(near, lambda item: self.pairs.verify(query_ns, query, item[1].stamp_ns,
                                                                         item[1].features))
        if outcome is None:
            return None
        rank, place = near[outcome.winner]
        candidate = posterior.candidates[rank]
        return Match(place, candidate.probability, candidate.log_likelihood, outcome.verification)

    def nearby_frames(self, track: LoopTrack, query_ns: int, query: Features, posterior: Posterior,
                      tried: set[int], usable: PlaceFilter) -> Match | None:
        """The stored frames nearest the tracked place in time, not tried yet; best verified wins."""
        config = self.config()
        min_age_ns = round(config.track_min_age_seconds * 1e9)
        robot = track.place_robot
        places = []
        for stamp_ns in track.nearby_frames(query_ns, self.store.timeline, config.track_frames, min_age_ns,
                                            usable=lambda stamp: stamp in self.store and usable(stamp, robot)):
            features = self.store.get(stamp_ns)
            place_id = self.store.timeline.place_of(stamp_ns)
            if stamp_ns not in tried and features is not None and place_id is not None:
                session, place_robot = self.place_sessions.of(place_id)
                places.append(PlaceToVerify(place_id, stamp_ns, features, session, place_robot))
        tried.update(place.stamp_ns for place in places)
        outcome = rerank_by_inliers(places, lambda place: self.pairs.verify(query_ns, query, place.stamp_ns,
                                                                            place.features))
        if outcome is None:
            return None
        place = places[outcome.winner]
        # The place's posterior when it is among the query's top candidates; FAB-MAP did not rank it otherwise.
        ranked = [candidate for candidate in posterior.candidates if candidate.place_id == place.place_id]
        if ranked:
            return Match(place, ranked[0].probability, ranked[0].log_likelihood, outcome.verification, True)
        return Match(place, 0.0, float("nan"), outcome.verification, True)
