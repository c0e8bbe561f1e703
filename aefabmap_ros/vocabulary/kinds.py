"""The vocabulary kinds the package knows: the one registry CLI choices, configs, the model directory
and the evaluation read.

Each kind has two modules of this folder. Its *runtime* module provides ``load_quantizer(stored)`` (a
:class:`~aefabmap_ros.vocabulary.base.Quantizer` from a model directory) and quantizes with numpy alone:
it is what a node imports. Its *training* module provides ``train_quantizer(descriptors, config, *, pairs,
progress, work_dir)`` and may import torch, faiss and scikit-learn: only training imports it. A new
vocabulary kind is those two modules plus one line in each table here.

Plain Python on purpose: a CLI builds its ``--help`` from this without importing torch or scikit-learn,
and a kind's module is imported only when that kind is trained or loaded.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from aefabmap_ros.errors import ConfigError

# kind -> the module that loads and quantizes it (numpy only)
VOCABULARY_KINDS = {
    "autoencoder": "aefabmap_ros.vocabulary.autoencoder",
    "kmeans": "aefabmap_ros.vocabulary.kmeans",
}
# kind -> the module that trains it (torch, faiss, scikit-learn)
VOCABULARY_TRAINERS = {
    "autoencoder": "aefabmap_ros.vocabulary.autoencoder_training",
    "kmeans": "aefabmap_ros.vocabulary.kmeans_training",
}


def _known(kind: str) -> str:
    if kind not in VOCABULARY_KINDS:
        raise ConfigError(f"unknown vocabulary kind {kind!r}; known: {', '.join(VOCABULARY_KINDS)}")
    return kind


def runtime_module(kind: str) -> ModuleType:
    """The module that loads and quantizes vocabulary ``kind`` (imported now); ConfigError for an unknown kind."""
    return importlib.import_module(VOCABULARY_KINDS[_known(kind)])


def training_module(kind: str) -> ModuleType:
    """The module that trains vocabulary ``kind`` (imported now); ConfigError for an unknown kind."""
    return importlib.import_module(VOCABULARY_TRAINERS[_known(kind)])


__all__ = ["VOCABULARY_KINDS", "VOCABULARY_TRAINERS", "runtime_module", "training_module"]
