import numpy as np

from aefabmap_ros.visualization.graph_markers import (
    ACCEPTED_LOOP_COLOUR,
    REFUSED_LOOP_COLOUR,
    GraphDrawing,
    PathThinner,
    Shape,
    graph_markers,
)


def test_a_hand_made_graph():
    keyframes = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0]], float)
    refused_from, refused_to = np.array([5, 5, 0]), np.array([0, 9, 0])
    drawing = GraphDrawing(keyframes=keyframes, odometry_path=np.array([[0, 0, 0], [1, 0, 0]], float),
                           loops=[(keyframes[2], keyframes[0], True), (refused_from, refused_to, False)])
    markers = {marker.namespace: marker for marker in graph_markers(drawing)}
    assert markers["keyframes"].shape is Shape.SPHERE_LIST
    np.testing.assert_array_equal(markers["keyframes"].points, keyframes)
    # Odometry edges between consecutive keyframes, as segment pairs: (k0, k1), (k1, k2).
    edges = markers["odometry_edges"]
    assert edges.shape is Shape.LINE_LIST
    np.testing.assert_array_equal(edges.points, keyframes[[0, 1, 1, 2]])
    loops = markers["loop_edges"]
    np.testing.assert_array_equal(loops.points, [keyframes[2], keyframes[0], refused_from, refused_to])
    np.testing.assert_array_equal(loops.colours, [ACCEPTED_LOOP_COLOUR] * 2 + [REFUSED_LOOP_COLOUR] * 2)
    np.testing.assert_array_equal(markers["trajectory_optimised"].points, keyframes)
    assert len(markers["trajectory_odometry"].points) == 2
    assert all(len(m.colours) == len(m.points) for m in markers.values())


def test_an_empty_graph_still_has_every_namespace_so_a_viewer_clears_them():
    markers = graph_markers(GraphDrawing())
    assert {m.namespace for m in markers} == {"keyframes", "odometry_edges", "loop_edges", "trajectory_odometry",
                                              "trajectory_optimised"}
    assert all(m.points.shape == (0, 3) for m in markers)


def test_path_thinner_keeps_points_spacing_apart():
    thinner = PathThinner(spacing_m=1.0)
    for x in np.arange(0, 5.01, 0.1):
        thinner.add(np.array([x, 0.0, 0.0]))
    np.testing.assert_allclose(thinner.points()[:, 0], [0, 1, 2, 3, 4, 5], atol=1e-9)
