"""Image messages -> grayscale arrays, duck-typed: rclpy and rosbags messages alike, no ROS import."""

from __future__ import annotations

from typing import Any

import numpy as np

from aefabmap_ros.core.images import decode_compressed, image_to_gray


def image_message_to_gray(message: Any) -> np.ndarray:
    """``sensor_msgs/Image`` or ``CompressedImage`` -> (H, W) uint8; ``ImageError`` when undecodable."""
    if hasattr(message, "encoding"):
        return image_to_gray(
            bytes(message.data), message.encoding, int(message.height), int(message.width), int(message.step)
        )
    return decode_compressed(bytes(message.data), str(getattr(message, "format", "")))
