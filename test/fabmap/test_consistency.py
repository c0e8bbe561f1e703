"""TemporalConsistency on hand-made match sequences (matched place stamps in seconds)."""

import pytest

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


@pytest.mark.parametrize(("args", "message"), [((0, 1.0), "min_matches = 0"), ((True, 1.0), "min_matches = True"),
                                              ((2, -1.0), "island_seconds = -1.0"),
                                              ((2, float("nan")), "island_seconds = nan")])
def test_bad_config(args, message):
    with pytest.raises(ConfigError, match=message):
        TemporalConsistency(*args)
