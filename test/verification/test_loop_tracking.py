"""Loop tracking's window: after a verified closure, candidates near its place in map time, for a while."""

import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.verification.loop_tracking import LoopTrack

SECOND = 10**9


def _stamp(place: tuple[str, int]) -> int:
    return place[1]


PLACES = [("far before", 10 * SECOND), ("just before", 48 * SECOND), ("tracked", 50 * SECOND),
          ("just after", 53 * SECOND), ("far after", 54 * SECOND)]


def test_no_track_before_a_verified_closure():
    track = LoopTrack(track_seconds=1.0, island_seconds=3.0)
    assert not track.is_active(100 * SECOND)
    assert track.near(100 * SECOND, PLACES, _stamp) == []


def test_candidates_within_the_island_of_the_tracked_place_keep_their_order():
    track = LoopTrack(track_seconds=1.0, island_seconds=3.0)
    track.accept(100 * SECOND, 50 * SECOND)
    near = track.near(100 * SECOND + SECOND // 2, PLACES[::-1], _stamp)
    assert [name for name, _ in near] == ["just after", "tracked", "just before"]


def test_the_track_ends_track_seconds_after_the_last_verified_closure():
    track = LoopTrack(track_seconds=1.0, island_seconds=3.0)
    track.accept(100 * SECOND, 50 * SECOND)
    assert not track.is_active(100 * SECOND)  # the closure's own frame is not tracked again
    assert track.is_active(101 * SECOND)
    assert not track.is_active(101 * SECOND + 1)
    assert track.near(102 * SECOND, PLACES, _stamp) == []
    # A tracked closure extends it and moves the island with the robot.
    track.accept(101 * SECOND, 53 * SECOND)
    assert [name for name, _ in track.near(102 * SECOND, PLACES, _stamp)] == ["tracked", "just after", "far after"]


def test_an_older_closure_does_not_move_the_track_back():
    track = LoopTrack(track_seconds=1.0, island_seconds=3.0)
    track.accept(100 * SECOND, 50 * SECOND)
    track.accept(99 * SECOND, 10 * SECOND)  # verified late (its features came after)
    assert [name for name, _ in track.near(100 * SECOND + 1, PLACES, _stamp)] == ["just before", "tracked",
                                                                                   "just after"]


def test_off_and_reset():
    off = LoopTrack(track_seconds=0.0, island_seconds=3.0)
    off.accept(100 * SECOND, 50 * SECOND)
    assert not off.enabled and not off.is_active(100 * SECOND + 1)
    track = LoopTrack(track_seconds=1.0, island_seconds=3.0)
    track.accept(100 * SECOND, 50 * SECOND)
    track.reset()
    assert not track.is_active(100 * SECOND + 1)


@pytest.mark.parametrize(("track_seconds", "island_seconds"), [(-1.0, 3.0), (1.0, -0.5), (float("nan"), 3.0)])
def test_bad_windows(track_seconds, island_seconds):
    with pytest.raises(ConfigError, match="must be >= 0"):
        LoopTrack(track_seconds, island_seconds)
