"""FAB-MAP 1/2: openFABMAP golden outputs, FAB-MAP 2 == FAB-MAP 1 up to a constant, posteriors, errors."""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.engines import FabMap1, FabMap2
from aefabmap_ros.fabmap.observation import FabMapModel
from test.fabmap.oracles import fabmap_score_matrices

openfabmap = FabMapConfig.openfabmap  # openFABMAP's semantics: the golden references' config

GOLDEN_RUNS = [
    ("fabmap2_sampled", openfabmap(), "fabmap2"),
    ("fabmap2_sampled_motion", openfabmap(motion_model=True), "fabmap2"),
    ("fabmap1_meanfield", openfabmap(new_place_model="meanfield"), "fabmap1"),
    ("fabmaplut_meanfield", openfabmap(new_place_model="meanfield"), "fabmaplut"),
]


@pytest.mark.parametrize(("prefix", "config", "method"), GOLDEN_RUNS)
def test_reproduces_openfabmap_golden_outputs(golden_dir, prefix, config, method):
    from aefabmap_ros.fabmap.openfabmap import read_bow, read_chow_liu_tree

    tree = read_chow_liu_tree(golden_dir / "tree.yml")
    train = read_bow(golden_dir / "bowtrain.yml")
    test = read_bow(golden_dir / "bowtest.yml")
    result = fabmap_score_matrices(sp.csr_matrix(test), tree, sp.csr_matrix(train), config, method)
    golden_ll = np.loadtxt(golden_dir / f"{prefix}.loglik.txt")
    golden_p = np.loadtxt(golden_dir / f"{prefix}.probabilities.txt")
    assert result.log_likelihoods.shape == golden_ll.shape == (84, 84)
    np.testing.assert_array_equal(np.isnan(result.log_likelihoods), np.isnan(golden_ll))
    known = ~np.isnan(golden_ll)
    np.testing.assert_allclose(result.log_likelihoods[known], golden_ll[known], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(result.probabilities, golden_p, rtol=0, atol=1e-5)
    np.testing.assert_allclose(result.probabilities.sum(axis=1), 1.0, atol=1e-12)


def _random_tree(rng: np.random.Generator, v: int) -> ChowLiuTree:
    order = rng.permutation(v)
    parent = np.empty(v, dtype=np.int64)
    parent[order[0]] = order[0]
    for k in range(1, v):
        parent[order[k]] = order[rng.integers(0, k)]
    probs = rng.uniform(0.02, 0.98, size=(3, v))
    probs[1:, order[0]] = probs[0, order[0]]
    return ChowLiuTree(parent, probs[0], probs[1], probs[2])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), v=st.integers(2, 30), dense=st.floats(0.05, 0.9))
def test_fabmap2_differences_equal_fabmap1(seed, v, dense):
    rng = np.random.default_rng(seed)
    tree = _random_tree(rng, v)
    model = FabMapModel(tree, p_z_given_e=rng.uniform(0.1, 0.9), p_z_given_not_e=rng.uniform(0, 0.05))
    fm1 = FabMap1(model, None, "meanfield")
    fm2 = FabMap2(model, None, "meanfield")
    places = [np.flatnonzero(rng.random(v) < dense) for _ in range(6)] + [np.zeros(0, dtype=np.int64)]
    for words in places:
        fm1.add(words)
        fm2.add(words)
    for _ in range(3):
        query = np.flatnonzero(rng.random(v) < dense)  # words whose parent is observed or not
        new1, exact = fm1.log_likelihoods(query)
        new2, relative = fm2.log_likelihoods(query)
        empty_place = exact[-1]
        np.testing.assert_allclose(relative, exact - empty_place, rtol=0, atol=1e-9)
        assert new2 == pytest.approx(new1 - empty_place, abs=1e-9)


def test_sampled_new_place_is_mean_sample_likelihood_and_can_exclude_the_query():
    rng = np.random.default_rng(5)
    tree = _random_tree(rng, 12)
    samples = [np.flatnonzero(rng.random(12) < 0.4) for _ in range(5)]
    model = FabMapModel(tree)
    fm2 = FabMap2(model, samples, "sampled")
    query = samples[2]
    state = model.query_state(query)
    ll = fm2.sample_log_likelihoods(state)
    assert fm2.new_place_log_likelihood(state) == pytest.approx(np.log(np.mean(np.exp(ll))))
    kept = np.delete(ll, 2)
    assert fm2.new_place_log_likelihood(state, exclude_sample=2) == pytest.approx(np.log(np.mean(np.exp(kept))))
    with pytest.raises(DataError, match="exclude_sample 9 out of range"):
        fm2.new_place_log_likelihood(state, exclude_sample=9)
    with pytest.raises(DataError, match="at least one new-place sample"):
        FabMap2(model, None, "sampled")


@pytest.mark.parametrize("engine_class", [FabMap1, FabMap2])
def test_clear_forgets_the_places_and_keeps_the_samples(engine_class):
    rng = np.random.default_rng(7)
    tree = _random_tree(rng, 12)
    samples = [np.flatnonzero(rng.random(12) < 0.4) for _ in range(5)]
    engine = engine_class(FabMapModel(tree), samples, "sampled")
    query = np.flatnonzero(rng.random(12) < 0.4)
    new_before, _ = engine.log_likelihoods(query)
    for _ in range(3):
        engine.add(np.flatnonzero(rng.random(12) < 0.4))
    engine.clear()
    new_after, places = engine.log_likelihoods(query)
    assert engine.num_places == 0 and places.shape == (0,)
    assert new_after == new_before  # the new-place samples belong to the model, not to the map
    assert engine.add(query) == 0  # place ids start afresh


def test_exact_revisit_gets_highest_posterior_and_posteriors_sum_to_one():
    rng = np.random.default_rng(11)
    v = 50
    tree = _random_tree(rng, v)
    sequence = [np.flatnonzero(rng.random(v) < 0.2) for _ in range(15)]
    sequence.append(sequence[4].copy())  # revisit of frame 4
    samples = sp.csr_matrix(rng.random((20, v)) < 0.2)
    for config in (openfabmap(), openfabmap(motion_model=True), openfabmap(new_place_model="meanfield")):
        result = fabmap_score_matrices(sequence, tree, samples, config)
        np.testing.assert_allclose(result.probabilities.sum(axis=1), 1.0, atol=1e-12)
        assert np.all(np.triu(result.probabilities, 1) == 0)
        last = result.probabilities[-1, :-1]
        assert int(np.argmax(last)) == 4
        assert int(np.nanargmax(result.log_likelihoods[-1, :-1])) == 4


def test_empty_observations_keep_their_index():
    rng = np.random.default_rng(2)
    tree = _random_tree(rng, 10)
    rows = [np.array([1, 2, 3]), np.zeros(0, dtype=np.int64), np.array([1, 2, 3])]
    result = fabmap_score_matrices(rows, tree, [np.array([0, 4])], openfabmap())
    assert result.probabilities.shape == (3, 3)
    np.testing.assert_allclose(result.probabilities.sum(axis=1), 1.0)
    # An empty query scores every place by its default; an empty place scores 0 (relative scale).
    assert result.log_likelihoods[2, 1] == 0.0
    assert np.argmax(result.probabilities[2, :2]) == 0


def test_input_errors_are_clear():
    rng = np.random.default_rng(0)
    tree = _random_tree(rng, 8)
    config = openfabmap()
    samples = [np.array([1])]
    with pytest.raises(DataError, match="word id 8 out of range for a vocabulary of 8"):
        fabmap_score_matrices([np.array([1, 8])], tree, samples, config)
    with pytest.raises(DataError, match="word id -1 out of range"):
        fabmap_score_matrices([np.array([-1, 2])], tree, samples, config)
    with pytest.raises(DataError, match="9 words per row but the vocabulary has 8"):
        fabmap_score_matrices(sp.csr_matrix((2, 9)), tree, samples, config)
    with pytest.raises(DataError, match="9 words per row but the vocabulary has 8"):
        fabmap_score_matrices([np.array([1])], tree, sp.csr_matrix((2, 9)), config)
    with pytest.raises(DataError, match="integers"):
        fabmap_score_matrices([np.array([1.5])], tree, samples, config)
    with pytest.raises(ConfigError, match="method = 'fabmap3'"):
        fabmap_score_matrices([np.array([1])], tree, samples, config, method="fabmap3")
    with pytest.raises(DataError, match="exclude_samples has 2 entries for 1"):
        fabmap_score_matrices([np.array([1])], tree, samples, config, exclude_samples=[0, 0])
