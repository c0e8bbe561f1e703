"""verifier_node: ``loop_closure_candidates`` -> ``loop_closures`` (geometric verification).

Keeps the features of recent frames (``aefabmap/features``, by image stamp). For every loop
closure candidate from fabmap_node it matches the query image's features against the matched
place's and publishes the closure on ``loop_closures``, with its ``inliers`` count filled in, when
enough matches fit one fundamental matrix (``min_inliers``); otherwise it is counted and logged as
rejected. ``loop_closures`` is what a SLAM backend subscribes to: every message on it passed.

Re-ranking (``candidates`` > 1, see verification/geometric.py): once the matched place is accepted, the
query's other top candidates from its ``place_posteriors`` message are verified too, and the
closure is republished to the accepted one with the most inliers -- the view that shares the most
scene with the query. ``probability`` and ``log_likelihood`` stay those of the detection.

Loop tracking (``track_seconds`` > 0, see verification/loop_tracking.py): for a short while after a
verified closure, a frame with no candidate of its own (or whose candidate failed) is verified
against its top candidates from ``place_posteriors`` that lie near the last verified place in map
time; the accepted one with the most inliers is published like any other closure (``probability``
is that place's posterior). When none passes, the ``track_frames`` stored frames nearest the last
verified place in time (at least ``track_min_age_seconds`` older than the query) are verified the
same way: ``matched_stamp`` is then that frame's stamp, ``matched_place_id`` the place it belongs to
(from its ``place_posteriors`` message), and ``probability`` that place's posterior, 0 when the
query's top candidates do not include it (``log_likelihood`` NaN). Every message on
``loop_closures`` passed the same geometric check.

A closure can arrive before its query's features or posterior (separate topics): it waits, up to
``max_pending`` closures, until they come. A closure whose place is older than the store
(``max_stored_frames``) cannot be verified and is dropped. With ``store_dir`` the store is saved
to that folder (every ``save_period_s`` the frames added since the last save, as one more chunk
file, and on shutdown) and reloaded on start, so after a restart the places seen before it can
still be verified; so is each frame's place (``timeline-*.npz``), so that loop tracking still
reaches the frames stored before the restart.

Odometry gate (``odometry_gate``, backend/odometry_gate.py): once odometry arrives on ``odom``
(``nav_msgs/Odometry``), a verified closure is published only when its relative pose agrees with
odometry's between the two stamps within what odometry drift explains over the distance travelled
between them (the example backend's test, same parameters). Perceptual aliasing -- an identical
corner elsewhere -- passes every appearance and geometric check, not this one. A closure whose query
is newer than the newest odometry waits for it (up to ``max_pending`` closures; odometry is often
processed after the images it belongs to). A closure without a relative pose is dropped (counted)
while the gate is active. Where odometry has nothing to say -- a robot without odometry, a place
mapped before this odometry began (a map reloaded after a restart) -- verified closures are
published unchecked (the latter counted).

Relative pose (verification/relative_pose.py): every published closure carries the matched place's camera
pose in the query camera's frame, computed from the matches, or ``pose_available`` false and the
reason in ``pose_status`` (counted). Intrinsics come from ``camera_info`` (``sensor_msgs/CameraInfo``)
or the ``camera_matrix`` parameter (fx, fy, cx, cy; it wins when set). Without depth the pose is
the essential matrix's (rotation and translation direction, ``translation_metric`` false); with
``depth_topic`` set (an aligned ``sensor_msgs/Image``, 16UC1 in mm or 32FC1 in m, stamped like the
images) the depth at each stored keypoint and the depth image on a coarse grid (~12 KiB a frame,
verification/frame_depths.py) are kept beside the features (same frame bound) and the pose is PnP's, in
metres. With ``store_dir`` they are saved there too (``depth-*.npz`` beside the feature chunks, at the
same times), so after a restart the reloaded places still give metric poses. With depth and intrinsics
the metric test decides too (verification/metric.py: one rigid motion by PnP, under which the views
overlap and the query's depth lands on the place's surface): it accepts a candidate the epipolar test
refused for its share of the keypoints (counted as ``metric_test_accepted``) and refuses one it accepted
whose views do not overlap or are not covisible (``metric_test_refused_no_view_overlap``); the image size
it needs comes from the features messages.

Malformed input is counted and dropped by name, the state kept as it was: a depth image of another size
than its image (``depth_size_mismatch``: its pixels are not the keypoints'), a CameraInfo without usable
intrinsics (``bad_camera_info``: K all zero, focal lengths not positive and finite; the previous
intrinsics stay), a PlacePosterior whose candidate arrays differ in length (``bad_posterior``), odometry
with an unusable stamp or pose (``bad_odometry``: NaN, a quaternion whose norm is not 1;
backend/validation.py), and a closure whose pose the odometry gate cannot judge (``bad_closure_pose``).
Any other exception a message causes is counted by its type (``node_callback``).
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Iterator, Sequence
from dataclasses import replace
from enum import Enum
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from aefabmap_msgs.msg import Features, LoopClosure, PlacePosterior
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from aefabmap_ros.backend.odometry_gate import GateResult, OdometryGate
from aefabmap_ros.backend.pose_graph import PoseGraphConfig
from aefabmap_ros.errors import AefabmapError, ConfigError
from aefabmap_ros.features.extraction import Features as CoreFeatures
from aefabmap_ros.io.atomic import remove_stale_temporaries
from aefabmap_ros.io.chunk_folder import chunk_pattern
from aefabmap_ros.io.image_messages import depth_message_to_metres
from aefabmap_ros.nodes.common import (
    LOG_THROTTLE_S,
    ODOMETRY_QOS,
    RESULT_QOS,
    DropCounter,
    PeriodicSave,
    RuntimeParameters,
    counted_subscription,
    declare_config,
    declare_parameter,
    node_callback,
    pipeline_qos,
    report_when_connected,
    result_qos,
    run_node,
)
from aefabmap_ros.nodes.messages import (
    extrinsic_to_gtsam,
    fill_relative_pose,
    loop_closure_pose,
    loop_closure_pose_problem,
    message_to_features,
    odometry_problem,
    pose_to_gtsam,
    posterior_problem,
    time_from_ns,
)
from aefabmap_ros.nodes.sensor_inputs import SensorInput, check_sensor_qos
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.feature_store import FeatureStore, FeatureStoreFolder
from aefabmap_ros.verification.frame_depths import FrameDepthFolder, FrameDepthStore, depth_size_problem
from aefabmap_ros.verification.geometric import Verification, VerificationConfig, matched_points, verify_pair
from aefabmap_ros.verification.loop_tracking import FrameTimeline, FrameTimelineFolder, LoopTrack
from aefabmap_ros.verification.metric import KeypointDepths
from aefabmap_ros.verification.relative_pose import (
    CameraModel,
    RelativePoseConfig,
    camera_info_to_model,
    relative_pose,
)
from aefabmap_ros.verification.reranking import rerank_by_inliers

# Posteriors kept by query stamp: a closure is published right after its query's posterior, so
# only the last few are ever looked up; the rest bounds memory when no closures come.
POSTERIOR_HISTORY = 1000

# The example backend's drift model and gate (pose_graph_node's parameters of the same names).
ODOMETRY_GATE_SETTINGS = frozenset({"odometry_translation_drift", "odometry_rotation_drift_rad_per_m",
                                    "odometry_min_sigma", "loop_min_sigma_m", "loop_min_sigma_rad", "gate_chi2",
                                    "max_odometry"})

# The geometric check's settings, read afresh for every pair: ``ros2 param set`` applies them from the
# next closure on. The others size the store or the subscriptions at start-up and are refused.
RUNTIME_SETTINGS = frozenset({"min_inliers", "min_inlier_ratio", "ratio", "ransac_threshold_px", "confidence",
                              "max_iterations", "metric_min_inliers", "metric_min_view_overlap", "metric_ratio",
                              "metric_min_covisibility", "metric_depth_tolerance_m",
                              "metric_depth_relative_tolerance"})


class PlaceToVerify(NamedTuple):
    """A place to verify the query against."""

    place_id: int
    stamp: Any  # builtin_interfaces/Time, as republished in matched_stamp
    features: CoreFeatures


class GateDecision(Enum):
    """What happens to a verified closure at the odometry gate."""

    PUBLISH = "publish"
    WAIT = "wait"  # for odometry to reach its stamps
    REFUSE = "refuse"


class TrackedMatch(NamedTuple):
    """A loop-tracking closure before it is published."""

    place: PlaceToVerify
    probability: float
    log_likelihood: float
    verification: Verification


class VerifierNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("verifier_node", **node_kwargs)
        depth = declare_parameter(self, "queue_depth", 100, "Queue depth of the features, depth and CameraInfo "
                                  "subscriptions, and of the candidates and posteriors (at least 100).")
        max_frames = declare_parameter(
            self, "max_stored_frames", 20000,
            "Frames whose features are kept for verification (the oldest are forgotten first).",
        )
        max_features = declare_parameter(
            self, "max_stored_features", 500,
            "Strongest keypoints kept per frame (0 = all); ~128 KiB per frame of 500 SIFT features.",
        )
        self.max_pending = declare_parameter(
            self, "max_pending", 100, "Loop closures waiting for their query's features (and posterior) at most."
        )
        self.max_lag_s = declare_parameter(
            self, "max_lag_s", 0.25,
            "A closure verified more than this long after its query's features were sent is checked against its "
            "detection only (no re-ranking) and loop tracking waits, so the verifier catches up with a live camera "
            "instead of falling behind during a revisit (seconds; 0 = never: a lockstep replay, reproducible).",
        )
        store_dir = declare_parameter(
            self, "store_dir", "",
            "Folder the feature store (with each frame's place, for loop tracking) is saved to and reloaded from "
            "('' = memory only).",
        )
        save_period_s = declare_parameter(
            self, "save_period_s", 10.0,
            "Save the frames added since the last save this often (seconds; 0 = only on shutdown).",
        )
        self.config = declare_config(self, VerificationConfig)
        self.pose_config = declare_config(self, RelativePoseConfig, prefix="pose_")
        camera_matrix = declare_parameter(
            self, "camera_matrix", [0.0, 0.0, 0.0, 0.0],
            "Intrinsics fx, fy, cx, cy for the relative pose (all 0 = take them from camera_info).",
        )
        depth_topic = declare_parameter(
            self, "depth_topic", "",
            "Aligned depth image topic (16UC1 mm or 32FC1 m) for metric relative poses ('' = monocular).",
        )
        odometry_gate = declare_parameter(
            self, "odometry_gate", True,
            "Refuse verified closures that odometry on 'odom' contradicts beyond its drift (active once odometry "
            "arrives; see backend/odometry_gate.py).",
        )
        base_to_camera = extrinsic_to_gtsam(declare_parameter(
            self, "base_to_camera", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            "The camera's pose in the odometry's child (base) frame, [x, y, z, qx, qy, qz, qw] (identity: the "
            "camera is the base frame), for the odometry gate.",
        ))
        drift_model = declare_config(self, PoseGraphConfig, only=ODOMETRY_GATE_SETTINGS)
        sensor_qos = check_sensor_qos(declare_parameter(
            self, "sensor_qos", "auto",
            "QoS of the camera_info, depth and odom subscriptions: auto (reliable, moving to best effort once a "
            "publisher offers only that, as drivers often do), best_effort (= sensor_data) or reliable.",
        ), "sensor_qos")
        if max_frames < 1 or max_features < 0 or self.max_pending < 1:
            raise ConfigError(f"verifier_node: max_stored_frames ({max_frames}) and max_pending "
                              f"({self.max_pending}) must be >= 1, max_stored_features ({max_features}) >= 0")
        self.store = FeatureStore(max_frames, max_features)
        self.camera = _camera_from_parameter(camera_matrix)
        self.camera_fixed = self.camera is not None
        self.depths = FrameDepthStore(max_frames) if depth_topic else None
        self.image_size: tuple[int, int] | None = None  # (width, height), from the features messages
        self.timeline = FrameTimeline(max_frames)  # the frames' places, for tracking through unranked frames
        self.store_folder = FeatureStoreFolder(Path(store_dir)) if store_dir else None
        self.depth_folder = FrameDepthFolder(Path(store_dir)) if store_dir and self.depths is not None else None
        self.timeline_folder = FrameTimelineFolder(Path(store_dir)) if store_dir else None
        if store_dir:
            self._reload_stores(Path(store_dir))
        self.pending: OrderedDict[int, LoopClosure] = OrderedDict()  # query stamp -> closure, oldest first
        self.awaiting_odometry: list[LoopClosure] = []  # verified, until odometry reaches their stamps (in order)
        self.rerank = self.config.candidates > 1
        self.track = LoopTrack(self.config.track_seconds, self.config.track_island_seconds)
        self.odometry_gate = OdometryGate(drift_model, base_to_camera) if odometry_gate else None
        self.posteriors: OrderedDict[int, PlacePosterior] = OrderedDict()  # query stamp -> posterior
        # Features stamp -> when feature_node sent them (wall clock ns, as DDS stamps them): how far behind the verifier
        # is, the time they waited in its queue included (max_lag_s).
        self.arrivals: dict[int, int] = {}
        self.delays_s: deque[float] = deque(maxlen=10_000)  # from a query's features sent to its closure going out
        self.counter = DropCounter(self)
        self.publisher = self.create_publisher(LoopClosure, "loop_closures", RESULT_QOS)
        features = counted_subscription(self, Features, "aefabmap/features", self._on_features, pipeline_qos(depth),
                                        self.counter, pass_source_time=True)
        # A place whose features the verifier never heard cannot be verified.
        report_when_connected(self, features, "features")
        if depth_topic:  # the depth images of frames feature_node skips wait for no features
            self.create_subscription(Header, "aefabmap/skipped_frames", self._on_skipped_frame,
                                     pipeline_qos(max(depth, 100)))
        # As deep as the features queue: a verifier behind during a revisit must not lose the candidates and
        # posteriors of the frames it has yet to reach.
        counted_subscription(self, LoopClosure, "loop_closure_candidates", self._on_loop_closure, result_qos(depth),
                             self.counter)
        # The robot's own sensor topics: they connect to a best-effort driver as to a reliable replay.
        self.inputs: list[SensorInput] = []
        if not self.camera_fixed:
            self.inputs.append(SensorInput(self, CameraInfo, "camera_info", self._on_camera_info, policy=sensor_qos,
                                           depth=depth, counter=self.counter,
                                           without_it="closures get no relative pose (set camera_matrix, or remap "
                                           "camera_info to the camera's)"))
        if depth_topic:
            self.inputs.append(SensorInput(self, Image, depth_topic, self._on_depth, policy=sensor_qos, depth=depth,
                                           counter=self.counter,
                                           without_it="no metric poses and no metric test (monocular poses only)"))
        if self.odometry_gate is not None:
            self.inputs.append(SensorInput(self, Odometry, "odom", self._on_odometry, policy=sensor_qos,
                                           depth=ODOMETRY_QOS.depth, counter=self.counter,
                                           without_it="closures are published without the odometry gate"))
        if self.rerank or self.track.enabled:
            counted_subscription(self, PlacePosterior, "place_posteriors", self._on_posterior, result_qos(depth),
                                 self.counter)
        self.store_saver = PeriodicSave(
            self, None if self.store_folder is None else self.store_folder.folder, self._save_store,
            "the feature store", save_period_s,
        )
        self.runtime_parameters = RuntimeParameters(self, RUNTIME_SETTINGS, self._reconfigure)
        metric_test = (f" or, with depth, >= {self.config.metric_min_inliers} PnP inliers (matches at ratio "
                       f"{self.config.metric_ratio:g}), {self.config.metric_min_view_overlap:.0%} view overlap and "
                       f"{self.config.metric_min_covisibility:.0%} covisibility"
                       if depth_topic and self.config.metric_min_inliers else "")
        self.get_logger().info(
            f"verifying loop closures: >= {self.config.min_inliers} fundamental-matrix inliers and "
            f"{self.config.min_inlier_ratio:.0%} of the keypoints{metric_test}, "
            f"re-ranking the best {self.config.candidates} candidates, "
            f"tracking loops for {self.config.track_seconds:g} s, features of the last {max_frames} frames, "
            + ("closures checked against odometry on odom once it arrives" if odometry_gate else "no odometry gate")
        )

    @node_callback
    def _on_features(self, message: Features, sent_ns: int | None = None) -> None:
        stamp_ns = stamp_to_ns(message.header.stamp)
        try:
            self.store.add(stamp_ns, message_to_features(message))
        except AefabmapError as exc:
            self.counter.drop("bad_features", str(exc))
            return
        self.store_saver.mark_changed()
        self.arrivals[stamp_ns] = time.time_ns() if sent_ns is None else sent_ns
        while len(self.arrivals) > POSTERIOR_HISTORY:
            del self.arrivals[next(iter(self.arrivals))]
        if message.image_width and message.image_height:  # one camera: its images' size, for the metric test
            self.image_size = (int(message.image_width), int(message.image_height))
        stored = self.store.get(stamp_ns)
        if self.depths is not None and stored is not None:
            image_size = (int(message.image_width), int(message.image_height)) if message.image_width else None
            try:
                self.depths.add_features(stamp_ns, stored.keypoints, image_size)
            except AefabmapError as exc:  # its depth image, come first, is of another size: not kept
                self.counter.drop("depth_size_mismatch", f"frame at stamp {stamp_ns}: {exc}")
        self._verify_if_ready(stamp_ns)

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
        self.camera = camera

    @node_callback
    def _on_skipped_frame(self, message: Header) -> None:
        if self.depths is not None:
            self.depths.skip_frame(stamp_to_ns(message.stamp))

    @node_callback
    def _on_depth(self, message: Image) -> None:
        if self.depths is None:
            return
        stamp_ns = stamp_to_ns(message.header.stamp)
        # Checked before decoding; a depth image before any features is checked when its frame's features come.
        problem = None if self.image_size is None else depth_size_problem(
            (int(message.width), int(message.height)), self.image_size)
        if problem is not None:
            self.counter.drop("depth_size_mismatch", f"depth image at stamp {stamp_ns}: {problem}")
            return
        try:
            self.depths.add_depth(stamp_ns, depth_message_to_metres(message))
        except AefabmapError as exc:
            self.counter.drop("bad_depth", str(exc))
            return
        self.store_saver.mark_changed()  # a frame's depths may come after its features were saved

    @node_callback
    def _on_odometry(self, message: Odometry) -> None:
        if self.odometry_gate is None:
            return
        problem = odometry_problem(message)
        if problem is not None:  # the gate would interpolate NaN between its neighbours
            self.counter.drop("bad_odometry", problem)
            return
        if not self.odometry_gate.add_odometry(stamp_to_ns(message.header.stamp), pose_to_gtsam(message.pose.pose)):
            self.counter.drop("odometry_out_of_order", "odometry stamp not after the previous one")
            return
        # Only the closures this odometry reaches can be judged now; the others keep waiting, in order, without
        # their poses converted again for every odometry message.
        reached: list[LoopClosure] = []
        still_waiting: list[LoopClosure] = []
        for closure in self.awaiting_odometry:
            reaches = self.odometry_gate.reaches(stamp_to_ns(closure.header.stamp), stamp_to_ns(closure.matched_stamp))
            (reached if reaches else still_waiting).append(closure)
        self.awaiting_odometry = still_waiting
        for closure in reached:
            self._publish_if_consistent(closure)

    def _publish_if_consistent(self, closure: LoopClosure) -> None:
        """Publish a verified closure once the odometry gate agrees; hold it while odometry is behind its stamps."""
        decision = self._odometry_decision(closure)
        if decision is GateDecision.WAIT:
            # Tracking goes on from it meanwhile, as it would without the gate: every closure tracked from it is
            # verified and judged by the gate itself.
            self.track.accept(stamp_to_ns(closure.header.stamp), stamp_to_ns(closure.matched_stamp))
            self.awaiting_odometry.append(closure)
            if len(self.awaiting_odometry) > self.max_pending:
                oldest = self.awaiting_odometry.pop(0)
                self.counter.drop("odometry_never_came", f"loop closure query {oldest.query_id}: no odometry up "
                                                         f"to its stamp while {self.max_pending} newer ones waited")
            return
        if decision is GateDecision.PUBLISH:
            self.track.accept(stamp_to_ns(closure.header.stamp), stamp_to_ns(closure.matched_stamp))  # idempotent
            self.publisher.publish(closure)
            sent_ns = self.arrivals.get(stamp_to_ns(closure.header.stamp))
            if sent_ns is not None:
                self.delays_s.append((time.time_ns() - sent_ns) / 1e9)

    def _odometry_decision(self, closure: LoopClosure) -> GateDecision:
        """The odometry gate on one verified closure (always PUBLISH when it is off or inactive); refusals are
        counted and logged."""
        gate = self.odometry_gate
        if gate is None or not gate.active:
            return GateDecision.PUBLISH
        text = f"loop closure query {closure.query_id} -> place {closure.matched_place_id}"
        if not closure.pose_available:
            self.counter.drop("no_pose_for_odometry_gate", f"{text} has no relative pose to check against odometry")
            return GateDecision.REFUSE
        problem = loop_closure_pose_problem(closure)
        if problem is not None:
            self.counter.drop("bad_closure_pose", f"{text}: {problem}")
            return GateDecision.REFUSE
        result, distance = gate.check(stamp_to_ns(closure.header.stamp), stamp_to_ns(closure.matched_stamp),
                                      *loop_closure_pose(closure))
        if result is GateResult.CONSISTENT:
            return GateDecision.PUBLISH
        if result is GateResult.NOT_YET:
            return GateDecision.WAIT
        if result is GateResult.NO_ODOMETRY:
            # A place mapped before this odometry began (a map reloaded after a restart): odometry has nothing to
            # say about it, as for a robot without odometry.
            self.counter.ok("unchecked_place_before_odometry")
            return GateDecision.PUBLISH
        self.counter.drop(result.value, f"{text} refused: Mahalanobis distance squared {distance:.1f} > gate "
                                        f"{gate.config.gate_chi2:g}")
        return GateDecision.REFUSE

    def _attach_pose(self, closure: LoopClosure, query: CoreFeatures, place: CoreFeatures,
                     verification: Verification) -> None:
        """Fill the closure's relative pose from the matches verification accepted (or say why there is none)."""
        rows = verification.matched_rows
        assert rows is not None, "verify_pair keeps the matched rows of every verification it returns"
        query_points, place_points = matched_points(query, place, rows)
        # The depth store samples the stored keypoints in their order: a keypoint row is its depth's index.
        place_depths = self._depths_at(stamp_to_ns(closure.matched_stamp), rows[:, 1])
        query_depths = self._depths_at(stamp_to_ns(closure.header.stamp), rows[:, 0])
        outcome = relative_pose(query_points, place_points, self.camera, self.pose_config, place_depths,
                                None if place_depths is None else query_depths)
        fill_relative_pose(closure, outcome)
        self.counter.ok(f"pose_{outcome.status.name.lower()}")

    def _depths_at(self, stamp_ns: int, keypoint_rows: np.ndarray) -> np.ndarray | None:
        """The stored depths of a frame's keypoints ``keypoint_rows``; None when that frame has none."""
        frame_depths = None if self.depths is None else self.depths.get(stamp_ns)
        return None if frame_depths is None else frame_depths.keypoints[keypoint_rows].astype(np.float64)

    @node_callback
    def _on_posterior(self, message: PlacePosterior) -> None:
        problem = posterior_problem(message)
        if problem is not None:  # re-ranking and tracking index the four arrays by one rank
            self.counter.drop("bad_posterior", problem)
            return
        stamp_ns = stamp_to_ns(message.header.stamp)
        if message.query_id >= 0 and message.current_place_id >= 0:
            self.timeline.add(stamp_ns, int(message.current_place_id))
        self.posteriors[stamp_ns] = message
        self.posteriors.move_to_end(stamp_ns)
        while len(self.posteriors) > POSTERIOR_HISTORY:
            self.posteriors.popitem(last=False)
        self._verify_if_ready(stamp_ns)

    @node_callback
    def _on_loop_closure(self, message: LoopClosure) -> None:
        query_ns = stamp_to_ns(message.header.stamp)
        self.pending[query_ns] = message
        self.pending.move_to_end(query_ns)
        while len(self.pending) > self.max_pending:
            oldest_ns, oldest = self.pending.popitem(last=False)
            if oldest_ns not in self.store:
                self.counter.drop("query_features_never_came",
                                  f"no features stamped like the closure of query {oldest.query_id}")
            else:
                self.counter.drop("query_posterior_never_came",
                                  f"no place_posteriors message for query {oldest.query_id} "
                                  "(candidates: 1 verifies without them)")
        self._verify_if_ready(query_ns)

    def _verify_if_ready(self, query_ns: int) -> None:
        """Verify the closure of this query once its features (and posterior, to re-rank) are in; track a
        loop through a frame without a closure once its features and posterior are in."""
        if query_ns not in self.store:
            return
        posterior = self.posteriors.get(query_ns)
        if query_ns in self.pending:
            if self.rerank and posterior is None:
                return
            self.posteriors.pop(query_ns, None)  # this frame is done
            self._verify(self.pending.pop(query_ns), posterior)
        elif posterior is not None and not posterior.loop_closure_candidate:
            del self.posteriors[query_ns]  # this frame is done: no closure will come for it
            self._track(posterior)

    def _posterior_places(self, posterior: PlacePosterior) -> list[tuple[int, PlaceToVerify]]:
        """The posterior's candidates (rank, place) whose features are stored, best first."""
        places = []
        for rank, (place_id, stamp) in enumerate(zip(posterior.place_ids, posterior.place_stamps, strict=False)):
            features = self.store.get(stamp_to_ns(stamp))
            if features is not None:
                places.append((rank, PlaceToVerify(int(place_id), stamp, features)))
        return places

    def _candidates(self, message: LoopClosure, posterior: PlacePosterior | None) -> list[PlaceToVerify] | None:
        """The matched place first, then the posterior's next best with stored features; None: place unknown."""
        matched = self.store.get(stamp_to_ns(message.matched_stamp))
        if matched is None:
            return None
        candidates = [PlaceToVerify(int(message.matched_place_id), message.matched_stamp, matched)]
        if posterior is not None:
            matched_id = candidates[0].place_id
            others = [place for _, place in self._posterior_places(posterior) if place.place_id != matched_id]
            candidates += others[: self.config.candidates - 1]
        return candidates

    def _track(self, posterior: PlacePosterior) -> None:
        """Loop tracking: verify the frame's top candidates near the last verified place, then the stored
        frames nearest that place; publish the accepted one with the most inliers."""
        query_ns = stamp_to_ns(posterior.header.stamp)
        query = self.store.get(query_ns)
        if query is None or not self.track.is_active(query_ns):
            return
        if self._behind(query_ns):
            self.counter.ok("tracking_skipped_behind")
            return
        try:
            tried: set[int] = set()
            match = self._track_candidates(query_ns, query, posterior, tried)
            if match is None:
                match = self._track_nearby_frames(query_ns, query, posterior, tried)
        except AefabmapError as exc:
            self.counter.drop("unverifiable", str(exc))
            return
        if not tried:
            return
        if match is None:
            self.counter.ok("track_rejected")
            return
        place = match.place
        closure = LoopClosure(
            header=posterior.header, query_id=posterior.query_id, query_place_id=posterior.assigned_place_id,
            matched_place_id=place.place_id, matched_stamp=place.stamp, probability=match.probability,
            log_likelihood=match.log_likelihood, inliers=match.verification.inliers,
        )
        self._attach_pose(closure, query, place.features, match.verification)
        self.counter.ok("accepted_by_tracking")
        self.get_logger().info(f"loop closure query {posterior.query_id} -> place {place.place_id} tracked: "
                               f"{match.verification.inliers} inliers of {match.verification.matches} matches",
                               throttle_duration_sec=LOG_THROTTLE_S)
        self._publish_if_consistent(closure)

    def _within_lag(self, query_ns: int, candidates: list[PlaceToVerify]) -> Iterator[PlaceToVerify]:
        """The detection, then the other candidates while the verifier is not behind (max_lag_s): re-ranking
        stops where the time is spent, so a closure is published within about max_lag_s of its features."""
        for rank, candidate in enumerate(candidates):
            if rank > 0 and self._behind(query_ns):
                self.counter.ok("reranking_cut_short_behind")
                return
            yield candidate

    def _behind(self, query_ns: int) -> bool:
        """More than max_lag_s since the query's features were sent: the verifier is behind the camera."""
        sent_ns = self.arrivals.get(query_ns)
        return bool(self.max_lag_s) and sent_ns is not None and time.time_ns() - sent_ns > self.max_lag_s * 1e9

    def _track_candidates(self, query_ns: int, query: CoreFeatures, posterior: PlacePosterior,
                          tried: set[int]) -> TrackedMatch | None:
        """The query's top candidates near the tracked place, best verified wins (their stamps go to ``tried``)."""
        near = self.track.near(query_ns, self._posterior_places(posterior),
                               lambda ranked: stamp_to_ns(ranked[1].stamp))[: self.config.candidates]
        tried.update(stamp_to_ns(place.stamp) for _, place in near)
        outcome = rerank_by_inliers(near, lambda ranked: self._verify_pair(query_ns, query, ranked[1]))
        if outcome is None:
            return None
        rank, place = near[outcome.winner]
        return TrackedMatch(place, float(posterior.probabilities[rank]), float(posterior.log_likelihoods[rank]),
                            outcome.verification)

    def _track_nearby_frames(self, query_ns: int, query: CoreFeatures, posterior: PlacePosterior,
                             tried: set[int]) -> TrackedMatch | None:
        """The stored frames nearest the tracked place in time, not tried yet; best verified wins."""
        min_age_ns = round(self.config.track_min_age_seconds * 1e9)
        places = []
        for stamp_ns in self.track.nearby_frames(query_ns, self.timeline, self.config.track_frames, min_age_ns):
            features = self.store.get(stamp_ns)
            place_id = self.timeline.place_of(stamp_ns)
            if stamp_ns not in tried and features is not None and place_id is not None:
                places.append(PlaceToVerify(place_id, time_from_ns(stamp_ns), features))
        tried.update(stamp_to_ns(place.stamp) for place in places)
        outcome = rerank_by_inliers(places, lambda place: self._verify_pair(query_ns, query, place))
        if outcome is None:
            return None
        place = places[outcome.winner]
        # The place's posterior when it is among the query's top candidates; FAB-MAP did not rank it otherwise.
        ranks = [rank for rank, place_id in enumerate(posterior.place_ids) if place_id == place.place_id]
        if ranks:
            return TrackedMatch(place, float(posterior.probabilities[ranks[0]]),
                                float(posterior.log_likelihoods[ranks[0]]), outcome.verification)
        return TrackedMatch(place, 0.0, float("nan"), outcome.verification)

    def _verify_pair(self, query_ns: int, query: CoreFeatures, place: PlaceToVerify) -> Verification:
        """The geometric check of one pair; with both frames' depths and the intrinsics, the metric test
        decides too (verification/metric.py)."""
        verification = verify_pair(query, place.features, self.config,
                                   self._pair_depths(query_ns, stamp_to_ns(place.stamp)))
        if verification.accepted and not verification.epipolar_accepted:
            self.counter.ok("metric_test_accepted")
        elif verification.epipolar_accepted and not verification.accepted:
            self.counter.ok("metric_test_refused_no_view_overlap")
        return verification

    def _pair_depths(self, query_ns: int, place_ns: int) -> KeypointDepths | None:
        if self.depths is None or self.camera is None or self.image_size is None:
            return None
        query_depths, place_depths = self.depths.get(query_ns), self.depths.get(place_ns)
        if query_depths is None or place_depths is None:
            return None
        return KeypointDepths(self.camera, self.image_size, query_depths.keypoints, place_depths.keypoints,
                              query_depths.grid, place_depths.grid)

    def _verify(self, message: LoopClosure, posterior: PlacePosterior | None) -> None:
        query_ns = stamp_to_ns(message.header.stamp)
        query = self.store.get(query_ns)
        candidates = self._candidates(message, posterior)
        if query is None or candidates is None:
            self.counter.drop("place_features_unknown",
                              f"no stored features of place {message.matched_place_id} (before this node started, "
                              "or older than max_stored_frames)")
            return
        try:
            outcome = rerank_by_inliers(
                self._within_lag(query_ns, candidates), lambda candidate: self._verify_pair(query_ns, query, candidate),
                require_best=True)
        except AefabmapError as exc:
            self.counter.drop("unverifiable", str(exc))
            return
        text = f"loop closure query {message.query_id} -> place {message.matched_place_id}"
        if outcome is None:
            self.counter.ok("rejected")
            # A stream of aliased candidates must not flood the log.
            self.get_logger().info(f"{text} rejected: fewer than {self.config.min_inliers} inliers",
                                   throttle_duration_sec=LOG_THROTTLE_S)
            if posterior is not None:
                self._track(posterior)  # the detection failed; the frame may still continue a verified loop
            return
        self.counter.ok("accepted")
        winner = candidates[outcome.winner]
        if outcome.winner > 0:
            self.counter.ok("moved_to_better_verified_place")
            text += f" moved to place {winner.place_id} (candidate {outcome.winner + 1})"
            message.matched_place_id = winner.place_id
            message.matched_stamp = winner.stamp
        self.get_logger().info(f"{text} accepted: {outcome.verification.inliers} inliers of "
                               f"{outcome.verification.matches} matches")
        message.inliers = outcome.verification.inliers
        self._attach_pose(message, query, winner.features, outcome.verification)
        self._publish_if_consistent(message)

    def _reconfigure(self, changes: dict[str, Any]) -> None:
        self.config = replace(self.config, **changes)  # validated as a whole: ConfigError refuses the change

    def _reload_stores(self, folder: Path) -> None:
        """What ``store_dir`` holds: a corrupt chunk stops start-up (ERROR) and is not overwritten."""
        # Every kind of chunk, whether or not this run keeps it (a run without depth still cleans depth chunks'
        # leftovers).
        for chunk_folder in (FeatureStoreFolder, FrameDepthFolder, FrameTimelineFolder):
            for leftover in remove_stale_temporaries(folder, chunk_pattern(chunk_folder.PREFIX)):
                self.get_logger().warning(f"deleted {leftover}, left by a save that was killed")
        if self.store_folder is not None:
            self.store_folder.load_into(self.store)
            if len(self.store):
                self.get_logger().info(f"reloaded the features of {len(self.store)} frames from {folder}")
        if self.depth_folder is not None and self.depths is not None:
            self.depth_folder.load_into(self.depths)
            if len(self.depths):
                self.get_logger().info(f"reloaded the depths of {len(self.depths)} frames")
        if self.timeline_folder is not None:
            # Without it, loop tracking after a restart would never reach the frames stored before it.
            self.timeline_folder.load_into(self.timeline)
            if len(self.timeline):
                self.get_logger().info(f"reloaded the places of {len(self.timeline)} frames for loop tracking")

    def _save_store(self, _folder: Path) -> None:
        if self.store_folder is not None:
            self.store_folder.save(self.store)
        if self.depth_folder is not None and self.depths is not None:
            self.depth_folder.save(self.depths)
        if self.timeline_folder is not None:
            self.timeline_folder.save(self.timeline)

    def close(self) -> bool:
        """The final store save; False when it failed (the process then exits 1)."""
        saved = self.store_saver.final_save()
        self.get_logger().info(
            f"verifier_node: {len(self.store)} frames stored ({self.store.nbytes / 2**20:.1f} MiB"
            f"{'' if saved else ', NOT all saved'}), {len(self.pending)} closures still waiting; "
            f"{self.counter.summary()}; {delay_summary(self.delays_s)}; "
            + ("; ".join(sensor_input.summary() for sensor_input in self.inputs)
                                              or "no sensor inputs")
        )
        return saved


def delay_summary(delays_s: Sequence[float]) -> str:
    """From a query's features being sent to its closure going out: median, p95 and max."""
    if not delays_s:
        return "no closure published"
    p50, p95 = np.percentile(delays_s, [50, 95])
    return f"features -> published closure: median {p50:.3f} s, p95 {p95:.3f} s, max {max(delays_s):.3f} s"


def _camera_from_parameter(values: list[float]) -> CameraModel | None:
    """fx, fy, cx, cy -> intrinsics; None when unset (all zero)."""
    if len(values) != 4:
        raise ConfigError(f"verifier_node: camera_matrix must be [fx, fy, cx, cy], got {values}")
    fx, fy, cx, cy = (float(value) for value in values)
    if not any((fx, fy, cx, cy)):
        return None
    if fx <= 0 or fy <= 0:
        raise ConfigError(f"verifier_node: camera_matrix focal lengths must be > 0, got {values}")
    return CameraModel(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))


def main(args: list[str] | None = None) -> int:
    return run_node(VerifierNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
