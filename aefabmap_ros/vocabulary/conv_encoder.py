"""The paper's convolutional encoder (``autoencoder_network.ConvAutoencoder``) as a numpy forward pass.

The network is kept as the plain arrays of its torch ``state_dict`` (decoder included: every one of them
is part of the vocabulary id), under the same names and shapes, so the model directory needs no torch
to be read and the id of a model does not change when its weights move from torch's file to numpy's.
The encoder, exactly as the torch module defines it, on a P-long vector seen as a 1-channel signal:

    encoder.0  Conv1d(1, 32, 3, padding=1)             ReLU   MaxPool1d(2)   -> 32 x P/2
    encoder.3  Conv1d(32, 64, 3, padding=1, stride=2)  ReLU                  -> 64 x P/4
    encoder.5  Conv1d(64, 128, 3, padding=1)           ReLU                  -> 128 x P/4
    encoder.8  Linear(128 * P/4, E) of the channel-major flattening (index c * P/4 + l)

Here signals are held channels-last, (rows, length, channels), so that each convolution is one matrix
product of the three shifted copies of the signal side by side; the dense layer's columns are permuted
once to take the flattening in that order. Rows are encoded ``EMBED_ROWS`` at a time so memory stays
bounded. The result is torch's up to float32 round-off (a different order of the same sums).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from aefabmap_ros.errors import DataError

EMBED_ROWS = 1024  # rows encoded at once: the widest intermediate is EMBED_ROWS x P/4 x 192 floats
# (name, stride) of the encoder's convolutions, in order; a 2-wide max-pool follows the first.
CONVOLUTIONS = (("encoder.0", 1), ("encoder.3", 2), ("encoder.5", 1))
DENSE = "encoder.8"


def conv_shapes(input_dim: int, embedding_dim: int) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every array of the network for P = ``input_dim`` (a multiple of 4) and
    E = ``embedding_dim``: torch's ``state_dict`` of ``ConvAutoencoder(input_dim, embedding_dim)``."""
    flat = 128 * (input_dim // 4)
    layers = {
        "encoder.0": (32, 1, 3), "encoder.3": (64, 32, 3), "encoder.5": (128, 64, 3),
        "encoder.8": (embedding_dim, flat),
        "decoder.0": (flat, embedding_dim), "decoder.3": (128, 128, 3), "decoder.6": (64, 128, 3),
        "decoder.9": (1, 64, 3),
    }
    shapes: dict[str, tuple[int, ...]] = {}
    for name, weight in layers.items():
        shapes[f"{name}.weight"] = weight
        shapes[f"{name}.bias"] = (weight[0],)
    return shapes


@dataclass(frozen=True)
class ConvEncoder:
    """The convolutional network's arrays and the numpy forward pass of its encoder."""

    arrays: dict[str, np.ndarray]  # the state_dict's arrays, float32, names as conv_shapes gives them
    input_dim: int  # P
    embedding_dim: int  # E

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> ConvEncoder:
        """From a state_dict's arrays; DataError unless they are exactly the network's, finite."""
        dense = arrays.get(f"{DENSE}.weight")
        if dense is None or dense.ndim != 2 or dense.shape[1] % 128:
            raise DataError(f"the network's arrays lack a {DENSE}.weight of shape (E, 128 * P/4), got "
                            f"{None if dense is None else dense.shape}")
        input_dim, embedding_dim = dense.shape[1] // 128 * 4, int(dense.shape[0])
        expected = conv_shapes(input_dim, embedding_dim)
        if set(arrays) != set(expected):
            raise DataError(f"the network's arrays are not the convolutional autoencoder's: missing "
                            f"{sorted(set(expected) - set(arrays))}, unexpected {sorted(set(arrays) - set(expected))}")
        wrong = {name: tuple(arrays[name].shape) for name, shape in expected.items() if arrays[name].shape != shape}
        if wrong:
            raise DataError(f"the network's arrays have the wrong shapes for P={input_dim}, E={embedding_dim}: {wrong}")
        checked = {name: np.ascontiguousarray(arrays[name], np.float32) for name in sorted(expected)}
        for name, array in checked.items():
            if not np.all(np.isfinite(array)):
                raise DataError(f"the network's {name} contains NaN or infinity")
        return cls(checked, input_dim, embedding_dim)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The arrays by name, sorted (the order the vocabulary id hashes them in)."""
        return dict(sorted(self.arrays.items()))

    @functools.cached_property
    def _layers(self) -> tuple[list[tuple[np.ndarray, np.ndarray, int]], np.ndarray, np.ndarray]:
        """Each convolution as a (3 C, O) matrix (row k * C + c: tap k of input channel c) with its bias and
        stride; the dense layer as an (L * C, E) matrix whose rows follow the channels-last flattening."""
        convolutions = []
        for name, stride in CONVOLUTIONS:
            weight = self.arrays[f"{name}.weight"]  # (O, C, 3)
            matrix = weight.transpose(2, 1, 0).reshape(3 * weight.shape[1], weight.shape[0])
            convolutions.append((np.ascontiguousarray(matrix), self.arrays[f"{name}.bias"], stride))
        dense = self.arrays[f"{DENSE}.weight"]  # (E, C * L), column c * L + l
        channels = self.arrays[f"{CONVOLUTIONS[-1][0]}.weight"].shape[0]
        length = dense.shape[1] // channels
        channels_last = dense.reshape(self.embedding_dim, channels, length).transpose(0, 2, 1)
        dense_matrix = np.ascontiguousarray(channels_last.reshape(self.embedding_dim, -1).T)
        return convolutions, dense_matrix, self.arrays[f"{DENSE}.bias"]

    def embed(self, x: np.ndarray) -> np.ndarray:
        """(N, P) float32 vectors in [0, 1] -> (N, E) float32 embeddings."""
        if x.ndim != 2 or x.shape[1] != self.input_dim:
            raise DataError(f"the network encodes (N, {self.input_dim}) vectors, got shape {x.shape}")
        out = np.empty((x.shape[0], self.embedding_dim), np.float32)
        for start in range(0, x.shape[0], EMBED_ROWS):
            out[start:start + EMBED_ROWS] = self._embed_rows(np.asarray(x[start:start + EMBED_ROWS], np.float32))
        return out

    def _embed_rows(self, x: np.ndarray) -> np.ndarray:
        convolutions, dense_matrix, dense_bias = self._layers
        signal = x[:, :, None]  # (B, P, 1): one channel
        for index, (matrix, bias, stride) in enumerate(convolutions):
            signal = _conv3_relu(signal, matrix, bias, stride)
            if index == 0:
                rows, length, channels = signal.shape
                signal = signal.reshape(rows, length // 2, 2, channels).max(axis=2)  # MaxPool1d(2)
        z: np.ndarray = signal.reshape(signal.shape[0], -1) @ dense_matrix
        z += dense_bias
        return z


def _conv3_relu(signal: np.ndarray, matrix: np.ndarray, bias: np.ndarray, stride: int) -> np.ndarray:
    """ReLU(Conv1d(kernel 3, padding 1, ``stride``)) of a channels-last (B, L, C) signal -> (B, L_out, O)."""
    rows, length, channels = signal.shape
    padded = np.zeros((rows, length + 2, channels), np.float32)
    padded[:, 1:-1] = signal
    out_length = (length - 1) // stride + 1  # (L + 2 * padding - kernel) // stride + 1
    span = stride * (out_length - 1) + 1
    out: np.ndarray
    if channels == 1:  # the first layer: three multiply-adds per output, no product worth BLAS
        out = padded[:, 0:span:stride] * matrix[0] + bias
        for k in (1, 2):
            out += padded[:, k:k + span:stride] * matrix[k]
        np.maximum(out, 0.0, out=out)
        return out
    taps = np.concatenate([padded[:, k:k + span:stride] for k in range(3)], axis=2)  # (B, L_out, 3 C)
    # one (B L_out, 3 C) x (3 C, O) product: a 3-D matmul would be B small ones
    out = taps.reshape(rows * out_length, 3 * channels) @ matrix
    out += bias
    np.maximum(out, 0.0, out=out)
    return out.reshape(rows, out_length, matrix.shape[1])


__all__ = ["CONVOLUTIONS", "DENSE", "EMBED_ROWS", "ConvEncoder", "conv_shapes"]
