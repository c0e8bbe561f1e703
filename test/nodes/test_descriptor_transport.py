"""Descriptors cross DDS losslessly in the smallest type: bytes for ORB and integer-valued SIFT."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip("aefabmap_msgs.msg")

from std_msgs.msg import Header

from aefabmap_ros.features.extraction import FeatureConfig, Features, extract_features, rootsift
from aefabmap_ros.nodes.messages import features_to_message, message_to_features


def _textured_image(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(60, 80), dtype=np.uint8)
    return np.kron(small, np.ones((4, 4), np.uint8))  # blocks: corners and blobs for every detector


def _round_trip(features: Features) -> tuple[Features, Any]:
    message = features_to_message(features, Header(), (320, 240))
    return message_to_features(message), message


@pytest.mark.parametrize("kind", ["sift", "orb", "rootsift"])
def test_extracted_descriptors_round_trip_exactly(kind: str) -> None:
    features = extract_features(_textured_image(), FeatureConfig(type=kind, max_features=200))
    assert len(features) > 20
    got, _ = _round_trip(features)
    assert got.descriptors.dtype == features.descriptors.dtype
    np.testing.assert_array_equal(got.descriptors, features.descriptors)
    np.testing.assert_array_equal(got.keypoints, features.keypoints)
    assert got.descriptor_type == kind


def test_sift_crosses_as_bytes_and_rootsift_as_floats() -> None:
    image = _textured_image()
    sift = extract_features(image, FeatureConfig(type="sift", max_features=200))
    _, sift_message = _round_trip(sift)
    assert len(sift_message.binary_descriptors) == sift.descriptors.size
    assert len(sift_message.float_descriptors) == 0
    root = Features(sift.keypoints, rootsift(sift.descriptors), "rootsift")
    _, root_message = _round_trip(root)
    assert len(root_message.float_descriptors) == root.descriptors.size
    assert len(root_message.binary_descriptors) == 0


@pytest.mark.parametrize("values", [[0.5, 3.0], [-1.0, 2.0], [256.0, 1.0]])
def test_sift_typed_floats_that_do_not_fit_a_byte_fall_back_to_float(values: list[float]) -> None:
    descriptors = np.zeros((2, 128), np.float32)
    descriptors[:, :2] = values
    features = Features(np.zeros((2, 5), np.float32), descriptors, "sift")
    got, message = _round_trip(features)
    assert len(message.float_descriptors) == descriptors.size
    assert got.descriptors.dtype == np.float32
    np.testing.assert_array_equal(got.descriptors, descriptors)


def test_older_float32_sift_messages_still_read() -> None:
    descriptors = np.arange(2 * 128, dtype=np.float32).reshape(2, 128) % 256
    message = features_to_message(Features(np.zeros((2, 5), np.float32), descriptors, "sift"), Header(), (8, 8))
    message.binary_descriptors = []  # what the suite sent before descriptors crossed as bytes
    message.float_descriptors = descriptors.reshape(-1).tolist()
    got = message_to_features(message)
    assert got.descriptors.dtype == np.float32
    np.testing.assert_array_equal(got.descriptors, descriptors)
