"""Tests for the model directory (aefabmap_ros/model/directory.py)."""

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse

from aefabmap_ros.errors import ModelError
from aefabmap_ros.features.extraction import FeatureConfig
from aefabmap_ros.io.npz_files import npz_bytes
from aefabmap_ros.model.directory import (
    METADATA,
    TREE,
    VOCABULARY,
    Model,
    compute_vocabulary_id,
    load_model,
    save_model,
)
from aefabmap_ros.vocabulary.autoencoder import (
    ENCODER_FILE,
    NETWORK_FILE,
    PCA_FILE,
    STUDENT_FILE,
    AutoencoderQuantizer,
)
from aefabmap_ros.vocabulary.base import Quantizer, VocabularyConfig, train_vocabulary
from aefabmap_ros.vocabulary.mlp_encoder import MlpEncoder

V = 6


def _descriptors(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 100, (V, 128))
    return np.maximum(centres[rng.integers(0, V, 600)] + rng.normal(0, 4, (600, 128)), 0).astype(np.float32)


@pytest.fixture(scope="module")
def ae_quantizer() -> Quantizer:
    config = VocabularyConfig(size=V, pca_dim=8, ae_embedding_dim=4, ae_epochs=1, num_threads=1, ae_network="conv",
                             ae_student_hidden=8)  # the paper's network and an encoder distilled from it
    return train_vocabulary(_descriptors(), config, progress=False)


@pytest.fixture(scope="module")
def km_quantizer() -> Quantizer:
    return train_vocabulary(_descriptors(), VocabularyConfig(kind="kmeans", size=V))


def _model(quantizer: Quantizer, **extra: object) -> Model:
    config = VocabularyConfig(kind=quantizer.kind, size=V, pca_dim=8, ae_embedding_dim=4)
    tree = np.vstack([np.arange(V) - 1.0, np.full((3, V), 0.2)])
    tree[0, 0] = 0
    samples = scipy.sparse.csr_matrix(np.random.default_rng(0).integers(0, 2, (5, V)))
    values: dict[str, object] = dict(tree_matrix=tree, new_place_samples=samples,
                                     provenance={"bags": [{"path": "a.mcap", "sha256": "00ff"}]})
    values.update(extra)
    return Model.create(FeatureConfig(), config, quantizer, **values)  # type: ignore[arg-type]


@pytest.mark.parametrize("which", ["ae", "km"])
def test_round_trip_quantizes_identically(which: str, ae_quantizer: Quantizer, km_quantizer: Quantizer,
                                          tmp_path: Path) -> None:
    quantizer = ae_quantizer if which == "ae" else km_quantizer
    model = _model(quantizer)
    save_model(tmp_path / "model", model)
    loaded = load_model(tmp_path / "model")
    assert loaded.vocabulary_id == model.vocabulary_id and len(loaded.vocabulary_id) == 16
    assert loaded.feature_config == model.feature_config and loaded.vocabulary_config == model.vocabulary_config
    x = _descriptors(1)
    np.testing.assert_array_equal(loaded.quantizer.quantize(x), quantizer.quantize(x))
    np.testing.assert_array_equal(loaded.quantizer.centroids, quantizer.centroids)
    assert model.tree_matrix is not None and loaded.tree_matrix is not None
    np.testing.assert_array_equal(loaded.tree_matrix, model.tree_matrix)
    assert loaded.new_place_samples is not None and model.new_place_samples is not None
    assert (loaded.new_place_samples != model.new_place_samples).nnz == 0
    assert loaded.provenance == {"bags": [{"path": "a.mcap", "sha256": "00ff"}]}
    metadata = json.loads((tmp_path / "model" / METADATA).read_text())
    assert metadata["format_version"] == 1 and metadata["vocabulary"]["size"] == V
    assert metadata["created_utc"].endswith("Z")


def test_optional_parts_may_be_absent(km_quantizer: Quantizer, tmp_path: Path) -> None:
    save_model(tmp_path / "m", _model(km_quantizer, tree_matrix=None, new_place_samples=None))
    loaded = load_model(tmp_path / "m")
    assert loaded.tree_matrix is None and loaded.new_place_samples is None
    assert not (tmp_path / "m" / TREE).exists()


def test_vocabulary_id_depends_on_vocabulary_only(ae_quantizer: Quantizer, km_quantizer: Quantizer) -> None:
    assert compute_vocabulary_id(ae_quantizer) == compute_vocabulary_id(ae_quantizer)
    assert compute_vocabulary_id(ae_quantizer) != compute_vocabulary_id(km_quantizer)
    assert _model(km_quantizer).vocabulary_id == _model(km_quantizer, tree_matrix=None).vocabulary_id
    other = train_vocabulary(_descriptors(), VocabularyConfig(kind="kmeans", size=V, seed=9))
    assert compute_vocabulary_id(other) != compute_vocabulary_id(km_quantizer)


def test_student_is_stored_and_part_of_the_vocabulary_id(ae_quantizer: Quantizer, tmp_path: Path) -> None:
    assert isinstance(ae_quantizer, AutoencoderQuantizer) and ae_quantizer.encoder is not None
    network_only = ae_quantizer.with_encoder(None)
    assert compute_vocabulary_id(network_only) != compute_vocabulary_id(ae_quantizer)
    arrays = ae_quantizer.encoder.to_arrays()
    nudged = MlpEncoder(arrays["w1"], arrays["b1"], arrays["w2"], arrays["b2"] + np.float32(1e-3))
    assert compute_vocabulary_id(ae_quantizer.with_encoder(nudged)) != compute_vocabulary_id(ae_quantizer)
    save_model(tmp_path / "m", _model(ae_quantizer))
    assert (tmp_path / "m" / ENCODER_FILE).is_file() and (tmp_path / "m" / NETWORK_FILE).is_file()
    loaded = load_model(tmp_path / "m").quantizer
    assert isinstance(loaded, AutoencoderQuantizer) and loaded.encoder is not None
    for name, array in arrays.items():
        np.testing.assert_array_equal(loaded.encoder.to_arrays()[name], array)


def test_model_without_student_loads_and_quantizes_with_the_network(ae_quantizer: Quantizer,
                                                                    tmp_path: Path) -> None:
    """A model directory written before the distilled encoder existed: no student file, no ae_student_* keys."""
    assert isinstance(ae_quantizer, AutoencoderQuantizer)
    network_only = ae_quantizer.with_encoder(None)
    save_model(tmp_path / "old", _model(network_only))
    assert not (tmp_path / "old" / ENCODER_FILE).exists()
    metadata = json.loads((tmp_path / "old" / METADATA).read_text())
    for key in [key for key in metadata["vocabulary_config"] if key.startswith("ae_student_")]:
        del metadata["vocabulary_config"][key]
    (tmp_path / "old" / METADATA).write_text(json.dumps(metadata))
    loaded = load_model(tmp_path / "old")
    assert isinstance(loaded.quantizer, AutoencoderQuantizer) and loaded.quantizer.encoder is None
    x = _descriptors(2)
    np.testing.assert_array_equal(loaded.quantizer.quantize(x), network_only.quantize(x))
    np.testing.assert_allclose(loaded.quantizer.embed(x), network_only.embed(x), rtol=1e-6)


def test_student_file_of_earlier_folders_loads_as_the_encoder(ae_quantizer: Quantizer, saved_ae: Path) -> None:
    """Model folders of earlier versions keep the distilled encoder in student.npz: the same arrays."""
    (saved_ae / ENCODER_FILE).rename(saved_ae / STUDENT_FILE)
    metadata = json.loads((saved_ae / METADATA).read_text())
    metadata["files"][STUDENT_FILE] = metadata["files"].pop(ENCODER_FILE)
    (saved_ae / METADATA).write_text(json.dumps(metadata))
    loaded = load_model(saved_ae).quantizer
    assert isinstance(loaded, AutoencoderQuantizer) and loaded.encoder is not None
    x = _descriptors(3)
    np.testing.assert_array_equal(loaded.quantize(x), ae_quantizer.quantize(x))


def test_mlp_autoencoder_folder_has_no_network_and_quantizes_as_trained(tmp_path: Path) -> None:
    config = VocabularyConfig(size=V, pca_dim=8, ae_embedding_dim=4, ae_epochs=1, num_threads=1, ae_mlp_hidden=16)
    assert config.ae_network == "mlp"  # the default
    trained = train_vocabulary(_descriptors(), config, progress=False)
    assert isinstance(trained, AutoencoderQuantizer) and trained.network is None and trained.encoder is not None
    save_model(tmp_path / "mlp", _model(trained))
    assert (tmp_path / "mlp" / ENCODER_FILE).is_file() and not (tmp_path / "mlp" / NETWORK_FILE).exists()
    loaded = load_model(tmp_path / "mlp")
    assert loaded.vocabulary_id == compute_vocabulary_id(trained)
    x = _descriptors(4)
    np.testing.assert_array_equal(loaded.quantizer.quantize(x), trained.quantize(x))


def test_autoencoder_folder_without_any_encoder_is_refused(saved_ae: Path) -> None:
    metadata = json.loads((saved_ae / METADATA).read_text())
    for name in (ENCODER_FILE, NETWORK_FILE):
        del metadata["files"][name]
    (saved_ae / METADATA).write_text(json.dumps(metadata))
    with pytest.raises(ModelError, match="autoencoder vocabulary without an encoder"):
        load_model(saved_ae)


def test_student_of_other_dimensions(saved_ae: Path) -> None:
    arrays = dict(np.load(saved_ae / ENCODER_FILE))
    hidden = arrays["w1"].shape[1]
    arrays["w1"] = np.zeros((arrays["w1"].shape[0] + 4, hidden), np.float32)  # a PCA of 12 dims, not 8
    np.savez(saved_ae / ENCODER_FILE, **arrays)
    _refresh_checksum(saved_ae, ENCODER_FILE)
    with pytest.raises(ModelError, match=r"dimension mismatch .* MLP encoder maps 12 -> 4 but the PCA gives 8"):
        load_model(saved_ae)
    del arrays["b2"]
    np.savez(saved_ae / ENCODER_FILE, **arrays)
    _refresh_checksum(saved_ae, ENCODER_FILE)
    with pytest.raises(ModelError, match=r"MLP encoder .*encoder.npz: .*lacks the array\(s\) \['b2'\]"):
        load_model(saved_ae)


def test_save_replaces_existing_model_atomically(ae_quantizer: Quantizer, km_quantizer: Quantizer,
                                                 tmp_path: Path) -> None:
    target = tmp_path / "model"
    save_model(target, _model(ae_quantizer))
    save_model(target, _model(km_quantizer))
    assert load_model(target).quantizer.kind == "kmeans"
    assert not (target / NETWORK_FILE).exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]  # no temp dirs left


def test_failed_save_leaves_previous_model(km_quantizer: Quantizer, tmp_path: Path) -> None:
    target = tmp_path / "model"
    save_model(target, _model(km_quantizer))
    wrong = _model(km_quantizer)
    wrong.vocabulary_id = "0123456789abcdef"
    with pytest.raises(ModelError, match="does not match its contents"):
        save_model(target, wrong)
    assert load_model(target).vocabulary_id == _model(km_quantizer).vocabulary_id
    with pytest.raises(ModelError, match="not a model directory"):
        (tmp_path / "other").mkdir()
        (tmp_path / "other" / "precious.txt").write_text("x")
        save_model(tmp_path / "other", _model(km_quantizer))
    assert (tmp_path / "other" / "precious.txt").exists()


def test_save_refuses_inconsistent_models(km_quantizer: Quantizer, tmp_path: Path) -> None:
    with pytest.raises(ModelError, match=r"tree_matrix has shape \(4, 3\), expected \(4, 6\)"):
        save_model(tmp_path / "m", _model(km_quantizer, tree_matrix=np.zeros((4, 3))))
    with pytest.raises(ModelError, match=r"new_place_samples has shape \(2, 4\)"):
        save_model(tmp_path / "m", _model(km_quantizer, new_place_samples=scipy.sparse.csr_matrix((2, 4))))
    orb_model = _model(km_quantizer)
    orb_model.feature_config = FeatureConfig(type="orb")
    with pytest.raises(ModelError, match="128-d descriptors but feature type 'orb' gives 32-d"):
        save_model(tmp_path / "m", orb_model)


@pytest.fixture
def saved_ae(ae_quantizer: Quantizer, tmp_path: Path) -> Path:
    save_model(tmp_path / "model", _model(ae_quantizer))
    return tmp_path / "model"


def _rewrite_metadata(directory: Path, **changes: object) -> None:
    metadata = json.loads((directory / METADATA).read_text())
    metadata.update(changes)
    (directory / METADATA).write_text(json.dumps(metadata))


def _refresh_checksum(directory: Path, name: str) -> None:
    import hashlib

    metadata = json.loads((directory / METADATA).read_text())
    metadata["files"][name] = hashlib.sha256((directory / name).read_bytes()).hexdigest()
    (directory / METADATA).write_text(json.dumps(metadata))


def test_missing_directory_and_files(saved_ae: Path, tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="does not exist"):
        load_model(tmp_path / "nowhere")
    (saved_ae / NETWORK_FILE).unlink()
    with pytest.raises(ModelError, match=f"{NETWORK_FILE} is missing"):
        load_model(saved_ae)
    (saved_ae / METADATA).unlink()
    with pytest.raises(ModelError, match=f"{METADATA} is missing"):
        load_model(saved_ae)


def test_wrong_format_version(saved_ae: Path) -> None:
    _rewrite_metadata(saved_ae, format_version=99)
    with pytest.raises(ModelError, match="format_version 99 is not supported"):
        load_model(saved_ae)


def test_unreadable_metadata(saved_ae: Path) -> None:
    (saved_ae / METADATA).write_text("{not json")
    with pytest.raises(ModelError, match="cannot read"):
        load_model(saved_ae)
    (saved_ae / METADATA).write_text('{"format_version": 1}')
    with pytest.raises(ModelError, match="lacks the key"):
        load_model(saved_ae)


def test_checksum_mismatch(saved_ae: Path) -> None:
    with open(saved_ae / VOCABULARY, "ab") as handle:
        handle.write(b"tampered")
    with pytest.raises(ModelError, match=rf"checksum mismatch for .*{VOCABULARY}"):
        load_model(saved_ae)


def test_vocabulary_id_mismatch(saved_ae: Path) -> None:
    _rewrite_metadata(saved_ae, model_id="ffffffffffffffff")
    with pytest.raises(ModelError, match=r"checksum mismatch .* metadata says ffffffffffffffff"):
        load_model(saved_ae)


def test_corrupt_weights(saved_ae: Path) -> None:
    (saved_ae / NETWORK_FILE).write_bytes(b"PK\x03\x04 not an archive")
    _refresh_checksum(saved_ae, NETWORK_FILE)
    with pytest.raises(ModelError, match=rf"cannot read .*{NETWORK_FILE}"):
        load_model(saved_ae)


def test_non_finite_weights(saved_ae: Path) -> None:
    arrays = dict(np.load(saved_ae / NETWORK_FILE))
    first = sorted(arrays)[0]
    arrays[first] = np.full_like(arrays[first], np.nan)
    np.savez(saved_ae / NETWORK_FILE, **arrays)
    _refresh_checksum(saved_ae, NETWORK_FILE)
    with pytest.raises(ModelError, match=f"{first} contains NaN"):
        load_model(saved_ae)


def test_weights_of_other_dimensions(saved_ae: Path) -> None:
    other = train_vocabulary(_descriptors(), VocabularyConfig(size=V, pca_dim=12, ae_embedding_dim=4, ae_epochs=1,
                                                              ae_network="conv"), progress=False)
    assert isinstance(other, AutoencoderQuantizer) and other.network is not None
    (saved_ae / NETWORK_FILE).write_bytes(npz_bytes(other.network.to_arrays()))
    _refresh_checksum(saved_ae, NETWORK_FILE)
    with pytest.raises(ModelError, match=r"dimension mismatch .*the network maps 12 -> 4 but the PCA gives 8"):
        load_model(saved_ae)
    arrays = other.network.to_arrays()
    del arrays["decoder.9.bias"]
    (saved_ae / NETWORK_FILE).write_bytes(npz_bytes(arrays))
    _refresh_checksum(saved_ae, NETWORK_FILE)
    with pytest.raises(ModelError, match=r"not the convolutional autoencoder's: missing \['decoder.9.bias'\]"):
        load_model(saved_ae)


def test_dimension_mismatch_in_metadata(saved_ae: Path) -> None:
    metadata = json.loads((saved_ae / METADATA).read_text())
    metadata["vocabulary"]["size"] = V + 1
    (saved_ae / METADATA).write_text(json.dumps(metadata))
    with pytest.raises(ModelError, match=f"metadata says vocabulary size {V + 1}"):
        load_model(saved_ae)


def test_dimension_mismatch_pca(saved_ae: Path) -> None:
    metadata = json.loads((saved_ae / METADATA).read_text())
    metadata["pca"]["dim"] = 16
    (saved_ae / METADATA).write_text(json.dumps(metadata))
    with pytest.raises(ModelError, match="dimension mismatch: metadata says PCA dim 16"):
        load_model(saved_ae)


def test_feature_type_mismatch(saved_ae: Path) -> None:
    metadata = json.loads((saved_ae / METADATA).read_text())
    metadata["feature_config"]["type"] = "orb"
    (saved_ae / METADATA).write_text(json.dumps(metadata))
    with pytest.raises(ModelError, match=r"dimension mismatch: .*feature type 'orb' gives 32-d"):
        load_model(saved_ae)


def test_bad_tree_file(saved_ae: Path) -> None:
    np.save(saved_ae / TREE, np.zeros((4, V + 2)))
    _refresh_checksum(saved_ae, TREE)
    with pytest.raises(ModelError, match=r"dimension mismatch: .*shape \(4, 8\), expected \(4, 6\)"):
        load_model(saved_ae)


def test_corrupt_npz(saved_ae: Path) -> None:
    (saved_ae / PCA_FILE).write_bytes(b"PK\x03\x04 broken zip")
    _refresh_checksum(saved_ae, PCA_FILE)
    with pytest.raises(ModelError, match=rf"cannot read .*{PCA_FILE}"):
        load_model(saved_ae)


def test_invalid_config_in_metadata(saved_ae: Path) -> None:
    metadata = json.loads((saved_ae / METADATA).read_text())
    metadata["vocabulary_config"]["size"] = -3
    (saved_ae / METADATA).write_text(json.dumps(metadata))
    with pytest.raises(ModelError, match=r"invalid configuration: .*size=-3"):
        load_model(saved_ae)
