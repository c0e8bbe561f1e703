"""FAB-MAP 2's place storage: places as sparse word lists in a growable posting pool, an inverted index
word -> places, and the compiled (numba) kernels of the query and of posting storage.

Places are stored sparsely (their word ids); memory grows with the number of stored words.
"""

from __future__ import annotations

import time

import numba
import numpy as np

from aefabmap_ros.fabmap.observation import FabMapModel, QueryState


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
