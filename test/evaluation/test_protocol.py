"""evaluation.protocol: FAB-MAP posterior matrices against openFABMAP and an independent renormalisation,
tf-idf scores, recordings, reports and every error path."""

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.special import logsumexp

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.evaluation.metrics import evaluate_scores
from aefabmap_ros.evaluation.protocol import (
    EvaluationConfig,
    MethodResult,
    evaluate_model,
    fabmap_evaluation_config,
    fabmap_posterior_matrix,
    leave_one_out_samples,
    model_tree,
    tfidf_matrix,
    verified_result,
)
from aefabmap_ros.evaluation.tfidf import tfidf_score_matrix
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.features.extraction import FeatureConfig, Features
from aefabmap_ros.model.directory import Model
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.vocabulary.base import VocabularyConfig
from aefabmap_ros.vocabulary.kmeans_training import train_kmeans_quantizer
from test.conftest import require_shared
from test.fabmap.oracles import fabmap_score_matrices

openfabmap = FabMapConfig.openfabmap  # openFABMAP's semantics: the golden references' config



@pytest.fixture(scope="module")
def golden():
    directory = require_shared("golden", "openfabmap_rtab")
    from aefabmap_ros.fabmap.openfabmap import read_bow, read_chow_liu_tree

    return SimpleNamespace(
        tree=read_chow_liu_tree(directory / "tree.yml"),
        train=sp.csr_matrix(read_bow(directory / "bowtrain.yml") > 0),
        test=sp.csr_matrix(read_bow(directory / "bowtest.yml") > 0),
        probabilities=np.loadtxt(directory / "fabmap2_sampled.probabilities.txt"),
        loglik=np.loadtxt(directory / "fabmap2_sampled.loglik.txt"),
    )


def random_tree_and_bow(seed=0, frames=30, words=40):
    rng = np.random.default_rng(seed)
    bow = (rng.random((frames, words)) < 0.2).astype(np.float64)
    parent = np.arange(words)
    parent[1:] = rng.integers(0, np.arange(1, words))  # parents precede children: a tree
    marginal = np.clip(bow.mean(axis=0), 0.05, 0.95)
    matrix = np.vstack([parent, marginal, np.full(words, 0.6), np.full(words, 0.1)])
    return ChowLiuTree.from_matrix(matrix), sp.csr_matrix(bow)


# ------------------------------------------------------------------------------------------ FAB-MAP


def test_posterior_without_exclusion_reproduces_openfabmap(golden):
    # openFABMAP recognises every frame, also its two blank ones (min_words=0).
    scores, new_place = fabmap_posterior_matrix(golden.test, golden.tree, golden.train, openfabmap(min_words=0), 0)
    lower = np.tril(np.ones(scores.shape, dtype=bool), -1)
    np.testing.assert_allclose(scores[lower], golden.probabilities[lower], atol=1e-5)  # file: 6 digits
    np.testing.assert_allclose(new_place, np.diag(golden.probabilities), atol=1e-5)
    assert np.all(scores[~lower] == 0)
    # The golden README's figures: recall 0.57 at 100 % precision, AP 0.87 (min gap 10).
    gt = np.load(require_shared("datasets", "rtabmap_samples", "loop_gt.npz"))["gt"]
    metrics = evaluate_scores(scores, gt, 10, 0.99)
    assert metrics.recall_at_100_precision == pytest.approx(25 / 44)
    assert metrics.average_precision == pytest.approx(0.85, abs=0.03)


def test_blank_frames_are_neither_queries_nor_places(golden):
    """Independent reference: openFABMAP's log-likelihoods, softmax over {new} + the non-blank earlier frames."""
    scores, new_place = fabmap_posterior_matrix(golden.test, golden.tree, golden.train, openfabmap(), 0)
    blank = np.flatnonzero(np.asarray(golden.test.sum(axis=1)).ravel() == 0)
    assert blank.tolist() == [18, 45]  # the golden README's two frames without keypoints
    assert np.all(scores[blank] == 0) and np.all(scores[:, blank] == 0) and np.all(np.isnan(new_place[blank]))
    for i in (1, 19, 20, 46, 60, 83):
        kept = np.setdiff1d(np.arange(i), blank)
        hypotheses = np.r_[golden.loglik[i, i], golden.loglik[i, kept]]
        p = np.exp(hypotheses - logsumexp(hypotheses))
        p = 0.99 * p + 0.01 / p.size
        assert new_place[i] == pytest.approx(p[0], rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(scores[i, kept], p[1:], rtol=1e-9, atol=1e-12)
    # openFABMAP's most confident false loop is blank frame 45 -> blank frame 18; without the blank
    # frames, recall at 100 % precision rises from 25/44 to 33/44.
    gt = np.load(require_shared("datasets", "rtabmap_samples", "loop_gt.npz"))["gt"]
    assert evaluate_scores(scores, gt, 10, 0.99).recall_at_100_precision == pytest.approx(33 / 44)


@pytest.mark.parametrize("exclude", [1, 9])
def test_posterior_with_exclusion_renormalises_over_older_places(golden, exclude):
    """Independent reference: openFABMAP's log-likelihoods, softmax over {new} + {j < i - N}, smoothing."""
    config = openfabmap(min_words=0)
    scores, new_place = fabmap_posterior_matrix(golden.test, golden.tree, golden.train, config, exclude)
    for i in (0, 5, exclude, exclude + 1, 40, 83):
        kept = np.arange(max(i - exclude, 0))
        hypotheses = np.r_[golden.loglik[i, i], golden.loglik[i, kept]]
        p = np.exp(hypotheses - logsumexp(hypotheses))
        p = 0.99 * p + 0.01 / p.size
        assert new_place[i] == pytest.approx(p[0], rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(scores[i, kept], p[1:], rtol=1e-9, atol=1e-12)
        assert np.all(scores[i, max(i - exclude, 0):] == 0)
        assert scores[i].sum() + new_place[i] == pytest.approx(1.0)


def test_leave_one_out_matches_fabmap_score_matrices():
    tree, bow = random_tree_and_bow()
    exclude = leave_one_out_samples(bow.shape[0], np.arange(bow.shape[0]))
    assert exclude.tolist() == list(range(bow.shape[0]))
    scores, new_place = fabmap_posterior_matrix(bow, tree, bow, openfabmap(), 0, exclude.tolist())
    reference = fabmap_score_matrices(bow, tree, bow, openfabmap(), exclude_samples=exclude.tolist())
    lower = np.tril(np.ones(scores.shape, dtype=bool), -1)
    np.testing.assert_allclose(scores[lower], reference.probabilities[lower], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(new_place, np.diag(reference.probabilities), rtol=1e-10)
    # Without leaving out, the query's own sample raises its new-place probability.
    _, with_self = fabmap_posterior_matrix(bow, tree, bow, openfabmap(), 0)
    assert np.all(with_self[1:] >= new_place[1:] - 1e-12) and np.any(with_self > new_place + 1e-6)


def test_leave_one_out_with_a_subsample_of_frames():
    assert leave_one_out_samples(5, np.array([0, 2, 4])).tolist() == [0, -1, 1, -1, 2]
    with pytest.raises(DataError, match=r"sample frames must lie in \[0, 5\)"):
        leave_one_out_samples(5, np.array([0, 5]))


def test_evaluation_config_fixes_what_the_protocol_needs():
    config = fabmap_evaluation_config(
        openfabmap(add_policy="new_only", keyframe_min_frames=3, exclude_recent_seconds=2.0, top_k=5,
                     p_z_given_e=0.3, keyframe_max_seconds=1.0, exclude_linked_overlap=0.2, consistency_matches=3,
                     likelihood_temperature=3.0), 4)
    assert (config.add_policy, config.keyframe_min_frames, config.exclude_recent_seconds) == ("all", 1, 0.0)
    assert (config.keyframe_max_seconds, config.exclude_linked_overlap, config.consistency_matches) == (0.0, 0.0, 1)
    assert config.exclude_recent_frames == 4 and config.p_z_given_e == 0.3
    assert config.likelihood_temperature == 3.0  # the posterior is the node's, only the protocol's policies change
    with pytest.raises(ConfigError, match="exclude_recent_frames=-1"):
        fabmap_evaluation_config(openfabmap(), -1)


def test_fabmap_matrix_errors():
    tree, bow = random_tree_and_bow()
    with pytest.raises(DataError, match="observations have 39 words"):
        fabmap_posterior_matrix(bow[:, :39], tree, bow, openfabmap(), 0)
    with pytest.raises(DataError, match="exclude_samples has 2 entries for 30 frames"):
        fabmap_posterior_matrix(bow, tree, bow, openfabmap(), 0, [0, 1])


# ------------------------------------------------------------------------------------ methods, models


def test_tfidf_matrix_is_core_tfidf():
    rng = np.random.default_rng(1)
    counts = sp.csr_matrix(rng.poisson(0.5, (12, 20)).astype(float))
    source = sp.csr_matrix(rng.random((7, 20)) < 0.3)
    np.testing.assert_array_equal(tfidf_matrix(counts, source), tfidf_score_matrix(counts, source))


@pytest.mark.parametrize(("values", "message"), [
    ({"min_gap": 0}, "min_gap=0"),
    ({"threshold": 1.5}, "threshold=1.5"),
    ({"bow_threshold": -0.1}, "bow_threshold=-0.1"),
    ({"fabmap_exclude_recent": -2}, "fabmap_exclude_recent=-2"),
    ({"verify_more_candidates": -1}, "verify_more_candidates=-1"),
    ({"verify_more_candidates": 1.0}, "verify_more_candidates=1.0"),
])
def test_evaluation_config_errors(values, message):
    with pytest.raises(ConfigError, match=message):
        EvaluationConfig(**values)


def test_evaluation_config_exclusion_window():
    assert EvaluationConfig(min_gap=7).fabmap_exclusion_frames == 0
    assert EvaluationConfig(min_gap=7, fabmap_exclude_recent=-1).fabmap_exclusion_frames == 6
    assert EvaluationConfig(fabmap_exclude_recent=3).fabmap_exclusion_frames == 3


def small_model_and_features(seed=0, frames=24):
    """A k-means model whose words are the descriptors' clusters; frames revisit after `frames // 2`."""
    rng = np.random.default_rng(seed)
    centres = rng.random((30, 8)).astype(np.float32) * 10
    half = frames // 2
    place_words = [rng.choice(30, size=6, replace=False) for _ in range(half)]
    features = []
    for i in range(frames):
        words = place_words[i % half]
        descriptors = centres[words] + rng.normal(0, 0.05, (6, 8)).astype(np.float32)
        features.append(Features(np.zeros((6, 5), np.float32), descriptors.astype(np.float32), "sift"))
    training = np.concatenate([centres + rng.normal(0, 0.05, (30, 8)).astype(np.float32) for _ in range(20)])
    quantizer = train_kmeans_quantizer(training, 30, 0, 10, 256)
    bow = sp.csr_matrix(rng.random((40, 30)) < 0.2, dtype=np.float64)
    tree = np.vstack([np.arange(30), np.full(30, 0.2), np.full(30, 0.2), np.full(30, 0.2)])
    model = Model.create(FeatureConfig(), VocabularyConfig(kind="kmeans", size=30), quantizer, tree_matrix=tree,
                         new_place_samples=bow)
    gt = np.zeros((frames, frames), np.uint8)
    gt[np.arange(half, frames), np.arange(half)] = 1
    return model, features, gt


def test_evaluate_model_finds_exact_revisits():
    model, features, gt = small_model_and_features()
    results = evaluate_model(model, features, gt, ("FABMAP2", "BoW"), EvaluationConfig(min_gap=3), openfabmap())
    assert [r.name for r in results] == ["FABMAP2", "BoW"]
    for result in results:
        assert result.scores.shape == (24, 24) and np.all((result.scores >= 0) & (result.scores <= 1 + 1e-12))
        assert result.metrics.num_positive_queries == 12
        assert result.metrics.recall_at_100_precision == 1.0  # every revisit has identical words
        assert result.vocabulary_kind == "kmeans" and result.vocabulary_id == model.vocabulary_id
    assert results[0].new_place is not None and results[1].new_place is None
    assert results[0].metrics.threshold == 0.99 and results[1].metrics.threshold == EvaluationConfig().bow_threshold


def test_evaluate_model_errors():
    model, features, gt = small_model_and_features()
    with pytest.raises(ConfigError, match="AE-FABMAP needs a autoencoder vocabulary"):
        evaluate_model(model, features, gt, ("AE-FABMAP",), EvaluationConfig(), openfabmap())
    with pytest.raises(ConfigError, match="unknown method 'X'"):
        evaluate_model(model, features, gt, ("X",), EvaluationConfig(), openfabmap())
    with pytest.raises(DataError, match="23 test frames but the ground truth is 24x24"):
        evaluate_model(model, features[:-1], gt, ("BoW",), EvaluationConfig(), openfabmap())
    model.tree_matrix = None
    with pytest.raises(ModelError, match="has no Chow-Liu tree"):
        model_tree(model)


def test_gv_rows_search_past_the_best_candidates_only_when_they_all_fail():
    """Query 3's true place 0 is FAB-MAP's third: with 2 candidates the "+ GV" row misses it, with 1 more it is
    found and keeps its own score (the best accepted one's); query 2's best candidate passes, so its deeper
    candidate is never verified."""
    from test.verification.test_reranking import FakeVerifier

    scores = np.zeros((4, 4))
    scores[3, :3] = [0.1, 0.2, 0.3]
    scores[2, :2] = [0.4, 0.5]
    gt = np.zeros((4, 4), np.uint8)
    gt[3, 0] = gt[2, 1] = 1
    result = MethodResult(name="AE-FABMAP", vocabulary_kind="autoencoder", vocabulary_size=4, vocabulary_id="v",
                          scores=scores, metrics=evaluate_scores(scores, gt, 1, 0.99), seconds=0.0)
    verify = FakeVerifier({(3, 0), (2, 1), (2, 0)})
    shallow = verified_result(result, (VerificationConfig(candidates=2), verify), gt, 1)
    assert shallow.scores[3].sum() == 0.0 and shallow.metrics.recall_at_100_precision == 0.5
    verify.calls.clear()
    deep = verified_result(result, (VerificationConfig(candidates=1), verify), gt, 1, more_candidates=2)
    assert deep.scores[3, 0] == 0.1 and deep.scores[2, 1] == 0.5 and deep.metrics.recall_at_100_precision == 1.0
    assert (2, 0) not in verify.calls and verify.calls[-3:] == [(3, 2), (3, 1), (3, 0)]
