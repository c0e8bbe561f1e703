"""feature_server_node: a robot's end of the link to a base station (several robots, docs/fleet.md).

Runs on the robot, in its namespace, beside feature_node and quantizer_node. Everything the robot sends the
base goes through it, and only this:

- every frame, its words: ``aefabmap/robot_words`` (quantizer_node's output, remapped) is republished on
  ``aefabmap/words`` without ``keypoint_words``;
- the features of the frames the base asks for on ``aefabmap/feature_requests`` (``FeatureRequest``), on
  ``aefabmap/requested_features`` (``RequestedFeatures``): the strongest ``max_features`` keypoints'
  positions and descriptors, and, with ``depth_topic``, their depths and a coarse depth grid sampled here (no
  depth image crosses the link), with the camera's intrinsics from ``camera_info``;
- the robot's odometry (``odom``) thinned to ``odometry_rate_hz`` by stamp on ``aefabmap/odom``, for the
  base's odometry gate (a 50-200 Hz odometry stream would be 35-140 kB/s; the gate interpolates between
  messages, and 10 Hz leaves it a message within 0.1 s of every frame).

It keeps the robot's recent frames (``aefabmap/features``; with ``depth_topic``, their depths) within
``max_store_mb`` and ``max_stored_frames``, oldest forgotten first (verification/feature_server.py). Requests
are counted by outcome: ``served``, ``dropped_not_kept_any_more`` (forgotten, or never taken),
``dropped_never_came`` (its features did not come within ``wait_s`` of newer frames); malformed input is
counted and dropped by name (``bad_features``, ``bad_request``, ``bad_depth``, ``bad_camera_info``).
"""

from __future__ import annotations

from typing import Any

from aefabmap_msgs.msg import BagOfWords, FeatureRequest, Features, RequestedFeatures
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from aefabmap_ros.errors import AefabmapError, ConfigError
from aefabmap_ros.io.image_messages import depth_message_to_metres
from aefabmap_ros.nodes import common
from aefabmap_ros.nodes.common import counted_subscription, declare_parameter, node_callback, pipeline_qos
from aefabmap_ros.nodes.fleet_messages import (
    camera_values,
    requested_stamps,
    served_frame_to_message,
    words_for_link,
)
from aefabmap_ros.nodes.messages import header_stamp_problem, message_to_features, time_from_ns
from aefabmap_ros.nodes.sensor_inputs import SensorInput, check_sensor_qos
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.feature_server import FeatureServer, ServedFrame
from aefabmap_ros.verification.frame_store import FrameStore

ROBOT_WORDS_TOPIC = "aefabmap/robot_words"  # quantizer_node's words on the robot (remapped from aefabmap/words)
REQUESTS_TOPIC = "aefabmap/feature_requests"
REQUESTED_FEATURES_TOPIC = "aefabmap/requested_features"
# Keypoints sent per frame by default: ~33 kB an answer with depth, so that at the base's default budget (0.4
# requests a frame) a robot's link carries under 20 kB a frame, DDS's own traffic included (docs/fleet.md).
LINK_MAX_FEATURES = 300


class FeatureServerNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("feature_server_node", **node_kwargs)
        self.robot = declare_parameter(self, "robot", "", "This robot's name, sent with every answer (the base "
                                       "subscribes to /<robot>/aefabmap/requested_features).")
        max_frames = declare_parameter(self, "max_stored_frames", 5000, "Frames kept for the base's requests "
                                       "at most (with max_store_mb; the oldest are forgotten first).")
        max_mb = float(declare_parameter(self, "max_store_mb", 128.0, "Memory of the kept frames' features and "
                                         "depths at most (MiB): ~40-100 KiB a frame."))
        max_features = declare_parameter(self, "max_features", LINK_MAX_FEATURES, "Strongest keypoints kept and "
                                         "sent per frame (0 = all; at most the base verifier's max_stored_features): "
                                         "~100 bytes each on the link.")
        depth_topic = declare_parameter(self, "depth_topic", "", "Aligned depth image topic (16UC1 mm or 32FC1 m): "
                                        "each keypoint's depth and a coarse grid go with the features ('' = none).")
        wait_s = float(declare_parameter(self, "wait_s", 2.0, "A request waits this long (stamp time: the newest "
                                         "frame is that much newer) for its frame's features and depth."))
        policy = check_sensor_qos(declare_parameter(
            self, "sensor_qos", "auto", "QoS of the camera_info, depth and odom subscriptions: auto, best_effort "
            "(= sensor_data) or reliable."), "sensor_qos")
        odometry_hz = float(declare_parameter(self, "odometry_rate_hz", 10.0, "Odometry forwarded to the base on "
                                              "aefabmap/odom at most this often, by stamp (0 = none)."))
        depth = declare_parameter(self, "queue_depth", 100, "Queue depth of the subscriptions and publications.")
        if max_frames < 1 or not max_mb > 0 or max_features < 0 or not odometry_hz >= 0:
            raise ConfigError(f"feature_server_node: max_stored_frames ({max_frames}) must be >= 1, max_store_mb "
                              f"({max_mb}) > 0, max_features ({max_features}) and odometry_rate_hz >= 0")
        self.counter = common.DropCounter(self)
        store = FrameStore(max_frames, round(max_mb * 2**20), max_features, keep_depths=bool(depth_topic))
        self.server = FeatureServer(store, self.counter, wait_s)
        self.camera: tuple[list[float], list[float]] | None = None
        self.frame_ids: dict[int, str] = {}
        self.words_publisher = self.create_publisher(BagOfWords, "aefabmap/words", pipeline_qos(depth))
        self.publisher = self.create_publisher(RequestedFeatures, REQUESTED_FEATURES_TOPIC, common.result_qos(depth))
        counted_subscription(self, BagOfWords, ROBOT_WORDS_TOPIC, self._on_words, pipeline_qos(depth), self.counter)
        features = counted_subscription(self, Features, "aefabmap/features", self._on_features, pipeline_qos(depth),
                                        self.counter)
        common.report_when_connected(self, features, "features")
        counted_subscription(self, FeatureRequest, REQUESTS_TOPIC, self._on_request, common.result_qos(depth),
                             self.counter)
        self.inputs = [SensorInput(self, CameraInfo, "camera_info", self._on_camera_info, policy=policy, depth=depth,
                                   counter=self.counter, without_it="the base gets no intrinsics: closures of this "
                                   "robot get no relative pose")]
        if depth_topic:
            self.inputs.append(SensorInput(self, Image, depth_topic, self._on_depth, policy=policy, depth=depth,
                                           counter=self.counter, without_it="answers carry no depth (no metric "
                                           "poses or metric test at the base)"))
            self.create_subscription(Header, "aefabmap/skipped_frames", self._on_skipped_frame, pipeline_qos(100))
        self.odometry_period_ns = round(1e9 / odometry_hz) if odometry_hz else 0
        self.last_odometry_ns: int | None = None
        self.odometry_publisher = self.create_publisher(Odometry, "aefabmap/odom", common.ODOMETRY_QOS)
        if odometry_hz:
            self.inputs.append(SensorInput(self, Odometry, "odom", self._on_odometry, policy=policy,
                                           depth=common.ODOMETRY_QOS.depth, counter=self.counter,
                                           without_it="the base has no odometry gate for this robot"))
        self.get_logger().info(f"serving robot {self.robot!r}'s frames to the base: words every frame, features on "
                               f"request (at most {max_features or 'all'} keypoints, {max_mb:g} MiB kept"
                               f"{', with depth' if depth_topic else ''})")

    @node_callback
    def _on_words(self, message: BagOfWords) -> None:
        self.words_publisher.publish(words_for_link(message))
        self.counter.ok("words_forwarded")

    @node_callback
    def _on_features(self, message: Features) -> None:
        try:
            features = message_to_features(message)
            stamp_ns = stamp_to_ns(message.header.stamp)
            size = (int(message.image_width), int(message.image_height)) if message.image_width else None
            self.frame_ids[stamp_ns] = message.header.frame_id
            self._send(self.server.add_features(stamp_ns, features, size))
        except AefabmapError as exc:
            self.counter.drop("bad_features", str(exc))
        if len(self.frame_ids) > 2 * len(self.server.store) + 100:
            self.frame_ids = {stamp: frame for stamp, frame in self.frame_ids.items() if stamp in self.server.store}

    @node_callback
    def _on_request(self, message: FeatureRequest) -> None:
        try:
            stamps = requested_stamps(message)
        except AefabmapError as exc:
            self.counter.drop("bad_request", str(exc))
            return
        self.counter.ok("requests")
        self.counter.counts["frames_requested"] += len(stamps)
        self._send(self.server.request(stamps))

    @node_callback
    def _on_camera_info(self, message: CameraInfo) -> None:
        if len(message.k) != 9 or not all(abs(float(value)) < float("inf") for value in [*message.k, *message.d]):
            self.counter.drop("bad_camera_info", "CameraInfo K is not 9 finite values (or D not finite)")
            return
        self.camera = camera_values(message)

    @node_callback
    def _on_depth(self, message: Image) -> None:
        problem = header_stamp_problem(message.header, "depth image")
        if problem is not None:
            self.counter.drop("bad_stamp", problem)
            return
        try:
            self._send(self.server.add_depth(stamp_to_ns(message.header.stamp), depth_message_to_metres(message)))
        except AefabmapError as exc:
            self.counter.drop("bad_depth", str(exc))

    @node_callback
    def _on_odometry(self, message: Odometry) -> None:
        """Forward one message per odometry period (by stamp): the first at or after the period's start."""
        if header_stamp_problem(message.header, "odometry") is not None:
            self.counter.drop("bad_odometry", "odometry stamp is not a ROS time")
            return
        stamp_ns = stamp_to_ns(message.header.stamp)
        if self.last_odometry_ns is None or stamp_ns - self.last_odometry_ns >= self.odometry_period_ns \
                or stamp_ns < self.last_odometry_ns:  # a restarted source starts again
            self.last_odometry_ns = stamp_ns
            self.odometry_publisher.publish(message)
            self.counter.ok("odometry_forwarded")

    @node_callback
    def _on_skipped_frame(self, message: Header) -> None:
        if header_stamp_problem(message, "skipped frame") is None:
            self.server.skip_frame(stamp_to_ns(message.stamp))

    def _send(self, frames: list[ServedFrame]) -> None:
        for frame in frames:
            header = Header(stamp=time_from_ns(frame.stamp_ns), frame_id=self.frame_ids.get(frame.stamp_ns, ""))
            self.publisher.publish(served_frame_to_message(frame, self.robot, header, self.camera))

    def close(self) -> bool:
        store = self.server.store
        self.get_logger().info(f"feature_server_node: {len(store)} frames kept ({store.nbytes / 2**20:.1f} MiB), "
                               f"{len(self.server.waiting)} requests waiting; {self.counter.summary()}; "
                               + "; ".join(sensor_input.summary() for sensor_input in self.inputs))
        return True


def main(args: list[str] | None = None) -> int:
    return common.run_node(FeatureServerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
