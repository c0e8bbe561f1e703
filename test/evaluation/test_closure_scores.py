"""The closures of one recorded topic scored against hand-made ground truth: missed frames split by whether a
true place was ranked, and a recording with lost frames scored as its closures are in the full sequence."""

import numpy as np
import pytest

from aefabmap_ros.evaluation.closure_scores import (
    closure_scores_markdown,
    closure_scores_to_dict,
    score_recorded_closures,
)
from aefabmap_ros.evaluation.metrics import event_scores
from test.evaluation.test_recordings import closure, frames_of, posterior


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
    closures = [closure(20, 0, 0.99, inliers=30), closure(22, 9, 0.99, inliers=30)]  # 22 -> 9 is false
    # 3 revisiting frames missed (21, 22, 23), 1 of them with a true place ranked.
    row = score_recorded_closures("published", "loop_closures", closures, posteriors, gt, frames_of(30), 10)
    assert row.num_missed_ranked == 1
    assert row.events.num_revisiting_frames - row.events.num_revisiting_frames_closed == 3
    assert closure_scores_markdown([row]).splitlines()[-1].endswith("| 0.250 (1/4) | 1 / 3 |")
    assert closure_scores_to_dict(row)["missed_revisiting_frames_with_a_true_place_ranked"] == 1


# ------------------------------------------------------------------------------------------ frames lost


def _three_event_gt() -> np.ndarray:
    """40 frames, min gap 10. Event A: 12, 13, 14, 15, 17 (one frame missing: bridged); event B: 25..28
    (each revisits two frames 19-20 back); event C: 35 (revisits 20). 10 revisiting frames."""
    gt = np.zeros((40, 40), np.uint8)
    for query, place in ((12, 0), (13, 1), (14, 2), (15, 3), (17, 5), (35, 20)):
        gt[query, place] = 1
    for query in range(25, 29):
        gt[query, [query - 20, query - 19]] = 1
    return gt


# Frames that never reached fabmap_node (a live camera's losses, a detection-rate policy): no message of theirs.
LOST = (3, 9, 10, 14, 16, 22, 26, 33)
# (query frame, matched frame) of the closures, in the sequence's frames: 15 -> 4 and 35 -> 21 are false.
CLOSURE_FRAMES = ((12, 0), (13, 1), (15, 4), (17, 5), (25, 5), (27, 8), (35, 21))


def lossy_recording():
    """What fabmap_node publishes when the LOST frames never reach it: its query ids count the frames it got."""
    received = [frame for frame in range(40) if frame not in LOST]
    query_id = {frame: index for index, frame in enumerate(received)}
    posteriors = [posterior(frame, [], [], query_id=query_id[frame]) for frame in received]
    closures = [closure(q, m, query_id=query_id[q]) for q, m in CLOSURE_FRAMES]
    for message, (_, matched) in zip(closures, CLOSURE_FRAMES, strict=True):
        message.matched_place_id = query_id[matched]
    return posteriors, closures


def test_a_recording_with_lost_frames_scores_as_its_closures_do_in_the_full_sequence():
    gt = _three_event_gt()
    posteriors, closures = lossy_recording()
    row = score_recorded_closures("published", "loop_closures", closures, posteriors, gt, frames_of(40), 10)
    reference = event_scores(list(CLOSURE_FRAMES), gt, 10)  # the same closures, given as frame pairs
    assert row.events == reference
    assert (reference.num_closures, reference.num_false_closures) == (7, 2)
    assert row.precision == pytest.approx(5 / 7)
    assert [(r.query_frame, r.matched_frame) for r in row.rows] == list(CLOSURE_FRAMES)
    # Recall over the revisiting frames the detector processed: 14 and 26 were lost, so 10 - 2 = 8 of them;
    # closed by a true closure: 12, 13, 17, 25, 27.
    revisiting = np.flatnonzero((gt & np.tril(np.ones((40, 40), np.uint8), -10)).any(axis=1)).tolist()
    processed = [frame for frame in revisiting if frame not in LOST]
    assert (row.num_processed_revisiting, row.num_processed_revisiting_closed) == (len(processed), 5) == (8, 5)
    assert row.processed_recall == pytest.approx(5 / 8) and row.events.frame_recall == pytest.approx(5 / 10)
    assert closure_scores_to_dict(row)["recall_revisiting_frames_processed"] == pytest.approx(5 / 8)
    # The query ids, read as frames, would have put these closures on other rows (what this replaces):
    by_id = [(int(c.query_id), int(c.matched_place_id)) for c in closures]
    assert event_scores(by_id, gt, 10) != reference
