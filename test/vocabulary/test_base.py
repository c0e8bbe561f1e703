"""Tests for vocabularies: k-means, the autoencoder quantizer, bag-of-words (vocabulary/base.py,
vocabulary/kmeans.py, vocabulary/autoencoder.py)."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from sklearn.metrics import normalized_mutual_info_score

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.vocabulary import autoencoder, conv_encoder
from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer
from aefabmap_ros.vocabulary.autoencoder_network import (
    ConvAutoencoder,
    MlpAutoencoder,
    student_t,
    target_distribution,
)
from aefabmap_ros.vocabulary.autoencoder_training import cosine_rate
from aefabmap_ros.vocabulary.base import (
    Quantizer,
    VocabularyConfig,
    bag_of_words,
    train_vocabulary,
    word_usage,
)
from aefabmap_ros.vocabulary.kmeans import KMeansQuantizer
from aefabmap_ros.vocabulary.kmeans_training import kmeans, reseed_empty
from aefabmap_ros.vocabulary.training_checkpoint import CHECKPOINT_NAME, Checkpoint

K_TRUE = 8


def _blobs(n_per: int = 250, dim: int = 128, seed: int = 0, spread: float = 6.0) -> tuple[np.ndarray, np.ndarray,
                                                                                           np.ndarray]:
    """SIFT-like non-negative descriptors around K_TRUE well-separated centres."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 120, (K_TRUE, dim)).astype(np.float32)
    labels = np.repeat(np.arange(K_TRUE), n_per)
    x = centres[labels] + rng.normal(0, spread, (labels.size, dim)).astype(np.float32)
    order = rng.permutation(labels.size)
    return np.maximum(x[order], 0).astype(np.float32), labels[order], centres


def _small_ae(**overrides: object) -> VocabularyConfig:
    values: dict[str, object] = dict(kind="autoencoder", size=K_TRUE, pca_dim=16, ae_embedding_dim=8,
                                     ae_epochs=6, ae_batch_size=64, num_threads=1, seed=0)
    values.update(overrides)
    return VocabularyConfig(**values)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def blobs() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return _blobs()


@pytest.fixture(scope="module")
def ae_quantizer(blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Quantizer:
    return train_vocabulary(blobs[0], _small_ae(), progress=False)


def test_kmeans_recovers_known_clusters(blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    x, labels, centres = blobs
    quantizer = train_vocabulary(x, VocabularyConfig(kind="kmeans", size=K_TRUE, seed=1), progress=False)
    assert isinstance(quantizer, Quantizer) and quantizer.kind == "kmeans" and quantizer.size == K_TRUE
    words = quantizer.quantize(x)
    assert words.dtype == np.int64 and words.shape == (x.shape[0],)
    assert normalized_mutual_info_score(labels, words) > 0.9
    # The word of each true centre is the word its cluster's descriptors get.
    for k in range(K_TRUE):
        assert quantizer.quantize(centres[k:k + 1])[0] == np.bincount(words[labels == k]).argmax()
    assert quantizer.centroids.shape == (K_TRUE, 128) and quantizer.centroids.dtype == np.float32


@pytest.fixture(scope="module")
def conv_quantizer(blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Quantizer:
    """The paper's convolutional network and a student distilled from it."""
    return train_vocabulary(blobs[0], _small_ae(ae_network="conv", ae_student_hidden=32), progress=False)


@pytest.mark.parametrize("network", ["mlp", "conv"])
def test_autoencoder_recovers_known_clusters(blobs: tuple[np.ndarray, np.ndarray, np.ndarray], network: str,
                                             request: pytest.FixtureRequest) -> None:
    x, labels, centres = blobs
    ae_quantizer = request.getfixturevalue("ae_quantizer" if network == "mlp" else "conv_quantizer")
    assert isinstance(ae_quantizer, AutoencoderQuantizer) and ae_quantizer.kind == "autoencoder"
    words = ae_quantizer.quantize(x)
    assert words.dtype == np.int64 and words.shape == (x.shape[0],)
    assert normalized_mutual_info_score(labels, words) > 0.9
    for k in range(K_TRUE):
        assert ae_quantizer.quantize(centres[k:k + 1])[0] == np.bincount(words[labels == k]).argmax()
    # Descriptor-space centroids = mean of each word's descriptors (paper eq. 3), close to the true centres.
    centroids = ae_quantizer.centroids
    assert centroids.shape == (K_TRUE, 128) and np.all(np.isfinite(centroids))
    for word in range(K_TRUE):
        np.testing.assert_allclose(centroids[word], x[words == word].mean(axis=0), rtol=1e-4, atol=1e-3)


def test_autoencoder_word_of_a_training_cluster_centre(ae_quantizer: Quantizer,
                                                       blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    # Quantizing a word's own descriptor-space centroid returns that word.
    centroids = ae_quantizer.centroids
    np.testing.assert_array_equal(ae_quantizer.quantize(centroids), np.arange(K_TRUE))


def test_soft_assignment_rows_are_distributions(ae_quantizer: Quantizer,
                                                blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    assert isinstance(ae_quantizer, AutoencoderQuantizer)
    q = ae_quantizer.soft_assign(blobs[0][:50])
    assert q.shape == (50, K_TRUE)
    np.testing.assert_allclose(q.sum(axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(q.argmax(axis=1), ae_quantizer.quantize(blobs[0][:50]))


def test_network_quantizes_each_row_whatever_the_batch(blobs: tuple[np.ndarray, np.ndarray, np.ndarray],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The paper's convolutional network (the setting without an MLP encoder) quantizes in numpy, in chunks of
    rows: a row's word does not depend on the rows quantized with it, nor on where the chunks end."""
    network = train_vocabulary(blobs[0], _small_ae(ae_network="conv", ae_student_hidden=0, ae_epochs=1),
                               progress=False)
    assert isinstance(network, AutoencoderQuantizer) and network.network is not None and network.encoder is None
    whole = network.quantize(blobs[0])
    monkeypatch.setattr(autoencoder, "QUANTIZE_BATCH", 300)
    monkeypatch.setattr(conv_encoder, "EMBED_ROWS", 7)
    np.testing.assert_array_equal(network.quantize(blobs[0]), whole)
    for n in (1, 255, 257, 600):
        np.testing.assert_array_equal(network.quantize(blobs[0][:n]), whole[:n])
        np.testing.assert_array_equal(network.soft_assign(blobs[0][:n]).argmax(axis=1), whole[:n])


def test_empty_input_gives_empty_words(ae_quantizer: Quantizer) -> None:
    assert ae_quantizer.quantize(np.zeros((0, 128), np.float32)).shape == (0,)
    km = KMeansQuantizer(np.eye(4, 128, dtype=np.float32), 128, binary=False)
    assert km.quantize(np.zeros((0, 128), np.float32)).dtype == np.int64


def test_quantize_refuses_wrong_shapes_and_dtypes(ae_quantizer: Quantizer) -> None:
    with pytest.raises(DataError, match=r"expected \(N, 128\) descriptors, got shape \(3, 64\)"):
        ae_quantizer.quantize(np.zeros((3, 64), np.float32))
    with pytest.raises(DataError, match="binary"):
        ae_quantizer.quantize(np.zeros((3, 128), np.uint8))


def test_training_is_deterministic_given_seed(blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    x = blobs[0][:600]
    config = _small_ae(ae_epochs=2)
    a = train_vocabulary(x, config, progress=False)
    b = train_vocabulary(x, config, progress=False)
    assert isinstance(a, AutoencoderQuantizer) and isinstance(b, AutoencoderQuantizer)
    np.testing.assert_array_equal(a.embedding_centres, b.embedding_centres)
    np.testing.assert_array_equal(a.quantize(x), b.quantize(x))
    k1 = train_vocabulary(x, VocabularyConfig(kind="kmeans", size=8, seed=3))
    k2 = train_vocabulary(x, VocabularyConfig(kind="kmeans", size=8, seed=3))
    np.testing.assert_array_equal(k1.centroids, k2.centroids)


def test_interrupted_training_resumes_from_checkpoint(blobs: tuple[np.ndarray, np.ndarray, np.ndarray],
                                                      tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    x = blobs[0][:600]
    config = _small_ae(ae_epochs=3)
    reference = train_vocabulary(x, config, progress=False)
    assert isinstance(reference, AutoencoderQuantizer)

    real_save = Checkpoint.save
    calls: list[int] = []

    def save_then_interrupt(self: object, stage: str, epoch: int, *args: object, **kwargs: object) -> None:
        real_save(self, stage, epoch, *args, **kwargs)  # type: ignore[arg-type]
        calls.append(epoch)
        if epoch == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(Checkpoint, "save", save_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        train_vocabulary(x, config, progress=False, work_dir=tmp_path)
    assert (tmp_path / CHECKPOINT_NAME).exists()
    monkeypatch.setattr(Checkpoint, "save", real_save)
    resumed = train_vocabulary(x, config, progress=False, work_dir=tmp_path)
    assert isinstance(resumed, AutoencoderQuantizer)
    # Epochs 0-1 came from the checkpoint, epoch 2 ran again: the result is the uninterrupted one.
    np.testing.assert_allclose(resumed.embedding_centres, reference.embedding_centres, rtol=1e-5, atol=1e-5)
    assert not (tmp_path / CHECKPOINT_NAME).exists()  # removed once training completed


def test_corrupt_checkpoint_is_reported(blobs: tuple[np.ndarray, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    (tmp_path / CHECKPOINT_NAME).write_bytes(b"garbage")
    with pytest.raises(ModelError, match="cannot read training checkpoint"):
        train_vocabulary(blobs[0][:200], _small_ae(ae_epochs=1), progress=False, work_dir=tmp_path)


def test_refinement_runs_and_keeps_every_word(blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    x, labels, _ = blobs
    config = _small_ae(refine=True, refine_epochs=2, refine_update_interval=5, ae_epochs=4)
    quantizer = train_vocabulary(x, config, progress=False)
    words = quantizer.quantize(x)
    assert normalized_mutual_info_score(labels, words) > 0.9
    assert np.all(np.bincount(words, minlength=K_TRUE) > 0)


def test_match_term_needs_pairs_and_uses_them(blobs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    x, labels, _ = blobs
    with pytest.raises(DataError, match="needs matched descriptor pairs"):
        train_vocabulary(x, _small_ae(ae_match_weight=1.0), progress=False)
    with pytest.raises(DataError, match="pairs must be"):
        train_vocabulary(x, _small_ae(), progress=False, pairs=np.array([[0, x.shape[0]]]))
    # Pairs within the same true cluster: the term pulls them together; clusters stay recovered.
    rng = np.random.default_rng(0)
    a = rng.integers(0, x.shape[0], 3000)
    same = np.array([rng.choice(np.flatnonzero(labels == labels[i])) for i in a])
    quantizer = train_vocabulary(x, _small_ae(ae_match_weight=1.0), progress=False,
                                 pairs=np.stack([a, same], axis=1))
    assert normalized_mutual_info_score(labels, quantizer.quantize(x)) > 0.9


def test_binary_descriptors_cluster_on_bits() -> None:
    rng = np.random.default_rng(5)
    prototypes = rng.integers(0, 2, (4, 256), dtype=np.uint8)
    labels = np.repeat(np.arange(4), 100)
    bits = prototypes[labels] ^ (rng.random((400, 256)) < 0.05).astype(np.uint8)
    descriptors = np.packbits(bits, axis=1)
    for kind, extra in (("kmeans", {}), ("autoencoder", {"pca_dim": 16, "ae_embedding_dim": 8, "ae_epochs": 6,
                                                        "ae_batch_size": 32})):
        quantizer = train_vocabulary(descriptors, VocabularyConfig(kind=kind, size=4, **extra),  # type: ignore[arg-type]
                                     progress=False)
        assert normalized_mutual_info_score(labels, quantizer.quantize(descriptors)) > 0.9
        centroids = quantizer.centroids
        assert centroids.shape == (4, 32) and centroids.dtype == np.float32
        # Binary centres are the packed majority bits: the prototypes themselves.
        assert {tuple(row) for row in centroids.astype(np.uint8)} == {tuple(p) for p in np.packbits(prototypes, 1)}


def test_reseed_empty_fills_dead_centres() -> None:
    x, _, _ = _blobs(n_per=50)
    centres = np.concatenate([kmeans(x, 6, seed=0), np.full((2, 128), 1e4, np.float32)])  # two dead centres
    fixed = reseed_empty(x, centres, np.random.default_rng(0))
    counts = np.bincount(KMeansQuantizer(fixed, 128, False).quantize(x), minlength=8)
    assert np.all(counts > 0)


def test_student_t_and_target_distribution_match_formulas() -> None:
    z = torch.tensor([[0.0, 0.0], [1.0, 2.0]])
    mu = torch.tensor([[0.0, 0.0], [3.0, 0.0]])
    q = student_t(z, mu)
    raw = np.array([[1.0, 1 / (1 + 9)], [1 / (1 + 5), 1 / (1 + 8)]])
    np.testing.assert_allclose(q.numpy(), raw / raw.sum(1, keepdims=True), rtol=1e-6)
    p = target_distribution(q).numpy()
    qn = q.numpy()
    w = qn**2 / qn.sum(0)
    np.testing.assert_allclose(p, w / w.sum(1, keepdims=True), rtol=1e-6)


def test_numpy_soft_assignment_is_the_torch_one() -> None:
    rng = np.random.default_rng(0)
    z, mu = rng.normal(size=(40, 6)).astype(np.float32), rng.normal(size=(9, 6)).astype(np.float32)
    for alpha in (1.0, 2.5):
        expected = student_t(torch.from_numpy(z), torch.from_numpy(mu), alpha).numpy()
        np.testing.assert_allclose(autoencoder.student_t(z, mu, alpha), expected, rtol=1e-5, atol=1e-7)


def test_autoencoder_shapes_and_finite_output() -> None:
    torch.manual_seed(0)
    net = ConvAutoencoder(64, 32)
    x = torch.rand(5, 64)
    z, logits = net(x)
    assert z.shape == (5, 32) and logits.shape == (5, 64)
    assert torch.isfinite(z).all() and torch.isfinite(logits).all()
    with pytest.raises(ConfigError, match="pca_dim=30 must be a multiple of 4"):
        ConvAutoencoder(30, 8)
    with pytest.raises(ConfigError, match="ae_embedding_dim=0"):
        ConvAutoencoder(16, 0)


def test_mlp_autoencoder_quantizes_with_exactly_its_trained_encoder() -> None:
    torch.manual_seed(0)
    net = MlpAutoencoder(16, 32, 8).eval()
    x = torch.rand(50, 16)
    z, logits = net(x)
    assert z.shape == (50, 8) and logits.shape == (50, 16)
    # The numpy encoder that quantizes is the same function: relu(x W1 + b1) W2 + b2, computed by hand.
    p = {name: value.detach().numpy() for name, value in net.encoder.named_parameters()}
    by_hand = np.maximum(x.numpy() @ p["0.weight"].T + p["0.bias"], 0) @ p["2.weight"].T + p["2.bias"]
    np.testing.assert_allclose(net.numpy_encoder().embed(x.numpy()), by_hand, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(z.detach().numpy(), by_hand, rtol=1e-5, atol=1e-6)
    with pytest.raises(ConfigError, match="ae_mlp_hidden=0"):
        MlpAutoencoder(16, 0, 8)
    with pytest.raises(ConfigError, match="ae_embedding_dim=0"):
        MlpAutoencoder(16, 8, 0)


def test_cosine_rate_falls_from_the_base_rate_to_zero() -> None:
    assert cosine_rate(1e-3, 0, 100) == pytest.approx(1e-3)
    assert cosine_rate(1e-3, 25, 100) == pytest.approx(1e-3 * (1 + np.sqrt(0.5)) / 2)
    assert cosine_rate(1e-3, 50, 100) == pytest.approx(5e-4)
    assert cosine_rate(1e-3, 100, 100) == pytest.approx(0.0, abs=1e-18)


@pytest.mark.parametrize(("field", "value", "match"), [
    ("kind", "vlad", "kind='vlad' is not one of autoencoder, kmeans"),
    ("size", 1, "size=1 must be >= 2"),
    ("pca_dim", 30, "pca_dim=30 must be a multiple of 4"),
    ("ae_learning_rate", 0.0, "ae_learning_rate=0.0"),
    ("ae_network", "transformer", "ae_network='transformer' must be one of mlp, conv"),
    ("ae_mlp_hidden", 0, "ae_mlp_hidden=0 must be >= 1"),
    ("tol", 1.0, r"tol=1.0 must be in \[0, 1\)"),
])
def test_config_validation_names_field(field: str, value: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        VocabularyConfig(**{field: value})  # type: ignore[arg-type]


def test_config_round_trip() -> None:
    config = VocabularyConfig(kind="kmeans", size=321, refine=True)
    assert VocabularyConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ConfigError, match="unknown field"):
        VocabularyConfig.from_dict({"sise": 3})


def test_train_vocabulary_refuses_bad_input() -> None:
    with pytest.raises(DataError, match=r"needs \(N, D\) descriptors"):
        train_vocabulary(np.zeros(10, np.float32), VocabularyConfig(kind="kmeans", size=2))
    with pytest.raises(DataError, match="needs at least that many"):
        train_vocabulary(np.zeros((5, 8), np.float32), VocabularyConfig(kind="kmeans", size=10))
    with pytest.raises(DataError, match="NaN"):
        train_vocabulary(np.full((20, 8), np.nan, np.float32), VocabularyConfig(kind="kmeans", size=2))
    with pytest.raises(DataError, match="must be float32/float64 or uint8"):
        train_vocabulary(np.zeros((20, 8), np.int32), VocabularyConfig(kind="kmeans", size=2))


def test_bag_of_words_sorted_unique_counts() -> None:
    ids, counts = bag_of_words(np.array([5, 1, 5, 3, 5, 1]), 10)
    np.testing.assert_array_equal(ids, [1, 3, 5])
    np.testing.assert_array_equal(counts, [2, 1, 3])
    assert ids.dtype == np.uint32 and counts.dtype == np.uint32
    empty_ids, empty_counts = bag_of_words(np.zeros(0, np.int64), 10)
    assert empty_ids.shape == (0,) and empty_counts.shape == (0,)
    with pytest.raises(DataError, match=r"in \[0, 10\), got range \[0, 10\]"):
        bag_of_words(np.array([0, 10]), 10)
    with pytest.raises(DataError, match="1-D"):
        bag_of_words(np.zeros((2, 2), np.int64), 10)
    with pytest.raises(DataError, match="integers"):
        bag_of_words(np.array([0.5]), 10)


@pytest.fixture(scope="module")
def real_descriptors() -> np.ndarray:
    from test.conftest import require_shared

    rtabmap_dir = require_shared("datasets", "rtabmap_samples")
    config = FeatureConfig(max_features=300)
    paths = sorted((rtabmap_dir / "images").glob("*.jpg"), key=lambda p: int(p.stem))[::3]
    chunks = []
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert image is not None
        chunks.append(extract_features(image, config).descriptors)
    return np.concatenate(chunks)


@pytest.mark.parametrize("kind", ["kmeans", "autoencoder"])
def test_real_images_use_most_words_evenly(real_descriptors: np.ndarray, kind: str) -> None:
    descriptors = real_descriptors
    config = VocabularyConfig(kind=kind, size=150, ae_epochs=3, num_threads=1)
    quantizer = train_vocabulary(descriptors, config, progress=False)
    usage = word_usage(quantizer, descriptors)
    assert usage.sum() == descriptors.shape[0]
    assert (usage > 0).mean() > 0.95
    assert usage.max() / usage.sum() < 0.03  # no word takes more than a few percent
