"""What a vocabulary's words say about an image sequence, before any loop is scored.

FAB-MAP and tf-idf see an image as the words its descriptors fall in. Two things decide how well they
tell a revisit from another place, and both can be read off a sequence with no ground truth:

- **does a scene point keep its word as the view changes**: of the descriptor pairs matched between
  frames ``gap`` apart (Lowe's ratio test, then the epipolar inliers the verifier counts), the share
  whose two descriptors get one word (``one_word``). A word that changes with the view is a place's
  observation missed on a revisit;
- **how much two unrelated views share**: the share of a frame's words that the frame ``far_gap``
  later holds too (``shared_far``), against the next frame (``shared_next``). FAB-MAP's evidence for a
  place is the gap between what a revisit shares and what any other frame shares by chance.

Word usage is summed up by its perplexity (``exp`` of the entropy of how often each word is used: the
number of equally used words that would be as spread), and each image by its number of distinct words.
Every figure is about the quantizer on these features, so two vocabularies of one feature type compare
on the same pairs. The pairs are those the descriptors match, so they lean towards words found in the
descriptors' own space (k-means'): views the descriptor does not match count for no vocabulary.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.vocabulary.base import Quantizer


@dataclass(frozen=True)
class GapAgreement:
    """How often matched descriptor pairs between frames ``gap`` apart get one word."""

    gap: int
    pairs: int
    one_word: float  # NaN with no pairs


@dataclass(frozen=True)
class WordStatistics:
    """A vocabulary's words on one image sequence (module docstring)."""

    size: int  # words in the vocabulary
    used: int  # words at least one descriptor of the sequence falls in
    perplexity: float
    words_per_image: float  # distinct words, mean over the frames
    agreement: tuple[GapAgreement, ...]
    shared_next: float  # NaN with fewer than two frames with features
    shared_far: float  # NaN when no frame pair is far_gap apart
    far_gap: int


def word_statistics(quantizer: Quantizer, features: Sequence[Features], pairs_by_gap: Mapping[int, np.ndarray],
                    far_gap: int = 50) -> WordStatistics:
    """The statistics of ``quantizer``'s words on ``features`` (frames in order).

    ``pairs_by_gap``: frame gap -> (M, 2) rows into the frames' descriptors concatenated in order, the
    two descriptors of one scene point (``model.training.pairs_at_gap``).
    """
    if far_gap < 1:
        raise ConfigError(f"far_gap={far_gap} must be >= 1")
    counts = np.array([len(f.descriptors) for f in features], np.int64)
    if counts.sum() == 0:
        raise DataError("no frame of the sequence has features: there are no words to count")
    words = quantizer.quantize(np.concatenate([f.descriptors for f in features]))
    per_frame = [np.unique(chunk) for chunk in np.split(words, np.cumsum(counts)[:-1])]
    return WordStatistics(
        size=quantizer.size,
        used=int(np.unique(words).size),
        perplexity=usage_perplexity(words, quantizer.size),
        words_per_image=float(np.mean([len(w) for w, n in zip(per_frame, counts, strict=True) if n > 0])),
        agreement=tuple(pair_agreement(words, gap, pairs) for gap, pairs in sorted(pairs_by_gap.items())),
        shared_next=shared_words(per_frame, 1),
        shared_far=shared_words(per_frame, far_gap),
        far_gap=far_gap,
    )


def usage_perplexity(words: np.ndarray, size: int) -> float:
    """``exp`` of the entropy of the words' usage: ``size`` when every word is used equally, 1 for one word."""
    share = np.bincount(words, minlength=size) / max(1, words.size)
    share = share[share > 0]
    return float(np.exp(-np.sum(share * np.log(share))))


def pair_agreement(words: np.ndarray, gap: int, pairs: np.ndarray) -> GapAgreement:
    """Share of ``pairs`` (rows into ``words``) whose two rows have one word."""
    if pairs.ndim != 2 or pairs.shape[1] != 2 or (pairs.size and (pairs.min() < 0 or pairs.max() >= words.size)):
        raise DataError(f"pairs at gap {gap} must be (M, 2) rows into {words.size} descriptors, got shape "
                        f"{pairs.shape}")
    if len(pairs) == 0:
        return GapAgreement(gap, 0, float("nan"))
    return GapAgreement(gap, len(pairs), float(np.mean(words[pairs[:, 0]] == words[pairs[:, 1]])))


def shared_words(per_frame: Sequence[np.ndarray], gap: int) -> float:
    """Mean over frames i with words of the share of frame i's distinct words that frame i + gap holds too."""
    shares = [np.intersect1d(per_frame[i], per_frame[i + gap], assume_unique=True).size / per_frame[i].size
              for i in range(len(per_frame) - gap) if per_frame[i].size and per_frame[i + gap].size]
    return float(np.mean(shares)) if shares else float("nan")
