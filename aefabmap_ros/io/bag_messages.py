"""rosbags messages without a ROS installation: the ROS 2 Jazzy type store with the suite's own types
(``aefabmap_msgs/msg/*.msg``) registered, and builders of the standard messages the package writes (image,
depth, camera info, odometry, headers and times)."""

from __future__ import annotations

import os
import sys
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg
from rosbags.typesys import get_typestore as _rosbags_typestore
from rosbags.typesys.store import Typestore

from aefabmap_ros.errors import BagError

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)
MESSAGE_PACKAGE = "aefabmap_msgs"


def _message_dir_candidates() -> list[Path]:
    """Where the .msg files may live: the source tree (editable install), then installed prefixes."""
    candidates = [Path(__file__).resolve().parents[2] / MESSAGE_PACKAGE / "msg"]
    prefixes = [sys.prefix, *os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)]
    candidates += [Path(prefix) / "share" / MESSAGE_PACKAGE / "msg" for prefix in prefixes if prefix]
    return candidates


def find_message_dir() -> Path:
    for candidate in _message_dir_candidates():
        if any(candidate.glob("*.msg")):
            return candidate
    searched = ", ".join(str(c) for c in _message_dir_candidates())
    raise BagError(f"cannot find the {MESSAGE_PACKAGE} .msg definitions (searched: {searched})")


def no_pose_fields() -> dict[str, Any]:
    """LoopClosure's relative-pose fields for a closure without a pose (rosbags messages need every field)."""
    types = get_typestore().types
    pose = types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                           orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                             w=1.0))
    return {"pose_available": False, "pose_status": 5, "pose": pose, "pose_covariance": np.zeros(36),
            "translation_metric": False}


@cache
def get_typestore() -> Typestore:
    """The ROS 2 Jazzy type store with the aefabmap_msgs types registered."""
    typestore = _rosbags_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for msg_file in sorted(find_message_dir().glob("*.msg")):
        types.update(get_types_from_msg(msg_file.read_text(), f"{MESSAGE_PACKAGE}/msg/{msg_file.stem}"))
    typestore.register(types)
    return typestore


def make_time(stamp_ns: int) -> Any:
    time_type = get_typestore().types["builtin_interfaces/msg/Time"]
    return time_type(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def make_header(stamp_ns: int, frame_id: str = "camera") -> Any:
    header_type = get_typestore().types["std_msgs/msg/Header"]
    return header_type(stamp=make_time(stamp_ns), frame_id=frame_id)


def make_image_message(image: np.ndarray, stamp_ns: int, frame_id: str = "camera") -> Any:
    """A rosbags ``sensor_msgs/Image`` from a mono8 (H, W) or bgr8 (H, W, 3) uint8 array, or a 16UC1
    (H, W) uint16 depth image (millimetres, 0 = no depth; stored little-endian)."""
    depth = image.dtype == np.uint16 and image.ndim == 2
    colour = image.dtype == np.uint8 and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3))
    if not (depth or colour):
        raise BagError(f"expected a uint8 (H, W) or (H, W, 3) image or a uint16 (H, W) depth image, "
                       f"got {image.dtype} {image.shape}")
    height, width = image.shape[:2]
    channels = 1 if image.ndim == 2 else 3
    encoding = "16UC1" if depth else ("mono8" if channels == 1 else "bgr8")
    data = np.ascontiguousarray(image.astype("<u2") if depth else image).view(np.uint8).reshape(-1)
    image_type = get_typestore().types[IMAGE_TYPE]
    return image_type(
        header=make_header(stamp_ns, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * channels * image.itemsize,
        data=data,
    )


def make_camera_info_message(
    camera_matrix: np.ndarray, width: int, height: int, stamp_ns: int, frame_id: str = "camera"
) -> Any:
    """A rosbags ``sensor_msgs/CameraInfo`` of an undistorted pinhole camera: K, R = I, P = [K | 0]."""
    matrix = np.asarray(camera_matrix, dtype=np.float64)
    if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
        raise BagError(f"camera_matrix must be a finite (3, 3) array, got shape {matrix.shape}")
    types = get_typestore().types
    return types[CAMERA_INFO_TYPE](
        header=make_header(stamp_ns, frame_id),
        height=int(height),
        width=int(width),
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=matrix.reshape(9),
        r=np.eye(3).reshape(9),
        p=np.hstack([matrix, np.zeros((3, 1))]).reshape(12),
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def make_odometry_message(pose: np.ndarray, stamp_ns: int, frame_id: str = "odom",
                          child_frame_id: str = "camera") -> Any:
    """A rosbags ``nav_msgs/Odometry`` of a (3|4, 4) child-to-odom pose; zero twist, covariances unknown (0)."""
    matrix = np.asarray(pose, dtype=np.float64)
    if matrix.shape not in ((3, 4), (4, 4)) or not np.isfinite(matrix).all():
        raise BagError(f"odometry pose must be a finite (3|4, 4) array, got shape {matrix.shape}")
    from scipy.spatial.transform import Rotation

    types = get_typestore().types
    qx, qy, qz, qw = Rotation.from_matrix(matrix[:3, :3]).as_quat()
    x, y, z = (float(value) for value in matrix[:3, 3])
    vector = types["geometry_msgs/msg/Vector3"]
    return types[ODOMETRY_TYPE](
        header=make_header(stamp_ns, frame_id),
        child_frame_id=child_frame_id,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)),
            covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=vector(x=0.0, y=0.0, z=0.0),
                                                   angular=vector(x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36)),
    )
