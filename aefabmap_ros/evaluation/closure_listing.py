"""Each recorded loop closure as one row: its frames, its ground-truth value, its relative pose and, given a
pose ground truth (a TUM file), that pose's error; ``closures.csv`` and the markdown listing of
``aefabmap_eval --recording``."""

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
from aefabmap_ros.evaluation.recordings import RecordedClosure, seconds_text
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.pose_error import OUTSIDE_COVARIANCE_CHI2, PoseError, relative_pose_error
from aefabmap_ros.verification.relative_pose import pose_message_to_matrix

# A closure's two stamps take the ground-truth poses nearest in time within this much (as the ATE does).
POSE_TRUTH_MAX_OFFSET_NS = 10_000_000
# A closure's relative pose is wrong beyond these errors (rotation and, monocular, translation direction; metric).
WRONG_POSE_DEG = 5.0
WRONG_POSE_M = 0.2


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
    covariance = np.asarray(message.pose_covariance, dtype=np.float64) if message.translation_metric else None
    return relative_pose_error(query, matched, pose_message_to_matrix(message.pose), covariance)


def pose_is_wrong(error: PoseError, metric: bool) -> bool:
    """Rotation beyond WRONG_POSE_DEG, or the translation beyond WRONG_POSE_M (metric) / its direction beyond
    WRONG_POSE_DEG (monocular; undefined when the cameras are less than 1 mm apart)."""
    if error.rotation_deg > WRONG_POSE_DEG:
        return True
    if metric:
        return error.translation_m > WRONG_POSE_M
    return not math.isnan(error.direction_deg) and error.direction_deg > WRONG_POSE_DEG


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

    @property
    def pose_outside_covariance(self) -> bool | None:
        """Whether the metric pose's error lies outside its covariance's 99.9 % region (None: not checked)."""
        if self.error is None or math.isnan(self.error.mahalanobis2):
            return None
        return self.error.mahalanobis2 > OUTSIDE_COVARIANCE_CHI2


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
               "rotation_error_deg", "translation_error_m", "direction_error_deg", "pose_wrong",
               "pose_error_mahalanobis2")


def closures_csv(rows: Iterable[ClosureRow]) -> str:
    """closures.csv: one line per recorded closure (CSV_COLUMNS). Empty cells: no pose, or no pose truth;
    translation_error_m and pose_error_mahalanobis2 (the error under the pose's covariance) only for a metric
    pose."""
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
                         int(row.translation_metric), *pose, *errors, "" if wrong is None else int(wrong),
                         "" if error is None else number(error.mahalanobis2)])
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
