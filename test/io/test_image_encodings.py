"""Tests for ROS image encodings -> grayscale (aefabmap_ros/io/image_encodings.py)."""

import cv2
import numpy as np
import pytest

from aefabmap_ros.errors import ImageError
from aefabmap_ros.io.image_encodings import SUPPORTED_ENCODINGS, decode_compressed, image_to_gray

RNG = np.random.default_rng(7)
H, W = 12, 10


def _reference_gray(bgr: np.ndarray) -> np.ndarray:
    """ITU-R BT.601 luma, computed independently of OpenCV."""
    b, g, r = (bgr[..., i].astype(np.float64) for i in range(3))
    return np.clip(np.rint(0.299 * r + 0.587 * g + 0.114 * b), 0, 255).astype(np.uint8)


@pytest.fixture
def bgr() -> np.ndarray:
    return RNG.integers(0, 256, (H, W, 3), dtype=np.uint8)


def test_mono8_with_row_padding_drops_padding() -> None:
    gray = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    padded = np.zeros((H, W + 6), np.uint8)
    padded[:, :W] = gray
    padded[:, W:] = 99
    out = image_to_gray(padded.tobytes(), "mono8", H, W, W + 6)
    np.testing.assert_array_equal(out, gray)
    assert out.dtype == np.uint8 and out.shape == (H, W)


@pytest.mark.parametrize("encoding", ["bgr8", "8UC3", "rgb8", "bgra8", "rgba8"])
def test_colour_encodings_match_bt601_luma(bgr: np.ndarray, encoding: str) -> None:
    pixels = bgr[..., ::-1] if encoding.startswith("rgb") else bgr
    if encoding.endswith("a8"):
        pixels = np.concatenate([pixels, np.full((H, W, 1), 7, np.uint8)], axis=2)
    out = image_to_gray(np.ascontiguousarray(pixels).tobytes(), encoding, H, W, W * pixels.shape[2])
    assert np.abs(out.astype(int) - _reference_gray(bgr).astype(int)).max() <= 1


def test_mono16_scales_full_range_and_honours_endianness() -> None:
    values = np.array([[0, 257, 65535, 32896]], np.uint16)
    expected = np.array([[0, 1, 255, 128]], np.uint8)
    np.testing.assert_array_equal(image_to_gray(values.astype("<u2").tobytes(), "mono16", 1, 4, 8), expected)
    np.testing.assert_array_equal(
        image_to_gray(values.astype(">u2").tobytes(), "mono16", 1, 4, 8, is_bigendian=True), expected
    )


def test_16uc1_depth_is_stretched_over_valid_pixels() -> None:
    depth = np.array([[0, 1000, 2000, 3000]], np.uint16)
    out = image_to_gray(depth.tobytes(), "16UC1", 1, 4, 8)
    np.testing.assert_array_equal(out, [[0, 1, 128, 255]])


def test_32fc1_stretches_and_zeroes_nan() -> None:
    depth = np.array([[np.nan, 0.5, 1.0, 1.5]], np.float32)
    out = image_to_gray(depth.tobytes(), "32FC1", 1, 4, 16)
    np.testing.assert_array_equal(out, [[0, 1, 128, 255]])
    constant = image_to_gray(np.ones((2, 2), np.float32), "32FC1", 2, 2, 8)
    np.testing.assert_array_equal(constant, 0)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_patterns_demosaic_to_the_right_gray(pattern: str) -> None:
    # A smooth colour image: demosaicing recovers it almost exactly, so a wrong pattern shows up as a
    # large error (red and blue swapped changes the luma of a saturated image).
    yy, xx = np.mgrid[0:32, 0:32]
    bgr = np.stack([40 + 2 * xx, 60 + yy, 200 - 3 * yy], axis=2).clip(0, 255).astype(np.uint8)
    channel = {"r": 2, "g": 1, "b": 0}
    mosaic = np.zeros((32, 32), np.uint8)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        mosaic[dy::2, dx::2] = bgr[dy::2, dx::2, channel[pattern[k]]]
    out = image_to_gray(mosaic.tobytes(), f"bayer_{pattern}8", 32, 32, 32)
    inner = (slice(2, -2), slice(2, -2))
    assert np.abs(out[inner].astype(int) - _reference_gray(bgr)[inner].astype(int)).mean() < 3.0
    wide = image_to_gray((mosaic.astype(np.uint16) << 8).tobytes(), f"bayer_{pattern}16", 32, 32, 64)
    np.testing.assert_array_equal(wide, out)


@pytest.mark.parametrize(("encoding", "y_offset"), [("yuv422", 1), ("uyvy", 1), ("yuyv", 0), ("yuv422_yuy2", 0)])
def test_yuv422_takes_the_luma_bytes(encoding: str, y_offset: int) -> None:
    luma = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    packed = np.full((H, 2 * W), 128, np.uint8)
    packed[:, y_offset::2] = luma
    np.testing.assert_array_equal(image_to_gray(packed.tobytes(), encoding, H, W, 2 * W), luma)


def test_accepts_numpy_buffers_and_bytearrays() -> None:
    gray = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    np.testing.assert_array_equal(image_to_gray(gray, "mono8", H, W, W), gray)
    np.testing.assert_array_equal(image_to_gray(bytearray(gray.tobytes()), "mono8", H, W, W), gray)


def test_unsupported_encoding_is_named_with_the_supported_list() -> None:
    with pytest.raises(ImageError, match=r"unsupported image encoding 'nv21'.*bgr8.*mono8"):
        image_to_gray(b"\0" * 4, "nv21", 2, 2, 2)
    assert "32FC1" in SUPPORTED_ENCODINGS and "rgb8" in SUPPORTED_ENCODINGS


@pytest.mark.parametrize(("height", "width"), [(0, 4), (4, 0)])
def test_zero_size_image_is_refused(height: int, width: int) -> None:
    with pytest.raises(ImageError, match="zero size"):
        image_to_gray(b"", "mono8", height, width, width)


def test_wrong_data_length_is_refused() -> None:
    with pytest.raises(ImageError, match=r"has 11 bytes, expected step\*height"):
        image_to_gray(b"\0" * 11, "mono8", 3, 4, 4)


def test_step_too_small_or_misaligned_is_refused() -> None:
    with pytest.raises(ImageError, match="step=8 bytes is smaller"):
        image_to_gray(b"\0" * 24, "bgr8", 3, 4, 8)
    with pytest.raises(ImageError, match="not a multiple"):
        image_to_gray(b"\0" * 27, "mono16", 3, 4, 9)


def test_odd_width_yuv_is_refused() -> None:
    with pytest.raises(ImageError, match="even width"):
        image_to_gray(b"\0" * 6, "uyvy", 1, 3, 6)


def test_non_buffer_data_is_refused() -> None:
    with pytest.raises(ImageError, match="not a byte buffer"):
        image_to_gray([1, 2, 3, 4], "mono8", 2, 2, 2)  # type: ignore[arg-type]


@pytest.mark.parametrize(("ext", "hint"), [(".png", "png"), (".jpg", "bgr8; jpeg compressed bgr8")])
def test_decode_compressed_matches_opencv_gray(bgr: np.ndarray, ext: str, hint: str) -> None:
    ok, payload = cv2.imencode(ext, bgr)
    assert ok
    out = decode_compressed(payload.tobytes(), hint)
    assert out.shape == (H, W) and out.dtype == np.uint8
    expected = cv2.imdecode(payload, cv2.IMREAD_GRAYSCALE)
    assert expected is not None
    assert np.abs(out.astype(int) - expected.astype(int)).max() <= 1


def test_decode_compressed_gray_png_is_lossless() -> None:
    gray = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    _, payload = cv2.imencode(".png", gray)
    np.testing.assert_array_equal(decode_compressed(payload.tobytes(), "png"), gray)


def test_decode_compressed_depth_skips_header_and_stretches() -> None:
    depth = np.array([[0, 1000], [2000, 3000]], np.uint16)
    _, payload = cv2.imencode(".png", depth)
    out = decode_compressed(b"\0" * 12 + payload.tobytes(), "16UC1; compressedDepth png")
    np.testing.assert_array_equal(out, [[0, 1], [128, 255]])


def test_corrupt_compressed_data_is_refused(bgr: np.ndarray) -> None:
    _, payload = cv2.imencode(".jpg", bgr)
    with pytest.raises(ImageError, match=r"cannot decode compressed image \(jpeg"):
        decode_compressed(b"not an image at all" * 3, "jpeg")
    with pytest.raises(ImageError, match="cannot decode"):
        decode_compressed(payload.tobytes()[:20], "jpeg")
    with pytest.raises(ImageError, match="has no data"):
        decode_compressed(b"", "png")
    with pytest.raises(ImageError, match="12-byte header"):
        decode_compressed(b"\0" * 5, "16UC1; compressedDepth png")
