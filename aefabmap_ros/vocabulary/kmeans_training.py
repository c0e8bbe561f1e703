"""Training of the k-means vocabulary (``kmeans.py`` holds the quantizer the nodes run) and the k-means
helpers the autoencoder's training reuses.

k-means++ seeding (scikit-learn's ``kmeans_plusplus`` on a subsample of at most
``KMEANS_PLUSPLUS_MAX_POINTS`` points: exact k-means++ costs O(N K log K) distance evaluations, minutes
for 300k x 1000), then Lloyd iterations with faiss on (a faiss subsample of at most
``max_points_per_centroid * K``) the data. faiss re-seeds empty clusters by splitting large ones; a last
pass here re-seeds any word that still gets no training descriptor, so every word is used.

Binary descriptors (ORB, uint8 rows of packed bits): k-means on the unpacked bits as 0/1 floats. Squared
Euclidean distance between bit vectors is their Hamming distance, and the mean of a cluster is its per-bit
frequency, whose rounding is the k-majority centre; the centres kept are the bit frequencies (``kmeans.py``).

Training only: faiss and scikit-learn are imported here, never by a node.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import faiss
import numpy as np
import scipy.sparse
from sklearn.cluster import kmeans_plusplus

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.vocabulary.kmeans import KMeansQuantizer

if TYPE_CHECKING:
    from aefabmap_ros.vocabulary.config import VocabularyConfig

KMEANS_PLUSPLUS_MAX_POINTS = 50_000


def kmeans(
    x: np.ndarray,
    k: int,
    seed: int,
    iterations: int = 25,
    max_points_per_centroid: int = 256,
) -> np.ndarray:
    """k-means++-seeded k-means of (N, D) float32 rows -> (k, D) float32 centres (all non-empty on x)."""
    n = x.shape[0]
    if k < 1:
        raise ConfigError(f"vocabulary size={k} must be >= 1")
    if n < k:
        raise DataError(f"k-means needs at least size={k} training descriptors, got {n}")
    x = np.ascontiguousarray(x, np.float32)
    rng = np.random.default_rng(seed)
    init_idx = rng.choice(n, size=min(n, max(KMEANS_PLUSPLUS_MAX_POINTS, k)), replace=False)
    init_idx.sort()
    init, _ = kmeans_plusplus(x[init_idx], n_clusters=k, random_state=int(rng.integers(2**31 - 1)))
    centres = np.ascontiguousarray(init, np.float32)
    if iterations > 0 and k > 1:
        km = faiss.Kmeans(
            x.shape[1], k, niter=iterations, seed=int(rng.integers(2**31 - 1)),
            max_points_per_centroid=max_points_per_centroid, min_points_per_centroid=1,
            verbose=False, spherical=False,
        )
        km.train(x, init_centroids=centres)
        centres = np.ascontiguousarray(km.centroids, np.float32)
    return reseed_empty(x, centres, rng)


def nearest(centres: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest centre of each row: (labels (N,) int64, squared distances (N,) float32)."""
    if x.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    index = faiss.IndexFlatL2(centres.shape[1])
    index.add(np.ascontiguousarray(centres, np.float32))
    distances, labels = index.search(np.ascontiguousarray(x, np.float32), 1)
    return labels[:, 0].astype(np.int64), distances[:, 0]


def reseed_empty(x: np.ndarray, centres: np.ndarray, rng: np.random.Generator,
                 rounds: int = 3) -> np.ndarray:
    """Move centres that own no row of x onto the worst-fitted rows of the largest clusters.

    A couple of Lloyd steps after each move let the neighbours adapt; words still empty
    after ``rounds`` (duplicate rows) are left as they are.
    """
    centres = centres.copy()
    for _ in range(rounds):
        labels, distances = nearest(centres, x)
        counts = np.bincount(labels, minlength=len(centres))
        empty = np.flatnonzero(counts == 0)
        if empty.size == 0:
            break
        # Worst-fitted rows (far from their centre) of clusters with more than one member.
        candidates = np.flatnonzero(counts[labels] > 1)
        if candidates.size == 0:
            break
        order = candidates[np.argsort(-distances[candidates], kind="stable")]
        chosen = order[: empty.size * 4]
        picks = rng.choice(chosen, size=min(empty.size, chosen.size), replace=False)
        centres[empty[: picks.size]] = x[picks]
        centres = _lloyd_steps(x, centres, steps=2)
    return centres


def _lloyd_steps(x: np.ndarray, centres: np.ndarray, steps: int) -> np.ndarray:
    for _ in range(steps):
        labels, _ = nearest(centres, x)
        centres = cluster_means(x, labels, len(centres), centres)  # a centre with no member stays where it is
    return centres


def cluster_means(x: np.ndarray, labels: np.ndarray, k: int, fallback: np.ndarray) -> np.ndarray:
    """Mean of the rows of each label (paper eq. 3); ``fallback`` rows for labels with no member."""
    counts = np.bincount(labels, minlength=k).astype(np.float64)
    # The sums as one sparse (K, N) membership matrix times x: np.add.at takes 5x as long on 200k rows.
    membership = scipy.sparse.csr_matrix((np.ones(labels.size), (labels, np.arange(labels.size))),
                                         shape=(k, labels.size))
    sums = np.asarray(membership @ x.astype(np.float64))
    means = np.asarray(fallback, np.float64).copy()
    filled = counts > 0
    means[filled] = sums[filled] / counts[filled, None]
    return means.astype(np.float32)


def train_quantizer(descriptors: np.ndarray, config: VocabularyConfig, *, pairs: np.ndarray | None = None,
                    progress: bool = True, work_dir: Path | None = None) -> KMeansQuantizer:
    """The kind's trainer for ``train_vocabulary`` (k-means uses no pairs, progress or checkpoints)."""
    return train_kmeans_quantizer(descriptors, config.size, config.seed, config.kmeans_iterations,
                                  config.kmeans_max_points_per_centroid)


def train_kmeans_quantizer(
    descriptors: np.ndarray, size: int, seed: int, iterations: int = 25, max_points_per_centroid: int = 256
) -> KMeansQuantizer:
    """k-means vocabulary of ``size`` words from (N, D) descriptors (uint8 rows = binary)."""
    kind = kind_of(descriptors)
    x = kind.vectors(descriptors)
    centres = kmeans(x, size, seed, iterations, max_points_per_centroid)
    return KMeansQuantizer(centres, descriptors.shape[1], kind.binary)


__all__ = ["KMEANS_PLUSPLUS_MAX_POINTS", "cluster_means", "kmeans", "nearest", "reseed_empty", "train_kmeans_quantizer",
           "train_quantizer"]
