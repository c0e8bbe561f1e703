"""What pose_graph_node shows of its graph besides the path: each robot's map -> odom, and the graph's markers,
drawn only while someone subscribes to ``pose_graph/markers``."""

from __future__ import annotations

import gtsam
import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from aefabmap_ros.backend.pose_graph import ClosureResult, PoseGraph, SessionId
from aefabmap_ros.nodes.common import RESULT_QOS, DropCounter
from aefabmap_ros.nodes.gtsam_poses import gtsam_to_pose
from aefabmap_ros.nodes.messages import time_from_ns
from aefabmap_ros.nodes.view_messages import marker_array
from aefabmap_ros.visualization.graph_markers import GraphDrawing, PathThinner, graph_markers

try:  # /tf needs tf2_msgs, which the PyPI ROS wheels used here do not ship
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None

MARKERS_TOPIC = "pose_graph/markers"
ODOMETRY_PATH_SPACING_M = 0.25
ROBOT_ODOM_FRAME = "{robot}/odom"  # each robot's odometry frame when several robots share the map


def session_frame(template: str, session_id: SessionId) -> str:
    """``session_odom_frame`` for a session: ``{robot}`` and ``{session}`` replaced."""
    return template.format(robot=session_id[0], session=session_id[1])


class MapToOdom:
    """map -> odom of each robot's current session, on ``/tf`` (``pose_graph/map_to_odom`` as TransformStamped
    without tf2_msgs), all robots' in one message.

    Its child frame: for one robot (``robots`` empty) ``odom_frame`` for the map's first session and
    ``session_odom_frame`` (or ``odom_frame``) for a later one; for several robots every session's is
    ``session_odom_frame``, by default ``{robot}/odom``, since each robot's odometry has a frame of its own. A
    session not joined to the map has no map frame: its transform is withheld, logged once per session and
    counted (``map_to_odom_unjoined``)."""

    def __init__(self, node: Node, counter: DropCounter, *, map_frame: str, odom_frame: str, session_odom_frame: str,
                 robots: list[str]) -> None:
        self.node, self.counter = node, counter
        self.map_frame, self.odom_frame, self.robots = map_frame, odom_frame, robots
        self.session_odom_frame = session_odom_frame or (ROBOT_ODOM_FRAME if robots else "")
        self.withheld: set[SessionId] = set()  # unjoined sessions whose map -> odom was withheld
        if TFMessage is not None:
            self.publisher = node.create_publisher(TFMessage, "/tf", RESULT_QOS)
        else:
            self.publisher = node.create_publisher(TransformStamped, "pose_graph/map_to_odom", RESULT_QOS)

    def publish(self, graph: PoseGraph, stamp_ns: int) -> None:
        transforms = [transform for robot in self.robots or [graph.robot]
                      if (transform := self.transform(graph, robot, stamp_ns)) is not None]
        if TFMessage is not None and transforms:
            self.publisher.publish(TFMessage(transforms=transforms))
        elif TFMessage is None:  # pragma: no cover - depends on the installation
            for transform in transforms:
                self.publisher.publish(transform)

    def transform(self, graph: PoseGraph, robot: str, stamp_ns: int) -> TransformStamped | None:
        """map -> odom of the robot's current session (the graph's own robot: else the anchor's); None before it
        has one, or while it is not joined to the map."""
        session_id = graph.current_session(robot)
        if session_id is None and robot == graph.robot:
            session_id = graph.anchor
        if session_id is None:
            return None
        if not graph.is_joined(*session_id):
            self.counter.ok("map_to_odom_unjoined")
            if session_id not in self.withheld:
                self.withheld.add(session_id)
                self.node.get_logger().info(
                    f"map -> odom of session {session_id[1]} of robot {session_id[0]!r} not published: no closure has "
                    "joined it to the map yet, so its map frame is undefined (its graph is optimised on its own)")
            return None
        transform = TransformStamped()
        transform.header.frame_id, transform.header.stamp = self.map_frame, time_from_ns(stamp_ns)
        transform.child_frame_id = (self.odom_frame if not self.session_odom_frame
                                    or (not self.robots and session_id == graph.anchor)
                                    else session_frame(self.session_odom_frame, session_id))
        pose = gtsam_to_pose(graph.map_to_odom(*session_id))
        transform.transform.translation.x = pose.position.x
        transform.transform.translation.y = pose.position.y
        transform.transform.translation.z = pose.position.z
        transform.transform.rotation = pose.orientation
        return transform


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
