"""A recorded run of the nodes scored offline: the posteriors and loop closures of a bag against ground truth.

``aefabmap_eval --recording``: the score matrix is rebuilt from ``place_posteriors``, and each
closure topic (raw candidates, published closures) is scored per closure and per revisit event.

Frames are found by image stamp, never by ``query_id``: a message's ``header.stamp`` is its query
image's stamp, ``matched_stamp`` / ``place_stamps`` are the matched places' image stamps, and each
maps to the ground-truth frame with that stamp (:class:`FrameIndex`). ``query_id`` counts the
frames that reached fabmap_node: one frame lost before it (a live camera, best-effort QoS, a
detection-rate policy) would shift every later closure onto the wrong row. Only for a lossless
replay, whose query ids are the frame indices, can :func:`frames_by_query_id` map by id.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.metrics import (
    DEFAULT_EVENT_GAP,
    EventScores,
    eligible_mask,
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
from aefabmap_ros.verification.pose_error import PoseError, relative_pose_error
from aefabmap_ros.verification.relative_pose import pose_message_to_matrix

# A stamp read from a file of float seconds (a times file) matches the frame within this much.
FLOAT_SECONDS_TOLERANCE_NS = 1_000_000
# A closure's two stamps take the ground-truth poses nearest in time within this much (as the ATE does).
POSE_TRUTH_MAX_OFFSET_NS = 10_000_000
# A closure's relative pose is wrong beyond these errors (rotation and, monocular, translation direction; metric).
WRONG_POSE_DEG = 5.0
WRONG_POSE_M = 0.2


def seconds_text(stamp_ns: int) -> str:
    """A stamp as exact decimal seconds, ``1700000000.100000000``."""
    sign = "-" if stamp_ns < 0 else ""
    whole, fraction = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{whole}.{fraction:09d}"


# ------------------------------------------------------------------------------------------ stamps -> frames


class FrameIndex:
    """Which ground-truth frame an image stamp is.

    ``stamps_ns[i]`` is frame i's stamp (-1: unknown). A stamp maps to the frame with exactly that
    stamp; with ``tolerance_ns`` > 0 (stamps read from float seconds) to the one frame within the
    tolerance, and two frames within it are refused as ambiguous.
    """

    def __init__(self, stamps_ns: np.ndarray | Sequence[int], source: str, tolerance_ns: int = 0) -> None:
        stamps = np.asarray(stamps_ns)
        if stamps.ndim != 1 or not (stamps.size == 0 or np.issubdtype(stamps.dtype, np.integer)):
            raise DataError(f"frame stamps of {source} must be a 1-D array of integer nanoseconds, "
                            f"got {stamps.dtype} of shape {stamps.shape}")
        self.stamps_ns = stamps.astype(np.int64)
        self.source = source
        self.tolerance_ns = int(tolerance_ns)
        known = np.flatnonzero(self.stamps_ns >= 0)
        order = np.argsort(self.stamps_ns[known], kind="stable")
        self._sorted = self.stamps_ns[known][order]
        self._frames = known[order]
        same = np.flatnonzero(np.diff(self._sorted) == 0)
        if same.size:
            first, second = sorted((int(self._frames[same[0]]), int(self._frames[same[0] + 1])))
            raise DataError(f"frames {first} and {second} of {source} have the same stamp "
                            f"{seconds_text(int(self._sorted[same[0]]))} s: a stamp must name one frame")

    @property
    def num_frames(self) -> int:
        return int(self.stamps_ns.size)

    def describe(self) -> str:
        known = self._sorted
        span = (f"{known.size} stamped frames, {seconds_text(int(known[0]))} to {seconds_text(int(known[-1]))} s"
                if known.size else "no stamped frame")
        within = f", matched within {self.tolerance_ns / 1e6:g} ms" if self.tolerance_ns else ", matched exactly"
        return f"{self.source} ({span}{within})"

    def frame_of(self, stamp_ns: int) -> int | None:
        """The frame of ``stamp_ns``; None when no frame has it (DataError when two are within the tolerance)."""
        position = int(np.searchsorted(self._sorted, stamp_ns))
        if position < self._sorted.size and self._sorted[position] == stamp_ns:
            return int(self._frames[position])
        if not self.tolerance_ns:
            return None
        low = int(np.searchsorted(self._sorted, stamp_ns - self.tolerance_ns, side="left"))
        high = int(np.searchsorted(self._sorted, stamp_ns + self.tolerance_ns, side="right"))
        if high - low > 1:
            frames = ", ".join(str(int(f)) for f in self._frames[low:high])
            raise DataError(f"stamp {seconds_text(stamp_ns)} s is within {self.tolerance_ns / 1e6:g} ms of frames "
                            f"{frames} of {self.source}: ambiguous (frames that close need exact stamps: a --gt "
                            ".npz with stamps_ns, or --bag)")
        return int(self._frames[low]) if high > low else None


def frames_by_query_id(posteriors: Sequence[Any], closure_lists: Iterable[Sequence[Any]],
                       num_frames: int) -> FrameIndex:
    """Frame index of a lossless replay's recording: frame ``query_id`` has its messages' stamp.

    Right only when every frame of the sequence reached fabmap_node, once and in order (e.g.
    ``aefabmap_replay --lockstep``); a place stamped like no recorded query then matches no frame.
    """
    stamps = np.full(num_frames, -1, dtype=np.int64)
    messages = [("place_posteriors", m) for m in posteriors if int(m.query_id) >= 0]
    messages += [("loop closure", m) for closures in closure_lists for m in closures]
    for what, message in messages:
        query, stamp = int(message.query_id), stamp_to_ns(message.header.stamp)
        if not 0 <= query < num_frames:
            raise DataError(f"{what}: query id {query} outside the {num_frames} frames of the ground truth")
        if stamps[query] not in (-1, stamp):
            raise DataError(f"query id {query} has two stamps in the recording ({seconds_text(int(stamps[query]))} "
                            f"and {seconds_text(stamp)} s): not a lossless replay's recording, map frames by stamp")
        stamps[query] = stamp
    return FrameIndex(stamps, "the recording's query ids (--frames-by-query-id)")


class _StampMapper:
    """Maps stamps to frames, collecting the stamps that match none so that one error names them all."""

    def __init__(self, frames: FrameIndex) -> None:
        self.frames = frames
        self.unmatched: list[tuple[str, int]] = []

    def frame(self, stamp_ns: int, what: str) -> int:
        frame = self.frames.frame_of(stamp_ns)
        if frame is None:
            self.unmatched.append((what, stamp_ns))
            return -1
        return frame

    def check(self) -> None:
        if not self.unmatched:
            return
        what, stamp = self.unmatched[0]
        raise DataError(
            f"{len(self.unmatched)} recorded stamp{'s match' if len(self.unmatched) > 1 else ' matches'} no frame of "
            f"{self.frames.describe()}; the first: "
            f"{what} stamped {seconds_text(stamp)} s. The frame stamps must be those of the images the run was fed: "
            "pass --times FILE (one line of seconds per frame), a --gt .npz with a stamps_ns array (aefabmap_gt, "
            "aefabmap_synth write one) or --bag BAG --topic TOPIC (the images); a times file of seconds since the "
            "first frame (KITTI's, aefabmap_synth's times.txt) matches only a bag stamped from it (aefabmap_bag "
            "--times)")


# ------------------------------------------------------------------------------------------ the score matrix


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
    num_posteriors: int  # place_posteriors messages of processed frames (query_id >= 0)
    num_dropped_posteriors: int  # place_posteriors of frames fabmap_node dropped (query_id -1): not scored
    num_loop_closures: int
    processed: np.ndarray  # (N,) bool: frames with a place_posteriors message (the frames the detector processed)


def scores_from_recording(posteriors: Sequence[Any], loop_closures: Sequence[Any],
                          frames: FrameIndex) -> RecordingScores:
    """Score matrix of the ground truth's frames from ``PlacePosterior`` and ``LoopClosure`` messages.

    Messages are rosbags/rclpy objects (attributes as in aefabmap_msgs). Every query and place is
    mapped to its frame by stamp (:class:`FrameIndex`); DataError for a stamp that matches no frame
    and for a place mapped to a frame not before its query.
    """
    mapper = _StampMapper(frames)
    entries: list[tuple[int, int, float, str]] = []
    processed = np.zeros(frames.num_frames, dtype=bool)
    dropped = 0
    for message in posteriors:
        if int(message.query_id) < 0:  # dropped by fabmap_node (in the map already, out of order, ...)
            dropped += 1
            continue
        stamp = stamp_to_ns(message.header.stamp)
        query = mapper.frame(stamp, "place_posteriors query")
        place_ids = np.asarray(message.place_ids, dtype=np.int64)
        probabilities = np.asarray(message.probabilities, dtype=np.float64)
        place_stamps = [stamp_to_ns(s) for s in message.place_stamps]
        if probabilities.shape != place_ids.shape or len(place_stamps) != place_ids.size:
            raise DataError(f"place_posteriors at {seconds_text(stamp)} s: {place_ids.size} place ids, "
                            f"{probabilities.size} probabilities and {len(place_stamps)} place stamps")
        if query >= 0:
            processed[query] = True
        for place_stamp, probability in zip(place_stamps, probabilities.tolist(), strict=True):
            entries.append((query, mapper.frame(place_stamp, "place_posteriors place"), probability,
                            "place_posteriors"))
    closures = []
    for message in loop_closures:
        query = mapper.frame(stamp_to_ns(message.header.stamp), "loop closure query")
        matched = mapper.frame(stamp_to_ns(message.matched_stamp), "loop closure matched place")
        entries.append((query, matched, float(message.probability), "loop closure"))
        closures.append(RecordedClosure(query, matched, float(message.probability)))
    mapper.check()
    scores = np.zeros((frames.num_frames, frames.num_frames))
    for query, frame, probability, what in entries:
        if not 0 <= frame < query:
            raise DataError(f"{what}: query frame {query} ({seconds_text(int(frames.stamps_ns[query]))} s) maps "
                            f"to frame {frame}, which is not an earlier frame")
        scores[query, frame] = max(scores[query, frame], probability)
    return RecordingScores(scores, closures, len(posteriors) - dropped, dropped, len(loop_closures), processed)


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


# ------------------------------------------------------------------------------------------ closure poses


@dataclass(frozen=True)
class PoseTruth:
    """Ground-truth camera-to-world poses by stamp (a TUM file)."""

    stamps_ns: np.ndarray  # (M,) int64, increasing
    poses: np.ndarray  # (M, 4, 4) camera-to-world
    source: str
    max_offset_ns: int = POSE_TRUTH_MAX_OFFSET_NS

    def pose_at(self, stamp_ns: int) -> np.ndarray | None:
        """The pose nearest in time to ``stamp_ns``, None when none is within ``max_offset_ns``."""
        after = int(np.searchsorted(self.stamps_ns, stamp_ns))
        nearby = [i for i in (after - 1, after) if 0 <= i < self.stamps_ns.size]
        if not nearby:
            return None
        best = min(nearby, key=lambda i: abs(int(self.stamps_ns[i]) - stamp_ns))
        return self.poses[best] if abs(int(self.stamps_ns[best]) - stamp_ns) <= self.max_offset_ns else None


def read_pose_truth(path: Path) -> PoseTruth:
    """A TUM file (``t x y z qx qy qz qw``, camera-to-world, as aefabmap_synth's groundtruth.tum), read by evo."""
    from aefabmap_ros.evaluation.trajectory_error import read_tum  # evo: loaded only when a truth is given

    trajectory = read_tum(path)
    stamps = np.rint(np.asarray(trajectory.timestamps, dtype=np.float64) * 1e9).astype(np.int64)
    order = np.argsort(stamps, kind="stable")
    poses = np.asarray(trajectory.poses_se3, dtype=np.float64)[order]
    if poses.shape[0] == 0:
        raise DataError(f"pose truth {path} holds no poses")
    return PoseTruth(stamps[order], poses, str(path))


def closure_pose_error(message: Any, truth: PoseTruth) -> PoseError | None:
    """Error of a LoopClosure's relative pose (T_q_m: the matched place's camera in the query camera's
    frame) against the truth at its two stamps; None without a pose or without truth at either stamp."""
    if not message.pose_available:
        return None
    query = truth.pose_at(stamp_to_ns(message.header.stamp))
    matched = truth.pose_at(stamp_to_ns(message.matched_stamp))
    if query is None or matched is None:
        return None
    return relative_pose_error(query, matched, pose_message_to_matrix(message.pose))


def pose_is_wrong(error: PoseError, metric: bool) -> bool:
    """Rotation beyond WRONG_POSE_DEG, or the translation beyond WRONG_POSE_M (metric) / its direction beyond
    WRONG_POSE_DEG (monocular; undefined when the cameras are less than 1 mm apart)."""
    if error.rotation_deg > WRONG_POSE_DEG:
        return True
    if metric:
        return error.translation_m > WRONG_POSE_M
    return not math.isnan(error.direction_deg) and error.direction_deg > WRONG_POSE_DEG


# ------------------------------------------------------------------------------------------ per closure


@dataclass(frozen=True)
class ClosureRow:
    """One recorded closure, located in the ground truth."""

    topic: str
    query_stamp_ns: int
    query_frame: int
    matched_stamp_ns: int
    matched_frame: int
    probability: float
    inliers: int
    gt_value: int  # gt[query, matched], as the ground-truth file holds it
    pose_available: bool
    translation_metric: bool
    pose: tuple[float, ...]  # x y z qx qy qz qw of the message (T_q_m)
    error: PoseError | None  # against --pose-truth

    @property
    def true(self) -> bool:
        return self.gt_value == 1

    @property
    def pose_wrong(self) -> bool | None:
        return None if self.error is None else pose_is_wrong(self.error, self.translation_metric)


def closure_rows(topic: str, loop_closures: Sequence[Any], closures: Sequence[RecordedClosure], gt: np.ndarray,
                 pose_truth: PoseTruth | None = None) -> list[ClosureRow]:
    """The listing of one topic's closures: ``closures`` are ``loop_closures`` mapped to frames, in order."""
    rows = []
    for message, closure in zip(loop_closures, closures, strict=True):
        position, orientation = message.pose.position, message.pose.orientation
        rows.append(ClosureRow(
            topic, stamp_to_ns(message.header.stamp), closure.query_frame, stamp_to_ns(message.matched_stamp),
            closure.matched_frame, float(message.probability), int(message.inliers),
            int(gt[closure.query_frame, closure.matched_frame]), bool(message.pose_available),
            bool(message.translation_metric),
            tuple(float(v) for v in (position.x, position.y, position.z, orientation.x, orientation.y, orientation.z,
                                     orientation.w)),
            None if pose_truth is None else closure_pose_error(message, pose_truth)))
    return rows


CSV_COLUMNS = ("topic", "query_stamp", "query_frame", "matched_stamp", "matched_frame", "probability", "inliers",
               "true", "gt", "pose_available", "translation_metric", "x", "y", "z", "qx", "qy", "qz", "qw",
               "rotation_error_deg", "translation_error_m", "direction_error_deg", "pose_wrong")


def closures_csv(rows: Iterable[ClosureRow]) -> str:
    """closures.csv: one line per recorded closure (CSV_COLUMNS). Empty cells: no pose, or no pose truth;
    translation_error_m only for a metric pose."""
    def number(value: float) -> str:
        return "" if math.isnan(value) else f"{value:.6f}"

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for row in rows:
        pose = [f"{value:.9g}" for value in row.pose] if row.pose_available else [""] * 7
        error = row.error
        errors = ["", "", ""] if error is None else [
            number(error.rotation_deg), number(error.translation_m) if row.translation_metric else "",
            number(error.direction_deg)]
        wrong = row.pose_wrong
        writer.writerow([row.topic, seconds_text(row.query_stamp_ns), row.query_frame,
                         seconds_text(row.matched_stamp_ns), row.matched_frame, f"{row.probability:.6g}",
                         row.inliers, int(row.true), row.gt_value, int(row.pose_available),
                         int(row.translation_metric), *pose, *errors, "" if wrong is None else int(wrong)])
    return buffer.getvalue()


def _closure_lines(rows: Sequence[ClosureRow], limit: int) -> list[str]:
    lines = ["| topic | query frame | query stamp (s) | matched frame | matched stamp (s) | probability | inliers "
             "| rotation error (deg) | translation error |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in rows[:limit]:
        error = row.error
        rotation = "" if error is None else f"{error.rotation_deg:.2f}"
        translation = ("" if error is None else f"{error.translation_m:.3f} m" if row.translation_metric
                       else f"{error.direction_deg:.2f} deg (direction)")
        lines.append(f"| `{row.topic}` | {row.query_frame} | {seconds_text(row.query_stamp_ns)} | {row.matched_frame} "
                     f"| {seconds_text(row.matched_stamp_ns)} | {row.probability:.4f} | {row.inliers} | {rotation} "
                     f"| {translation} |")
    if len(rows) > limit:
        lines.append(f"\n... and {len(rows) - limit} more (closures.csv).")
    return lines


def closure_listing_markdown(rows: Sequence[ClosureRow], pose_truth_given: bool, limit: int = 50) -> str:
    """The false closures (and, with a pose truth, the wrong poses) of every topic; closures.csv lists all."""
    false = [row for row in rows if not row.true]
    lines = ["", "False closures (gt[i, j] = 0; every closure is in closures.csv):", ""]
    lines += _closure_lines(false, limit) if false else ["None."]
    if pose_truth_given:
        wrong = [row for row in rows if row.pose_wrong]
        lines += ["", f"Closures with a wrong relative pose (rotation > {WRONG_POSE_DEG:g} deg, translation > "
                      f"{WRONG_POSE_M:g} m, or for a monocular pose its direction > {WRONG_POSE_DEG:g} deg):", ""]
        lines += _closure_lines(wrong, limit) if wrong else ["None."]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------ per topic


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
        + (f" wrong poses (> {WRONG_POSE_DEG:g} deg or > {WRONG_POSE_M:g} m) / checked |" if poses else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if poses else ""),
    ]
    for row in rows:
        e = row.events
        lines.append(
            f"| {row.role} | `{row.topic}` | {e.num_closures} | {row.num_verified} | {e.num_false_closures} "
            f"| {fmt(row.precision)} | {e.num_events} | {e.num_events_closed} | {fmt(e.fraction_closed)} "
            f"| {recall_cell(e)} | {_processed_recall_cell(row)} | {missed_ranked_cell(row.num_missed_ranked, e)} |"
            + (f" {row.num_wrong_poses} / {row.num_poses_checked} |" if poses else "")
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
            "poses_checked": row.num_poses_checked if row.pose_truth_given else None}
