"""FAB-MAP's observation model as tables: per word, the log-probabilities every engine sums.

Observation model (Cummins & Newman; openFABMAP ``InferBinary::PzqGzpqL``): for word q with
tree parent p, query state z_q, parent state z_p and place L,

    p(z_q | z_p, L) = sum_s p(e_q = s | L) * p(z_q | e_q = s, z_p)
    p(z_q | e_q, z_p) ∝ p(z_q | e_q) p(z_q | z_p) / p(z_q)       (normalised over z_q)
    p(e_q = 1 | L)   = Bayes on the detector model (PzGe, PzGNe) with prior p(z_q)

and log p(Z | L) = sum_q log p(z_q | z_p(q), L). A root word is its own parent.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree, binarize_bow


def _detector(z: int, e: int, p_z_given_e: float, p_z_given_not_e: float) -> float:
    """p(z_q = z | e_q = e) of the detector model (openFABMAP PzqGeq)."""
    p = p_z_given_e if e else p_z_given_not_e
    return p if z else 1.0 - p


def _log_table(tree: ChowLiuTree, p_z_given_e: float, p_z_given_not_e: float) -> np.ndarray:
    """log p(z_q | z_p, L) indexed [q, z_q, z_p, L_q] (V, 2, 2, 3); the last L index 2 = mean-field new place."""
    marginal = tree.marginal
    cond = {1: tree.p_given_parent_present, 0: tree.p_given_parent_absent}

    def p_z(q_state: int) -> np.ndarray:
        return marginal if q_state else 1.0 - marginal

    def p_z_given_parent(q_state: int, parent_state: int) -> np.ndarray:
        return cond[parent_state] if q_state else 1.0 - cond[parent_state]

    # p(e_q = 1 | L_q) for a place that has (1) or lacks (0) word q (openFABMAP PeqGLzq).
    p_e_given_l = {}
    for lq in (0, 1):
        alpha = _detector(lq, 1, p_z_given_e, p_z_given_not_e) * marginal
        beta = _detector(lq, 0, p_z_given_e, p_z_given_not_e) * (1.0 - marginal)
        p_e_given_l[lq] = alpha / (alpha + beta)

    table = np.empty((tree.vocabulary_size, 2, 2, 3), dtype=np.float64)
    for zq in (0, 1):
        for zp in (0, 1):
            given_e = {}
            for e in (0, 1):
                alpha = p_z(zq) * _detector(1 - zq, e, p_z_given_e, p_z_given_not_e) * p_z_given_parent(
                    1 - zq, zp
                )
                beta = p_z(1 - zq) * _detector(zq, e, p_z_given_e, p_z_given_not_e) * p_z_given_parent(zq, zp)
                given_e[e] = beta / (alpha + beta)
            for lq in (0, 1):
                pe = p_e_given_l[lq]
                table[:, zq, zp, lq] = np.log((1.0 - pe) * given_e[0] + pe * given_e[1])
            table[:, zq, zp, 2] = np.log((1.0 - marginal) * given_e[0] + marginal * given_e[1])
    return table


class FabMapModel:
    """Log-probability tables of one Chow-Liu tree and detector model, shared by all FAB-MAP variants."""

    def __init__(self, tree: ChowLiuTree, p_z_given_e: float = 0.39, p_z_given_not_e: float = 0.0) -> None:
        if not 0.0 < p_z_given_e < 1.0 or not 0.0 <= p_z_given_not_e < p_z_given_e:
            raise ConfigError(
                f"detector model needs 0 <= p_z_given_not_e < p_z_given_e < 1, got "
                f"p_z_given_e={p_z_given_e!r}, p_z_given_not_e={p_z_given_not_e!r}"
            )
        self.tree = tree
        self.vocabulary_size = tree.vocabulary_size
        self.parent = tree.parent
        table = _log_table(tree, p_z_given_e, p_z_given_not_e)
        table.flags.writeable = False
        self.log_table = table  # (V, 2, 2, 3)

        # FAB-MAP 2 log-ratios "place has q" vs "place lacks q" (openFABMAP d1..d4).
        ratio = table[:, :, :, 1] - table[:, :, :, 0]  # (V, z_q, z_p)
        self.d1 = ratio[:, 0, 0].copy()
        self.d2 = ratio[:, 0, 1] - self.d1
        self.d3 = ratio[:, 1, 0] - self.d1
        self.d4 = ratio[:, 1, 1] - self.d1
        # Mean-field new place minus empty place, and both absolute, for words in state (0, 0).
        self._new_minus_empty = table[:, :, :, 2] - table[:, :, :, 0]
        self._new_minus_empty_00_sum = float(self._new_minus_empty[:, 0, 0].sum())
        self._new_absolute_00_sum = float(table[:, 0, 0, 2].sum())

        # Children lists (CSR) without the self-loop of roots.
        words = np.arange(self.vocabulary_size)
        non_root = self.parent != words
        order = np.argsort(self.parent[non_root], kind="stable")
        self._children = words[non_root][order]
        self._children_ptr = np.zeros(self.vocabulary_size + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.parent[non_root], minlength=self.vocabulary_size), out=self._children_ptr[1:])

    # -- query decomposition ---------------------------------------------------------------

    def check_word_ids(self, word_ids: np.ndarray | Sequence[int]) -> np.ndarray:
        """Validate and normalise word ids: (K,) sorted unique int64 in [0, V); raises DataError."""
        return as_word_ids(word_ids, self.vocabulary_size)

    def query_state(self, word_ids: np.ndarray) -> QueryState:
        """Words whose (z_q, z_p) state differs from (0, 0) and their FAB-MAP 2 corrections."""
        observed = word_ids
        present = np.zeros(self.vocabulary_size, dtype=bool)
        present[observed] = True
        parent_observed = present[self.parent[observed]]
        starts = self._children_ptr[observed]
        lengths = self._children_ptr[observed + 1] - starts
        total = int(lengths.sum())
        if total:
            offsets = np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
            children = self._children[offsets + np.arange(total)]
            children = np.sort(children[~present[children]])
        else:
            children = np.zeros(0, dtype=np.int64)
        weights_observed = np.where(parent_observed, self.d4[observed], self.d3[observed])
        return QueryState(
            observed=observed,
            parent_observed=parent_observed,
            unobserved_children=children,
            touched=np.concatenate([observed, children]),
            corrections=np.concatenate([weights_observed, self.d2[children]]),
        )

    def meanfield_log_likelihood(self, state: QueryState, relative: bool) -> float:
        """Mean-field new-place log-likelihood; relative=True: minus the empty place's (FAB-MAP 2 scale)."""
        zq = np.concatenate([np.ones(state.observed.size, dtype=np.int64),
                             np.zeros(state.unobserved_children.size, dtype=np.int64)])
        zp = np.concatenate([state.parent_observed.astype(np.int64),
                             np.ones(state.unobserved_children.size, dtype=np.int64)])
        q = state.touched
        if relative:
            terms = self._new_minus_empty
            return self._new_minus_empty_00_sum + float(np.sum(terms[q, zq, zp] - terms[q, 0, 0]))
        table = self.log_table
        return self._new_absolute_00_sum + float(np.sum(table[q, zq, zp, 2] - table[q, 0, 0, 2]))

    def exact_log_likelihood(self, query_present: np.ndarray, place_present: np.ndarray) -> float:
        """FAB-MAP 1: absolute log p(Z | L), summing all V words ((V,) bool vectors)."""
        zq = query_present.astype(np.int64)
        zp = zq[self.parent]
        lq = place_present.astype(np.int64)
        return float(self.log_table[np.arange(self.vocabulary_size), zq, zp, lq].sum())


@dataclass(frozen=True)
class QueryState:
    """A query decomposed for FAB-MAP 2 (all arrays int64 word ids or float64 weights)."""

    observed: np.ndarray  # (K,) observed words
    parent_observed: np.ndarray  # (K,) bool: the parent of each observed word is observed
    unobserved_children: np.ndarray  # (C,) unobserved words whose parent is observed
    touched: np.ndarray  # (K + C,) observed then unobserved children
    corrections: np.ndarray  # (K + C,) FAB-MAP 2 correction of a place holding each touched word


def as_word_ids(word_ids: np.ndarray | Sequence[int], vocabulary_size: int) -> np.ndarray:
    """(K,) sorted unique int64 word ids in [0, vocabulary_size); raises DataError naming the bad value."""
    array = np.asarray(word_ids)
    if array.ndim != 1:
        raise DataError(f"word ids must be a 1-D array, got shape {array.shape}")
    if array.size == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.issubdtype(array.dtype, np.integer):
        raise DataError(f"word ids must be integers, got dtype {array.dtype}")
    ids = array.astype(np.int64)
    low, high = int(ids.min()), int(ids.max())
    if low < 0 or high >= vocabulary_size:
        bad = low if low < 0 else high
        raise DataError(f"word id {bad} out of range for a vocabulary of {vocabulary_size} words")
    if ids.size > 1 and not np.all(ids[1:] > ids[:-1]):
        ids = np.unique(ids)
    return ids


def rows_to_word_ids(
    observations: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray], vocabulary_size: int
) -> list[np.ndarray]:
    """(N, V) bag-of-words (dense/sparse, value > 0 = present) or a list of word-id arrays -> word-id arrays."""
    if isinstance(observations, (np.ndarray, sp.spmatrix, sp.sparray)):
        shape = observations.shape
        if len(shape) != 2:
            raise DataError(f"observations must be (N, V), got shape {shape}")
        if shape[1] != vocabulary_size:
            raise DataError(
                f"observations have {shape[1]} words per row but the vocabulary has {vocabulary_size}"
            )
        present = binarize_bow(observations)
        return [present.indices[present.indptr[i] : present.indptr[i + 1]].astype(np.int64)
                for i in range(present.shape[0])]
    return [as_word_ids(row, vocabulary_size) for row in observations]
