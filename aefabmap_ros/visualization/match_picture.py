"""A loop closure as one picture: the query and the matched place side by side, the verification's matches drawn.

The matches are found again with the package's own verification code (``features.matching`` and the
fundamental-matrix RANSAC of ``verification.geometric``), so the picture shows the inliers the verifier
counted, not a look-alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.features.matching import match_indices
from aefabmap_ros.verification.geometric import VerificationConfig, fundamental_matrix, matched_points

# BGR colours: green reads as "agrees with one geometry", red as "matched a descriptor but not the geometry".
INLIER_COLOUR = (0, 200, 0)
OUTLIER_COLOUR = (0, 0, 230)
REFUSED_BANNER_COLOUR = (0, 0, 160)
ACCEPTED_BANNER_COLOUR = (0, 110, 0)
BANNER_HEIGHT_PX = 22
# More lines than this hide the images under them: an evenly spread subset is drawn (the caption has the counts).
MAX_DRAWN_INLIERS = 80
JPEG_QUALITY = 85


@dataclass(frozen=True)
class PairMatches:
    """Matched keypoints of a (query, place) pair in image pixels and which fit one fundamental matrix."""

    query_points: np.ndarray  # (M, 2) float32
    place_points: np.ndarray  # (M, 2) float32
    inliers: np.ndarray  # (M,) bool


def encode_jpeg(image: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise DataError(f"cannot encode a {image.shape} image as JPEG")
    return bytes(encoded.tobytes())


def decode_jpeg(jpeg: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise DataError("not a JPEG image")
    return np.asarray(image)


def make_thumbnail(image: np.ndarray, max_width: int) -> bytes:
    """``image`` (gray or BGR) shrunk to at most ``max_width`` pixels wide (never enlarged), as a JPEG. Where
    its keypoints fall on it follows from the two widths (``closure_picture``)."""
    if image.ndim not in (2, 3) or image.shape[0] == 0 or image.shape[1] == 0:
        raise DataError(f"a thumbnail needs an (H, W) or (H, W, 3) image, got {image.shape}")
    scale = min(1.0, max_width / image.shape[1])
    if scale < 1.0:
        size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return encode_jpeg(image)


def pair_matches(query: Features, place: Features, config: VerificationConfig) -> PairMatches:
    """The verifier's matches of a pair (ratio test, one-to-one) and its RANSAC inliers."""
    rows = match_indices(query, place, ratio=config.ratio)
    query_points, place_points = matched_points(query, place, rows)
    _, inliers = fundamental_matrix(query_points, place_points, config)
    return PairMatches(query_points, place_points, inliers)


def side_by_side(query: np.ndarray, place: np.ndarray) -> tuple[np.ndarray, int]:
    """One BGR canvas, the query left and the place right (top-aligned, black below the shorter), and the
    x offset of the place."""
    query, place = (_to_bgr(image) for image in (query, place))
    height = max(query.shape[0], place.shape[0])
    canvas = np.zeros((height, query.shape[1] + place.shape[1], 3), np.uint8)
    canvas[:query.shape[0], :query.shape[1]] = query
    canvas[:place.shape[0], query.shape[1]:] = place
    return canvas, query.shape[1]


def draw_matches(query: np.ndarray, place: np.ndarray, matches: PairMatches, query_scale: float,
                 place_scale: float, caption: str, refused: bool) -> np.ndarray:
    """The pair side by side under a caption banner: a line per inlier (``MAX_DRAWN_INLIERS`` of them at most), a
    dot at each end of an outlier match.

    ``query_scale`` and ``place_scale`` take the matches' image pixels to the given (thumbnail) images.
    """
    canvas, offset = side_by_side(query, place)
    query_xy = np.rint(matches.query_points * query_scale).astype(np.int32)
    place_xy = np.rint(matches.place_points * place_scale).astype(np.int32) + np.array([offset, 0], np.int32)
    for (qx, qy), (px, py) in zip(query_xy[~matches.inliers], place_xy[~matches.inliers], strict=True):
        cv2.circle(canvas, (int(qx), int(qy)), 2, OUTLIER_COLOUR, -1, cv2.LINE_AA)
        cv2.circle(canvas, (int(px), int(py)), 2, OUTLIER_COLOUR, -1, cv2.LINE_AA)
    inliers = np.flatnonzero(matches.inliers)
    drawn = inliers[np.linspace(0, len(inliers) - 1, MAX_DRAWN_INLIERS).round().astype(int)] \
        if len(inliers) > MAX_DRAWN_INLIERS else inliers
    for (qx, qy), (px, py) in zip(query_xy[drawn], place_xy[drawn], strict=True):
        cv2.line(canvas, (int(qx), int(qy)), (int(px), int(py)), INLIER_COLOUR, 1, cv2.LINE_AA)
    banner = np.zeros((BANNER_HEIGHT_PX, canvas.shape[1], 3), np.uint8)
    banner[:] = REFUSED_BANNER_COLOUR if refused else ACCEPTED_BANNER_COLOUR
    cv2.putText(banner, caption, (4, BANNER_HEIGHT_PX - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                cv2.LINE_AA)
    return np.vstack([banner, canvas])


def closure_picture(query: tuple[bytes, int], place: tuple[bytes, int], matches: PairMatches, caption: str,
                    refused: bool) -> bytes:
    """The JPEG a viewer shows for one closure (or refused candidate): each frame given as its thumbnail's JPEG
    and the width in pixels of the image its keypoints are in (the thumbnail's scale follows from the two)."""
    (query_image, query_scale), (place_image, place_scale) = (_decoded_with_scale(*frame) for frame in (query, place))
    drawn = draw_matches(query_image, place_image, matches, query_scale, place_scale, caption, refused)
    return encode_jpeg(drawn)


def _decoded_with_scale(jpeg: bytes, image_width: int) -> tuple[np.ndarray, float]:
    if image_width <= 0:
        raise DataError(f"the image's width must be > 0, got {image_width}")
    image = decode_jpeg(jpeg)
    return image, image.shape[1] / image_width


def _to_bgr(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
