"""TemporalConsistency on hand-made match sequences (matched place stamps in seconds)."""

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.fabmap.consistency import TemporalConsistency

S = 10**9


def _run(chain: TemporalConsistency, matches: list[float | None]) -> list[bool]:
    return [chain.observe(None if m is None else int(m * S)) for m in matches]


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


@pytest.mark.parametrize(("args", "message"), [((0, 1.0), "min_matches = 0"), ((True, 1.0), "min_matches = True"),
                                              ((2, -1.0), "island_seconds = -1.0"),
                                              ((2, float("nan")), "island_seconds = nan"),
                                              ((3, 1.0, -1), "max_skipped = -1")])
def test_bad_config(args, message):
    with pytest.raises(ConfigError, match=message):
        TemporalConsistency(*args)
