"""Tests for the encoder distilled from the autoencoder (aefabmap_ros/vocabulary/distilled.py) and its use by
the autoencoder quantizer (vocabulary/autoencoder.py, vocabulary/autoencoder_training.py)."""

from collections.abc import Iterator

import numpy as np
import pytest
import torch

import aefabmap_ros.vocabulary.autoencoder_training as training_module
from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.vocabulary.autoencoder import ENCODER_FILE, AutoencoderQuantizer
from aefabmap_ros.vocabulary.autoencoder_training import _distill, noisy_copies
from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary
from aefabmap_ros.vocabulary.distilled import DistillOptions, distill_student, word_assignment_loss
from aefabmap_ros.vocabulary.mlp_encoder import CentreSearch, MlpEncoder, mlp_network

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
    values: dict[str, object] = dict(ae_network="conv", size=K, pca_dim=16, ae_embedding_dim=8, ae_epochs=6,
                                     ae_batch_size=64, num_threads=1, seed=0, ae_student_hidden=32,
                                     ae_student_epochs=20)
    values.update(overrides)
    return VocabularyConfig(**values)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def trained() -> AutoencoderQuantizer:
    quantizer = train_vocabulary(_clustered(250, seed=0)[0], _config(), progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer)
    return quantizer


def test_numpy_forward_pass_equals_torch() -> None:
    torch.manual_seed(3)
    network = mlp_network(16, 24, 8).eval()
    student = MlpEncoder.from_torch(network)
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
    assert trained.encoder is not None and trained.encoder.hidden_dim == 32
    x, _ = _clustered(50, seed=7)
    z = trained.encoder.embed(trained.pca.transform_scaled(x)).astype(np.float64)
    brute = ((z[:, None, :] - trained.embedding_centres[None].astype(np.float64)) ** 2).sum(axis=2).argmin(axis=1)
    np.testing.assert_array_equal(trained.quantize(x), brute)
    # embed and soft_assign use the same encoder as quantize.
    np.testing.assert_allclose(trained.embed(x), z, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(trained.soft_assign(x).argmax(axis=1), brute)
    # ... which is not the network's: its embeddings differ (the student only approximates them).
    assert not np.allclose(trained.with_encoder(None).embed(x), z, atol=1e-3)


def test_student_agrees_with_the_network_on_held_out_descriptors(trained: AutoencoderQuantizer) -> None:
    x, _ = _clustered(250, seed=11)  # not seen in training
    student_words = trained.quantize(x)
    network_words = trained.with_encoder(None).quantize(x)
    assert np.mean(student_words == network_words) >= 0.98
    assert trained.training_info["student_word_agreement"] >= 0.98
    assert trained.training_info["student_held_out_descriptors"] == 100  # 5 % of 2,000
    assert trained.training_info["student_hidden"] == 32
    # Both found the true clusters (agreement is not both being constant).
    assert len(np.unique(network_words)) == K


def test_untrained_student_disagrees(trained: AutoencoderQuantizer) -> None:
    """The agreement above is learnt: a student with random weights of the same shape gets few words right."""
    torch.manual_seed(0)
    random_student = MlpEncoder.from_torch(mlp_network(16, 32, 8))
    x, _ = _clustered(100, seed=12)
    agreement = np.mean(trained.with_encoder(random_student).quantize(x) == trained.with_encoder(None).quantize(x))
    assert agreement < 0.6


def test_network_setting_trains_no_student() -> None:
    quantizer = train_vocabulary(_clustered(100, seed=0)[0], _config(ae_student_hidden=0, ae_epochs=1),
                                 progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer) and quantizer.encoder is None
    assert "student_word_agreement" not in quantizer.training_info
    assert ENCODER_FILE not in quantizer.other_files()


def test_the_convolutional_network_is_distilled_into_a_256_unit_student_by_default() -> None:
    # Saved settings from before the student report none.
    defaults = VocabularyConfig()
    student_defaults = (defaults.ae_student_hidden, defaults.ae_student_epochs, defaults.ae_student_noise_rows)
    assert student_defaults == (256, 30, 300_000)
    config = _config(ae_epochs=1, ae_student_hidden=defaults.ae_student_hidden, ae_student_epochs=1)
    quantizer = train_vocabulary(_clustered(60, seed=0)[0], config, progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer) and quantizer.encoder is not None
    assert quantizer.encoder.hidden_dim == 256 and ENCODER_FILE in quantizer.other_files()
    before = {k: v for k, v in defaults.to_dict().items() if not k.startswith("ae_student_")}
    assert VocabularyConfig.from_dict(before).ae_student_hidden == 0
    assert VocabularyConfig.from_dict(before).ae_student_noise_rows == 0
    assert VocabularyConfig.from_dict(defaults.to_dict()) == defaults


def test_distillation_is_deterministic_given_seed() -> None:
    x = _clustered(80, seed=0)[0]
    a, b = (train_vocabulary(x, _config(ae_epochs=1, ae_student_epochs=2), progress=False) for _ in range(2))
    assert isinstance(a, AutoencoderQuantizer) and isinstance(b, AutoencoderQuantizer)
    assert a.encoder is not None and b.encoder is not None
    for name, array in a.encoder.to_arrays().items():
        np.testing.assert_array_equal(array, b.encoder.to_arrays()[name])


def test_student_that_does_not_fit_is_refused(trained: AutoencoderQuantizer) -> None:
    torch.manual_seed(0)
    with pytest.raises(DataError, match="MLP encoder maps 12 -> 8 but the PCA gives 16"):
        trained.with_encoder(MlpEncoder.from_torch(mlp_network(12, 32, 8)))
    with pytest.raises(DataError, match=r"maps 16 -> 5 .* embedding centres have 8"):
        trained.with_encoder(MlpEncoder.from_torch(mlp_network(16, 32, 5)))
    with pytest.raises(DataError, match="do not chain"):
        MlpEncoder(np.zeros((16, 4)), np.zeros(4), np.zeros((5, 8)), np.zeros(8))
    with pytest.raises(DataError, match="b2 contains NaN"):
        MlpEncoder(np.zeros((16, 4)), np.zeros(4), np.zeros((4, 8)), np.full(8, np.nan))


def _word_loss(student: np.ndarray, teacher: np.ndarray, centres: np.ndarray, temperature: float) -> float:
    return float(word_assignment_loss(torch.from_numpy(student), torch.from_numpy(teacher), torch.from_numpy(centres),
                                      temperature))


def test_word_assignment_loss_is_kl_of_softened_nearest_centre_assignments() -> None:
    rng = np.random.default_rng(4)
    student, teacher, centres = rng.normal(size=(5, 3)), rng.normal(size=(5, 3)), rng.normal(size=(7, 3))
    temperature = 0.7

    def soft(z: np.ndarray) -> np.ndarray:  # exp(-|z - c|^2 / T), normalised per row, straight from the definition
        weights = np.exp(-((z[:, None, :] - centres[None]) ** 2).sum(axis=2) / temperature)
        result: np.ndarray = weights / weights.sum(axis=1, keepdims=True)
        return result

    p, q = soft(teacher), soft(student)
    expected = float(np.mean(np.sum(p * np.log(p / q), axis=1)))
    assert _word_loss(student, teacher, centres, temperature) == pytest.approx(expected, rel=1e-9)
    assert _word_loss(teacher, teacher, centres, temperature) == pytest.approx(0.0, abs=1e-12)
    # Along a direction in which every centre is the same, the assignment (hence the loss) does not move.
    centres[:, 2] = 0.5
    moved = student.copy()
    moved[:, 2] += 3.0
    a, b = (_word_loss(z, teacher, centres, temperature) for z in (student, moved))
    assert a == pytest.approx(b, rel=1e-9) and a > 0.01


def _nuisance_teacher(x: np.ndarray) -> np.ndarray:
    """Embeddings whose first 2 dimensions decide the words and whose other 4 vary 6x more, words aside."""
    word_dims = np.stack([np.sin(3 * x[:, 0]) + x[:, 1], np.cos(3 * x[:, 1]) - x[:, 2]], axis=1)
    nuisance = 6 * np.sin(4 * x[:, 3:7] * x[:, 4:8])
    return np.concatenate([word_dims, nuisance], axis=1).astype(np.float32)


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """As training holds it (``num_threads: 1``): thousands of tiny steps on two threads of a loaded machine
    spend their time waiting for each other."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.mark.usefixtures("one_torch_thread")
def test_word_term_raises_agreement_where_the_mse_spends_capacity_on_what_does_not_decide_words() -> None:
    """16 centres on a grid in the 2 dimensions that decide the words (equal in the others); an 8-unit
    student cannot fit all 6 dimensions. The MSE, dominated by the large nuisance dimensions, fits them
    and barely beats chance (1/16) on the words; the word term aims the same capacity at the words."""
    rng = np.random.default_rng(0)
    x_fit, x_held = (rng.uniform(-1, 1, (4000, 8)).astype(np.float32) for _ in range(2))
    grid = np.array([-1.2, -0.4, 0.4, 1.2])
    centres = np.zeros((16, 6), np.float32)
    centres[:, :2] = np.array([(a, b) for a in grid for b in grid])

    def words(z: np.ndarray) -> np.ndarray:
        result: np.ndarray = ((z[:, None, :] - centres[None]) ** 2).sum(axis=2).argmin(axis=1)
        return result

    teacher_words = words(_nuisance_teacher(x_held))
    assert np.bincount(teacher_words, minlength=16).min() >= 100  # every word is used: chance is 1/16

    def agreement(word_weight: float) -> float:
        student = distill_student(x_fit, _nuisance_teacher(x_fit), centres, DistillOptions(
            hidden_dim=8, epochs=1, batch_size=64, learning_rate=3e-3, seed=0, word_weight=word_weight,
            word_temperature=0.1))
        return float(np.mean(words(student.embed(x_held)) == teacher_words))

    mse_alone, with_word_term = agreement(0.0), agreement(1.0)
    assert mse_alone < 0.3
    assert with_word_term > 0.55


def test_distillation_refuses_centres_of_another_space() -> None:
    x = np.zeros((10, 4), np.float32)
    with pytest.raises(DataError, match="centres in the embedding space"):
        distill_student(x, np.zeros((10, 3), np.float32), np.zeros((5, 2), np.float32),
                        DistillOptions(hidden_dim=4, epochs=1, batch_size=4, learning_rate=1e-3, seed=0))


@pytest.mark.parametrize(("field", "value"), [("ae_student_hidden", -1), ("ae_student_epochs", 0),
                                              ("ae_student_learning_rate", 0.0), ("ae_student_word_weight", -1.0),
                                              ("ae_student_word_temperature", 0.0), ("ae_student_noise_rows", -1),
                                              ("ae_student_noise_scale", 0.0)])
def test_config_validation(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=f"{field}={value}"):
        VocabularyConfig(**{field: value})  # type: ignore[arg-type]


def test_noisy_copies_spread_each_dimension_by_its_own_scale_and_stay_in_range() -> None:
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(0.4, 0.6, 5000), rng.uniform(0.45, 0.55, 5000)]).astype(np.float32)
    copies = noisy_copies(x, 20000, 0.5, seed=3)
    assert copies.shape == (20000, 2) and copies.dtype == np.float32
    assert copies.min() >= 0.0 and copies.max() <= 1.0
    # Far from the [0, 1] bounds nothing is clipped: uniform spread plus noise of half that spread.
    np.testing.assert_allclose(copies.std(axis=0), x.std(axis=0) * np.sqrt(1 + 0.5**2), rtol=0.03)
    np.testing.assert_array_equal(copies, noisy_copies(x, 20000, 0.5, seed=3))
    assert not np.array_equal(copies, noisy_copies(x, 20000, 0.5, seed=4))


def test_noisy_copies_teach_the_student_the_network_off_the_training_descriptors() -> None:
    """Training rows on a 2-D sheet in 8-D; a robot's descriptors fall around it. Fitted to the sheet
    alone the student gives the network's word to under half of the points around it (measured 0.46);
    with noisy copies labelled by the network, to most of them (0.73)."""
    dim, words = 8, 16
    generator = torch.Generator().manual_seed(0)
    w1, w2 = torch.randn(dim, 32, generator=generator) * 2, torch.randn(32, 4, generator=generator)

    def network(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return (torch.tanh(torch.from_numpy(x) @ w1 - 1.0) @ w2).numpy().astype(np.float32)

    rng = np.random.default_rng(0)
    basis = rng.normal(0, 1, (2, dim))

    def sheet(count: int, points: np.random.Generator) -> np.ndarray:
        return np.clip(0.5 + 0.15 * points.uniform(-1, 1, (count, 2)) @ basis, 0, 1).astype(np.float32)

    x = sheet(3000, rng)
    centres = network(np.clip(x[rng.choice(3000, words)] + rng.normal(0, 0.1, (words, dim)), 0, 1).astype(np.float32))
    around = noisy_copies(sheet(3000, np.random.default_rng(9)), 3000, 0.5, seed=99)
    network_words = _brute_force_words(centres, network(around))

    def agreement_around(noise_rows: int) -> float:
        options = VocabularyConfig(size=words, seed=0, ae_student_hidden=16, ae_student_epochs=5, ae_batch_size=256,
                                   ae_student_noise_rows=noise_rows)
        student, _ = _distill(x, network(x), centres, options, teacher=network)
        return float(np.mean(_brute_force_words(centres, student.embed(around)) == network_words))

    assert agreement_around(0) < 0.55
    assert agreement_around(5000) > 0.65


def test_noisy_copies_are_at_most_two_per_training_row(monkeypatch: pytest.MonkeyPatch) -> None:
    # The default 300k copies would drown a small training set (and slow its distillation) in copies of itself.
    drawn: list[int] = []
    real = training_module.noisy_copies

    def recording(x: np.ndarray, rows: int, scale: float, seed: int) -> np.ndarray:
        drawn.append(rows)
        return real(x, rows, scale, seed)

    monkeypatch.setattr(training_module, "noisy_copies", recording)
    x = np.random.default_rng(0).uniform(0.2, 0.8, (400, 8)).astype(np.float32)
    z = x[:, :4] * 3.0
    centres = z[:6].copy()
    for requested, expected in ((VocabularyConfig().ae_student_noise_rows, 2 * (400 - 20)), (100, 100)):
        options = VocabularyConfig(size=6, seed=0, ae_student_hidden=8, ae_student_epochs=1,
                                   ae_student_noise_rows=requested)
        _distill(x, z, centres, options, teacher=lambda rows: rows[:, :4] * 3.0)
        assert drawn[-1] == expected  # 400 rows, 5 % (20) held out


def _brute_force_words(centres: np.ndarray, z: np.ndarray) -> np.ndarray:
    distances = ((z[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2)
    result: np.ndarray = distances.argmin(axis=1)
    return result
