"""verifier_node's parameters: declared once here, read into the chain's settings.

``max_store_mb`` (512) bounds the frames the verifier keeps (features, keypoint depths): about 5,000
frames of 300-500 SIFT features with depth (~100 KiB a frame), a quarter of a 2 GB robot computer's memory
and an eighth of a 4 GB one, with the rest of the stack (images, the autoencoder, FAB-MAP's map) beside
it. The frames that created places are kept longest (verification/frame_store.py): at a place every few
metres that is several kilometres of revisitable route.

``odometry_wait_s`` (5 s of stamp time) is how long a verified closure waits for odometry to reach its
stamps: a verifier under load takes odometry late, and a closure must not be dropped for that. How late
it got is printed in the shutdown summary (``odometry behind the newest frame``); see docs/verifier.md
for the measurements the default comes from.

``robots`` (a base station, docs/fleet.md): each robot's frames come from its feature server on request, with
their depths and the robot's camera, so ``depth_topic``, ``camera_info`` and ``camera_matrix`` are not used;
odometry comes from ``/<robot>/aefabmap/odom`` (the robot's, thinned by its feature server).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from rclpy.node import Node

from aefabmap_ros.backend.pose_graph import PoseGraphConfig
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.common import declare_config, declare_parameter
from aefabmap_ros.nodes.fleet_parameters import declare_robots
from aefabmap_ros.nodes.gtsam_poses import extrinsic_to_gtsam
from aefabmap_ros.nodes.sensor_inputs import check_sensor_qos
from aefabmap_ros.verification.feature_store import DEFAULT_MAX_STORED_FEATURES
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.relative_pose import CameraModel, RelativePoseConfig

# The example backend's drift model and gate (pose_graph_node's parameters of the same names).
ODOMETRY_GATE_SETTINGS = frozenset({"odometry_translation_drift", "odometry_rotation_drift_rad_per_m",
                                    "odometry_min_sigma", "loop_min_sigma_m", "loop_min_sigma_rad", "gate_chi2",
                                    "max_odometry"})

REQUESTS_PER_FRAME = ("Several robots: frames asked for per frame a robot sends, on average, beyond the places "
                      "(queries and tracked frames within it; 0 = no budget): each robot's link carries its words "
                      "and at most this many answers per frame (docs/fleet.md).")

# The geometric check's settings, read afresh for every pair: ``ros2 param set`` applies them from the
# next closure on. The others size the store or the subscriptions at start-up and are refused.
RUNTIME_SETTINGS = frozenset({"min_inliers", "min_inlier_ratio", "ratio", "ransac_threshold_px", "confidence",
                              "max_iterations", "metric_min_inliers", "metric_min_view_overlap", "metric_ratio",
                              "metric_min_covisibility", "metric_depth_tolerance_m",
                              "metric_depth_relative_tolerance"})


@dataclass(frozen=True)
class VerifierParameters:
    queue_depth: int
    max_frames: int
    max_store_bytes: int
    max_features: int
    max_pending: int
    max_lag_s: float
    drop_after_lag_s: float
    store_dir: str
    save_period_s: float
    config: VerificationConfig
    pose_config: RelativePoseConfig
    camera: CameraModel | None  # camera_matrix; None: from camera_info
    depth_topic: str
    depth_wait_s: float
    odometry_gate: bool
    odometry_wait_s: float
    max_awaiting_odometry: int
    base_to_camera: gtsam.Pose3
    drift_model: PoseGraphConfig
    sensor_qos: str
    robots: tuple[str, ...] = ()  # several robots (docs/fleet.md): each robot's frames from its feature server
    requests_per_frame: float = 0.4  # several robots: the link's budget (verification/frame_requests.py)


def declare_verifier_parameters(node: Node) -> VerifierParameters:
    """Every parameter of verifier_node, checked (ConfigError names the bad one)."""
    def number(name: str, default: float, description: str) -> float:
        return float(declare_parameter(node, name, default, description))

    parameters = VerifierParameters(
        queue_depth=declare_parameter(node, "queue_depth", 100, "Queue depth of the features, depth and CameraInfo "
                                      "subscriptions, and of the candidates and posteriors (at least 100)."),
        max_frames=declare_parameter(node, "max_stored_frames", 20000, "Frames kept for verification at most "
                                     "(with max_store_mb; see verification/frame_store.py for which go first)."),
        max_store_bytes=round(number("max_store_mb", 512.0, "Memory of the kept frames' features and depths at "
                                     "most (MiB); past it the frames that only joined a place go first.") * 2**20),
        max_features=declare_parameter(node, "max_stored_features", DEFAULT_MAX_STORED_FEATURES, "Strongest "
                                       "keypoints kept per frame (0 = all); ~128 KiB per frame of 500 SIFT features."),
        max_pending=declare_parameter(node, "max_pending", 100, "Loop closures waiting for their query's "
                                      "features (and posterior) at most."),
        max_lag_s=number("max_lag_s", 0.25, "A closure verified more than this long after its query's features "
                         "were sent is checked against its detection only (no re-ranking) and loop tracking waits, "
                         "so the verifier catches up with a live camera instead of falling behind during a "
                         "revisit (seconds; 0 = never: a lockstep replay, reproducible)."),
        drop_after_lag_s=number("drop_after_lag_s", 1.0, "While the verifier takes features more than this long "
                                "after they were sent (it is that far behind the camera), it drops the detections "
                                "it takes unverified (dropped_behind), so its lag stays bounded (seconds, 0 or >= "
                                "max_lag_s; 0 = never: a lockstep replay)."),
        store_dir=declare_parameter(node, "store_dir", "", "Folder the frame store (features, depths, each "
                                    "frame's place) is saved to and reloaded from ('' = memory only)."),
        save_period_s=number("save_period_s", 10.0, "Save the frames added since the last save this often "
                             "(seconds; 0 = only on shutdown)."),
        config=declare_config(node, VerificationConfig),
        pose_config=declare_config(node, RelativePoseConfig, prefix="pose_"),
        camera=_camera_from_parameter(declare_parameter(
            node, "camera_matrix", [0.0, 0.0, 0.0, 0.0],
            "Intrinsics fx, fy, cx, cy for the relative pose (all 0 = take them from camera_info).")),
        depth_topic=declare_parameter(node, "depth_topic", "", "Aligned depth image topic (16UC1 mm or 32FC1 m) "
                                      "for metric relative poses ('' = monocular)."),
        depth_wait_s=number("depth_wait_s", 2.0, "With depth_topic, a query waits for its own depth image until "
                            "it comes, a later one comes, or the newest frame is this much newer (stamp time); "
                            "then it is verified without it (query_depth_missing)."),
        odometry_gate=declare_parameter(node, "odometry_gate", True, "Refuse verified closures that odometry on "
                                        "'odom' contradicts beyond its drift (active once odometry arrives; see "
                                        "backend/odometry_gate.py)."),
        odometry_wait_s=number("odometry_wait_s", 5.0, "A verified closure waits this long (stamp time: the "
                               "newest frame is that much newer) for odometry to reach its stamps, then is "
                               "dropped as odometry_never_came."),
        max_awaiting_odometry=declare_parameter(node, "max_awaiting_odometry", 1000, "Verified closures waiting "
                                                "for odometry at most (the oldest is dropped)."),
        base_to_camera=extrinsic_to_gtsam(declare_parameter(
            node, "base_to_camera", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], "The camera's pose in the odometry's "
            "child (base) frame, [x, y, z, qx, qy, qz, qw] (identity: the camera is the base frame), for the "
            "odometry gate.")),
        drift_model=declare_config(node, PoseGraphConfig, only=ODOMETRY_GATE_SETTINGS),
        sensor_qos=check_sensor_qos(declare_parameter(
            node, "sensor_qos", "auto", "QoS of the camera_info, depth and odom subscriptions: auto (reliable, "
            "moving to best effort once a publisher offers only that, as drivers often do), best_effort "
            "(= sensor_data) or reliable."), "sensor_qos"),
        robots=tuple(declare_robots(node)),
        requests_per_frame=number("requests_per_frame", 0.4, REQUESTS_PER_FRAME),
    )
    _check(parameters)
    return parameters


def _check(parameters: VerifierParameters) -> None:
    bounds = {"max_stored_frames": parameters.max_frames, "max_pending": parameters.max_pending,
              "max_awaiting_odometry": parameters.max_awaiting_odometry, "max_store_mb": parameters.max_store_bytes}
    too_small = [f"{name} ({value})" for name, value in bounds.items() if value < 1]
    if parameters.drop_after_lag_s and not parameters.drop_after_lag_s >= parameters.max_lag_s:
        raise ConfigError(f"verifier_node: drop_after_lag_s ({parameters.drop_after_lag_s}) must be 0 (never) or >= "
                          f"max_lag_s ({parameters.max_lag_s}): a closure is cut short before it is dropped")
    if too_small or parameters.max_features < 0 or not parameters.odometry_wait_s >= 0 \
            or not parameters.depth_wait_s >= 0 or not parameters.requests_per_frame >= 0:
        raise ConfigError(f"verifier_node: {', '.join(too_small) or 'the bounds'} must be >= 1 (max_store_mb > 0), "
                          f"max_stored_features ({parameters.max_features}), odometry_wait_s "
                          f"({parameters.odometry_wait_s}), depth_wait_s ({parameters.depth_wait_s}) and "
                          f"requests_per_frame ({parameters.requests_per_frame}) >= 0")


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
