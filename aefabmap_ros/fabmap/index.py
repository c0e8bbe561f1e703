"""FAB-MAP 2's place storage: places as sparse word lists, an inverted index word -> places in a growable
posting pool, and a query's scores over every place, on as many threads as the process may use
(fabmap/kernels.py has the compiled kernels).

Places are stored sparsely (their word ids); memory grows with the number of stored words: about 2 bytes per
(place, word) for the word lists, 4 for the postings, and ``max_dense_words / 8`` bytes and one float64 per
place.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from aefabmap_ros.fabmap.kernels import (
    BYTE_BITS,
    add_byte_tables,
    append_places,
    count_words,
    move_blocks,
    scatter_postings,
)
from aefabmap_ros.fabmap.kernels import warm_up_kernels as warm_up_kernels
from aefabmap_ros.fabmap.observation import FabMapModel, QueryState

# A query is split over threads only for maps this large per thread: below it a thread's start costs more
# than it saves.
MIN_PLACES_PER_THREAD = 32_768
# Rows a bulk load stores at a time: its temporaries (the int32 word ids of a chunk) stay small.
BULK_CHUNK_ROWS = 65_536


def scoring_threads() -> int:
    """Threads a query's scoring may use: NUMBA_NUM_THREADS when set (aefabmap_launch sets it to each
    process's share of the cores), else the cores this process may run on."""
    configured = os.environ.get("NUMBA_NUM_THREADS", "")
    if configured.isdigit() and int(configured) > 0:
        return int(configured)
    return max(len(os.sched_getaffinity(0)), 1)


_executors: dict[int, ThreadPoolExecutor] = {}


def _shared_executor(threads: int) -> ThreadPoolExecutor:
    """One pool of ``threads`` scoring threads per process, made on first use (the kernels release the GIL)."""
    if threads not in _executors:
        _executors[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="fabmap-scores")
    return _executors[threads]


class GrowableArray:
    """A 1-D numpy buffer with amortised O(1) append (capacity 1.5x when full, or exactly as reserved)."""

    def __init__(self, dtype: np.dtype | type, capacity: int = 16) -> None:
        self._data = np.empty(max(capacity, 1), dtype=dtype)
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def adopt(self, values: np.ndarray) -> None:
        """Become ``values`` (of this array's type, 1-D, contiguous), without a copy: an empty index takes a
        loaded map's word ids as they are, instead of holding them twice while it loads. When ``values`` are the
        first of a larger 1-D buffer of theirs (a map read with room to grow), the buffer is the capacity."""
        if self._size or values.dtype != self._data.dtype or values.ndim != 1 or not values.flags.c_contiguous:
            raise ValueError("adopt needs an empty array and contiguous values of its type")
        base = values.base
        starts_base = (isinstance(base, np.ndarray) and base.ndim == 1 and base.dtype == values.dtype
                       and base.flags.c_contiguous and base.size >= values.size
                       and base.__array_interface__["data"][0] == values.__array_interface__["data"][0])
        self._data = base if isinstance(base, np.ndarray) and starts_base else values
        self._size = values.size

    def reserve(self, capacity: int) -> None:
        """Room for ``capacity`` values in all: a bulk load that knows its size wastes no capacity."""
        if capacity > self._data.size:
            grown = np.empty(capacity, dtype=self._data.dtype)
            grown[: self._size] = self._data[: self._size]
            self._data = grown

    def extend(self, values: np.ndarray) -> None:
        need = self._size + values.size
        if need > self._data.size:
            self.reserve(max(need, self._data.size + self._data.size // 2))
        self._data[self._size : need] = values
        self._size = need

    def view(self) -> np.ndarray:
        return self._data[: self._size]

    @property
    def nbytes(self) -> int:
        return int(self._data.nbytes)


def _exclusive_cumsum(values: np.ndarray) -> np.ndarray:
    out = np.zeros(values.size, dtype=np.int64)
    np.cumsum(values[:-1], out=out[1:])
    return out


class PostingPool:
    """word -> increasing place ids, all words' postings in one int32 pool (a growable CSR).

    Word w's posting is ``pool[starts[w] : starts[w] + lengths[w]]`` inside a block of
    ``capacities[w]`` slots. A block that overflows moves to the free end of the pool with room to
    grow (its old slots become garbage): half its size again when places come one at a time, an eighth
    after a bulk load (a map loaded from a file). When the free end runs out, the live blocks are moved
    down over the garbage in place and the pool is resized (``ndarray.resize``: a realloc, which for a
    large pool remaps its pages rather than copying them), with an eighth of the live size free at the end.
    Appends are amortised O(1) per (place, word); a bulk-loaded pool is ~1.25x the stored pairs.
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

    def reserve(self, counts: np.ndarray, bulk: bool = False) -> None:
        """Make room for ``counts[w]`` more places in each word w's posting ((V,) int64); appending is
        then ``pool[starts[w] + lengths[w]] = place; lengths[w] += 1`` (see ``kernels.append_places``).
        ``bulk``: the counts are a large batch's, so the blocks get an eighth to grow instead of a half."""
        need = self.lengths + counts
        moving = np.flatnonzero(need > self.capacities)
        if moving.size:
            self._relocate(moving, need[moving], 8 if bulk else 2)

    def _relocate(self, words: np.ndarray, need: np.ndarray, slack_divisor: int) -> None:
        capacity = need + need // slack_divisor + 4
        total = int(capacity.sum())
        if self._end + total > self._pool.size:
            self._repack(total)
        new_starts = self._end + _exclusive_cumsum(capacity)
        move_blocks(self._pool, self._pool, self.starts[words], new_starts, self.lengths[words])
        self.starts[words] = new_starts
        self.capacities[words] = capacity
        self._end += total

    def _repack(self, reserve: int) -> None:
        """Move the live blocks down over the garbage, in place and in the order they lie (each moves to a lower
        address, never over a block not moved yet), then resize the pool to hold ``reserve`` more slots and an
        eighth of all of them free."""
        held = np.flatnonzero(self.capacities > 0)
        order = held[np.argsort(self.starts[held], kind="stable")]
        new_starts = _exclusive_cumsum(self.capacities[order])
        move_blocks(self._pool, self._pool, self.starts[order], new_starts, self.lengths[order])
        self.starts[order] = new_starts
        live = int(self.capacities.sum())
        self._pool.resize(live + reserve + (live + reserve) // 8, refcheck=False)
        self._end = live

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
    ``max_dense_words / 8`` bytes per place.
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
        """(indptr (P + 1,) int64, indices) of all places' words: views, the ids in their stored type (uint16
        when the vocabulary fits, else int32), so saving a large map copies nothing."""
        return self._word_ptr.view(), self._word_data.view()

    def add(self, word_ids: np.ndarray) -> int:
        """Append one place (validated sorted unique word ids); returns its index."""
        index = self.num_places
        self.add_many(np.array([0, word_ids.size], dtype=np.int64), word_ids)
        return index

    def add_many(self, indptr: np.ndarray, indices: np.ndarray) -> None:
        """Append places given as CSR rows (indices sorted unique per row, in range, any integer type).

        Every array is sized once for the whole batch; the rows are then stored a chunk at a time in one
        compiled pass over the (place, word) pairs, so a large map loads without temporaries of its size.
        """
        n_new = indptr.size - 1
        first = self.num_places
        indptr = np.ascontiguousarray(indptr, dtype=np.int64)
        bulk = n_new >= 256
        counts = np.zeros(self._model.vocabulary_size, dtype=np.int64)
        for start in range(0, n_new, BULK_CHUNK_ROWS):
            end = min(start + BULK_CHUNK_ROWS, n_new)
            count_words(np.ascontiguousarray(indices[indptr[start]:indptr[end]], dtype=np.int32), counts)
        counts[self._dense_slot >= 0] = 0
        self._postings.reserve(counts, bulk)
        self._reserve_bits(first, first + n_new)
        pairs = indices[indptr[0]:indptr[-1]]
        adopted = first == 0 and pairs.dtype == self._word_data.view().dtype and pairs.flags.c_contiguous
        if adopted:
            self._word_data.adopt(pairs)
        elif bulk:
            self._word_data.reserve(len(self._word_data) + pairs.size)
        if bulk:
            self._word_ptr.reserve(len(self._word_ptr) + n_new)
            self._defaults.reserve(first + n_new)
        for start in range(0, n_new, BULK_CHUNK_ROWS):
            end = min(start + BULK_CHUNK_ROWS, n_new)
            self._append_rows(indptr[start:end + 1], indices[indptr[start]:indptr[end]], first + start, adopted)

    def _append_rows(self, indptr: np.ndarray, indices: np.ndarray, first: int, words_stored: bool) -> None:
        """Store one chunk of rows. A large chunk is shared by the scoring threads: the postings are split
        between them by word (each appends its own words' only), the bits and defaults are the first's."""
        rows = np.ascontiguousarray(indices, dtype=np.int32)
        local = indptr - indptr[0]
        defaults = np.empty(local.size - 1)
        postings = self._postings
        parts = max(1, min(scoring_threads(), rows.size // (MIN_PLACES_PER_THREAD * 16)))
        owner = np.arange(self._model.vocabulary_size, dtype=np.int64) % parts

        def append(part: int) -> None:
            append_places(local, rows, first, self._dense_slot, self._model.d1, self._bits, postings.pool,
                          postings.starts, postings.lengths, defaults, owner, part)

        if parts == 1:
            append(0)
        else:
            list(_shared_executor(parts).map(append, range(parts)))
        self._defaults.extend(defaults)
        if not words_stored:
            self._word_data.extend(rows)  # cast to the stored dtype on copy
        self._word_ptr.extend(self._word_ptr.view()[-1] + local[1:])

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

    def scores(self, state: QueryState, threads: int | None = None) -> np.ndarray:
        """(P,) float64 FAB-MAP 2 log-likelihood of every place relative to an empty place.

        The places are split in contiguous ranges over ``threads`` (default ``scoring_threads()``; at least
        ``MIN_PLACES_PER_THREAD`` places each); every place's score is summed in the same order whatever the
        split, so the result does not depend on it.
        """
        num_places = self.num_places
        scores = np.empty(num_places)
        groups, tables = self._byte_tables(state)
        sparse = self._dense_slot[state.touched] < 0
        words, weights = state.touched[sparse], state.corrections[sparse]
        defaults, postings = self._defaults.view(), self._postings

        def score_range(first: int, end: int) -> None:
            part = scores[first:end]
            part[:] = defaults[first:end]
            add_byte_tables(part, self._bits, groups, tables, first, end)
            scatter_postings(part, postings.pool, postings.starts, postings.lengths, words, weights, first, end)

        count = max(1, min(threads or scoring_threads(), num_places // MIN_PLACES_PER_THREAD))
        bounds = np.linspace(0, num_places, count + 1).astype(np.int64)
        if count == 1:
            score_range(0, num_places)
        else:
            list(_shared_executor(count).map(score_range, bounds[:-1].tolist(), bounds[1:].tolist()))
        return scores

    def _byte_tables(self, state: QueryState) -> tuple[np.ndarray, np.ndarray]:
        """The groups of frequent words the query touches and, per group, the 256-entry table of corrections:
        tables[k, b] is the sum of the corrections of group groups[k]'s words whose bits are set in byte b."""
        slots = self._dense_slot[state.touched]
        dense = slots >= 0
        if not np.any(dense):
            return np.zeros(0, dtype=np.int64), np.zeros((0, 256))
        weights = np.zeros(8 * self._bits.shape[0])
        weights[slots[dense]] = state.corrections[dense]
        group_weights = weights.reshape(-1, 8)
        groups = np.flatnonzero(np.any(group_weights != 0, axis=1))
        return groups, np.ascontiguousarray(group_weights[groups] @ BYTE_BITS.T)

    @property
    def nbytes(self) -> int:
        return int(
            self._word_data.nbytes + self._word_ptr.nbytes + self._defaults.nbytes + self._postings.nbytes
            + self._bits.nbytes
        )
