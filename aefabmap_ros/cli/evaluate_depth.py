"""aefabmap_eval's depth and odometry inputs: the test sequence's depth and intrinsics, for verification's
metric test, and its odometry, for the online chain's odometry gate (``--odometry-topic``).

With them the "+ GV" rows and the online chain verify as verifier_node does with ``depth_topic`` and
camera_info: a pair the epipolar test refuses gets the metric test (verification/metric.py). A bag
brings its own aligned depth topic and CameraInfo topic, matched to the images by header stamp; a
folder of images a folder of 16-bit depth PNGs (millimetres, one per image, in the same order) and a
camera_info.yaml. Frames without a depth image are verified by the epipolar test alone.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import gtsam
import numpy as np

from aefabmap_ros.backend.odometry_gate import OdometryGate
from aefabmap_ros.backend.pose_graph import PoseGraphConfig
from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.evaluation.online_chain import ChainInputs
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.io import bags
from aefabmap_ros.io.image_messages import depth_image_to_metres, depth_message_to_metres
from aefabmap_ros.io.rgbd import list_depth_files, read_camera_info_yaml
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.verification.feature_store import DEFAULT_MAX_STORED_FEATURES, stored_rows
from aefabmap_ros.verification.frame_depths import (
    DepthGrid,
    FrameDepths,
    depth_at_pixels,
    sample_depth_grid,
)
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.relative_pose import CameraModel, camera_info_to_model, pose_message_to_matrix
from aefabmap_ros.verification.reranking import SequenceDepths


def sequence_depths(args: argparse.Namespace, source: ImageSource,
                    features: Sequence[Features]) -> SequenceDepths | None:
    """The depth at every keypoint of every test frame, with the camera; None when no depth was given."""
    if args.depth is None and args.depth_topic is None:
        if args.camera_info is not None or args.camera_info_topic is not None:
            raise ConfigError("--camera-info/--camera-info-topic are for the metric test: give --depth (folder) "
                              "or --depth-topic (bag) too")
        return None
    if args.depth is not None and args.images is None:
        raise ConfigError("--depth is a folder of depth PNGs for --images; with --bag give --depth-topic")
    if args.depth_topic is not None and args.bag is None:
        raise ConfigError("--depth-topic is a topic of --bag; with --images give --depth DIR")
    if args.camera_info_topic is not None and args.bag is None:
        raise ConfigError("--camera-info-topic is a topic of --bag; with --images give --camera-info FILE")
    if (args.camera_info is None) == (args.camera_info_topic is None):
        raise ConfigError("the metric test needs the intrinsics: give --camera-info FILE or --camera-info-topic "
                          "TOPIC, exactly one")
    camera, size = (_camera_from_yaml(args.camera_info) if args.camera_info is not None
                    else _camera_from_bag(args.bag, args.camera_info_topic))
    images = (_depth_from_folder(args.depth, len(features)) if args.depth is not None
              else _depth_from_bag(args.bag, args.depth_topic, source.stamps_ns()))
    keypoint_depths: list[np.ndarray | None] = [None] * len(features)
    depth_grids: list[DepthGrid | None] = [None] * len(features)
    stored: list[FrameDepths | None] = [None] * len(features)
    for index, depth in images:  # one image at a time: a long sequence's depth does not fit in memory
        if (depth.shape[1], depth.shape[0]) != size:
            raise DataError(f"depth image {index} is {depth.shape[1]}x{depth.shape[0]}, the camera's images "
                            f"{size[0]}x{size[1]}")
        keypoint_depths[index] = depth_at_pixels(depth, features[index].keypoints[:, :2])
        depth_grids[index] = sample_depth_grid(depth)
        rows = stored_rows(features[index], DEFAULT_MAX_STORED_FEATURES)
        stored[index] = FrameDepths.sample(depth.astype(np.float16).astype(np.float32),
                                           features[index].keypoints[rows, :2].astype(np.float32))
    if all(depths is None for depths in keypoint_depths):
        raise DataError(f"no depth image of {args.depth or args.depth_topic} belongs to a test image")
    return SequenceDepths(camera, size, keypoint_depths, depth_grids, stored)


def _camera_from_yaml(path: Path) -> tuple[CameraModel, tuple[int, int]]:
    info = read_camera_info_yaml(path)
    return CameraModel(info.matrix, info.distortion), (info.width, info.height)


def _camera_from_bag(bag: Path, topic: str) -> tuple[CameraModel, tuple[int, int]]:
    for message in bags.read_messages(bag, [topic]):
        info = message.message
        camera = camera_info_to_model(info)
        if camera is not None and int(info.width) > 0 and int(info.height) > 0:
            return camera, (int(info.width), int(info.height))
    raise DataError(f"{topic} in {bag} holds no calibrated CameraInfo (K and image size)")


def _depth_from_bag(bag: Path, topic: str, image_stamps_ns: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """(frame, depth in metres) of the test images the bag has a depth image for, matched by header stamp."""
    frame_of = {int(stamp): index for index, stamp in enumerate(image_stamps_ns.tolist())}
    for message in bags.read_messages(bag, [topic]):
        index = frame_of.get(int(message.stamp_ns))
        if index is not None:
            yield index, depth_message_to_metres(message.message)


def _depth_from_folder(folder: Path, num_frames: int) -> Iterator[tuple[int, np.ndarray]]:
    files = list_depth_files(folder)
    if len(files) != num_frames:
        raise DataError(f"depth folder {folder} has {len(files)} images for {num_frames} test images")
    for index, path in enumerate(files):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None or image.dtype != np.uint16 or image.ndim != 2:
            raise DataError(f"depth image {path} must be a readable 16-bit single-channel PNG")
        yield index, depth_image_to_metres(image, "16UC1")


def chain_inputs(args: argparse.Namespace, features: Sequence[Features], config: VerificationConfig,
                 depths: SequenceDepths | None) -> ChainInputs:
    """What verifier_node's chain verifies with offline: the features, the depths and intrinsics when given,
    and the odometry of ``--odometry-topic`` (its gate)."""
    odometry = [] if args.odometry_topic is None else _odometry_from_bag(args.bag, args.odometry_topic)
    if depths is None:
        return ChainInputs(config, features, odometry=odometry, gate_factory=example_backend_gate)
    return ChainInputs(config, features, depths.stored, depths.camera, depths.image_size, odometry,
                       gate_factory=example_backend_gate)


def example_backend_gate() -> OdometryGate:
    """verifier_node's gate with its default drift model, the camera at the odometry's base frame."""
    return OdometryGate(PoseGraphConfig(), gtsam.Pose3())


def _odometry_from_bag(bag: Path | None, topic: str) -> list[tuple[int, gtsam.Pose3]]:
    """(stamp, T_odom_base) of every odometry message of the bag, in stamp order (a repeated stamp once)."""
    if bag is None:
        raise ConfigError("--odometry-topic is a topic of --bag")
    odometry: dict[int, gtsam.Pose3] = {}
    for message in bags.read_messages(bag, [topic]):
        matrix = pose_message_to_matrix(message.message.pose.pose)
        odometry[int(message.stamp_ns)] = gtsam.Pose3(np.asarray(matrix, dtype=np.float64))
    if not odometry:
        raise DataError(f"{bag} has no messages on {topic}")
    return sorted(odometry.items(), key=lambda item: item[0])
