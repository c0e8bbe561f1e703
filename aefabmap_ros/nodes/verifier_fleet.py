"""verifier_node's links to several robots (parameter ``robots``; docs/fleet.md).

Per robot: it asks the robot's feature server for frames on ``/<robot>/aefabmap/feature_requests`` (which
ones: verification/frame_requests.py), takes the answers from ``/<robot>/aefabmap/requested_features`` (the
features with their depths and the robot's camera; no depth image or camera_info crosses the link), and,
with ``odometry_gate``, the robot's odometry as its feature server thins it (``/<robot>/aefabmap/odom``) for that
robot's own gate.

A candidate between two robots may match a place stamped after its query (``candidate_refusal``): the other
robot made it before FAB-MAP took this robot's frame, later in stamp time by at most the link's delay (or by
more, where the robots' clocks disagree). One robot's own place is always older than its query.

An answer is stored as its robot's frame (the topic it came on names the robot): one whose stamp is stored for
another robot is dropped (``stamp_of_another_robot``), one naming another robot than its topic's is dropped
(``answer_of_another_robot``), and a malformed one (``bad_requested_features``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial

from aefabmap_msgs.msg import FeatureRequest, LoopClosure, RequestedFeatures
from nav_msgs.msg import Odometry
from rclpy.node import Node

from aefabmap_ros.errors import AefabmapError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.nodes import closure_messages as convert
from aefabmap_ros.nodes import common
from aefabmap_ros.nodes.common import counted_subscription, node_callback
from aefabmap_ros.nodes.fleet_messages import ReceivedFrame, feature_request, message_to_received_frame
from aefabmap_ros.nodes.fleet_parameters import robot_topic
from aefabmap_ros.nodes.future_stamps import FutureStamps
from aefabmap_ros.nodes.gtsam_poses import pose_to_gtsam
from aefabmap_ros.nodes.messages import loop_closure_stamp_problem
from aefabmap_ros.nodes.sensor_inputs import SensorInput
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.chain import LoopClosureChain
from aefabmap_ros.verification.closures import Detection, Posterior
from aefabmap_ros.verification.frame_depths import FrameDepths
from aefabmap_ros.verification.frame_requests import FrameRequests

REQUESTS_TOPIC = "aefabmap/feature_requests"
REQUESTED_FEATURES_TOPIC = "aefabmap/requested_features"
ODOMETRY_TOPIC = "aefabmap/odom"  # the robot's odometry, thinned by its feature server


class RobotLinks:
    """The verifier's subscriptions, publishers and requests for each of several robots."""

    def __init__(self, node: Node, chain: LoopClosureChain, robots: list[str], counter: common.DropCounter, *,
                 depth: int, sensor_qos: str, odometry: bool, max_features: int, future_stamps: FutureStamps,
                 requests_per_frame: float, on_frame: Callable[[int, int | None], None]) -> None:
        """``on_frame(stamp, sent_ns)``: a robot's frame was stored (the node's clock and periodic save)."""
        self.node, self.chain, self.counter = node, chain, counter
        self.max_features = max_features
        self.on_frame = on_frame
        self.requests = FrameRequests(robots, counter, requests_per_frame)
        self.future_stamps = future_stamps
        self.publishers = {robot: node.create_publisher(FeatureRequest, robot_topic(robot, REQUESTS_TOPIC),
                                                        common.result_qos(depth)) for robot in robots}
        self.inputs: list[SensorInput] = []
        for robot in robots:
            answers = counted_subscription(node, RequestedFeatures, robot_topic(robot, REQUESTED_FEATURES_TOPIC),
                                           partial(self._on_answer, robot=robot), common.result_qos(depth), counter,
                                           pass_source_time=True)
            common.report_when_connected(node, answers, f"requested features of {robot}")
            if odometry:
                self.inputs.append(SensorInput(
                    node, Odometry, robot_topic(robot, ODOMETRY_TOPIC), partial(self._on_odometry, robot=robot),
                    policy=sensor_qos, depth=common.ODOMETRY_QOS.depth, counter=counter,
                    without_it=f"closures within {robot}'s sessions are published without its odometry gate"))

    def after_posterior(self, posterior: Posterior) -> None:
        """Ask for the posterior's frame if it will be verified (the chain has taken the posterior already)."""
        tracking = self.chain.tracks.active(posterior.robot, posterior.query_ns)
        self.requests.after_posterior(posterior, tracking, self.chain.store.__contains__)
        self._send()

    def after_detection(self, detection: Detection) -> None:
        """Ask for a candidate's frames (the chain holds it already); one whose query will not come is let go."""
        if not self.requests.after_detection(detection, self.chain.store.__contains__) \
                and self.chain.pending.pop(detection.query_ns, None) is not None:
            self.counter.ok("candidates_over_link_budget")
        self._send()

    def _send(self) -> None:
        now_ns = time.time_ns()
        for robot, stamps in self.requests.take().items():
            self.publishers[robot].publish(feature_request(stamps, now_ns))
            self.counter.ok("feature_requests_sent")

    @node_callback
    def _on_answer(self, message: RequestedFeatures, sent_ns: int | None = None, robot: str = "") -> None:
        try:
            frame = message_to_received_frame(message)
        except AefabmapError as exc:
            self.counter.drop("bad_requested_features", f"from {robot}: {exc}")
            return
        if frame.robot != robot:
            self.counter.drop("answer_of_another_robot", f"a frame of robot {frame.robot!r} on {robot}'s topic")
            return
        if frame.camera.camera is not None or robot not in self.chain.pairs.robot_cameras:
            self.chain.pairs.robot_cameras[robot] = frame.camera
        features, depths = _within(frame, self.max_features)
        if self.chain.add_frame(frame.stamp_ns, robot, features, depths):
            self.counter.ok("requested_features_received")
            self.on_frame(frame.stamp_ns, sent_ns)

    @node_callback
    def _on_odometry(self, message: Odometry, robot: str = "") -> None:
        refusal = convert.odometry_refusal(message, self.future_stamps)
        if refusal is not None:
            self.counter.drop(*refusal)
        elif not self.chain.add_odometry(stamp_to_ns(message.header.stamp), pose_to_gtsam(message.pose.pose), robot):
            self.counter.drop("odometry_out_of_order", f"{robot}'s odometry stamp not after the previous one")


def candidate_refusal(message: LoopClosure) -> tuple[str, str] | None:
    """closure_messages.candidate_refusal, except that a place of another robot may be stamped after the query
    (never at the same stamp: the two frames would be one in the store)."""
    if message.query_robot == message.matched_robot:
        return convert.candidate_refusal(message)
    problem = loop_closure_stamp_problem(message)
    if problem is not None:
        return "bad_closure_stamp", problem
    text = f"candidate of query {message.query_id} -> place {message.matched_place_id}"
    if stamp_to_ns(message.matched_stamp) == stamp_to_ns(message.header.stamp):
        return "bad_candidate", f"{text}: its place has the query's stamp"
    if not 0.0 <= message.probability <= 1.0:  # NaN fails too
        return "bad_candidate", f"{text}: probability {message.probability} is not in [0, 1]"
    return None


def _within(frame: ReceivedFrame, max_features: int) -> tuple[Features, FrameDepths | None]:
    """The frame's first ``max_features`` keypoints (0 = all), with their depths: a feature server sends at most
    its own max_features, strongest kept; a verifier set to keep fewer keeps the first."""
    features, depths = frame.features, frame.depths
    if not max_features or len(features) <= max_features:
        return features, depths
    kept = Features(features.keypoints[:max_features], features.descriptors[:max_features], features.descriptor_type)
    return kept, None if depths is None else replace(depths, keypoints=depths.keypoints[:max_features])
