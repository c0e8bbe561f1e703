"""When a query stops waiting for its depth image: the three ways it ends, by stamps alone."""

from __future__ import annotations

import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.verification.depth_wait import DepthWait

SECOND = 1_000_000_000


def test_a_query_waits_only_while_its_depth_image_can_still_come() -> None:
    wait = DepthWait(2.0)
    assert wait.ready(5 * SECOND, has_depth=False)  # no depth stream yet: nothing to wait for
    wait.depth_came(4 * SECOND)
    wait.frame_came(5 * SECOND)
    assert not wait.ready(5 * SECOND, has_depth=False) and list(wait.waiting) == [5 * SECOND]
    assert wait.ready(5 * SECOND, has_depth=True) and not wait.waiting  # it came
    assert not wait.ready(6 * SECOND, has_depth=False)
    wait.depth_came(6 * SECOND + 1)  # a later one came first: the query's was lost
    assert wait.ready(6 * SECOND, has_depth=False)
    assert not wait.ready(7 * SECOND, has_depth=False)
    wait.frame_came(9 * SECOND)  # exactly depth_wait_s newer: still waiting
    assert not wait.ready(7 * SECOND, has_depth=False)
    wait.frame_came(9 * SECOND + 1)
    assert wait.ready(7 * SECOND, has_depth=False) and not wait.waiting
    assert len(wait.waits_s) == 3 and all(held >= 0 for held in wait.waits_s)  # 5 s, 6 s and 7 s waited
    assert wait.summary().startswith("3 queries waited for their depth image: median")
    assert DepthWait(1.0).summary() == "no query waited for its depth image"


def test_stamps_older_than_the_newest_do_not_move_it_back() -> None:
    wait = DepthWait(1.0)
    wait.depth_came(10 * SECOND)
    wait.depth_came(3 * SECOND)
    wait.frame_came(10 * SECOND)
    wait.frame_came(3 * SECOND)
    assert wait.newest_depth_ns == 10 * SECOND and wait.newest_frame_ns == 10 * SECOND
    assert wait.ready(9 * SECOND, has_depth=False)


def test_a_query_the_chain_dropped_waits_no_longer_and_a_negative_wait_is_refused() -> None:
    wait = DepthWait(1.0)
    wait.depth_came(0)
    assert not wait.ready(SECOND, has_depth=False) and not wait.ready(2 * SECOND, has_depth=False)
    assert wait.waiting_among(lambda stamp: stamp == 2 * SECOND) == [2 * SECOND]
    assert list(wait.waiting) == [2 * SECOND]
    with pytest.raises(ConfigError, match="depth_wait_s"):
        DepthWait(-0.5)
