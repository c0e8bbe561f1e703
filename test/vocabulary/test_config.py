"""Tests for the vocabulary settings by kind (vocabulary/config.py) and for model folders saved before them."""

import json
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.features.extraction import FeatureConfig
from aefabmap_ros.io.config_files import build_config, read_sections
from aefabmap_ros.model.directory import Model, load_model, save_model
from aefabmap_ros.vocabulary.base import train_vocabulary
from aefabmap_ros.vocabulary.config import (
    SAVED_BEFORE,
    AutoencoderOptions,
    CommonVocabularyOptions,
    KMeansOptions,
    VocabularyConfig,
)

KIND_CLASSES = (CommonVocabularyOptions, KMeansOptions, AutoencoderOptions)


def test_every_key_is_declared_by_exactly_one_kind() -> None:
    owners: dict[str, list[str]] = {}
    for options in KIND_CLASSES:
        for name in options.__annotations__:
            owners.setdefault(name, []).append(options.__name__)
    assert {name for name, classes in owners.items() if len(classes) > 1} == set()
    assert set(owners) == {f.name for f in fields(VocabularyConfig)}
    assert len(fields(VocabularyConfig)) == 32  # the flat keys YAML files and model folders use


def test_the_config_is_each_kinds_options_with_the_same_values() -> None:
    config = VocabularyConfig(kind="kmeans", size=12, kmeans_iterations=3, ae_epochs=2)
    assert isinstance(config, KMeansOptions) and isinstance(config, AutoencoderOptions)
    assert (config.kmeans_iterations, config.ae_epochs, config.size) == (3, 2, 12)


def test_a_yaml_section_in_the_flat_keys_builds_it(tmp_path: Path) -> None:
    path = tmp_path / "train.yaml"
    path.write_text("vocabulary:\n  kind: kmeans\n  size: 40\n  ae_learning_rate: 1\n  refine: true\n")
    section = read_sections(path, {"vocabulary"})["vocabulary"]
    config = build_config(VocabularyConfig, section, str(path))
    assert (config.kind, config.size, config.ae_learning_rate, config.refine) == ("kmeans", 40, 1.0, True)
    with pytest.raises(ConfigError, match="unknown key"):
        build_config(VocabularyConfig, {"epochs": 3}, "inline")


@pytest.mark.parametrize(("key", "value", "match"), [
    ("kmeans_iterations", -1, "kmeans_iterations=-1 must be >= 0"),
    ("ae_batch_size", 1, "ae_batch_size=1 must be >= 2"),
    ("num_threads", -2, "num_threads=-2 must be >= 0"),
])
def test_each_kinds_rules_are_checked(key: str, value: int, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        VocabularyConfig(**{key: value})  # type: ignore[arg-type]


def test_settings_saved_before_the_student_read_back_as_trained() -> None:
    saved = {k: v for k, v in VocabularyConfig().to_dict().items() if k not in SAVED_BEFORE}
    restored = VocabularyConfig.from_dict(saved)
    assert (restored.ae_student_hidden, restored.ae_student_epochs, restored.ae_student_noise_rows) == (0, 10, 0)
    assert restored.ae_network == "conv"  # saved before the MLP autoencoder: the paper's network


# The keys model folders were written with before the input projection, the distilled encoder and the MLP
# autoencoder existed.
OLDER_KEYS = sorted({f.name for f in fields(VocabularyConfig)} - {"ae_input", "ae_mlp_hidden"} - set(SAVED_BEFORE))


@pytest.mark.parametrize("kind", ["autoencoder", "kmeans"])
def test_a_model_folder_written_with_the_older_keys_still_loads(kind: str, tmp_path: Path) -> None:
    """A folder whose metadata names only the older keys loads as what it was trained as (principal axes,
    the network quantizing) and quantizes as the folder's own files say."""
    descriptors = np.random.default_rng(0).uniform(0, 100, (400, 128)).astype(np.float32)
    config = VocabularyConfig(kind=kind, size=4, pca_dim=8, ae_embedding_dim=4, ae_epochs=1, ae_network="conv",
                              ae_student_hidden=0, num_threads=1)
    quantizer = train_vocabulary(descriptors, config, progress=False)
    folder = tmp_path / kind
    save_model(folder, Model.create(FeatureConfig(), config, quantizer))  # a tree is optional: not what is tested
    metadata = json.loads((folder / "metadata.json").read_text())
    metadata["vocabulary_config"] = {key: metadata["vocabulary_config"][key] for key in OLDER_KEYS}
    (folder / "metadata.json").write_text(json.dumps(metadata))

    model = load_model(folder)
    restored = model.vocabulary_config.to_dict()
    assert {key: restored[key] for key in OLDER_KEYS} == metadata["vocabulary_config"]
    assert restored["ae_input"] == "pca"  # saved before the match projection: trained on principal axes
    assert {key: restored[key] for key in SAVED_BEFORE} == SAVED_BEFORE
    assert model.quantizer.kind == kind
    np.testing.assert_array_equal(model.quantizer.quantize(descriptors), quantizer.quantize(descriptors))
