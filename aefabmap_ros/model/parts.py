"""What each node loads of a model directory, and no more.

``load_model`` reads everything: the vocabulary's arrays and encoder, the tree, the new-place samples. A node
needs one part: feature_node the feature settings (``load_feature_config``), fabmap_node the Chow-Liu tree
and the new-place samples with the vocabulary's id and size (``load_place_model``), quantizer_node the
vocabulary (``load_model``). These read the metadata and the files they need, after ``check_model_files``
has checked every listed file against its checksum, so a folder changed after saving is refused here as by
``load_model``; the vocabulary id is the one metadata.json gives (checksummed with the files it was
computed from), and the vocabulary's code is never imported.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse

from aefabmap_ros.errors import ModelError
from aefabmap_ros.features.extraction import FeatureConfig
from aefabmap_ros.model.files import (
    NEW_PLACE_SAMPLES,
    TREE,
    check_model_files,
    feature_config_of,
    load_samples,
    load_tree,
)


def load_feature_config(directory: Path) -> FeatureConfig:
    """The feature settings of a model directory (all its files checked); ModelError names what is wrong."""
    directory = Path(directory)
    return feature_config_of(directory, check_model_files(directory))


@dataclass(frozen=True)
class PlaceModel:
    """What FAB-MAP needs of a model: the vocabulary's id and size, the Chow-Liu tree, the new-place samples."""

    vocabulary_id: str
    vocabulary_size: int
    feature_config: FeatureConfig
    tree_matrix: np.ndarray  # (4, V) float64
    new_place_samples: scipy.sparse.csr_matrix  # (S, V) binary


def load_place_model(directory: Path) -> PlaceModel:
    """The tree and new-place samples of a model directory; ModelError if it has none or they do not fit
    its vocabulary's size."""
    directory = Path(directory)
    metadata = check_model_files(directory)
    files, size = metadata["files"], metadata["vocabulary"]["size"]
    if TREE not in files or NEW_PLACE_SAMPLES not in files:
        raise ModelError(f"model {directory} has no Chow-Liu tree / new-place samples ({TREE}, {NEW_PLACE_SAMPLES})")
    if not isinstance(size, int) or size < 1:
        raise ModelError(f"model {directory}: metadata gives no valid vocabulary size ({size!r})")
    return PlaceModel(
        vocabulary_id=str(metadata["model_id"]), vocabulary_size=size,
        feature_config=feature_config_of(directory, metadata),
        tree_matrix=load_tree(directory / TREE, size),
        new_place_samples=load_samples(directory / NEW_PLACE_SAMPLES, size),
    )


__all__ = ["PlaceModel", "load_feature_config", "load_place_model"]
