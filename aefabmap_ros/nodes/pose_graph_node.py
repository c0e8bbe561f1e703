"""pose_graph_node: an EXAMPLE SLAM backend on ``/loop_closures`` (the pattern to copy into your own).

Subscribes to odometry (``odom``, ``nav_msgs/Odometry``, strictly increasing stamps per robot) and to
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
written): every session joined to the map, by stamp; a session not joined yet to
``<stem>.session<k><suffix>`` beside it (``<stem>.<robot>.session<k><suffix>`` for a named robot), in its own
graph's frame.

Several sessions (backend/pose_graph.py has the model). Closures name each endpoint's (robot, session); this
node's odometry is of robot ``robot`` (parameter, '' = the map's only robot) and belongs to the newest session
named for it: on ``place_posteriors`` from the session's first frame on (odometry stamped from then on moves to
it), or by a closure's query. A closure into a session the backend never saw (no odometry, not in ``graph_file``) is
counted as ``unknown_session`` and logged with the robot and session it names. ``map -> odom`` is the current
session's: as ``map_frame -> odom_frame`` for the map's first session, and for a later one as ``map_frame ->
session_odom_frame`` ('' = ``odom_frame``; ``{robot}`` and ``{session}`` in it are replaced); not published
while the current session is not joined to the map (its map frame is undefined: logged once per session,
counted as ``map_to_odom_unjoined``; nodes/graph_view.py). With ``graph_file`` set the graph (sessions,
keyframes, odometry, factors; backend/graph_file.py) is reloaded at start -- a file that cannot be used stops the
node with one error naming it, and is left as it was -- and saved atomically on shutdown and every
``save_period_s`` when it changed.

Several robots (a base station, docs/fleet.md): with ``robots`` each robot's odometry comes on
``/<robot>/aefabmap/odom`` (as its feature server thins it; ``odom`` is not subscribed) and goes to that robot's
newest session, named by its posteriors or a closure's query; ``robot`` is the first of them unless it is one of
them, and its first session is the map's anchor. Another robot's sessions are graphs of their own until a closure
joins them to the map. ``map -> odom`` goes out for every robot's current joined session, all in one message,
each as ``map_frame -> session_odom_frame`` ('' = ``{robot}/odom``: each robot's odometry has its own frame);
``trajectory_file`` holds every robot's joined sessions in the one map frame, the markers' odometry path is
``robot``'s.

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
or the graph cannot be written at shutdown.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

from aefabmap_msgs.msg import LoopClosure, PlacePosterior
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMessage
from rclpy.node import Node

from aefabmap_ros.backend.graph_file import load_graph, save_graph
from aefabmap_ros.backend.odometry import closure_in_base_frame
from aefabmap_ros.backend.pose_graph import (
    Closure,
    ClosureResult,
    PoseGraph,
    PoseGraphConfig,
    SessionId,
    trajectory_arrays,
)
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io.atomic import atomic_write_text, remove_stale_temporaries
from aefabmap_ros.nodes.common import (
    ODOMETRY_QOS,
    RESULT_QOS,
    DropCounter,
    PeriodicSave,
    declare_config,
    declare_parameter,
    node_callback,
    run_node,
)
from aefabmap_ros.nodes.fleet_parameters import declare_robots as declare_fleet_robots
from aefabmap_ros.nodes.fleet_parameters import robot_topic
from aefabmap_ros.nodes.future_stamps import FutureStamps
from aefabmap_ros.nodes.graph_view import GraphView, MapToOdom, session_frame
from aefabmap_ros.nodes.gtsam_poses import extrinsic_to_gtsam, gtsam_to_poses, loop_closure_pose, pose_to_gtsam
from aefabmap_ros.nodes.messages import (
    header_stamp_problem,
    loop_closure_pose_problem,
    loop_closure_stamp_problem,
    odometry_problem,
    time_from_ns,
)
from aefabmap_ros.nodes.sensor_inputs import SensorInput, check_sensor_qos
from aefabmap_ros.stamps import stamp_to_ns

ROBOT_ODOMETRY_TOPIC = "aefabmap/odom"  # a robot's odometry on a base station, as its feature server thins it
_DROPPED = {ClosureResult.UNKNOWN_STAMP, ClosureResult.UNKNOWN_SESSION, ClosureResult.BAD_COVARIANCE,
            ClosureResult.INCONSISTENT, ClosureResult.NO_POSE, ClosureResult.SOLVER_FAILED}


def session_trajectory_path(trajectory_file: Path, session_id: SessionId) -> Path:
    """Where a session not joined to the map has its keyframes written: beside ``trajectory_file``, named by
    the session (and its robot, when named)."""
    robot, number = session_id
    robot_part = f".{robot}" if robot else ""
    return trajectory_file.with_name(f"{trajectory_file.stem}{robot_part}.session{number}{trajectory_file.suffix}")


def declare_robots(node: Node) -> list[str]:
    """Parameter ``robots``: the robots whose odometry this node takes."""
    return declare_fleet_robots(node, "Robots whose odometry this node takes, each on /<robot>/aefabmap/odom as "
                                "its feature server thins it (a base station, docs/fleet.md); [] = one robot, robot, "
                                "on odom.")


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
        self.robots = declare_robots(self)
        robot = str(declare_parameter(
            self, "robot", "", "The robot whose odometry this node receives ('' = the map's only robot): its newest "
            "query session in the closures is the session the odometry belongs to. With robots, the one whose "
            "first session is the map's anchor (the first of robots unless it is one of them)."))
        self.robot = robot if not self.robots or robot in self.robots else self.robots[0]
        session_odom_frame = str(declare_parameter(
            self, "session_odom_frame", "", "Odometry frame of a session other than the map's first, the child of "
            "its map -> odom ('' = odom_frame; {robot} and {session} are replaced, e.g. odom_{session}). With "
            "robots, every session's ('' = {robot}/odom)."))
        try:
            session_frame(session_odom_frame, ("", 0))
        except (KeyError, IndexError, ValueError) as exc:
            raise ConfigError(f"pose_graph_node: session_odom_frame {session_odom_frame!r} is not a frame "
                              f"name with {{robot}} / {{session}} fields: {exc}") from exc
        self.graph = self._graph_from_file(declare_config(self, PoseGraphConfig))
        self.future_stamps = FutureStamps(self)
        self.counter = DropCounter(self)
        self.path_publisher = self.create_publisher(PathMessage, "pose_graph/path", RESULT_QOS)
        self.graph_view = GraphView(self, self.map_frame)
        self.map_to_odom = MapToOdom(self, self.counter, map_frame=self.map_frame, odom_frame=self.odom_frame,
                                     session_odom_frame=session_odom_frame, robots=self.robots)
        self.tf_publisher = self.map_to_odom.publisher
        self.odometry_inputs = self._subscribe_odometry()
        self.odometry = self.odometry_inputs[0]
        self.create_subscription(LoopClosure, "loop_closures", self._on_loop_closure, RESULT_QOS)
        # fabmap_node answers every frame with its session: the backend learns a new session of its robot (a
        # relocation while it ran) at its first frame, not at its first closure, so no odometry goes astray.
        self.create_subscription(PlacePosterior, "place_posteriors", self._on_posterior, RESULT_QOS)
        self._path_changed_ns: int | None = None  # stamp of the newest change not published yet
        self._markers_changed_ns: int | None = None
        self.create_timer(publish_period_s, self.publish_changes)
        self.get_logger().info(f"pose graph (example backend): odometry on "
                               f"{', '.join(odometry.topic for odometry in self.odometry_inputs)}, closures on "
                               "loop_closures")

    def _subscribe_odometry(self) -> list[SensorInput]:
        """``odom`` for ``robot``; with ``robots``, each robot's as its feature server thins it."""
        sensor_qos = check_sensor_qos(declare_parameter(
            self, "sensor_qos", "auto",
            "QoS of the odom subscriptions: auto (reliable, moving to best effort once a publisher offers only "
            "that, as drivers often do), best_effort (= sensor_data) or reliable.",
        ), "sensor_qos")
        topics = {robot: robot_topic(robot, ROBOT_ODOMETRY_TOPIC) for robot in self.robots} or {self.robot: "odom"}
        return [SensorInput(self, Odometry, topic, partial(self._on_odometry, robot=robot), policy=sensor_qos,
                            depth=ODOMETRY_QOS.depth, counter=self.counter,
                            without_it=f"no keyframes of {robot or 'the robot'}: the graph is built on odometry")
                for robot, topic in topics.items()]

    def _graph_from_file(self, config: PoseGraphConfig) -> PoseGraph:
        """The graph saved at parameter ``graph_file`` (a fresh one without it), and its periodic save."""
        graph_file = str(declare_parameter(
            self, "graph_file", "", "The graph's file (.npz): reloaded at start, saved on shutdown and every "
            "save_period_s when changed ('' = none: the graph lives as long as the node)."))
        save_period_s = float(declare_parameter(
            self, "save_period_s", 10.0, "Save the graph this often when it changed (seconds; 0 = only on shutdown)."))
        if not save_period_s >= 0:
            raise ConfigError(f"pose_graph_node: save_period_s must be >= 0, got {save_period_s}")
        graph_path = Path(graph_file) if graph_file else None
        graph = PoseGraph(config, self.robot)
        if graph_path is not None:
            for leftover in remove_stale_temporaries(graph_path.parent, graph_path.name):
                self.get_logger().warning(f"deleted {leftover}, left by a save that was killed")
            if graph_path.exists():
                graph = load_graph(graph_path, config, self.robot)
                self.get_logger().info(f"reloaded {len(graph.sessions)} session(s), {len(graph.keyframes)} "
                                       f"keyframes from {graph_path}")
        for robot in self.robots:  # a closure into a robot's new session waits for its odometry
            graph.follow(robot)
        self.graph_saver = PeriodicSave(self, graph_path, lambda path: save_graph(self.graph, path), "pose graph",
                                        save_period_s)
        return graph

    @node_callback
    def _on_odometry(self, message: Odometry, robot: str | None = None) -> None:
        """One odometry message of ``robot`` (default: the node's ``robot``)."""
        robot = self.robot if robot is None else robot
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
        results = self.graph.add_odometry(stamp_to_ns(message.header.stamp), pose, robot)
        if self.graph.counts["odometry_out_of_order"] > before:
            self.counter.drop("odometry_out_of_order", f"odometry of {robot or 'the robot'} stamp not after the "
                              "previous one")
        else:
            if robot == self.robot:  # the markers' odometry path: the map's first robot's, in its odom frame
                self.graph_view.on_odometry(pose)
            self.graph_saver.mark_changed()
        self._report(results, stamp_to_ns(message.header.stamp))

    @node_callback
    def _on_posterior(self, message: PlacePosterior) -> None:
        current = self.graph.current_session(message.robot)
        if message.query_id < 0 or message.robot not in (self.robots or [self.robot]) or (
                current is not None and int(message.session) <= current[1]):
            return
        problem = header_stamp_problem(message.header, "PlacePosterior")
        if problem is not None:
            self.counter.drop("bad_posterior", problem)
            return
        session = (message.robot, int(message.session))
        self.graph.start_session(session, stamp_to_ns(message.header.stamp) if current is not None else None)
        self.get_logger().info(f"session {session[1]} of robot {session[0]!r} started at "
                               f"{stamp_to_ns(message.header.stamp) / 1e9:.3f} s")
        self.graph_saver.mark_changed()

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
        closure = Closure(stamp_to_ns(message.header.stamp), stamp_to_ns(message.matched_stamp), pose, covariance,
                          query_session=(message.query_robot, int(message.query_session)),
                          place_session=(message.matched_robot, int(message.matched_session)))
        self._report([self.graph.add_closure(closure)], closure.query_ns, closure)

    def _report(self, results: list[ClosureResult], stamp_ns: int, closure: Closure | None = None) -> None:
        for result in results:
            if result is ClosureResult.UNKNOWN_SESSION and closure is not None:
                unknown = [session_id for session_id in (closure.query_session, closure.place_session)
                           if session_id not in self.graph.sessions]
                named = ", ".join(f"session {number} of robot {robot!r}" for robot, number in unknown)
                self.counter.drop(result.value, f"loop closure near stamp {stamp_ns} dropped: it names {named}, "
                                  "which the backend never saw (no odometry, not in graph_file)")
            elif result is ClosureResult.SOLVER_FAILED:
                self.counter.drop(result.value, f"loop closure near stamp {stamp_ns} dropped: iSAM2 could not take "
                                  f"it ({self.graph.solver_error})")
            elif result in _DROPPED:
                self.counter.drop(result.value, f"loop closure near stamp {stamp_ns} dropped: {result.value}")
            else:
                self.counter.ok(result.value)
        if ClosureResult.ADDED in results:
            self.map_to_odom.publish(self.graph, stamp_ns)
            self._path_changed_ns = stamp_ns
        if any(result is not ClosureResult.WAITING for result in results):  # a loop edge to draw
            self._markers_changed_ns = stamp_ns
        if results:
            self.graph_saver.mark_changed()  # the counts at least; the session table when a closure named a new one

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

    def close(self) -> bool:
        """Save the graph and write the keyframe trajectories; False (the process then exits 1) when either
        cannot be written."""
        saved = self.graph_saver.final_save()
        if self.trajectory_file is not None:
            from aefabmap_ros.evaluation.trajectory_error import tum_text  # evo: loaded at shutdown only

            files = [(self.trajectory_file, self.graph.trajectory())]
            files += [(session_trajectory_path(self.trajectory_file, session_id),
                       self.graph.session_trajectory(*session_id))
                      for session_id, session in self.graph.sessions.items()
                      if session.keyframes and not self.graph.is_joined(*session_id)]
            for path, trajectory in files:
                stamps_s, poses = trajectory_arrays(trajectory)
                try:
                    atomic_write_text(path, tum_text(stamps_s, poses))
                    self.get_logger().info(f"wrote {len(stamps_s)} keyframes to {path}")
                except OSError as exc:
                    saved = False
                    self.get_logger().error(f"FINAL SAVE FAILED: the keyframe trajectory not written to "
                                            f"{path} ({type(exc).__name__}: {exc})")
        self.get_logger().info(f"pose_graph_node: {len(self.graph.keyframes)} keyframes; {self.counter.summary()}; "
                               f"{'; '.join(odometry.summary() for odometry in self.odometry_inputs)}")
        return saved


def main(args: list[str] | None = None) -> int:
    return run_node(PoseGraphNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
