"""A recorded run's loop closures scored per pair of sessions (``aefabmap_eval --recording`` on a map of several
sessions): for each query session and matched session, the closures published, the false ones, the recall of
the query session's frames that revisit the matched session, and the closures' pose errors.

A session is (robot, session number), as LoopClosure's ``query_robot``/``query_session`` and
``matched_robot``/``matched_session`` and PlacePosterior's ``robot``/``session`` name it; a recording made before
sessions (no such fields) is one session, ('', 0). Which session each ground-truth frame belongs to comes from
the recording itself: its posteriors (the query's session, each ranked place's), and its closures' two ends.

Recall of the pair (Q -> M): of the frames of Q whose ground-truth row has a revisit in M (a frame of M at least
min_gap frames earlier, as everywhere in the evaluation), the share with a true closure (gt[i, j] = 1) whose
message names M as the matched session.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.closure_listing import WRONG_POSE_DEG, WRONG_POSE_M, ClosureRow
from aefabmap_ros.evaluation.metrics import eligible_mask
from aefabmap_ros.evaluation.recordings import FrameIndex, seconds_text
from aefabmap_ros.evaluation.reports import fmt, jsonable_float
from aefabmap_ros.stamps import stamp_to_ns

SessionId = tuple[str, int]  # (robot, session number); robot '' = the map's only robot


def session_name(session: SessionId) -> str:
    robot, number = session
    return f"{robot}/{number}" if robot else str(number)


def closure_sessions(message: Any) -> tuple[SessionId, SessionId]:
    """(query session, matched session) of a LoopClosure; ('', 0) for a recording without session fields."""
    return ((str(getattr(message, "query_robot", "")), int(getattr(message, "query_session", 0))),
            (str(getattr(message, "matched_robot", "")), int(getattr(message, "matched_session", 0))))


def recorded_sessions(closure_lists: Iterable[Sequence[Any]]) -> list[SessionId]:
    """Every session a closure names (either end), sorted."""
    return sorted({session for closures in closure_lists for message in closures
                   for session in closure_sessions(message)})


def frame_sessions(posteriors: Sequence[Any], closure_lists: Iterable[Sequence[Any]],
                   frames: FrameIndex) -> list[SessionId | None]:
    """The session of each ground-truth frame (None: never named): the one its own place_posteriors message
    names, else its closures' query session, else the session a place or matched end of a closure names for it
    (those name the matched *place's* session, which a frame that joined a place of an earlier session need not
    share). DataError when two posteriors name one frame in two sessions."""
    own: list[SessionId | None] = [None] * frames.num_frames
    claimed: list[SessionId | None] = [None] * frames.num_frames

    def claim(stamp_ns: int, session: SessionId) -> None:
        frame = frames.frame_of(stamp_ns)
        if frame is not None and claimed[frame] is None:
            claimed[frame] = session

    for message in posteriors:
        if int(message.query_id) < 0:
            continue
        stamp_ns = stamp_to_ns(message.header.stamp)
        session = (str(getattr(message, "robot", "")), int(getattr(message, "session", 0)))
        frame = frames.frame_of(stamp_ns)
        if frame is not None:
            named = own[frame]
            if named is not None and named != session:
                raise DataError(f"the recording names frame {frame} ({seconds_text(stamp_ns)} s) in two sessions, "
                                f"{session_name(named)} and {session_name(session)}")
            own[frame] = session
    for closures in closure_lists:
        for message in closures:
            claim(stamp_to_ns(message.header.stamp), closure_sessions(message)[0])
    for closures in closure_lists:
        for message in closures:
            claim(stamp_to_ns(message.matched_stamp), closure_sessions(message)[1])
    for message in posteriors:
        place_sessions = list(getattr(message, "place_sessions", []))
        place_robots = list(getattr(message, "place_robots", []))
        if int(message.query_id) >= 0 and len(place_sessions) == len(message.place_stamps) == len(place_robots):
            for stamp, number, robot in zip(message.place_stamps, place_sessions, place_robots, strict=True):
                claim(stamp_to_ns(stamp), (str(robot), int(number)))
    return [mine if mine is not None else other for mine, other in zip(own, claimed, strict=True)]


def revisit_recall(pairs: Iterable[tuple[int, int]], gt: np.ndarray, query_frames: np.ndarray,
                   matched_frames: np.ndarray, min_gap: int) -> tuple[int, int]:
    """(closed, revisiting): the frames of ``query_frames`` (a bool mask) whose ground-truth row has a revisit
    among ``matched_frames`` at least ``min_gap`` frames back, and those of them with a true closure
    (gt[i, j] = 1) into one of ``matched_frames`` among ``pairs`` (query frame, matched frame)."""
    matched_frames = np.asarray(matched_frames, dtype=bool)
    truth = np.asarray(gt).astype(bool) & eligible_mask(gt.shape[0], min_gap) & matched_frames[None, :]
    revisiting = np.asarray(query_frames, dtype=bool) & truth.any(axis=1)
    closed = np.zeros_like(revisiting)
    for query, matched in pairs:
        if 0 <= query < len(closed) and 0 <= matched < len(closed) and gt[query, matched] == 1 \
                and matched_frames[matched]:
            closed[query] = True
    return int((revisiting & closed).sum()), int(revisiting.sum())


@dataclass(frozen=True)
class SessionPairScores:
    """The closures from one session into another (or into itself), scored."""

    query: SessionId
    matched: SessionId
    closures: int
    false: int
    revisiting: int  # frames of the query session with a ground-truth revisit in the matched session
    revisiting_closed: int  # ... and a true closure into it
    poses_checked: int
    wrong_poses: int
    # Closures whose matched image belongs to another session than the one they name (e.g. a frame that joined a
    # place of an earlier session, named by the place's session): none counts as closing a revisit of this pair.
    mislabelled: int
    median_rotation_deg: float  # over the poses checked
    median_translation_m: float  # over the metric poses checked

    @property
    def recall(self) -> float:
        return self.revisiting_closed / self.revisiting if self.revisiting else float("nan")


def score_session_pairs(rows: Sequence[ClosureRow], sessions: Sequence[tuple[SessionId, SessionId]],
                        frame_session: Sequence[SessionId | None], gt: np.ndarray,
                        min_gap: int) -> list[SessionPairScores]:
    """One entry per (query session, matched session) that has closures, or revisits of an earlier (or the
    same) session; ``rows`` are one topic's closures and ``sessions`` their messages' sessions, in order.
    Sessions are ordered by their first frame."""
    first_frame: dict[SessionId, int] = {}
    for frame, session in enumerate(frame_session):
        if session is not None:
            first_frame.setdefault(session, frame)
    for query, matched in sessions:
        for session in (query, matched):
            first_frame.setdefault(session, len(frame_session))
    order = sorted(first_frame, key=lambda session: (first_frame[session], session))
    masks = {session: np.array([s == session for s in frame_session], dtype=bool) for session in order}
    wanted = dict.fromkeys(sessions)
    wanted.update(dict.fromkeys((q, m) for i, q in enumerate(order) for m in order[:i + 1]))
    scores = []
    for query, matched in sorted(wanted, key=lambda pair: (order.index(pair[0]), order.index(pair[1]))):
        chosen = [row for row, pair in zip(rows, sessions, strict=True) if pair == (query, matched)]
        mislabelled = [row for row in chosen if frame_session[row.matched_frame] not in (None, matched)]
        closed, revisiting = revisit_recall([(row.query_frame, row.matched_frame) for row in chosen
                                             if row not in mislabelled], gt, masks[query], masks[matched], min_gap)
        if not chosen and not revisiting:
            continue
        errors = [row for row in chosen if row.error is not None]
        metric = [row.error.translation_m for row in errors if row.translation_metric and row.error is not None]
        scores.append(SessionPairScores(
            query, matched, len(chosen), sum(1 for row in chosen if not row.true), revisiting, closed,
            len(errors), sum(1 for row in errors if row.pose_wrong), len(mislabelled),
            float(np.median([row.error.rotation_deg for row in errors if row.error is not None]))
            if errors else float("nan"),
            float(np.median(metric)) if metric else float("nan")))
    return scores


def session_pairs_markdown(topic: str, pairs: Sequence[SessionPairScores], pose_truth_given: bool) -> str:
    lines = [f"\nLoop closures per pair of sessions (`{topic}`; a session is robot/number, or its number for the "
             "map's only robot). Recall: of the query session's frames with a ground-truth revisit in the matched "
             "session, the share with a true closure into it. A frame's session is the one its place_posteriors "
             "message names; a closure whose matched image is of another session than the one it names closes "
             "no revisit of its pair.\n",
             "| query session -> matched session | closures | false | matched image in another session "
             "| recall (revisiting frames closed) "
             + (f"| wrong poses (> {WRONG_POSE_DEG:g} deg or > {WRONG_POSE_M:g} m) / checked | median rotation "
                "error (deg) | median translation error (m, metric) |" if pose_truth_given else "|"),
             "|---|---|---|---|---|" + ("---|---|---|" if pose_truth_given else "")]
    for pair in pairs:
        lines.append(f"| {session_name(pair.query)} -> {session_name(pair.matched)} | {pair.closures} | {pair.false} "
                     f"| {pair.mislabelled} | {fmt(pair.recall)} ({pair.revisiting_closed}/{pair.revisiting}) |"
                     + (f" {pair.wrong_poses} / {pair.poses_checked} | {fmt(pair.median_rotation_deg)} "
                        f"| {fmt(pair.median_translation_m)} |" if pose_truth_given else ""))
    return "\n".join(lines) + "\n"


def session_pair_to_dict(pair: SessionPairScores, pose_truth_given: bool) -> dict[str, Any]:
    return {"query_robot": pair.query[0], "query_session": pair.query[1], "matched_robot": pair.matched[0],
            "matched_session": pair.matched[1], "closures": pair.closures, "false_closures": pair.false,
            "matched_image_in_another_session": pair.mislabelled,
            "revisiting_frames": pair.revisiting, "revisiting_frames_closed": pair.revisiting_closed,
            "recall_revisiting_frames": jsonable_float(pair.recall),
            "poses_checked": pair.poses_checked if pose_truth_given else None,
            "wrong_poses": pair.wrong_poses if pose_truth_given else None,
            "median_rotation_error_deg": jsonable_float(pair.median_rotation_deg) if pose_truth_given else None,
            "median_translation_error_m": jsonable_float(pair.median_translation_m) if pose_truth_given else None}
