"""A recorded run of the nodes scored offline: the posteriors and loop closures of a bag against ground truth.

``aefabmap_eval --recording``: the score matrix is rebuilt from ``place_posteriors`` here; each closure
topic (raw candidates, published closures) is scored per revisit event in ``closure_scores`` and listed
per closure in ``closure_listing``.

Frames are found by image stamp, never by ``query_id``: a message's ``header.stamp`` is its query
image's stamp, ``matched_stamp`` / ``place_stamps`` are the matched places' image stamps, and each
maps to the ground-truth frame with that stamp (:class:`FrameIndex`). ``query_id`` counts the
frames that reached fabmap_node: one frame lost before it (a live camera, best-effort QoS, a
detection-rate policy) would shift every later closure onto the wrong row. Only for a lossless
replay, whose query ids are the frame indices, can :func:`frames_by_query_id` map by id.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.stamps import stamp_to_ns

# A stamp read from a file of float seconds (a times file) matches the frame within this much.
FLOAT_SECONDS_TOLERANCE_NS = 1_000_000


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
