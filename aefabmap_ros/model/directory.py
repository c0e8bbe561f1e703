"""The model directory (DESIGN 5): everything the nodes load, validated on load.

Layout (format_version 1)::

    metadata.json             format_version, model_id, created_utc, feature_config,
                              vocabulary_config, pca {input_dim, dim} | null,
                              vocabulary {kind, size, descriptor_dim, binary, embedding_dim},
                              provenance (free-form: training bags, their sha256, ...),
                              files {name: sha256} of every other file
    vocabulary.npz            the quantizer's arrays (centres / centroids ...)
    pca.npz                   PCA + [0, 1] scaling (autoencoder vocabularies)
    encoder.npz               the MLP encoder that quantizes (autoencoder vocabularies that have one)
    network.npz               the convolutional autoencoder's state_dict arrays (when it is the autoencoder;
                              folders not yet converted hold them as autoencoder.pt, torch's file)
    chow_liu_tree.npy         (4, V) float64 [parent; marginal; p(z|parent=1); p(z|parent=0)] (optional)
    new_place_samples.npz     scipy.sparse CSR (S, V) binary training observations (optional)

The *vocabulary id* (``Model.vocabulary_id``; the key ``model_id`` of metadata.json, kept for
the directories already written) is a short sha256 over the vocabulary-defining contents (PCA,
vocabulary arrays, autoencoder weights: the values, with their names, dtypes and shapes, not the file
bytes), so two models quantize the same way iff they have the same id, and it stays the same when the
weights move from torch's file to numpy's (``convert.py``); maps and messages carry it (``vocabulary_id``)
to refuse data from another vocabulary. Saving is atomic: the directory is written beside the target and renamed into
place; an existing model directory is replaced only once the new one is complete.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.features.extraction import FeatureConfig
from aefabmap_ros.io.digests import file_sha256
from aefabmap_ros.io.npz_files import npz_bytes, read_npz
from aefabmap_ros.model.files import (
    FORMAT_VERSION,
    METADATA,
    NEW_PLACE_SAMPLES,
    TREE,
    VOCABULARY,
    check_descriptor_dim,
    check_model_files,
    check_samples,
    check_tree,
    feature_config_of,
    load_samples,
    load_tree,
    write_file,
)
from aefabmap_ros.vocabulary.base import Quantizer, StoredVocabulary, VocabularyConfig
from aefabmap_ros.vocabulary.kinds import VOCABULARY_KINDS, runtime_module

VOCABULARY_ID_LENGTH = 16


@dataclass
class Model:
    vocabulary_id: str
    feature_config: FeatureConfig
    vocabulary_config: VocabularyConfig
    quantizer: Quantizer
    tree_matrix: np.ndarray | None = None  # (4, V) float64
    new_place_samples: scipy.sparse.csr_matrix | None = None  # (S, V) binary
    provenance: dict[str, object] = field(default_factory=dict)
    created_utc: str = ""

    @classmethod
    def create(
        cls,
        feature_config: FeatureConfig,
        vocabulary_config: VocabularyConfig,
        quantizer: Quantizer,
        *,
        tree_matrix: np.ndarray | None = None,
        new_place_samples: scipy.sparse.csr_matrix | None = None,
        provenance: dict[str, object] | None = None,
    ) -> Model:
        """A Model with its id computed from the quantizer and the creation time set to now."""
        return cls(
            vocabulary_id=compute_vocabulary_id(quantizer),
            feature_config=feature_config,
            vocabulary_config=vocabulary_config,
            quantizer=quantizer,
            tree_matrix=tree_matrix,
            new_place_samples=new_place_samples,
            provenance=dict(provenance or {}),
            created_utc=datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        )

    @property
    def vocabulary_size(self) -> int:
        return self.quantizer.size


def compute_vocabulary_id(quantizer: Quantizer) -> str:
    """Short sha256 over the values that define how descriptors map to words."""
    digest = hashlib.sha256(quantizer.kind.encode())
    for name, array in sorted(quantizer.to_arrays().items()):
        _hash_array(digest, name, array)
    for name, array in quantizer.identity_arrays().items():  # in the quantizer's order
        _hash_array(digest, name, array)
    return digest.hexdigest()[:VOCABULARY_ID_LENGTH]


def _hash_array(digest: Any, name: str, array: np.ndarray) -> None:
    array = np.ascontiguousarray(array)
    digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
    digest.update(array.tobytes())


# ---------------------------------------------------------------------------------------------- save


def save_model(directory: Path, model: Model) -> None:
    """Write ``model`` to ``directory`` atomically (replacing an existing model directory)."""
    directory = Path(directory)
    _check_consistent(model)
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=directory.parent, prefix=f".{directory.name}.tmp-"))
    try:
        files = _write_contents(tmp, model)
        metadata = _metadata(model, files)
        write_file(tmp / METADATA, json.dumps(metadata, indent=2, sort_keys=True).encode() + b"\n")
        _replace_dir(tmp, directory)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _check_consistent(model: Model) -> None:
    computed = compute_vocabulary_id(model.quantizer)
    if model.vocabulary_id != computed:
        raise ModelError(f"vocabulary_id {model.vocabulary_id!r} does not match its contents ({computed!r}); "
                         "build the Model with Model.create")
    if model.quantizer.kind != model.vocabulary_config.kind:
        raise ModelError(f"quantizer kind {model.quantizer.kind!r} != vocabulary_config.kind "
                         f"{model.vocabulary_config.kind!r}")
    check_descriptor_dim(model.feature_config, model.quantizer.descriptor_dim, "quantizer")
    check_tree(model.tree_matrix, model.quantizer.size, "tree_matrix")
    check_samples(model.new_place_samples, model.quantizer.size, "new_place_samples")


def _write_contents(tmp: Path, model: Model) -> dict[str, str]:
    quantizer = model.quantizer
    write_file(tmp / VOCABULARY, npz_bytes(quantizer.to_arrays()))
    for name, content in quantizer.other_files().items():
        write_file(tmp / name, content)
    if model.tree_matrix is not None:
        buffer = io.BytesIO()
        np.save(buffer, np.asarray(model.tree_matrix, np.float64))
        write_file(tmp / TREE, buffer.getvalue())
    if model.new_place_samples is not None:
        buffer = io.BytesIO()
        scipy.sparse.save_npz(buffer, scipy.sparse.csr_matrix(model.new_place_samples, dtype=np.uint8))
        write_file(tmp / NEW_PLACE_SAMPLES, buffer.getvalue())
    return {path.name: file_sha256(path) for path in sorted(tmp.iterdir())}


def _metadata(model: Model, files: dict[str, str]) -> dict[str, Any]:
    quantizer = model.quantizer
    described = quantizer.metadata()
    return {
        "format_version": FORMAT_VERSION,
        "model_id": model.vocabulary_id,
        "created_utc": model.created_utc or datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "feature_config": model.feature_config.to_dict(),
        "vocabulary_config": model.vocabulary_config.to_dict(),
        "pca": described["pca"],
        "vocabulary": {
            "kind": quantizer.kind,
            "size": quantizer.size,
            "descriptor_dim": quantizer.descriptor_dim,
            "binary": bool(quantizer.binary),
            "embedding_dim": described["embedding_dim"],
        },
        "has_chow_liu_tree": model.tree_matrix is not None,
        "has_new_place_samples": model.new_place_samples is not None,
        "provenance": _jsonable(model.provenance),
        "files": files,
    }


def _jsonable(provenance: dict[str, object]) -> dict[str, Any]:
    try:
        result: dict[str, Any] = json.loads(json.dumps(provenance, default=str))
    except (TypeError, ValueError) as error:
        raise ModelError(f"provenance cannot be written as JSON: {error}") from error
    return result


def _replace_dir(tmp: Path, directory: Path) -> None:
    """Rename the finished temp dir to ``directory``; an existing one is moved aside first, then removed."""
    old: Path | None = None
    if directory.exists() or directory.is_symlink():
        if not directory.is_dir():
            raise ModelError(f"cannot save model: {directory} exists and is not a directory")
        if any(directory.iterdir()) and not (directory / METADATA).exists():
            raise ModelError(f"refusing to replace {directory}: it is not empty and not a model directory")
        old = Path(tempfile.mkdtemp(dir=directory.parent, prefix=f".{directory.name}.old-"))
        os.replace(directory, old / "model")
    try:
        os.replace(tmp, directory)
    except BaseException:
        if old is not None:  # put the previous model back
            os.replace(old / "model", directory)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    with contextlib.suppress(OSError):  # make the renames durable where the platform allows
        fd = os.open(directory.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


# ---------------------------------------------------------------------------------------------- load


def load_model(directory: Path) -> Model:
    """Load and validate a model directory; ModelError names what is missing or wrong."""
    directory = Path(directory)
    metadata = check_model_files(directory)
    files = metadata["files"]
    feature_config = feature_config_of(directory, metadata)
    try:
        vocabulary_config = VocabularyConfig.from_dict(metadata["vocabulary_config"])
    except (ConfigError, TypeError) as error:
        raise ModelError(f"{directory / METADATA}: invalid configuration: {error}") from error
    quantizer = _load_quantizer(directory, metadata, files)
    vocab = metadata["vocabulary"]
    if quantizer.size != vocab["size"]:
        raise ModelError(f"dimension mismatch in {directory}: metadata says vocabulary size {vocab['size']}, "
                         f"{VOCABULARY} has {quantizer.size} words")
    try:
        check_descriptor_dim(feature_config, quantizer.descriptor_dim, f"{directory / VOCABULARY}")
    except ModelError as error:
        raise ModelError(f"dimension mismatch: {error}") from error
    tree = load_tree(directory / TREE, quantizer.size) if TREE in files else None
    samples = load_samples(directory / NEW_PLACE_SAMPLES, quantizer.size) if NEW_PLACE_SAMPLES in files else None
    vocabulary_id = compute_vocabulary_id(quantizer)
    if vocabulary_id != metadata["model_id"]:
        raise ModelError(f"checksum mismatch in {directory}: contents hash to vocabulary id {vocabulary_id}, "
                         f"metadata says {metadata['model_id']}")
    return Model(
        vocabulary_id=vocabulary_id, feature_config=feature_config, vocabulary_config=vocabulary_config,
        quantizer=quantizer, tree_matrix=tree, new_place_samples=samples,
        provenance=dict(metadata.get("provenance") or {}), created_utc=str(metadata.get("created_utc", "")),
    )


def _load_quantizer(directory: Path, metadata: dict[str, Any], files: dict[str, str]) -> Quantizer:
    """The vocabulary, loaded by its kind's own loader (``vocabulary/kinds.py``)."""
    arrays = read_npz(directory / VOCABULARY)
    kind = metadata["vocabulary"]["kind"]
    if kind not in VOCABULARY_KINDS:
        raise ModelError(f"{directory / METADATA}: unknown vocabulary kind {kind!r}")

    def listed_file(name: str) -> Path:
        if name not in files:
            raise ModelError(f"model file {directory / name} is missing (needed by a vocabulary of kind {kind!r})")
        return directory / name

    try:
        quantizer: Quantizer = runtime_module(kind).load_quantizer(StoredVocabulary(arrays, metadata, listed_file))
    except KeyError as error:
        raise ModelError(f"{directory / VOCABULARY} lacks the array {error}") from error
    except (DataError, ConfigError) as error:
        raise ModelError(f"dimension mismatch in {directory}: {error}") from error
    return quantizer


__all__ = ["FORMAT_VERSION", "METADATA", "NEW_PLACE_SAMPLES", "TREE", "VOCABULARY", "VOCABULARY_ID_LENGTH", "Model",
           "check_model_files", "compute_vocabulary_id", "load_model", "save_model"]
