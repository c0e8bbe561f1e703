"""FAB-MAP 1 (exact reference) and FAB-MAP 2 (inverted index), with openFABMAP's semantics.

Both score log p(Z | L), the sum over words of the observation model in ``observation.py``.
FAB-MAP 1 evaluates that sum over all V words for every place (O(V) per place).
FAB-MAP 2 stores, per word, the log-ratio of a place having versus not having the word in the
four (z_q, z_p) cases (openFABMAP's d1..d4), so a place's score relative to an empty place is
``sum_{q in L} d1[q]`` (its *default*, computed when it is added) plus corrections only for
words the query observed (d3 / d4) and unobserved children of observed words (d2), found
through an inverted index word -> places. The difference between any two places is exactly
FAB-MAP 1's.

New place: "sampled" = log of the mean likelihood of the training samples, scored through the
same machinery (FAB-MAP 2: in the relative scale; openFABMAP's FAB-MAP 2 averages over ALL
samples); "meanfield" = the likelihood of a place whose word-existence probabilities are the
marginals p(z_q) (in FAB-MAP 2's relative scale: minus the empty place's log-likelihood).

The places' storage and inverted index are ``index.py``, the posterior over {new, places}
``posterior.py``, the settings ``config.py``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import ClassVar

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import NEW_PLACE_MODELS, FabMapConfig
from aefabmap_ros.fabmap.index import InvertedIndex
from aefabmap_ros.fabmap.observation import FabMapModel, QueryState, rows_to_word_ids

# --------------------------------------------------------------------------------------------
# FAB-MAP 2 and FAB-MAP 1 engines (offline and online share them)


class FabMapEngine(ABC):
    """What both engines share: the places and new-place samples (word sets in an ``InvertedIndex``,
    the one place store the recognizer and the map file read), and the new-place model. Subclasses
    say how a query is scored against them."""

    method: ClassVar[str]

    def __init__(
        self,
        model: FabMapModel,
        new_place_samples: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray] | None,
        new_place_model: str = "sampled",
    ) -> None:
        if new_place_model not in NEW_PLACE_MODELS:
            raise ConfigError(f"new_place_model = {new_place_model!r}: must be one of {NEW_PLACE_MODELS}")
        self.model = model
        self.new_place_model = new_place_model
        self.places = InvertedIndex(model)
        self.samples = InvertedIndex(model)
        if new_place_samples is not None:
            rows = rows_to_word_ids(new_place_samples, model.vocabulary_size)
            lengths = np.array([r.size for r in rows], dtype=np.int64)
            indptr = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
            indices = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
            self.samples.add_many(indptr, indices)
        if new_place_model == "sampled" and self.samples.num_places == 0:
            raise DataError("the 'sampled' new-place model needs at least one new-place sample")

    @property
    def num_places(self) -> int:
        return self.places.num_places

    def add(self, word_ids: np.ndarray) -> int:
        return self.places.add(word_ids)

    def clear(self) -> None:
        """Forget every place (the new-place samples stay: they belong to the model)."""
        self.places = InvertedIndex(self.model)

    @abstractmethod
    def log_likelihoods(self, word_ids: np.ndarray, exclude_sample: int | None = None) -> tuple[float, np.ndarray]:
        """(new-place log-likelihood, (P,) place log-likelihoods) of validated word ids."""


class FabMap2(FabMapEngine):
    """FAB-MAP 2: scores through the inverted index, relative to an empty place."""

    method = "fabmap2"

    def place_log_likelihoods(self, state: QueryState) -> np.ndarray:
        return self.places.scores(state)

    def sample_log_likelihoods(self, state: QueryState) -> np.ndarray:
        return self.samples.scores(state)

    def new_place_log_likelihood(self, state: QueryState, exclude_sample: int | None = None) -> float:
        if self.new_place_model == "meanfield":
            return self.model.meanfield_log_likelihood(state, relative=True)
        return _log_mean_exp(self.sample_log_likelihoods(state), exclude_sample)

    def log_likelihoods(self, word_ids: np.ndarray, exclude_sample: int | None = None) -> tuple[float, np.ndarray]:
        state = self.model.query_state(word_ids)
        return self.new_place_log_likelihood(state, exclude_sample), self.place_log_likelihoods(state)


class FabMap1(FabMapEngine):
    """FAB-MAP 1: exact O(V) sum per place (absolute log-likelihoods); the reference for FAB-MAP 2.
    It reads the places' word sets from the shared store and never its postings."""

    method = "fabmap1"

    def _exact(self, index: InvertedIndex, word_ids: np.ndarray) -> np.ndarray:
        query = np.zeros(self.model.vocabulary_size, dtype=bool)
        query[word_ids] = True
        place = np.zeros(self.model.vocabulary_size, dtype=bool)
        out = np.empty(index.num_places)
        for i in range(index.num_places):
            place[:] = False
            place[index.place_words(i)] = True
            out[i] = self.model.exact_log_likelihood(query, place)
        return out

    def log_likelihoods(self, word_ids: np.ndarray, exclude_sample: int | None = None) -> tuple[float, np.ndarray]:
        places = self._exact(self.places, word_ids)
        if self.new_place_model == "meanfield":
            new = self.model.meanfield_log_likelihood(self.model.query_state(word_ids), relative=False)
        else:
            new = _log_mean_exp(self._exact(self.samples, word_ids), exclude_sample)
        return new, places


def _log_mean_exp(log_values: np.ndarray, exclude: int | None) -> float:
    if exclude is not None:
        if not 0 <= exclude < log_values.size:
            raise DataError(f"exclude_sample {exclude} out of range for {log_values.size} samples")
        if log_values.size == 1:
            raise DataError("cannot exclude the only new-place sample")
        log_values = np.delete(log_values, exclude)
    peak = np.max(log_values)  # numpy, not scipy's logsumexp: ~10x less overhead per call
    return float(peak + np.log(np.mean(np.exp(log_values - peak))))


# --------------------------------------------------------------------------------------------
# Engine by name


ENGINES: dict[str, type[FabMapEngine]] = {"fabmap2": FabMap2, "fabmap1": FabMap1}


def make_engine(
    tree: ChowLiuTree,
    new_place_samples: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray] | None,
    config: FabMapConfig,
    engine: str = "fabmap2",
) -> FabMapEngine:
    """The engine ``engine`` (a key of ENGINES) on ``tree`` with ``config``'s detector and new-place model."""
    if engine not in ENGINES:
        raise ConfigError(f"engine = {engine!r}: must be one of {tuple(ENGINES)}")
    model = FabMapModel(tree, config.p_z_given_e, config.p_z_given_not_e)
    engine_class = ENGINES[engine]
    samples = new_place_samples if config.new_place_model == "sampled" else None
    return engine_class(model, samples, config.new_place_model)
