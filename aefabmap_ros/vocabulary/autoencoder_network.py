"""The autoencoders as torch modules, for training: the MLP autoencoder and the paper's convolutional one,
DEC's soft assignment and target, and the conversion of a trained network to the arrays that quantize.

Training only (``autoencoder_training.py``, ``distilled.py``): a node never imports this module. What a
node runs is numpy: ``mlp_encoder.MlpEncoder`` (from ``MlpAutoencoder.numpy_encoder``) and
``conv_encoder.ConvEncoder`` (from ``ConvAutoencoder.numpy_network``), the same functions to float32
round-off.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.vocabulary.conv_encoder import ConvEncoder
from aefabmap_ros.vocabulary.mlp_encoder import MlpEncoder, mlp_network

EMBED_BATCH = 8192  # rows a torch network embeds at once


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
    conv 1x3 -> logits (sigmoid = reconstruction in [0, 1]). ``conv_encoder.py`` runs the encoder in
    numpy from the ``state_dict``'s arrays; its ``conv_shapes`` must stay this module's shapes.
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

    def numpy_network(self) -> ConvEncoder:
        """The network as the arrays the model directory stores, with the numpy encoder that quantizes."""
        return ConvEncoder.from_arrays(state_arrays(self))

    @classmethod
    def from_numpy(cls, network: ConvEncoder) -> ConvAutoencoder:
        """The torch module of stored arrays (to compare with the numpy forward pass, or train on)."""
        model = cls(network.input_dim, network.embedding_dim)
        model.load_state_dict({name: torch.from_numpy(array.copy()) for name, array in network.arrays.items()})
        return model.eval()


def state_arrays(model: nn.Module) -> dict[str, np.ndarray]:
    """A module's ``state_dict`` as float32 numpy arrays by name."""
    return {name: tensor.detach().cpu().numpy().astype(np.float32) for name, tensor in model.state_dict().items()}


def student_t(z: torch.Tensor, centres: torch.Tensor, alpha: float = 1.0) -> torch.Tensor:
    """Soft assignment q_ij of DEC: Student-t kernel (1 + |z_i - mu_j|^2 / alpha)^(-(alpha+1)/2), row-normalised."""
    sq = torch.cdist(z, centres).pow(2)
    q = (1.0 + sq / alpha).pow(-(alpha + 1.0) / 2.0)
    return q / q.sum(dim=1, keepdim=True)


def target_distribution(q: torch.Tensor) -> torch.Tensor:
    """DEC's sharpened target p_ij = (q_ij^2 / f_j) / sum_j'(...), f_j = sum_i q_ij."""
    weight = q.pow(2) / q.sum(dim=0)
    return weight / weight.sum(dim=1, keepdim=True)


def embed_rows(model: Autoencoder, x: np.ndarray) -> np.ndarray:
    """(N, P) -> (N, E) float32 embeddings by the torch network, ``EMBED_BATCH`` rows at a time."""
    out = np.empty((x.shape[0], model.embedding_dim), np.float32)
    with torch.inference_mode():
        for start in range(0, x.shape[0], EMBED_BATCH):
            out[start:start + EMBED_BATCH] = model.encode(torch.from_numpy(x[start:start + EMBED_BATCH])).numpy()
    return out


__all__ = ["EMBED_BATCH", "Autoencoder", "ConvAutoencoder", "MlpAutoencoder", "embed_rows", "state_arrays",
           "student_t", "target_distribution"]
