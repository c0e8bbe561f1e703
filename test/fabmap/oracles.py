"""Test-only oracles of the FAB-MAP engines: openFABMAP's look-up-table FAB-MAP 1 and its golden-run scorer.

Neither runs in the library: they reproduce openFABMAP's offline runs (``../shared/golden``) so the tests
can compare the engines with openFABMAP's numbers, and the online recognizer with an offline run.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.engines import ENGINES, FabMap1, FabMapEngine, make_engine
from aefabmap_ros.fabmap.index import InvertedIndex
from aefabmap_ros.fabmap.observation import FabMapModel, rows_to_word_ids
from aefabmap_ros.fabmap.posterior import motion_log_prior, posterior


class FabMapLUT(FabMap1):
    """openFABMAP's FabMapLUT: FAB-MAP 1 with each log term truncated to ``precision`` decimals.

    openFABMAP stores ``-(int)(log p * 10^precision)`` per (word, z_q, z_p, L_q) and sums those
    integers, so every term is truncated toward zero; its mean-field new place stays exact.
    """

    method = "fabmaplut"

    def __init__(
        self,
        model: FabMapModel,
        new_place_samples: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray] | None,
        new_place_model: str = "meanfield",
        precision: int = 6,
    ) -> None:
        super().__init__(model, new_place_samples, new_place_model)
        scale = 10.0**precision
        self._lut = np.trunc(model.log_table[:, :, :, :2] * scale) / scale  # (V, 2, 2, 2)

    def _exact(self, index: InvertedIndex, word_ids: np.ndarray) -> np.ndarray:
        zq = np.zeros(self.model.vocabulary_size, dtype=np.int64)
        zq[word_ids] = 1
        words = np.arange(self.model.vocabulary_size)
        terms = self._lut[words, zq, zq[self.model.parent]]  # (V, 2): place lacks / has the word
        out = np.empty(index.num_places)
        for i in range(index.num_places):
            has = np.zeros(self.model.vocabulary_size, dtype=np.int64)
            has[index.place_words(i)] = 1
            out[i] = float(terms[words, has].sum())
        return out


ORACLE_METHODS = (*ENGINES, "fabmaplut")


@dataclass(frozen=True)
class ScoreMatrices:
    """openFABMAP golden layout: row i = query i; [i, j < i] place j; [i, i] new place; above: 0 / NaN."""

    probabilities: np.ndarray  # (N, N)
    log_likelihoods: np.ndarray  # (N, N)


def _engine(
    tree: ChowLiuTree,
    new_place_samples: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray] | None,
    config: FabMapConfig,
    method: str,
) -> FabMapEngine:
    """The library's engine of that name, or openFABMAP's look-up-table FAB-MAP 1."""
    if method not in ORACLE_METHODS:
        raise ConfigError(f"method = {method!r}: must be one of {ORACLE_METHODS}")
    if method in ENGINES:
        return make_engine(tree, new_place_samples, config, method)
    model = FabMapModel(tree, config.p_z_given_e, config.p_z_given_not_e)
    samples = new_place_samples if config.new_place_model == "sampled" else None
    return FabMapLUT(model, samples, config.new_place_model)


def fabmap_score_matrices(
    observations: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray],
    tree: ChowLiuTree,
    new_place_samples: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray] | None,
    config: FabMapConfig,
    method: str = "fabmap2",
    exclude_samples: Sequence[int] | None = None,
) -> ScoreMatrices:
    """Run FAB-MAP over a sequence like openFABMAP's golden run: query i vs places 0..i-1, then add it.

    ``method``: "fabmap2" (inverted index, log-likelihoods relative to an empty place), "fabmap1"
    (exact O(V) per place, absolute) or "fabmaplut" (openFABMAP's 6-decimal look-up-table FAB-MAP 1).

    ``exclude_samples[i]`` (optional, -1 = none) is the index of a new-place sample that *is*
    query i, left out of query i's sample mean (samples are identified by index, not by content).
    Only the likelihood and posterior parts of ``config`` apply (no exclusion window, keyframes, ...).
    """
    engine = _engine(tree, new_place_samples, config, method)
    rows = rows_to_word_ids(observations, tree.vocabulary_size)
    n = len(rows)
    if exclude_samples is not None and len(exclude_samples) != n:
        raise DataError(f"exclude_samples has {len(exclude_samples)} entries for {n} observations")
    probabilities = np.zeros((n, n))
    log_likelihoods = np.full((n, n), np.nan)
    previous: np.ndarray | None = None
    for i, words in enumerate(rows):
        exclude = None if exclude_samples is None or exclude_samples[i] < 0 else int(exclude_samples[i])
        new_ll, place_ll = engine.log_likelihoods(words, exclude)
        hypotheses = np.concatenate([[new_ll], place_ll])
        log_prior = (
            motion_log_prior(previous, i, config.p_new, config.motion_bias) if config.motion_model else None
        )
        p = posterior(hypotheses / config.likelihood_temperature, log_prior, config.smoothing)
        previous = p
        probabilities[i, :i] = p[1:]
        probabilities[i, i] = p[0]
        log_likelihoods[i, :i] = place_ll
        log_likelihoods[i, i] = new_ll
        engine.add(words)
    return ScoreMatrices(probabilities=probabilities, log_likelihoods=log_likelihoods)
