"""Image messages -> grayscale arrays, depth images -> metres; duck-typed: rclpy and rosbags messages alike,
no ROS import."""

from __future__ import annotations

import io
import warnings
from typing import Any

import numpy as np
from PIL import Image as PILImage

from aefabmap_ros.errors import DataError, ImageTooLargeError
from aefabmap_ros.io.image_encodings import decode_compressed, image_to_gray


def image_message_pixels(message: Any) -> int | None:
    """Pixels the message's image has, read without decoding it (a compressed image's header only);
    None when a compressed image's header is not one Pillow reads (the decoder then decides)."""
    if hasattr(message, "encoding"):
        return int(message.height) * int(message.width)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PILImage.DecompressionBombWarning)
            with PILImage.open(io.BytesIO(bytes(message.data))) as header:  # lazy: reads the header only
                width, height = header.size
    except PILImage.DecompressionBombError:  # Pillow's own bound (~179 MP): larger still
        return 2 * PILImage.MAX_IMAGE_PIXELS if PILImage.MAX_IMAGE_PIXELS else None
    except Exception:  # not a header Pillow knows: no size to check before decoding
        return None
    return int(width) * int(height)


def image_message_to_gray(message: Any, max_pixels: int = 0) -> np.ndarray:
    """``sensor_msgs/Image`` or ``CompressedImage`` -> (H, W) uint8; ``ImageError`` when undecodable.

    ``max_pixels`` > 0: an image with more pixels is refused (``ImageTooLargeError``) before it is
    decoded -- a 69 KB PNG can decode to 8000 x 8000, and the decoder's buffers then take gigabytes.
    """
    if max_pixels > 0:
        pixels = image_message_pixels(message)
        if pixels is not None and pixels > max_pixels:
            raise ImageTooLargeError(f"image of {pixels} pixels exceeds max_image_pixels {max_pixels}")
    if hasattr(message, "encoding"):
        return image_to_gray(
            bytes(message.data), message.encoding, int(message.height), int(message.width), int(message.step)
        )
    return decode_compressed(bytes(message.data), str(getattr(message, "format", "")))


def depth_image_to_metres(image: np.ndarray, encoding: str) -> np.ndarray:
    """A depth image as float32 metres with NaN where there is none: 16UC1 in millimetres (0 = none) or
    32FC1 in metres (NaN, inf or <= 0 = none), the two ROS depth conventions (REP 118)."""
    if image.ndim != 2:
        raise DataError(f"depth image must be single-channel, got shape {image.shape}")
    if encoding in ("16UC1", "mono16"):
        metres = image.astype(np.float32) / 1000.0
    elif encoding == "32FC1":
        metres = image.astype(np.float32, copy=True)
    else:
        raise DataError(f"depth encoding {encoding!r} is not 16UC1 (mm) or 32FC1 (m)")
    metres[~np.isfinite(metres) | (metres <= 0)] = np.nan
    return metres


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
