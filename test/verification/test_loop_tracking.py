"""Loop tracking's window: after a verified closure, candidates near its place in map time, for a while."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aefabmap_ros.errors import ConfigError, ModelError
from aefabmap_ros.verification.loop_tracking import FrameTimeline, FrameTimelineFolder, LoopTrack, LoopTracks

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


def _timeline(stamps: list[int], max_frames: int = 1000) -> FrameTimeline:
    timeline = FrameTimeline(max_frames)
    for place, stamp in enumerate(stamps):
        assert timeline.add(stamp, place)
    return timeline


@settings(max_examples=200, deadline=None)
@given(stamps=st.lists(st.integers(0, 200), unique=True, max_size=40).map(sorted),
       max_frames=st.integers(1, 50), centre=st.integers(-10, 210), oldest=st.integers(-10, 210),
       width=st.integers(0, 120), count=st.integers(0, 12))
def test_nearest_frames_are_those_a_full_sort_by_distance_picks(stamps, max_frames, centre, oldest, width, count):
    timeline = _timeline(stamps, max_frames)
    kept = stamps[-max_frames:]
    newest = oldest + width
    # Reference: every kept frame in the window, sorted by (distance to the centre, stamp).
    expected = sorted((s for s in kept if oldest <= s <= newest), key=lambda s: (abs(s - centre), s))[:count]
    assert timeline.nearest(centre, oldest, newest, count) == expected
    assert len(timeline) == len(kept)
    assert [timeline.place_of(s) for s in kept] == [stamps.index(s) for s in kept]
    assert all(timeline.place_of(s) is None for s in stamps[: len(stamps) - len(kept)])


def test_a_stamp_already_there_or_older_than_every_frame_is_ignored_and_one_in_between_is_inserted():
    """Several robots' frames interleave (each robot's in order): a frame older than the newest takes its place."""
    timeline = _timeline([10, 20])
    assert not timeline.add(20, 7) and not timeline.add(5, 7)
    assert timeline.add(15, 7)
    assert timeline.frames() == [(10, 0), (15, 7), (20, 1)] and timeline.place_of(5) is None
    with pytest.raises(ConfigError, match="max_frames >= 1"):
        FrameTimeline(0)


def test_a_frame_inserted_before_the_last_save_is_saved_next():
    timeline = _timeline([10, 20])
    timeline.mark_saved()
    assert timeline.unsaved() == []
    timeline.add(15, 7)
    timeline.add(30, 8)
    assert timeline.unsaved() == [(15, 7), (30, 8)]
    timeline.mark_saved()
    assert timeline.unsaved() == []


def test_each_robot_has_its_own_loop_track():
    tracks = LoopTracks(track_seconds=1.0, island_seconds=3.0)
    tracks.of("robot1").accept(100 * SECOND, 50 * SECOND, "robot2")
    assert tracks.active("robot1", 100 * SECOND + 1) and tracks.of("robot1").place_robot == "robot2"
    assert not tracks.active("robot2", 100 * SECOND + 1) and not tracks.of("robot2").is_active(100 * SECOND + 1)
    assert tracks.enabled and not LoopTracks(0.0, 3.0).enabled


def test_nearby_frames_lie_in_the_island_and_never_in_the_recent_past():
    timeline = _timeline([s * SECOND // 2 for s in range(0, 220)])  # 2 Hz for 110 s
    track = LoopTrack(track_seconds=1.0, island_seconds=3.0)
    assert track.nearby_frames(100 * SECOND, timeline, 4, 5 * SECOND) == []  # no track yet
    track.accept(100 * SECOND, 50 * SECOND)
    nearby = track.nearby_frames(100 * SECOND + SECOND // 2, timeline, 4, 5 * SECOND)
    assert nearby == [50 * SECOND, 49 * SECOND + SECOND // 2, 50 * SECOND + SECOND // 2, 49 * SECOND]
    assert len(track.nearby_frames(101 * SECOND, timeline, 100, 5 * SECOND)) == 13  # 47 .. 53 s
    assert track.nearby_frames(101 * SECOND + 1, timeline, 4, 5 * SECOND) == []  # the track ended
    # A revisit of a place only 6 s old: the island reaches into the last 5 s, which stay out.
    track.accept(105 * SECOND, 99 * SECOND)
    nearby = track.nearby_frames(105 * SECOND + SECOND // 2, timeline, 100, 5 * SECOND)
    assert max(nearby) == 100 * SECOND + SECOND // 2 and min(nearby) == 96 * SECOND


def test_a_saved_timeline_reloads_the_frames_and_places_it_kept(tmp_path):
    folder = FrameTimelineFolder(tmp_path)
    timeline = FrameTimeline(max_frames=4)
    for stamp, place in ((10, 0), (20, 0), (30, 1)):
        timeline.add(stamp, place)
    folder.save(timeline)
    assert timeline.unsaved() == []  # a second save writes nothing new
    folder.save(timeline)
    assert len(list(tmp_path.glob("timeline-*.npz"))) == 1
    for stamp, place in ((40, 2), (50, 2), (60, 3)):  # 10 and 20 are forgotten (4 kept)
        timeline.add(stamp, place)
    assert timeline.unsaved() == [(40, 2), (50, 2), (60, 3)]
    folder.save(timeline)
    reloaded = FrameTimeline(max_frames=4)
    FrameTimelineFolder(tmp_path).load_into(reloaded)
    assert [(s, reloaded.place_of(s)) for s in (30, 40, 50, 60)] == [(30, 1), (40, 2), (50, 2), (60, 3)]
    assert len(reloaded) == 4 and reloaded.place_of(20) is None and reloaded.unsaved() == []
    assert reloaded.nearest(45, 0, 100, 2) == [40, 50]
    smaller = FrameTimeline(max_frames=2)  # a restart with a smaller store keeps the newest frames
    FrameTimelineFolder(tmp_path).load_into(smaller)
    assert [s for s in (30, 40, 50, 60) if s in smaller] == [50, 60]
    # Only new frames are written after a reload, and a chunk whose frames are all forgotten is deleted.
    reloaded.add(70, 4)
    reloaded.add(80, 4)
    folder = FrameTimelineFolder(tmp_path)
    folder.load_into(FrameTimeline(max_frames=4))  # learns the chunks on disk, as a node's start does
    folder.save(reloaded)
    chunks = sorted(tmp_path.glob("timeline-*.npz"))
    assert [c.name for c in chunks] == ["timeline-000000001.npz", "timeline-000000002.npz"]
    with np.load(chunks[-1]) as chunk:
        assert chunk["stamps_ns"].tolist() == [70, 80] and chunk["place_ids"].tolist() == [4, 4]


@pytest.mark.parametrize("arrays, message", [
    ({"stamps_ns": np.array([1, 2]), "place_ids": np.array([0])}, "do not agree"),
    ({"stamps_ns": np.array([1, 2]), "place_ids": np.array([0, -1])}, "do not agree"),
    ({"stamps_ns": np.array([1, 2])}, "not a frame timeline chunk"),
])
def test_a_bad_timeline_chunk_is_refused_by_name(tmp_path, arrays, message):
    chunk = tmp_path / "timeline-000000000.npz"
    np.savez(chunk, format_version=np.array(1), **arrays)
    timeline = FrameTimeline(max_frames=4)
    timeline.add(5, 0)
    with pytest.raises(ModelError, match=message) as error:
        FrameTimelineFolder(tmp_path).load_into(timeline)
    assert str(chunk) in str(error.value)
    assert timeline.place_of(5) == 0  # unchanged
    chunk.write_bytes(b"corrupt")
    with pytest.raises(ModelError, match="cannot read frame timeline chunk"):
        FrameTimelineFolder(tmp_path).load_into(timeline)
