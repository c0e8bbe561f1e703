"""A recorded run of the nodes scored offline: the posteriors and loop closures of a bag against ground truth.

``aefabmap_eval --recording``: the score matrix is rebuilt from ``place_posteriors``, and each
closure topic (raw candidates, published closures) is scored per closure and per revisit event.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.metrics import (
    DEFAULT_EVENT_GAP,
    EventScores,
    event_scores,
    missed_with_a_true_place_ranked,
)
from aefabmap_ros.evaluation.reports import (
    MISSED_RANKED_KEY,
    events_to_dict,
    fmt,
    jsonable_float,
    missed_ranked_cell,
    recall_cell,
)
from aefabmap_ros.stamps import stamp_to_ns


@dataclass(frozen=True)
class RecordedClosure:
    query_frame: int
    matched_frame: int
    probability: float


@dataclass
class RecordingScores:
    """Score matrix rebuilt from a recording, and the detector's own loop-closure decisions."""

    scores: np.ndarray  # (N, N) float64, [i, j] = recorded posterior of frame j for query i, 0 if unreported
    closures: list[RecordedClosure]
    num_posteriors: int
    num_loop_closures: int
    stamp_aligned_candidates: int  # candidates mapped to a frame through their stamp


def scores_from_recording(
    posteriors: Sequence[Any], loop_closures: Sequence[Any], num_frames: int
) -> RecordingScores:
    """Score matrix of ``num_frames`` frames from ``PlacePosterior`` and ``LoopClosure`` messages.

    Messages are rosbags/rclpy objects (attributes as in aefabmap_msgs). See the module doc for
    how place ids become frame indices. Raises DataError for query or place frames outside
    [0, num_frames) and for a place mapped to a frame not before its query.
    """
    stamp_to_frame: dict[int, int] = {}
    for message in posteriors:
        stamp_to_frame.setdefault(stamp_to_ns(message.header.stamp), int(message.query_id))
    for message in loop_closures:
        stamp_to_frame.setdefault(stamp_to_ns(message.header.stamp), int(message.query_id))

    scores = np.zeros((num_frames, num_frames))
    aligned = 0

    def frame_of(place_id: int, stamp_ns: int) -> int:
        nonlocal aligned
        frame = stamp_to_frame.get(stamp_ns)
        if frame is not None:
            aligned += 1
            return frame
        return int(place_id)

    def put(query: int, frame: int, probability: float, what: str) -> None:
        if not 0 <= query < num_frames:
            raise DataError(f"{what}: query id {query} outside the {num_frames} frames of the ground truth")
        if not 0 <= frame < query:
            raise DataError(f"{what}: query {query} maps to frame {frame}, which is not an earlier frame")
        scores[query, frame] = max(scores[query, frame], probability)

    for message in posteriors:
        query = int(message.query_id)
        place_ids = np.asarray(message.place_ids, dtype=np.int64)
        probabilities = np.asarray(message.probabilities, dtype=np.float64)
        stamps = [stamp_to_ns(s) for s in message.place_stamps]
        if probabilities.shape != place_ids.shape:
            raise DataError(f"place_posteriors query {query}: {place_ids.size} place ids but "
                            f"{probabilities.size} probabilities")
        if len(stamps) != place_ids.size:
            stamps = [-1] * place_ids.size
        for place_id, stamp_ns, probability in zip(place_ids.tolist(), stamps, probabilities.tolist(), strict=True):
            put(query, frame_of(place_id, stamp_ns), probability, "place_posteriors")
    closures = []
    for message in loop_closures:
        query = int(message.query_id)
        frame = frame_of(int(message.matched_place_id), stamp_to_ns(message.matched_stamp))
        put(query, frame, float(message.probability), "loop_closures")
        closures.append(RecordedClosure(query, frame, float(message.probability)))
    return RecordingScores(scores, closures, len(posteriors), len(loop_closures), aligned)


def closure_precision_recall(closures: Sequence[RecordedClosure], gt: np.ndarray, min_gap: int) -> tuple[float, float]:
    """Precision and recall of a detector's own decisions (one closure per query at most counts).

    A closure is true when ``gt[query, matched] = 1``; recall = true queries / queries with an
    eligible ground-truth loop (``j <= i - min_gap``), as in ``evaluation.metrics``.
    """
    truth = np.asarray(gt).astype(bool)
    index = np.arange(truth.shape[0])
    positive = int((truth & (index[None, :] <= index[:, None] - min_gap)).any(axis=1).sum())
    true_queries = {c.query_frame for c in closures if truth[c.query_frame, c.matched_frame]}
    precision = sum(bool(truth[c.query_frame, c.matched_frame]) for c in closures) / len(closures) if closures \
        else float("nan")
    recall = len(true_queries) / positive if positive else 0.0
    return float(precision), float(recall)


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


def score_recorded_closures(role: str, topic: str, loop_closures: Sequence[Any], posteriors: Sequence[Any],
                            gt: np.ndarray, min_gap: int, event_gap: int = DEFAULT_EVENT_GAP) -> TopicClosureScores:
    """Score the ``LoopClosure`` messages of one recorded topic (frames as in :func:`scores_from_recording`):
    precision, and per revisit event and revisiting frame (:func:`evaluation.metrics.event_scores`)."""
    recorded = scores_from_recording(posteriors, loop_closures, gt.shape[0])
    closures = recorded.closures
    precision, _ = closure_precision_recall(closures, gt, min_gap)
    pairs = [(c.query_frame, c.matched_frame) for c in closures]
    events = event_scores(pairs, gt, min_gap, event_gap)
    verified = sum(1 for message in loop_closures if int(message.inliers) > 0)
    queries, frames = np.nonzero(recorded.scores > 0)  # sparse: a posterior reports a few places
    ranked = list(zip(queries.tolist(), frames.tolist(), strict=True))
    return TopicClosureScores(role, topic, verified, precision, events,
                              missed_with_a_true_place_ranked(pairs, ranked, gt, min_gap))


def closure_scores_markdown(rows: Sequence[TopicClosureScores]) -> str:
    """A markdown table: one row per recorded closure topic."""
    lines = [
        "| closures | topic | closures | verified (inliers > 0) | false | precision | revisit events "
        "| events closed | fraction of events closed | recall (revisiting frames) "
        "| missed frames with a true place ranked |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        e = row.events
        lines.append(
            f"| {row.role} | `{row.topic}` | {e.num_closures} | {row.num_verified} | {e.num_false_closures} "
            f"| {fmt(row.precision)} | {e.num_events} | {e.num_events_closed} | {fmt(e.fraction_closed)} "
            f"| {recall_cell(e)} | {missed_ranked_cell(row.num_missed_ranked, e)} |"
        )
    return "\n".join(lines) + "\n"


def closure_scores_to_dict(row: TopicClosureScores) -> dict[str, Any]:
    return {"role": row.role, "topic": row.topic, "verified": row.num_verified,
            "precision": jsonable_float(row.precision), **events_to_dict(row.events),
            MISSED_RANKED_KEY: row.num_missed_ranked}
