"""The paper's autoencoder quantizer (DESIGN 4.3): self-supervised vector quantization.

Pipeline: descriptors -> PCA -> [0, 1] (``pca.py``) -> 1-D convolutional autoencoder ->
embedding -> K centres in embedding space -> word = argmax of the Student-t soft
assignment (= the nearest centre, the kernel being monotone in distance).

Training (``train_autoencoder_quantizer``):
1. Pre-train the autoencoder with binary cross-entropy (paper eq. 1) on at most
   ``ae_max_train_descriptors`` PCA vectors (a random subsample: the conv net costs far
   more per descriptor than k-means, and a 100k sample already covers the space).
   Optional self-supervised match term (``ae_match_weight`` > 0, needs ``pairs``): the
   same scene point seen in neighbouring frames (SIFT matches) should embed close
   together. InfoNCE with squared Euclidean logits, so that it shapes the same geometry
   k-means and the Student-t kernel use: for a batch of matched pairs (a_i, b_i),
   ``-log softmax_j(-|z(a_i) - z(b_j)|^2 / T)[i]``, symmetric.
2. k-means (k-means++ seeded) on the embeddings of all training descriptors gives K
   centres; empty words are re-seeded.
3. Optional DEC/IDEC refinement (``refine``): reconstruction + gamma * KL(P || Q) against
   the sharpened target P = q^2 / f, normalised; P is recomputed every
   ``refine_update_interval`` batches; training stops when fewer than ``refine_tol`` of the
   labels change between two targets. Empty words are re-seeded at every target update.
   Off by default: measured downstream (below) it lowers retrieval precision (AP 0.561
   against 0.902 without, seed 0; the prototype saw 0.26-0.63 and no settling at lr 1e-3);
   kept, with a lower learning rate and the empty-word guard, as the option the paper
   describes.
4. Distillation (``ae_student_hidden`` > 0, the default; ``distilled.py``): a one-hidden-layer MLP,
   PCA vector -> H (ReLU) -> embedding, is fitted to the network's embeddings (mean squared error,
   plus ``ae_student_word_weight`` times the KL between the network's and the student's soft
   assignments to the fixed centres at ``ae_student_word_temperature``) of all training descriptors
   but a held-out 5 % (at most 20,000), on which ``training_info`` records
   ``student_word_agreement``: how many get the network's word from the student.
5. Descriptor-space centroids = mean of each word's training descriptors (paper eq. 3), words as the
   vocabulary's encoder (the student, if any) gives them.

Inference: the distilled encoder by default (issue 14; ``ae_student_hidden: 0``: the paper's network, the
reference setting). Counted in multiply-adds per
descriptor (P = E = 64, K = 1000, SIFT D = 128), the paper's encoder is about 5x k-means' search on
raw SIFT (K * D = 128k) before its own centre search, so no leaner forward pass of it (fusion,
export, lower precision) can quantize as cheaply as k-means. The student costs P * H + H * E + K * E
= 97k at H = 256 (+ 8k for the PCA), in plain numpy float32: two matmuls and the centre search as one
matmul with the centres' squared norms computed once; no torch at inference. Its words are the
network's words for most descriptors, not all: on kitti00_first300 (300k SIFT, 1000 words; a
network trained with the demo's settings, 20k held-out descriptors; targets not yet normalised)
H = 128 and 10 epochs agreed on 91.6 %, 30 epochs 92.7 %, H = 256 92.2 %; trained on the words instead (cross-entropy on
-|z - c|^2 logits against the fixed centres, T = 1 / 0.1) 81.7 / 80.7 %, both losses together
83.1 %. Agreement saturates near 92-95 %: the rest lie near a boundary between two words. With targets
and centres normalised, a soft word term (KL to the network's assignment at temperature T, weight w,
beside the MSE) helps a little where the hard one hurts (seed 0, H = 128, 10 epochs: MSE 92.8 %;
cross-entropy on the hard word, w = 1, T = 1: 90.5 %; KL w = 1 at T = 1 / 4 / 8 / 16: 91.0 / 93.3 /
93.5 / 93.1 %; w = 0.3 / 3 / 10: 93.1 / 92.9 / 92.6 %), hence T = 8 when the term is used;
H = 256 and 30 epochs: 94.8 / 95.0 / 95.0 % (seeds 0-2) against the MSE's 94.5 % (seed 0), but the
distillation is 2-3x slower and closes no more loops than that MSE student, so the term is off by
default (w = 0). Noisy copies of the training rows labelled by the network (``ae_student_noise_rows``,
300k by default) teach the student the network around the training descriptors, where another
environment's descriptors fall. Hence the defaults: H = 256, 30 epochs, MSE, 300k noisy rows (about
2.5 minutes of distillation on two cores for kitti00's 300 images).

Measured (README "Accuracy offline" and "Speed"): 1,000 kitti SIFT quantized in 0.88x k-means' time (the
network: 7.1x); quantizer_node 4.5 ms CPU per image against 48-51 ms. Retrieval, kitti-trained with
three seeds each, against the paper's network with its three seeds: AE-FABMAP, every verified row and the
online chain within the networks' spread; AE-BoW without verification is lower, and so is the network's
when trained the same way (SIFT's octave rule, ``features/extraction.py``): the student follows its own
network. A model directory without ``student.npz`` quantizes with the network.

Defaults, as measured downstream (SIFT, vocabulary of 1000 words trained on
kitti00_first300, tf-idf cosine retrieval on rtabmap_samples, best earlier frame at
least 10 frames back; average precision / recall at 100 % precision, seeds 0-2):
k-means on raw SIFT 0.889 / 0.712; autoencoder with a 64-d embedding 0.895 / 0.727;
32-d embedding (seed 0 only) 0.856 / 0.523 against k-means' 0.885 / 0.705 on that seed.
IDEC refinement on top of the 64-d default (seed 0): 0.561 / 0.091. The match term at
weight 1.0 (seed 0) fell to 0.337 / 0.068: instance discrimination of
KITTI points spreads the embedding uniformly and the words stop generalising. Hence:
64-d embedding, no refinement, match term off by default.

Determinism: given ``seed`` (torch.manual_seed, numpy Generators derived from the seed
and epoch, deterministic torch algorithms during training) the same data gives the same
vocabulary on the same machine and thread count. Training can be interrupted and resumed:
with a ``work_dir`` a checkpoint (stage, epoch, model / optimizer / centre state, RNG state,
a fingerprint of config and data) is written atomically after every epoch and picked up
by the next call with the same config and data.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.features.descriptors import kind_of, kind_of_vocabulary
from aefabmap_ros.io.atomic import atomic_write_bytes
from aefabmap_ros.io.npz_files import npz_bytes, read_npz
from aefabmap_ros.vocabulary.distilled import CentreSearch, DistillOptions, StudentEncoder, distill_student
from aefabmap_ros.vocabulary.kmeans import (
    check_descriptors,
    cluster_means,
    kmeans,
    nearest,
    reseed_empty,
)
from aefabmap_ros.vocabulary.pca import PCA, fit_pca

if TYPE_CHECKING:
    from aefabmap_ros.vocabulary.base import StoredVocabulary, VocabularyConfig

CHECKPOINT_NAME = "ae_checkpoint.pt"
# The model directory's files of an autoencoder vocabulary, beside vocabulary.npz:
PCA_FILE = "pca.npz"  # PCA + [0, 1] scaling
AUTOENCODER = "autoencoder.pt"  # the network's state_dict
STUDENT_FILE = "student.npz"  # the distilled encoder (``distilled.py``), when there is one
QUANTIZE_BATCH = 8192
# Batches are padded to a multiple of this many rows. oneDNN (torch's CPU convolutions) caches a
# compiled primitive per input shape: images give a different number of features each, and a node
# quantizing them unpadded grew from 0.35 to 1.4 GiB over 600 images (measured, random sizes 50-2,000);
# padded, it stayed at 0.4 GiB. At most QUANTIZE_BATCH / QUANTIZE_ROWS_STEP shapes ever occur.
QUANTIZE_ROWS_STEP = 256


class ConvAutoencoder(nn.Module):
    """1-D conv autoencoder over a P-long PCA vector seen as a 1-channel signal (P divisible by 4).

    Encoder: conv 32x3 + max-pool /2, conv 64x3 stride 2, conv 128x3, dense -> embedding.
    Decoder (mirror): dense -> 128 x P/4, conv 128x3 + up-sample x2, conv 64x3 + up-sample x2,
    conv 1x3 -> logits (sigmoid = reconstruction in [0, 1]).
    """

    def __init__(self, input_dim: int, embedding_dim: int) -> None:
        super().__init__()
        if input_dim < 4 or input_dim % 4:
            raise ConfigError(f"pca_dim={input_dim} must be a multiple of 4 (two /2 poolings) and >= 4")
        if embedding_dim < 1:
            raise ConfigError(f"ae_embedding_dim={embedding_dim} must be >= 1")
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
        """(B, P) in [0, 1] -> (B, E) embeddings."""
        result: torch.Tensor = self.encoder(x.unsqueeze(1))
        return result

    def decode_logits(self, z: torch.Tensor) -> torch.Tensor:
        """(B, E) -> (B, P) reconstruction logits."""
        result: torch.Tensor = self.decoder(z).squeeze(1)
        return result

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = self.encode(x)
        return z, self.decode_logits(z)


def student_t(z: torch.Tensor, centres: torch.Tensor, alpha: float = 1.0) -> torch.Tensor:
    """Soft assignment q_ij of DEC: Student-t kernel (1 + |z_i - mu_j|^2 / alpha)^(-(alpha+1)/2), row-normalised."""
    sq = torch.cdist(z, centres).pow(2)
    q = (1.0 + sq / alpha).pow(-(alpha + 1.0) / 2.0)
    return q / q.sum(dim=1, keepdim=True)


def target_distribution(q: torch.Tensor) -> torch.Tensor:
    """DEC's sharpened target p_ij = (q_ij^2 / f_j) / sum_j'(...), f_j = sum_i q_ij."""
    weight = q.pow(2) / q.sum(dim=0)
    return weight / weight.sum(dim=1, keepdim=True)


@dataclass(frozen=True)
class AETrainingOptions:
    """The autoencoder-specific part of VocabularyConfig (kept flat there; gathered here)."""

    size: int
    pca_dim: int
    pca_per_component: bool
    seed: int
    num_threads: int
    embedding_dim: int
    epochs: int
    batch_size: int
    learning_rate: float
    max_train_descriptors: int
    match_weight: float
    match_temperature: float
    kmeans_iterations: int
    refine: bool
    refine_epochs: int
    refine_learning_rate: float
    refine_update_interval: int
    gamma: float
    tol: float
    alpha: float
    student_hidden: int = 0
    student_epochs: int = 0
    student_learning_rate: float = 1e-3
    student_word_weight: float = 0.0
    student_word_temperature: float = 1.0
    student_noise_rows: int = 0
    student_noise_scale: float = 0.5


class AutoencoderQuantizer:
    """PCA + encoder + embedding centres; ``quantize`` is one batched forward pass.

    The encoder is the distilled ``student`` when there is one (numpy, no torch), else the paper's
    network ``model``. ``quantize``, ``embed`` and ``soft_assign`` all use that same encoder.
    """

    kind = "autoencoder"

    def __init__(
        self,
        pca: PCA,
        model: ConvAutoencoder,
        embedding_centres: np.ndarray,  # (K, E) float32
        descriptor_centroids: np.ndarray,  # (K, D) float32 (packed majority bits for binary)
        binary: bool,
        descriptor_dim: int,
        alpha: float = 1.0,
        student: StudentEncoder | None = None,
    ) -> None:
        k = embedding_centres.shape[0] if embedding_centres.ndim == 2 else -1
        if embedding_centres.ndim != 2 or embedding_centres.shape[1] != model.embedding_dim or k < 1:
            raise DataError(
                f"embedding centres must be (K, {model.embedding_dim}), got {embedding_centres.shape}"
            )
        if descriptor_centroids.shape != (k, descriptor_dim):
            raise DataError(
                f"descriptor centroids must be ({k}, {descriptor_dim}), got {descriptor_centroids.shape}"
            )
        if pca.dim != model.input_dim or pca.input_dim != (descriptor_dim * 8 if binary else descriptor_dim):
            raise DataError(
                f"PCA maps {pca.input_dim} -> {pca.dim} but the autoencoder takes {model.input_dim} and "
                f"descriptors have {descriptor_dim} {'bytes' if binary else 'dims'}"
            )
        if student is not None and (student.input_dim, student.embedding_dim) != (pca.dim, model.embedding_dim):
            raise DataError(
                f"the student encoder maps {student.input_dim} -> {student.embedding_dim} but the PCA gives "
                f"{pca.dim} and the embedding has {model.embedding_dim} dims"
            )
        for name, array in (("embedding centres", embedding_centres), ("centroids", descriptor_centroids)):
            if not np.all(np.isfinite(array)):
                raise DataError(f"autoencoder {name} contain NaN or infinity")
        self.pca = pca
        self.model = model.eval()
        self.student = student
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
        """The student path's nearest-centre matmul, built on its first use (the network path has its own)."""
        return CentreSearch(self.embedding_centres)

    def with_student(self, student: StudentEncoder | None) -> AutoencoderQuantizer:
        """The same vocabulary quantized by ``student`` (None: by the paper's network)."""
        return AutoencoderQuantizer(self.pca, self.model, self.embedding_centres, self._centroids, self.binary,
                                    self.descriptor_dim, self.alpha, student)

    def embed(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) raw descriptors -> (N, E) float32 embeddings, by the encoder ``quantize`` uses."""
        check_descriptors(descriptors, self.descriptor_dim, self.binary)
        return self._encode(self.pca.transform_scaled(kind_of_vocabulary(self.binary).vectors(descriptors)))

    def _encode(self, x: np.ndarray) -> np.ndarray:
        if self.student is not None:
            return self.student.embed(x)
        return _embed(self.model, x)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) raw descriptors -> (N,) int64 word ids (argmax of the Student-t assignment)."""
        check_descriptors(descriptors, self.descriptor_dim, self.binary)
        if descriptors.shape[0] == 0:
            return np.zeros(0, np.int64)
        x = self.pca.transform_scaled(kind_of_vocabulary(self.binary).vectors(descriptors))
        if self.student is not None:
            return self._centre_search.nearest(self.student.embed_with_one(x))
        out = np.empty(x.shape[0], np.int64)
        centres_sq = (self._centres_t * self._centres_t).sum(dim=1)
        with torch.inference_mode():
            for start in range(0, x.shape[0], QUANTIZE_BATCH):
                batch = x[start:start + QUANTIZE_BATCH]
                rows = batch.shape[0]
                z = self.model.encode(torch.from_numpy(_pad_rows(batch, QUANTIZE_ROWS_STEP)))[:rows]
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
            "embedding_dim": np.array(self.model.embedding_dim),
            "alpha": np.array(self.alpha),
        }

    def identity_arrays(self) -> dict[str, np.ndarray]:
        arrays = {"pca." + name: array for name, array in sorted(self.pca.to_arrays().items())}
        for name, tensor in sorted(self.model.state_dict().items()):
            arrays["ae." + name] = tensor.detach().cpu().numpy()
        if self.student is not None:  # it decides the words: a vocabulary with another student is another one
            arrays.update({"student." + name: array for name, array in self.student.to_arrays().items()})
        return arrays

    def other_files(self) -> dict[str, bytes]:
        weights = io.BytesIO()
        torch.save(self.model.state_dict(), weights)
        files = {PCA_FILE: npz_bytes(self.pca.to_arrays()), AUTOENCODER: weights.getvalue()}
        if self.student is not None:
            files[STUDENT_FILE] = npz_bytes(self.student.to_arrays())
        return files

    def metadata(self) -> dict[str, Any]:
        return {"pca": {"input_dim": self.pca.input_dim, "dim": self.pca.dim},
                "embedding_dim": self.model.embedding_dim}


def _pad_rows(x: np.ndarray, step: int) -> np.ndarray:
    """``x`` (N, D) with zero rows appended up to a multiple of ``step`` (rows are encoded independently)."""
    missing = -x.shape[0] % step
    if missing == 0:
        return np.ascontiguousarray(x)
    return np.concatenate([x, np.zeros((missing, x.shape[1]), x.dtype)])


def _embed(model: ConvAutoencoder, x: np.ndarray) -> np.ndarray:
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


@contextlib.contextmanager
def _torch_settings(num_threads: int) -> Iterator[None]:
    """Deterministic algorithms and the requested thread count, restored afterwards."""
    previous_threads = torch.get_num_threads()
    previous_deterministic = torch.are_deterministic_algorithms_enabled()
    try:
        if num_threads > 0:
            torch.set_num_threads(num_threads)
        torch.use_deterministic_algorithms(True, warn_only=True)
        yield
    finally:
        torch.set_num_threads(previous_threads)
        torch.use_deterministic_algorithms(previous_deterministic)


def train_quantizer(descriptors: np.ndarray, config: VocabularyConfig, *, pairs: np.ndarray | None = None,
                    progress: bool = True, work_dir: Path | None = None) -> AutoencoderQuantizer:
    """The kind's trainer for ``train_vocabulary`` (registered in ``kinds.py``)."""
    return train_autoencoder_quantizer(descriptors, config.ae_options(), pairs=pairs, progress=progress,
                                       work_dir=work_dir)


def load_quantizer(stored: StoredVocabulary) -> AutoencoderQuantizer:
    """The kind's loader for the model directory: vocabulary.npz, ``PCA_FILE`` and ``AUTOENCODER``."""
    pca_path, weights_path = stored.file(PCA_FILE), stored.file(AUTOENCODER)
    pca = PCA.from_arrays(read_npz(pca_path))
    stored_pca = stored.metadata.get("pca") or {}
    if stored_pca.get("dim") != pca.dim:
        raise ModelError(f"dimension mismatch: metadata says PCA dim {stored_pca.get('dim')}, {PCA_FILE} has {pca.dim}")
    arrays = stored.arrays
    network = ConvAutoencoder(pca.dim, int(arrays["embedding_dim"]))
    _load_weights(weights_path, network)
    # A model directory trained before the student (or with ae_student_hidden 0) quantizes with the network.
    student = _load_student(stored.file(STUDENT_FILE)) if STUDENT_FILE in stored.metadata["files"] else None
    return AutoencoderQuantizer(
        pca, network, arrays["embedding_centres"], arrays["centroids"], bool(arrays["binary"]),
        int(arrays["descriptor_dim"]), float(arrays["alpha"]), student,
    )


def _load_student(path: Path) -> StudentEncoder:
    try:
        return StudentEncoder.from_arrays(read_npz(path))
    except DataError as error:
        raise ModelError(f"student encoder {path}: {error}") from error


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


def train_autoencoder_quantizer(
    descriptors: np.ndarray,
    options: AETrainingOptions,
    *,
    pairs: np.ndarray | None = None,
    progress: bool = True,
    work_dir: Path | None = None,
) -> AutoencoderQuantizer:
    """Train PCA + autoencoder + centres on (N, D) descriptors (uint8 rows = binary).

    ``pairs``: optional (M, 2) int64 row indices of descriptors of the same scene point in
    neighbouring frames, used by the match term when ``options.match_weight`` > 0.
    """
    kind = kind_of(descriptors)
    n = descriptors.shape[0]
    if n < options.size:
        raise DataError(f"autoencoder vocabulary of size={options.size} needs >= {options.size} descriptors, got {n}")
    if options.match_weight > 0 and (pairs is None or len(pairs) == 0):
        raise DataError("ae_match_weight > 0 needs matched descriptor pairs (none given)")
    if pairs is not None and len(pairs) and (pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.min() < 0
                                             or pairs.max() >= n):
        raise DataError(f"pairs must be (M, 2) row indices in [0, {n}), got shape {pairs.shape}")
    rows = kind.vectors(descriptors)
    clock = _StageClock()
    with _torch_settings(options.num_threads):
        pca = fit_pca(_subsample(rows, 200_000, options.seed), options.pca_dim, options.pca_per_component)
        x_all = pca.transform_scaled(rows)
        clock.lap("pca_s")
        checkpoint = _Checkpoint(work_dir, _fingerprint(options, descriptors, pairs))
        torch.manual_seed(options.seed)
        model = ConvAutoencoder(options.pca_dim, options.embedding_dim)
        train_idx = np.sort(np.random.default_rng([options.seed, 1]).permutation(n)[
            : min(n, options.max_train_descriptors)])
        _pretrain(model, x_all, train_idx, pairs, options, checkpoint, progress)
        model.eval()
        clock.lap("pretrain_s")
        z_all = _embed(model, x_all)
        clock.lap("embed_s")
        centres = kmeans(z_all, options.size, options.seed, options.kmeans_iterations)
        clock.lap("kmeans_s")
        if options.refine:
            centres = _refine(model, centres, x_all, train_idx, options, checkpoint, progress)
            z_all = _embed(model, x_all)
            centres = reseed_empty(z_all, centres, np.random.default_rng([options.seed, 3]))
            clock.lap("refine_s")
        model.eval()
        student_info: dict[str, float] = {}
        student = None
        if options.student_hidden > 0:
            student, student_info = _distill(x_all, z_all, centres, options,
                                             teacher=functools.partial(_embed, model))
            z_all = student.embed(x_all)  # the words of the vocabulary are the ones the student gives
            clock.lap("distill_s")
        labels, _ = nearest(centres, z_all)
        fallback = _nearest_rows(rows, z_all, centres)
        means = cluster_means(rows, labels, options.size, fallback)
        centroids = kind.centres(means)
        clock.lap("centroids_s")
        checkpoint.finish()
    quantizer = AutoencoderQuantizer(pca, model, centres, centroids, kind.binary, descriptors.shape[1],
                                     options.alpha, student)
    counts = np.bincount(labels, minlength=options.size)
    quantizer.training_info = {
        **clock.seconds,
        "descriptors": float(n),
        "ae_train_descriptors": float(train_idx.size),
        "empty_words": float(np.sum(counts == 0)),
        "largest_word_fraction": float(counts.max() / max(1, n)),
        **student_info,
    }
    return quantizer


# At most this many noisy copies per training row (``ae_student_noise_rows`` caps the total): the default 300k
# is about one to one and a half per row for a few hundred camera images (kitti00: 207k-285k rows); a small
# training set is not drowned in copies of itself, nor its distillation slowed by them.
MAX_NOISE_COPIES_PER_ROW = 2
# Descriptors held out of the student's training to measure its agreement with the network.
STUDENT_HELD_OUT_FRACTION = 0.05
STUDENT_HELD_OUT_MAX = 20_000


def _distill(x_all: np.ndarray, z_all: np.ndarray, centres: np.ndarray, options: AETrainingOptions, *,
             teacher: Callable[[np.ndarray], np.ndarray]) -> tuple[StudentEncoder, dict[str, float]]:
    """Distil the student from the network's embeddings ``z_all`` (plus ``options.student_noise_rows``
    noisy copies of the fit rows, at most ``MAX_NOISE_COPIES_PER_ROW`` per row, embedded by ``teacher``);
    its word agreement on held-out rows."""
    n = x_all.shape[0]
    held_count = min(STUDENT_HELD_OUT_MAX, max(1, int(n * STUDENT_HELD_OUT_FRACTION))) if n > 1 else 0
    order = np.random.default_rng([options.seed, 6]).permutation(n)
    held, fit = np.sort(order[:held_count]), np.sort(order[held_count:])
    x_fit, z_fit = x_all[fit], z_all[fit]
    noise_rows = min(options.student_noise_rows, MAX_NOISE_COPIES_PER_ROW * x_fit.shape[0])
    if noise_rows > 0:
        noisy = noisy_copies(x_fit, noise_rows, options.student_noise_scale, options.seed)
        x_fit, z_fit = np.concatenate([x_fit, noisy]), np.concatenate([z_fit, teacher(noisy)])
    student = distill_student(x_fit, z_fit, centres, DistillOptions(
        hidden_dim=options.student_hidden, epochs=options.student_epochs, batch_size=options.batch_size,
        learning_rate=options.student_learning_rate, seed=options.seed, word_weight=options.student_word_weight,
        word_temperature=options.student_word_temperature))
    info = {"student_hidden": float(options.student_hidden), "student_held_out_descriptors": float(held.size)}
    if held.size:
        teacher_words, _ = nearest(centres, z_all[held])
        student_words, _ = nearest(centres, student.embed(x_all[held]))
        info["student_word_agreement"] = float(np.mean(teacher_words == student_words))
    return student, info


def noisy_copies(x: np.ndarray, rows: int, scale: float, seed: int) -> np.ndarray:
    """``rows`` rows of ``x`` (PCA-scaled, in [0, 1]) drawn with replacement, plus Gaussian noise of
    ``scale`` times each dimension's spread, clipped back to [0, 1]. The training descriptors alone
    teach the student the network only where they lie; a robot's own descriptors fall around them,
    and there a student fitted to them alone gave other words (92 % agreement on other data against
    95 % held-out)."""
    rng = np.random.default_rng([seed, 8])
    picked = x[rng.integers(0, x.shape[0], rows)]
    noise = rng.standard_normal(picked.shape).astype(np.float32) * (np.float32(scale) * x.std(axis=0))
    result: np.ndarray = np.clip(picked + noise, 0.0, 1.0).astype(np.float32)
    return result


class _StageClock:
    """Wall-clock seconds per training stage (reported by the benchmark and kept as provenance)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = now - self._last
        self._last = now


def _nearest_rows(rows: np.ndarray, z: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """For each centre, the descriptor whose embedding is nearest (centroid of a word with no member)."""
    index_rows, _ = nearest(z, centres)
    result: np.ndarray = rows[index_rows]
    return result


def _subsample(x: np.ndarray, limit: int, seed: int) -> np.ndarray:
    if x.shape[0] <= limit:
        return x
    idx = np.sort(np.random.default_rng([seed, 0]).choice(x.shape[0], limit, replace=False))
    return x[idx]


def _pretrain(
    model: ConvAutoencoder,
    x_all: np.ndarray,
    train_idx: np.ndarray,
    pairs: np.ndarray | None,
    options: AETrainingOptions,
    checkpoint: _Checkpoint,
    progress: bool,
) -> None:
    optimizer = torch.optim.Adam(model.parameters(), lr=options.learning_rate)
    start_epoch = min(checkpoint.restore("pretrain", model, optimizer), options.epochs)
    bce = nn.BCEWithLogitsLoss()
    batch = options.batch_size
    use_pairs = options.match_weight > 0 and pairs is not None
    bar = tqdm(range(start_epoch, options.epochs), desc="autoencoder", unit="epoch", disable=not progress,
               initial=start_epoch, total=options.epochs)
    for epoch in bar:
        model.train()
        rng = np.random.default_rng([options.seed, 2, epoch])
        order = train_idx[rng.permutation(train_idx.size)]
        pair_order = rng.permutation(len(pairs)) if use_pairs and pairs is not None else None
        n_batches = max(1, order.size // batch)
        total = 0.0
        for b in range(n_batches):
            xb = torch.from_numpy(x_all[order[b * batch:(b + 1) * batch]])
            _, logits = model(xb)
            loss = bce(logits, xb)
            if pair_order is not None and pairs is not None:
                chosen = pairs[pair_order[np.arange(b * batch, (b + 1) * batch) % len(pairs)]]
                loss = loss + options.match_weight * _match_loss(model, x_all, chosen, options.match_temperature)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach())
        bar.set_postfix(loss=f"{total / n_batches:.4f}")
        checkpoint.save("pretrain", epoch, model, optimizer)


def _match_loss(model: ConvAutoencoder, x_all: np.ndarray, chosen: np.ndarray, temperature: float) -> torch.Tensor:
    """Symmetric InfoNCE with -|z_a - z_b|^2 / T logits over the batch of matched pairs."""
    za = model.encode(torch.from_numpy(x_all[chosen[:, 0]]))
    zb = model.encode(torch.from_numpy(x_all[chosen[:, 1]]))
    # Scale by the batch's mean squared distance so that T is unit-free (the embedding scale drifts).
    sq = torch.cdist(za, zb).pow(2)
    logits = -sq / (temperature * sq.detach().mean().clamp_min(1e-8))
    target = torch.arange(za.shape[0])
    ce = nn.functional.cross_entropy
    return 0.5 * (ce(logits, target) + ce(logits.T, target))


def _refine(
    model: ConvAutoencoder,
    centres_np: np.ndarray,
    x_all: np.ndarray,
    train_idx: np.ndarray,
    options: AETrainingOptions,
    checkpoint: _Checkpoint,
    progress: bool,
) -> np.ndarray:
    """IDEC: reconstruction + gamma * KL(P || Q); P recomputed every refine_update_interval batches."""
    centres = nn.Parameter(torch.from_numpy(centres_np.copy()))
    optimizer = torch.optim.Adam([*model.parameters(), centres], lr=options.refine_learning_rate)
    start_epoch = min(checkpoint.restore("refine", model, optimizer, centres), options.refine_epochs)
    x_train = x_all[train_idx]
    bce = nn.BCEWithLogitsLoss()
    rng_reseed = np.random.default_rng([options.seed, 4])
    previous: np.ndarray | None = None
    bar = tqdm(range(start_epoch, options.refine_epochs), desc="refine", unit="epoch", disable=not progress,
               initial=start_epoch, total=options.refine_epochs)
    batch = options.batch_size
    for epoch in bar:
        rng = np.random.default_rng([options.seed, 5, epoch])
        order = rng.permutation(x_train.shape[0])
        n_batches = max(1, order.size // batch)
        changed = 1.0
        target = torch.empty(0)
        for b in range(n_batches):
            if b % options.refine_update_interval == 0:
                target, labels = _full_target(model, x_train, centres, options.alpha)
                changed = 1.0 if previous is None else float(np.mean(labels != previous))
                previous = labels
                _reseed_in_place(model, x_train, centres, labels, rng_reseed)
                if changed < options.tol:
                    break
                model.train()
            idx = order[b * batch:(b + 1) * batch]
            xb = torch.from_numpy(x_train[idx])
            z, logits = model(xb)
            q = student_t(z, centres, options.alpha)
            kl = nn.functional.kl_div(q.clamp_min(1e-12).log(), target[idx], reduction="batchmean")
            loss = bce(logits, xb) + options.gamma * kl
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        bar.set_postfix(changed=f"{changed:.4f}")
        checkpoint.save("refine", epoch, model, optimizer, centres)
        if changed < options.tol:
            break
    return centres.detach().numpy().copy()


def _full_target(model: ConvAutoencoder, x: np.ndarray, centres: torch.Tensor,
                 alpha: float) -> tuple[torch.Tensor, np.ndarray]:
    model.eval()
    with torch.no_grad():
        z = torch.from_numpy(_embed(model, x))
        q = student_t(z, centres.detach(), alpha)
        return target_distribution(q), q.argmax(dim=1).numpy()


def _reseed_in_place(model: ConvAutoencoder, x: np.ndarray, centres: nn.Parameter, labels: np.ndarray,
                     rng: np.random.Generator) -> None:
    """Guard against words the KL term empties: move them onto members of the largest words."""
    counts = np.bincount(labels, minlength=centres.shape[0])
    empty = np.flatnonzero(counts == 0)
    if empty.size == 0:
        return
    crowded = np.flatnonzero(counts[labels] > 1)
    picks = rng.choice(crowded, size=min(empty.size, crowded.size), replace=False)
    z = _embed(model, x[picks])
    with torch.no_grad():
        centres[torch.from_numpy(empty[: picks.size])] = torch.from_numpy(z)


def _fingerprint(options: AETrainingOptions, descriptors: np.ndarray, pairs: np.ndarray | None) -> str:
    digest = hashlib.sha256(json.dumps(options.__dict__, sort_keys=True).encode())
    digest.update(str(descriptors.shape).encode() + str(descriptors.dtype).encode())
    step = max(1, descriptors.shape[0] // 1000)
    digest.update(np.ascontiguousarray(descriptors[::step]).tobytes())
    if pairs is not None:
        digest.update(np.ascontiguousarray(pairs).tobytes())
    return digest.hexdigest()[:16]


class _Checkpoint:
    """Per-epoch training state in ``work_dir`` (atomic writes), resumed when the fingerprint matches."""

    def __init__(self, work_dir: Path | None, fingerprint: str) -> None:
        self.path = None if work_dir is None else Path(work_dir) / CHECKPOINT_NAME
        self.fingerprint = fingerprint
        self.state: dict[str, Any] | None = None
        if self.path is not None and self.path.exists():
            try:
                state = torch.load(self.path, map_location="cpu", weights_only=False)
            except Exception as error:  # a truncated or foreign file: say so and start afresh
                raise ModelError(
                    f"cannot read training checkpoint {self.path}: {error}; delete it to restart"
                ) from error
            if isinstance(state, dict) and state.get("fingerprint") == fingerprint:
                self.state = state

    def restore(self, stage: str, model: nn.Module, optimizer: torch.optim.Optimizer,
                centres: nn.Parameter | None = None) -> int:
        """Load the checkpoint's state if it is at or past ``stage``; the first epoch still to run."""
        if self.state is None:
            return 0
        stages = ("pretrain", "refine")
        saved_stage = self.state["stage"]
        if stages.index(saved_stage) < stages.index(stage):
            return 0
        model.load_state_dict(self.state["model"])
        if saved_stage != stage:  # past this stage: its result is in the model already
            return _SKIP
        optimizer.load_state_dict(self.state["optimizer"])
        if centres is not None and self.state.get("centres") is not None:
            with torch.no_grad():
                centres.copy_(self.state["centres"])
        torch.set_rng_state(self.state["torch_rng"])
        return int(self.state["epoch"]) + 1

    def save(self, stage: str, epoch: int, model: nn.Module, optimizer: torch.optim.Optimizer,
             centres: nn.Parameter | None = None) -> None:
        if self.path is None:
            return
        state = {
            "fingerprint": self.fingerprint, "stage": stage, "epoch": epoch,
            "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "centres": None if centres is None else centres.detach().clone(),
            "torch_rng": torch.get_rng_state(),
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        torch.save(state, buffer)
        atomic_write_bytes(self.path, buffer.getvalue())

    def finish(self) -> None:
        """Training completed: the checkpoint has served its purpose."""
        if self.path is not None and self.path.exists():
            self.path.unlink()


_SKIP = 1 << 30  # an epoch number past any stage's end: the stage's loop runs no epoch


