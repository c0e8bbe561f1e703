"""The descriptor-kind policy: one place decides how binary and float rows are held and summarised."""

import cv2
import numpy as np

from aefabmap_ros.features.descriptors import BINARY, FLOAT, kind_of, kind_of_type, kind_of_vocabulary
from aefabmap_ros.features.kinds import FEATURE_TYPES


def test_kinds_by_dtype_feature_type_and_vocabulary():
    assert kind_of(np.zeros((2, 32), np.uint8)) is BINARY
    assert kind_of(np.zeros((2, 128), np.float32)) is FLOAT and kind_of(np.zeros((2, 128), np.float16)) is FLOAT
    assert [t for t in FEATURE_TYPES if kind_of_type(t) is BINARY] == ["orb"]
    assert kind_of_vocabulary(True) is BINARY and kind_of_vocabulary(False) is FLOAT
    assert (BINARY.cv_norm, FLOAT.cv_norm) == (cv2.NORM_HAMMING, cv2.NORM_L2)


def test_binary_vectors_are_bits_and_centres_the_packed_majority():
    rows = np.array([[0b10110000], [0b10100000], [0b00110000]], np.uint8)
    vectors = BINARY.vectors(rows)
    assert vectors.dtype == np.float32 and vectors.shape == (3, 8)
    np.testing.assert_array_equal(vectors[0], [1, 0, 1, 1, 0, 0, 0, 0])
    centre = BINARY.centres(vectors.mean(axis=0, keepdims=True))
    np.testing.assert_array_equal(centre, [[0b10110000]])  # each bit set in 2 of 3 rows stays set


def test_float_vectors_and_centres_are_the_values():
    rows = np.array([[1.5, 2.0]], np.float64)
    assert FLOAT.vectors(rows).dtype == np.float32
    np.testing.assert_array_equal(FLOAT.centres(rows), rows)
