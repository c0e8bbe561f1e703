"""The files of a model directory, read without its vocabulary: names, metadata, checksums, the feature
settings, the Chow-Liu tree and the new-place samples.

What a node that does not quantize needs (feature_node: the feature settings; fabmap_node: the tree and the
samples) is read from here, and none of it imports a vocabulary's code. Layout: ``directory.py``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse

from aefabmap_ros.errors import ConfigError, ModelError
from aefabmap_ros.features.extraction import FeatureConfig, descriptor_length
from aefabmap_ros.io.digests import file_sha256

FORMAT_VERSION = 1
METADATA = "metadata.json"
VOCABULARY = "vocabulary.npz"
TREE = "chow_liu_tree.npy"
NEW_PLACE_SAMPLES = "new_place_samples.npz"


def check_model_files(directory: Path) -> dict[str, Any]:
    """A model directory's metadata, once it and every file it lists are there with their checksums: what a
    launcher checks before it starts the nodes, without loading a vocabulary itself. ModelError names
    what is missing or wrong; the contents are checked by ``load_model``."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ModelError(f"model directory {directory} does not exist or is not a directory")
    metadata = read_metadata(directory)
    for name, expected in metadata["files"].items():
        path = directory / name
        if not path.is_file():
            raise ModelError(f"model file {path} is missing")
        if file_sha256(path) != expected:
            raise ModelError(f"checksum mismatch for {path}: the file is corrupt or was changed after saving")
    return metadata


def read_metadata(directory: Path) -> dict[str, Any]:
    """metadata.json of a model directory, once it is of this format and has the keys every reader needs."""
    path = directory / METADATA
    if not path.is_file():
        raise ModelError(f"model file {path} is missing (is {directory} a model directory?)")
    try:
        metadata = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ModelError(f"cannot read {path}: {error}") from error
    if not isinstance(metadata, dict):
        raise ModelError(f"{path} does not hold a JSON object")
    version = metadata.get("format_version")
    if version != FORMAT_VERSION:
        raise ModelError(f"{path}: format_version {version!r} is not supported (this build reads "
                         f"format_version {FORMAT_VERSION})")
    required = ("model_id", "feature_config", "vocabulary_config", "vocabulary", "files")
    missing = [key for key in required if key not in metadata]
    if missing:
        raise ModelError(f"{path} lacks the key(s) {missing}")
    if not isinstance(metadata["files"], dict) or VOCABULARY not in metadata["files"]:
        raise ModelError(f"{path}: 'files' must list {VOCABULARY} with its checksum")
    vocab = metadata["vocabulary"]
    if not isinstance(vocab, dict) or not {"kind", "size", "descriptor_dim"} <= set(vocab):
        raise ModelError(f"{path}: 'vocabulary' must give kind, size and descriptor_dim")
    return metadata


def feature_config_of(directory: Path, metadata: dict[str, Any]) -> FeatureConfig:
    """The feature settings metadata.json gives; ModelError naming the file if they are invalid."""
    try:
        return FeatureConfig.from_dict(metadata["feature_config"])
    except (ConfigError, TypeError) as error:
        raise ModelError(f"{Path(directory) / METADATA}: invalid configuration: {error}") from error


def write_file(path: Path, data: bytes) -> None:
    """``data`` into ``path``, flushed to the disk (the folder it is in is renamed into place afterwards)."""
    with open(path, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


def check_descriptor_dim(feature_config: FeatureConfig, descriptor_dim: int, where: str) -> None:
    expected = descriptor_length(feature_config)
    if descriptor_dim != expected:
        raise ModelError(f"{where} is for {descriptor_dim}-d descriptors but feature type "
                         f"{feature_config.type!r} gives {expected}-d")


def check_tree(tree: np.ndarray | None, size: int, where: str) -> None:
    if tree is None:
        return
    if tree.shape != (4, size):
        raise ModelError(f"dimension mismatch: {where} has shape {tree.shape}, expected (4, {size})")
    if not np.all(np.isfinite(tree)):
        raise ModelError(f"{where} contains NaN or infinity")


def check_samples(samples: scipy.sparse.csr_matrix | None, size: int, where: str) -> None:
    if samples is None:
        return
    if samples.ndim != 2 or samples.shape[1] != size:
        raise ModelError(f"dimension mismatch: {where} has shape {samples.shape}, expected (S, {size})")


def load_tree(path: Path, size: int) -> np.ndarray:
    try:
        tree = np.load(path, allow_pickle=False)
    except Exception as error:
        raise ModelError(f"cannot read {path}: {error}") from error
    check_tree(tree, size, str(path))
    return np.asarray(tree, np.float64)


def load_samples(path: Path, size: int) -> scipy.sparse.csr_matrix:
    try:
        samples = scipy.sparse.load_npz(path).tocsr()
    except Exception as error:
        raise ModelError(f"cannot read {path}: {error}") from error
    check_samples(samples, size, str(path))
    return scipy.sparse.csr_matrix(samples)


__all__ = ["FORMAT_VERSION", "METADATA", "NEW_PLACE_SAMPLES", "TREE", "VOCABULARY", "check_descriptor_dim",
           "check_model_files", "check_samples", "check_tree", "feature_config_of", "load_samples", "load_tree",
           "read_metadata", "write_file"]
