"""The messages that cross a robot's link to the base station (docs/fleet.md) <-> plain values.

Every frame: the words, as ``aefabmap_msgs/BagOfWords`` without ``keypoint_words`` (nobody on the base reads
which keypoint got which word, and it is 4 bytes a keypoint). On request: ``aefabmap_msgs/RequestedFeatures``,
the frame as the verifier keeps it (keypoint positions, descriptors compressed with zlib, keypoint depths and
the coarse depth grid, the camera's intrinsics), asked for with ``aefabmap_msgs/FeatureRequest``. What the
base receives is checked here (``DataError`` naming the fault), so a bad answer is dropped, never stored.
"""

from __future__ import annotations

import zlib
from typing import Any, NamedTuple

import numpy as np
from aefabmap_msgs.msg import BagOfWords, FeatureRequest, RequestedFeatures

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.extraction import Features, compact_descriptors, restore_descriptors
from aefabmap_ros.features.kinds import FEATURE_TYPES
from aefabmap_ros.features.matching import check_features
from aefabmap_ros.nodes.messages import copy_header, header_stamp_problem, time_from_ns
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.feature_server import ServedFrame
from aefabmap_ros.verification.frame_depths import DepthGrid, FrameDepths
from aefabmap_ros.verification.pair_check import RobotCamera
from aefabmap_ros.verification.relative_pose import CameraModel

ZLIB_LEVEL = 6  # ~3 ms for 300 SIFT descriptors; a quarter fewer bytes than raw (docs/fleet.md)
MAX_KEYPOINTS = 100_000  # an answer claiming more is refused before anything is decompressed


class ReceivedFrame(NamedTuple):
    """A robot's frame as the base takes it from a RequestedFeatures message."""

    stamp_ns: int
    robot: str
    features: Features  # (N, 2) keypoints
    depths: FrameDepths | None
    camera: RobotCamera


def words_for_link(message: BagOfWords) -> BagOfWords:
    """The words message as it crosses the link: the same, without ``keypoint_words``."""
    out = BagOfWords(header=message.header, vocabulary_id=message.vocabulary_id,
                     vocabulary_size=message.vocabulary_size, num_features=message.num_features)
    out.word_ids, out.counts = message.word_ids, message.counts
    return out


def feature_request(stamps_ns: list[int], now_ns: int) -> FeatureRequest:
    message = FeatureRequest(stamps=[time_from_ns(stamp) for stamp in stamps_ns])
    message.header.stamp = time_from_ns(now_ns)
    return message


def requested_stamps(message: FeatureRequest) -> list[int]:
    """The stamps a request names (DataError for one that is no ROS time)."""
    stamps = []
    for stamp in message.stamps:
        if not (0 <= stamp.nanosec < 1_000_000_000) or stamp.sec < 0:
            raise DataError(f"FeatureRequest stamp {stamp.sec}.{stamp.nanosec:09d} is not a ROS time")
        stamps.append(stamp_to_ns(stamp))
    return stamps


def camera_values(camera_info: Any) -> tuple[list[float], list[float]]:
    """([fx, fy, cx, cy], distortion) of a CameraInfo; zeros for an uncalibrated camera (K all zero)."""
    k = [float(value) for value in camera_info.k]
    return [k[0], k[4], k[2], k[5]], [float(value) for value in camera_info.d]


def served_frame_to_message(frame: ServedFrame, robot: str, header: Any,
                            camera: tuple[list[float], list[float]] | None) -> RequestedFeatures:
    """One served frame (``header``: its image's stamp and frame) as it crosses the link."""
    features = frame.features
    message = RequestedFeatures(robot=robot, descriptor_type=features.descriptor_type)
    message.header = copy_header(header)
    if frame.image_size is not None:
        message.image_width, message.image_height = (int(v) for v in frame.image_size)
    if camera is not None:
        message.camera_matrix, message.distortion = camera[0], camera[1]
    keypoints = np.asarray(features.keypoints, dtype=np.float32)
    message.x, message.y = keypoints[:, 0].copy(), keypoints[:, 1].copy()
    descriptors = compact_descriptors(np.asarray(features.descriptors))
    if descriptors.dtype != np.uint8:
        descriptors = descriptors.astype(np.float16)
        message.descriptor_encoding = RequestedFeatures.DESCRIPTORS_FLOAT16
    message.descriptor_length = int(descriptors.shape[1])
    message.descriptors_zlib = zlib.compress(np.ascontiguousarray(descriptors).tobytes(), ZLIB_LEVEL)
    if frame.depths is not None:
        message.keypoint_depths = np.asarray(frame.depths.keypoints, dtype=np.float32)
        grid = frame.depths.grid
        if grid is not None:
            message.depth_grid_step, message.depth_grid_columns = int(grid.step), int(grid.values.shape[1])
            message.depth_grid_zlib = zlib.compress(grid.values.astype(np.float16).tobytes(), ZLIB_LEVEL)
    return message


def _inflate(data: Any, expected: int, what: str) -> bytes:
    """zlib data that must inflate to exactly ``expected`` bytes (no more is ever inflated)."""
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(bytes(data), expected + 1)
    except zlib.error as exc:
        raise DataError(f"RequestedFeatures {what}: {exc}") from exc
    if len(raw) != expected or inflater.unconsumed_tail:
        raise DataError(f"RequestedFeatures {what} inflate to {len(raw)}+ bytes, expected {expected}")
    return raw


def _features(message: RequestedFeatures, count: int) -> Features:
    length, encoding = int(message.descriptor_length), int(message.descriptor_encoding)
    if str(message.descriptor_type) not in FEATURE_TYPES or not 0 < length <= 512 or encoding not in (0, 1):
        raise DataError(f"RequestedFeatures descriptors {message.descriptor_type!r} of length {length}, encoding "
                        f"{encoding}: not a known kind")
    dtype = np.uint8 if encoding == RequestedFeatures.DESCRIPTORS_UINT8 else np.float16
    raw = _inflate(message.descriptors_zlib, count * length * np.dtype(dtype).itemsize, "descriptors")
    descriptors = restore_descriptors(np.frombuffer(raw, dtype=dtype).reshape(count, length),
                                      str(message.descriptor_type))
    if not np.isfinite(descriptors).all():
        raise DataError("RequestedFeatures descriptors are not all finite")
    keypoints = np.stack([np.asarray(message.x, np.float32), np.asarray(message.y, np.float32)], axis=1)
    if not np.isfinite(keypoints).all():
        raise DataError("RequestedFeatures keypoints are not all finite")
    features = Features(keypoints=keypoints, descriptors=descriptors, descriptor_type=str(message.descriptor_type))
    check_features(features, "RequestedFeatures")
    return features


def _depths(message: RequestedFeatures, count: int) -> FrameDepths | None:
    if not len(message.keypoint_depths):
        return None
    if len(message.keypoint_depths) != count:
        raise DataError(f"RequestedFeatures has {len(message.keypoint_depths)} keypoint depths for {count} keypoints")
    grid = None
    step, columns = int(message.depth_grid_step), int(message.depth_grid_columns)
    if step:
        if not 0 < columns <= 10_000:
            raise DataError(f"RequestedFeatures depth grid of {columns} columns")
        raw = zlib.decompressobj().decompress(bytes(message.depth_grid_zlib), 10_000 * columns * 2 + 1)
        if not raw or len(raw) % (2 * columns) or len(raw) > 10_000 * columns * 2:
            raise DataError(f"RequestedFeatures depth grid of {len(raw)} bytes is no {columns}-column float16 grid")
        grid = DepthGrid(np.frombuffer(raw, dtype=np.float16).reshape(-1, columns).copy(), step)
    return FrameDepths(np.asarray(message.keypoint_depths, dtype=np.float32), grid)


def _camera(message: RequestedFeatures) -> RobotCamera:
    fx, fy, cx, cy = (float(value) for value in message.camera_matrix)
    size = (int(message.image_width), int(message.image_height)) if message.image_width else None
    if fx == 0.0:
        return RobotCamera(None, size)
    matrix = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return RobotCamera(CameraModel(matrix, np.asarray(message.distortion, dtype=np.float64)), size)


def message_to_received_frame(message: RequestedFeatures) -> ReceivedFrame:
    """A checked frame of a RequestedFeatures message; DataError naming the first fault."""
    problem = header_stamp_problem(message.header, "RequestedFeatures")
    if problem is not None:
        raise DataError(problem)
    count = len(message.x)
    if len(message.y) != count or count > MAX_KEYPOINTS:
        raise DataError(f"RequestedFeatures has {count} x and {len(message.y)} y (at most {MAX_KEYPOINTS})")
    return ReceivedFrame(stamp_to_ns(message.header.stamp), str(message.robot), _features(message, count),
                         _depths(message, count), _camera(message))
