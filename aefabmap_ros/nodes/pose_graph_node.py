"""pose_graph_node: an EXAMPLE SLAM backend on ``/loop_closures`` (the pattern to copy into your own).

Subscribes to odometry (``odom``, ``nav_msgs/Odometry``, strictly increasing stamps) and to
``loop_closures``; every closure with a relative pose adds a keyframe at each endpoint (odometry
interpolated at the image stamps) and a robust loop factor, and the graph is re-optimised with
iSAM2 (backend/pose_graph.py has the model). Publishes ``map -> odom`` after every added closure: on
``/tf`` when the ``tf2_msgs`` package is installed, else as a ``geometry_msgs/TransformStamped`` on
``pose_graph/map_to_odom`` (tf2_msgs has no PyPI wheel for this venv). The optimised keyframe trajectory
(``pose_graph/path``, ``nav_msgs/Path`` in ``map_frame``) and, while something subscribes to
``pose_graph/markers`` (``visualization_msgs/MarkerArray``), the graph (keyframes, odometry edges, loop
edges green when added and red when refused, the odometry path and the optimised one; nodes/graph_view.py)
go out at most every ``publish_period_s`` when the graph changed: each holds every keyframe, and
republished per closure at 10 closures a second they cost the node more than the graph itself. On
shutdown the keyframe trajectory is written in TUM format to ``trajectory_file`` (atomically; '' = not
written).

The closures' poses are between camera frames, odometry is of its child (base) frame: parameter
``base_to_camera`` ([x, y, z, qx, qy, qz, qw], the camera's pose in the base frame, T_base_camera;
identity by default, for a camera that is the odometry's child frame) turns each closure into one
between the two base poses (backend/pose_graph.py ``closure_in_base_frame``).
Bad input is counted and dropped: odometry out of order, odometry with an unusable stamp or pose
(``bad_odometry``: NaN, a quaternion whose norm is not 1, io/message_values.py), a closure without a
pose, one with an unusable pose or covariance (``bad_closure_pose``) or stamp (``bad_closure_stamp``),
a closure to a stamp the odometry never covered, a closure the odometry drift cannot explain, one the
solver cannot take (``solver_failed``). Any other exception a message causes is counted by its type
and dropped (``node_callback``): no message stops the node. Exit code 1 when the trajectory file
cannot be written at shutdown.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from aefabmap_msgs.msg import LoopClosure
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMessage
from rclpy.node import Node

from aefabmap_ros.backend.odometry import closure_in_base_frame
from aefabmap_ros.backend.pose_graph import Closure, ClosureResult, PoseGraph, PoseGraphConfig, trajectory_arrays
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io.atomic import atomic_write_text
from aefabmap_ros.nodes.common import (
    ODOMETRY_QOS,
    RESULT_QOS,
    DropCounter,
    declare_config,
    declare_parameter,
    node_callback,
    run_node,
)
from aefabmap_ros.nodes.future_stamps import FutureStamps
from aefabmap_ros.nodes.graph_view import GraphView
from aefabmap_ros.nodes.gtsam_poses import (
    extrinsic_to_gtsam,
    gtsam_to_pose,
    gtsam_to_poses,
    loop_closure_pose,
    pose_to_gtsam,
)
from aefabmap_ros.nodes.messages import (
    loop_closure_pose_problem,
    loop_closure_stamp_problem,
    odometry_problem,
    time_from_ns,
)
from aefabmap_ros.nodes.sensor_inputs import SensorInput, check_sensor_qos
from aefabmap_ros.stamps import stamp_to_ns

try:  # /tf needs tf2_msgs, which the PyPI ROS wheels used here do not ship
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None

_DROPPED = {ClosureResult.UNKNOWN_STAMP, ClosureResult.BAD_COVARIANCE, ClosureResult.INCONSISTENT,
            ClosureResult.NO_POSE, ClosureResult.SOLVER_FAILED}


class PoseGraphNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("pose_graph_node", **node_kwargs)
        self.map_frame = declare_parameter(self, "map_frame", "map", "Frame of the optimised trajectory.")
        self.odom_frame = declare_parameter(self, "odom_frame", "odom", "Odometry's fixed frame (map -> odom).")
        trajectory_file = declare_parameter(
            self, "trajectory_file", "", "TUM file the keyframe trajectory is written to on shutdown ('' = none).")
        self.trajectory_file = Path(trajectory_file) if trajectory_file else None
        self.base_to_camera = extrinsic_to_gtsam(declare_parameter(
            self, "base_to_camera", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            "The camera's pose in the odometry's child (base) frame, [x, y, z, qx, qy, qz, qw] (identity: the "
            "camera is the base frame)."))
        publish_period_s = float(declare_parameter(
            self, "publish_period_s", 1.0, "The path and the graph's markers are republished at most this often, "
            "when the graph changed (seconds, > 0; map -> odom goes out on every added closure)."))
        if not publish_period_s > 0:
            raise ConfigError(f"pose_graph_node: publish_period_s must be > 0, got {publish_period_s}")
        self.graph = PoseGraph(declare_config(self, PoseGraphConfig))
        self.future_stamps = FutureStamps(self)
        self.counter = DropCounter(self)
        self.path_publisher = self.create_publisher(PathMessage, "pose_graph/path", RESULT_QOS)
        self.graph_view = GraphView(self, self.map_frame)
        if TFMessage is not None:
            self.tf_publisher = self.create_publisher(TFMessage, "/tf", RESULT_QOS)
        else:
            self.tf_publisher = self.create_publisher(TransformStamped, "pose_graph/map_to_odom", RESULT_QOS)
        sensor_qos = check_sensor_qos(declare_parameter(
            self, "sensor_qos", "auto",
            "QoS of the odom subscription: auto (reliable, moving to best effort once a publisher offers only that, "
            "as drivers often do), best_effort (= sensor_data) or reliable.",
        ), "sensor_qos")
        self.odometry = SensorInput(self, Odometry, "odom", self._on_odometry, policy=sensor_qos,
                                    depth=ODOMETRY_QOS.depth, counter=self.counter,
                                    without_it="no keyframes: the graph is built on odometry")
        self.create_subscription(LoopClosure, "loop_closures", self._on_loop_closure, RESULT_QOS)
        self._path_changed_ns: int | None = None  # stamp of the newest change not published yet
        self._markers_changed_ns: int | None = None
        self.create_timer(publish_period_s, self.publish_changes)
        self.get_logger().info("pose graph (example backend): odometry on odom, closures on loop_closures")

    @node_callback
    def _on_odometry(self, message: Odometry) -> None:
        problem = odometry_problem(message)
        if problem is not None:
            self.counter.drop("bad_odometry", problem)
            return
        problem = self.future_stamps.problem(stamp_to_ns(message.header.stamp))
        if problem is not None:  # it would make every later odometry message "out of order"
            self.counter.drop("stamp_in_future", f"odometry {problem}")
            return
        before = self.graph.counts["odometry_out_of_order"]
        pose = pose_to_gtsam(message.pose.pose)
        results = self.graph.add_odometry(stamp_to_ns(message.header.stamp), pose)
        if self.graph.counts["odometry_out_of_order"] > before:
            self.counter.drop("odometry_out_of_order", "odometry stamp not after the previous one")
        else:
            self.graph_view.on_odometry(pose)
        self._report(results, stamp_to_ns(message.header.stamp))

    @node_callback
    def _on_loop_closure(self, message: LoopClosure) -> None:
        if not message.pose_available:
            self.counter.drop(ClosureResult.NO_POSE.value, f"closure of query {message.query_id} has no pose "
                              f"(pose_status {message.pose_status})")
            return
        problem = loop_closure_stamp_problem(message)
        if problem is not None:
            self.counter.drop("bad_closure_stamp", f"closure of query {message.query_id}: {problem}")
            return
        newest_ns = max(stamp_to_ns(message.header.stamp), stamp_to_ns(message.matched_stamp))
        problem = self.future_stamps.problem(newest_ns)
        if problem is not None:  # it would wait for odometry that never comes, and push out the closures waiting
            self.counter.drop("stamp_in_future", f"closure of query {message.query_id}: {problem}")
            return
        problem = loop_closure_pose_problem(message)
        if problem is not None:
            self.counter.drop("bad_closure_pose", f"closure of query {message.query_id}: {problem}")
            return
        pose, covariance = closure_in_base_frame(*loop_closure_pose(message), self.base_to_camera)
        closure = Closure(stamp_to_ns(message.header.stamp), stamp_to_ns(message.matched_stamp), pose, covariance)
        self._report([self.graph.add_closure(closure)], closure.query_ns)

    def _report(self, results: list[ClosureResult], stamp_ns: int) -> None:
        for result in results:
            if result is ClosureResult.SOLVER_FAILED:
                self.counter.drop(result.value, f"loop closure near stamp {stamp_ns} dropped: iSAM2 could not take "
                                  f"it ({self.graph.solver_error})")
            elif result in _DROPPED:
                self.counter.drop(result.value, f"loop closure near stamp {stamp_ns} dropped: {result.value}")
            else:
                self.counter.ok(result.value)
        if ClosureResult.ADDED in results:
            self._publish_map_to_odom(stamp_ns)
            self._path_changed_ns = stamp_ns
        if any(result is not ClosureResult.WAITING for result in results):  # a loop edge to draw
            self._markers_changed_ns = stamp_ns

    @node_callback
    def publish_changes(self) -> None:
        """The path and the markers, if the graph changed since they were last published (the timer's)."""
        if self._path_changed_ns is not None:
            self._publish_path(self._path_changed_ns)
            self._path_changed_ns = None
        if self._markers_changed_ns is not None:
            self.graph_view.publish_if_watched(self.graph, self._markers_changed_ns)
            self._markers_changed_ns = None

    def _publish_path(self, stamp_ns: int) -> None:
        path = PathMessage()
        path.header.frame_id, path.header.stamp = self.map_frame, time_from_ns(stamp_ns)
        trajectory = self.graph.trajectory()
        for (keyframe_ns, _), pose in zip(trajectory, gtsam_to_poses([pose for _, pose in trajectory]), strict=True):
            entry = PoseStamped(pose=pose)
            entry.header.frame_id, entry.header.stamp = self.map_frame, time_from_ns(keyframe_ns)
            path.poses.append(entry)
        self.path_publisher.publish(path)

    def _publish_map_to_odom(self, stamp_ns: int) -> None:
        transform = TransformStamped()
        transform.header.frame_id, transform.header.stamp = self.map_frame, time_from_ns(stamp_ns)
        transform.child_frame_id = self.odom_frame
        pose = gtsam_to_pose(self.graph.map_to_odom())
        transform.transform.translation.x = pose.position.x
        transform.transform.translation.y = pose.position.y
        transform.transform.translation.z = pose.position.z
        transform.transform.rotation = pose.orientation
        self.tf_publisher.publish(TFMessage(transforms=[transform]) if TFMessage is not None else transform)

    def close(self) -> bool:
        """Write the keyframe trajectory; False (the process then exits 1) when it cannot be written."""
        saved = True
        if self.trajectory_file is not None:
            from aefabmap_ros.evaluation.trajectory_error import tum_text  # evo: loaded at shutdown only

            stamps_s, poses = trajectory_arrays(self.graph.trajectory())
            try:
                atomic_write_text(self.trajectory_file, tum_text(stamps_s, poses))
                self.get_logger().info(f"wrote {len(stamps_s)} keyframes to {self.trajectory_file}")
            except OSError as exc:
                saved = False
                self.get_logger().error(f"FINAL SAVE FAILED: the keyframe trajectory not written to "
                                        f"{self.trajectory_file} ({type(exc).__name__}: {exc})")
        self.get_logger().info(f"pose_graph_node: {len(self.graph.keyframes)} keyframes; {self.counter.summary()}; "
                               f"{self.odometry.summary()}")
        return saved


def main(args: list[str] | None = None) -> int:
    return run_node(PoseGraphNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
