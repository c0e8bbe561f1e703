"""How far behind the camera verifier_node is, by the wall-clock time each query's features were sent."""

import time

import pytest

pytest.importorskip("rclpy")

from aefabmap_ros.nodes.verifier_summary import FeatureClock, delay_summary

SECOND = 1_000_000_000


def test_a_query_is_behind_after_max_lag_and_the_verifier_too_late_while_its_input_waits_past_drop_after_lag(
) -> None:
    clock = FeatureClock(max_lag_s=0.25, drop_after_lag_s=1.0)
    now = time.time_ns()
    clock.sent(1, now - SECOND // 2)  # taken 0.5 s after it was sent
    assert clock.behind(1) and not clock.too_late(1)
    clock.sent(2, now - 2 * SECOND)  # taken 2 s after: the verifier is 2 s behind the camera
    assert clock.behind(2) and clock.too_late(2) and clock.too_late(1)
    clock.sent(3, time.time_ns())  # caught up: a query that waited (for its depth image, say) is verified
    assert clock.behind(2) and not clock.too_late(2) and not clock.too_late(3)
    assert not clock.behind(99)  # features never seen: nothing to measure by


def test_zero_means_never_as_a_lockstep_replay_wants() -> None:
    clock = FeatureClock(max_lag_s=0.0, drop_after_lag_s=0.0)
    clock.sent(1, time.time_ns() - 3600 * SECOND)
    assert not clock.behind(1) and not clock.too_late(1)


def test_published_delays_are_summarised_from_the_features_sending() -> None:
    clock = FeatureClock(max_lag_s=0.25)
    clock.sent(1, time.time_ns() - SECOND)
    clock.published(1)
    clock.published(42)  # a query whose sending was not seen has no delay
    (delay,) = clock.delays_s
    assert 1.0 <= delay < 2.0
    assert delay_summary([]) == "no closure published"
    assert delay_summary([0.1, 0.2, 0.3]).startswith("features -> published closure: median 0.200 s")
