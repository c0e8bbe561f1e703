"""What a closure viewer keeps of past frames and the picture of a (query, place) pair it draws from them.

Of every frame that got features it keeps, by image stamp and bounded by bytes, the frame as it arrived
(serialized: its features and a JPEG thumbnail). Nothing is decoded until a picture needs the two frames of
a pair, so keeping the album costs a viewer nobody watches no more than receiving one message a frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.visualization.match_picture import closure_picture, pair_matches
from aefabmap_ros.visualization.stores import ByteBoundedStore


@dataclass(frozen=True)
class ViewFrame:
    """One kept frame, decoded: its features, the width in pixels of the image they were found in, and the
    JPEG thumbnail of that image."""

    features: Features
    image_width: int
    thumbnail_jpeg: bytes


FrameLoader = Callable[[bytes], ViewFrame]
"""A serialized frame -> the frame; raises DataError for one that does not decode."""


@dataclass(frozen=True)
class AlbumConfig:
    # ~3,400 frames of 1000 SIFT keypoints (80 KB as received, binary descriptors) with a 320 x 240 thumbnail
    max_frame_bytes: int = 320 << 20

    def __post_init__(self) -> None:
        if self.max_frame_bytes <= 0:
            raise ValueError(f"max_frame_bytes must be > 0, got {self.max_frame_bytes}")


@dataclass(frozen=True)
class Picture:
    jpeg: bytes
    matches: int
    inliers: int


class ClosureAlbum:
    def __init__(self, config: AlbumConfig, verification: VerificationConfig, load_frame: FrameLoader) -> None:
        self.config = config
        self.verification = verification
        self._load_frame = load_frame
        self.frames: ByteBoundedStore[bytes] = ByteBoundedStore(config.max_frame_bytes, len)

    def add_frame(self, stamp_ns: int, serialized: bytes) -> None:
        self.frames.add(stamp_ns, serialized)

    def picture(self, query_ns: int, place_ns: int, caption: str, refused: bool) -> Picture | None:
        """The pair with the verifier's matches drawn, ``caption`` followed by the counts; None while either
        frame is missing. A frame that does not decode raises DataError."""
        query_blob, place_blob = self.frames.get(query_ns), self.frames.get(place_ns)
        if query_blob is None or place_blob is None:
            return None
        query, place = self._load_frame(query_blob), self._load_frame(place_blob)
        matches = pair_matches(query.features, place.features, self.verification)
        inliers = int(np.count_nonzero(matches.inliers))
        counted = f"{caption}  {inliers} inliers / {len(matches.inliers)} matches"
        jpeg = closure_picture((query.thumbnail_jpeg, query.image_width), (place.thumbnail_jpeg, place.image_width),
                               matches, counted, refused)
        return Picture(jpeg, len(matches.inliers), inliers)
