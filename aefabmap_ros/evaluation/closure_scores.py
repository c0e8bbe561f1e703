"""The loop closures recorded on one topic scored against the ground truth (``aefabmap_eval --recording``):
precision, revisit events, recall over the revisiting frames the detector processed, wrong relative poses;
their markdown table and JSON."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aefabmap_ros.evaluation.closure_listing import WRONG_POSE_DEG, WRONG_POSE_M, ClosureRow, PoseTruth, closure_rows
from aefabmap_ros.evaluation.metrics import (
    DEFAULT_EVENT_GAP,
    EventScores,
    eligible_mask,
    event_scores,
    missed_with_a_true_place_ranked,
)
from aefabmap_ros.evaluation.recordings import FrameIndex, closure_precision_recall, scores_from_recording
from aefabmap_ros.evaluation.reports import (
    MISSED_RANKED_KEY,
    events_to_dict,
    fmt,
    jsonable_float,
    missed_ranked_cell,
    recall_cell,
)


@dataclass(frozen=True)
class TopicClosureScores:
    """The loop closures recorded on one topic, scored against the ground truth."""

    role: str  # what the topic carries: "FAB-MAP candidates", "published"
    topic: str
    num_verified: int  # closures with inliers > 0 (passed geometric verification)
    precision: float  # true closures / closures (nan without closures)
    events: EventScores
    # Revisiting frames without a true closure whose recorded posterior ranked a true place: the decision
    # (consistency, verification) missed them; the other missed frames the ranking (vocabulary, FAB-MAP) did.
    num_missed_ranked: int
    # Revisiting frames the detector processed (a place_posteriors message), and those of them with a true
    # closure; None when the recording has no place_posteriors.
    num_processed_revisiting: int | None
    num_processed_revisiting_closed: int | None
    rows: tuple[ClosureRow, ...]
    pose_truth_given: bool = False

    @property
    def processed_recall(self) -> float:
        if not self.num_processed_revisiting or self.num_processed_revisiting_closed is None:
            return float("nan")
        return self.num_processed_revisiting_closed / self.num_processed_revisiting

    @property
    def num_poses_checked(self) -> int:
        return sum(1 for row in self.rows if row.error is not None)

    @property
    def num_wrong_poses(self) -> int:
        return sum(1 for row in self.rows if row.pose_wrong)

    @property
    def num_covariance_checked(self) -> int:
        """Metric poses whose error was measured under their own covariance."""
        return sum(1 for row in self.rows if row.pose_outside_covariance is not None)

    @property
    def num_outside_covariance(self) -> int:
        return sum(1 for row in self.rows if row.pose_outside_covariance)


def score_recorded_closures(role: str, topic: str, loop_closures: Sequence[Any], posteriors: Sequence[Any],
                            gt: np.ndarray, frames: FrameIndex, min_gap: int, event_gap: int = DEFAULT_EVENT_GAP,
                            pose_truth: PoseTruth | None = None) -> TopicClosureScores:
    """Score the ``LoopClosure`` messages of one recorded topic (frames as in :func:`scores_from_recording`):
    precision, per revisit event and revisiting frame (:func:`evaluation.metrics.event_scores`), recall over the
    revisiting frames the detector processed, and (``pose_truth``) the closures' relative poses."""
    recorded = scores_from_recording(posteriors, loop_closures, frames)
    closures = recorded.closures
    precision, _ = closure_precision_recall(closures, gt, min_gap)
    pairs = [(c.query_frame, c.matched_frame) for c in closures]
    events = event_scores(pairs, gt, min_gap, event_gap)
    verified = sum(1 for message in loop_closures if int(message.inliers) > 0)
    queries, places = np.nonzero(recorded.scores > 0)  # sparse: a posterior reports a few places
    ranked = list(zip(queries.tolist(), places.tolist(), strict=True))
    truth = np.asarray(gt).astype(bool)
    revisiting = (truth & eligible_mask(truth.shape[0], min_gap)).any(axis=1)
    processed_revisiting: int | None = None
    processed_closed: int | None = None
    if recorded.num_posteriors:
        closed = np.zeros_like(revisiting)
        closed[[c.query_frame for c in closures if truth[c.query_frame, c.matched_frame]]] = True
        processed_revisiting = int((revisiting & recorded.processed).sum())
        processed_closed = int((revisiting & recorded.processed & closed).sum())
    return TopicClosureScores(role, topic, verified, precision, events,
                              missed_with_a_true_place_ranked(pairs, ranked, gt, min_gap),
                              processed_revisiting, processed_closed,
                              tuple(closure_rows(topic, loop_closures, closures, gt, pose_truth)),
                              pose_truth is not None)


def _processed_recall_cell(row: TopicClosureScores) -> str:
    if row.num_processed_revisiting is None:
        return "n/a"
    return f"{fmt(row.processed_recall)} ({row.num_processed_revisiting_closed}/{row.num_processed_revisiting})"


def closure_scores_markdown(rows: Sequence[TopicClosureScores]) -> str:
    """A markdown table: one row per recorded closure topic (a wrong-pose column when a pose truth was given)."""
    poses = any(row.pose_truth_given for row in rows)
    lines = [
        "| closures | topic | closures | verified (inliers > 0) | false | precision | revisit events "
        "| events closed | fraction of events closed | recall (revisiting frames) "
        "| recall (revisiting frames processed) | missed frames with a true place ranked |"
        + (f" wrong poses (> {WRONG_POSE_DEG:g} deg or > {WRONG_POSE_M:g} m) / checked "
           "| metric poses outside their covariance's 99.9 % region / checked |" if poses else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|---|" + ("---|---|" if poses else ""),
    ]
    for row in rows:
        e = row.events
        lines.append(
            f"| {row.role} | `{row.topic}` | {e.num_closures} | {row.num_verified} | {e.num_false_closures} "
            f"| {fmt(row.precision)} | {e.num_events} | {e.num_events_closed} | {fmt(e.fraction_closed)} "
            f"| {recall_cell(e)} | {_processed_recall_cell(row)} | {missed_ranked_cell(row.num_missed_ranked, e)} |"
            + (f" {row.num_wrong_poses} / {row.num_poses_checked} "
               f"| {row.num_outside_covariance} / {row.num_covariance_checked} |" if poses else "")
        )
    return "\n".join(lines) + "\n"


def closure_scores_to_dict(row: TopicClosureScores) -> dict[str, Any]:
    return {"role": row.role, "topic": row.topic, "verified": row.num_verified,
            "precision": jsonable_float(row.precision), **events_to_dict(row.events),
            "revisiting_frames_processed": row.num_processed_revisiting,
            "revisiting_frames_processed_closed": row.num_processed_revisiting_closed,
            "recall_revisiting_frames_processed": jsonable_float(row.processed_recall),
            MISSED_RANKED_KEY: row.num_missed_ranked,
            "wrong_poses": row.num_wrong_poses if row.pose_truth_given else None,
            "poses_checked": row.num_poses_checked if row.pose_truth_given else None,
            "poses_outside_covariance": row.num_outside_covariance if row.pose_truth_given else None,
            "poses_covariance_checked": row.num_covariance_checked if row.pose_truth_given else None}
