"""Two robots on one map: each one's odometry in its own frame, a known rigid offset from the map.

Ground truth: robot r1 drives the square loop of test_pose_graph from the origin, its odometry exact, so r1's
odometry frame is the map frame (r1 is the graph's own robot: its first session anchors the map). Robot r2
drives the same square at the same time, started at its first corner and 0.3 m to the side (test_sessions'
path B): its odometry is T_offset^-1 * truth with T_offset = its first true pose, so it starts at its own
identity. The two robots' odometry arrives interleaved (r2's half a second after r1's). A closure between the
robots carries the true relative pose of the two frames; after it, r2's keyframes in the map frame must be
r2's truth and r2's map -> odom must be T_offset, whichever robot closed a loop of its own first.
"""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.graph_file import load_graph, save_graph
from aefabmap_ros.backend.pose_graph import Closure, ClosureResult, PoseGraph, PoseGraphConfig, SessionId
from test.backend.test_pose_graph import square_truth, stamp
from test.backend.test_sessions import COVARIANCE, SECOND, b_odometry, b_offset, b_truth

R1: SessionId = ("r1", 0)
R2: SessionId = ("r2", 0)
END = len(square_truth()) - 1


def r2_stamp(index: int) -> int:
    return stamp(index) + SECOND // 2


def stamp_of(session_id: SessionId, index: int) -> int:
    return r2_stamp(index) if session_id[0] == "r2" else stamp(index)


def truth_of(session_id: SessionId) -> list[gtsam.Pose3]:
    return b_truth() if session_id[0] == "r2" else square_truth()


def interleaved(graph: PoseGraph, indices: range) -> list[ClosureResult]:
    """Both robots' odometry of those frames, r1's then r2's, each routed by its robot."""
    results = []
    for index in indices:
        results += graph.add_odometry(stamp(index), square_truth()[index], robot="r1")
        results += graph.add_odometry(r2_stamp(index), b_odometry()[index], robot="r2")
    return results


def closure(query: SessionId, query_index: int, place: SessionId, place_index: int) -> Closure:
    """The true T_query_place of two frames, each of its robot's session."""
    relative = truth_of(query)[query_index].between(truth_of(place)[place_index])
    return Closure(stamp_of(query, query_index), stamp_of(place, place_index), relative, COVARIANCE,
                   query_session=query, place_session=place)


def assert_on_truth(graph: PoseGraph, session_id: SessionId, tolerance_m: float) -> None:
    keyframes = graph.session_trajectory(*session_id)
    assert keyframes
    for stamp_ns, pose in keyframes:
        index = (stamp_ns - stamp_of(session_id, 0)) // SECOND
        assert graph.keyframe_in_map(session_id, stamp_ns) is not None  # joined: in the map frame
        assert np.linalg.norm(pose.translation() - truth_of(session_id)[index].translation()) < tolerance_m
        assert np.linalg.norm(gtsam.Rot3.Logmap(pose.rotation().between(truth_of(session_id)[index].rotation()))) \
            < 1e-4


@pytest.mark.parametrize("r2_first", [True, False])
def test_a_second_robot_joins_the_map_at_its_first_closure_into_it(r2_first: bool) -> None:
    graph = PoseGraph(PoseGraphConfig(), robot="r1")
    assert interleaved(graph, range(END + 1)) == []
    own_loops = [closure(R2, END, R2, 2), closure(R1, END, R1, 2)]
    for own in own_loops if r2_first else own_loops[::-1]:
        assert graph.add_closure(own) is ClosureResult.ADDED
    assert graph.current_session("r1") == R1 and graph.current_session("r2") == R2 and graph.current == R1
    # Before the closure between them: r1 holds the map, r2 is a graph of its own, at its own odometry.
    assert graph.anchor == R1 and graph.is_joined(*R1) and not graph.is_joined(*R2)
    assert graph.keyframe_in_map(R2, r2_stamp(END)) is None
    assert graph.map_to_odom(*R2).equals(gtsam.Pose3(), 1e-6)
    for stamp_ns, pose in graph.session_trajectory(*R2):
        assert pose.equals(b_odometry()[(stamp_ns - r2_stamp(0)) // SECOND], 1e-6)
    assert [stamp_ns for stamp_ns, _ in graph.trajectory()] == [stamp(0), stamp(2), stamp(END)]

    # r2's frame 10 sees r1's frame 31 (near it on the square's second side): the join.
    assert graph.add_closure(closure(R2, 10, R1, 31)) is ClosureResult.ADDED
    assert graph.is_joined(*R2)
    assert_on_truth(graph, R2, 1e-3)
    assert_on_truth(graph, R1, 1e-3)
    assert graph.map_to_odom(*R2).equals(b_offset(), 1e-4)
    assert graph.map_to_odom(*R1).equals(gtsam.Pose3(), 1e-6)
    stamps = [stamp_ns for stamp_ns, _ in graph.trajectory()]
    assert stamps == sorted(stamps) and set(stamps) == {stamp(0), stamp(2), stamp(31), stamp(END), r2_stamp(0),
                                                       r2_stamp(2), r2_stamp(10), r2_stamp(END)}
    # The joined graph goes on: a true closure between the robots is gated and added, a 5 m wrong one refused.
    assert graph.add_closure(closure(R2, 30, R1, 51)) is ClosureResult.ADDED
    wrong = closure(R2, 40, R1, 61)
    wrong = Closure(wrong.query_ns, wrong.place_ns, wrong.query_to_place.compose(
        gtsam.Pose3(gtsam.Rot3(), np.array([5.0, 0.0, 0.0]))), COVARIANCE, R2, R1)
    assert graph.add_closure(wrong) is ClosureResult.INCONSISTENT
    assert_on_truth(graph, R2, 1e-3)


def test_the_first_closure_between_the_robots_may_come_first_either_way_round() -> None:
    """No loop of either robot's own: the closure between them makes both graphs, r1's the anchor whichever robot
    is its query. (A closure names only its query's session as its robot's current one -- a place may be of any
    earlier run -- so the sessions are named first, as the posteriors of their first frames name them.)"""
    for query, query_index, place, place_index in ((R1, 31, R2, 10), (R2, 10, R1, 31)):
        graph = PoseGraph(PoseGraphConfig(), robot="r1")
        interleaved(graph, range(END + 1))
        assert graph.add_closure(closure(query, query_index, place, place_index)) is ClosureResult.UNKNOWN_SESSION
        graph.start_session(place)
        assert graph.add_closure(closure(query, query_index, place, place_index)) is ClosureResult.ADDED
        assert graph.anchor == R1 and graph.is_joined(*R2)
        assert graph.map_to_odom(*R2).equals(b_offset(), 1e-4)
        assert_on_truth(graph, R2, 1e-3)


def test_odometry_before_any_session_of_its_robot_is_named_goes_to_that_robots_first_session() -> None:
    graph = PoseGraph(PoseGraphConfig(), robot="r1")
    interleaved(graph, range(20))
    assert graph.sessions == {} and graph.current_session("r2") is None
    # r1's first session named: r1's early odometry only; r2's stays aside until a session of r2 is named.
    assert graph.add_closure(closure(R1, 15, R1, 2)) is ClosureResult.ADDED
    assert graph.sessions[R1].odometry.samples()[0] == [stamp(index) for index in range(20)]
    assert list(graph.sessions) == [R1] and graph.current_session("r2") is None
    graph.add_odometry(r2_stamp(20), b_odometry()[20], robot="r2")
    assert graph.add_closure(closure(R2, 18, R2, 3)) is ClosureResult.ADDED  # names r2's first session
    assert graph.sessions[R2].odometry.samples()[0] == [r2_stamp(index) for index in range(21)]
    assert graph.sessions[R1].odometry.last_ns == stamp(19)
    assert not graph.is_joined(*R2)


def test_a_closure_into_a_followed_robots_new_session_waits_for_its_odometry() -> None:
    """A base names its robots up front: a closure of a robot whose odometry has not come yet waits for it; one of
    a robot the graph does not follow names a session it will never have."""
    graph = PoseGraph(PoseGraphConfig(), robot="r1")
    graph.follow("r2")
    interleaved(graph, range(1))  # one sample each: no closure can be resolved yet
    graph.add_odometry(stamp(1), square_truth()[1], robot="r1")
    assert graph.add_closure(closure(R2, 12, R2, 3)) is ClosureResult.WAITING
    assert graph.add_closure(closure(("r3", 0), 12, R1, 0)) is ClosureResult.UNKNOWN_SESSION
    assert graph.current_session("r2") == R2 and graph.current_session("r3") is None
    assert interleaved(graph, range(1, 12)) == []  # r1's odometry does not resolve r2's closure
    assert graph.add_odometry(r2_stamp(12), b_odometry()[12], robot="r2") == [ClosureResult.ADDED]


def test_a_new_session_of_one_robot_moves_its_odometry_and_leaves_the_other_robots_alone() -> None:
    """r2 is relocated at its frame 6 (its odometry restarts; r1 drives on): r2's new session, named with the stamp
    of its first frame, takes r2's samples from then on; r1's session keeps all of its own. A closure waiting for
    r2's old session's odometry is dropped (it will not come); one waiting for r1's is not."""
    graph = PoseGraph(PoseGraphConfig(), robot="r1")
    graph.start_session(R1)
    graph.start_session(R2)
    step = gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0]))
    for index in range(9):
        graph.add_odometry(stamp(index), square_truth()[index], robot="r1")
        r2_pose = gtsam.Pose3(gtsam.Rot3(), np.array([float(index if index < 6 else index - 6), 0.0, 0.0]))
        graph.add_odometry(r2_stamp(index), r2_pose, robot="r2")
    waits_for_r1 = closure(R1, 12, R1, 2)
    waits_for_old_r2 = closure(R2, 12, R2, 2)
    assert graph.add_closure(waits_for_r1) is ClosureResult.WAITING
    assert graph.add_closure(waits_for_old_r2) is ClosureResult.WAITING
    graph.start_session(("r2", 1), first_stamp_ns=r2_stamp(6))
    assert graph.current_session("r2") == ("r2", 1) and graph.current == R1
    assert graph.sessions[R2].odometry.samples()[0] == [r2_stamp(index) for index in range(6)]
    stamps, poses, _ = graph.sessions[("r2", 1)].odometry.samples()
    assert stamps == [r2_stamp(index) for index in range(6, 9)]
    np.testing.assert_allclose(poses[0].translation(), [0.0, 0.0, 0.0], atol=1e-12)
    assert graph.sessions[R1].odometry.samples()[0] == [stamp(index) for index in range(9)]
    assert graph.counts["unknown_stamp"] == 1 and [closure for closure, _ in graph.decided] == [waits_for_old_r2]
    graph.add_odometry(r2_stamp(9), step, robot="r2")
    assert len(graph.sessions[("r2", 1)].odometry) == 4 and len(graph.sessions[R2].odometry) == 6
    results = [result for index in range(9, 13)
               for result in graph.add_odometry(stamp(index), square_truth()[index], robot="r1")]
    assert results == [ClosureResult.ADDED]


def test_two_robots_graph_saves_and_reloads_and_each_robot_goes_on(tmp_path: Path) -> None:
    """The graph file holds sessions whatever their robot: reloaded (only the backend restarted, both robots
    drive on), each robot's odometry continues its session once a closure names it again."""
    graph = PoseGraph(PoseGraphConfig(), robot="r1")
    interleaved(graph, range(41))
    for joined in (closure(R1, 40, R1, 2), closure(R2, 40, R2, 3), closure(R2, 10, R1, 31)):
        assert graph.add_closure(joined) is ClosureResult.ADDED
    path = tmp_path / "base.graph.npz"
    save_graph(graph, path)
    loaded = load_graph(path, PoseGraphConfig(), "r1")
    assert list(loaded.sessions) == [R1, R2] and loaded.anchor == R1 and loaded.is_joined(*R2)
    assert loaded.map_to_odom(*R2).equals(b_offset(), 1e-4)
    assert interleaved(loaded, range(41, END + 1)) == []  # no session named yet: kept aside per robot
    # Names R2 again (its odometry goes on there); its place is in what r1 saved (r1 not named again yet).
    assert loaded.add_closure(closure(R2, END, R1, 35)) is ClosureResult.ADDED
    assert loaded.sessions[R2].odometry.last_ns == r2_stamp(END) and loaded.current_session("r1") is None
    assert_on_truth(loaded, R2, 1e-3)
