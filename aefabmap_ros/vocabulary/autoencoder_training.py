"""Training of the autoencoder vocabulary (``autoencoder_network.py`` holds the torch networks,
``autoencoder.py`` the numpy quantizer the training returns and the nodes run).

1. PCA of the descriptors, scaled to [0, 1] (``pca.py``).
2. Pre-training of the autoencoder (``ae_network``: the MLP, or the paper's convolutional network) with
   binary cross-entropy (paper eq. 1) on at most ``ae_max_train_descriptors`` rows, the MLP's learning
   rate cosine-annealed to 0; with ``ae_match_weight`` > 0 plus a match term on descriptor
   pairs of the same scene point in neighbouring frames: symmetric InfoNCE over the batch with
   ``-|z(a_i) - z(b_j)|^2 / T`` logits, the geometry k-means and the Student-t kernel use.
3. k-means (k-means++ seeded) of all embeddings: the K word centres; empty words re-seeded.
4. Optional DEC/IDEC refinement (``refine``): reconstruction + gamma * KL(P || Q), the sharpened target
   P recomputed every ``refine_update_interval`` batches, stopped when fewer than ``refine_tol`` of the
   labels change; empty words re-seeded at every target update.
5. The MLP encoder that quantizes: the MLP autoencoder's own encoder; for the convolutional network
   (``ae_student_hidden`` > 0) a student distilled as in ``distilled.py``, fitted to the network's
   embeddings of all but a held-out 5 % of the rows (plus ``ae_student_noise_rows`` noisy copies
   labelled by the network); ``training_info`` records its word agreement on the held-out rows.
6. Descriptor-space centroids: the mean of each word's descriptors (paper eq. 3), words as the
   quantizing encoder gives them.

Deterministic given ``seed`` on one machine and thread count (seeded torch and numpy generators,
torch's deterministic algorithms). With a ``work_dir`` a checkpoint is written after every epoch
(``training_checkpoint.py``), so an interrupted run resumes.
"""

from __future__ import annotations

import contextlib
import functools
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer
from aefabmap_ros.vocabulary.autoencoder_network import (
    Autoencoder,
    ConvAutoencoder,
    MlpAutoencoder,
    embed_rows,
    student_t,
    target_distribution,
)
from aefabmap_ros.vocabulary.config import VocabularyConfig
from aefabmap_ros.vocabulary.conv_encoder import ConvEncoder
from aefabmap_ros.vocabulary.distilled import DistillOptions, distill_student
from aefabmap_ros.vocabulary.kmeans_training import cluster_means, kmeans, nearest, reseed_empty
from aefabmap_ros.vocabulary.mlp_encoder import MlpEncoder
from aefabmap_ros.vocabulary.pca import PCA, fit_match_projection, fit_pca
from aefabmap_ros.vocabulary.training_checkpoint import Checkpoint, fingerprint


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


def train_quantizer(
    descriptors: np.ndarray,
    options: VocabularyConfig,
    *,
    pairs: np.ndarray | None = None,
    progress: bool = True,
    work_dir: Path | None = None,
) -> AutoencoderQuantizer:
    """Train PCA + autoencoder + centres on (N, D) descriptors (uint8 rows = binary).

    ``pairs``: optional (M, 2) int64 row indices of descriptors of the same scene point in
    neighbouring frames, used by the match term (``ae_match_weight`` > 0) and the match projection
    (``ae_input: matches``).
    """
    _check_inputs(descriptors, options, pairs)
    kind, n = kind_of(descriptors), descriptors.shape[0]
    rows = kind.vectors(descriptors)
    clock = _StageClock()
    with _torch_settings(options.num_threads):
        pca = _fit_input_projection(rows, pairs, options)
        x_all = pca.transform_scaled(rows)
        clock.lap("pca_s")
        checkpoint = Checkpoint(work_dir, fingerprint(options, descriptors, pairs))
        torch.manual_seed(options.seed)
        model = new_autoencoder(options)
        train_idx = np.sort(np.random.default_rng([options.seed, 1]).permutation(n)[
            : min(n, options.ae_max_train_descriptors)])
        _pretrain(model, x_all, train_idx, pairs, options, checkpoint, progress)
        model.eval()
        clock.lap("pretrain_s")
        z_all = embed_rows(model, x_all)
        clock.lap("embed_s")
        centres = kmeans(z_all, options.size, options.seed, options.kmeans_iterations)
        clock.lap("kmeans_s")
        if options.refine:
            centres = _refine(model, centres, x_all, train_idx, options, checkpoint, progress)
            z_all = embed_rows(model, x_all)
            centres = reseed_empty(z_all, centres, np.random.default_rng([options.seed, 3]))
            clock.lap("refine_s")
        model.eval()
        network, encoder, student_info = _quantizing_encoders(model, x_all, z_all, centres, options)
        if encoder is not None:
            z_all = encoder.embed(x_all)  # the words of the vocabulary are the ones the MLP encoder gives
        if student_info:
            clock.lap("distill_s")
        labels, _ = nearest(centres, z_all)
        fallback = _centroids_of_empty_words(rows, z_all, centres, labels)
        centroids = kind.centres(cluster_means(rows, labels, options.size, fallback))
        clock.lap("centroids_s")
        checkpoint.finish()
    quantizer = AutoencoderQuantizer(pca, network, centres, centroids, kind.binary, descriptors.shape[1],
                                     options.alpha, encoder)
    quantizer.training_info = {**clock.seconds, **_word_usage_info(labels, options.size, train_idx.size),
                               **student_info}
    return quantizer


def _quantizing_encoders(model: Autoencoder, x_all: np.ndarray, z_all: np.ndarray, centres: np.ndarray,
                         options: VocabularyConfig) -> tuple[ConvEncoder | None, MlpEncoder | None,
                                                             dict[str, float]]:
    """What the vocabulary keeps to quantize with, as numpy arrays: the convolutional network (None for the
    MLP, whose decoder is not needed), the MLP encoder (the MLP's own, or a student distilled from the
    network), and the distillation's record (empty without one)."""
    if isinstance(model, MlpAutoencoder):
        return None, model.numpy_encoder(), {}
    assert isinstance(model, ConvAutoencoder)
    if options.ae_student_hidden == 0:
        return model.numpy_network(), None, {}
    student, info = _distill(x_all, z_all, centres, options, teacher=functools.partial(embed_rows, model))
    return model.numpy_network(), student, info


def new_autoencoder(options: VocabularyConfig) -> Autoencoder:
    """The untrained autoencoder ``options.ae_network`` names (initialised from torch's generator)."""
    if options.ae_network == "mlp":
        return MlpAutoencoder(options.pca_dim, options.ae_mlp_hidden, options.ae_embedding_dim)
    return ConvAutoencoder(options.pca_dim, options.ae_embedding_dim)


def _word_usage_info(labels: np.ndarray, size: int, pretrained_rows: int) -> dict[str, float]:
    counts = np.bincount(labels, minlength=size)
    return {"descriptors": float(labels.size), "ae_train_descriptors": float(pretrained_rows),
            "empty_words": float(np.sum(counts == 0)),
            "largest_word_fraction": float(counts.max() / max(1, labels.size))}


def _check_inputs(descriptors: np.ndarray, options: VocabularyConfig, pairs: np.ndarray | None) -> None:
    n = descriptors.shape[0]
    if n < options.size:
        raise DataError(f"autoencoder vocabulary of size={options.size} needs >= {options.size} descriptors, got {n}")
    if (options.ae_match_weight > 0 or options.ae_input == "matches") and (pairs is None or len(pairs) < 2):
        raise DataError("ae_match_weight > 0 or ae_input 'matches': needs matched descriptor pairs (none given)")
    if pairs is not None and len(pairs) and (pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.min() < 0
                                             or pairs.max() >= n):
        raise DataError(f"pairs must be (M, 2) row indices in [0, {n}), got shape {pairs.shape}")


def _fit_input_projection(rows: np.ndarray, pairs: np.ndarray | None, options: VocabularyConfig) -> PCA:
    if options.ae_input == "matches" and pairs is not None:
        return fit_match_projection(rows, pairs, options.pca_dim, options.pca_per_component)
    return fit_pca(_subsample(rows, 200_000, options.seed), options.pca_dim, options.pca_per_component)


# At most this many noisy copies per training row (``ae_student_noise_rows`` caps the total): the default 300k
# is about one to one and a half per row for a few hundred camera images (kitti00: 207k-285k rows); a small
# training set is not drowned in copies of itself, nor its distillation slowed by them.
MAX_NOISE_COPIES_PER_ROW = 2
# Descriptors held out of the student's training to measure its agreement with the network.
STUDENT_HELD_OUT_FRACTION = 0.05
STUDENT_HELD_OUT_MAX = 20_000


def _distill(x_all: np.ndarray, z_all: np.ndarray, centres: np.ndarray, options: VocabularyConfig, *,
             teacher: Callable[[np.ndarray], np.ndarray]) -> tuple[MlpEncoder, dict[str, float]]:
    """Distil the student from the network's embeddings ``z_all`` (plus ``options.ae_student_noise_rows``
    noisy copies of the fit rows, at most ``MAX_NOISE_COPIES_PER_ROW`` per row, embedded by ``teacher``);
    its word agreement on held-out rows."""
    n = x_all.shape[0]
    held_count = min(STUDENT_HELD_OUT_MAX, max(1, int(n * STUDENT_HELD_OUT_FRACTION))) if n > 1 else 0
    order = np.random.default_rng([options.seed, 6]).permutation(n)
    held, fit = np.sort(order[:held_count]), np.sort(order[held_count:])
    x_fit, z_fit = x_all[fit], z_all[fit]
    noise_rows = min(options.ae_student_noise_rows, MAX_NOISE_COPIES_PER_ROW * x_fit.shape[0])
    if noise_rows > 0:
        noisy = noisy_copies(x_fit, noise_rows, options.ae_student_noise_scale, options.seed)
        x_fit, z_fit = np.concatenate([x_fit, noisy]), np.concatenate([z_fit, teacher(noisy)])
    student = distill_student(x_fit, z_fit, centres, DistillOptions(
        hidden_dim=options.ae_student_hidden, epochs=options.ae_student_epochs, batch_size=options.ae_batch_size,
        learning_rate=options.ae_student_learning_rate, seed=options.seed, word_weight=options.ae_student_word_weight,
        word_temperature=options.ae_student_word_temperature))
    info = {"student_hidden": float(options.ae_student_hidden), "student_held_out_descriptors": float(held.size)}
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


def _centroids_of_empty_words(rows: np.ndarray, z: np.ndarray, centres: np.ndarray,
                              labels: np.ndarray) -> np.ndarray:
    """(K, D): for each word no descriptor falls in, the descriptor whose embedding is nearest its centre
    (its centroid); zeros for the others, whose centroid is their members' mean. Searched for the empty
    words alone: all K centres against every row cost seconds for nothing when no word is empty."""
    fallback = np.zeros((centres.shape[0], rows.shape[1]), rows.dtype)
    empty = np.flatnonzero(np.bincount(labels, minlength=centres.shape[0]) == 0)
    if empty.size:
        index_rows, _ = nearest(z, centres[empty])
        fallback[empty] = rows[index_rows]
    return fallback


def _subsample(x: np.ndarray, limit: int, seed: int) -> np.ndarray:
    if x.shape[0] <= limit:
        return x
    idx = np.sort(np.random.default_rng([seed, 0]).choice(x.shape[0], limit, replace=False))
    return x[idx]


def _pretrain(
    model: Autoencoder,
    x_all: np.ndarray,
    train_idx: np.ndarray,
    pairs: np.ndarray | None,
    options: VocabularyConfig,
    checkpoint: Checkpoint,
    progress: bool,
) -> None:
    optimizer = torch.optim.Adam(model.parameters(), lr=options.ae_learning_rate)
    start_epoch = min(checkpoint.restore("pretrain", model, optimizer), options.ae_epochs)
    bce = nn.BCEWithLogitsLoss()
    batch = options.ae_batch_size
    use_pairs = options.ae_match_weight > 0 and pairs is not None
    bar = tqdm(range(start_epoch, options.ae_epochs), desc="autoencoder", unit="epoch", disable=not progress,
               initial=start_epoch, total=options.ae_epochs)
    n_batches = max(1, train_idx.size // batch)
    # The MLP makes a few passes over many rows: annealing its rate to 0 settles it where the last passes
    # lead. The convolutional network keeps the paper's constant rate (the reference setting).
    anneal = isinstance(model, MlpAutoencoder)
    for epoch in bar:
        model.train()
        rng = np.random.default_rng([options.seed, 2, epoch])
        order = train_idx[rng.permutation(train_idx.size)]
        pair_order = rng.permutation(len(pairs)) if use_pairs and pairs is not None else None
        total = 0.0
        for b in range(n_batches):
            if anneal:
                _set_learning_rate(optimizer, cosine_rate(options.ae_learning_rate, epoch * n_batches + b,
                                                          options.ae_epochs * n_batches))
            xb = torch.from_numpy(x_all[order[b * batch:(b + 1) * batch]])
            _, logits = model(xb)
            loss = bce(logits, xb)
            if pair_order is not None and pairs is not None:
                chosen = pairs[pair_order[np.arange(b * batch, (b + 1) * batch) % len(pairs)]]
                loss = loss + options.ae_match_weight * _match_loss(model, x_all, chosen, options.ae_match_temperature)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach())
        bar.set_postfix(loss=f"{total / n_batches:.4f}")
        checkpoint.save("pretrain", epoch, model, optimizer)


def cosine_rate(base: float, step: int, total_steps: int) -> float:
    """base * (1 + cos(pi * step / total_steps)) / 2: from ``base`` at step 0 towards 0 at ``total_steps``
    (a function of the step alone, so a run resumed from a checkpoint continues the same schedule)."""
    return base * 0.5 * (1.0 + math.cos(math.pi * step / max(1, total_steps)))


def _set_learning_rate(optimizer: torch.optim.Optimizer, rate: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = rate


def _match_loss(model: Autoencoder, x_all: np.ndarray, chosen: np.ndarray, temperature: float) -> torch.Tensor:
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
    model: Autoencoder,
    centres_np: np.ndarray,
    x_all: np.ndarray,
    train_idx: np.ndarray,
    options: VocabularyConfig,
    checkpoint: Checkpoint,
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
    batch = options.ae_batch_size
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


def _full_target(model: Autoencoder, x: np.ndarray, centres: torch.Tensor,
                 alpha: float) -> tuple[torch.Tensor, np.ndarray]:
    model.eval()
    with torch.no_grad():
        z = torch.from_numpy(embed_rows(model, x))
        q = student_t(z, centres.detach(), alpha)
        return target_distribution(q), q.argmax(dim=1).numpy()


def _reseed_in_place(model: Autoencoder, x: np.ndarray, centres: nn.Parameter, labels: np.ndarray,
                     rng: np.random.Generator) -> None:
    """Guard against words the KL term empties: move them onto members of the largest words."""
    counts = np.bincount(labels, minlength=centres.shape[0])
    empty = np.flatnonzero(counts == 0)
    if empty.size == 0:
        return
    crowded = np.flatnonzero(counts[labels] > 1)
    picks = rng.choice(crowded, size=min(empty.size, crowded.size), replace=False)
    z = embed_rows(model, x[picks])
    with torch.no_grad():
        centres[torch.from_numpy(empty[: picks.size])] = torch.from_numpy(z)
