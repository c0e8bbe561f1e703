"""The autoencoder quantizer (DESIGN 4.3) as the nodes run it: self-supervised vector quantization, numpy.

Descriptors -> linear projection -> [0, 1] (``pca.py``: the principal axes, or with ``ae_input: matches``
the axes that keep one scene point's descriptors together across frames) -> encoder -> embedding -> K
centres in embedding space. The word is the argmax of the Student-t soft assignment, i.e. the nearest
centre (the kernel is monotone in distance).

Two encoders, both numpy, neither needing torch:
- the MLP encoder (``mlp_encoder.MlpEncoder``): the MLP autoencoder's own encoder (``ae_network: mlp``,
  the default), or an encoder distilled from the paper's network (``distilled.py``);
- the paper's 1-D convolutional network (``conv_encoder.ConvEncoder``), kept in full (its decoder too:
  the vocabulary id covers it) when it is the autoencoder. It quantizes only when no MLP encoder was
  distilled from it: counted in multiply-adds per descriptor it costs about 5x k-means' search.
The torch modules and the training are ``autoencoder_network.py`` and ``autoencoder_training.py``; model
folders whose network is still in torch's format (``AUTOENCODER``) are read by ``legacy_weights.py``.
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from aefabmap_ros.errors import DataError, ModelError
from aefabmap_ros.features.descriptors import kind_of_vocabulary
from aefabmap_ros.io.npz_files import npz_bytes, read_npz
from aefabmap_ros.vocabulary.conv_encoder import ConvEncoder
from aefabmap_ros.vocabulary.kmeans import check_descriptors
from aefabmap_ros.vocabulary.mlp_encoder import CentreSearch, MlpEncoder
from aefabmap_ros.vocabulary.pca import PCA

if TYPE_CHECKING:
    from aefabmap_ros.vocabulary.base import StoredVocabulary

# The model directory's files of an autoencoder vocabulary, beside vocabulary.npz:
PCA_FILE = "pca.npz"  # PCA + [0, 1] scaling
NETWORK_FILE = "network.npz"  # the convolutional network's arrays (``conv_encoder.py``), when it is the autoencoder
AUTOENCODER = "autoencoder.pt"  # the same as a torch state_dict, in model folders not yet converted
ENCODER_FILE = "encoder.npz"  # the MLP encoder that quantizes (``mlp_encoder.py``), when there is one
STUDENT_FILE = "student.npz"  # the same arrays under the name model folders of earlier versions give them
QUANTIZE_BATCH = 8192  # rows quantized at once: bounds the (rows, K) scores


class AutoencoderQuantizer:
    """PCA + encoder + embedding centres; ``quantize`` is one batched forward pass, in numpy.

    The encoder is the MLP ``encoder`` when there is one: the MLP autoencoder's own encoder, or a student
    distilled from the convolutional ``network``. Without one, the ``network`` quantizes. ``quantize``,
    ``embed`` and ``soft_assign`` all use that same encoder.
    """

    kind = "autoencoder"

    def __init__(
        self,
        pca: PCA,
        network: ConvEncoder | None,
        embedding_centres: np.ndarray,  # (K, E) float32
        descriptor_centroids: np.ndarray,  # (K, D) float32 (packed majority bits for binary)
        binary: bool,
        descriptor_dim: int,
        alpha: float = 1.0,
        encoder: MlpEncoder | None = None,
    ) -> None:
        if network is None and encoder is None:
            raise DataError("an autoencoder vocabulary needs an encoder: the MLP encoder, the network or both")
        _check_parts(pca, network, encoder, embedding_centres, descriptor_centroids, binary, descriptor_dim)
        self.pca = pca
        self.network = network
        self.encoder = encoder
        self.embedding_centres = np.ascontiguousarray(embedding_centres, np.float32)
        self._centroids = np.ascontiguousarray(descriptor_centroids, np.float32)
        self.binary = binary
        self.descriptor_dim = descriptor_dim
        self.alpha = alpha
        # Filled by training: seconds per stage, word usage on the training set, the student's agreement.
        self.training_info: dict[str, float] = {}

    @property
    def size(self) -> int:
        return int(self.embedding_centres.shape[0])

    @property
    def centroids(self) -> np.ndarray:
        """(K, D) float32: mean descriptor of each word (paper eq. 3)."""
        return self._centroids

    @functools.cached_property
    def _centre_search(self) -> CentreSearch:
        """The nearest-centre matmul, built on its first use."""
        return CentreSearch(self.embedding_centres)

    @property
    def embedding_dim(self) -> int:
        return int(self.embedding_centres.shape[1])

    def with_encoder(self, encoder: MlpEncoder | None) -> AutoencoderQuantizer:
        """The same vocabulary quantized by ``encoder`` (None: by the convolutional network)."""
        return AutoencoderQuantizer(self.pca, self.network, self.embedding_centres, self._centroids, self.binary,
                                    self.descriptor_dim, self.alpha, encoder)

    def embed(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) raw descriptors -> (N, E) float32 embeddings, by the encoder ``quantize`` uses."""
        check_descriptors(descriptors, self.descriptor_dim, self.binary)
        return self._encode(self._inputs(descriptors))

    def _inputs(self, descriptors: np.ndarray) -> np.ndarray:
        return self.pca.transform_scaled(kind_of_vocabulary(self.binary).vectors(descriptors))

    def _encode(self, x: np.ndarray) -> np.ndarray:
        if self.encoder is not None:
            return self.encoder.embed(x)
        assert self.network is not None  # one of the two, checked on construction
        return self.network.embed(x)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) raw descriptors -> (N,) int64 word ids (argmax of the Student-t assignment)."""
        check_descriptors(descriptors, self.descriptor_dim, self.binary)
        out = np.empty(descriptors.shape[0], np.int64)
        for start in range(0, descriptors.shape[0], QUANTIZE_BATCH):
            x = self._inputs(descriptors[start:start + QUANTIZE_BATCH])
            # the embedding with a column of ones, so the centre search is one product (mlp_encoder.CentreSearch)
            z = self.encoder.embed_with_one(x) if self.encoder is not None else _with_one(self._encode(x))
            out[start:start + x.shape[0]] = self._centre_search.nearest(z)
        return out

    def soft_assign(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, K) float32 Student-t soft assignments (rows sum to 1) of ``embed``'s embeddings."""
        return student_t(self.embed(descriptors), self.embedding_centres, self.alpha)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "embedding_centres": self.embedding_centres,
            "centroids": self._centroids,
            "binary": np.array(self.binary),
            "descriptor_dim": np.array(self.descriptor_dim),
            "embedding_dim": np.array(self.embedding_dim),
            "alpha": np.array(self.alpha),
        }

    def identity_arrays(self) -> dict[str, np.ndarray]:
        arrays = {"pca." + name: array for name, array in sorted(self.pca.to_arrays().items())}
        if self.network is not None:  # keyed by the torch state_dict's names, sorted: stored models' ids keep
            arrays.update({"ae." + name: array for name, array in self.network.to_arrays().items()})
        if self.encoder is not None:  # it decides the words: a vocabulary with another encoder is another one
            # (keyed "student." whichever way the encoder was trained: the key is part of saved models' ids)
            arrays.update({"student." + name: array for name, array in self.encoder.to_arrays().items()})
        return arrays

    def other_files(self) -> dict[str, bytes]:
        files = {PCA_FILE: npz_bytes(self.pca.to_arrays())}
        if self.network is not None:
            files[NETWORK_FILE] = npz_bytes(self.network.to_arrays())
        if self.encoder is not None:
            files[ENCODER_FILE] = npz_bytes(self.encoder.to_arrays())
        return files

    def metadata(self) -> dict[str, Any]:
        return {"pca": {"input_dim": self.pca.input_dim, "dim": self.pca.dim}, "embedding_dim": self.embedding_dim}


def _check_parts(pca: PCA, network: ConvEncoder | None, encoder: MlpEncoder | None, embedding_centres: np.ndarray,
                 descriptor_centroids: np.ndarray, binary: bool, descriptor_dim: int) -> None:
    """DataError unless the parts of an autoencoder vocabulary fit each other."""
    k = embedding_centres.shape[0] if embedding_centres.ndim == 2 else -1
    embedding_dim = embedding_centres.shape[1] if k >= 1 else -1
    if k < 1:
        raise DataError(f"embedding centres must be (K, E) with K >= 1, got {embedding_centres.shape}")
    if descriptor_centroids.shape != (k, descriptor_dim):
        raise DataError(f"descriptor centroids must be ({k}, {descriptor_dim}), got {descriptor_centroids.shape}")
    if pca.input_dim != (descriptor_dim * 8 if binary else descriptor_dim):
        raise DataError(f"PCA maps {pca.input_dim} -> {pca.dim} but descriptors have {descriptor_dim} "
                        f"{'bytes' if binary else 'dims'}")
    for name, dims in (("network", network and (network.input_dim, network.embedding_dim)),
                       ("MLP encoder", encoder and (encoder.input_dim, encoder.embedding_dim))):
        if dims and dims != (pca.dim, embedding_dim):
            raise DataError(f"the {name} maps {dims[0]} -> {dims[1]} but the PCA gives {pca.dim} and the "
                            f"embedding centres have {embedding_dim} dims")
    for name, array in (("embedding centres", embedding_centres), ("centroids", descriptor_centroids)):
        if not np.all(np.isfinite(array)):
            raise DataError(f"autoencoder {name} contain NaN or infinity")


def _with_one(z: np.ndarray) -> np.ndarray:
    return np.concatenate([z, np.ones((z.shape[0], 1), np.float32)], axis=1)


def student_t(z: np.ndarray, centres: np.ndarray, alpha: float = 1.0) -> np.ndarray:
    """DEC's soft assignment q_ij: (1 + |z_i - mu_j|^2 / alpha)^(-(alpha+1)/2), row-normalised; float32."""
    squared = np.einsum("ne,ne->n", z, z)[:, None] + np.einsum("ke,ke->k", centres, centres)[None, :] \
        - 2.0 * (z @ centres.T)
    q = (1.0 + np.maximum(squared, 0.0) / alpha) ** (-(alpha + 1.0) / 2.0)
    result: np.ndarray = (q / q.sum(axis=1, keepdims=True)).astype(np.float32)
    return result


def load_quantizer(stored: StoredVocabulary) -> AutoencoderQuantizer:
    """The kind's loader for the model directory: vocabulary.npz, ``PCA_FILE``, and ``ENCODER_FILE`` (or
    ``STUDENT_FILE``), the network (``NETWORK_FILE``, or ``AUTOENCODER`` in folders not yet converted) or both."""
    pca = PCA.from_arrays(read_npz(stored.file(PCA_FILE)))
    stored_pca = stored.metadata.get("pca") or {}
    if stored_pca.get("dim") != pca.dim:
        raise ModelError(f"dimension mismatch: metadata says PCA dim {stored_pca.get('dim')}, {PCA_FILE} has {pca.dim}")
    arrays = stored.arrays
    listed = stored.metadata["files"]
    network = _load_network(stored, listed)
    encoder_file = next((name for name in (ENCODER_FILE, STUDENT_FILE) if name in listed), None)
    encoder = _load_encoder(stored.file(encoder_file)) if encoder_file else None
    if network is None and encoder is None:
        raise ModelError(f"autoencoder vocabulary without an encoder: the model lists none of {NETWORK_FILE}, "
                         f"{AUTOENCODER}, {ENCODER_FILE}, {STUDENT_FILE}")
    return AutoencoderQuantizer(
        pca, network, arrays["embedding_centres"], arrays["centroids"], bool(arrays["binary"]),
        int(arrays["descriptor_dim"]), float(arrays["alpha"]), encoder,
    )


def _load_network(stored: StoredVocabulary, listed: dict[str, str]) -> ConvEncoder | None:
    """The convolutional network of the model, if it has one: its arrays, or its torch weights converted."""
    if NETWORK_FILE in listed:
        path = stored.file(NETWORK_FILE)
        arrays = read_npz(path)
    elif AUTOENCODER in listed:
        from aefabmap_ros.vocabulary.legacy_weights import CONVERT_COMMAND, read_torch_weights  # torch

        path = stored.file(AUTOENCODER)
        arrays = read_torch_weights(path)
        warnings.warn(f"{path}: the network's weights are in torch's format, converted on load; convert the "
                      f"folder once ({CONVERT_COMMAND} {path.parent}) to load it without torch", stacklevel=2)
    else:
        return None
    for name, array in arrays.items():
        if np.issubdtype(array.dtype, np.floating) and not np.all(np.isfinite(array)):
            raise ModelError(f"autoencoder weights {path}: {name} contains NaN or infinity")
    try:
        return ConvEncoder.from_arrays(arrays)
    except DataError as error:
        raise ModelError(f"dimension mismatch: autoencoder weights {path} do not fit the network "
                         f"(pca/embedding dims): {error}") from error


def _load_encoder(path: Path) -> MlpEncoder:
    try:
        return MlpEncoder.from_arrays(read_npz(path))
    except DataError as error:
        raise ModelError(f"MLP encoder {path}: {error}") from error


__all__ = ["AUTOENCODER", "ENCODER_FILE", "NETWORK_FILE", "PCA_FILE", "QUANTIZE_BATCH", "STUDENT_FILE",
           "AutoencoderQuantizer", "load_quantizer", "student_t"]
