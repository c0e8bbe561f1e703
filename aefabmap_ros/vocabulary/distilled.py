"""Distillation of the paper's convolutional autoencoder into an MLP encoder that quantizes in numpy.

The paper's encoder (conv 32/64/128 + dense, ``autoencoder.py``) costs about five times k-means'
nearest-centre search per descriptor in multiply-adds, so no leaner forward pass of it can quantize
as cheaply as k-means. The student is a one-hidden-layer MLP, PCA vector (P) -> H (ReLU) -> embedding
(E), trained after the teacher to reproduce the teacher's embeddings (mean squared error) on the
same PCA-scaled training vectors, plus (``word_weight`` > 0) a word term: the teacher's soft assignment
to the fixed centres, matched by the student's (``word_assignment_loss``). The words stay the
teacher's: the same K centres in the same embedding space, nearest centre = word. Per descriptor it
quantizes as ``mlp_encoder.MlpEncoder`` (numpy): two matmuls and the centre search as one matmul.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from aefabmap_ros.errors import DataError
from aefabmap_ros.vocabulary.mlp_encoder import MlpEncoder, mlp_network


@dataclass(frozen=True)
class DistillOptions:
    hidden_dim: int
    epochs: int
    batch_size: int
    learning_rate: float
    seed: int
    # The word term (``word_assignment_loss``): its weight against the embedding MSE (0 = MSE alone) and its
    # temperature, in the normalised embedding space (unit variance per dimension, see ``distill_student``).
    word_weight: float = 0.0
    word_temperature: float = 1.0


def word_assignment_loss(student_z: torch.Tensor, teacher_z: torch.Tensor, centres: torch.Tensor,
                         temperature: float) -> torch.Tensor:
    """KL(teacher's soft word assignment || student's), batch mean; logits -|z - c_k|^2 / temperature.

    The words are the nearest centres, so what the student must get right is the side of each boundary
    between two words, not the embedding as a whole (the MSE's aim). The logits' differences are
    2 z.(c_j - c_k) + const: matching the softened assignment matches the embedding along the directions
    between the centres near the teacher's point, weighted by how near they are, and leaves the rest
    to the MSE. A soft target rather than the teacher's hard word: cross-entropy on the hard word grows
    without bound as the student pushes its point away from every other centre, off the teacher's
    embedding (docs/vocabulary.md: 90.5 % agreement against 92.8 % for the MSE alone).
    """
    squared_norms = (centres * centres).sum(dim=1)

    def logits(z: torch.Tensor) -> torch.Tensor:
        return (2.0 * z @ centres.T - squared_norms - (z * z).sum(dim=1, keepdim=True)) / temperature

    target = torch.softmax(logits(teacher_z), dim=1)
    return nn.functional.kl_div(torch.log_softmax(logits(student_z), dim=1), target, reduction="batchmean")


# Small training sets still get this many optimizer steps (epochs are repeated): a few thousand descriptors
# in batches of 256 would otherwise give the student a few dozen steps and leave it far from the network.
MIN_DISTILL_STEPS = 2000


def distill_student(x: np.ndarray, teacher_z: np.ndarray, centres: np.ndarray,
                    options: DistillOptions) -> MlpEncoder:
    """Fit a student to the teacher's embeddings ``teacher_z`` (N, E) of PCA vectors ``x`` (N, P).

    Mean squared error on the embeddings, centred and divided by one overall scale (so that the
    learning rate suits any embedding scale while the loss still weighs every dimension as the
    distance to the centres does); the scaling is folded back into the last layer afterwards. With
    ``options.word_weight`` > 0, plus that weight times ``word_assignment_loss`` against the word
    ``centres`` (K, E), fixed, in the same normalised space (so the temperature does not depend on the
    embedding's scale either). Adam, the learning rate cosine-annealed to 0. Deterministic given
    ``options.seed`` (the caller holds torch's deterministic settings).
    """
    if x.shape[0] != teacher_z.shape[0] or x.shape[0] == 0:
        raise DataError(f"distillation needs as many embeddings as vectors, got {x.shape} and {teacher_z.shape}")
    if centres.ndim != 2 or centres.shape[1] != teacher_z.shape[1]:
        raise DataError(f"distillation needs centres in the embedding space ({teacher_z.shape[1]}-d), "
                        f"got {centres.shape}")
    mean = teacher_z.mean(axis=0, dtype=np.float64)
    scale = float(np.sqrt(np.mean((teacher_z - mean) ** 2))) or 1.0
    targets = torch.from_numpy(((teacher_z - mean) / scale).astype(np.float32))
    normalised_centres = torch.from_numpy(((centres - mean) / scale).astype(np.float32))
    inputs = torch.from_numpy(np.ascontiguousarray(x, np.float32))
    torch.manual_seed(options.seed)
    network = mlp_network(x.shape[1], options.hidden_dim, teacher_z.shape[1])
    optimizer = torch.optim.Adam(network.parameters(), lr=options.learning_rate)
    batch = min(options.batch_size, x.shape[0])
    n_batches = x.shape[0] // batch
    epochs = max(options.epochs, -(-MIN_DISTILL_STEPS // n_batches))
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=epochs * n_batches)
    mse = nn.MSELoss()
    network.train()
    for epoch in range(epochs):
        order = torch.from_numpy(np.random.default_rng([options.seed, 7, epoch]).permutation(x.shape[0]))
        for b in range(n_batches):
            idx = order[b * batch:(b + 1) * batch]
            prediction = network(inputs[idx])
            loss = mse(prediction, targets[idx])
            if options.word_weight > 0:
                loss = loss + options.word_weight * word_assignment_loss(
                    prediction, targets[idx], normalised_centres, options.word_temperature)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
    network.eval()
    student = MlpEncoder.from_torch(network)
    # z = scale * (normalised prediction) + mean: exact, folded into the second layer.
    return MlpEncoder(student.w1, student.b1, student.w2 * np.float32(scale),
                      (student.b2 * scale + mean).astype(np.float32))


__all__ = ["MIN_DISTILL_STEPS", "DistillOptions", "distill_student", "word_assignment_loss"]
