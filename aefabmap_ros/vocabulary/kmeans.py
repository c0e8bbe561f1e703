"""The k-means vocabulary (the classic FAB-MAP 2 / BoW baseline) as the nodes run it: nearest centre, numpy.

Training is ``kmeans_training.py`` (faiss, scikit-learn); this module imports neither, so quantizing needs
only numpy. A word is the nearest centre by L2 (``nearest.NearestCentre``, the search faiss made when the
vocabulary was trained).

Binary descriptors (ORB, uint8 rows of packed bits): the centres are the per-bit frequencies of the
words' members ((K, 8 * D) floats, a soft k-majority) and a descriptor's word is the centre nearest its
unpacked 0/1 bits by L2, |c|^2 - 2 x.c: a Hamming distance weighted by how sure each centre is of each bit.
Plain Hamming distance to the majority bits would give other words than the ones the vocabulary was
trained and its maps were built with. ``centroids`` of a binary vocabulary are the packed majority bits,
(K, 32) as float32 values 0..255, i.e. valid ORB descriptors.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.descriptors import kind_of, kind_of_vocabulary
from aefabmap_ros.vocabulary.nearest import NearestCentre

if TYPE_CHECKING:
    from aefabmap_ros.vocabulary.base import StoredVocabulary


class KMeansQuantizer:
    """Nearest-centre quantizer; centres in descriptor space (bit space for binary descriptors)."""

    kind = "kmeans"

    def __init__(self, centres: np.ndarray, descriptor_dim: int, binary: bool) -> None:
        centres = np.ascontiguousarray(centres, np.float32)
        expected = descriptor_dim * 8 if binary else descriptor_dim
        if centres.ndim != 2 or centres.shape[0] < 1 or centres.shape[1] != expected:
            raise DataError(
                f"k-means centres must be (K, {expected}) for {descriptor_dim}-d "
                f"{'binary' if binary else 'float'} descriptors, got {centres.shape}"
            )
        if not np.all(np.isfinite(centres)):
            raise DataError("k-means centres contain NaN or infinity")
        self.centres = centres  # (K, D) float32, or (K, 8*D) bit frequencies for binary descriptors
        self.descriptor_dim = descriptor_dim
        self.binary = binary
        self._search = NearestCentre(centres)

    @property
    def size(self) -> int:
        return int(self.centres.shape[0])

    @property
    def centroids(self) -> np.ndarray:
        """(K, D) float32 in descriptor space (packed majority bits for binary descriptors)."""
        return kind_of_vocabulary(self.binary).centres(self.centres)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) raw descriptors -> (N,) int64 word ids."""
        check_descriptors(descriptors, self.descriptor_dim, self.binary)
        return self._search.nearest_of(descriptors, kind_of_vocabulary(self.binary).vectors)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "centres": self.centres,
            "descriptor_dim": np.array(self.descriptor_dim),
            "binary": np.array(self.binary),
        }

    def identity_arrays(self) -> dict[str, np.ndarray]:
        return {}  # the centres say it all

    def other_files(self) -> dict[str, bytes]:
        return {}

    def metadata(self) -> dict[str, Any]:
        return {"pca": None, "embedding_dim": None}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> KMeansQuantizer:
        return cls(np.asarray(arrays["centres"]), int(arrays["descriptor_dim"]), bool(arrays["binary"]))


def load_quantizer(stored: StoredVocabulary) -> KMeansQuantizer:
    """The kind's loader for the model directory (registered in ``kinds.py``)."""
    return KMeansQuantizer.from_arrays(stored.arrays)


def check_descriptors(descriptors: np.ndarray, descriptor_dim: int, binary: bool) -> None:
    """DataError unless descriptors are (N, descriptor_dim) of the vocabulary's kind (uint8 if binary)."""
    if not isinstance(descriptors, np.ndarray) or descriptors.ndim != 2 or descriptors.shape[1] != descriptor_dim:
        raise DataError(
            f"expected (N, {descriptor_dim}) descriptors, got shape {getattr(descriptors, 'shape', None)}"
        )
    given = kind_of(descriptors)
    if binary and not given.binary:
        raise DataError(f"this vocabulary is for binary (uint8) descriptors, got dtype {descriptors.dtype}")
    if not binary and given.binary:
        raise DataError("this vocabulary is for float descriptors, got uint8 (binary, e.g. ORB) descriptors")


__all__ = ["KMeansQuantizer", "check_descriptors", "load_quantizer"]
