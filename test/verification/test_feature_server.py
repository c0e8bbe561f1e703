"""A robot's feature server without ROS: which requested frames it serves, when, and what it counts."""

from __future__ import annotations

import numpy as np

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.closures import CountedOutcomes
from aefabmap_ros.verification.feature_server import MAX_WAITING_REQUESTS, FeatureServer
from aefabmap_ros.verification.frame_store import FrameStore

SECOND = 1_000_000_000


def _features(count: int = 30, seed: int = 0) -> Features:
    rng = np.random.default_rng(seed)
    keypoints = np.column_stack([rng.uniform(0, 64, (count, 2)), np.ones((count, 2)), rng.uniform(0, 1, count)])
    return Features(keypoints.astype(np.float32), rng.integers(0, 256, (count, 128)).astype(np.float32), "sift")


def _server(depths: bool = False, max_bytes: int = 2**30, wait_s: float = 2.0) -> tuple[FeatureServer, CountedOutcomes]:
    outcomes = CountedOutcomes()
    return FeatureServer(FrameStore(1000, max_bytes, 20, keep_depths=depths), outcomes, wait_s), outcomes


def test_a_kept_frame_is_served_as_stored_and_a_forgotten_one_counted() -> None:
    server, outcomes = _server(max_bytes=3 * 20 * (8 + 256))  # three frames of 20 float16 descriptors
    for sec in range(1, 6):
        assert server.add_features(sec * SECOND, _features(seed=sec), (64, 64)) == []
    served = server.request([5 * SECOND, 5 * SECOND, 1 * SECOND])  # the same stamp twice is served once
    assert [frame.stamp_ns for frame in served] == [5 * SECOND]
    frame = served[0]
    assert frame.features.keypoints.shape == (20, 2) and frame.image_size == (64, 64) and frame.depths is None
    assert outcomes.counts == {"served": 1, "dropped_not_kept_any_more": 1}


def test_a_request_before_its_frame_waits_for_it_or_gives_up() -> None:
    server, outcomes = _server(wait_s=2.0)
    server.add_features(1 * SECOND, _features(), None)
    assert server.request([2 * SECOND, 3 * SECOND]) == []  # not here yet
    assert [f.stamp_ns for f in server.add_features(2 * SECOND, _features(), None)] == [2 * SECOND]
    server.add_features(6 * SECOND, _features(), None)  # 3 s never came, and 6 s is more than 2 s newer
    assert outcomes.counts == {"served": 1, "dropped_never_came": 1} and not server.waiting


def test_with_a_depth_camera_a_frame_is_served_with_its_depths() -> None:
    server, outcomes = _server(depths=True)
    server.add_depth(1 * SECOND, np.full((64, 64), 2.0, np.float32))  # the first depth image: depth exists
    server.add_features(2 * SECOND, _features(), (64, 64))
    assert server.request([2 * SECOND]) == []  # its depth image is still to come
    (frame,) = server.add_depth(2 * SECOND, np.full((64, 64), 3.0, np.float32))
    assert frame.depths is not None and np.allclose(frame.depths.keypoints[np.isfinite(frame.depths.keypoints)], 3.0)
    assert frame.depths.grid is not None
    server.add_features(3 * SECOND, _features(), (64, 64))
    server.add_depth(4 * SECOND, np.full((64, 64), 3.0, np.float32))  # a later depth image: 3 s's will not come
    (late,) = server.request([3 * SECOND])
    assert late.depths is None and outcomes.counts["served"] == 2


def test_the_waiting_requests_are_bounded() -> None:
    server, outcomes = _server()
    server.add_features(1 * SECOND, _features(), None)
    server.request([(2 + k) * SECOND for k in range(MAX_WAITING_REQUESTS + 5)])
    assert len(server.waiting) == MAX_WAITING_REQUESTS and outcomes.counts["dropped_never_came"] == 5
