"""What a closure viewer keeps of past frames (a thumbnail and the features of each, by image stamp, bounded by
bytes) and the picture of a (query, place) pair it draws from them on request."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.visualization.match_picture import Thumbnail, closure_picture, make_thumbnail, pair_matches
from aefabmap_ros.visualization.stores import ByteBoundedStore


@dataclass(frozen=True)
class AlbumConfig:
    thumbnail_width: int = 320
    max_thumbnail_bytes: int = 64 << 20  # ~4000 thumbnails of 320 x 240
    max_feature_bytes: int = 256 << 20  # ~1000 SIFT frames of 500 keypoints as float32
    max_waiting_image_bytes: int = 32 << 20  # images waiting for their features (most never get any)

    def __post_init__(self) -> None:
        for name in ("thumbnail_width", "max_thumbnail_bytes", "max_feature_bytes", "max_waiting_image_bytes"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class Picture:
    jpeg: bytes
    matches: int
    inliers: int


def features_nbytes(features: Features) -> int:
    return int(features.keypoints.nbytes + features.descriptors.nbytes)


class ClosureAlbum:
    """Thumbnails only of frames that got features (the detector's frames; a 30 Hz camera's others never become
    places): an image waits, by bytes, for its features, and is shrunk when they arrive."""

    def __init__(self, config: AlbumConfig, verification: VerificationConfig) -> None:
        self.config = config
        self.verification = verification
        self.thumbnails: ByteBoundedStore[Thumbnail] = ByteBoundedStore(config.max_thumbnail_bytes,
                                                                        lambda t: t.nbytes)
        self.features: ByteBoundedStore[Features] = ByteBoundedStore(config.max_feature_bytes, features_nbytes)
        self.waiting_images: ByteBoundedStore[np.ndarray] = ByteBoundedStore(config.max_waiting_image_bytes,
                                                                             lambda image: int(image.nbytes))

    def add_image(self, stamp_ns: int, image: np.ndarray) -> None:
        if stamp_ns in self.features:
            self.thumbnails.add(stamp_ns, make_thumbnail(image, self.config.thumbnail_width))
        else:
            self.waiting_images.add(stamp_ns, image)

    def add_features(self, stamp_ns: int, features: Features) -> None:
        self.features.add(stamp_ns, features)
        image = self.waiting_images.pop(stamp_ns)
        if image is not None:
            self.thumbnails.add(stamp_ns, make_thumbnail(image, self.config.thumbnail_width))

    def has_pair(self, query_ns: int, place_ns: int) -> bool:
        return all(stamp in self.thumbnails and stamp in self.features for stamp in (query_ns, place_ns))

    def picture(self, query_ns: int, place_ns: int, caption: str, refused: bool) -> Picture | None:
        """The pair with the verifier's matches drawn, ``caption`` followed by the counts; None while a thumbnail
        or the features of either frame are missing."""
        query, place = self.thumbnails.get(query_ns), self.thumbnails.get(place_ns)
        query_features, place_features = self.features.get(query_ns), self.features.get(place_ns)
        if query is None or place is None or query_features is None or place_features is None:
            return None
        matches = pair_matches(query_features, place_features, self.verification)
        inliers = int(np.count_nonzero(matches.inliers))
        counted = f"{caption}  {inliers} inliers / {len(matches.inliers)} matches"
        return Picture(closure_picture(query, place, matches, counted, refused), len(matches.inliers), inliers)
