"""Tests for a vocabulary's word statistics on a sequence (aefabmap_ros/evaluation/word_statistics.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.evaluation.word_statistics import usage_perplexity, word_statistics
from aefabmap_ros.features.extraction import FeatureConfig, Features, extract_features
from aefabmap_ros.model.training import pairs_at_gap, sequence_pairs
from aefabmap_ros.vocabulary.kmeans import KMeansQuantizer

CENTRES = np.arange(4, dtype=np.float32)[:, None] * np.full((1, 128), 10.0, np.float32)  # word k: every dim 10 k


def _frame(words: list[int]) -> Features:
    """A frame whose descriptors lie on the given words' centres (so its words are known)."""
    keypoints = np.zeros((len(words), 5), np.float32)
    return Features(keypoints, CENTRES[words] + 1.0, "sift")


def test_perplexity_is_the_number_of_equally_used_words() -> None:
    assert usage_perplexity(np.array([0, 1, 2, 3]), 10) == pytest.approx(4.0)
    assert usage_perplexity(np.array([5, 5, 5]), 10) == pytest.approx(1.0)
    # shares 1/2, 1/4, 1/4: entropy 1.5 ln 2, perplexity 2 ** 1.5
    assert usage_perplexity(np.array([0, 0, 1, 2]), 3) == pytest.approx(2 ** 1.5)


def test_figures_of_frames_with_known_words_match_a_hand_count() -> None:
    quantizer = KMeansQuantizer(CENTRES, descriptor_dim=128, binary=False)
    # words per frame: {0, 1}, {1, 2}, {2, 3} (frame 1 holds word 1 twice), then a frame with no features
    frames = [_frame([0, 1]), _frame([1, 1, 2]), _frame([2, 3]), Features(np.zeros((0, 5), np.float32),
                                                                           np.zeros((0, 128), np.float32), "sift")]
    # rows: frame 0 = 0, 1; frame 1 = 2, 3, 4; frame 2 = 5, 6. Pairs one word: (1, 2), (1, 3); not: (0, 4).
    pairs = {1: np.array([[1, 2], [1, 3], [0, 4]]), 2: np.zeros((0, 2), np.int64)}
    stats = word_statistics(quantizer, frames, pairs, far_gap=2)
    assert (stats.size, stats.used) == (4, 4)
    assert stats.words_per_image == pytest.approx(2.0)  # the empty frame is not an image with words
    assert [(a.gap, a.pairs) for a in stats.agreement] == [(1, 3), (2, 0)]
    assert stats.agreement[0].one_word == pytest.approx(2 / 3)
    assert math.isnan(stats.agreement[1].one_word)
    assert stats.shared_next == pytest.approx(0.5)  # {0,1}->{1,2}: 1/2; {1,2}->{2,3}: 1/2; the empty frame skipped
    assert stats.shared_far == pytest.approx(0.0)  # {0,1} and {2,3} share nothing
    # usage: word 0 once, 1 three times, 2 twice, 3 once, of 7
    share = np.array([1, 3, 2, 1]) / 7
    assert stats.perplexity == pytest.approx(math.exp(-np.sum(share * np.log(share))))


def test_bad_input_is_refused() -> None:
    quantizer = KMeansQuantizer(CENTRES, descriptor_dim=128, binary=False)
    with pytest.raises(ConfigError, match="far_gap=0"):
        word_statistics(quantizer, [_frame([0])], {}, far_gap=0)
    empty = Features(np.zeros((0, 5), np.float32), np.zeros((0, 128), np.float32), "sift")
    with pytest.raises(DataError, match="no frame of the sequence has features"):
        word_statistics(quantizer, [empty, empty], {1: np.zeros((0, 2), np.int64)})
    with pytest.raises(DataError, match="pairs at gap 1"):
        word_statistics(quantizer, [_frame([0, 1])], {1: np.array([[0, 2]])})


def _shifted_views(count: int, step: int) -> list[Features]:
    """Crops of one textured image, each ``step`` pixels further right: a pure translation between views."""
    rng = np.random.default_rng(3)
    base = np.zeros((200, 300), np.uint8)
    for _ in range(60):
        cv2.circle(base, (int(rng.integers(0, 300)), int(rng.integers(0, 200))), int(rng.integers(3, 12)),
                   int(rng.integers(60, 255)), -1)
    return [extract_features(base[:, s:s + 220], FeatureConfig()) for s in range(0, count * step, step)]


def test_pairs_at_a_gap_are_matches_between_frames_exactly_that_far_apart() -> None:
    frames = _shifted_views(4, 4)
    offsets = np.cumsum([0] + [len(f) for f in frames])
    keypoints = np.concatenate([f.keypoints for f in frames])
    for gap in (1, 2, 3):
        pairs = pairs_at_gap(frames, gap)
        assert len(pairs) > 10
        frame_of = np.searchsorted(offsets, pairs, side="right") - 1
        np.testing.assert_array_equal(frame_of[:, 1] - frame_of[:, 0], gap)
        # the scene moved 4 px left per frame: a true match moves by -4 gap
        np.testing.assert_allclose(np.median(keypoints[pairs[:, 1], 0] - keypoints[pairs[:, 0], 0]), -4 * gap,
                                   atol=0.5)
    # sequence_pairs up to gap 2 is the union of the gap-1 and gap-2 pairs
    union = {tuple(p) for gap in (1, 2) for p in pairs_at_gap(frames, gap)}
    assert {tuple(p) for p in sequence_pairs(frames, max_gap=2)} == union
    with pytest.raises(ConfigError, match="gap=0"):
        pairs_at_gap(frames, 0)


def test_one_word_for_everything_keeps_every_pair_and_every_word() -> None:
    """A one-word vocabulary: every matched pair shares it, every frame holds exactly it."""
    frames = _shifted_views(3, 5)
    quantizer = KMeansQuantizer(np.full((1, 128), 20.0, np.float32), descriptor_dim=128, binary=False)
    stats = word_statistics(quantizer, frames, {1: pairs_at_gap(frames, 1)}, far_gap=2)
    assert stats.agreement[0].one_word == 1.0 and stats.agreement[0].pairs > 10
    assert (stats.perplexity, stats.words_per_image, stats.shared_next, stats.shared_far) == (1.0, 1.0, 1.0, 1.0)
