"""FAB-MAP 2's compiled (numba) kernels: a query's scores over a range of places, and posting storage.

Single-threaded each, and releasing the GIL (``nogil``): fabmap/index.py runs one per range of places on as
many threads as the process may use, and every place's score is summed in the same order whatever the split
(its default, then the byte tables of its frequent words four groups at a time, then its postings word by
word), so a split changes no bit of the result. ``cache=True`` keeps the compiled code in __pycache__ (or
numba's user cache dir when the package is read-only), so only the first process on a machine compiles them.
"""

from __future__ import annotations

import time

import numba
import numpy as np

# All 256 bytes as bits (256, 8): row b = the bits of b, least significant first.
BYTE_BITS = ((np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1).astype(np.float64)


@numba.njit(cache=True, nogil=True)
def add_byte_tables(
    scores: np.ndarray, bits: np.ndarray, groups: np.ndarray, tables: np.ndarray, first: int, end: int
) -> None:
    """scores[p - first] += sum_k tables[k, bits[groups[k], p]] for first <= p < end.

    scores (end - first,) float64, bits (G, capacity) uint8, groups (K,) int64, tables (K, 256) float64.
    Four groups per pass over ``scores``: the read-modify-write of scores, not the look-ups, bounds
    a one-group pass.
    """
    n_groups = groups.size
    k = 0
    while k + 4 <= n_groups:
        b0, b1, b2, b3 = bits[groups[k]], bits[groups[k + 1]], bits[groups[k + 2]], bits[groups[k + 3]]
        t0, t1, t2, t3 = tables[k], tables[k + 1], tables[k + 2], tables[k + 3]
        for p in range(first, end):
            scores[p - first] += (t0[b0[p]] + t1[b1[p]]) + (t2[b2[p]] + t3[b3[p]])
        k += 4
    while k < n_groups:
        b0, t0 = bits[groups[k]], tables[k]
        for p in range(first, end):
            scores[p - first] += t0[b0[p]]
        k += 1


@numba.njit(cache=True, nogil=True)
def scatter_postings(
    scores: np.ndarray, pool: np.ndarray, starts: np.ndarray, lengths: np.ndarray, words: np.ndarray,
    weights: np.ndarray, first: int, end: int,
) -> None:
    """scores[p - first] += weight for every place first <= p < end of each word's posting, for each (word,
    weight) in (words, weights).

    Postings hold increasing place ids: the range of each is found by bisection. A place occurs at most once
    per posting, so the adds of one word never collide.
    """
    for k in range(words.size):
        word = words[k]
        weight = weights[k]
        low, high = starts[word], starts[word] + lengths[word]
        stop = high
        while low < high:  # the first entry >= first
            middle = (low + high) // 2
            if pool[middle] < first:
                low = middle + 1
            else:
                high = middle
        j = low
        while j < stop:
            place = pool[j]
            if place >= end:
                break
            scores[place - first] += weight
            j += 1


@numba.njit(cache=True, nogil=True)
def move_blocks(
    source: np.ndarray, destination: np.ndarray, old_starts: np.ndarray, new_starts: np.ndarray,
    lengths: np.ndarray,
) -> None:
    """destination[new_starts[k] + j] = source[old_starts[k] + j] for j < lengths[k] (blocks must not overlap)."""
    for k in range(lengths.size):
        old, new = old_starts[k], new_starts[k]
        for j in range(lengths[k]):
            destination[new + j] = source[old + j]


@numba.njit(cache=True, nogil=True)
def count_words(indices: np.ndarray, counts: np.ndarray) -> None:
    """counts[w] += occurrences of w in indices (np.bincount would first copy int32 ids to int64)."""
    for k in range(indices.size):
        counts[indices[k]] += 1


@numba.njit(cache=True, nogil=True)
def append_places(
    indptr: np.ndarray, indices: np.ndarray, first_place: int, dense_slot: np.ndarray, d1: np.ndarray,
    bits: np.ndarray, pool: np.ndarray, starts: np.ndarray, lengths: np.ndarray, defaults: np.ndarray,
    owner: np.ndarray, part: int,
) -> None:
    """Store places first_place + i (CSR rows i of word ids) in the bits and the (reserved) postings: the part
    of the work that is ``part``'s, so that several threads can share a bulk load.

    indptr (N + 1,) int64, indices int32, dense_slot (V,) int64 (-1 = posting), d1 (V,) float64,
    bits (G, capacity) uint8, pool int32, starts/lengths (V,) int64, owner (V,) int64: the part that stores
    each word's posting. Part 0 also sets the bits and writes defaults (N,) float64 (the sum of d1 over each
    row, in row order as np.bincount would). Rows are visited in order, so postings stay in increasing place
    order; the parts write disjoint postings and only part 0 the bits and defaults.
    """
    for i in range(indptr.size - 1):
        place = first_place + i
        default = 0.0
        for j in range(indptr[i], indptr[i + 1]):
            word = indices[j]
            slot = dense_slot[word]
            if part == 0:
                default += d1[word]
                if slot >= 0:
                    bits[slot >> 3, place] |= np.uint8(1 << (slot & 7))
            if slot < 0 and owner[word] == part:
                pool[starts[word] + lengths[word]] = place
                lengths[word] += 1
        if part == 0:
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
    add_byte_tables(scores, bits, ids, np.zeros((1, 256)), 0, 1)
    scatter_postings(scores, pool, ids, ids, ids, scores, 0, 1)
    move_blocks(pool, pool, ids, ids, ids)
    count_words(pool, ids.copy())
    append_places(np.zeros(1, dtype=np.int64), pool, 0, ids, scores, bits, pool, ids, ids.copy(), scores.copy(),
                  ids, 0)
    return time.perf_counter() - start
