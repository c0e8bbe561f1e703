"""TemporalConsistency on hand-made match sequences (matched place stamps in seconds)."""

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.fabmap.consistency import TemporalConsistency

S = 10**9


def _run(chain: TemporalConsistency, matches: list[float | None], frame_period: float = 1.0,
         start: float = 100.0) -> list[bool]:
    """Feed one match per frame (frames ``frame_period`` seconds apart from ``start``)."""
    return [chain.observe(round((start + i * frame_period) * S), None if m is None else int(m * S))
            for i, m in enumerate(matches)]


def test_needs_min_matches_consecutive_matches():
    assert _run(TemporalConsistency(3, 2.0), [10, 10.5, 11, 11.2]) == [False, False, True, True]


def test_a_frame_without_match_breaks_the_chain():
    assert _run(TemporalConsistency(2, 2.0), [10, None, 10.5, 11]) == [False, False, False, True]


def test_matches_must_stay_within_the_island():
    # 10 -> 13 jumps 3 s in map time: a look-alike elsewhere, not the same stretch of the map.
    assert _run(TemporalConsistency(2, 2.0), [10, 13, 13.5, 40, 40.2]) == [False, False, True, False, True]
    # The bound is inclusive and symmetric (a revisit driven backwards walks the map backwards).
    assert _run(TemporalConsistency(2, 2.0), [10, 12, 10]) == [False, True, True]


def test_one_match_is_enough_with_min_matches_1():
    assert _run(TemporalConsistency(1, 0.0), [None, 5, None, 7]) == [False, True, False, True]


def test_reset_forgets():
    chain = TemporalConsistency(2, 1.0)
    _run(chain, [1, 1])
    chain.reset()
    assert _run(chain, [1]) == [False]


def test_a_skip_lets_one_flickering_frame_pass():
    # 30 Hz video: the revisit's second frame matched nothing, the third matched the same stretch again.
    assert _run(TemporalConsistency(2, 2.0, max_skipped=1), [10, None, 10.5]) == [False, False, True]
    # A look-alike far away in between is passed over too, and is not consistent itself.
    assert _run(TemporalConsistency(2, 2.0, max_skipped=1), [10, 40, 10.5]) == [False, False, True]


def test_the_skips_bound_how_far_back_matches_count():
    assert _run(TemporalConsistency(2, 2.0, max_skipped=1), [10, None, None, 10.5]) == [False] * 4
    assert _run(TemporalConsistency(2, 2.0, max_skipped=2), [10, None, None, 10.5]) == [False, False, False, True]


def test_this_frame_must_match():
    assert _run(TemporalConsistency(2, 2.0, max_skipped=3), [10, 10.2, None]) == [False, True, False]


def test_matches_chain_within_the_island_one_to_the_next():
    # Walking back from 14: 12.5 is within 2 s of 14, 11 within 2 s of 12.5; 10 is not within 2 s of 14 directly.
    assert _run(TemporalConsistency(3, 2.0, max_skipped=1), [11, None, 12.5, 14]) == [False, False, False, True]


def test_the_window_reaches_back_over_a_flicker_of_many_frames():
    # 30 Hz: the revisit matched, then 10 frames matched look-alikes or nothing (1/3 s), then matched again.
    flicker: list[float | None] = [40.0, None] * 5
    matches = [10.0, *flicker, 10.4]
    assert _run(TemporalConsistency(2, 2.0, max_skipped=1, window_seconds=0.5), matches, 1 / 30)[-1]
    assert not _run(TemporalConsistency(2, 2.0, max_skipped=1, window_seconds=0.3), matches, 1 / 30)[-1]
    # The window is in the frames' own time: at 1 Hz the same frames are 11 s apart and do not chain.
    assert not _run(TemporalConsistency(2, 2.0, max_skipped=1, window_seconds=0.5), matches, 1.0)[-1]


def test_the_window_does_not_shrink_when_frames_are_dropped():
    # A busy pipeline took every 6th frame of a 30 Hz camera: two frames 0.2 s apart, one between.
    assert _run(TemporalConsistency(2, 2.0, window_seconds=0.5), [10.0, None, 10.2], 0.2) == [False, False, True]
    assert _run(TemporalConsistency(2, 2.0, window_seconds=0.1), [10.0, None, 10.2], 0.2) == [False] * 3


def test_the_frame_count_still_reaches_back_at_a_low_frame_rate():
    # 1 Hz, window 0.5 s: the one allowed skip is what lets the flickering frame pass.
    assert _run(TemporalConsistency(2, 2.0, max_skipped=1, window_seconds=0.5), [10.0, None, 10.5]) == [
        False, False, True]


def test_memory_stays_bounded_by_the_window_and_after_stamps_jump_back():
    chain = TemporalConsistency(2, 2.0, max_skipped=1, window_seconds=0.5)
    _run(chain, [10.0] * 3000, 1 / 30)
    assert len(chain) <= 0.5 * 30 + 2  # frames within 0.5 s, and the chain's own 3 at least
    # A bag replayed again into a live node: stamps jump back by 200 s. Frames far from the new stamps
    # in either direction are out of the window; only the last frames by count stay.
    _run(chain, [None], 1 / 30, start=0.0)
    assert len(chain) == 3


def _consecutive_reference(matches: list[float | None], k: int, island: float) -> list[bool]:
    """The rule without a window, brute force: the last k frames all matched, each within the island of the next."""
    out = []
    for end in range(len(matches)):
        last = matches[max(0, end - k + 1):end + 1]
        ok = len(last) == k and all(m is not None for m in last)
        out.append(ok and all(abs(b - a) <= island for a, b in itertools.pairwise(last)))  # type: ignore[operator]
    return out


@given(st.lists(st.one_of(st.none(), st.integers(0, 20).map(float)), max_size=30), st.integers(1, 4))
def test_without_skips_it_is_the_consecutive_rule(matches, k):
    assert _run(TemporalConsistency(k, 2.0), matches) == _consecutive_reference(matches, k, 2.0)


@pytest.mark.parametrize(("args", "options", "message"), [
    ((0, 1.0), {}, "min_matches = 0"), ((True, 1.0), {}, "min_matches = True"),
    ((2, -1.0), {}, "island_seconds = -1.0"), ((2, float("nan")), {}, "island_seconds = nan"),
    ((3, 1.0), {"max_skipped": -1}, "max_skipped = -1"), ((3, 1.0), {"window_seconds": -0.5}, "window_seconds = -0.5")])
def test_bad_config(args, options, message):
    with pytest.raises(ConfigError, match=message):
        TemporalConsistency(*args, **options)
