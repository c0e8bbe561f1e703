"""pose_graph_node's drawing of its graph: the example backend's square loop, one true and one wrong closure."""

from __future__ import annotations

import numpy as np

from aefabmap_ros.backend.pose_graph import ClosureResult, PoseGraph, PoseGraphConfig
from aefabmap_ros.nodes.graph_view import drawing
from test.backend.test_pose_graph import closure, drifting_odometry, square_truth, stamp


def test_accepted_loops_join_keyframes_and_refused_ones_the_odometry_poses():
    truth = square_truth()
    odometry = drifting_odometry(truth)
    graph = PoseGraph(PoseGraphConfig())
    for index, pose in enumerate(odometry):
        graph.add_odometry(stamp(index), pose)
    last = len(truth) - 1
    graph.add_closure(closure(truth, last, 0))  # back at the start: true
    graph.add_closure(closure(truth, 30, 10, wrong_place=50))  # a pose the odometry cannot explain: refused
    drawn = drawing(graph, np.zeros((0, 3)))
    keyframes = {stamp_ns: np.asarray(pose.translation()) for stamp_ns, pose in graph.trajectory()}
    assert [result for _, result in graph.decided] == [ClosureResult.ADDED, ClosureResult.INCONSISTENT]
    assert [accepted for *_, accepted in drawn.loops] == [True, False]
    (start, end, _), (refused_start, refused_end, _) = drawn.loops
    np.testing.assert_allclose(start, keyframes[stamp(last)])
    np.testing.assert_allclose(end, keyframes[stamp(0)])
    # The refused loop's ends: the odometry poses of frames 30 and 10 in the map frame (map <- odom from the graph).
    map_to_odom = graph.map_to_odom()
    for point, index in ((refused_start, 30), (refused_end, 10)):
        np.testing.assert_allclose(point, map_to_odom.compose(odometry[index]).translation(), atol=1e-9)
    np.testing.assert_allclose(drawn.keyframes, np.array(list(keyframes.values())))
