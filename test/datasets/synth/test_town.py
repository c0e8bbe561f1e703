"""Synthetic town sequences: shapes, poses, ground truth, image statistics, determinism, colour (the parts:
test_config.py, test_world.py, test_trajectory.py, test_renderer.py)."""

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.town import depth_to_16uc1, generate_sequence
from aefabmap_ros.evaluation.covisibility import covisibility_loop_matrix
from aefabmap_ros.evaluation.ground_truth import positions_and_axes

# 640x480 so that SIFT statistics mean what they mean at the default size; 120 frames over 2 laps.
SEQUENCE_CONFIG = SynthConfig(seed=5, num_frames=120)
TINY_CONFIG = SynthConfig(seed=3, num_frames=6, width=96, height=72, texels_per_m=16.0, ground_texels_per_m=8.0)


@pytest.fixture(scope="module")
def sequence():
    return generate_sequence(SEQUENCE_CONFIG)


class _LazySift:
    """SIFT of a frame computed on first use: the tests need only a few dozen of the frames."""

    def __init__(self, images):
        self.images = images
        self.sift = cv2.SIFT_create()  # type: ignore[attr-defined]
        self.cache = {}

    def __getitem__(self, index):
        if index not in self.cache:
            self.cache[index] = self.sift.detectAndCompute(self.images[index], None)
        return self.cache[index]


@pytest.fixture(scope="module")
def sift_features(sequence):
    return _LazySift(sequence.images)


def test_shapes_and_types(sequence):
    n = SEQUENCE_CONFIG.num_frames
    assert len(sequence.images) == n
    assert all(image.shape == (480, 640) and image.dtype == np.uint8 for image in sequence.images)
    assert sequence.stamps_ns.dtype == np.int64 and sequence.stamps_ns.shape == (n,)
    np.testing.assert_array_equal(np.diff(sequence.stamps_ns), 100_000_000)  # 10 Hz
    assert sequence.positions.shape == (n, 3) and sequence.optical_axes.shape == (n, 3)
    assert sequence.gt.shape == (n, n) and sequence.gt.dtype == np.uint8
    assert sequence.poses.shape == (n, 3, 4)
    focal = 320 / math.tan(math.radians(30))
    expected = np.array([[focal, 0, 319.5], [0, focal, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(sequence.camera_matrix, expected)


def test_images_are_not_flat_or_saturated(sequence):
    for image in sequence.images[::10]:
        assert 40 < image.mean() < 215
        assert image.std() > 20
        assert (image == 255).mean() < 0.05 and (image == 0).mean() < 0.05


def test_poses_are_rotations_consistent_with_axes(sequence):
    rotations = sequence.poses[:, :, :3]
    identity = np.einsum("nji,njk->nik", rotations, rotations)
    np.testing.assert_allclose(identity, np.broadcast_to(np.eye(3), identity.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0)
    positions, axes = positions_and_axes(sequence.poses)
    np.testing.assert_allclose(positions, sequence.positions)
    np.testing.assert_allclose(axes, sequence.optical_axes)
    np.testing.assert_allclose(rotations[:, :, 1], np.tile([0, 0, -1.0], (len(rotations), 1)))  # y down


def test_speed_is_plausible(sequence):
    steps = np.linalg.norm(np.diff(sequence.positions[:, :2], axis=0), axis=1)
    assert 0.5 < np.median(steps) < 3.0
    assert steps.max() < 3 * np.median(steps)


def test_gt_poses_agrees_with_poses(sequence):
    """Recompute the pose-rule loop matrix with a plain double loop over the published poses."""
    cfg = SEQUENCE_CONFIG
    n = cfg.num_frames
    expected = np.zeros((n, n), dtype=np.uint8)
    for i in range(n):
        for j in range(i - cfg.gt_min_gap_frames + 1):
            close = np.linalg.norm(sequence.positions[i] - sequence.positions[j]) <= cfg.gt_max_distance_m
            cosine = float(np.dot(sequence.optical_axes[i], sequence.optical_axes[j]))
            if close and math.degrees(math.acos(min(1.0, cosine))) <= cfg.gt_max_angle_deg:
                expected[i, j] = 1
    np.testing.assert_array_equal(sequence.gt_poses, expected)
    # Two laps of a figure-eight: the second lap revisits the first, and the middle street is driven twice a lap.
    assert sequence.gt_poses.any(axis=1).sum() >= n // 3


def test_gt_is_covisibility_of_the_written_depth(sequence):
    n = SEQUENCE_CONFIG.num_frames
    assert sequence.depths.shape == (n, 480, 640) and sequence.depths.dtype == np.float32
    expected = covisibility_loop_matrix(depth_to_16uc1(sequence.depths), sequence.poses, sequence.camera_matrix,
                                        sequence.stamps_ns, min_gap_s=SEQUENCE_CONFIG.gt_min_gap_s, depth_scale=1000.0)
    np.testing.assert_array_equal(sequence.gt, expected)
    # 60 frames (6 s) a lap: the second lap revisits the first, beyond the 5 s gap.
    assert sequence.gt[70:].any(axis=1).sum() >= 25
    assert not sequence.gt[:50].any()
    # Most revisits are close in space too (the same street, the same direction).
    i, j = np.nonzero(sequence.gt)
    distance = np.linalg.norm(sequence.positions[i] - sequence.positions[j], axis=1)
    assert np.median(distance) < 5.0


def test_depth_to_16uc1():
    depth = np.array([[0.0, 0.0004, 0.0006, 1.2344], [65.535, 65.536, np.inf, np.nan]], dtype=np.float32)
    millimetres = depth_to_16uc1(depth)
    assert millimetres.dtype == np.uint16
    assert millimetres.tolist() == [[0, 0, 1, 1234], [65535, 0, 0, 0]]


def test_sift_finds_plenty_of_keypoints(sift_features):
    counts = np.array([len(sift_features[index][0]) for index in range(0, SEQUENCE_CONFIG.num_frames, 4)])
    assert np.median(counts) >= 300
    assert np.percentile(counts, 10) >= 150  # even the motion-blurred frames keep texture


def _ratio_matches(first, second) -> int:
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(first, second, k=2)
    return sum(1 for pair in matches if len(pair) == 2 and pair[0].distance < 0.75 * pair[1].distance)


def test_revisits_look_alike(sequence, sift_features):
    rng = np.random.default_rng(0)
    loop_i, loop_j = np.nonzero(sequence.gt)
    picks = rng.choice(loop_i.size, size=min(15, loop_i.size), replace=False)
    revisit = [_ratio_matches(sift_features[loop_i[p]][1], sift_features[loop_j[p]][1]) for p in picks]
    others: list[int] = []
    while len(others) < 15:
        i, j = (int(v) for v in rng.integers(0, len(sequence.images), size=2))
        far = np.linalg.norm(sequence.positions[i] - sequence.positions[j]) > 10.0
        if i - j >= 10 and far:
            others.append(_ratio_matches(sift_features[i][1], sift_features[j][1]))
    assert np.mean(revisit) > 3 * np.mean(others)
    assert np.median(revisit) > 60


def test_deterministic_given_seed():
    first = generate_sequence(TINY_CONFIG)
    second = generate_sequence(TINY_CONFIG)
    for a, b in zip(first.images, second.images, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first.positions, second.positions)
    other = generate_sequence(replace(TINY_CONFIG, seed=4))
    assert not np.array_equal(first.images[0], other.images[0])


def test_color_images():
    sequence = generate_sequence(replace(TINY_CONFIG, color=True, num_frames=2))
    assert sequence.images[0].shape == (72, 96, 3)
    channels = sequence.images[0].reshape(-1, 3).mean(axis=0)
    assert channels.max() - channels.min() > 1.0  # bluish sky, coloured facades: not grey
