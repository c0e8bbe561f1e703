"""The one descriptor matcher: nearest neighbours under Lowe's ratio test, one-to-one.

The verifier (``verification.geometric``), the verifier node's relative pose and the autoencoder's
self-supervised training pairs (``vocabulary.base.sequence_pairs``) all match through this, so a
"match" means the same thing wherever the package counts one. Geometry (which matches fit one
fundamental matrix) is the verifier's part.
"""

from __future__ import annotations

import cv2
import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.features.extraction import Features


def match_indices(query: Features, place: Features, *, ratio: float) -> np.ndarray:
    """Matches from ``query`` to ``place``: (M, 2) int64 keypoint rows (into query, into place).

    Binary (uint8) descriptors are compared by Hamming distance, float ones by L2. Each query keypoint
    keeps its nearest place keypoint when that is closer than ``ratio`` times the second nearest; a
    place keypoint claimed by several query keypoints keeps only the closest (so no correspondence is
    counted twice). Rows come in the order place keypoints were first claimed (the order RANSAC
    samples from downstream, so it is part of the verifier's reproducible result).

    Raises:
        DataError: malformed features, or features of two different descriptor types or sizes.
    """
    check_features(query, "query")
    check_features(place, "place")
    if query.descriptor_type != place.descriptor_type:
        raise DataError(f"cannot match {query.descriptor_type!r} features against {place.descriptor_type!r} ones")
    if len(query) == 0 or len(place) < 2:
        return np.zeros((0, 2), np.int64)
    kind = kind_of(query.descriptors)
    if kind != kind_of(place.descriptors):
        raise DataError(f"descriptor dtypes differ: {query.descriptors.dtype} vs {place.descriptors.dtype}")
    if query.descriptors.shape[1] != place.descriptors.shape[1]:  # e.g. 128-d SIFT vs 64-d SURF
        raise DataError(f"cannot match {query.descriptors.shape[1]}-d descriptors against "
                        f"{place.descriptors.shape[1]}-d ones")
    matcher = cv2.BFMatcher(kind.cv_norm)
    pairs = matcher.knnMatch(np.ascontiguousarray(query.descriptors, dtype=kind.dtype),
                             np.ascontiguousarray(place.descriptors, dtype=kind.dtype), k=2)
    best_by_place: dict[int, tuple[float, int]] = {}
    for pair in pairs:
        if len(pair) < 2 or pair[0].distance >= ratio * pair[1].distance:
            continue
        nearest = pair[0]
        kept = best_by_place.get(nearest.trainIdx)
        if kept is None or nearest.distance < kept[0]:
            best_by_place[nearest.trainIdx] = (nearest.distance, nearest.queryIdx)
    matches = np.array([(query_row, place_row) for place_row, (_, query_row) in best_by_place.items()],
                       np.int64)
    return matches.reshape(-1, 2)


def check_features(features: Features, role: str) -> None:
    """Keypoints (N, >= 2) and N descriptor rows, or a DataError naming ``role``."""
    if features.keypoints.ndim != 2 or features.keypoints.shape[1] < 2:
        raise DataError(f"{role} keypoints must be (N, >= 2), got shape {features.keypoints.shape}")
    if features.descriptors.ndim != 2 or features.descriptors.shape[0] != features.keypoints.shape[0]:
        raise DataError(f"{role} has {features.keypoints.shape[0]} keypoints but descriptors of shape "
                        f"{features.descriptors.shape}")


__all__ = ["check_features", "match_indices"]
