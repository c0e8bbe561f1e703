"""Tests for training a whole model (aefabmap_ros/model/training.py)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.features.extraction import FeatureConfig, Features, extract_features
from aefabmap_ros.model.directory import load_model, save_model
from aefabmap_ros.model.training import TrainingConfig, sequence_pairs, train_model
from aefabmap_ros.vocabulary.base import VocabularyConfig

WORDS = 6


def _frames(count: int, seed: int = 0) -> list[Features]:
    """Frames of SIFT-like descriptors drawn around a few centres, each frame from a subset of them."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 100, (WORDS, 128))
    frames = []
    for _ in range(count):
        rows = centres[rng.choice(WORDS, 60)] + rng.normal(0, 4, (60, 128))
        keypoints = np.column_stack([rng.uniform(0, 100, (60, 2)), np.ones(60), np.zeros(60), np.ones(60)])
        frames.append(Features(keypoints.astype(np.float32), np.clip(rows, 0, 255).astype(np.float32), "sift"))
    return frames


def test_the_distilled_encoders_agreement_is_kept_in_the_model_directory(tmp_path: Path) -> None:
    config = VocabularyConfig(size=WORDS, pca_dim=8, ae_embedding_dim=4, ae_epochs=1, num_threads=1,
                              ae_network="conv", ae_student_hidden=8, ae_match_weight=0.0)
    model, _ = train_model([_frames(20)], FeatureConfig(), config, TrainingConfig(), {"sources": []}, progress=False)
    save_model(tmp_path / "model", model)
    kept = load_model(tmp_path / "model").provenance["vocabulary_training"]
    assert isinstance(kept, dict)
    assert 0.0 <= kept["student_word_agreement"] <= 1.0
    assert kept["student_hidden"] == 8.0 and kept["student_held_out_descriptors"] == 60.0  # 5 % of 1,200


def test_a_kmeans_model_has_no_vocabulary_training_record(tmp_path: Path) -> None:
    config = VocabularyConfig(kind="kmeans", size=WORDS)
    model, _ = train_model([_frames(10)], FeatureConfig(), config, TrainingConfig(), {"sources": []}, progress=False)
    assert "vocabulary_training" not in model.provenance


def test_sequence_pairs_index_into_concatenated_descriptors() -> None:
    rng = np.random.default_rng(1)
    base = np.zeros((200, 260), np.uint8)
    for _ in range(50):
        cv2.circle(base, (int(rng.integers(0, 260)), int(rng.integers(0, 200))), int(rng.integers(3, 12)),
                   int(rng.integers(60, 255)), -1)
    frames = [extract_features(base[:, s:s + 220], FeatureConfig()) for s in (0, 4, 8)]
    pairs = sequence_pairs(frames, max_gap=1)
    offsets = np.cumsum([0] + [len(f) for f in frames])
    assert len(pairs) > 10
    all_kp = np.concatenate([f.keypoints for f in frames])
    frame_of = np.searchsorted(offsets, pairs, side="right") - 1
    np.testing.assert_array_equal(frame_of[:, 1] - frame_of[:, 0], 1)
    shift = all_kp[pairs[:, 1], 0] - all_kp[pairs[:, 0], 0]
    np.testing.assert_allclose(np.median(shift), -4, atol=0.5)
    with pytest.raises(ConfigError, match="max_gap=0"):
        sequence_pairs(frames, max_gap=0)
    assert sequence_pairs([Features(np.zeros((0, 5), np.float32), np.zeros((0, 128), np.float32), "sift")]).shape \
        == (0, 2)
