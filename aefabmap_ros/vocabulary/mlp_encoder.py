"""The one-hidden-layer MLP encoder that quantizes in numpy, and the nearest-centre search it feeds.

``MlpEncoder`` is relu(x @ w1 + b1) @ w2 + b2, PCA vector (P) -> H (ReLU) -> embedding (E). It is either
the encoder half of the MLP autoencoder (``ae_network: mlp``, trained directly) or a student distilled from
the paper's convolutional network (``distilled.py``); either way the model directory stores its four
arrays and quantizing needs no torch. Per descriptor it costs P*H + H*E multiply-adds, plus K*E for the
centre search, against k-means' K*D (P = E = 64, H = 256, K = 1000, SIFT D = 128: 97k against 128k).

torch is imported only inside the two functions that make or read a torch network (``mlp_network``,
``MlpEncoder.from_torch``), which training alone calls: a node imports this module without torch.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from aefabmap_ros.errors import DataError

if TYPE_CHECKING:
    from torch import nn

# The arrays of an MLP encoder as the model directory stores them, in this order.
MLP_ARRAYS = ("w1", "b1", "w2", "b2")


@dataclass(frozen=True)
class MlpEncoder:
    """relu(x @ w1 + b1) @ w2 + b2: (N, P) PCA-scaled vectors -> (N, E) embeddings, float32."""

    w1: np.ndarray  # (P, H)
    b1: np.ndarray  # (H,)
    w2: np.ndarray  # (H, E)
    b2: np.ndarray  # (E,)

    def __post_init__(self) -> None:
        arrays = {name: np.ascontiguousarray(getattr(self, name), np.float32) for name in MLP_ARRAYS}
        w1, b1, w2, b2 = (arrays[name] for name in MLP_ARRAYS)
        if w1.ndim != 2 or w2.ndim != 2 or b1.shape != (w1.shape[1],) or w2.shape[0] != w1.shape[1] \
                or b2.shape != (w2.shape[1],):
            raise DataError(f"MLP encoder arrays do not chain: w1 {w1.shape}, b1 {b1.shape}, "
                            f"w2 {w2.shape}, b2 {b2.shape} (expected (P, H), (H,), (H, E), (E,))")
        for name, array in arrays.items():
            if not np.all(np.isfinite(array)):
                raise DataError(f"MLP encoder {name} contains NaN or infinity")
            object.__setattr__(self, name, array)

    @property
    def input_dim(self) -> int:
        return int(self.w1.shape[0])

    @property
    def hidden_dim(self) -> int:
        return int(self.w1.shape[1])

    @property
    def embedding_dim(self) -> int:
        return int(self.w2.shape[1])

    def embed(self, x: np.ndarray) -> np.ndarray:
        """(N, P) float32 -> (N, E) float32."""
        result: np.ndarray = self._hidden(x) @ self.w2 + self.b2
        return result

    def embed_with_one(self, x: np.ndarray) -> np.ndarray:
        """(N, P) -> (N, E + 1): the embedding with a column of ones appended, made by the same matmul
        (a zero column in w2, a 1 in b2), for ``CentreSearch.nearest``."""
        w2, b2 = self._with_one
        z = self._hidden(x) @ w2
        z += b2
        result: np.ndarray = z
        return result

    def _hidden(self, x: np.ndarray) -> np.ndarray:
        hidden = x @ self.w1
        hidden += self.b1
        np.maximum(hidden, 0.0, out=hidden)
        result: np.ndarray = hidden
        return result

    @functools.cached_property
    def _with_one(self) -> tuple[np.ndarray, np.ndarray]:
        w2 = np.concatenate([self.w2, np.zeros((self.w2.shape[0], 1), np.float32)], axis=1)
        return np.ascontiguousarray(w2), np.append(self.b2, np.float32(1.0))

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in MLP_ARRAYS}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> MlpEncoder:
        missing = [name for name in MLP_ARRAYS if name not in arrays]
        if missing:
            raise DataError(f"MLP encoder lacks the array(s) {missing}")
        return cls(*(arrays[name] for name in MLP_ARRAYS))

    @classmethod
    def from_torch(cls, network: nn.Sequential) -> MlpEncoder:
        """From ``mlp_network``'s layers (torch stores Linear weights as (out, in))."""
        from torch import nn

        first, second = network[0], network[2]
        if not isinstance(first, nn.Linear) or not isinstance(second, nn.Linear):
            raise DataError("an MLP encoder is Linear, ReLU, Linear (see mlp_network)")
        return cls(first.weight.detach().numpy().T, first.bias.detach().numpy(),
                   second.weight.detach().numpy().T, second.bias.detach().numpy())


def mlp_network(input_dim: int, hidden_dim: int, embedding_dim: int) -> nn.Sequential:
    """The torch form of ``MlpEncoder`` (for training), P -> H (ReLU) -> E."""
    from torch import nn

    return nn.Sequential(nn.Linear(input_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, embedding_dim))


class CentreSearch:
    """Nearest centre as one matmul: argmin_k |z - c_k|^2 = argmin_k (|c_k|^2 - 2 z.c_k), |z|^2 being the
    same for every centre of a row; with a 1 appended to z the bias |c_k|^2 is a row of the matrix too,
    so the (N, K) scores are written once and read once by argmin (no passes to scale and shift them)."""

    def __init__(self, centres: np.ndarray) -> None:
        centres = np.asarray(centres, np.float32)
        squared_norms = np.einsum("ke,ke->k", centres, centres)
        self.matrix = np.ascontiguousarray(np.vstack([-2.0 * centres.T, squared_norms[None, :]]), np.float32)

    def nearest(self, z_with_one: np.ndarray) -> np.ndarray:
        """(N, E + 1) embeddings with a trailing column of ones -> (N,) int64 nearest centre."""
        result: np.ndarray = np.argmin(z_with_one @ self.matrix, axis=1).astype(np.int64)
        return result


__all__ = ["MLP_ARRAYS", "CentreSearch", "MlpEncoder", "mlp_network"]
