"""Loop-closure detection metrics (DESIGN section 6).

Protocol (the field's standard one, e.g. Cummins & Newman; Lowry et al.'s survey):

* ``scores[i, j]`` for ``j < i`` is how likely frame ``i`` revisits frame ``j`` (higher = more
  likely; log-likelihoods, probabilities and similarities all work, ``-inf`` is allowed);
  ``gt[i, j] = 1`` means frame ``i`` really revisits earlier frame ``j``. Entries with
  ``j > i - min_gap`` (the recent past, which always looks alike) are ignored in both.
* Every query ``i`` with at least one eligible candidate (``i >= min_gap``) proposes its single
  best candidate ``j* = argmax_j scores[i, j]``. Ties between candidates go to the **most
  recent** ``j`` (the largest index): deterministic, and it is the place a SLAM backend would
  most likely still hold in its window.
* At a threshold ``t`` the query's proposal is a positive prediction when its best score is
  ``>= t``; it is a true positive when ``gt[i, j*] = 1``.
  precision = TP / predictions; recall = TP / (queries that have any ground-truth loop among
  their eligible candidates).
* The threshold is swept over every distinct best score: predictions with equal scores enter
  the curve together, because no threshold can separate them. The curve therefore has one point
  per distinct score, ordered by decreasing threshold (increasing recall).
* average precision = sum_k (R_k - R_{k-1}) P_k (the step-wise area used by scikit-learn);
  max F1 over the curve; recall at 100 % precision = the largest recall of any curve point whose
  precision is exactly 1 (0 when the top-scoring proposal is already wrong).
* The paper's "accuracy" is the precision at the fixed threshold (``nan`` when nothing is
  predicted there: there is nothing to be accurate about), its "recall" the recall there.
* With no positive query, recall is 0 everywhere and so are AP, max F1 and recall@100P.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError


@dataclass(frozen=True)
class LoopMetrics:
    """Summary of one score matrix against a ground-truth loop matrix.

    The ``pr_*`` arrays hold one point per distinct best score, by decreasing threshold.
    """

    average_precision: float
    max_f1: float
    recall_at_100_precision: float
    precision_at_threshold: float  # the paper's "accuracy"; nan when no prediction at `threshold`
    recall_at_threshold: float
    threshold: float
    num_queries: int  # queries with at least one eligible candidate
    num_positive_queries: int  # queries with a ground-truth loop among their eligible candidates
    num_predictions_at_threshold: int
    pr_precision: np.ndarray  # (K,) float64
    pr_recall: np.ndarray  # (K,) float64
    pr_thresholds: np.ndarray  # (K,) float64, strictly decreasing


def _check_min_gap(min_gap: int) -> None:
    if isinstance(min_gap, bool) or not isinstance(min_gap, int | np.integer) or min_gap < 1:
        raise ConfigError(f"min_gap must be an integer >= 1 (a frame never revisits itself), got {min_gap!r}")


def _check_scores(scores: np.ndarray) -> np.ndarray:
    array = np.asarray(scores)
    if array.ndim != 2 or array.shape[0] != array.shape[1]:
        raise DataError(f"scores must be a square (N, N) matrix, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
        raise DataError(f"scores must be numeric, got dtype {array.dtype}")
    array = array.astype(np.float64)
    if np.isnan(array).any():
        rows, cols = np.nonzero(np.isnan(array))
        raise DataError(f"scores contain NaN (first at [{rows[0]}, {cols[0]}]); use -inf for 'impossible'")
    return array


def _check_gt(gt: np.ndarray, num_frames: int) -> np.ndarray:
    array = np.asarray(gt)
    if array.shape != (num_frames, num_frames):
        raise DataError(f"gt shape {array.shape} does not match scores shape ({num_frames}, {num_frames})")
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
        raise DataError(f"gt must be numeric or bool, got dtype {array.dtype}")
    bad = ~np.isin(array, (0, 1))
    if bad.any():
        rows, cols = np.nonzero(bad)
        raise DataError(f"gt must hold only 0 and 1, got {array[rows[0], cols[0]].item()!r} at [{rows[0]}, {cols[0]}]")
    return array.astype(bool)


def eligible_mask(num_frames: int, min_gap: int) -> np.ndarray:
    """(N, N) bool: ``[i, j]`` is True where ``j <= i - min_gap``."""
    _check_min_gap(min_gap)
    index = np.arange(num_frames)
    return index[None, :] <= index[:, None] - min_gap


def best_candidates(scores: np.ndarray, min_gap: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Best eligible earlier frame per query and its score.

    Returns ``best_j`` (N,) int64 (-1 where the query has no eligible candidate, i.e. ``i < min_gap``)
    and ``best_score`` (N,) float64 (-inf there). Ties go to the most recent candidate.
    """
    matrix = _check_scores(scores)
    num_frames = matrix.shape[0]
    eligible = eligible_mask(num_frames, min_gap)
    has_candidate = eligible.any(axis=1)
    masked = np.where(eligible, matrix, -np.inf)
    best_score = masked.max(axis=1, initial=-np.inf)
    # Among eligible entries equal to the row maximum, take the largest column (most recent frame).
    hits = eligible & (masked == best_score[:, None])
    best_j = num_frames - 1 - np.argmax(hits[:, ::-1], axis=1)
    best_j = np.where(has_candidate, best_j, -1).astype(np.int64)
    best_score = np.where(has_candidate, best_score, -np.inf)
    return best_j, best_score


def _pr_curve(
    best_score: np.ndarray, is_true: np.ndarray, num_positive: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision, recall, thresholds at every distinct score (decreasing), ties entering together."""
    order = np.argsort(-best_score, kind="stable")
    sorted_scores = best_score[order]
    cumulative_tp = np.cumsum(is_true[order])
    # Last index of each run of equal scores: the curve point where that whole group has entered.
    group_ends = np.nonzero(np.r_[sorted_scores[1:] != sorted_scores[:-1], True])[0]
    true_positives = cumulative_tp[group_ends].astype(np.float64)
    predictions = (group_ends + 1).astype(np.float64)
    precision = true_positives / predictions
    recall = true_positives / num_positive if num_positive > 0 else np.zeros_like(true_positives)
    return precision, recall, sorted_scores[group_ends]


def evaluate_scores(
    scores: np.ndarray, gt: np.ndarray, min_gap: int = 10, threshold: float = 0.99
) -> LoopMetrics:
    """Precision-recall analysis of a score matrix against a ground-truth loop matrix (see module doc)."""
    matrix = _check_scores(scores)
    truth = _check_gt(gt, matrix.shape[0])
    if isinstance(threshold, bool) or not isinstance(threshold, int | float | np.number) or np.isnan(threshold):
        raise ConfigError(f"threshold must be a number, got {threshold!r}")
    best_j, best_score = best_candidates(matrix, min_gap)
    queries = np.nonzero(best_j >= 0)[0]
    eligible = eligible_mask(matrix.shape[0], min_gap)
    num_positive = int((truth & eligible)[queries].any(axis=1).sum())
    query_scores = best_score[queries]
    is_true = truth[queries, best_j[queries]]

    if queries.size == 0:
        empty = np.zeros(0, dtype=np.float64)
        return LoopMetrics(0.0, 0.0, 0.0, float("nan"), 0.0, float(threshold), 0, 0, 0, empty, empty, empty)

    precision, recall, thresholds = _pr_curve(query_scores, is_true, num_positive)
    recall_steps = np.diff(np.r_[0.0, recall])
    average_precision = float(np.sum(recall_steps * precision))
    denominator = precision + recall
    f1 = np.divide(2 * precision * recall, denominator, out=np.zeros_like(denominator), where=denominator > 0)
    perfect = precision == 1.0
    recall_at_100 = float(recall[perfect].max()) if perfect.any() else 0.0

    predicted = query_scores >= threshold
    num_predicted = int(predicted.sum())
    true_at_threshold = int((predicted & is_true).sum())
    precision_at = true_at_threshold / num_predicted if num_predicted else float("nan")
    recall_at = true_at_threshold / num_positive if num_positive else 0.0
    return LoopMetrics(
        average_precision=average_precision,
        max_f1=float(f1.max()),
        recall_at_100_precision=recall_at_100,
        precision_at_threshold=float(precision_at),
        recall_at_threshold=float(recall_at),
        threshold=float(threshold),
        num_queries=int(queries.size),
        num_positive_queries=num_positive,
        num_predictions_at_threshold=num_predicted,
        pr_precision=precision,
        pr_recall=recall,
        pr_thresholds=thresholds,
    )


# ------------------------------------------------------------------------------ revisit events

# Revisiting frames at most this many non-revisiting frames apart belong to one revisit event.
DEFAULT_EVENT_GAP = 3


@dataclass(frozen=True)
class RevisitEvent:
    """A stretch of the sequence that revisits mapped ground: its first and last revisiting frame."""

    first_frame: int
    last_frame: int
    frames: tuple[int, ...]  # its revisiting frames (the bridged gap frames are not among them)


def revisit_events(gt: np.ndarray, min_gap: int = 10, max_gap: int = DEFAULT_EVENT_GAP) -> list[RevisitEvent]:
    """The revisit events of a ground-truth loop matrix.

    A frame ``i`` is *revisiting* when its row has a 1 among its eligible earlier frames
    (``gt[i, j] = 1`` for some ``j <= i - min_gap``). An event is a maximal run of revisiting
    frames in which consecutive ones are at most ``max_gap`` non-revisiting frames apart (0 =
    strictly consecutive): a blank frame or a pose just outside the labelling rule does not split
    one pass through a mapped place into two events.
    """
    if isinstance(max_gap, bool) or not isinstance(max_gap, int | np.integer) or max_gap < 0:
        raise ConfigError(f"max_gap must be an integer >= 0 (non-revisiting frames bridged in an event), "
                          f"got {max_gap!r}")
    array = np.asarray(gt)
    if array.ndim != 2:
        raise DataError(f"gt must be a square (N, N) matrix, got shape {array.shape}")
    truth = _check_gt(array, array.shape[0])
    revisiting = (truth & eligible_mask(truth.shape[0], min_gap)).any(axis=1)
    runs: list[list[int]] = []
    for frame in np.flatnonzero(revisiting).tolist():
        if runs and frame - runs[-1][-1] - 1 <= max_gap:
            runs[-1].append(frame)
        else:
            runs.append([frame])
    return [RevisitEvent(run[0], run[-1], tuple(run)) for run in runs]


@dataclass(frozen=True)
class EventScores:
    """Loop closures (a detector's own decisions) scored per closure, per revisit event and per frame."""

    num_closures: int
    num_false_closures: int  # closures (i, j) with gt[i, j] = 0
    num_events: int
    num_events_closed: int  # events with at least one true closure from one of their revisiting frames
    num_revisiting_frames: int
    num_revisiting_frames_closed: int  # revisiting frames with at least one true closure
    max_gap: int

    @property
    def fraction_closed(self) -> float:
        """Events closed / events (nan without events)."""
        return self.num_events_closed / self.num_events if self.num_events else float("nan")

    @property
    def frame_recall(self) -> float:
        """Revisiting frames with a true closure / revisiting frames (nan without revisiting frames)."""
        return (self.num_revisiting_frames_closed / self.num_revisiting_frames if self.num_revisiting_frames
                else float("nan"))


def event_scores(closures: Sequence[tuple[int, int]], gt: np.ndarray, min_gap: int = 10,
                 max_gap: int = DEFAULT_EVENT_GAP) -> EventScores:
    """Score loop closures ``(query frame i, matched frame j)`` against a ground-truth loop matrix.

    A closure is true when ``gt[i, j] = 1``, false otherwise. An event (:func:`revisit_events`)
    is closed when at least one true closure starts at one of its revisiting frames: what a SLAM
    backend needs, one correct constraint per revisit, rather than one per frame.
    """
    events = revisit_events(gt, min_gap, max_gap)
    truth = np.asarray(gt).astype(bool)
    num_frames = truth.shape[0]
    true_queries: set[int] = set()
    false = 0
    for query, matched in closures:
        if not (0 <= query < num_frames and 0 <= matched < num_frames):
            raise DataError(f"closure {query} -> {matched} is outside the {num_frames} frames of the ground truth")
        if truth[query, matched]:
            true_queries.add(int(query))
        else:
            false += 1
    revisiting = [frame for event in events for frame in event.frames]
    return EventScores(
        num_closures=len(closures),
        num_false_closures=false,
        num_events=len(events),
        num_events_closed=sum(1 for event in events if true_queries.intersection(event.frames)),
        num_revisiting_frames=len(revisiting),
        num_revisiting_frames_closed=len(true_queries.intersection(revisiting)),
        max_gap=int(max_gap),
    )


def missed_with_a_true_place_ranked(closures: Sequence[tuple[int, int]], ranked: Sequence[tuple[int, int]],
                                    gt: np.ndarray, min_gap: int = 10) -> int:
    """Revisiting frames (a ground-truth loop at least ``min_gap`` frames back) that no true closure
    ``(query, matched)`` came from, although a true place of theirs was ``ranked``: among the
    ``(query, frame)`` pairs of the places each frame's posterior reported.

    What limits recall: these frames were missed by the decision after the ranking (temporal
    consistency, geometric verification); the other missed frames were never ranked right, a matter
    of the vocabulary and FAB-MAP.
    """
    truth = np.asarray(gt).astype(bool)
    revisiting = (truth & eligible_mask(truth.shape[0], min_gap)).any(axis=1)
    closed = {int(query) for query, matched in closures if truth[query, matched]}
    ranked_true = {int(query) for query, frame in ranked if frame <= query - min_gap and truth[query, frame]}
    return sum(1 for query in ranked_true if revisiting[query] and query not in closed)
