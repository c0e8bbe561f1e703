"""How to train a vocabulary: one dataclass per kind, each field declared once.

``KMeansOptions`` holds what only k-means reads, ``AutoencoderOptions`` what only the autoencoder
reads, ``CommonVocabularyOptions`` what both read. ``VocabularyConfig`` is all three at once by
inheritance, so its fields are the flat keys of a YAML ``vocabulary:`` section, of a model's
metadata.json and of ROS parameters, and a trainer takes it as the options of its own kind with no
copy in between. Plain Python (no torch): CLIs build their help from it cheaply.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.vocabulary.kinds import VOCABULARY_KINDS

AE_INPUTS = ("pca", "matches")  # the autoencoder's input projections (``AutoencoderOptions.ae_input``)
AE_NETWORKS = ("mlp", "conv")  # the autoencoders (``AutoencoderOptions.ae_network``)
Check = tuple[str, bool, str]  # field name, whether its value is valid, the rule it breaks otherwise


def _describe(default: Any, description: str) -> Any:
    return field(default=default, metadata={"description": description})


def _raise_on(owner: str, config: object, checks: list[Check]) -> None:
    for name, ok, rule in checks:
        if not ok:
            raise ConfigError(f"{owner}.{name}={getattr(config, name)!r} must be {rule}")


@dataclass(frozen=True)
class CommonVocabularyOptions:
    """Settings every vocabulary kind reads."""

    kind: str = _describe("autoencoder", "Vocabulary kind: autoencoder | kmeans.")
    size: int = _describe(1000, "Number of visual words K.")
    pca_dim: int = _describe(64, "PCA dimension of the autoencoder's input (multiple of 4).")
    pca_per_component: bool = _describe(
        False, "Scale each PCA component to [0, 1] separately (true) or all with one range, keeping PCA "
        "geometry (false).")
    seed: int = _describe(0, "Random seed (same seed + data = same vocabulary).")
    num_threads: int = _describe(0, "torch threads while training (0 = leave torch's default).")

    def common_checks(self) -> list[Check]:
        return [
            ("kind", self.kind in VOCABULARY_KINDS, f"one of {', '.join(VOCABULARY_KINDS)}"),
            ("size", self.size >= 2, ">= 2"),
            ("pca_dim", self.pca_dim >= 4 and self.pca_dim % 4 == 0, "a multiple of 4, >= 4"),
            ("num_threads", self.num_threads >= 0, ">= 0"),
        ]


@dataclass(frozen=True)
class KMeansOptions:
    """k-means' settings (also the autoencoder's clustering of its embeddings)."""

    kmeans_iterations: int = _describe(25, "Lloyd iterations after k-means++ seeding.")
    kmeans_max_points_per_centroid: int = _describe(
        256, "k-means trains on at most this many descriptors per word (random subsample).")

    def kmeans_checks(self) -> list[Check]:
        return [
            ("kmeans_iterations", self.kmeans_iterations >= 0, ">= 0"),
            ("kmeans_max_points_per_centroid", self.kmeans_max_points_per_centroid >= 1, ">= 1"),
        ]


@dataclass(frozen=True)
class AutoencoderOptions:
    """The autoencoder's settings: the MLP autoencoder or the paper's network and its distilled encoder, the
    optional refinement."""

    ae_network: str = _describe(
        "mlp", "The autoencoder: 'mlp' (PCA -> ae_mlp_hidden (ReLU) -> embedding and back; its encoder quantizes, "
        "in numpy) or 'conv' (the paper's 1-D convolutional network, the reference setting: an MLP student "
        "distilled from it quantizes, see ae_student_hidden). docs/vocabulary.md compares the two.")
    ae_mlp_hidden: int = _describe(256, "Hidden units of the MLP autoencoder (ae_network 'mlp').")
    ae_input: str = _describe(
        "pca", "The linear projection before the network: 'pca' (principal axes, the paper's) or 'matches' "
        "(discriminant axes of descriptors matched between neighbouring training frames, which aefabmap_train "
        "finds: directions where different scene points differ most relative to one point's frame-to-frame "
        "change).")
    ae_embedding_dim: int = _describe(64, "Autoencoder embedding size (the space the words live in).")
    ae_epochs: int = _describe(
        10, "Autoencoder pre-training epochs (with ae_network 'mlp' the learning rate is cosine-annealed to 0 "
        "over them).")
    ae_batch_size: int = _describe(256, "Autoencoder mini-batch size.")
    ae_learning_rate: float = _describe(1e-3, "Adam learning rate, pre-training.")
    ae_max_train_descriptors: int = _describe(
        250_000, "Pre-train the autoencoder on at most this many descriptors (random subsample); all "
        "descriptors are embedded for the word centres.")
    ae_match_weight: float = _describe(
        0.0, "Weight of the self-supervised match term (same point in neighbouring frames embeds close); "
        "needs matched pairs; 0 = off.")
    ae_match_temperature: float = _describe(
        0.5, "Temperature of the match term's InfoNCE (relative to the batch's mean squared distance).")
    ae_student_hidden: int = _describe(
        256, "ae_network 'conv': hidden units of a small encoder distilled from the network that then quantizes "
        "(PCA -> hidden -> embedding, numpy) instead of the network; 0 = the paper's network quantizes "
        "(docs/vocabulary.md).")
    ae_student_epochs: int = _describe(30, "Epochs distilling the student from the network's embeddings.")
    ae_student_learning_rate: float = _describe(
        3e-3, "Adam learning rate of the distillation (cosine-annealed to 0).")
    ae_student_word_weight: float = _describe(
        0.0, "Weight of the distillation's word term (KL between the network's and the student's soft word "
        "assignments) against the embedding MSE; 0 = MSE alone (docs/vocabulary.md).")
    ae_student_word_temperature: float = _describe(
        8.0, "Temperature of the word term's soft assignment, exp(-|z - c|^2 / T), in the embedding space "
        "normalised to unit variance per dimension.")
    ae_student_noise_rows: int = _describe(
        300_000, "Noisy copies of training rows added to the distillation, labelled by the network (0 = none; "
        "at most two per training row): the student also learns the network around the training "
        "descriptors, where another environment's descriptors fall.")
    ae_student_noise_scale: float = _describe(0.5, "Std of that noise, as a fraction of each PCA dimension's spread.")
    refine: bool = _describe(False, "DEC/IDEC refinement of encoder and centres with reconstruction + gamma*KL(P||Q).")
    refine_epochs: int = _describe(5, "Maximum refinement epochs.")
    refine_learning_rate: float = _describe(1e-4, "Adam learning rate during refinement.")
    refine_update_interval: int = _describe(100, "Recompute the target distribution every this many batches.")
    gamma: float = _describe(0.1, "Weight of the clustering KL term (IDEC).")
    tol: float = _describe(0.001, "Stop refining when fewer than this fraction of labels change between targets.")
    alpha: float = _describe(1.0, "Student-t degrees of freedom of the soft assignment.")

    def autoencoder_checks(self) -> list[Check]:
        return [
            ("ae_input", self.ae_input in AE_INPUTS, f"one of {', '.join(AE_INPUTS)}"),
            ("ae_network", self.ae_network in AE_NETWORKS, f"one of {', '.join(AE_NETWORKS)}"),
            ("ae_mlp_hidden", self.ae_mlp_hidden >= 1, ">= 1"),
            ("ae_embedding_dim", self.ae_embedding_dim >= 1, ">= 1"),
            ("ae_epochs", self.ae_epochs >= 0, ">= 0"),
            ("ae_batch_size", self.ae_batch_size >= 2, ">= 2"),
            ("ae_learning_rate", self.ae_learning_rate > 0, "> 0"),
            ("ae_max_train_descriptors", self.ae_max_train_descriptors >= 1, ">= 1"),
            ("ae_match_weight", self.ae_match_weight >= 0, ">= 0"),
            ("ae_match_temperature", self.ae_match_temperature > 0, "> 0"),
            ("ae_student_hidden", self.ae_student_hidden >= 0, ">= 0"),
            ("ae_student_epochs", self.ae_student_epochs >= 1, ">= 1"),
            ("ae_student_learning_rate", self.ae_student_learning_rate > 0, "> 0"),
            ("ae_student_word_weight", self.ae_student_word_weight >= 0, ">= 0"),
            ("ae_student_word_temperature", self.ae_student_word_temperature > 0, "> 0"),
            ("ae_student_noise_rows", self.ae_student_noise_rows >= 0, ">= 0"),
            ("ae_student_noise_scale", self.ae_student_noise_scale > 0, "> 0"),
            ("refine_epochs", self.refine_epochs >= 0, ">= 0"),
            ("refine_learning_rate", self.refine_learning_rate > 0, "> 0"),
            ("refine_update_interval", self.refine_update_interval >= 1, ">= 1"),
            ("gamma", self.gamma >= 0, ">= 0"),
            ("tol", 0 <= self.tol < 1, "in [0, 1)"),
            ("alpha", self.alpha > 0, "> 0"),
        ]


# Settings saved before these fields existed (a model's vocabulary_config) were trained without them: say so
# when reading one back, not today's defaults (the quantizer itself comes from the model's files either way).
SAVED_BEFORE = {"ae_student_hidden": 0, "ae_student_epochs": 10, "ae_student_noise_rows": 0, "ae_network": "conv"}


@dataclass(frozen=True)
class VocabularyConfig(AutoencoderOptions, KMeansOptions, CommonVocabularyOptions):
    """How to train a vocabulary: every kind's settings, flat (one YAML key / ROS parameter each)."""

    def __post_init__(self) -> None:
        if self.kind not in VOCABULARY_KINDS:  # named first: the other rules depend on the kind
            raise ConfigError(f"VocabularyConfig.kind={self.kind!r} is not one of {', '.join(VOCABULARY_KINDS)}")
        _raise_on("VocabularyConfig", self, self.common_checks() + self.kmeans_checks() + self.autoencoder_checks())

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> VocabularyConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"VocabularyConfig: unknown field(s) {unknown}")
        return cls(**{**SAVED_BEFORE, **values})


__all__ = [
    "AE_INPUTS",
    "AE_NETWORKS",
    "SAVED_BEFORE",
    "AutoencoderOptions",
    "CommonVocabularyOptions",
    "KMeansOptions",
    "VocabularyConfig",
]
