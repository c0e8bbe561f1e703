"""tf-idf bag-of-words cosine similarity (the paper's "BoW" / "AE-BoW" baselines).

Sivic & Zisserman weighting: tf = n_id / n_d (word count over the image's word total),
idf = log(M / df_i) with M the number of idf-source images and df_i the number holding word i
(df clipped to >= 1 so a word unseen in the source gets the largest weight, log M, instead of
infinity). Vectors are L2-normalised; the score is their cosine in [0, 1]. Images without
words have a zero vector and score 0 against everything (also themselves).

``tfidf_score_matrix`` is the offline form (every pair at once); :class:`TfIdfIndex` the
online form with the same scores (query against the stored images, then add).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import DataError


def _counts_csr(counts: sp.spmatrix | sp.sparray | np.ndarray, name: str) -> sp.csr_matrix:
    matrix = sp.csr_matrix(counts, dtype=np.float64)
    if matrix.ndim != 2:
        raise DataError(f"{name} must be 2-D (images x words), got shape {matrix.shape}")
    if matrix.nnz and (not np.all(np.isfinite(matrix.data)) or matrix.data.min() < 0):
        raise DataError(f"{name} must hold finite non-negative counts")
    matrix.eliminate_zeros()
    return matrix


def inverse_document_frequency(idf_source: sp.spmatrix | sp.sparray | np.ndarray) -> np.ndarray:
    """(V,) float64 idf = log(M / max(df, 1)) from an (M, V) bag-of-words (value > 0 = present)."""
    source = _counts_csr(idf_source, "idf_source")
    if source.shape[0] == 0:
        raise DataError("idf_source has no images")
    df = np.bincount(source.indices, minlength=source.shape[1]).astype(np.float64)
    result: np.ndarray = np.log(source.shape[0] / np.maximum(df, 1.0))
    return result


def tfidf_vectors(counts: sp.spmatrix | sp.sparray | np.ndarray, idf: np.ndarray) -> sp.csr_matrix:
    """(N, V) L2-normalised tf-idf rows (sparse)."""
    matrix = _counts_csr(counts, "counts")
    if idf.shape != (matrix.shape[1],):
        raise DataError(f"idf has {idf.shape} entries for a vocabulary of {matrix.shape[1]} words")
    totals = np.asarray(matrix.sum(axis=1)).ravel()
    weighted = sp.diags(1.0 / np.maximum(totals, 1e-300)) @ matrix @ sp.diags(idf)
    weighted = sp.csr_matrix(weighted)
    norms = np.sqrt(np.asarray(weighted.multiply(weighted).sum(axis=1)).ravel())
    scale = np.divide(1.0, norms, out=np.zeros_like(norms), where=norms > 0)
    return sp.csr_matrix(sp.diags(scale) @ weighted)


def tfidf_score_matrix(
    counts: sp.spmatrix | sp.sparray | np.ndarray,
    idf_source: sp.spmatrix | sp.sparray | np.ndarray | None = None,
) -> np.ndarray:
    """(N, N) cosine similarity of tf-idf vectors; symmetric, row i column j < i is "query i vs image j".

    ``idf_source`` (M, V): training bag-of-words for the idf; None = the ``counts`` themselves
    (the database). Must have the same vocabulary size.
    """
    matrix = _counts_csr(counts, "counts")
    source = matrix if idf_source is None else _counts_csr(idf_source, "idf_source")
    if source.shape[1] != matrix.shape[1]:
        raise DataError(f"idf_source has {source.shape[1]} words, counts have {matrix.shape[1]}")
    vectors = tfidf_vectors(matrix, inverse_document_frequency(source))
    return np.asarray((vectors @ vectors.T).toarray())


class TfIdfIndex:
    """Online tf-idf cosine scorer with a fixed idf (from a training bag-of-words)."""

    def __init__(self, idf: np.ndarray) -> None:
        idf = np.asarray(idf, dtype=np.float64)
        if idf.ndim != 1 or idf.size == 0 or not np.all(np.isfinite(idf)) or idf.min() < 0:
            raise DataError(f"idf must be a non-empty 1-D array of finite non-negative values, got shape {idf.shape}")
        self.idf = idf
        self._rows: list[sp.csr_matrix] = []
        self._stacked: sp.csr_matrix | None = None

    @property
    def num_places(self) -> int:
        return len(self._rows)

    def _vector(self, word_ids: np.ndarray, word_counts: np.ndarray | None) -> sp.csr_matrix:
        ids = np.asarray(word_ids, dtype=np.int64)
        if ids.ndim != 1 or (ids.size and (ids.min() < 0 or ids.max() >= self.idf.size)):
            raise DataError(f"word ids must be 1-D in [0, {self.idf.size}), got {ids!r}")
        values = np.ones(ids.size) if word_counts is None else np.asarray(word_counts, dtype=np.float64)
        if values.shape != ids.shape:
            raise DataError(f"word_counts shape {values.shape} does not match word ids {ids.shape}")
        row = sp.csr_matrix((values, (np.zeros(ids.size, dtype=np.int64), ids)), shape=(1, self.idf.size))
        return tfidf_vectors(row, self.idf)

    def score(self, word_ids: np.ndarray, word_counts: np.ndarray | None = None) -> np.ndarray:
        """(P,) cosine similarity of the query with every stored image."""
        if not self._rows:
            return np.zeros(0)
        if self._stacked is None or self._stacked.shape[0] != len(self._rows):
            self._stacked = sp.csr_matrix(sp.vstack(self._rows))
        query = self._vector(word_ids, word_counts)
        return np.asarray((self._stacked @ query.T).toarray()).ravel()

    def add(self, word_ids: np.ndarray, word_counts: np.ndarray | None = None) -> int:
        self._rows.append(self._vector(word_ids, word_counts))
        return len(self._rows) - 1
