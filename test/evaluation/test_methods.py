"""The evaluation's method table and its parsing."""

import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.evaluation.methods import METHODS, method_kinds, methods_of_kind, parse_methods
from aefabmap_ros.vocabulary.kinds import VOCABULARY_KINDS


def test_parse_methods():
    assert parse_methods(["ae-fabmap", "BOW", " fabmap2"]) == ("FABMAP2", "AE-FABMAP", "BoW")
    assert parse_methods(METHODS) == tuple(METHODS)
    assert methods_of_kind("autoencoder", tuple(METHODS)) == ("AE-FABMAP", "AE-BoW")
    with pytest.raises(ConfigError, match="unknown method 'SeqSLAM'"):
        parse_methods(["FABMAP2", "SeqSLAM"])
    with pytest.raises(ConfigError, match="no method selected"):
        parse_methods([])


def test_every_method_uses_a_known_vocabulary_kind():
    assert {kind for kind, _ in METHODS.values()} == set(VOCABULARY_KINDS)
    assert method_kinds() == ("kmeans", "autoencoder")  # k-means first, as the methods table lists them
