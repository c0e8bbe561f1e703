"""Nearest centre in numpy: one BLAS product per chunk of rows, so memory stays bounded.

argmin_k |x - c_k|^2 = argmin_k (|c_k|^2 - 2 x.c_k): |x|^2 is the same for every centre of a row, so the
scores are one (rows, D) x (D, K) product plus a row of squared norms. Rows go through in chunks of at
most ``CHUNK_SCORES`` scores (16 MiB of float32), whatever the number of rows asked for. This is the
search faiss' ``IndexFlatL2`` makes (its distances are |x|^2 + |c|^2 - 2 x.c in float32 too): the two give
the same centre except where two centres are within float32 round-off of each other.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aefabmap_ros.errors import DataError

CHUNK_SCORES = 1 << 22  # scores (rows x centres) computed at once


class NearestCentre:
    """The nearest of K fixed centres (K, D) for rows (N, D), all float32."""

    def __init__(self, centres: np.ndarray) -> None:
        centres = np.ascontiguousarray(centres, np.float32)
        if centres.ndim != 2 or centres.shape[0] < 1:
            raise DataError(f"centres must be (K, D) with K >= 1, got shape {centres.shape}")
        self.minus_two_transposed = np.ascontiguousarray(-2.0 * centres.T, np.float32)  # (D, K)
        self.squared_norms = np.einsum("kd,kd->k", centres, centres).astype(np.float32)  # (K,)

    @property
    def size(self) -> int:
        return int(self.squared_norms.shape[0])

    @property
    def dim(self) -> int:
        return int(self.minus_two_transposed.shape[0])

    def chunk_rows(self) -> int:
        """Rows per chunk: ``CHUNK_SCORES`` scores, at least one row."""
        return max(1, CHUNK_SCORES // self.size)

    def scores(self, x: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, K) float32 |c_k|^2 - 2 x.c_k (the squared distance less |x|^2)."""
        result: np.ndarray = np.ascontiguousarray(x, np.float32) @ self.minus_two_transposed
        result += self.squared_norms
        return result

    def nearest(self, x: np.ndarray) -> np.ndarray:
        """(N, D) float rows -> (N,) int64 index of the nearest centre."""
        return self.nearest_of(x, lambda rows: rows)

    def nearest_of(self, rows: np.ndarray, vectors: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """(N, ...) rows -> (N,) int64 nearest centre of ``vectors(chunk)``, the rows made vectors a chunk at a
        time (binary descriptors unpack to 8x their size: never all at once)."""
        out = np.empty(rows.shape[0], np.int64)
        step = self.chunk_rows()
        for start in range(0, rows.shape[0], step):
            chunk = vectors(rows[start:start + step])
            out[start:start + chunk.shape[0]] = np.argmin(self.scores(chunk), axis=1)
        return out


__all__ = ["CHUNK_SCORES", "NearestCentre"]
