"""pose_graph_node's markers: the graph drawn only while someone subscribes to ``pose_graph/markers``."""

from __future__ import annotations

import gtsam
import numpy as np
from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from aefabmap_ros.backend.pose_graph import ClosureResult, PoseGraph
from aefabmap_ros.nodes.common import RESULT_QOS
from aefabmap_ros.nodes.messages import time_from_ns
from aefabmap_ros.nodes.view_messages import marker_array
from aefabmap_ros.visualization.graph_markers import GraphDrawing, PathThinner, graph_markers

MARKERS_TOPIC = "pose_graph/markers"
ODOMETRY_PATH_SPACING_M = 0.25


class GraphView:
    """Keeps a thinned odometry path (cheap) and draws the graph when published to a subscriber."""

    def __init__(self, node: Node, map_frame: str) -> None:
        self.map_frame = map_frame
        self.publisher = node.create_publisher(MarkerArray, MARKERS_TOPIC, RESULT_QOS)
        self.odometry_path = PathThinner(ODOMETRY_PATH_SPACING_M)

    def on_odometry(self, pose: gtsam.Pose3) -> None:
        self.odometry_path.add(np.asarray(pose.translation(), np.float64))

    def publish_if_watched(self, graph: PoseGraph, stamp_ns: int) -> bool:
        if self.publisher.get_subscription_count() == 0:
            return False
        self.publisher.publish(marker_array(graph_markers(drawing(graph, self.odometry_path.points())),
                                            self.map_frame, time_from_ns(stamp_ns)))
        return True


def drawing(graph: PoseGraph, odometry_path: np.ndarray) -> GraphDrawing:
    """The graph in the map frame: accepted loops between their optimised keyframes, refused ones between the
    odometry poses at their stamps (map <- odom of their sessions as the graph has it now; they never became
    keyframes). A loop with an end in a session not joined to the map (its frame is not the map's) is left out."""
    trajectory = graph.trajectory()
    positions = np.array([pose.translation() for _, pose in trajectory], np.float64).reshape(-1, 3)
    loops = []
    for closure, result in graph.decided:
        accepted = result is ClosureResult.ADDED
        locate = graph.keyframe_in_map if accepted else graph.odometry_in_map
        start, end = locate(closure.query_session, closure.query_ns), locate(closure.place_session, closure.place_ns)
        if start is not None and end is not None:
            loops.append((np.asarray(start.translation(), np.float64), np.asarray(end.translation(), np.float64),
                          accepted))
    return GraphDrawing(keyframes=positions, odometry_path=odometry_path, loops=loops)
