"""Image messages -> grayscale arrays, duck-typed: rclpy and rosbags messages alike, no ROS import."""

from __future__ import annotations

from typing import Any

import numpy as np

from aefabmap_ros.core.errors import DataError
from aefabmap_ros.core.images import decode_compressed, image_to_gray
from aefabmap_ros.core.relative_pose import depth_image_to_metres


def image_message_to_gray(message: Any) -> np.ndarray:
    """``sensor_msgs/Image`` or ``CompressedImage`` -> (H, W) uint8; ``ImageError`` when undecodable."""
    if hasattr(message, "encoding"):
        return image_to_gray(
            bytes(message.data), message.encoding, int(message.height), int(message.width), int(message.step)
        )
    return decode_compressed(bytes(message.data), str(getattr(message, "format", "")))


def depth_message_to_metres(message: Any) -> np.ndarray:
    """``sensor_msgs/Image`` depth (16UC1 mm or 32FC1 m) -> (H, W) float32 metres, NaN where none."""
    encoding = str(message.encoding)
    dtype = {"16UC1": np.uint16, "mono16": np.uint16, "32FC1": np.float32}.get(encoding)
    if dtype is None:
        return depth_image_to_metres(np.zeros((1, 1)), encoding)  # raises DataError naming the encoding
    height, width, step = int(message.height), int(message.width), int(message.step)
    item = np.dtype(dtype).itemsize
    data = np.frombuffer(bytes(message.data), dtype=np.uint8)
    if step < width * item or data.size < height * step:
        raise DataError(f"depth image {width}x{height} {encoding}: step {step} and {data.size} bytes do not fit")
    rows = data[: height * step].reshape(height, step)[:, : width * item]
    image = rows.copy().view(np.dtype(dtype).newbyteorder(">" if message.is_bigendian else "<")).reshape(height, width)
    return depth_image_to_metres(image.astype(dtype), encoding)
