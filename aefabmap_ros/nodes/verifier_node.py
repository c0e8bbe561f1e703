"""verifier_node: ``loop_closure_candidates`` -> ``loop_closures`` (geometric verification, odometry gate).

A thin adapter around the ROS-free decision chain (verification/chain.py) and its frame store
(verification/frame_store.py); parameters in nodes/verifier_parameters.py. In: ``aefabmap/features``,
``loop_closure_candidates``, ``place_posteriors`` (re-ranking or tracking), ``camera_info`` (unless
``camera_matrix``), the depth topic and ``aefabmap/skipped_frames`` (``depth_topic``), ``odom``
(``odometry_gate``). Out: verified, odometry-consistent closures with inliers and relative pose. Malformed
input is counted and dropped by name (``bad_features``, ``depth_size_mismatch``, ``bad_depth``,
``bad_camera_info``, ``bad_posterior``, ``bad_closure_stamp``, ``bad_candidate``, ``bad_odometry``,
``stamp_in_future``, ``odometry_out_of_order``, ``bad_stamp``, ``bad_closure_pose``).

Several robots (``robots``, a base station; docs/fleet.md): instead of ``aefabmap/features``, depth and
camera_info, the node asks each robot's feature server for the frames it will verify and takes them with their
depths and camera (nodes/verifier_fleet.py); each robot has its own odometry gate on ``/<robot>/aefabmap/odom``. A
detection is verified only against the frames of the robots it names (``robot_mismatch``), and only between
robots with the same camera (``cameras_differ``); a frame whose stamp another robot's frame has taken is
dropped (``stamp_of_another_robot``).
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

from aefabmap_msgs.msg import Features, LoopClosure, PlacePosterior
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from aefabmap_ros.backend.odometry_gate import OdometryGate
from aefabmap_ros.errors import AefabmapError
from aefabmap_ros.io.image_messages import depth_message_to_metres
from aefabmap_ros.nodes import closure_messages as convert
from aefabmap_ros.nodes import common
from aefabmap_ros.nodes.common import counted_subscription, node_callback, pipeline_qos, result_qos
from aefabmap_ros.nodes.future_stamps import FutureStamps
from aefabmap_ros.nodes.gtsam_poses import pose_to_gtsam
from aefabmap_ros.nodes.messages import header_stamp_problem, message_to_features, posterior_problem
from aefabmap_ros.nodes.sensor_inputs import SensorInput
from aefabmap_ros.nodes.verifier_fleet import RobotLinks
from aefabmap_ros.nodes.verifier_fleet import candidate_refusal as fleet_candidate_refusal
from aefabmap_ros.nodes.verifier_parameters import RUNTIME_SETTINGS, declare_verifier_parameters
from aefabmap_ros.nodes.verifier_summary import FeatureClock, shutdown_summary, startup_summary
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.chain import LoopClosureChain
from aefabmap_ros.verification.closures import Closure
from aefabmap_ros.verification.frame_depths import depth_size_problem
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.relative_pose import camera_info_to_model


class VerifierNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("verifier_node", **node_kwargs)
        p = declare_verifier_parameters(self)
        self.counter = common.DropCounter(self)
        self.publisher = self.create_publisher(LoopClosure, "loop_closures", common.RESULT_QOS)
        self.store = FrameStore(p.max_frames, p.max_store_bytes, p.max_features,
                                keep_depths=bool(p.depth_topic) or bool(p.robots),
                                folder=Path(p.store_dir) if p.store_dir else None)
        for note in self.store.load():
            self.get_logger().info(note)
        self.clock = FeatureClock(p.max_lag_s, p.drop_after_lag_s)
        self.future_stamps = FutureStamps(self)
        gates = {robot: OdometryGate(p.drift_model, p.base_to_camera) for robot in p.robots} if p.odometry_gate else {}
        self.chain = LoopClosureChain(
            self.store, p.config, p.pose_config, self._publish, self.counter,
            gate=OdometryGate(p.drift_model, p.base_to_camera) if p.odometry_gate and not p.robots else None,
            robot_gates=gates,
            max_pending=p.max_pending, odometry_wait_s=p.odometry_wait_s,
            max_awaiting_odometry=p.max_awaiting_odometry, depth_wait_s=p.depth_wait_s, behind=self.clock.behind,
            too_late=self.clock.too_late,
            log=self._log)
        self.chain.pairs.camera = p.camera
        self.camera_fixed = self.chain.pairs.camera is not None
        depth = p.queue_depth
        self.links = RobotLinks(self, self.chain, list(p.robots), self.counter, depth=depth, sensor_qos=p.sensor_qos,
                                odometry=p.odometry_gate, max_features=p.max_features,
                                future_stamps=self.future_stamps, requests_per_frame=p.requests_per_frame,
                                on_frame=self._on_robot_frame) if p.robots else None
        if self.links is None:
            features = counted_subscription(self, Features, "aefabmap/features", self._on_features,
                                            pipeline_qos(depth), self.counter, pass_source_time=True)
            common.report_when_connected(self, features, "features")  # a place never heard cannot be verified
        if p.depth_topic and self.links is None:  # the depth images of frames feature_node skips wait for no features
            self.create_subscription(Header, "aefabmap/skipped_frames", self._on_skipped_frame,
                                     pipeline_qos(max(depth, 100)))
        # As deep as the features queue: a verifier behind during a revisit must not lose the candidates and
        # posteriors of the frames it has yet to reach.
        counted_subscription(self, LoopClosure, "loop_closure_candidates", self._on_loop_closure, result_qos(depth),
                             self.counter)
        self.inputs = (self.links.inputs if self.links is not None
                       else self._sensor_inputs(p.depth_topic, p.sensor_qos, depth, p.odometry_gate))
        if self.chain.needs_posteriors or self.links is not None:  # several robots: posteriors say what to ask for
            counted_subscription(self, PlacePosterior, "place_posteriors", self._on_posterior, result_qos(depth),
                                 self.counter)
        self.store_saver = common.PeriodicSave(self, self.store.folder, self.store.save, "the feature store",
                                               p.save_period_s)
        self.runtime_parameters = common.RuntimeParameters(self, RUNTIME_SETTINGS, self._reconfigure)
        self.get_logger().info(startup_summary(p))

    def _sensor_inputs(self, depth_topic: str, policy: str, depth: int, gate: bool) -> list[SensorInput]:
        """The robot's own sensor topics: they connect to a best-effort driver as to a reliable replay."""
        sensor = partial(SensorInput, self, policy=policy, counter=self.counter)
        inputs = []
        if not self.camera_fixed:
            inputs.append(sensor(CameraInfo, "camera_info", self._on_camera_info, depth=depth, without_it="closures "
                                 "get no relative pose (set camera_matrix, or remap camera_info to the camera's)"))
        if depth_topic:
            inputs.append(sensor(Image, depth_topic, self._on_depth, depth=depth,
                                 without_it="no metric poses and no metric test (monocular poses only)"))
        if gate:
            inputs.append(sensor(Odometry, "odom", self._on_odometry, depth=common.ODOMETRY_QOS.depth,
                                 without_it="closures are published without the odometry gate"))
        return inputs

    @node_callback
    def _on_features(self, message: Features, sent_ns: int | None = None) -> None:
        self.clock.sent(stamp_ns := stamp_to_ns(message.header.stamp), sent_ns)
        try:
            features = message_to_features(message)
        except AefabmapError as exc:
            self.counter.drop("bad_features", str(exc))
            return
        size = (int(message.image_width), int(message.image_height)) if message.image_width else None
        self.chain.add_features(stamp_ns, features, size)
        self.store_saver.mark_changed()  # depths and places come with or after it; close() checks the rest

    def _on_robot_frame(self, stamp_ns: int, sent_ns: int | None) -> None:
        """Several robots: a robot's frame was stored (its answer's send time: how far behind the verifier is)."""
        self.clock.sent(stamp_ns, sent_ns)
        self.store_saver.mark_changed()

    @node_callback
    def _on_camera_info(self, message: CameraInfo) -> None:
        if self.camera_fixed:
            return
        try:
            camera = camera_info_to_model(message)
        except AefabmapError as exc:
            self.counter.drop("bad_camera_info", f"{exc}; the previous intrinsics are kept")
            return
        if camera is None:
            self.counter.drop("bad_camera_info", f"CameraInfo K = {list(message.k)} has fx = 0 (an uncalibrated "
                                                 "camera); the previous intrinsics are kept")
            return
        self.chain.pairs.camera = camera

    @node_callback
    def _on_skipped_frame(self, message: Header) -> None:
        problem = header_stamp_problem(message, "skipped frame")
        if problem is not None:
            self.counter.drop("bad_stamp", problem)
        elif self.store.depths is not None:
            self.store.depths.skip_frame(stamp_to_ns(message.stamp))

    @node_callback
    def _on_depth(self, message: Image) -> None:
        stamp_ns, image_size = stamp_to_ns(message.header.stamp), self.chain.pairs.image_size
        # Checked before decoding; a depth image before any features is checked when its frame's features come.
        problem = None if image_size is None else depth_size_problem((message.width, message.height), image_size)
        if problem is not None:
            self.counter.drop("depth_size_mismatch", f"depth image at stamp {stamp_ns}: {problem}")
            return
        try:
            self.chain.add_depth(stamp_ns, depth_message_to_metres(message))
        except AefabmapError as exc:
            self.counter.drop("bad_depth", str(exc))

    @node_callback
    def _on_odometry(self, message: Odometry) -> None:
        refusal = convert.odometry_refusal(message, self.future_stamps)
        if refusal is not None:
            self.counter.drop(*refusal)
        elif not self.chain.add_odometry(stamp_to_ns(message.header.stamp), pose_to_gtsam(message.pose.pose)):
            self.counter.drop("odometry_out_of_order", "odometry stamp not after the previous one")

    @node_callback
    def _on_posterior(self, message: PlacePosterior) -> None:
        problem = posterior_problem(message)
        if problem is not None:  # re-ranking and tracking index the four arrays by one rank
            self.counter.drop("bad_posterior", problem)
            return
        posterior = convert.posterior_from_message(message)
        self.chain.add_posterior(posterior)
        if self.links is not None:
            self.links.after_posterior(posterior)

    @node_callback
    def _on_loop_closure(self, message: LoopClosure) -> None:
        refusal = (convert.candidate_refusal if self.links is None else fleet_candidate_refusal)(message)
        if refusal is not None:
            self.counter.drop(*refusal)
        else:
            detection = convert.detection_from_message(message)
            self.chain.add_detection(detection)
            if self.links is not None:
                self.links.after_detection(detection)

    def _publish(self, closure: Closure) -> None:
        self.publisher.publish(convert.closure_to_message(closure))
        self.clock.published(closure.detection.query_ns)

    def _log(self, text: str, throttled: bool) -> None:
        if throttled:  # rclpy fixes a call site's throttling at its first call: one site each
            self.get_logger().info(text, throttle_duration_sec=common.LOG_THROTTLE_S)
        else:
            self.get_logger().info(text)

    def _reconfigure(self, changes: dict[str, Any]) -> None:
        self.chain.pairs.config = replace(self.chain.pairs.config, **changes)  # ConfigError refuses the change

    def close(self) -> bool:
        """The final store save; False when it failed (the process then exits 1)."""
        if self.store.has_unsaved:  # features, depths or places (whichever callback brought them)
            self.store_saver.mark_changed()
        saved = self.store_saver.final_save()
        self.get_logger().info(shutdown_summary(self.chain, saved, self.counter.summary(), self.clock.delays_s,
                                                self.inputs))
        return saved


def main(args: list[str] | None = None) -> int:
    return common.run_node(VerifierNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
