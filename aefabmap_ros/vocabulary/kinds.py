"""The vocabulary kinds the package knows: the one registry CLI choices, configs and the evaluation read.

Plain Python on purpose: a CLI builds its ``--help`` from this without importing torch or scikit-learn.
A new vocabulary kind is added here and gets its own module in this folder.
"""

from __future__ import annotations

VOCABULARY_KINDS = ("autoencoder", "kmeans")
