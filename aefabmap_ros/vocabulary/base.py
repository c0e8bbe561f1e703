"""Vocabulary training and use: the common ``Quantizer`` protocol, ``train_vocabulary``, bag-of-words.

Two kinds (``VocabularyConfig.kind``, registered in ``kinds.py``):
- ``"autoencoder"``: the paper's self-supervised quantizer (``autoencoder.py``).
- ``"kmeans"``: the classic FAB-MAP 2 / BoW baseline (``kmeans.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.features.matching import match_indices
from aefabmap_ros.verification.geometric import VerificationConfig, epipolar_inliers
from aefabmap_ros.vocabulary.kinds import VOCABULARY_KINDS, kind_module

if TYPE_CHECKING:
    from aefabmap_ros.vocabulary.autoencoder import AETrainingOptions


@runtime_checkable
class Quantizer(Protocol):
    """Maps raw descriptors to visual words."""

    kind: str  # a key of VOCABULARY_KINDS
    binary: bool  # for uint8 (bit-packed, e.g. ORB) descriptors, else float ones
    descriptor_dim: int  # D: row length of the descriptors it quantizes (bytes when binary)

    @property
    def size(self) -> int:
        """K, the number of words."""
        ...

    @property
    def centroids(self) -> np.ndarray:
        """(K, D) float32 word centres in descriptor space (for openFABMAP export)."""
        ...

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) raw descriptors -> (N,) int64 word ids; (0, D) -> (0,)."""
        ...

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The arrays the model directory stores in its vocabulary.npz."""
        ...

    def identity_arrays(self) -> dict[str, np.ndarray]:
        """Arrays beyond ``to_arrays`` that decide how descriptors map to words, hashed into the model
        id in this order (e.g. the autoencoder's PCA and weights); empty when ``to_arrays`` says it all."""
        ...

    def other_files(self) -> dict[str, bytes]:
        """Further files of the model directory, name -> content (e.g. the autoencoder's weights)."""
        ...

    def metadata(self) -> dict[str, Any]:
        """What metadata.json says of it besides kind, size and dims: ``pca`` ({input_dim, dim} or None)
        and ``embedding_dim`` (int or None)."""
        ...


@dataclass(frozen=True)
class StoredVocabulary:
    """A vocabulary as a model directory holds it, for its kind's ``load_quantizer``."""

    arrays: dict[str, np.ndarray]  # vocabulary.npz
    metadata: dict[str, Any]  # metadata.json
    file: Callable[[str], Path]  # the path of another of its files by name; ModelError if it is missing


@dataclass(frozen=True)
class VocabularyConfig:
    """How to train a vocabulary (flat: one ROS parameter / YAML key each)."""

    kind: str = field(default="autoencoder", metadata={"description": "Vocabulary kind: autoencoder | kmeans."})
    size: int = field(default=1000, metadata={"description": "Number of visual words K."})
    pca_dim: int = field(
        default=64,
        metadata={"description": "PCA dimension of the autoencoder's input (multiple of 4); also used by "
                  "kmeans when kmeans_space is 'pca'."},
    )
    pca_per_component: bool = field(
        default=False,
        metadata={"description": "Scale each PCA component to [0, 1] separately (true) or all with one "
                  "range, keeping PCA geometry (false)."},
    )
    seed: int = field(default=0, metadata={"description": "Random seed (same seed + data = same vocabulary)."})
    num_threads: int = field(
        default=0, metadata={"description": "torch threads while training (0 = leave torch's default)."}
    )
    kmeans_iterations: int = field(
        default=25, metadata={"description": "Lloyd iterations after k-means++ seeding."}
    )
    kmeans_max_points_per_centroid: int = field(
        default=256,
        metadata={"description": "k-means trains on at most this many descriptors per word (random subsample)."},
    )
    ae_embedding_dim: int = field(
        default=64, metadata={"description": "Autoencoder embedding size (the space the words live in)."}
    )
    ae_epochs: int = field(default=8, metadata={"description": "Autoencoder pre-training epochs."})
    ae_batch_size: int = field(default=256, metadata={"description": "Autoencoder mini-batch size."})
    ae_learning_rate: float = field(default=1e-3, metadata={"description": "Adam learning rate, pre-training."})
    ae_max_train_descriptors: int = field(
        default=100_000,
        metadata={"description": "Pre-train the autoencoder on at most this many descriptors (random "
                  "subsample); all descriptors are embedded for the word centres."},
    )
    ae_match_weight: float = field(
        default=0.0,
        metadata={"description": "Weight of the self-supervised match term (same point in neighbouring "
                  "frames embeds close); needs matched pairs; 0 = off."},
    )
    ae_match_temperature: float = field(
        default=0.5, metadata={"description": "Temperature of the match term's InfoNCE (relative to the "
                                              "batch's mean squared distance)."}
    )
    ae_student_hidden: int = field(
        default=256,
        metadata={"description": "Hidden units of a small encoder distilled from the autoencoder that then "
                  "quantizes (PCA -> hidden -> embedding, numpy; 0.88x k-means' time at 256) instead of the "
                  "paper's convolutional network (7x k-means' time); 0 = the paper's network quantizes (the "
                  "reference setting; retrieval within noise of the student's, see README)."},
    )
    ae_student_epochs: int = field(
        default=30, metadata={"description": "Epochs distilling the student from the network's embeddings."}
    )
    ae_student_learning_rate: float = field(
        default=3e-3, metadata={"description": "Adam learning rate of the distillation (cosine-annealed to 0)."}
    )
    ae_student_word_weight: float = field(
        default=0.0,
        metadata={"description": "Weight of the distillation's word term (KL between the network's and the "
                  "student's soft word assignments) against the embedding MSE; 0 (default) = MSE alone: "
                  "1 raised agreement 0.2-0.6 points but closed no more loops, at 2-4x the distillation time."},
    )
    ae_student_word_temperature: float = field(
        default=8.0,
        metadata={"description": "Temperature of the word term's soft assignment, exp(-|z - c|^2 / T), in the "
                  "embedding space normalised to unit variance per dimension."},
    )
    ae_student_noise_rows: int = field(
        default=300_000,
        metadata={"description": "Noisy copies of training rows added to the distillation, labelled by the network "
                  "(0 = none; at most two per training row): the student also learns the network around the "
                  "training descriptors, where another environment's descriptors fall."},
    )
    ae_student_noise_scale: float = field(
        default=0.5,
        metadata={"description": "Std of that noise, as a fraction of each PCA dimension's spread."},
    )
    refine: bool = field(
        default=False,
        metadata={"description": "DEC/IDEC refinement of encoder and centres with reconstruction + "
                  "gamma*KL(P||Q)."},
    )
    refine_epochs: int = field(default=5, metadata={"description": "Maximum refinement epochs."})
    refine_learning_rate: float = field(
        default=1e-4, metadata={"description": "Adam learning rate during refinement."}
    )
    refine_update_interval: int = field(
        default=100, metadata={"description": "Recompute the target distribution every this many batches."}
    )
    gamma: float = field(default=0.1, metadata={"description": "Weight of the clustering KL term (IDEC)."})
    tol: float = field(
        default=0.001,
        metadata={"description": "Stop refining when fewer than this fraction of labels change between targets."},
    )
    alpha: float = field(default=1.0, metadata={"description": "Student-t degrees of freedom of the soft assignment."})

    def __post_init__(self) -> None:
        if self.kind not in VOCABULARY_KINDS:
            raise ConfigError(f"VocabularyConfig.kind={self.kind!r} is not one of {', '.join(VOCABULARY_KINDS)}")
        checks: list[tuple[str, bool, str]] = [
            ("size", self.size >= 2, ">= 2"),
            ("pca_dim", self.pca_dim >= 4 and self.pca_dim % 4 == 0, "a multiple of 4, >= 4"),
            ("num_threads", self.num_threads >= 0, ">= 0"),
            ("kmeans_iterations", self.kmeans_iterations >= 0, ">= 0"),
            ("kmeans_max_points_per_centroid", self.kmeans_max_points_per_centroid >= 1, ">= 1"),
            ("ae_embedding_dim", self.ae_embedding_dim >= 1, ">= 1"),
            ("ae_epochs", self.ae_epochs >= 0, ">= 0"),
            ("ae_batch_size", self.ae_batch_size >= 2, ">= 2"),
            ("ae_learning_rate", self.ae_learning_rate > 0, "> 0"),
            ("ae_max_train_descriptors", self.ae_max_train_descriptors >= 1, ">= 1"),
            ("ae_match_weight", self.ae_match_weight >= 0, ">= 0"),
            ("ae_match_temperature", self.ae_match_temperature > 0, "> 0"),
            ("ae_student_hidden", self.ae_student_hidden >= 0, ">= 0"),
            ("ae_student_epochs", self.ae_student_epochs >= 1, ">= 1"),
            ("ae_student_learning_rate", self.ae_student_learning_rate > 0, "> 0"),
            ("ae_student_word_weight", self.ae_student_word_weight >= 0, ">= 0"),
            ("ae_student_word_temperature", self.ae_student_word_temperature > 0, "> 0"),
            ("ae_student_noise_rows", self.ae_student_noise_rows >= 0, ">= 0"),
            ("ae_student_noise_scale", self.ae_student_noise_scale > 0, "> 0"),
            ("refine_epochs", self.refine_epochs >= 0, ">= 0"),
            ("refine_learning_rate", self.refine_learning_rate > 0, "> 0"),
            ("refine_update_interval", self.refine_update_interval >= 1, ">= 1"),
            ("gamma", self.gamma >= 0, ">= 0"),
            ("tol", 0 <= self.tol < 1, "in [0, 1)"),
            ("alpha", self.alpha > 0, "> 0"),
        ]
        for name, ok, rule in checks:
            if not ok:
                raise ConfigError(f"VocabularyConfig.{name}={getattr(self, name)!r} must be {rule}")

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> VocabularyConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"VocabularyConfig: unknown field(s) {unknown}")
        # Settings saved before these fields (a model's vocabulary_config) were trained without them: say so,
        # not today's defaults (the quantizer itself comes from the model's files either way).
        saved_before = {"ae_student_hidden": 0, "ae_student_epochs": 10, "ae_student_noise_rows": 0}
        return cls(**{**saved_before, **values})

    def ae_options(self) -> AETrainingOptions:
        from aefabmap_ros.vocabulary.autoencoder import AETrainingOptions  # torch, only for this kind

        return AETrainingOptions(
            size=self.size, pca_dim=self.pca_dim, pca_per_component=self.pca_per_component, seed=self.seed,
            num_threads=self.num_threads, embedding_dim=self.ae_embedding_dim, epochs=self.ae_epochs,
            batch_size=self.ae_batch_size, learning_rate=self.ae_learning_rate,
            max_train_descriptors=self.ae_max_train_descriptors, match_weight=self.ae_match_weight,
            match_temperature=self.ae_match_temperature, kmeans_iterations=self.kmeans_iterations,
            refine=self.refine, refine_epochs=self.refine_epochs, refine_learning_rate=self.refine_learning_rate,
            refine_update_interval=self.refine_update_interval, gamma=self.gamma, tol=self.tol, alpha=self.alpha,
            student_hidden=self.ae_student_hidden, student_epochs=self.ae_student_epochs,
            student_learning_rate=self.ae_student_learning_rate, student_word_weight=self.ae_student_word_weight,
            student_word_temperature=self.ae_student_word_temperature,
            student_noise_rows=self.ae_student_noise_rows, student_noise_scale=self.ae_student_noise_scale,
        )


def train_vocabulary(
    descriptors: np.ndarray,
    config: VocabularyConfig,
    *,
    progress: bool = True,
    work_dir: Path | None = None,
    pairs: np.ndarray | None = None,
) -> Quantizer:
    """Train a vocabulary of ``config.size`` words on (N, D) training descriptors.

    float32 rows (SIFT, RootSIFT, SURF) or uint8 rows (ORB, binary). ``pairs``: optional
    (M, 2) row indices of matched descriptors in neighbouring frames (``sequence_pairs``),
    used by the autoencoder's match term when ``ae_match_weight`` > 0. ``work_dir`` holds
    the autoencoder's resumable checkpoint.
    """
    if not isinstance(descriptors, np.ndarray) or descriptors.ndim != 2 or descriptors.shape[1] < 1:
        raise DataError(f"train_vocabulary needs (N, D) descriptors, got shape {getattr(descriptors, 'shape', None)}")
    if descriptors.dtype not in (np.float32, np.float64, np.uint8):
        raise DataError(f"descriptors must be float32/float64 or uint8 (binary), got {descriptors.dtype}")
    if not kind_of(descriptors).binary and not np.all(np.isfinite(descriptors)):
        raise DataError("training descriptors contain NaN or infinity")
    if descriptors.shape[0] < config.size:
        raise DataError(f"vocabulary size={config.size} needs at least that many descriptors, got "
                        f"{descriptors.shape[0]}")
    if descriptors.dtype == np.float64:
        descriptors = descriptors.astype(np.float32)
    quantizer: Quantizer = kind_module(config.kind).train_quantizer(
        descriptors, config, pairs=pairs, progress=progress, work_dir=work_dir)
    return quantizer


def bag_of_words(word_ids: np.ndarray, vocabulary_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Word ids of one image -> (sorted unique word ids uint32, their counts uint32)."""
    ids = np.asarray(word_ids)
    if ids.ndim != 1:
        raise DataError(f"word ids must be 1-D, got shape {ids.shape}")
    if ids.size == 0:
        return np.zeros(0, np.uint32), np.zeros(0, np.uint32)
    if not np.issubdtype(ids.dtype, np.integer):
        raise DataError(f"word ids must be integers, got {ids.dtype}")
    if ids.min() < 0 or ids.max() >= vocabulary_size:
        raise DataError(f"word ids must be in [0, {vocabulary_size}), got range [{ids.min()}, {ids.max()}]")
    unique, counts = np.unique(ids, return_counts=True)
    return unique.astype(np.uint32), counts.astype(np.uint32)


def sequence_pairs(features: Sequence[Features], *, max_gap: int = 1, ratio: float = 0.8) -> np.ndarray:
    """Matched descriptor pairs between frames up to ``max_gap`` apart in an image sequence.

    Returns (M, 2) int64 row indices into ``np.concatenate([f.descriptors for f in features])``:
    the self-supervised signal for ``train_vocabulary(..., pairs=...)``. The same matches the verifier
    counts (``features.matching``, then the epipolar inliers of its default settings).
    """

    if max_gap < 1:
        raise ConfigError(f"max_gap={max_gap} must be >= 1")
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in features])])
    geometry = VerificationConfig()
    chunks = []
    for i in range(len(features)):
        for j in range(i + 1, min(len(features), i + max_gap + 1)):
            local = match_indices(features[i], features[j], ratio=ratio)
            points = (features[i].keypoints[local[:, 0], :2].astype(np.float32),
                      features[j].keypoints[local[:, 1], :2].astype(np.float32))
            local = local[epipolar_inliers(*points, geometry)]
            chunks.append(local + np.array([offsets[i], offsets[j]]))
    return np.concatenate(chunks).astype(np.int64) if chunks else np.zeros((0, 2), np.int64)


def word_usage(quantizer: Quantizer, descriptors: np.ndarray) -> np.ndarray:
    """(K,) int64 number of descriptors quantized to each word."""
    return np.bincount(quantizer.quantize(descriptors), minlength=quantizer.size)


__all__ = [
    "VOCABULARY_KINDS",
    "Quantizer",
    "StoredVocabulary",
    "VocabularyConfig",
    "bag_of_words",
    "sequence_pairs",
    "train_vocabulary",
    "word_usage",
]
