"""The feature types the package knows: the one registry CLI choices, configs and messages read.

Plain Python on purpose: a CLI builds its ``--help`` from this without importing OpenCV or numpy.
A new feature type is added here (its row length) and in ``extraction.py`` (its OpenCV detector).
"""

from __future__ import annotations

FEATURE_TYPES = ("sift", "rootsift", "orb", "surf")
# Row length of each descriptor type (bytes for ORB, floats otherwise); SURF's depends on its config.
DESCRIPTOR_LENGTHS = {"sift": 128, "rootsift": 128, "orb": 32}
# Binary descriptors: uint8 rows compared by Hamming distance (the others: float32, L2).
BINARY_FEATURE_TYPES = frozenset({"orb"})
