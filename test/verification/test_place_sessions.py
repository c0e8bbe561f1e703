"""The session of a place the verifier only knows by id: a tracked nearby frame's place is of the session its
frames were recognised in, not of the newest accepted closure's place."""

from __future__ import annotations

from aefabmap_ros.verification.closures import Posterior, RankedPlace
from aefabmap_ros.verification.places import PlaceSessions


def test_a_frame_s_own_place_is_of_the_frame_s_session_and_candidates_name_theirs() -> None:
    sessions = PlaceSessions()
    # Session 1's frame 150 belongs to place 7, made by session 1; it ranks place 3 of session 0.
    sessions.learn(Posterior(150, 150, 7, 7, False, (RankedPlace(3, 40, 0.9, -1.0, 0, ""),), "", 1, ""))
    sessions.accepted(0, "")  # a closure into session 0 was just accepted
    assert sessions.of(7) == (1, "")
    assert sessions.of(3) == (0, "")
    assert sessions.of(99) == (0, "")  # never seen: the newest accepted closure's place session


def test_a_dropped_frame_s_posterior_teaches_nothing() -> None:
    sessions = PlaceSessions()
    sessions.learn(Posterior(150, -1, -1, 5, False, (), "", 4, "r9"))
    sessions.accepted(2, "r1")
    assert sessions.of(5) == (2, "r1")
