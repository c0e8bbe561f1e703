"""Vocabulary training and use: the common ``Quantizer`` protocol, ``train_vocabulary``, bag-of-words.

Two kinds (``VocabularyConfig.kind``, ``config.py``; registered in ``kinds.py``), each quantized in numpy by
one module and trained by another:
- ``"autoencoder"``: the paper's self-supervised quantizer (``autoencoder.py``; ``autoencoder_training.py``).
- ``"kmeans"``: the classic FAB-MAP 2 / BoW baseline (``kmeans.py``; ``kmeans_training.py``).
``train_vocabulary`` imports the training module of the kind it trains, so importing this module costs no torch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.vocabulary.config import VocabularyConfig
from aefabmap_ros.vocabulary.kinds import VOCABULARY_KINDS, training_module


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
    (M, 2) row indices of matched descriptors in neighbouring frames (``model.training.sequence_pairs``),
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
    quantizer: Quantizer = training_module(config.kind).train_quantizer(
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


def word_usage(quantizer: Quantizer, descriptors: np.ndarray) -> np.ndarray:
    """(K,) int64 number of descriptors quantized to each word."""
    return np.bincount(quantizer.quantize(descriptors), minlength=quantizer.size)


__all__ = [
    "VOCABULARY_KINDS",
    "Quantizer",
    "StoredVocabulary",
    "VocabularyConfig",
    "bag_of_words",
    "train_vocabulary",
    "word_usage",
]
