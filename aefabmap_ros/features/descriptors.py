"""Descriptor kinds: how rows of one kind are held, compared and averaged (DBoW2's ``FClass`` idea).

Two kinds. *Binary* descriptors (ORB): uint8 rows of packed bits, compared by Hamming distance; as
vectors (k-means, PCA) they are the unpacked 0/1 bits, and the mean of a set is the bitwise majority,
packed again. *Float* descriptors (SIFT, RootSIFT, SURF): float32 rows compared by L2, their own
vectors, the arithmetic mean; the verifier stores them as float16. A uint8 array is binary: SIFT
values that cross the wire as bytes are restored to float32 (``extraction.restore_descriptors``)
before anything asks for their kind. Vocabularies, verification, the feature store and the messages
ask :func:`kind_of` rather than testing dtypes themselves.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aefabmap_ros.features.kinds import BINARY_FEATURE_TYPES


@dataclass(frozen=True)
class DescriptorKind:
    """The policy of one descriptor kind."""

    name: str
    binary: bool
    dtype: type[np.generic]  # rows as extraction gives them and matchers and vocabularies take them
    stored_dtype: type[np.generic]  # rows as the verifier's feature store keeps them
    cv_norm: int  # OpenCV's distance for matching

    def vectors(self, descriptors: np.ndarray) -> np.ndarray:
        """float32 rows to cluster or project: the bits as 0/1 for binary descriptors."""
        if self.binary:
            return np.unpackbits(np.ascontiguousarray(descriptors, np.uint8), axis=1).astype(np.float32)
        return np.ascontiguousarray(descriptors, np.float32)

    def centres(self, vector_means: np.ndarray) -> np.ndarray:
        """(K, D) float32 word centres in descriptor space from means of ``vectors``: the packed
        majority bits (valid binary descriptors, held as float32 0..255) or the means themselves."""
        if self.binary:
            return np.packbits(vector_means >= 0.5, axis=1).astype(np.float32)
        return vector_means


BINARY = DescriptorKind("binary", True, np.uint8, np.uint8, cv2.NORM_HAMMING)
FLOAT = DescriptorKind("float", False, np.float32, np.float16, cv2.NORM_L2)


def kind_of(descriptors: np.ndarray) -> DescriptorKind:
    """The kind of descriptor rows by their dtype: uint8 is binary, anything else float."""
    return BINARY if np.asarray(descriptors).dtype == np.uint8 else FLOAT


def kind_of_type(feature_type: str) -> DescriptorKind:
    """The kind of a feature type's descriptors (``kinds.BINARY_FEATURE_TYPES`` are binary)."""
    return BINARY if feature_type in BINARY_FEATURE_TYPES else FLOAT


def kind_of_vocabulary(binary: bool) -> DescriptorKind:
    """The kind a vocabulary was trained on (vocabularies store ``binary``)."""
    return BINARY if binary else FLOAT
