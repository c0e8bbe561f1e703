"""The one descriptor matcher: nearest neighbours under Lowe's ratio test, one-to-one.

The verifier (``verification.geometric``), the verifier node's relative pose and the autoencoder's
self-supervised training pairs (``vocabulary.base.sequence_pairs``) all match through this, so a
"match" means the same thing wherever the package counts one. Geometry (which matches fit one
fundamental matrix) is the verifier's part.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.features.extraction import Features


@dataclass(frozen=True)
class NearestNeighbours:
    """Each query keypoint's two nearest place keypoints: what a ratio test filters. Computing them once
    lets one pair be matched under two ratios (the verifier's epipolar and metric tests) for one search."""

    query_rows: np.ndarray  # (K,) int64, in the matcher's order
    place_rows: np.ndarray  # (K,) int64, the nearest place keypoint of each
    nearest: np.ndarray  # (K,) float64 distance to it
    second: np.ndarray  # (K,) float64 distance to the second nearest


NO_NEIGHBOURS = NearestNeighbours(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))


def nearest_neighbours(query: Features, place: Features) -> NearestNeighbours:
    """The two nearest place keypoints of every query keypoint: Hamming distance for binary (uint8)
    descriptors, L2 for float ones.

    Raises:
        DataError: malformed features, or features of two different descriptor types or sizes.
    """
    check_features(query, "query")
    check_features(place, "place")
    if query.descriptor_type != place.descriptor_type:
        raise DataError(f"cannot match {query.descriptor_type!r} features against {place.descriptor_type!r} ones")
    if len(query) == 0 or len(place) < 2:
        return NO_NEIGHBOURS
    kind = kind_of(query.descriptors)
    if kind != kind_of(place.descriptors):
        raise DataError(f"descriptor dtypes differ: {query.descriptors.dtype} vs {place.descriptors.dtype}")
    if query.descriptors.shape[1] != place.descriptors.shape[1]:  # e.g. 128-d SIFT vs 64-d SURF
        raise DataError(f"cannot match {query.descriptors.shape[1]}-d descriptors against "
                        f"{place.descriptors.shape[1]}-d ones")
    if kind.cv_norm == cv2.NORM_L2:
        return _l2_nearest_two(np.asarray(query.descriptors, np.float32), np.asarray(place.descriptors, np.float32))
    matcher = cv2.BFMatcher(kind.cv_norm)
    pairs = [pair for pair in matcher.knnMatch(np.ascontiguousarray(query.descriptors, dtype=kind.dtype),
                                               np.ascontiguousarray(place.descriptors, dtype=kind.dtype), k=2)
             if len(pair) == 2]
    return NearestNeighbours(np.array([pair[0].queryIdx for pair in pairs], np.int64),
                             np.array([pair[0].trainIdx for pair in pairs], np.int64),
                             np.array([pair[0].distance for pair in pairs], np.float64),
                             np.array([pair[1].distance for pair in pairs], np.float64))


def _l2_nearest_two(query: np.ndarray, place: np.ndarray) -> NearestNeighbours:
    """Brute-force L2 nearest and second-nearest: the verifier's hot path (a revisit verifies several candidates
    a frame), about twice as fast as OpenCV's BFMatcher with its per-match Python objects.

    Squared distances |q|^2 - 2 q.p + |p|^2 come from one matrix product of rows extended by the norms, so no
    (N, M) temporary is made beside the product; float32 rounding moves a distance by ~1e-6 relative.
    """
    dims = query.shape[1]
    extended_query = np.empty((len(query), dims + 2), np.float32)
    extended_query[:, :dims] = query
    extended_query[:, dims] = np.einsum("ij,ij->i", query, query)
    extended_query[:, dims + 1] = 1.0
    extended_place = np.empty((len(place), dims + 2), np.float32)
    np.multiply(place, -2.0, out=extended_place[:, :dims])
    extended_place[:, dims] = 1.0
    extended_place[:, dims + 1] = np.einsum("ij,ij->i", place, place)
    squared = extended_query @ extended_place.T
    rows = np.arange(len(query))
    nearest = np.argmin(squared, axis=1)
    nearest_squared = squared[rows, nearest]
    squared[rows, nearest] = np.inf
    second_squared = squared.min(axis=1)
    return NearestNeighbours(rows.astype(np.int64), nearest.astype(np.int64),
                             np.sqrt(np.maximum(nearest_squared, 0.0)).astype(np.float64),
                             np.sqrt(np.maximum(second_squared, 0.0)).astype(np.float64))


def ratio_test_matches(neighbours: NearestNeighbours, ratio: float) -> np.ndarray:
    """(M, 2) int64 keypoint rows (into query, into place) of the neighbours that pass Lowe's ratio test.

    A query keypoint keeps its nearest place keypoint when that is closer than ``ratio`` times the
    second nearest; a place keypoint claimed by several query keypoints keeps only the closest (so no
    correspondence is counted twice). Rows come in the order place keypoints were first claimed (the
    order RANSAC samples from downstream, so it is part of the verifier's reproducible result).
    """
    best_by_place: dict[int, tuple[float, int]] = {}
    passed = np.flatnonzero(neighbours.nearest < ratio * neighbours.second)
    for query_row, place_row, distance in zip(neighbours.query_rows[passed].tolist(),
                                              neighbours.place_rows[passed].tolist(),
                                              neighbours.nearest[passed].tolist(), strict=True):
        kept = best_by_place.get(place_row)
        if kept is None or distance < kept[0]:
            best_by_place[place_row] = (distance, query_row)
    matches = np.array([(query_row, place_row) for place_row, (_, query_row) in best_by_place.items()], np.int64)
    return matches.reshape(-1, 2)


def match_indices(query: Features, place: Features, *, ratio: float) -> np.ndarray:
    """Matches from ``query`` to ``place``: (M, 2) int64 keypoint rows (into query, into place), nearest
    neighbours under Lowe's ratio test, one-to-one (:func:`ratio_test_matches`).

    Raises:
        DataError: malformed features, or features of two different descriptor types or sizes.
    """
    return ratio_test_matches(nearest_neighbours(query, place), ratio)


def check_features(features: Features, role: str) -> None:
    """Keypoints (N, >= 2) and N descriptor rows, or a DataError naming ``role``."""
    if features.keypoints.ndim != 2 or features.keypoints.shape[1] < 2:
        raise DataError(f"{role} keypoints must be (N, >= 2), got shape {features.keypoints.shape}")
    if features.descriptors.ndim != 2 or features.descriptors.shape[0] != features.keypoints.shape[0]:
        raise DataError(f"{role} has {features.keypoints.shape[0]} keypoints but descriptors of shape "
                        f"{features.descriptors.shape}")


__all__ = ["NO_NEIGHBOURS", "NearestNeighbours", "check_features", "match_indices", "nearest_neighbours",
           "ratio_test_matches"]
