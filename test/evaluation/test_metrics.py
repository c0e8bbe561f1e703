"""Loop-closure metrics against hand-computed answers and scikit-learn as an independent reference."""

import math

import numpy as np
import pytest
from sklearn.metrics import average_precision_score

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.evaluation.metrics import (
    best_candidates,
    eligible_mask,
    evaluate_scores,
    event_scores,
    missed_with_a_true_place_ranked,
    revisit_events,
)

N = 30
LAG = 20  # frame i >= LAG revisits frame i - LAG


def _loop_gt() -> np.ndarray:
    gt = np.zeros((N, N), dtype=np.uint8)
    for i in range(LAG, N):
        gt[i, i - LAG] = 1
    return gt


def test_perfect_scores():
    gt = _loop_gt()
    metrics = evaluate_scores(gt.astype(float), gt, min_gap=10, threshold=0.99)
    assert metrics.num_queries == N - 10
    assert metrics.num_positive_queries == N - LAG
    assert metrics.average_precision == pytest.approx(1.0)
    assert metrics.max_f1 == pytest.approx(1.0)
    assert metrics.recall_at_100_precision == pytest.approx(1.0)
    assert metrics.precision_at_threshold == pytest.approx(1.0)
    assert metrics.recall_at_threshold == pytest.approx(1.0)
    assert metrics.num_predictions_at_threshold == N - LAG
    # Two distinct best scores: 1 (the 10 loops) and 0 (the 10 queries without a loop, all tied).
    np.testing.assert_allclose(metrics.pr_thresholds, [1.0, 0.0])
    np.testing.assert_allclose(metrics.pr_precision, [1.0, 0.5])
    np.testing.assert_allclose(metrics.pr_recall, [1.0, 1.0])


def test_all_zero_scores_tie_everywhere():
    gt = _loop_gt()
    metrics = evaluate_scores(np.zeros((N, N)), gt, min_gap=10)
    # Every query's candidates tie, so each picks the most recent one (i - 10), which is wrong.
    assert metrics.pr_thresholds.tolist() == [0.0]
    assert metrics.pr_precision.tolist() == [0.0]
    assert metrics.average_precision == 0.0
    assert metrics.max_f1 == 0.0
    assert metrics.recall_at_100_precision == 0.0
    assert metrics.num_predictions_at_threshold == 0
    assert math.isnan(metrics.precision_at_threshold)
    assert metrics.recall_at_threshold == 0.0


def test_single_wrong_top_prediction_gives_zero_recall_at_full_precision():
    gt = _loop_gt()
    scores = gt.astype(float)
    scores[15, 2] = 2.0  # frame 15 has no loop, yet gets the highest score of all
    metrics = evaluate_scores(scores, gt, min_gap=10, threshold=0.99)
    assert metrics.recall_at_100_precision == 0.0
    np.testing.assert_allclose(metrics.pr_precision[:2], [0.0, 10 / 11])
    np.testing.assert_allclose(metrics.pr_recall[:2], [0.0, 1.0])
    assert metrics.average_precision == pytest.approx(10 / 11)
    assert metrics.max_f1 == pytest.approx(2 * (10 / 11) / (10 / 11 + 1))
    assert metrics.precision_at_threshold == pytest.approx(10 / 11)
    assert metrics.recall_at_threshold == pytest.approx(1.0)


def test_tied_scores_enter_the_curve_together():
    gt = _loop_gt()
    scores = np.zeros((N, N))
    scores[20, 0] = 0.9  # true loop
    scores[21, 1] = 0.9  # true loop
    scores[12, 0] = 0.9  # false: frame 12 has no loop; tied with the two true ones
    scores[22, 2] = 0.5  # true loop, lower score
    metrics = evaluate_scores(scores, gt, min_gap=10, threshold=0.9)
    # No threshold separates the three 0.9s: the first point is 2 TP out of 3 predictions.
    assert metrics.pr_thresholds[:2].tolist() == [0.9, 0.5]
    np.testing.assert_allclose(metrics.pr_precision[:2], [2 / 3, 3 / 4])
    np.testing.assert_allclose(metrics.pr_recall[:2], [2 / 10, 3 / 10])
    assert metrics.recall_at_100_precision == 0.0
    assert metrics.precision_at_threshold == pytest.approx(2 / 3)
    assert metrics.recall_at_threshold == pytest.approx(0.2)


def test_no_positive_queries():
    scores = np.random.default_rng(0).random((N, N))
    metrics = evaluate_scores(scores, np.zeros((N, N), dtype=np.uint8), min_gap=5, threshold=0.5)
    assert metrics.num_positive_queries == 0
    assert metrics.num_queries == N - 5
    assert metrics.average_precision == 0.0
    assert metrics.max_f1 == 0.0
    assert metrics.recall_at_100_precision == 0.0
    assert np.all(metrics.pr_recall == 0.0)
    assert np.all(metrics.pr_precision == 0.0)
    assert metrics.precision_at_threshold == 0.0


def test_no_queries_at_all():
    metrics = evaluate_scores(np.ones((5, 5)), np.zeros((5, 5)), min_gap=10)
    assert metrics.num_queries == 0
    assert metrics.pr_precision.size == 0
    assert metrics.average_precision == 0.0


def test_loops_inside_the_gap_are_not_counted():
    gt = np.zeros((N, N), dtype=np.uint8)
    gt[25, 20] = 1  # only 5 frames back: ineligible with min_gap 10
    gt[26, 3] = 1
    metrics = evaluate_scores(gt.astype(float), gt, min_gap=10)
    assert metrics.num_positive_queries == 1
    assert metrics.recall_at_100_precision == 1.0


def _brute_force_best(scores: np.ndarray, min_gap: int) -> tuple[list[int], list[float]]:
    best_j, best_s = [], []
    for i in range(scores.shape[0]):
        if i < min_gap:
            best_j.append(-1)
            best_s.append(-math.inf)
            continue
        row = scores[i, : i - min_gap + 1]
        top = row.max()
        best_j.append(max(j for j in range(row.size) if row[j] == top))
        best_s.append(top)
    return best_j, best_s


def test_best_candidates_match_brute_force_with_ties_and_minus_inf():
    rng = np.random.default_rng(3)
    scores = rng.integers(0, 4, size=(40, 40)).astype(float)  # many ties
    scores[rng.random((40, 40)) < 0.2] = -np.inf
    scores[30, :21] = -np.inf  # a row whose every eligible candidate is -inf
    best_j, best_s = best_candidates(scores, min_gap=10)
    ref_j, ref_s = _brute_force_best(scores, 10)
    assert best_j.tolist() == ref_j
    assert best_s.tolist() == ref_s
    assert best_j[30] == 20  # most recent eligible among the tied -inf


def test_random_scores_match_sklearn_average_precision():
    rng = np.random.default_rng(7)
    n = 120
    gt = np.tril((rng.random((n, n)) < 0.03).astype(np.uint8), k=-1)
    scores = np.round(rng.random((n, n)) + 0.5 * gt, 1)  # rounding creates ties
    metrics = evaluate_scores(scores, gt, min_gap=10)
    best_j, best_s = _brute_force_best(scores, 10)
    queries = [i for i in range(n) if best_j[i] >= 0]
    y_true = np.array([gt[i, best_j[i]] for i in queries])
    y_score = np.array([best_s[i] for i in queries])
    positives = sum(bool(gt[i, : i - 10 + 1].any()) for i in queries)
    assert metrics.num_positive_queries == positives
    # sklearn's recall denominator is the true proposals; ours all positive queries: AP scales by their ratio.
    reference = average_precision_score(y_true, y_score) * y_true.sum() / positives
    assert metrics.average_precision == pytest.approx(reference)
    assert np.all(np.diff(metrics.pr_thresholds) < 0)
    assert np.all(np.diff(metrics.pr_recall) >= 0)


def test_eligible_mask():
    mask = eligible_mask(4, 2)
    assert mask.tolist() == [
        [False, False, False, False],
        [False, False, False, False],
        [True, False, False, False],
        [True, True, False, False],
    ]


@pytest.mark.parametrize(
    ("scores", "gt", "kwargs", "error", "match"),
    [
        (np.zeros((3, 4)), np.zeros((3, 4)), {}, DataError, r"square \(N, N\).*\(3, 4\)"),
        (np.zeros(5), np.zeros(5), {}, DataError, r"square.*\(5,\)"),
        (np.zeros((4, 4)), np.zeros((5, 5)), {}, DataError, r"gt shape \(5, 5\).*\(4, 4\)"),
        (np.full((4, 4), np.nan), np.zeros((4, 4)), {}, DataError, "NaN"),
        (np.zeros((4, 4)), np.full((4, 4), 2), {}, DataError, "only 0 and 1, got 2"),
        (np.array([["a"]]), np.zeros((1, 1)), {}, DataError, "numeric"),
        (np.zeros((4, 4)), np.zeros((4, 4)), {"min_gap": 0}, ConfigError, "min_gap.*got 0"),
        (np.zeros((4, 4)), np.zeros((4, 4)), {"threshold": float("nan")}, ConfigError, "threshold.*nan"),
    ],
)
def test_errors(scores, gt, kwargs, error, match):
    with pytest.raises(error, match=match):
        evaluate_scores(scores, gt, **kwargs)


def test_best_candidates_rejects_bad_gap():
    with pytest.raises(ConfigError, match=r"min_gap.*-1"):
        best_candidates(np.zeros((3, 3)), min_gap=-1)


# ------------------------------------------------------------------------------ revisit events


def _event_gt() -> np.ndarray:
    """30 frames, min gap 5. Revisiting: 10, 11, 12, 14 | 20, 21 | 27 (with gaps 1, 5, 5 between).
    Frames 8 and 25 have a 1 only among recent frames (not eligible): not revisiting."""
    gt = np.zeros((30, 30), np.uint8)
    for query, place in ((10, 2), (11, 3), (12, 4), (14, 6), (20, 1), (21, 2), (27, 8), (8, 5), (25, 24)):
        gt[query, place] = 1
    return gt


def test_revisit_events_by_hand() -> None:
    gt = _event_gt()
    events = revisit_events(gt, min_gap=5, max_gap=3)
    assert [(e.first_frame, e.last_frame, e.frames) for e in events] == [
        (10, 14, (10, 11, 12, 14)), (20, 21, (20, 21)), (27, 27, (27,))]
    strict = revisit_events(gt, min_gap=5, max_gap=0)
    assert [(e.first_frame, e.last_frame) for e in strict] == [(10, 12), (14, 14), (20, 21), (27, 27)]
    assert [(e.first_frame, e.last_frame) for e in revisit_events(gt, min_gap=5, max_gap=5)] == [(10, 27)]
    # With min gap 3, frame 8's revisit of 5 becomes eligible: an event of its own (1 frame before 10).
    assert [(e.first_frame, e.last_frame) for e in revisit_events(gt, min_gap=3, max_gap=0)][:2] == [(8, 8), (10, 12)]
    assert revisit_events(np.zeros((4, 4), np.uint8), min_gap=1) == []


def test_event_scores_by_hand() -> None:
    gt = _event_gt()
    closures = [
        (11, 3),  # true: closes event 10-14 (frame 11)
        (12, 0),  # false
        (14, 6),  # true: same event, frame 14
        (20, 9),  # false: event 20-21 stays open
        (8, 5),  # true by gt (a recent frame), not false; frame 8 is no revisiting frame
        (25, 0),  # false
        (11, 3),  # the same true closure again: frame 11 counts once
    ]
    scores = event_scores(closures, gt, min_gap=5, max_gap=3)
    assert (scores.num_closures, scores.num_false_closures) == (7, 3)
    assert (scores.num_events, scores.num_events_closed) == (3, 1)
    assert scores.fraction_closed == pytest.approx(1 / 3)
    assert (scores.num_revisiting_frames, scores.num_revisiting_frames_closed) == (7, 2)
    assert scores.frame_recall == pytest.approx(2 / 7)
    strict = event_scores(closures, gt, min_gap=5, max_gap=0)  # 10-12 and 14 are two events, both closed
    assert (strict.num_events, strict.num_events_closed, strict.max_gap) == (4, 2, 0)
    assert event_scores(closures, gt, min_gap=5, max_gap=5).fraction_closed == 1.0
    nothing = event_scores([], gt, min_gap=5)
    assert (nothing.num_closures, nothing.num_events_closed, nothing.frame_recall) == (0, 0, 0.0)
    no_events = event_scores([(3, 0)], np.zeros((4, 4), np.uint8), min_gap=1)
    assert no_events.num_false_closures == 1 and math.isnan(no_events.fraction_closed)
    assert math.isnan(no_events.frame_recall)


def test_event_scores_errors() -> None:
    gt = _event_gt()
    with pytest.raises(DataError, match="closure 30 -> 2 is outside the 30 frames"):
        event_scores([(30, 2)], gt, min_gap=5)
    with pytest.raises(ConfigError, match="max_gap must be an integer >= 0"):
        revisit_events(gt, min_gap=5, max_gap=-1)
    with pytest.raises(ConfigError, match="min_gap"):
        revisit_events(gt, min_gap=0)
    with pytest.raises(DataError, match="only 0 and 1"):
        revisit_events(gt * 2, min_gap=5)


def test_missed_frames_with_a_true_place_ranked_by_hand() -> None:
    # Frames 20-23 revisit frames 0-3; frame 24 revisits 20, within the min gap: not a revisiting frame.
    gt = np.zeros((30, 30), np.uint8)
    for query in range(20, 24):
        gt[query, query - 20] = 1
    gt[24, 20] = 1
    ranked = [(20, 0), (20, 7),   # true place ranked, and closed below
              (21, 9), (21, 1),   # true place ranked second, never closed: the decision missed it
              (22, 9),            # only a wrong place ranked: the ranking missed it
              (24, 20)]           # (23 ranked nothing: the ranking missed it; 24 is no revisiting frame)
    closures = [(20, 0), (22, 9)]  # 22 -> 9 is false: it does not close 22
    assert missed_with_a_true_place_ranked(closures, ranked, gt, 10) == 1
    assert missed_with_a_true_place_ranked([(q, q - 20) for q in range(20, 24)], ranked, gt, 10) == 0
    assert missed_with_a_true_place_ranked([], ranked, gt, 10) == 2  # 20 and 21
    assert missed_with_a_true_place_ranked([], [(21, 1)], gt, 25) == 0  # 1 is not 25 frames before 21
