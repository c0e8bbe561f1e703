"""The model directory (DESIGN 5): everything the nodes load, validated on load.

Layout (format_version 1)::

    metadata.json             format_version, model_id, created_utc, feature_config,
                              vocabulary_config, pca {input_dim, dim} | null,
                              vocabulary {kind, size, descriptor_dim, binary, embedding_dim},
                              provenance (free-form: training bags, their sha256, ...),
                              files {name: sha256} of every other file
    vocabulary.npz            the quantizer's arrays (centres / centroids ...)
    pca.npz                   PCA + [0, 1] scaling (autoencoder vocabularies)
    autoencoder.pt            the autoencoder's state_dict (autoencoder vocabularies)
    chow_liu_tree.npy         (4, V) float64 [parent; marginal; p(z|parent=1); p(z|parent=0)] (optional)
    new_place_samples.npz     scipy.sparse CSR (S, V) binary training observations (optional)

The *vocabulary id* (``Model.vocabulary_id``; the key ``model_id`` of metadata.json, kept for
the directories already written) is a short sha256 over the vocabulary-defining contents (PCA,
vocabulary arrays, autoencoder weights: the values, not the file bytes), so two models quantize
the same way iff they have the same id; maps and messages carry it (``vocabulary_id``) to refuse
data from another vocabulary. Saving is atomic: the directory is written beside the target and renamed into
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
from aefabmap_ros.features.extraction import FeatureConfig, descriptor_length
from aefabmap_ros.io.digests import file_sha256
from aefabmap_ros.io.npz_files import npz_bytes, read_npz
from aefabmap_ros.vocabulary.base import Quantizer, StoredVocabulary, VocabularyConfig
from aefabmap_ros.vocabulary.kinds import VOCABULARY_KINDS, kind_module

FORMAT_VERSION = 1
METADATA = "metadata.json"
VOCABULARY = "vocabulary.npz"
TREE = "chow_liu_tree.npy"
NEW_PLACE_SAMPLES = "new_place_samples.npz"
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
        _write_file(tmp / METADATA, json.dumps(metadata, indent=2, sort_keys=True).encode() + b"\n")
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
    _check_descriptor_dim(model.feature_config, model.quantizer.descriptor_dim, "quantizer")
    _check_tree(model.tree_matrix, model.quantizer.size, "tree_matrix")
    _check_samples(model.new_place_samples, model.quantizer.size, "new_place_samples")


def _write_contents(tmp: Path, model: Model) -> dict[str, str]:
    quantizer = model.quantizer
    _write_file(tmp / VOCABULARY, npz_bytes(quantizer.to_arrays()))
    for name, content in quantizer.other_files().items():
        _write_file(tmp / name, content)
    if model.tree_matrix is not None:
        buffer = io.BytesIO()
        np.save(buffer, np.asarray(model.tree_matrix, np.float64))
        _write_file(tmp / TREE, buffer.getvalue())
    if model.new_place_samples is not None:
        buffer = io.BytesIO()
        scipy.sparse.save_npz(buffer, scipy.sparse.csr_matrix(model.new_place_samples, dtype=np.uint8))
        _write_file(tmp / NEW_PLACE_SAMPLES, buffer.getvalue())
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


def _write_file(path: Path, data: bytes) -> None:
    with open(path, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


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


def check_model_files(directory: Path) -> dict[str, Any]:
    """A model directory's metadata, once it and every file it lists are there with their checksums: what a
    launcher checks before it starts the nodes, without loading a vocabulary (torch) itself. ModelError names
    what is missing or wrong; the contents are checked by ``load_model``."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ModelError(f"model directory {directory} does not exist or is not a directory")
    metadata = _read_metadata(directory)
    for name, expected in metadata["files"].items():
        path = directory / name
        if not path.is_file():
            raise ModelError(f"model file {path} is missing")
        if file_sha256(path) != expected:
            raise ModelError(f"checksum mismatch for {path}: the file is corrupt or was changed after saving")
    return metadata


def load_model(directory: Path) -> Model:
    """Load and validate a model directory; ModelError names what is missing or wrong."""
    directory = Path(directory)
    metadata = check_model_files(directory)
    files = metadata["files"]
    try:
        feature_config = FeatureConfig.from_dict(metadata["feature_config"])
        vocabulary_config = VocabularyConfig.from_dict(metadata["vocabulary_config"])
    except (ConfigError, TypeError) as error:
        raise ModelError(f"{directory / METADATA}: invalid configuration: {error}") from error
    quantizer = _load_quantizer(directory, metadata, files)
    vocab = metadata["vocabulary"]
    if quantizer.size != vocab["size"]:
        raise ModelError(f"dimension mismatch in {directory}: metadata says vocabulary size {vocab['size']}, "
                         f"{VOCABULARY} has {quantizer.size} words")
    try:
        _check_descriptor_dim(feature_config, quantizer.descriptor_dim, f"{directory / VOCABULARY}")
    except ModelError as error:
        raise ModelError(f"dimension mismatch: {error}") from error
    tree = _load_tree(directory / TREE, quantizer.size) if TREE in files else None
    samples = _load_samples(directory / NEW_PLACE_SAMPLES, quantizer.size) if NEW_PLACE_SAMPLES in files else None
    vocabulary_id = compute_vocabulary_id(quantizer)
    if vocabulary_id != metadata["model_id"]:
        raise ModelError(f"checksum mismatch in {directory}: contents hash to vocabulary id {vocabulary_id}, "
                         f"metadata says {metadata['model_id']}")
    return Model(
        vocabulary_id=vocabulary_id, feature_config=feature_config, vocabulary_config=vocabulary_config,
        quantizer=quantizer, tree_matrix=tree, new_place_samples=samples,
        provenance=dict(metadata.get("provenance") or {}), created_utc=str(metadata.get("created_utc", "")),
    )


def _read_metadata(directory: Path) -> dict[str, Any]:
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
        quantizer: Quantizer = kind_module(kind).load_quantizer(StoredVocabulary(arrays, metadata, listed_file))
    except KeyError as error:
        raise ModelError(f"{directory / VOCABULARY} lacks the array {error}") from error
    except (DataError, ConfigError) as error:
        raise ModelError(f"dimension mismatch in {directory}: {error}") from error
    return quantizer


def _check_descriptor_dim(feature_config: FeatureConfig, descriptor_dim: int, where: str) -> None:
    expected = descriptor_length(feature_config)
    if descriptor_dim != expected:
        raise ModelError(f"{where} is for {descriptor_dim}-d descriptors but feature type "
                         f"{feature_config.type!r} gives {expected}-d")


def _check_tree(tree: np.ndarray | None, size: int, where: str) -> None:
    if tree is None:
        return
    if tree.shape != (4, size):
        raise ModelError(f"dimension mismatch: {where} has shape {tree.shape}, expected (4, {size})")
    if not np.all(np.isfinite(tree)):
        raise ModelError(f"{where} contains NaN or infinity")


def _check_samples(samples: scipy.sparse.csr_matrix | None, size: int, where: str) -> None:
    if samples is None:
        return
    if samples.ndim != 2 or samples.shape[1] != size:
        raise ModelError(f"dimension mismatch: {where} has shape {samples.shape}, expected (S, {size})")


def _load_tree(path: Path, size: int) -> np.ndarray:
    try:
        tree = np.load(path, allow_pickle=False)
    except Exception as error:
        raise ModelError(f"cannot read {path}: {error}") from error
    _check_tree(tree, size, str(path))
    return np.asarray(tree, np.float64)


def _load_samples(path: Path, size: int) -> scipy.sparse.csr_matrix:
    try:
        samples = scipy.sparse.load_npz(path).tocsr()
    except Exception as error:
        raise ModelError(f"cannot read {path}: {error}") from error
    _check_samples(samples, size, str(path))
    return scipy.sparse.csr_matrix(samples)
