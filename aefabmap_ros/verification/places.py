"""The places the verification chain checks a query against, and what it knows of their sessions and robots."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.closures import Posterior
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.geometric import Verification


class PlaceToVerify(NamedTuple):
    place_id: int
    stamp_ns: int
    features: Features
    session: int = 0  # the map's session and robot of the place
    robot: str = ""


class Match(NamedTuple):
    """An accepted place before it becomes a closure."""

    place: PlaceToVerify
    probability: float
    log_likelihood: float
    verification: Verification
    nearby_frame: bool = False


# (stamp, robot) of a place -> may the query be checked against it (its frame is that robot's, the cameras agree)
PlaceFilter = Callable[[int, str], bool]


def _any_place(_stamp_ns: int, _robot: str) -> bool:
    return True


def ranked_places(store: FrameStore, posterior: Posterior,
                  usable: PlaceFilter = _any_place) -> list[tuple[int, PlaceToVerify]]:
    """The posterior's candidates (rank, place) whose features are stored (and ``usable``), best first."""
    places = []
    for rank, candidate in enumerate(posterior.candidates):
        features = store.get(candidate.stamp_ns)
        if features is not None and usable(candidate.stamp_ns, candidate.robot):
            places.append((rank, PlaceToVerify(candidate.place_id, candidate.stamp_ns, features,
                                               candidate.session, candidate.robot)))
    return places


class PlaceSessions:
    """Place id -> (session, robot) of the map: a frame loop tracking verifies names only its place. Learned
    from every posterior: the place its frame belongs to (``current_place_id``) is of the frame's own session,
    which fabmap_node guarantees (a session's frames join only its own places), and each candidate names its
    own. A place never seen so takes the session of the newest accepted closure's place, which the frames near
    it in time share."""

    def __init__(self) -> None:
        self._known: dict[int, tuple[int, str]] = {}
        self._newest: tuple[int, str] = (0, "")

    def learn(self, posterior: Posterior) -> None:
        self._known.update((candidate.place_id, (candidate.session, candidate.robot))
                           for candidate in posterior.candidates)
        if posterior.query_id >= 0 and posterior.current_place_id >= 0:
            self._known[posterior.current_place_id] = (posterior.session, posterior.robot)

    def accepted(self, session: int, robot: str) -> None:
        self._newest = (session, robot)

    def of(self, place_id: int) -> tuple[int, str]:
        return self._known.get(place_id, self._newest)
