"""The vocabulary kinds the package knows: the one registry CLI choices, configs, the model directory
and the evaluation read.

Each kind is one module of this folder that provides ``train_quantizer(descriptors, config, *, pairs,
progress, work_dir)`` and ``load_quantizer(stored)`` (a :class:`~aefabmap_ros.vocabulary.base.Quantizer`
from a model directory). A new vocabulary kind is that module plus one line here.

Plain Python on purpose: a CLI builds its ``--help`` from this without importing torch or scikit-learn,
and a kind's module is imported only when that kind is trained or loaded.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from aefabmap_ros.errors import ConfigError

# kind -> the module implementing it
VOCABULARY_KINDS = {
    "autoencoder": "aefabmap_ros.vocabulary.autoencoder",
    "kmeans": "aefabmap_ros.vocabulary.kmeans",
}


def kind_module(kind: str) -> ModuleType:
    """The module implementing vocabulary ``kind`` (imported now); ConfigError for an unknown kind."""
    if kind not in VOCABULARY_KINDS:
        raise ConfigError(f"unknown vocabulary kind {kind!r}; known: {', '.join(VOCABULARY_KINDS)}")
    return importlib.import_module(VOCABULARY_KINDS[kind])
