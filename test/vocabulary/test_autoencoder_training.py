"""Tests for training the autoencoder vocabulary (aefabmap_ros/vocabulary/autoencoder_training.py)."""

import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer
from aefabmap_ros.vocabulary.autoencoder_training import _centroids_of_empty_words
from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary
from aefabmap_ros.vocabulary.kmeans_training import cluster_means


def _two_words_seen_twice(points: int = 600, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-d descriptors of scene points seen in two frames. Axes 0-3: wide spread, as wide between the two views
    of one point (std 20: no word can live there). Axes 4-7: two tight groups of points (the true words) at
    +-6 on every axis, each view within 0.3 of its point. Rows are (views x points); returns rows, pairs, word."""
    rng = np.random.default_rng(seed)
    word = rng.integers(0, 2, points)
    scene = np.zeros((points, 8))
    scene[:, 4:] = np.where(word[:, None] == 1, 6.0, -6.0) + rng.normal(0, 0.5, (points, 4))
    views = [scene + rng.normal(size=scene.shape) * np.r_[np.full(4, 20.0), np.full(4, 0.3)] for _ in range(2)]
    rows = np.concatenate(views) + 60.0  # SIFT-like: non-negative
    pairs = np.stack([np.arange(points), np.arange(points) + points], axis=1)
    return rows.astype(np.float32), pairs, np.concatenate([word, word])


def _purity(words: np.ndarray, truth: np.ndarray) -> float:
    """Share of rows whose vocabulary word agrees with the majority true word of that vocabulary word."""
    agreeing = sum(np.bincount(truth[words == w]).max() for w in np.unique(words))
    return float(agreeing / truth.size)


def _train(ae_input: str, rows: np.ndarray, pairs: np.ndarray) -> AutoencoderQuantizer:
    config = VocabularyConfig(size=2, pca_dim=4, ae_input=ae_input, ae_embedding_dim=4, ae_epochs=2,
                              ae_student_hidden=0, num_threads=1, seed=0)
    quantizer = train_vocabulary(rows, config, pairs=pairs, progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer)
    return quantizer


def test_words_from_matches_separate_the_groups_the_views_agree_on() -> None:
    rows, pairs, truth = _two_words_seen_twice()
    learned = _train("matches", rows, pairs)
    assert _purity(learned.quantize(rows), truth) > 0.95
    # The same vocabulary from the principal axes sees only the wide axes the views disagree on.
    assert _purity(_train("pca", rows, pairs).quantize(rows), truth) < 0.7


def test_the_match_projection_needs_pairs() -> None:
    rows, _, _ = _two_words_seen_twice(50)
    with pytest.raises(DataError, match="needs matched descriptor pairs"):
        train_vocabulary(rows, VocabularyConfig(size=2, pca_dim=4, ae_input="matches", ae_epochs=1,
                                                ae_student_hidden=0), progress=False)


def test_centroids_are_member_means_and_an_empty_words_nearest_descriptor() -> None:
    rng = np.random.default_rng(5)
    rows = rng.uniform(0, 100, (300, 16)).astype(np.float32)
    z = rng.normal(size=(300, 3)).astype(np.float32)
    centres = np.vstack([rng.normal(size=(3, 3)), [[40.0, 40.0, 40.0]]]).astype(np.float32)  # word 3: far off
    labels = np.argmin(((z[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
    assert np.all(labels != 3)
    fallback = _centroids_of_empty_words(rows, z, centres, labels)
    nearest_row = np.argmin(((z - centres[3]) ** 2).sum(axis=1))  # brute force
    np.testing.assert_array_equal(fallback[3], rows[nearest_row])
    means = cluster_means(rows, labels, 4, fallback)
    for word in range(3):
        np.testing.assert_allclose(means[word], rows[labels == word].mean(axis=0), rtol=1e-5)
    np.testing.assert_array_equal(means[3], rows[nearest_row])
