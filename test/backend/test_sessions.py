"""Two runs on one map: session B's odometry restarted at the identity, a known rigid offset from session A's.

Ground truth: A drives the square loop of test_pose_graph from the origin, its odometry exact, so A's odometry
frame is the map frame. B drives the same square, started at A's first corner and 0.3 m to the side:
B's odometry is T_offset^-1 * truth_B with T_offset = truth_B[0], so it starts at the identity. A closure
from B to A carries the true relative pose; after it, B's keyframes in the map frame must be B's truth and
B's map -> odom must be T_offset.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.pose_graph import (
    Closure,
    ClosureResult,
    FactorKind,
    PoseGraph,
    PoseGraphConfig,
    SessionId,
)
from test.backend.test_pose_graph import SIDE_STEPS, square_truth, stamp

A: SessionId = ("", 0)
B: SessionId = ("", 1)
B_START_NS = 10_000 * 1_000_000_000  # B runs later: its stamps are after A's
SECOND = 1_000_000_000
COVARIANCE = np.diag([0.02**2] * 3 + [0.005**2] * 3)


def b_stamp(index: int) -> int:
    return B_START_NS + stamp(index)


def b_truth() -> list[gtsam.Pose3]:
    """B's path: A's square from its first corner on (90 degrees turned), 0.3 m to the side, one lap."""
    side = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.3, 0.0]))
    square = square_truth()
    laps = square[SIDE_STEPS:-1] + square[:SIDE_STEPS + 1]
    return [pose.compose(side) for pose in laps]


def b_offset() -> gtsam.Pose3:
    """T_map_odomB: where B's odometry frame lies in the map (B's first true pose)."""
    return b_truth()[0]


def b_odometry() -> list[gtsam.Pose3]:
    offset_inverse = b_offset().inverse()
    return [offset_inverse.compose(pose) for pose in b_truth()]


def a_graph() -> PoseGraph:
    """Session A's odometry and one closure in it (the end of the loop back to the start)."""
    truth = square_truth()
    graph = PoseGraph(PoseGraphConfig())
    for index, pose in enumerate(truth):
        graph.add_odometry(stamp(index), pose)
    end = len(truth) - 1
    assert graph.add_closure(Closure(stamp(end), stamp(0), truth[end].between(truth[0]), COVARIANCE)) \
        is ClosureResult.ADDED
    return graph


def b_to_a(b_index: int, a_index: int, place: gtsam.Pose3 | None = None) -> Closure:
    """B's frame ``b_index`` sees A's frame ``a_index`` (its true pose, or ``place`` instead)."""
    target = square_truth()[a_index] if place is None else place
    return Closure(b_stamp(b_index), stamp(a_index), b_truth()[b_index].between(target), COVARIANCE,
                   query_session=B, place_session=A)


def feed_b(graph: PoseGraph) -> list[ClosureResult]:
    results = []
    for index, pose in enumerate(b_odometry()):
        results += graph.add_odometry(b_stamp(index), pose)
    return results


def assert_b_on_its_truth(graph: PoseGraph, tolerance_m: float) -> None:
    truth = b_truth()
    keyframes = graph.session_trajectory(*B)
    assert keyframes
    for stamp_ns, pose in keyframes:
        index = (stamp_ns - B_START_NS) // 1_000_000_000 - 1
        assert np.linalg.norm(pose.translation() - truth[index].translation()) < tolerance_m
        assert np.linalg.norm(gtsam.Rot3.Logmap(pose.rotation().between(truth[index].rotation()))) < 1e-4


def test_the_first_closure_into_an_earlier_session_puts_the_new_one_on_the_map() -> None:
    graph = a_graph()
    graph.start_session(B)
    assert feed_b(graph) == []
    assert graph.odometry.first_ns == b_stamp(0) and graph.sessions[A].odometry.last_ns == stamp(len(b_truth()) - 1)
    # B's frame 10 sees A's frame 31 (near it on the square's second side): the join, on the verifier's word.
    assert graph.add_closure(b_to_a(10, 31)) is ClosureResult.ADDED
    assert graph.is_joined(*A) and graph.is_joined(*B)
    assert_b_on_its_truth(graph, 1e-3)
    assert graph.map_to_odom(*B).equals(b_offset(), 1e-4)
    assert graph.map_to_odom(*A).equals(gtsam.Pose3(), 1e-6)  # A's odometry is exact: map == odom
    assert graph.map_to_odom().equals(b_offset(), 1e-4)  # the current session's
    # The map trajectory holds both sessions, by stamp.
    stamps = [stamp_ns for stamp_ns, _ in graph.trajectory()]
    assert stamps == sorted(stamps) and stamps[0] == stamp(0) and stamps[-1] == b_stamp(10)


def test_a_later_closure_between_joined_sessions_is_gated_against_the_graph() -> None:
    graph = a_graph()
    graph.start_session(B)
    feed_b(graph)
    assert graph.add_closure(b_to_a(10, 31)) is ClosureResult.ADDED
    # 20 m further on B: a true closure agrees with the joined graph; one whose place is 5 m off does not
    # (drift over the 20 m since the join explains ~0.4 m).
    assert graph.add_closure(b_to_a(30, 51)) is ClosureResult.ADDED
    off = square_truth()[51].compose(gtsam.Pose3(gtsam.Rot3(), np.array([5.0, 0.0, 0.0])))
    assert graph.add_closure(b_to_a(40, 61, place=off)) is ClosureResult.INCONSISTENT
    assert graph.counts["inconsistent_with_odometry"] == 1
    assert_b_on_its_truth(graph, 1e-3)


def test_a_new_session_is_a_graph_of_its_own_until_a_closure_joins_it() -> None:
    """B closes a loop of its own first (its closure waits for B's odometry, which restarts at the identity):
    both sessions have trajectories, B's in its own odometry frame and not on the map. The join then moves B's
    keyframes (already in iSAM2) onto the map."""
    graph = a_graph()
    odometry = b_odometry()
    end = len(odometry) - 1
    own_loop = Closure(b_stamp(end), b_stamp(0), b_truth()[end].between(b_truth()[0]), COVARIANCE,
                       query_session=B, place_session=B)
    assert graph.add_closure(own_loop) is ClosureResult.WAITING  # B named: the current session, no odometry yet
    assert graph.current == B
    assert feed_b(graph) == [ClosureResult.ADDED]
    assert graph.is_joined(*A) and not graph.is_joined(*B)
    assert [stamp_ns for stamp_ns, _ in graph.trajectory()] == [stamp(0), stamp(len(square_truth()) - 1)]
    own = dict(graph.session_trajectory(*B))
    assert sorted(own) == [b_stamp(0), b_stamp(end)]
    for stamp_ns, pose in own.items():  # held at its own odometry: map -> odom is the identity until joined
        index = (stamp_ns - B_START_NS) // 1_000_000_000 - 1
        assert pose.equals(odometry[index], 1e-6)
    assert graph.map_to_odom(*B).equals(gtsam.Pose3(), 1e-6)

    assert graph.add_closure(b_to_a(10, 31)) is ClosureResult.ADDED
    assert graph.is_joined(*B) and len(graph.session_trajectory(*B)) == 3
    assert_b_on_its_truth(graph, 1e-3)
    assert graph.map_to_odom(*B).equals(b_offset(), 1e-4)
    assert len(graph.trajectory()) == 6  # A's 3 keyframes (one made at the place) and B's 3
    # B's prior is gone: A's holds the whole graph, and the closure alone places B.
    assert [record.kind for record in graph.factors.values()].count(FactorKind.PRIOR) == 1
    assert graph.add_closure(b_to_a(30, 51)) is ClosureResult.ADDED  # the joined graph goes on


def test_a_closure_into_a_session_never_seen_is_counted_by_name() -> None:
    graph = a_graph()
    before = graph.trajectory()
    unknown = Closure(stamp(40), stamp(10), gtsam.Pose3(), COVARIANCE, query_session=A, place_session=("", 7))
    assert graph.add_closure(unknown) is ClosureResult.UNKNOWN_SESSION
    other_robot = Closure(stamp(40), stamp(10), gtsam.Pose3(), COVARIANCE, query_session=("rover", 0),
                          place_session=A)
    assert graph.add_closure(other_robot) is ClosureResult.UNKNOWN_SESSION
    assert graph.counts["unknown_session"] == 2 and graph.current == A  # another robot's query names no session here
    assert [(s, p.translation().tolist()) for s, p in graph.trajectory()] == \
        [(s, p.translation().tolist()) for s, p in before]


def test_odometry_before_the_first_closure_belongs_to_the_session_it_names() -> None:
    """A restarted backend cannot know the session its odometry is of until a closure names it."""
    graph = PoseGraph(PoseGraphConfig())
    for index, pose in enumerate(b_odometry()[:20]):
        graph.add_odometry(b_stamp(index), pose)
    assert graph.current is None and graph.sessions == {} and len(graph.odometry) == 20
    closure = Closure(b_stamp(15), b_stamp(2), b_odometry()[15].between(b_odometry()[2]), COVARIANCE,
                      query_session=B, place_session=B)
    assert graph.add_closure(closure) is ClosureResult.ADDED
    assert graph.current == B and graph.sessions[B].odometry.first_ns == b_stamp(0)
    assert graph.is_joined(*B)  # the first session given keyframes is the map's anchor


@pytest.mark.parametrize("wrong_robot", [False, True])
def test_an_older_or_foreign_query_session_does_not_take_the_odometry(wrong_robot: bool) -> None:
    graph = PoseGraph(PoseGraphConfig(), robot="rover")
    graph.start_session(("rover", 3))
    named: SessionId = ("other", 5) if wrong_robot else ("rover", 2)
    closure = Closure(stamp(5), stamp(1), gtsam.Pose3(), COVARIANCE, query_session=named, place_session=named)
    assert graph.add_closure(closure) is ClosureResult.UNKNOWN_SESSION
    assert graph.current == ("rover", 3)


def test_a_session_named_with_its_first_stamp_takes_the_odometry_from_then_on() -> None:
    """A robot relocated while the backend ran: odometry restarts at the identity at the new session's first
    frame. Named with that stamp, the new session takes exactly the samples from it on; the old keeps the rest."""
    graph = PoseGraph(PoseGraphConfig())
    graph.start_session(("", 0))
    for second in range(1, 6):  # session 0 drives along x
        graph.add_odometry(second * SECOND, gtsam.Pose3(gtsam.Rot3(), np.array([float(second), 0.0, 0.0])))
    for second in range(6, 9):  # relocated: odometry restarted, session 1 not named yet
        graph.add_odometry(second * SECOND, gtsam.Pose3(gtsam.Rot3(), np.array([float(second - 6), 0.0, 0.0])))
    graph.start_session(("", 1), first_stamp_ns=6 * SECOND)
    old_stamps, _, _ = graph.sessions[("", 0)].odometry.samples()
    new_stamps, new_poses, _ = graph.sessions[("", 1)].odometry.samples()
    assert old_stamps == [second * SECOND for second in range(1, 6)]
    assert new_stamps == [second * SECOND for second in range(6, 9)]
    np.testing.assert_allclose(new_poses[0].translation(), [0.0, 0.0, 0.0], atol=1e-12)
    graph.add_odometry(9 * SECOND, gtsam.Pose3(gtsam.Rot3(), np.array([3.0, 0.0, 0.0])))
    assert len(graph.sessions[("", 1)].odometry) == 4
