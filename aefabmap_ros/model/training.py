"""Offline training: image sequences -> features -> vocabulary -> training BoW -> Chow-Liu tree -> Model.

Library first (``train_model``); ``aefabmap_train`` only gathers images and calls it. Expensive
stages are cached in a work directory keyed by what they depend on, so a rerun after a failure or
an interruption resumes: per-sequence features (keyed by the source's fingerprint and the feature
settings) and the autoencoder's checkpoint (kept by ``train_vocabulary`` itself).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import learn_chow_liu_tree
from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.features.extraction import FeatureConfig, Features, extract_features
from aefabmap_ros.features.matching import match_indices
from aefabmap_ros.io.atomic import atomic_open
from aefabmap_ros.model.directory import Model
from aefabmap_ros.verification.geometric import VerificationConfig, epipolar_inliers
from aefabmap_ros.vocabulary.base import Quantizer, VocabularyConfig, train_vocabulary
from aefabmap_ros.vocabulary.kmeans import KMeansQuantizer


@dataclass(frozen=True)
class TrainingConfig:
    """Settings of the stages after the vocabulary (flat: one YAML key each)."""

    lower_info_bound: float = field(
        default=0.0005,
        metadata={"description": "Chow-Liu edges carrying less mutual information than this (nats) are dropped "
                  "(openFABMAP's LowerInfoBound)."},
    )
    pair_max_gap: int = field(
        default=1,
        metadata={"description": "Self-supervision: match features between frames up to this many apart "
                  "(used when the vocabulary's ae_match_weight > 0 or its ae_input is 'matches')."},
    )
    max_new_place_samples: int = field(
        default=2000,
        metadata={"description": "At most this many training images become new-place samples (evenly spaced)."},
    )

    def __post_init__(self) -> None:
        if not self.lower_info_bound >= 0:
            raise ConfigError(f"TrainingConfig.lower_info_bound={self.lower_info_bound} must be >= 0")
        if self.pair_max_gap < 1:
            raise ConfigError(f"TrainingConfig.pair_max_gap={self.pair_max_gap} must be >= 1")
        if self.max_new_place_samples < 1:
            raise ConfigError(f"TrainingConfig.max_new_place_samples={self.max_new_place_samples} must be >= 1")


Progress = Callable[[str], None]


def _no_progress(_message: str) -> None:
    pass


def config_digest(*configs: Any) -> str:
    payload = json.dumps([asdict(config) for config in configs], sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


# ---------------------------------------------------------------------------------------- features


def _save_features(path: Path, features: Sequence[Features]) -> None:
    counts = np.array([len(f.descriptors) for f in features], dtype=np.int64)
    keypoints = np.concatenate([f.keypoints for f in features]) if features else np.zeros((0, 5), np.float32)
    descriptors = np.concatenate([f.descriptors for f in features])
    with atomic_open(path) as file:
        np.savez(file, counts=counts, keypoints=keypoints, descriptors=descriptors,
                 descriptor_type=np.array(features[0].descriptor_type))


def _load_features(path: Path) -> list[Features]:
    with np.load(path) as data:
        offsets = np.concatenate([[0], np.cumsum(data["counts"])])
        keypoints, descriptors = data["keypoints"], data["descriptors"]
        descriptor_type = str(data["descriptor_type"])
    return [
        Features(keypoints=keypoints[a:b], descriptors=descriptors[a:b], descriptor_type=descriptor_type)
        for a, b in itertools.pairwise(offsets)
    ]


def extract_sequence_features(
    frames: Iterable[np.ndarray],
    config: FeatureConfig,
    *,
    cache_path: Path | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> list[Features]:
    """Features of every frame, in order (empty frames keep their index); cached at ``cache_path``."""
    if cache_path is not None and cache_path.exists():
        return _load_features(cache_path)
    features = []
    for index, gray in enumerate(frames):
        features.append(extract_features(gray, config))
        if on_frame is not None:
            on_frame(index)
    if not features:
        raise DataError("the image sequence is empty")
    if cache_path is not None:
        _save_features(cache_path, features)
    return features


# ------------------------------------------------------------------------- self-supervision pairs


def sequence_pairs(features: Sequence[Features], *, max_gap: int = 1, ratio: float = 0.8) -> np.ndarray:
    """Matched descriptor pairs between frames up to ``max_gap`` apart in an image sequence.

    Returns (M, 2) int64 row indices into ``np.concatenate([f.descriptors for f in features])``:
    the self-supervised signal for ``train_vocabulary(..., pairs=...)``. The same matches the verifier
    counts (``features.matching``, then the epipolar inliers of its default settings).
    """
    if max_gap < 1:
        raise ConfigError(f"max_gap={max_gap} must be >= 1")
    frames = [(i, j) for i in range(len(features)) for j in range(i + 1, min(len(features), i + max_gap + 1))]
    return _matched_rows(features, frames, ratio)


def pairs_at_gap(features: Sequence[Features], gap: int, *, ratio: float = 0.8) -> np.ndarray:
    """``sequence_pairs`` between frames exactly ``gap`` apart only: (M, 2) rows, the earlier frame's first."""
    if gap < 1:
        raise ConfigError(f"gap={gap} must be >= 1")
    return _matched_rows(features, [(i, i + gap) for i in range(len(features) - gap)], ratio)


def _matched_rows(features: Sequence[Features], frames: Iterable[tuple[int, int]], ratio: float) -> np.ndarray:
    """The epipolar-inlier matches of each (i, j) frame pair, as rows into the concatenated descriptors."""
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in features])])
    geometry = VerificationConfig()
    chunks = []
    for i, j in frames:
        local = match_indices(features[i], features[j], ratio=ratio)
        points = (features[i].keypoints[local[:, 0], :2].astype(np.float32),
                  features[j].keypoints[local[:, 1], :2].astype(np.float32))
        local = local[epipolar_inliers(*points, geometry)]
        chunks.append(local + np.array([offsets[i], offsets[j]]))
    return np.concatenate(chunks).astype(np.int64) if chunks else np.zeros((0, 2), np.int64)


def uses_pairs(config: VocabularyConfig) -> bool:
    """Whether training this vocabulary needs self-supervision pairs (the match term or the match projection)."""
    return config.kind == "autoencoder" and (config.ae_match_weight > 0 or config.ae_input == "matches")


def training_pairs(sequences: Sequence[Sequence[Features]], max_gap: int) -> np.ndarray:
    """``sequence_pairs`` of every sequence, as row indices into all their descriptors concatenated in order;
    pairs never cross from one sequence into the next."""
    offset, chunks = 0, [np.zeros((0, 2), np.int64)]
    for sequence in sequences:
        chunks.append(sequence_pairs(sequence, max_gap=max_gap) + offset)
        offset += sum(len(f.descriptors) for f in sequence)
    return np.concatenate(chunks)


# ------------------------------------------------------------------------------------- BoW, model


def binary_bow(quantizer: Quantizer, features: Sequence[Features]) -> sp.csr_matrix:
    """(N images, K words) binary CSR: word present in the image or not (what FAB-MAP observes)."""
    rows, cols = [], []
    for index, image_features in enumerate(features):
        words = np.unique(quantizer.quantize(image_features.descriptors))
        rows.append(np.full(words.size, index, dtype=np.int64))
        cols.append(words)
    row = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    col = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    data = np.ones(row.size, dtype=np.float64)
    return sp.csr_matrix((data, (row, col)), shape=(len(features), quantizer.size))


def count_bow(quantizer: Quantizer, features: Sequence[Features]) -> sp.csr_matrix:
    """(N images, K words) word counts (what tf-idf scores)."""
    rows = []
    for image_features in features:
        counts = np.bincount(quantizer.quantize(image_features.descriptors), minlength=quantizer.size)
        rows.append(sp.csr_matrix(counts.astype(np.float64)))
    return sp.vstack(rows, format="csr") if rows else sp.csr_matrix((0, quantizer.size))


def evenly_spaced(count: int, limit: int) -> np.ndarray:
    return np.unique(np.linspace(0, count - 1, num=min(count, limit)).round().astype(np.int64))


@dataclass
class TrainingReport:
    """What ``train_model`` did, for the CLI's summary."""

    num_images: int = 0
    num_descriptors: int = 0
    images_without_features: int = 0
    num_pairs: int = 0
    words_used: int = 0
    tree_edges: int = 0
    seconds: dict[str, float] = field(default_factory=dict)


def train_model(
    sequences: Sequence[Sequence[Features]],
    feature_config: FeatureConfig,
    vocabulary_config: VocabularyConfig,
    training_config: TrainingConfig,
    provenance: dict[str, Any],
    *,
    work_dir: Path | None = None,
    progress: bool = True,
    log: Progress = _no_progress,
) -> tuple[Model, TrainingReport]:
    """Train a complete model from the features of one or more training sequences."""
    report = TrainingReport()  # filled as the stages run
    all_features = [f for sequence in sequences for f in sequence]
    report.num_images = len(all_features)
    report.images_without_features = sum(1 for f in all_features if len(f.descriptors) == 0)
    descriptors = np.concatenate([f.descriptors for f in all_features]) if all_features else np.zeros((0, 0))
    report.num_descriptors = len(descriptors)
    if report.num_descriptors < vocabulary_config.size:
        raise DataError(
            f"{report.num_descriptors} training descriptors from {report.num_images} images are fewer than the "
            f"vocabulary size {vocabulary_config.size}: give more or richer images, or a smaller vocabulary"
        )

    pairs = None
    if uses_pairs(vocabulary_config):
        started = time.monotonic()
        log("matching features between neighbouring frames (self-supervision pairs)")
        pairs = training_pairs(sequences, training_config.pair_max_gap)
        report.num_pairs = len(pairs)
        report.seconds["pairs"] = time.monotonic() - started

    started = time.monotonic()
    log(f"training a {vocabulary_config.size}-word {vocabulary_config.kind} vocabulary on "
        f"{report.num_descriptors} descriptors")
    vocab_dir = None
    if work_dir is not None:
        vocab_dir = work_dir / f"vocabulary-{config_digest(feature_config, vocabulary_config)}"
        vocab_dir.mkdir(parents=True, exist_ok=True)
    quantizer = train_vocabulary(descriptors, vocabulary_config, progress=progress, work_dir=vocab_dir, pairs=pairs)
    report.seconds["vocabulary"] = time.monotonic() - started

    started = time.monotonic()
    log("quantizing the training images and learning the Chow-Liu tree")
    bow = binary_bow(quantizer, all_features)
    report.words_used = int((bow.sum(axis=0) > 0).sum())
    tree = learn_chow_liu_tree(bow, training_config.lower_info_bound)
    report.tree_edges = int(np.sum(tree.parent != np.arange(tree.vocabulary_size)))
    samples = bow[evenly_spaced(bow.shape[0], training_config.max_new_place_samples)]
    report.seconds["bow_and_tree"] = time.monotonic() - started

    model = Model.create(
        feature_config=feature_config,
        vocabulary_config=vocabulary_config,
        quantizer=quantizer,
        tree_matrix=tree.to_matrix(),
        new_place_samples=sp.csr_matrix(samples),
        provenance={**provenance, "training": asdict(training_config), **vocabulary_training(quantizer)},
    )
    return model, report


def vocabulary_training(quantizer: Quantizer) -> dict[str, dict[str, float]]:
    """What the vocabulary's training measured (an autoencoder's stage times, its distilled encoder's
    word agreement with the network on held-out descriptors), kept in the model's provenance so the
    figure travels with the directory instead of one line of aefabmap_train's output."""
    info: dict[str, float] = getattr(quantizer, "training_info", {})
    return {"vocabulary_training": {name: float(value) for name, value in info.items()}} if info else {}


def sampled_centres_model(
    features: Sequence[Features], feature_config: FeatureConfig, size: int, seed: int = 0,
    lower_info_bound: float = 0.0005,
) -> Model:
    """A complete model whose word centres are ``size`` descriptors sampled from ``features``.

    No clustering, so it costs seconds: for benchmarks and tests that exercise the machinery
    (timing, plumbing), not for accuracy. Binary descriptors (ORB) get bit-space centres.
    """
    descriptors = np.concatenate([f.descriptors for f in features])
    if len(descriptors) < size:
        raise DataError(f"{len(descriptors)} descriptors are fewer than the vocabulary size {size}")
    rng = np.random.default_rng(seed)
    kind = kind_of(descriptors)
    centres = kind.vectors(descriptors[rng.choice(len(descriptors), size=size, replace=False)])
    quantizer = KMeansQuantizer(centres, descriptor_dim=descriptors.shape[1], binary=kind.binary)
    bow = binary_bow(quantizer, features)
    return Model.create(
        feature_config=feature_config,
        vocabulary_config=VocabularyConfig(kind="kmeans", size=size, seed=seed),
        quantizer=quantizer,
        tree_matrix=learn_chow_liu_tree(bow, lower_info_bound).to_matrix(),
        new_place_samples=bow,
        provenance={"vocabulary": f"{size} sampled descriptors (no clustering)"},
    )
