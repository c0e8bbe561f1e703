"""FAB-MAP 1 (exact reference) and FAB-MAP 2 (inverted index), with openFABMAP's semantics.

Observation model (Cummins & Newman; openFABMAP ``InferBinary::PzqGzpqL``): for word q with
tree parent p, query state z_q, parent state z_p and place L,

    p(z_q | z_p, L) = sum_s p(e_q = s | L) * p(z_q | e_q = s, z_p)
    p(z_q | e_q, z_p) ∝ p(z_q | e_q) p(z_q | z_p) / p(z_q)       (normalised over z_q)
    p(e_q = 1 | L)   = Bayes on the detector model (PzGe, PzGNe) with prior p(z_q)

and log p(Z | L) = sum_q log p(z_q | z_p(q), L). A root word is its own parent.

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

The posterior over {new, places} is ``posterior.py``; the settings are ``config.py``.

Places are stored sparsely (their word ids); memory grows with the number of stored words.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree, binarize_bow
from aefabmap_ros.fabmap.config import NEW_PLACE_MODELS, FabMapConfig

# --------------------------------------------------------------------------------------------
# Per-word model tables


def _detector(z: int, e: int, p_z_given_e: float, p_z_given_not_e: float) -> float:
    """p(z_q = z | e_q = e) of the detector model (openFABMAP PzqGeq)."""
    p = p_z_given_e if e else p_z_given_not_e
    return p if z else 1.0 - p


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

        # log p(z_q | z_p, L) indexed [q, z_q, z_p, L_q]; the last L index 2 = mean-field new place.
        table = np.empty((self.vocabulary_size, 2, 2, 3), dtype=np.float64)
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


# --------------------------------------------------------------------------------------------
# Sparse place storage and inverted index


class GrowableArray:
    """A 1-D numpy buffer with amortised O(1) append (capacity doubling)."""

    def __init__(self, dtype: np.dtype | type, capacity: int = 16) -> None:
        self._data = np.empty(max(capacity, 1), dtype=dtype)
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def extend(self, values: np.ndarray) -> None:
        need = self._size + values.size
        if need > self._data.size:
            grown = np.empty(max(need, 2 * self._data.size), dtype=self._data.dtype)
            grown[: self._size] = self._data[: self._size]
            self._data = grown
        self._data[self._size : need] = values
        self._size = need

    def view(self) -> np.ndarray:
        return self._data[: self._size]

    @property
    def nbytes(self) -> int:
        return int(self._data.nbytes)


# All 256 bytes as bits (256, 8): row b = the bits of b, least significant first.
_BYTE_BITS = ((np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1).astype(np.float64)


# Compiled kernels of the FAB-MAP 2 query and of posting storage. Single-threaded on purpose (the
# latency target is per core); cache=True keeps the compiled code in __pycache__ (or numba's user
# cache dir when the package is read-only), so only the first process on a machine compiles them.


@numba.njit(cache=True, nogil=True)
def _add_byte_tables(
    scores: np.ndarray, bits: np.ndarray, groups: np.ndarray, tables: np.ndarray, num_places: int
) -> None:
    """scores[p] += sum_k tables[k, bits[groups[k], p]] for p < num_places.

    scores (P,) float64, bits (G, capacity) uint8, groups (K,) int64, tables (K, 256) float64.
    Four groups per pass over ``scores``: the read-modify-write of scores, not the look-ups, bounds
    a one-group pass.
    """
    n_groups = groups.size
    k = 0
    while k + 4 <= n_groups:
        b0, b1, b2, b3 = bits[groups[k]], bits[groups[k + 1]], bits[groups[k + 2]], bits[groups[k + 3]]
        t0, t1, t2, t3 = tables[k], tables[k + 1], tables[k + 2], tables[k + 3]
        for p in range(num_places):
            scores[p] += (t0[b0[p]] + t1[b1[p]]) + (t2[b2[p]] + t3[b3[p]])
        k += 4
    while k < n_groups:
        b0, t0 = bits[groups[k]], tables[k]
        for p in range(num_places):
            scores[p] += t0[b0[p]]
        k += 1


@numba.njit(cache=True, nogil=True)
def _scatter_postings(
    scores: np.ndarray, pool: np.ndarray, starts: np.ndarray, lengths: np.ndarray, words: np.ndarray,
    weights: np.ndarray,
) -> None:
    """scores[pool[starts[w] : starts[w] + lengths[w]]] += weight for each (w, weight) in (words, weights).

    A place occurs at most once per posting, so the adds of one word never collide.
    """
    for k in range(words.size):
        word = words[k]
        weight = weights[k]
        start = starts[word]
        for j in range(start, start + lengths[word]):
            scores[pool[j]] += weight


@numba.njit(cache=True, nogil=True)
def _move_blocks(
    source: np.ndarray, destination: np.ndarray, old_starts: np.ndarray, new_starts: np.ndarray,
    lengths: np.ndarray,
) -> None:
    """destination[new_starts[k] + j] = source[old_starts[k] + j] for j < lengths[k] (blocks must not overlap)."""
    for k in range(lengths.size):
        old, new = old_starts[k], new_starts[k]
        for j in range(lengths[k]):
            destination[new + j] = source[old + j]


@numba.njit(cache=True, nogil=True)
def _count_words(indices: np.ndarray, counts: np.ndarray) -> None:
    """counts[w] += occurrences of w in indices (np.bincount would first copy int32 ids to int64)."""
    for k in range(indices.size):
        counts[indices[k]] += 1


@numba.njit(cache=True, nogil=True)
def _append_places(
    indptr: np.ndarray, indices: np.ndarray, first_place: int, dense_slot: np.ndarray, d1: np.ndarray,
    bits: np.ndarray, pool: np.ndarray, starts: np.ndarray, lengths: np.ndarray, defaults: np.ndarray,
) -> None:
    """Store places first_place + i (CSR rows i of word ids) in the bits and the (reserved) postings.

    indptr (N + 1,) int64, indices int32, dense_slot (V,) int64 (-1 = posting), d1 (V,) float64,
    bits (G, capacity) uint8, pool int32, starts/lengths (V,) int64; writes defaults (N,) float64
    (the sum of d1 over each row, in row order as np.bincount would). Rows are visited in order, so
    postings stay in increasing place order.
    """
    for i in range(indptr.size - 1):
        place = first_place + i
        default = 0.0
        for j in range(indptr[i], indptr[i + 1]):
            word = indices[j]
            default += d1[word]
            slot = dense_slot[word]
            if slot >= 0:
                bits[slot >> 3, place] |= np.uint8(1 << (slot & 7))
            else:
                pool[starts[word] + lengths[word]] = place
                lengths[word] += 1
        defaults[i] = default


def warm_up_kernels() -> float:
    """Load the compiled FAB-MAP 2 kernels now (compile them if the cache is cold); returns seconds taken.

    Call at start-up so that the first query does not pay it: ~0.3 s per process with numba's cache
    (its runtime initialises), ~1 s the first time on a machine or after this module changed.
    """
    start = time.perf_counter()
    scores = np.zeros(1)
    ids = np.zeros(1, dtype=np.int64)
    pool = np.zeros(1, dtype=np.int32)
    bits = np.zeros((1, 1), dtype=np.uint8)
    _add_byte_tables(scores, bits, ids, np.zeros((1, 256)), 1)
    _scatter_postings(scores, pool, ids, ids, ids, scores)
    _move_blocks(pool, pool, ids, ids, ids)
    _count_words(pool, ids.copy())
    _append_places(np.zeros(1, dtype=np.int64), pool, 0, ids, scores, bits, pool, ids, ids.copy(), scores.copy())
    return time.perf_counter() - start


def _exclusive_cumsum(values: np.ndarray) -> np.ndarray:
    out = np.zeros(values.size, dtype=np.int64)
    np.cumsum(values[:-1], out=out[1:])
    return out


class PostingPool:
    """word -> increasing place ids, all words' postings in one int32 pool (a growable CSR).

    Word w's posting is ``pool[starts[w] : starts[w] + lengths[w]]`` inside a block of
    ``capacities[w]`` slots. A block that overflows moves to the free end of the pool with 1.5x
    the capacity it needs (its old slots become garbage); when the free end runs out the live blocks
    are repacked into a new pool a quarter larger than they need. Appends are amortised O(1) per
    (place, word); memory is ~1.9x the stored pairs after a bulk load, at most ~4x.
    """

    def __init__(self, vocabulary_size: int) -> None:
        self._pool = np.empty(0, dtype=np.int32)
        self._end = 0  # first free slot of the pool
        self.starts = np.zeros(vocabulary_size, dtype=np.int64)
        self.lengths = np.zeros(vocabulary_size, dtype=np.int64)
        self.capacities = np.zeros(vocabulary_size, dtype=np.int64)

    @property
    def pool(self) -> np.ndarray:
        """The whole int32 pool (including free and garbage slots); index it through starts/lengths."""
        return self._pool

    def posting(self, word: int) -> np.ndarray:
        start = int(self.starts[word])
        return self._pool[start : start + int(self.lengths[word])]

    def reserve(self, counts: np.ndarray) -> None:
        """Make room for ``counts[w]`` more places in each word w's posting ((V,) int64); appending is
        then ``pool[starts[w] + lengths[w]] = place; lengths[w] += 1`` (see ``_append_places``)."""
        need = self.lengths + counts
        moving = np.flatnonzero(need > self.capacities)
        if moving.size:
            self._relocate(moving, need[moving])

    def _relocate(self, words: np.ndarray, need: np.ndarray) -> None:
        # 1.5x slack, also after a bulk load: the places added online next would otherwise move most
        # postings (and repack the pool) within a few frames.
        capacity = need + need // 2 + 4
        total = int(capacity.sum())
        if self._end + total > self._pool.size:
            self._repack(total)
        new_starts = self._end + _exclusive_cumsum(capacity)
        _move_blocks(self._pool, self._pool, self.starts[words], new_starts, self.lengths[words])
        self.starts[words] = new_starts
        self.capacities[words] = capacity
        self._end += total

    def _repack(self, reserve: int) -> None:
        """Copy the live blocks into a new pool with ``reserve`` + a quarter of the total free at the end."""
        live = int(self.capacities.sum())
        pool = np.empty((live + reserve) * 5 // 4, dtype=np.int32)
        new_starts = _exclusive_cumsum(self.capacities)
        _move_blocks(self._pool, pool, self.starts, new_starts, self.lengths)
        self._pool, self.starts, self._end = pool, new_starts, live

    @property
    def nbytes(self) -> int:
        return int(self._pool.nbytes + self.starts.nbytes + self.lengths.nbytes + self.capacities.nbytes)


class InvertedIndex:
    """Places as word lists (CSR) + word -> places postings + each place's FAB-MAP 2 default.

    Frequent words (training marginal >= ``dense_min_marginal``, at most ``max_dense_words``)
    are kept as bits instead of postings: a place holds one bit per frequent word, packed 8 to a
    byte (a *group*), and a query adds, per group, a 256-entry table of its corrections (one
    look-up per place per 8 frequent words instead of one scattered add per place holding each
    word). Other words are postings in a :class:`PostingPool`. Memory is proportional to the number
    of stored (place, word) pairs: uint16/int32 word ids, int32 postings, one float64 default and
    ``max_dense_words / 8`` bytes per place (arrays grow by doubling / 1.5x).
    """

    def __init__(self, model: FabMapModel, dense_min_marginal: float = 0.15, max_dense_words: int = 1024) -> None:
        self._model = model
        vocabulary_size = model.vocabulary_size
        # Word ids of each place (for persistence and keyframing): 2 bytes each when V fits.
        self._word_data = GrowableArray(np.uint16 if vocabulary_size <= 2**16 else np.int32, 1024)
        self._word_ptr = GrowableArray(np.int64, 64)
        self._word_ptr.extend(np.zeros(1, dtype=np.int64))
        self._defaults = GrowableArray(np.float64, 64)
        self._postings = PostingPool(vocabulary_size)
        marginal = model.tree.marginal
        by_frequency = np.argsort(-marginal, kind="stable")
        dense = by_frequency[marginal[by_frequency] >= dense_min_marginal][:max_dense_words]
        self._dense_slot = np.full(vocabulary_size, -1, dtype=np.int64)  # word -> bit slot, -1 = posting
        self._dense_slot[dense] = np.arange(dense.size)
        self._bits = np.zeros(((dense.size + 7) // 8, 0), dtype=np.uint8)  # (groups, place capacity)

    @property
    def num_places(self) -> int:
        return len(self._defaults)

    @property
    def defaults(self) -> np.ndarray:
        """(P,) float64 sum of d1 over each place's words (its score against a query without words)."""
        return self._defaults.view()

    def place_words(self, index: int) -> np.ndarray:
        ptr = self._word_ptr.view()
        return self._word_data.view()[ptr[index] : ptr[index + 1]].astype(np.int64)

    def word_csr(self) -> tuple[np.ndarray, np.ndarray]:
        """(indptr (P + 1,) int64, indices int64) of all places' words."""
        return self._word_ptr.view().copy(), self._word_data.view().astype(np.int64)

    def add(self, word_ids: np.ndarray) -> int:
        """Append one place (validated sorted unique word ids); returns its index."""
        index = self.num_places
        self.add_many(np.array([0, word_ids.size], dtype=np.int64), word_ids)
        return index

    def add_many(self, indptr: np.ndarray, indices: np.ndarray) -> None:
        """Append places given as CSR rows (indices sorted unique per row, in range).

        One compiled pass over the (place, word) pairs; besides the index itself it allocates only
        (V,) and (rows,) arrays (and an int32 copy of ``indices`` if they are not int32 already), so
        loading a large map does not need several times its size in temporaries.
        """
        n_new = indptr.size - 1
        first = self.num_places
        indptr = np.ascontiguousarray(indptr, dtype=np.int64)
        indices = np.ascontiguousarray(indices, dtype=np.int32)
        counts = np.zeros(self._model.vocabulary_size, dtype=np.int64)
        _count_words(indices, counts)
        counts[self._dense_slot >= 0] = 0
        self._postings.reserve(counts)
        self._reserve_bits(first, first + n_new)
        defaults = np.empty(n_new)
        postings = self._postings
        _append_places(
            indptr, indices, first, self._dense_slot, self._model.d1, self._bits,
            postings.pool, postings.starts, postings.lengths, defaults,
        )
        self._defaults.extend(defaults)
        self._word_data.extend(indices)  # cast to the stored dtype on copy
        self._word_ptr.extend(self._word_ptr.view()[-1] + (indptr[1:] - indptr[0]))

    def posting(self, word: int) -> np.ndarray:
        """(n,) int64 increasing ids of the places holding ``word`` (whether stored as bits or a posting)."""
        slot = int(self._dense_slot[word])
        if slot < 0:
            return self._postings.posting(word).astype(np.int64)
        row = self._bits[slot >> 3, : self.num_places]
        return np.flatnonzero(row & (1 << (slot & 7)))

    @property
    def postings(self) -> PostingPool:
        """The postings of the words not stored as bits (read-only use)."""
        return self._postings

    def _reserve_bits(self, filled: int, num_places: int) -> None:
        """Make room for bits of ``num_places`` places, keeping the first ``filled`` columns."""
        capacity = self._bits.shape[1]
        if num_places > capacity:
            # Doubling, except the first allocation (a bulk load) is exact; new columns are zero.
            grown = np.zeros((self._bits.shape[0], max(num_places, 2 * capacity)), dtype=np.uint8)
            grown[:, :filled] = self._bits[:, :filled]
            self._bits = grown

    def scores(self, state: QueryState) -> np.ndarray:
        """(P,) float64 FAB-MAP 2 log-likelihood of every place relative to an empty place."""
        scores = self._defaults.view().copy()
        slots = self._dense_slot[state.touched]
        dense = slots >= 0
        if np.any(dense):
            weights = np.zeros(8 * self._bits.shape[0])
            weights[slots[dense]] = state.corrections[dense]
            group_weights = weights.reshape(-1, 8)
            groups = np.flatnonzero(np.any(group_weights != 0, axis=1))
            # tables[k, b]: sum of the corrections of group groups[k]'s words whose bits are set in byte b.
            tables = np.ascontiguousarray(group_weights[groups] @ _BYTE_BITS.T)
            _add_byte_tables(scores, self._bits, groups, tables, scores.size)
        sparse = ~dense
        postings = self._postings
        _scatter_postings(
            scores, postings.pool, postings.starts, postings.lengths, state.touched[sparse], state.corrections[sparse]
        )
        return scores

    @property
    def nbytes(self) -> int:
        return int(
            self._word_data.nbytes + self._word_ptr.nbytes + self._defaults.nbytes + self._postings.nbytes
            + self._bits.nbytes
        )


# --------------------------------------------------------------------------------------------
# FAB-MAP 2 and FAB-MAP 1 engines (offline and online share them)


class FabMap2:
    """FAB-MAP 2: places in an inverted index; scores relative to an empty place."""

    method = "fabmap2"

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

    def place_log_likelihoods(self, state: QueryState) -> np.ndarray:
        return self.places.scores(state)

    def sample_log_likelihoods(self, state: QueryState) -> np.ndarray:
        return self.samples.scores(state)

    def new_place_log_likelihood(self, state: QueryState, exclude_sample: int | None = None) -> float:
        if self.new_place_model == "meanfield":
            return self.model.meanfield_log_likelihood(state, relative=True)
        return _log_mean_exp(self.sample_log_likelihoods(state), exclude_sample)

    def log_likelihoods(self, word_ids: np.ndarray, exclude_sample: int | None = None) -> tuple[float, np.ndarray]:
        """(new-place log-likelihood, (P,) place log-likelihoods) of validated word ids."""
        state = self.model.query_state(word_ids)
        return self.new_place_log_likelihood(state, exclude_sample), self.place_log_likelihoods(state)


class FabMap1(FabMap2):
    """FAB-MAP 1: exact O(V) sum per place (absolute log-likelihoods); the reference for FAB-MAP 2."""

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


ENGINES: dict[str, type[FabMap2]] = {"fabmap2": FabMap2, "fabmap1": FabMap1}


def make_engine(
    tree: ChowLiuTree,
    new_place_samples: sp.spmatrix | sp.sparray | np.ndarray | Sequence[np.ndarray] | None,
    config: FabMapConfig,
    engine: str = "fabmap2",
) -> FabMap2:
    """The engine ``engine`` (a key of ENGINES) on ``tree`` with ``config``'s detector and new-place model."""
    if engine not in ENGINES:
        raise ConfigError(f"engine = {engine!r}: must be one of {tuple(ENGINES)}")
    model = FabMapModel(tree, config.p_z_given_e, config.p_z_given_not_e)
    engine_class = ENGINES[engine]
    samples = new_place_samples if config.new_place_model == "sampled" else None
    return engine_class(model, samples, config.new_place_model)
