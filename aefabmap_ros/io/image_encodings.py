"""ROS image encodings -> grayscale uint8, without ROS.

``image_to_gray`` takes the raw fields of a ``sensor_msgs/Image`` (data, encoding,
height, width, step) and returns an (H, W) uint8 array; ``decode_compressed`` does
the same for a ``sensor_msgs/CompressedImage`` payload (JPEG / PNG, and the
``compressedDepth`` PNG variant of image_transport).

Normalisation of non-8-bit data (features need 8-bit intensity):
- ``mono16``: an intensity image using the full 16-bit range -> value / 257
  (65535 -> 255), like cv_bridge's mono16 -> mono8.
- ``16UC1`` (usually depth in mm) and ``32FC1`` (depth in m, or any float): min-max
  over the valid pixels (finite; non-zero for 16UC1, where 0 means "no reading")
  stretched to 1..255; invalid pixels become 0. A constant image becomes all 0.
- 16-bit Bayer: the top 8 bits, then demosaiced.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

from aefabmap_ros.errors import ImageError

# encoding -> (channels, numpy dtype of one channel)
_LAYOUTS: Final[dict[str, tuple[int, type[np.generic]]]] = {
    "mono8": (1, np.uint8),
    "8uc1": (1, np.uint8),
    "mono16": (1, np.uint16),
    "16uc1": (1, np.uint16),
    "32fc1": (1, np.float32),
    "8uc3": (3, np.uint8),
    "bgr8": (3, np.uint8),
    "rgb8": (3, np.uint8),
    "bgra8": (4, np.uint8),
    "rgba8": (4, np.uint8),
    "8uc4": (4, np.uint8),
    "bayer_rggb8": (1, np.uint8),
    "bayer_bggr8": (1, np.uint8),
    "bayer_gbrg8": (1, np.uint8),
    "bayer_grbg8": (1, np.uint8),
    "bayer_rggb16": (1, np.uint16),
    "bayer_bggr16": (1, np.uint16),
    "bayer_gbrg16": (1, np.uint16),
    "bayer_grbg16": (1, np.uint16),
    "yuv422": (2, np.uint8),  # ROS "yuv422" is UYVY byte order
    "uyvy": (2, np.uint8),
    "yuyv": (2, np.uint8),
    "yuv422_yuy2": (2, np.uint8),  # YUYV byte order
}

# OpenCV 5 names Bayer conversions after the real mosaic (top-left 2x2 block); verified in the tests
# against a mosaic made from a known colour image.
_BAYER_CODES: Final[dict[str, int]] = {
    "rggb": cv2.COLOR_BayerRGGB2GRAY,
    "bggr": cv2.COLOR_BayerBGGR2GRAY,
    "gbrg": cv2.COLOR_BayerGBRG2GRAY,
    "grbg": cv2.COLOR_BayerGRBG2GRAY,
}

SUPPORTED_ENCODINGS: Final[tuple[str, ...]] = tuple(
    sorted(e.upper() if e[0].isdigit() else e for e in _LAYOUTS)
)


def image_to_gray(
    data: bytes | bytearray | memoryview | np.ndarray,
    encoding: str,
    height: int,
    width: int,
    step: int,
    is_bigendian: bool = False,
) -> np.ndarray:
    """Raw ``sensor_msgs/Image`` fields -> (height, width) uint8 grayscale (a new array).

    ``step`` is the row length in bytes (>= width * bytes per pixel; rows may be padded);
    ``data`` must hold exactly ``step * height`` bytes. Raises ImageError naming the problem.
    """
    key = encoding.strip().lower()
    if key not in _LAYOUTS:
        raise ImageError(
            f"unsupported image encoding {encoding!r}; supported: {', '.join(SUPPORTED_ENCODINGS)}"
        )
    channels, dtype = _LAYOUTS[key]
    itemsize = np.dtype(dtype).itemsize
    pixels = _as_pixels(data, key, channels, dtype, itemsize, height, width, step, is_bigendian)
    return _to_gray(pixels, key)


def _as_pixels(
    data: bytes | bytearray | memoryview | np.ndarray,
    encoding: str,
    channels: int,
    dtype: type[np.generic],
    itemsize: int,
    height: int,
    width: int,
    step: int,
    is_bigendian: bool,
) -> np.ndarray:
    """Validate geometry and view the bytes as (H, W[, C]) of ``dtype`` in native byte order."""
    if height <= 0 or width <= 0:
        raise ImageError(f"image has zero size: height={height} width={width} ({encoding})")
    row_bytes = width * channels * itemsize
    if step < row_bytes:
        raise ImageError(
            f"image step={step} bytes is smaller than width*bytes_per_pixel={row_bytes} ({encoding}, "
            f"width={width})"
        )
    if step % itemsize:
        raise ImageError(f"image step={step} is not a multiple of the {itemsize}-byte sample size ({encoding})")
    raw = _raw_bytes(data)
    if raw.size != step * height:
        raise ImageError(
            f"image data has {raw.size} bytes, expected step*height={step}*{height}={step * height} ({encoding})"
        )
    rows = raw.reshape(height, step)[:, :row_bytes]
    stored = np.dtype(dtype).newbyteorder(">" if is_bigendian else "<") if itemsize > 1 else np.dtype(dtype)
    typed = np.ascontiguousarray(rows).view(stored)
    typed = typed.astype(np.dtype(dtype), copy=False)  # native byte order
    if encoding in ("yuv422", "uyvy", "yuyv", "yuv422_yuy2"):
        if width % 2:
            raise ImageError(f"{encoding} needs an even width, got width={width}")
        return typed.reshape(height, width, 2)
    return typed.reshape(height, width, channels) if channels > 1 else typed.reshape(height, width)


def _raw_bytes(data: bytes | bytearray | memoryview | np.ndarray) -> np.ndarray:
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if isinstance(data, bytes | bytearray | memoryview):
        return np.frombuffer(data, dtype=np.uint8)
    try:  # e.g. array.array('B') from rclpy messages
        return np.frombuffer(memoryview(data), dtype=np.uint8)
    except TypeError as error:
        raise ImageError(f"image data of type {type(data).__name__} is not a byte buffer") from error


def _to_gray(pixels: np.ndarray, encoding: str) -> np.ndarray:
    if encoding in ("mono8", "8uc1"):
        return pixels.copy()
    if encoding in ("bgr8", "8uc3"):
        return cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)
    if encoding == "rgb8":
        return cv2.cvtColor(pixels, cv2.COLOR_RGB2GRAY)
    if encoding in ("bgra8", "8uc4"):
        return cv2.cvtColor(pixels, cv2.COLOR_BGRA2GRAY)
    if encoding == "rgba8":
        return cv2.cvtColor(pixels, cv2.COLOR_RGBA2GRAY)
    if encoding == "mono16":
        # Rounded value / 257 maps 0..65535 exactly onto 0..255.
        return ((pixels.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    if encoding == "16uc1":
        return stretch_to_uint8(pixels.astype(np.float64), pixels > 0)
    if encoding == "32fc1":
        return stretch_to_uint8(pixels.astype(np.float64), np.isfinite(pixels))
    if encoding.startswith("bayer_"):
        pattern = encoding[len("bayer_"):len("bayer_") + 4]
        mosaic = pixels if pixels.dtype == np.uint8 else (pixels >> 8).astype(np.uint8)
        return cv2.cvtColor(np.ascontiguousarray(mosaic), _BAYER_CODES[pattern])
    if encoding in ("yuv422", "uyvy"):
        return np.ascontiguousarray(pixels.reshape(pixels.shape[0], -1)[:, 1::2])  # U Y V Y: Y at odd bytes
    # yuyv / yuv422_yuy2: Y U Y V -> Y at even bytes
    return np.ascontiguousarray(pixels.reshape(pixels.shape[0], -1)[:, 0::2])


def stretch_to_uint8(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Min-max stretch valid pixels to 1..255 (0 is kept for invalid pixels); constant -> all 0."""
    gray = np.zeros(values.shape, np.uint8)
    if not valid.any():
        return gray
    lo = float(values[valid].min())
    hi = float(values[valid].max())
    if hi <= lo:
        return gray
    scaled = 1.0 + (values[valid] - lo) * (254.0 / (hi - lo))
    gray[valid] = np.clip(np.rint(scaled), 1, 255).astype(np.uint8)
    return gray


def decode_compressed(data: bytes | bytearray | memoryview | np.ndarray, format_hint: str = "") -> np.ndarray:
    """A ``sensor_msgs/CompressedImage`` payload (JPEG, PNG, ...) -> (H, W) uint8 grayscale.

    ``format_hint`` is the message's ``format`` field (e.g. ``"jpeg"``, ``"bgr8; jpeg compressed bgr8"``,
    ``"16UC1; compressedDepth png"``); the codec itself is detected from the data. For compressedDepth
    the 12-byte image_transport header is skipped and the 16-bit depth is stretched like 16UC1.
    """
    raw = _raw_bytes(data)
    if raw.size == 0:
        raise ImageError(f"compressed image ({format_hint or 'no format'}) has no data")
    depth = "compresseddepth" in format_hint.lower().replace(" ", "")
    if depth:
        if raw.size <= 12:
            raise ImageError(f"compressedDepth image has only {raw.size} bytes, not even its 12-byte header")
        raw = raw[12:]
    try:
        # Gray + any depth: libjpeg decodes the luma plane only (faster, the JPEG's own Y), 16-bit PNGs stay 16-bit.
        image = cv2.imdecode(raw, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    except cv2.error as error:
        image = None
        detail = f": {str(error).strip().splitlines()[-1]}"
    else:
        detail = ""
    if image is None or image.size == 0:
        raise ImageError(
            f"cannot decode compressed image ({format_hint or 'no format'}, {raw.size} bytes): "
            f"corrupt or unsupported data{detail}"
        )
    if image.dtype == np.uint8:
        return np.asarray(image)
    if depth or image.dtype != np.uint16:
        return stretch_to_uint8(image.astype(np.float64), np.isfinite(image) & (image != 0))
    return ((image.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
