"""Which robot frames a base station asks for, without ROS."""

from __future__ import annotations

from aefabmap_ros.verification.closures import CountedOutcomes, Detection, Posterior
from aefabmap_ros.verification.frame_requests import FrameRequests


def _posterior(stamp: int, robot: str, current_place: int, candidate: bool = False, query_id: int = 0) -> Posterior:
    return Posterior(stamp, query_id, current_place, current_place, candidate, (), "", 0, robot)


def test_places_queries_and_tracked_frames_are_asked_for_once_each() -> None:
    outcomes = CountedOutcomes()
    requests = FrameRequests(["robot1", "robot2"], outcomes)
    stored: set[int] = {40}
    requests.after_posterior(_posterior(10, "robot1", 0), False, stored.__contains__)  # made place 0
    requests.after_posterior(_posterior(20, "robot1", 0), False, stored.__contains__)  # joined it: not needed
    requests.after_posterior(_posterior(30, "robot2", 1), False, stored.__contains__)  # made place 1
    requests.after_posterior(_posterior(31, "robot2", 1, candidate=True), False, stored.__contains__)
    requests.after_posterior(_posterior(32, "robot2", 1), True, stored.__contains__)  # robot2's loop is tracked
    requests.after_posterior(_posterior(33, "robot2", 1, query_id=-1), True, stored.__contains__)  # dropped frame
    requests.after_posterior(_posterior(40, "robot1", 2), False, stored.__contains__)  # a place, stored already
    assert requests.take() == {"robot1": [10], "robot2": [30, 31, 32]}
    requests.after_detection(Detection(31, 5, 1, 0, 10, 0.9, -1.0, "", 0, "robot2", 0, "robot1"), stored.__contains__)
    assert requests.take() == {}  # both asked for already
    requests.after_detection(Detection(50, 6, 1, 0, 5, 0.9, -1.0, "", 0, "robot2", 0, "robot3"), stored.__contains__)
    assert requests.take() == {"robot2": [50]}
    assert outcomes.counts == {"requested_place": 2, "requested_query": 2, "requested_tracking": 1,
                               "dropped_request_for_unknown_robot": 1}


def test_with_a_budget_places_always_go_and_queries_only_while_requests_are_left() -> None:
    outcomes = CountedOutcomes()
    requests = FrameRequests(["r"], outcomes, requests_per_frame=0.5)
    stored: set[int] = set()
    for stamp in range(1, 41):  # 40 candidate frames, the first a place: the saved-up 10, then one in two
        requests.after_posterior(_posterior(stamp, "r", 0, candidate=True), False, stored.__contains__)
    asked = requests.take()["r"]
    assert asked[0] == 1 and outcomes.counts["requested_place"] == 1
    assert len(asked) == 1 + outcomes.counts["requested_query"] and 25 <= len(asked) <= 30
    refused = next(stamp for stamp in range(1, 41) if stamp not in asked)
    detection = Detection(refused, 5, 0, 0, 1, 0.9, -1.0, "", 0, "r", 0, "r")
    assert not requests.after_detection(detection, stored.__contains__)  # its query will not come: counted once
    assert outcomes.counts["request_over_budget_query"] == 40 - len(asked)
