"""The autoencoder quantizer (DESIGN 4.3): self-supervised vector quantization.

Descriptors -> linear projection -> [0, 1] (``pca.py``: the principal axes, or with ``ae_input: matches``
the axes that keep one scene point's descriptors together across frames) -> encoder -> embedding -> K
centres in embedding space. The word is the argmax of the Student-t soft assignment, i.e. the nearest
centre (the kernel is monotone in distance).

Two autoencoders (``ae_network``):
- ``MlpAutoencoder`` (the default): P -> H (ReLU) -> E and back. Its encoder quantizes as it was trained,
  in numpy (``mlp_encoder.MlpEncoder``), so training needs no second step and quantizing no torch.
- ``ConvAutoencoder``, the paper's 1-D convolutional network (the reference setting). Counted in
  multiply-adds per descriptor (P = E = 64, K = 1000, SIFT D = 128) it alone costs about 5x k-means'
  search on raw SIFT (K * D = 128k), so by default (``ae_student_hidden`` > 0) an MLP encoder distilled
  from it quantizes (``distilled.py``); without one the network quantizes.
Training is ``autoencoder_training.py``, the settings ``config.AutoencoderOptions``; measured retrieval and
timing figures, with the commands that made them, are in docs/vocabulary.md.
"""

from __future__ import annotations

import functools
import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.features.descriptors import kind_of_vocabulary
from aefabmap_ros.io.npz_files import npz_bytes, read_npz
from aefabmap_ros.vocabulary.kmeans import check_descriptors
from aefabmap_ros.vocabulary.mlp_encoder import CentreSearch, MlpEncoder, mlp_network
from aefabmap_ros.vocabulary.pca import PCA

if TYPE_CHECKING:
    from aefabmap_ros.vocabulary.base import StoredVocabulary, VocabularyConfig

# The model directory's files of an autoencoder vocabulary, beside vocabulary.npz:
PCA_FILE = "pca.npz"  # PCA + [0, 1] scaling
AUTOENCODER = "autoencoder.pt"  # the convolutional network's state_dict, when it is the autoencoder
ENCODER_FILE = "encoder.npz"  # the MLP encoder that quantizes (``mlp_encoder.py``), when there is one
STUDENT_FILE = "student.npz"  # the same arrays under the name model folders of earlier versions give them
QUANTIZE_BATCH = 8192
# Batches are padded to a multiple of this many rows. oneDNN (torch's CPU convolutions) caches a
# compiled primitive per input shape, and images give a different number of features each: unpadded, a
# node's memory grows with every new count (docs/vocabulary.md); padded, at most
# QUANTIZE_BATCH / QUANTIZE_ROWS_STEP shapes ever occur.
QUANTIZE_ROWS_STEP = 256


class Autoencoder(nn.Module):
    """An autoencoder of P-long vectors in [0, 1]: ``encode`` to E dims, ``decode_logits`` back, trained with
    binary cross-entropy on the logits (paper eq. 1)."""

    input_dim: int
    embedding_dim: int
    encoder: nn.Module
    decoder: nn.Module

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, P) in [0, 1] -> (B, E) embeddings."""
        result: torch.Tensor = self.encoder(x)
        return result

    def decode_logits(self, z: torch.Tensor) -> torch.Tensor:
        """(B, E) -> (B, P) reconstruction logits."""
        result: torch.Tensor = self.decoder(z)
        return result

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = self.encode(x)
        return z, self.decode_logits(z)


def _check_dims(input_dim: int, embedding_dim: int) -> None:
    if embedding_dim < 1:
        raise ConfigError(f"ae_embedding_dim={embedding_dim} must be >= 1")
    if input_dim < 1:
        raise ConfigError(f"pca_dim={input_dim} must be >= 1")


class MlpAutoencoder(Autoencoder):
    """P -> H (ReLU) -> E, decoder E -> H (ReLU) -> P logits. The encoder is ``mlp_network``, so that
    ``MlpEncoder.from_torch(model.encoder)`` quantizes with exactly the trained function."""

    def __init__(self, input_dim: int, hidden_dim: int, embedding_dim: int) -> None:
        super().__init__()
        _check_dims(input_dim, embedding_dim)
        if hidden_dim < 1:
            raise ConfigError(f"ae_mlp_hidden={hidden_dim} must be >= 1")
        self.input_dim = input_dim
        self.embedding_dim = embedding_dim
        self.encoder: nn.Sequential = mlp_network(input_dim, hidden_dim, embedding_dim)
        self.decoder = mlp_network(embedding_dim, hidden_dim, input_dim)

    def numpy_encoder(self) -> MlpEncoder:
        return MlpEncoder.from_torch(self.encoder)


class ConvAutoencoder(Autoencoder):
    """1-D conv autoencoder over a P-long PCA vector seen as a 1-channel signal (P divisible by 4).

    Encoder: conv 32x3 + max-pool /2, conv 64x3 stride 2, conv 128x3, dense -> embedding.
    Decoder (mirror): dense -> 128 x P/4, conv 128x3 + up-sample x2, conv 64x3 + up-sample x2,
    conv 1x3 -> logits (sigmoid = reconstruction in [0, 1]).
    """

    def __init__(self, input_dim: int, embedding_dim: int) -> None:
        super().__init__()
        _check_dims(input_dim, embedding_dim)
        if input_dim < 4 or input_dim % 4:
            raise ConfigError(f"pca_dim={input_dim} must be a multiple of 4 (two /2 poolings) and >= 4")
        self.input_dim = input_dim
        self.embedding_dim = embedding_dim
        reduced = input_dim // 4
        # Down-sampling after the second conv is its stride (half the cost of conv + pool).
        self.encoder = nn.Sequential(
            nn.Conv1d(1, 32, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool1d(2),
            nn.Conv1d(32, 64, 3, padding=1, stride=2), nn.ReLU(inplace=True),
            nn.Conv1d(64, 128, 3, padding=1), nn.ReLU(inplace=True),
            nn.Flatten(), nn.Linear(128 * reduced, embedding_dim),
        )
        self.decoder = nn.Sequential(
            nn.Linear(embedding_dim, 128 * reduced), nn.ReLU(inplace=True), nn.Unflatten(1, (128, reduced)),
            nn.Conv1d(128, 128, 3, padding=1), nn.ReLU(inplace=True), nn.Upsample(scale_factor=2),
            nn.Conv1d(128, 64, 3, padding=1), nn.ReLU(inplace=True), nn.Upsample(scale_factor=2),
            nn.Conv1d(64, 1, 3, padding=1),
        )

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, P) in [0, 1] -> (B, E) embeddings (the vector as a 1-channel signal)."""
        result: torch.Tensor = self.encoder(x.unsqueeze(1))
        return result

    def decode_logits(self, z: torch.Tensor) -> torch.Tensor:
        result: torch.Tensor = self.decoder(z).squeeze(1)
        return result


def student_t(z: torch.Tensor, centres: torch.Tensor, alpha: float = 1.0) -> torch.Tensor:
    """Soft assignment q_ij of DEC: Student-t kernel (1 + |z_i - mu_j|^2 / alpha)^(-(alpha+1)/2), row-normalised."""
    sq = torch.cdist(z, centres).pow(2)
    q = (1.0 + sq / alpha).pow(-(alpha + 1.0) / 2.0)
    return q / q.sum(dim=1, keepdim=True)


def target_distribution(q: torch.Tensor) -> torch.Tensor:
    """DEC's sharpened target p_ij = (q_ij^2 / f_j) / sum_j'(...), f_j = sum_i q_ij."""
    weight = q.pow(2) / q.sum(dim=0)
    return weight / weight.sum(dim=1, keepdim=True)


class AutoencoderQuantizer:
    """PCA + encoder + embedding centres; ``quantize`` is one batched forward pass.

    The encoder is the MLP ``encoder`` when there is one (numpy, no torch): the MLP autoencoder's own
    encoder, or a student distilled from the convolutional ``network``. Without one, the ``network``
    quantizes. ``quantize``, ``embed`` and ``soft_assign`` all use that same encoder.
    """

    kind = "autoencoder"

    def __init__(
        self,
        pca: PCA,
        network: ConvAutoencoder | None,
        embedding_centres: np.ndarray,  # (K, E) float32
        descriptor_centroids: np.ndarray,  # (K, D) float32 (packed majority bits for binary)
        binary: bool,
        descriptor_dim: int,
        alpha: float = 1.0,
        encoder: MlpEncoder | None = None,
    ) -> None:
        if network is None and encoder is None:
            raise DataError("an autoencoder vocabulary needs an encoder: the MLP encoder, the network or both")
        k = embedding_centres.shape[0] if embedding_centres.ndim == 2 else -1
        embedding_dim = embedding_centres.shape[1] if k >= 1 else -1
        if k < 1:
            raise DataError(f"embedding centres must be (K, E) with K >= 1, got {embedding_centres.shape}")
        if descriptor_centroids.shape != (k, descriptor_dim):
            raise DataError(
                f"descriptor centroids must be ({k}, {descriptor_dim}), got {descriptor_centroids.shape}"
            )
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
        self.pca = pca
        self.network = network.eval() if network is not None else None
        self.encoder = encoder
        self.embedding_centres = np.ascontiguousarray(embedding_centres, np.float32)
        self._centres_t = torch.from_numpy(self.embedding_centres)
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
        """The MLP encoder's nearest-centre matmul, built on its first use (the network path has its own)."""
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
        return self._encode(self.pca.transform_scaled(kind_of_vocabulary(self.binary).vectors(descriptors)))

    def _encode(self, x: np.ndarray) -> np.ndarray:
        if self.encoder is not None:
            return self.encoder.embed(x)
        assert self.network is not None  # one of the two, checked on construction
        return embed_rows(self.network, x)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) raw descriptors -> (N,) int64 word ids (argmax of the Student-t assignment)."""
        check_descriptors(descriptors, self.descriptor_dim, self.binary)
        if descriptors.shape[0] == 0:
            return np.zeros(0, np.int64)
        x = self.pca.transform_scaled(kind_of_vocabulary(self.binary).vectors(descriptors))
        if self.encoder is not None:
            return self._centre_search.nearest(self.encoder.embed_with_one(x))
        assert self.network is not None
        out = np.empty(x.shape[0], np.int64)
        centres_sq = (self._centres_t * self._centres_t).sum(dim=1)
        with torch.inference_mode():
            for start in range(0, x.shape[0], QUANTIZE_BATCH):
                batch = x[start:start + QUANTIZE_BATCH]
                rows = batch.shape[0]
                z = self.network.encode(torch.from_numpy(_pad_rows(batch, QUANTIZE_ROWS_STEP)))[:rows]
                # argmax of the Student-t kernel = argmin squared distance; |z|^2 is constant per row.
                scores = z @ self._centres_t.T * -2.0 + centres_sq
                out[start:start + rows] = scores.argmin(dim=1).numpy()
        return out

    def soft_assign(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, K) float32 Student-t soft assignments (rows sum to 1) of ``embed``'s embeddings."""
        z = torch.from_numpy(self.embed(descriptors))
        with torch.inference_mode():
            return student_t(z, self._centres_t, self.alpha).numpy()

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
        if self.network is not None:
            for name, tensor in sorted(self.network.state_dict().items()):
                arrays["ae." + name] = tensor.detach().cpu().numpy()
        if self.encoder is not None:  # it decides the words: a vocabulary with another encoder is another one
            # (keyed "student." whichever way the encoder was trained: the key is part of saved models' ids)
            arrays.update({"student." + name: array for name, array in self.encoder.to_arrays().items()})
        return arrays

    def other_files(self) -> dict[str, bytes]:
        files = {PCA_FILE: npz_bytes(self.pca.to_arrays())}
        if self.network is not None:
            weights = io.BytesIO()
            torch.save(self.network.state_dict(), weights)
            files[AUTOENCODER] = weights.getvalue()
        if self.encoder is not None:
            files[ENCODER_FILE] = npz_bytes(self.encoder.to_arrays())
        return files

    def metadata(self) -> dict[str, Any]:
        return {"pca": {"input_dim": self.pca.input_dim, "dim": self.pca.dim}, "embedding_dim": self.embedding_dim}


def _pad_rows(x: np.ndarray, step: int) -> np.ndarray:
    """``x`` (N, D) with zero rows appended up to a multiple of ``step`` (rows are encoded independently)."""
    missing = -x.shape[0] % step
    if missing == 0:
        return np.ascontiguousarray(x)
    return np.concatenate([x, np.zeros((missing, x.shape[1]), x.dtype)])


def embed_rows(model: Autoencoder, x: np.ndarray) -> np.ndarray:
    out = np.empty((x.shape[0], model.embedding_dim), np.float32)
    with torch.inference_mode():
        for start in range(0, x.shape[0], QUANTIZE_BATCH):
            out[start:start + QUANTIZE_BATCH] = model.encode(torch.from_numpy(x[start:start + QUANTIZE_BATCH])).numpy()
    return out


def limit_torch_threads(num_threads: int) -> None:
    """Cap torch's CPU thread pool for this process (a node sharing the cores with other nodes)."""
    if num_threads < 1:
        raise ConfigError(f"torch threads must be >= 1, got {num_threads}")
    torch.set_num_threads(num_threads)


def train_quantizer(descriptors: np.ndarray, config: VocabularyConfig, *, pairs: np.ndarray | None = None,
                    progress: bool = True, work_dir: Path | None = None) -> AutoencoderQuantizer:
    """The kind's trainer for ``train_vocabulary`` (registered in ``kinds.py``)."""
    from aefabmap_ros.vocabulary.autoencoder_training import train_autoencoder_quantizer  # imports this module

    return train_autoencoder_quantizer(descriptors, config, pairs=pairs, progress=progress, work_dir=work_dir)


def load_quantizer(stored: StoredVocabulary) -> AutoencoderQuantizer:
    """The kind's loader for the model directory: vocabulary.npz, ``PCA_FILE``, and ``ENCODER_FILE`` (or
    ``STUDENT_FILE``), ``AUTOENCODER`` or both."""
    pca = PCA.from_arrays(read_npz(stored.file(PCA_FILE)))
    stored_pca = stored.metadata.get("pca") or {}
    if stored_pca.get("dim") != pca.dim:
        raise ModelError(f"dimension mismatch: metadata says PCA dim {stored_pca.get('dim')}, {PCA_FILE} has {pca.dim}")
    arrays = stored.arrays
    listed = stored.metadata["files"]
    network = None
    if AUTOENCODER in listed:
        network = ConvAutoencoder(pca.dim, int(arrays["embedding_dim"]))
        _load_weights(stored.file(AUTOENCODER), network)
    encoder_file = next((name for name in (ENCODER_FILE, STUDENT_FILE) if name in listed), None)
    encoder = _load_encoder(stored.file(encoder_file)) if encoder_file else None
    if network is None and encoder is None:
        raise ModelError(f"autoencoder vocabulary without an encoder: the model lists none of {AUTOENCODER}, "
                         f"{ENCODER_FILE}, {STUDENT_FILE}")
    return AutoencoderQuantizer(
        pca, network, arrays["embedding_centres"], arrays["centroids"], bool(arrays["binary"]),
        int(arrays["descriptor_dim"]), float(arrays["alpha"]), encoder,
    )


def _load_encoder(path: Path) -> MlpEncoder:
    try:
        return MlpEncoder.from_arrays(read_npz(path))
    except DataError as error:
        raise ModelError(f"MLP encoder {path}: {error}") from error


def _load_weights(path: Path, network: ConvAutoencoder) -> None:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a corrupt file
        raise ModelError(f"cannot load autoencoder weights {path}: corrupt file ({error})") from error
    if not isinstance(state, dict):
        raise ModelError(f"{path} does not hold a state_dict")
    try:
        network.load_state_dict(state)
    except RuntimeError as error:
        first = str(error).strip().splitlines()
        raise ModelError(f"dimension mismatch: autoencoder weights {path} do not fit the network "
                         f"(pca/embedding dims): {' '.join(first[:3])}") from error
    for name, tensor in state.items():
        if not torch.isfinite(tensor).all():
            raise ModelError(f"autoencoder weights {path}: {name} contains NaN or infinity")
    network.eval()
