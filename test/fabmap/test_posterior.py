"""FAB-MAP's posterior: openFABMAP's motion prior and smoothing, top-k without a full sort."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aefabmap_ros.errors import DataError
from aefabmap_ros.fabmap.posterior import motion_log_prior, posterior, top_k_indices


def test_motion_prior_follows_openfabmap_formula():
    previous = np.array([0.1, 0.2, 0.3, 0.4])  # [new, place 0, 1, 2]
    prior = np.exp(motion_log_prior(previous, 4, p_new=0.9, motion_bias=0.7))
    b = 0.7
    expected = [
        0.9,
        (2 * (1 - b) * 0.2 + 0.2 + 2 * b * 0.3) / 3,
        (2 * (1 - b) * 0.2 + 0.3 + 2 * b * 0.4) / 3,
        (2 * (1 - b) * 0.3 + 0.4 + 2 * b * 0.4) / 3,
        1.0,  # a place created since the previous posterior
    ]
    np.testing.assert_allclose(prior, expected)
    np.testing.assert_allclose(np.exp(motion_log_prior(previous[:2], 2, 0.9, 0.5)), [0.9, 1.0, 1.0])
    p = posterior(np.array([0.0, 1.0, 2.0]), None, 0.9)
    np.testing.assert_allclose(p, 0.9 * np.exp([0, 1, 2]) / np.exp([0, 1, 2]).sum() + 0.1 / 3)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 300), k=st.integers(0, 8), scale=st.sampled_from([0.5, 500]))
def test_top_k_indices_equals_a_full_stable_sort(seed, n, k, scale):
    rng = np.random.default_rng(seed)
    log_likelihoods = rng.normal(0, scale, n)
    log_likelihoods[rng.random(n) < 0.2] = 0.0  # exact ties
    p = posterior(log_likelihoods, None, 0.99) if n else np.zeros(0)  # underflow: many equal floor values
    np.testing.assert_array_equal(top_k_indices(p, k), np.lexsort((np.arange(n), -p))[:k])


def test_top_k_indices_rejects_negative_k():
    with pytest.raises(DataError, match="k = -1 must be >= 0"):
        top_k_indices(np.zeros(3), -1)
