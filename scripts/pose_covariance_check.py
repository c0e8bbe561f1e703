"""How often a run's metric closure poses lie within their own covariance, for a range of keypoint-error floors.

Each metric closure a recorded run published (``OUT/online_recording``) is computed again offline with the
package, as verifier_node computes it: the test bag's image and depth at its two stamps, the model's features
(the strongest the verifier stores), ``verify_pair`` with the verifier's defaults, ``relative_pose`` with both
depths, once per floor (``RelativePoseConfig.min_pixel_sigma_px``). Each pose's error against the sequence's
``groundtruth.tum`` is measured under its covariance (Mahalanobis distance squared, 6 dof, and its translation
block, 3 dof) and the shares outside chi-square's 95 % and 99.9 % regions are printed: a calibrated covariance
leaves 5 % and 0.1 % outside (docs/backend.md, "pose_covariance").

    PYTHONPATH=. .venv/bin/python scripts/pose_covariance_check.py bags/dense/test output/dense_lockstep \\
        --model output/demo/models/autoencoder
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from aefabmap_ros.cli.evaluate_recording import read_recording
from aefabmap_ros.evaluation.closure_listing import read_pose_truth
from aefabmap_ros.features.extraction import Features, extract_features
from aefabmap_ros.io import bags
from aefabmap_ros.io.image_messages import depth_message_to_metres, image_message_to_gray
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.feature_store import DEFAULT_MAX_STORED_FEATURES, stored_rows
from aefabmap_ros.verification.frame_depths import FrameDepths
from aefabmap_ros.verification.geometric import VerificationConfig, matched_points, verify_pair
from aefabmap_ros.verification.metric import KeypointDepths
from aefabmap_ros.verification.pose_error import error_mahalanobis2
from aefabmap_ros.verification.relative_pose import (
    CameraModel,
    RelativePose,
    RelativePoseConfig,
    camera_info_to_model,
    relative_pose,
)

DEFAULT_FLOORS = (0.0, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0)


@dataclasses.dataclass
class Frame:
    features: Features
    depths: FrameDepths | None = None


def read_frames(bag: Path, stamps: set[int], model: Path, topics: argparse.Namespace
                ) -> tuple[dict[int, Frame], CameraModel, tuple[int, int]]:
    """The frames at ``stamps``: the features the verifier stores and their depths (float16, as it keeps them)."""
    feature_config = load_model(model).feature_config
    frames: dict[int, Frame] = {}
    depths: dict[int, np.ndarray] = {}
    camera: CameraModel | None = None
    size = (0, 0)
    for message in bags.read_messages(bag, [topics.image_topic, topics.depth_topic, topics.camera_info_topic]):
        if message.topic == topics.camera_info_topic and camera is None:
            camera = camera_info_to_model(message.message)
            size = (int(message.message.width), int(message.message.height))
        elif message.stamp_ns in stamps and message.topic == topics.image_topic:
            features = extract_features(image_message_to_gray(message.message), feature_config)
            rows = stored_rows(features, DEFAULT_MAX_STORED_FEATURES)
            frames[message.stamp_ns] = Frame(Features(features.keypoints[rows], features.descriptors[rows],
                                                      features.descriptor_type))
        elif message.stamp_ns in stamps and message.topic == topics.depth_topic:
            depths[message.stamp_ns] = depth_message_to_metres(message.message).astype(np.float16).astype(np.float32)
    if camera is None:
        raise SystemExit(f"ERROR: {topics.camera_info_topic} in {bag} holds no calibrated CameraInfo")
    for stamp, frame in frames.items():
        if stamp in depths:
            frame.depths = FrameDepths.sample(depths[stamp], frame.features.keypoints[:, :2].astype(np.float32))
    return frames, camera, size


def recomputed_pose(query: Frame, place: Frame, camera: CameraModel, size: tuple[int, int],
                    config: RelativePoseConfig) -> RelativePose | None:
    """The closure's metric pose as verifier_node computes it, or None when it has none."""
    if query.depths is None or place.depths is None:
        return None
    keypoint_depths = KeypointDepths(camera, size, query.depths.keypoints, place.depths.keypoints,
                                     query.depths.grid, place.depths.grid)
    verification = verify_pair(query.features, place.features, VerificationConfig(), keypoint_depths)
    rows = verification.matched_rows
    if not verification.accepted or rows is None:
        return None
    query_px, place_px = matched_points(query.features, place.features, rows)
    outcome = relative_pose(query_px, place_px, camera, config, place.depths.keypoints[rows[:, 1]].astype(np.float64),
                            query.depths.keypoints[rows[:, 0]].astype(np.float64))
    return outcome.pose if outcome.pose is not None and outcome.pose.metric else None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("test", type=Path, help="the test sequence: bag/ and groundtruth.tum")
    parser.add_argument("run", type=Path, help="an aefabmap_demo --out folder (its online_recording)")
    parser.add_argument("--model", type=Path, required=True, help="the run's model (its feature settings)")
    parser.add_argument("--floors", type=float, nargs="+", default=list(DEFAULT_FLOORS))
    parser.add_argument("--image-topic", default="/image")
    parser.add_argument("--depth-topic", default="/depth")
    parser.add_argument("--camera-info-topic", default="/camera_info")
    args = parser.parse_args()
    recorded = read_recording(args.run / "online_recording").published
    pairs = [(stamp_to_ns(m.header.stamp), stamp_to_ns(m.matched_stamp)) for m in (recorded[1] if recorded else [])
             if m.pose_available and m.translation_metric]
    truth = read_pose_truth(args.test / "groundtruth.tum")
    frames, camera, size = read_frames(args.test / "bag", {s for pair in pairs for s in pair}, args.model, args)
    print(f"{args.run}: {len(pairs)} metric closure poses published")
    print("| floor (px) | poses | 6 dof: outside 95 % / 99.9 % | translation: outside 95 % / 99.9 % |")
    print("|---|---|---|---|")
    for floor in args.floors:
        config = RelativePoseConfig(min_pixel_sigma_px=floor)
        full, translation = [], []
        for query_ns, place_ns in pairs:
            query_pose, place_pose = truth.pose_at(query_ns), truth.pose_at(place_ns)
            if query_ns not in frames or place_ns not in frames or query_pose is None or place_pose is None:
                continue
            pose = recomputed_pose(frames[query_ns], frames[place_ns], camera, size, config)
            if pose is None:
                continue
            measured = np.eye(4)
            measured[:3, :3], measured[:3, 3] = pose.rotation, pose.translation
            true = np.linalg.inv(query_pose) @ place_pose
            full.append(error_mahalanobis2(true, measured, pose.covariance))
            error = measured[:3, 3] - true[:3, 3]
            translation.append(float(error @ np.linalg.solve(pose.covariance[:3, :3], error)))
        shares = [np.mean(np.asarray(values) > chi2.ppf(level, dof))
                  for values, dof in ((full, 6), (translation, 3)) for level in (0.95, 0.999)]
        print(f"| {floor:g} | {len(full)} | {shares[0]:.1%} / {shares[1]:.1%} | {shares[2]:.1%} / {shares[3]:.1%} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
