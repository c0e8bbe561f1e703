"""Tests for the encoder distilled from the autoencoder (aefabmap_ros/vocabulary/distilled.py) and its use by
the autoencoder quantizer (vocabulary/autoencoder.py)."""

import numpy as np
import pytest
import torch

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer
from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary
from aefabmap_ros.vocabulary.distilled import CentreSearch, StudentEncoder, student_network

K = 8
DIM = 128


def _clustered(n_per: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """SIFT-like descriptors around K fixed well-separated centres (the same centres for every seed)."""
    centres = np.random.default_rng(100).uniform(0, 120, (K, DIM))
    rng = np.random.default_rng(seed)
    labels = rng.permutation(np.repeat(np.arange(K), n_per))
    x = np.maximum(centres[labels] + rng.normal(0, 8.0, (labels.size, DIM)), 0).astype(np.float32)
    return x, labels


def _config(**overrides: object) -> VocabularyConfig:
    values: dict[str, object] = dict(size=K, pca_dim=16, ae_embedding_dim=8, ae_epochs=6, ae_batch_size=64,
                                     num_threads=1, seed=0, ae_student_hidden=32, ae_student_epochs=20)
    values.update(overrides)
    return VocabularyConfig(**values)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def trained() -> AutoencoderQuantizer:
    quantizer = train_vocabulary(_clustered(250, seed=0)[0], _config(), progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer)
    return quantizer


def test_numpy_forward_pass_equals_torch() -> None:
    torch.manual_seed(3)
    network = student_network(16, 24, 8).eval()
    student = StudentEncoder.from_torch(network)
    x = np.random.default_rng(0).random((300, 16), dtype=np.float32)
    with torch.no_grad():
        expected = network(torch.from_numpy(x)).numpy()
    got = student.embed(x)
    assert got.dtype == np.float32 and got.shape == (300, 8)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
    with_one = student.embed_with_one(x)
    np.testing.assert_allclose(with_one[:, :8], expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(with_one[:, 8], 1.0)
    # The hidden layer's ReLU matters on these inputs (a network without it would not match).
    assert np.any(network[0](torch.from_numpy(x)).detach().numpy() < 0)


def test_centre_search_is_brute_force_nearest() -> None:
    rng = np.random.default_rng(1)
    z, centres = rng.normal(size=(500, 6)).astype(np.float32), rng.normal(size=(40, 6)).astype(np.float32)
    brute = ((z[:, None, :].astype(np.float64) - centres[None]) ** 2).sum(axis=2).argmin(axis=1)
    got = CentreSearch(centres).nearest(np.concatenate([z, np.ones((500, 1), np.float32)], axis=1))
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, brute)


def test_quantize_is_nearest_centre_of_the_student_embedding(trained: AutoencoderQuantizer) -> None:
    assert trained.student is not None and trained.student.hidden_dim == 32
    x, _ = _clustered(50, seed=7)
    z = trained.student.embed(trained.pca.transform_scaled(x)).astype(np.float64)
    brute = ((z[:, None, :] - trained.embedding_centres[None].astype(np.float64)) ** 2).sum(axis=2).argmin(axis=1)
    np.testing.assert_array_equal(trained.quantize(x), brute)
    # embed and soft_assign use the same encoder as quantize.
    np.testing.assert_allclose(trained.embed(x), z, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(trained.soft_assign(x).argmax(axis=1), brute)
    # ... which is not the network's: its embeddings differ (the student only approximates them).
    assert not np.allclose(trained.with_student(None).embed(x), z, atol=1e-3)


def test_student_agrees_with_the_network_on_held_out_descriptors(trained: AutoencoderQuantizer) -> None:
    x, _ = _clustered(250, seed=11)  # not seen in training
    student_words = trained.quantize(x)
    network_words = trained.with_student(None).quantize(x)
    assert np.mean(student_words == network_words) >= 0.98
    assert trained.training_info["student_word_agreement"] >= 0.98
    assert trained.training_info["student_held_out_descriptors"] == 100  # 5 % of 2,000
    assert trained.training_info["student_hidden"] == 32
    # Both found the true clusters (agreement is not both being constant).
    assert len(np.unique(network_words)) == K


def test_untrained_student_disagrees(trained: AutoencoderQuantizer) -> None:
    """The agreement above is learnt: a student with random weights of the same shape gets few words right."""
    torch.manual_seed(0)
    random_student = StudentEncoder.from_torch(student_network(16, 32, 8))
    x, _ = _clustered(100, seed=12)
    agreement = np.mean(trained.with_student(random_student).quantize(x) == trained.with_student(None).quantize(x))
    assert agreement < 0.6


def test_network_setting_trains_no_student() -> None:
    quantizer = train_vocabulary(_clustered(100, seed=0)[0], _config(ae_student_hidden=0, ae_epochs=1),
                                 progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer) and quantizer.student is None
    assert "student_word_agreement" not in quantizer.training_info
    assert "student.npz" not in quantizer.other_files()


def test_distillation_is_deterministic_given_seed() -> None:
    x = _clustered(80, seed=0)[0]
    a, b = (train_vocabulary(x, _config(ae_epochs=1, ae_student_epochs=2), progress=False) for _ in range(2))
    assert isinstance(a, AutoencoderQuantizer) and isinstance(b, AutoencoderQuantizer)
    assert a.student is not None and b.student is not None
    for name, array in a.student.to_arrays().items():
        np.testing.assert_array_equal(array, b.student.to_arrays()[name])


def test_student_that_does_not_fit_is_refused(trained: AutoencoderQuantizer) -> None:
    torch.manual_seed(0)
    with pytest.raises(DataError, match="student encoder maps 12 -> 8 but the PCA gives 16"):
        trained.with_student(StudentEncoder.from_torch(student_network(12, 32, 8)))
    with pytest.raises(DataError, match=r"maps 16 -> 5 .* embedding has 8"):
        trained.with_student(StudentEncoder.from_torch(student_network(16, 32, 5)))
    with pytest.raises(DataError, match="do not chain"):
        StudentEncoder(np.zeros((16, 4)), np.zeros(4), np.zeros((5, 8)), np.zeros(8))
    with pytest.raises(DataError, match="b2 contains NaN"):
        StudentEncoder(np.zeros((16, 4)), np.zeros(4), np.zeros((4, 8)), np.full(8, np.nan))


@pytest.mark.parametrize(("field", "value"), [("ae_student_hidden", -1), ("ae_student_epochs", 0),
                                              ("ae_student_learning_rate", 0.0)])
def test_config_validation(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=f"{field}={value}"):
        VocabularyConfig(**{field: value})  # type: ignore[arg-type]
