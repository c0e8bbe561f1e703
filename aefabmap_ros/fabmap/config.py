"""FAB-MAP's settings: the observation model, the new-place model, the posterior and the online
recognizer's policies, as one flat dataclass (one ROS parameter / YAML key per field).

Plain numpy: nodes and CLIs read and check the settings without compiling the engines' kernels.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from aefabmap_ros.errors import ConfigError

NEW_PLACE_MODELS = ("sampled", "meanfield")
ADD_POLICIES = ("all", "new_only")
# Why frames without words are skipped by default: FAB-MAP scores a place relative to a place without
# words, so an empty query scores exactly 0 against every empty place and below 0 against every
# textured one; with a new-place model trained on textured images, a blank wall then "recognises" any
# earlier blank wall with p ~ 1 (openFABMAP's own run on rtabmap_samples: its most confident false loop
# is blank frame 45 -> blank frame 18; skipping the two blank frames raises its recall at 100 %
# precision from 0.57 to 0.75, tested in test/evaluation/test_protocol.py). Frames with a handful
# of words are the same case, weaker: raise min_words for imagery with many near-blank frames (the
# right value depends on the vocabulary size and the features per image).
DEFAULT_MIN_WORDS = 1


@dataclass(frozen=True)
class FabMapConfig:
    """FAB-MAP parameters (openFABMAP names in brackets) and the online recognizer's policies."""

    p_z_given_e: float = field(
        default=0.39, metadata={"description": "Detector model p(z=1 | e=1) [PzGe], in (0, 1)."}
    )
    p_z_given_not_e: float = field(
        default=0.0,
        metadata={"description": "Detector model p(z=1 | e=0) [PzGNe], in [0, p_z_given_e)."},
    )
    new_place_model: str = field(
        default="sampled",
        metadata={
            "description": "New-place likelihood: 'sampled' (mean over the training samples) or "
            "'meanfield' (place with word-existence probabilities equal to the marginals)."
        },
    )
    motion_model: bool = field(
        default=False,
        metadata={"description": "Use openFABMAP's motion-model prior (spreads the last posterior to neighbours)."},
    )
    p_new: float = field(
        default=0.9, metadata={"description": "Motion model: prior weight of the new-place hypothesis [Pnew]."}
    )
    motion_bias: float = field(
        default=0.5,
        metadata={"description": "Motion model: forward bias in [0, 1]; 0.5 spreads evenly [mBias]."},
    )
    likelihood_temperature: float = field(
        default=3.0,
        metadata={
            "description": "Log-likelihoods are divided by this before the posterior (1 = FAB-MAP as published). "
            "FAB-MAP's independence assumptions make its likelihood ratios overconfident; a temperature "
            "> 1 calibrates the posterior (temperature scaling)."
        },
    )
    smoothing: float = field(
        default=0.99,
        metadata={"description": "Posterior smoothing s in (0, 1]: p <- s p + (1 - s) / n [sFactor]."},
    )
    match_threshold: float = field(
        default=0.1,
        metadata={"description": "A query matches a known place when that place's posterior exceeds this: the "
                  "match is a loop-closure candidate once temporally consistent (verification decides what is "
                  "published). The posterior is calibrated by likelihood_temperature (0.99 is the papers' "
                  "value for the raw posterior)."},
    )
    add_policy: str = field(
        default="all",
        metadata={
            "description": "'all': every (key)frame becomes a place (openFABMAP 'All'); "
            "'new_only': only frames not matched to a known place."
        },
    )
    exclude_recent_frames: int = field(
        default=0,
        metadata={
            "description": "Places created from the last N frames are not hypotheses of the posterior "
            "(0 = none excluded)."
        },
    )
    exclude_recent_seconds: float = field(
        default=5.0,
        metadata={
            "description": "Places stamped less than this many seconds before the query are not "
            "hypotheses of the posterior (0 = off)."
        },
    )
    exclude_linked_overlap: float = field(
        default=0.0,
        metadata={
            "description": "Walking back from the newest place, places whose Jaccard word overlap with the "
            "query is at least this are not hypotheses, up to the first that overlaps less: the stretch "
            "the camera is still in (a corridor seen moving along it) is no loop (0 = off)."
        },
    )
    keyframe_min_frames: int = field(
        default=1,
        metadata={
            "description": "A frame can become a place only if at least this many frames passed since "
            "the last added place (1 = any frame)."
        },
    )
    keyframe_max_overlap: float = field(
        default=0.5,
        metadata={
            "description": "A frame becomes a place only if the Jaccard overlap of its words with the "
            "last added place is at most this (1.0 = always), unless keyframe_max_frames forces it."
        },
    )
    keyframe_max_frames: int = field(
        default=0,
        metadata={
            "description": "Force a place once this many frames passed since the last added place, "
            "whatever the overlap (0 = never force)."
        },
    )
    keyframe_max_seconds: float = field(
        default=1.0,
        metadata={
            "description": "Force a place once this many seconds passed since the last added place, "
            "whatever the overlap (0 = never force): a long stay still becomes several places."
        },
    )
    consistency_matches: int = field(
        default=2,
        metadata={
            "description": "Temporal consistency: a match is a loop closure only when this many informative "
            "frames (this one included; consistency_skips others may come between) matched places within "
            "island_seconds of each other (1 = every match)."
        },
    )
    consistency_skips: int = field(
        default=1,
        metadata={
            "description": "Temporal consistency: up to this many informative frames among the chain's may "
            "match nothing, or a place elsewhere, without breaking it: along a real revisit the posterior "
            "flickers (0 = the consistency_matches frames must be consecutive)."
        },
    )
    consistency_window_seconds: float = field(
        default=0.5,
        metadata={
            "description": "Temporal consistency: frames up to this many seconds before this one may join "
            "its chain too, however many lie between (at video rate a revisit's posterior flickers for a "
            "fraction of a second, many frames; 0 = only consistency_skips counts)."
        },
    )
    island_seconds: float = field(
        default=3.0,
        metadata={
            "description": "Temporal consistency: largest gap in map time (stamps of the matched places) "
            "between two matches of the chain."
        },
    )
    top_k: int = field(
        default=5, metadata={"description": "Number of best place candidates reported per query."}
    )
    min_words: int = field(
        default=DEFAULT_MIN_WORDS,
        metadata={
            "description": "Frames with fewer distinct words are uninformative: they are not recognised "
            "(no posterior, no loop closure) and do not become places (0 = recognise every frame)."
        },
    )

    @classmethod
    def openfabmap(cls, **overrides: Any) -> FabMapConfig:
        """FAB-MAP as openFABMAP and the papers run it: every frame a place and a hypothesis, the raw
        posterior (no temperature), a match at 0.99, no time window, no consistency. The defaults of this class are
        the nodes' (dense video, calibrated, consistent); this is the reference for golden comparisons."""
        reference: dict[str, Any] = {"likelihood_temperature": 1.0, "match_threshold": 0.99,
                                     "exclude_recent_seconds": 0.0, "consistency_matches": 1, "consistency_skips": 0,
                                     "consistency_window_seconds": 0.0,
                                     "keyframe_max_overlap": 1.0, "keyframe_max_seconds": 0.0}
        return cls(**{**reference, **overrides})

    def __post_init__(self) -> None:
        def bad(name: str, rule: str) -> ConfigError:
            return ConfigError(f"FabMapConfig.{name} = {getattr(self, name)!r}: must be {rule}")

        kinds: dict[str, tuple[type, ...]] = {"float": (float, int), "int": (int,), "str": (str,), "bool": (bool,)}
        for f in fields(self):
            value = getattr(self, f.name)
            expected = kinds[str(f.type)]
            if not isinstance(value, expected) or (bool not in expected and isinstance(value, bool)):
                raise bad(f.name, f"of type {f.type}")
        if not 0.0 < self.p_z_given_e < 1.0:
            raise bad("p_z_given_e", "in (0, 1)")
        if not 0.0 <= self.p_z_given_not_e < self.p_z_given_e:
            raise bad("p_z_given_not_e", f"in [0, p_z_given_e = {self.p_z_given_e})")
        if self.new_place_model not in NEW_PLACE_MODELS:
            raise bad("new_place_model", f"one of {NEW_PLACE_MODELS}")
        if not 0.0 < self.p_new < 1.0:
            raise bad("p_new", "in (0, 1)")
        if not 0.0 <= self.motion_bias <= 1.0:
            raise bad("motion_bias", "in [0, 1]")
        if not (np.isfinite(self.likelihood_temperature) and self.likelihood_temperature > 0.0):
            raise bad("likelihood_temperature", "finite and > 0")
        if not 0.0 < self.smoothing <= 1.0:
            raise bad("smoothing", "in (0, 1]")
        if not 0.0 <= self.match_threshold <= 1.0:
            raise bad("match_threshold", "in [0, 1]")
        if self.add_policy not in ADD_POLICIES:
            raise bad("add_policy", f"one of {ADD_POLICIES}")
        if self.exclude_recent_frames < 0:
            raise bad("exclude_recent_frames", ">= 0")
        if not (np.isfinite(self.exclude_recent_seconds) and self.exclude_recent_seconds >= 0.0):
            raise bad("exclude_recent_seconds", "finite and >= 0")
        if not 0.0 <= self.exclude_linked_overlap <= 1.0:
            raise bad("exclude_linked_overlap", "in [0, 1]")
        if self.keyframe_min_frames < 1:
            raise bad("keyframe_min_frames", ">= 1")
        if not 0.0 <= self.keyframe_max_overlap <= 1.0:
            raise bad("keyframe_max_overlap", "in [0, 1]")
        if self.keyframe_max_frames < 0:
            raise bad("keyframe_max_frames", ">= 0")
        if not (np.isfinite(self.keyframe_max_seconds) and self.keyframe_max_seconds >= 0.0):
            raise bad("keyframe_max_seconds", "finite and >= 0")
        if self.consistency_matches < 1:
            raise bad("consistency_matches", ">= 1")
        if self.consistency_skips < 0:
            raise bad("consistency_skips", ">= 0")
        if not self.consistency_window_seconds >= 0.0:
            raise bad("consistency_window_seconds", ">= 0")
        if not (np.isfinite(self.island_seconds) and self.island_seconds >= 0.0):
            raise bad("island_seconds", "finite and >= 0")
        if self.top_k < 0:
            raise bad("top_k", ">= 0")
        if self.min_words < 0:
            raise bad("min_words", ">= 0")
