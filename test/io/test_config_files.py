"""Shipped YAML files are package data, found beside the code (not by counting parent folders)."""

from pathlib import Path

import pytest
import yaml

import aefabmap_ros
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io.config_files import coerce_like, shipped_config


@pytest.mark.parametrize("name", ["aefabmap.yaml", "demo.yaml", "demo_train.yaml", "paper_network_train.yaml"])
def test_shipped_configs_are_in_the_package(name):
    path = shipped_config(name)
    assert path.parent == Path(aefabmap_ros.__file__).parent / "config"
    assert isinstance(yaml.safe_load(path.read_text()), dict)


def test_an_unknown_shipped_config_is_a_config_error():
    with pytest.raises(ConfigError, match=r"no shipped config 'nope\.yaml'"):
        shipped_config("nope.yaml")


def test_coerce_like_turns_only_an_int_for_a_float_into_a_float():
    assert coerce_like(1, 0.5) == 1.0 and isinstance(coerce_like(1, 0.5), float)
    assert coerce_like(True, 0.5) is True  # a bool is no number here: the caller's type check refuses it
    assert coerce_like(2.5, 1) == 2.5 and isinstance(coerce_like(2.5, 1), float)  # never float -> int
    assert coerce_like("1", 0.5) == "1"


def test_the_paper_network_config_is_the_convolutional_reference_setting():
    from aefabmap_ros.io.config_files import build_config, read_sections
    from aefabmap_ros.vocabulary.config import VocabularyConfig

    path = shipped_config("paper_network_train.yaml")
    config = build_config(VocabularyConfig, read_sections(path, {"vocabulary"})["vocabulary"], str(path))
    assert (config.ae_network, config.ae_epochs, config.ae_max_train_descriptors) == ("conv", 8, 100_000)
    # The network's embeddings are distilled into a 256-unit student with the default distillation.
    assert (config.ae_student_hidden, config.ae_student_epochs, config.ae_student_noise_rows) == (256, 30, 300_000)
