"""A recorded run scored offline: the score matrix rebuilt from posteriors, closures scored per closure."""

from types import SimpleNamespace

import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.recordings import (
    RecordedClosure,
    closure_precision_recall,
    closure_scores_markdown,
    closure_scores_to_dict,
    score_recorded_closures,
    scores_from_recording,
)


def stamp(ns):
    return SimpleNamespace(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def posterior(query, places, probabilities, stamps_ns=None):
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp(1000 + query)), query_id=query, place_ids=np.array(places),
        probabilities=np.array(probabilities, dtype=float),
        place_stamps=[stamp(s) for s in (stamps_ns if stamps_ns is not None else [1000 + p for p in places])],
    )


def closure(query, place, probability, place_stamp_ns):
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp(1000 + query)), query_id=query,
                           matched_place_id=place, matched_stamp=stamp(place_stamp_ns), probability=probability)


def test_scores_from_recording_maps_places_by_stamp_then_id():
    posteriors = [posterior(0, [], []), posterior(1, [0], [0.2]), posterior(2, [1, 0], [0.7, 0.1]),
                  # place id 5 with the stamp of frame 1 (keyframing renumbered places): frame 1
                  posterior(3, [5, 0], [0.6, 0.3], stamps_ns=[1001, 9999])]
    closures = [closure(3, 5, 0.995, 1001)]
    recorded = scores_from_recording(posteriors, closures, 5)
    expected = np.zeros((5, 5))
    expected[1, 0], expected[2, 1], expected[2, 0] = 0.2, 0.7, 0.1
    expected[3, 1], expected[3, 0] = 0.995, 0.3  # the loop closure's probability is the larger
    np.testing.assert_allclose(recorded.scores, expected)
    assert recorded.closures == [RecordedClosure(3, 1, 0.995)]
    assert (recorded.num_posteriors, recorded.num_loop_closures) == (4, 1)
    assert recorded.stamp_aligned_candidates == 5  # all but the unknown stamp 9999 (place id 0 = frame 0)


@pytest.mark.parametrize(("posteriors", "message"), [
    ([posterior(7, [0], [0.5])], "query id 7 outside the 5 frames"),
    ([posterior(2, [2], [0.5])], "query 2 maps to frame 2, which is not an earlier frame"),
    ([posterior(2, [0, 1], [0.5])], "2 place ids but 1 probabilities"),
])
def test_scores_from_recording_errors(posteriors, message):
    with pytest.raises(DataError, match=message):
        scores_from_recording(posteriors, [], 5)


def test_closure_precision_recall():
    gt = np.zeros((30, 30), np.uint8)
    gt[20, 2] = gt[21, 3] = gt[22, 4] = gt[23, 20] = 1  # the last is within min gap: not a positive query
    closures = [RecordedClosure(20, 2, 1.0), RecordedClosure(21, 9, 1.0)]
    precision, recall = closure_precision_recall(closures, gt, 10)
    assert precision == 0.5 and recall == pytest.approx(1 / 3)
    precision, recall = closure_precision_recall([], gt, 10)
    assert np.isnan(precision) and recall == 0.0


def test_a_topic_s_missed_frames_are_split_by_whether_their_posterior_ranked_a_true_place():
    # Frames 20-23 revisit frames 0-3 (gt by hand); 24 revisits too but only within the min gap.
    gt = np.zeros((30, 30), np.uint8)
    for query in range(20, 24):
        gt[query, query - 20] = 1
    gt[24, 20] = 1
    posteriors = [posterior(20, [0, 7], [0.6, 0.1]),  # true place ranked, and closed below
                  posterior(21, [9, 1], [0.5, 0.2]),  # true place ranked second, never closed: a decision miss
                  posterior(22, [9], [0.9]),          # only a wrong place ranked: a ranking miss
                  posterior(23, [], []),              # nothing ranked: a ranking miss
                  posterior(24, [20], [0.9])]         # not a revisiting frame (gap), ignored
    closures = [closure(20, 0, 0.99, 1000), closure(22, 9, 0.99, 1009)]  # 22 -> 9 is false
    # 3 revisiting frames missed (21, 22, 23), 1 of them with a true place ranked.
    row = score_recorded_closures("published", "loop_closures",
                                  [SimpleNamespace(inliers=30, **vars(c)) for c in closures], posteriors, gt, 10)
    assert row.num_missed_ranked == 1
    assert row.events.num_revisiting_frames - row.events.num_revisiting_frames_closed == 3
    assert closure_scores_markdown([row]).splitlines()[-1].endswith("| 1 / 3 |")
    assert closure_scores_to_dict(row)["missed_revisiting_frames_with_a_true_place_ranked"] == 1
