"""The one descriptor matcher, on images shifted by a known offset and against brute force."""

import cv2
import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.extraction import FeatureConfig, Features, extract_features
from aefabmap_ros.features.matching import match_indices, nearest_neighbours, ratio_test_matches


def _textured(seed: int, shape: tuple[int, int]) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = np.zeros(shape, np.uint8)
    for _ in range(60):
        x, y = int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0]))
        cv2.circle(image, (x, y), int(rng.integers(3, 20)), int(rng.integers(60, 255)), -1)
    return cv2.GaussianBlur(image, (3, 3), 0)


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_matches_find_a_known_shift(kind: str) -> None:
    image = _textured(3, (260, 340))
    config = FeatureConfig(type=kind)
    a = extract_features(image[10:250, 10:330], config)
    b = extract_features(image[15:255, 3:323], config)  # the scene shifted by (+7, -5) pixels
    matches = match_indices(a, b, ratio=0.8)
    assert len(matches) > 20
    shift = b.keypoints[matches[:, 1], :2] - a.keypoints[matches[:, 0], :2]
    np.testing.assert_allclose(np.median(shift, axis=0), [7, -5], atol=0.5)


@pytest.mark.parametrize("ratio", [0.6, 0.8, 0.9, 1.0])
def test_matches_are_the_brute_force_ratio_test_made_one_to_one(ratio: float) -> None:
    rng = np.random.default_rng(4)
    place = rng.random((40, 16)).astype(np.float32)
    query = np.concatenate([place[:25] + rng.normal(0, 0.01, (25, 16)), place[:5] + rng.normal(0, 0.01, (5, 16)),
                            rng.random((10, 16))]).astype(np.float32)
    distances = np.linalg.norm(query[:, None] - place[None], axis=2)
    expected: dict[int, tuple[float, int]] = {}
    for q, row in enumerate(distances):
        first, second = np.sort(row)[:2]
        if first < ratio * second:
            p = int(np.argmin(row))
            if p not in expected or first < expected[p][0]:
                expected[p] = (float(first), q)
    keypoints = np.zeros((40, 5), np.float32)
    query_features, place_features = Features(keypoints, query, "sift"), Features(keypoints, place, "sift")
    got = match_indices(query_features, place_features, ratio=ratio)
    assert sorted(map(tuple, got.tolist())) == sorted((q, p) for p, (_, q) in expected.items())
    assert len(set(got[:, 1].tolist())) == len(got)  # one-to-one: the duplicated query rows claim a place once
    # One neighbour search serves any ratio (the verifier's epipolar and metric tests): the same rows, in order.
    neighbours = nearest_neighbours(query_features, place_features)
    np.testing.assert_array_equal(ratio_test_matches(neighbours, ratio), got)


def test_bad_pairs_are_data_errors_and_empty_features_match_nothing() -> None:
    image = _textured(3, (260, 340))
    sift = extract_features(image, FeatureConfig())
    orb = extract_features(image, FeatureConfig(type="orb"))
    with pytest.raises(DataError, match="cannot match 'sift' features against 'orb' ones"):
        match_indices(sift, orb, ratio=0.8)
    empty = Features(np.zeros((0, 5), np.float32), np.zeros((0, 128), np.float32), "sift")
    assert match_indices(sift, empty, ratio=0.8).shape == (0, 2)
    assert match_indices(empty, sift, ratio=0.8).shape == (0, 2)
    assert len(nearest_neighbours(empty, sift).query_rows) == 0
