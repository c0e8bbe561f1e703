"""tf-idf cosine scorer against a direct dense computation."""

import numpy as np
import pytest
import scipy.sparse as sp

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.tfidf import TfIdfIndex, inverse_document_frequency, tfidf_score_matrix


def _dense_reference(counts: np.ndarray, source: np.ndarray) -> np.ndarray:
    m = source.shape[0]
    idf = np.array([np.log(m / max((source[:, q] > 0).sum(), 1)) for q in range(counts.shape[1])])
    out = np.zeros((counts.shape[0], counts.shape[0]))
    vectors = []
    for row in counts:
        total = row.sum()
        vec = (row / total if total else row) * idf
        norm = np.linalg.norm(vec)
        vectors.append(vec / norm if norm else vec)
    for i, a in enumerate(vectors):
        for j, b in enumerate(vectors):
            out[i, j] = a @ b
    return out


def test_matches_dense_reference_with_database_and_training_idf():
    rng = np.random.default_rng(0)
    counts = rng.poisson(0.4, size=(12, 30)).astype(float)
    counts[5] = 0  # an image without words scores 0
    training = rng.poisson(0.3, size=(40, 30))
    np.testing.assert_allclose(tfidf_score_matrix(sp.csr_matrix(counts)), _dense_reference(counts, counts), atol=1e-12)
    scores = tfidf_score_matrix(counts, training)
    np.testing.assert_allclose(scores, _dense_reference(counts, training), atol=1e-12)
    assert np.all(scores[5] == 0)
    nonempty = [i for i in range(12) if i != 5]
    np.testing.assert_allclose(np.diag(scores)[nonempty], 1.0)


def test_online_index_equals_offline_matrix():
    rng = np.random.default_rng(1)
    counts = rng.poisson(0.5, size=(8, 20))
    training = rng.poisson(0.5, size=(30, 20))
    offline = tfidf_score_matrix(counts, training)
    index = TfIdfIndex(inverse_document_frequency(training))
    assert index.score(np.array([1])).size == 0
    for i, row in enumerate(counts):
        ids = np.flatnonzero(row)
        np.testing.assert_allclose(index.score(ids, row[ids]), offline[i, :i], atol=1e-12)
        assert index.add(ids, row[ids]) == i


def test_errors():
    with pytest.raises(DataError, match="idf_source has 5 words, counts have 4"):
        tfidf_score_matrix(np.ones((2, 4)), np.ones((3, 5)))
    with pytest.raises(DataError, match="non-negative"):
        tfidf_score_matrix(-np.ones((2, 4)))
    with pytest.raises(DataError, match="word ids must be 1-D in"):
        TfIdfIndex(np.ones(4)).add(np.array([4]))
    with pytest.raises(DataError, match="idf must be"):
        TfIdfIndex(np.array([np.nan]))
