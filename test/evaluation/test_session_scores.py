"""Closures per pair of sessions: which frame is in which session, and the recall of revisits into a session."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.closure_listing import ClosureRow
from aefabmap_ros.evaluation.recordings import FrameIndex
from aefabmap_ros.evaluation.session_scores import (
    closure_sessions,
    frame_sessions,
    revisit_recall,
    score_session_pairs,
    session_name,
)
from aefabmap_ros.io.bag_messages import make_header, make_time


def _closure(query: int, matched: int, **sessions: object) -> SimpleNamespace:
    return SimpleNamespace(header=make_header(1000 + query), matched_stamp=make_time(1000 + matched), **sessions)


def _row(query: int, matched: int, gt: np.ndarray) -> ClosureRow:
    return ClosureRow("loop_closures", 1000 + query, query, 1000 + matched, matched, 0.99, 30,
                      int(gt[query, matched]), False, False, (0.0,) * 7, None)


def test_a_closure_without_session_fields_is_session_zero_of_no_robot() -> None:
    assert closure_sessions(_closure(5, 1)) == (("", 0), ("", 0))
    named = _closure(5, 1, query_robot="rover", query_session=2, matched_robot="", matched_session=0)
    assert closure_sessions(named) == (("rover", 2), ("", 0))
    assert [session_name(s) for s in closure_sessions(named)] == ["rover/2", "0"]


def test_revisit_recall_counts_frames_not_closures() -> None:
    gt = np.zeros((30, 30), np.uint8)
    gt[20, 0] = gt[21, 1] = gt[22, 2] = gt[23, 15] = 1  # 23 revisits a frame of the same half
    later = np.arange(30) >= 15
    # Frames 20-22 revisit the earlier half (23 revisits a frame of its own half); 20 and 21 have a true closure
    # (20 -> 1 and 22 -> 9 are false).
    pairs = [(20, 0), (20, 1), (21, 1), (22, 9)]
    assert revisit_recall(pairs, gt, later, ~later, min_gap=10) == (2, 3)
    gt[20, 1] = 1  # two true closures of frame 20 count once
    assert revisit_recall(pairs, gt, later, ~later, min_gap=10) == (2, 3)
    assert revisit_recall([(22, 9)], gt, later, ~later, min_gap=10) == (0, 3)
    gt[22, 16] = 1  # 22 also revisits a frame of its own half: a true closure there closes no revisit of the other
    assert revisit_recall([(22, 16)], gt, later, ~later, min_gap=5) == (0, 3)
    assert revisit_recall([(22, 16)], gt, later, later, min_gap=5) == (1, 2)  # 22 -> 16 and 23 -> 15
    assert revisit_recall([(23, 15)], gt, later, later, min_gap=5) == (1, 2)
    assert revisit_recall([(23, 15)], gt, later, later, min_gap=10) == (0, 0)  # 8 frames back: too recent


def test_frames_are_given_the_sessions_the_recording_names() -> None:
    frames = FrameIndex(np.arange(1000, 1010), "test")
    posterior = SimpleNamespace(query_id=4, header=make_header(1006), robot="", session=1,
                                place_stamps=[make_time(1001)], place_sessions=[0], place_robots=[""])
    dropped = SimpleNamespace(query_id=-1, header=make_header(1007), robot="", session=5, place_stamps=[],
                              place_sessions=[], place_robots=[])
    closure = _closure(8, 2, query_robot="", query_session=1, matched_robot="", matched_session=0)
    sessions = frame_sessions([posterior, dropped], [[closure]], frames)
    assert sessions == [None, ("", 0), ("", 0), None, None, None, ("", 1), None, ("", 1), None]
    # A frame's own posterior says its session; what a closure or a ranked place names for it only fills a gap
    # (a frame that joined a place of an earlier session is named by that place's session).
    place_of_earlier = _closure(8, 6, query_robot="", query_session=1, matched_robot="", matched_session=0)
    assert frame_sessions([posterior], [[place_of_earlier]], frames)[6] == ("", 1)
    again = SimpleNamespace(query_id=5, header=make_header(1006), robot="", session=2, place_stamps=[],
                            place_sessions=[], place_robots=[])
    with pytest.raises(DataError, match=r"frame 6 .* in two sessions, 1 and 2"):
        frame_sessions([posterior, again], [], frames)


def test_pairs_in_session_order_with_revisits_left_unclosed() -> None:
    gt = np.zeros((40, 40), np.uint8)
    gt[20, 0] = gt[21, 1] = gt[39, 25] = 1
    a, b = ("", 0), ("", 1)
    frame_session = [a] * 20 + [b] * 20
    rows = [_row(20, 0, gt), _row(22, 3, gt)]
    pairs = score_session_pairs(rows, [(b, a), (b, a)], frame_session, gt, min_gap=10)
    assert [(p.query, p.matched) for p in pairs] == [(b, a), (b, b)]  # A -> A has neither closures nor revisits
    cross, inside = pairs
    assert (cross.closures, cross.false, cross.revisiting_closed, cross.revisiting) == (2, 1, 1, 2)
    assert (inside.closures, inside.revisiting_closed, inside.revisiting, inside.recall) == (0, 0, 1, 0.0)
    assert cross.poses_checked == 0 and np.isnan(cross.median_rotation_deg) and cross.mislabelled == 0


def test_a_closure_naming_the_wrong_session_closes_no_revisit_of_its_pair() -> None:
    """Frame 21 is of session B, though the closure names A (its place was made in A): it does not count as a
    closure into A, and it is counted as such."""
    gt = np.zeros((40, 40), np.uint8)
    gt[35, 5] = gt[35, 21] = 1
    a, b = ("", 0), ("", 1)
    frame_session = [a] * 20 + [b] * 20
    cross, inside = score_session_pairs([_row(35, 21, gt)], [(b, a)], frame_session, gt, min_gap=10)
    assert (cross.closures, cross.false, cross.mislabelled, cross.revisiting_closed, cross.revisiting) == \
        (1, 0, 1, 0, 1)
    assert (inside.closures, inside.revisiting_closed, inside.revisiting) == (0, 0, 1)  # named B -> A, not B -> B
