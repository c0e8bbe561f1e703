"""FAB-MAP 2's place storage and inverted index against dense references; its kernels warmed up once."""

import numpy as np
import pytest

from aefabmap_ros.fabmap.index import InvertedIndex
from aefabmap_ros.fabmap.observation import FabMapModel
from test.fabmap.test_engines import _random_tree


def _csr(rows):
    indptr = np.concatenate([[0], np.cumsum([r.size for r in rows])]).astype(np.int64)
    return indptr, np.concatenate(rows).astype(np.int64)


# 0.0: every word a bit (10 groups: 4 + 4 + 2 per pass); 0.4: bits and postings; 1.1: postings only.
@pytest.mark.parametrize("dense_min_marginal", [0.0, 0.4, 1.1])
def test_inverted_index_scores_match_a_dense_reference_while_growing(dense_min_marginal):
    rng = np.random.default_rng(3)
    v = 80
    model = FabMapModel(_random_tree(rng, v))
    index = InvertedIndex(model, dense_min_marginal=dense_min_marginal)
    places: list[np.ndarray] = []

    def check():
        for _ in range(3):
            state = model.query_state(np.flatnonzero(rng.random(v) < 0.3))
            correction = np.zeros(v)
            correction[state.touched] = state.corrections
            # score = sum over the place's words of d1 + the query's correction of that word
            expected = np.array([model.d1[w].sum() + correction[w].sum() for w in places])
            np.testing.assert_allclose(index.scores(state), expected, rtol=0, atol=1e-9)

    for phase in ("bulk", "single", "bulk", "single"):
        # A bulk load, then single places (postings relocate and repack), then both again.
        new = [np.flatnonzero(rng.random(v) < rng.uniform(0.05, 0.6)) for _ in range(70)]
        if phase == "bulk":
            index.add_many(*_csr(new))
        else:
            for words in new:
                index.add(words)
        places.extend(new)
        check()
    assert index.num_places == len(places)
    for i in (0, 69, 100, 279):
        np.testing.assert_array_equal(index.place_words(i), places[i])


@pytest.mark.parametrize("dense_min_marginal", [0.0, 0.4, 1.1])
def test_postings_stay_in_place_order_with_bounded_memory(dense_min_marginal):
    rng = np.random.default_rng(8)
    v = 60
    model = FabMapModel(_random_tree(rng, v))
    index = InvertedIndex(model, dense_min_marginal=dense_min_marginal)
    bulk = [np.flatnonzero(rng.random(v) < 0.15) for _ in range(40)]
    index.add_many(*_csr(bulk))
    pool = index.postings
    counts = np.bincount(np.concatenate(bulk), minlength=v)[pool.lengths > 0]
    # A small batch: each posting gets 1.5x + 4 slots, the pool an eighth more as free end.
    total = int(np.sum(counts + counts // 2 + 4))
    assert pool.pool.size == total + total // 8
    online = [np.flatnonzero(rng.random(v) < rng.uniform(0.01, 0.5)) for _ in range(600)]
    for words in online:  # one place at a time: postings move, the pool is repacked
        index.add(words)
    places = bulk + online
    for w in range(v):
        expected = [i for i, words in enumerate(places) if w in set(words.tolist())]
        np.testing.assert_array_equal(index.posting(w), expected)
    stored = int(pool.lengths.sum())
    assert stored == sum(int(np.sum(index._dense_slot[words] < 0)) for words in places)
    assert pool.pool.size <= 4 * stored + 12 * v


def test_warm_up_covers_the_kernel_signatures_of_adds_and_queries():
    from aefabmap_ros.fabmap import kernels as kernels_module

    assert kernels_module.warm_up_kernels() >= 0.0
    kernels = (
        kernels_module.add_byte_tables, kernels_module.scatter_postings, kernels_module.move_blocks,
        kernels_module.count_words, kernels_module.append_places,
    )
    warmed = [list(kernel.signatures) for kernel in kernels]
    rng = np.random.default_rng(4)
    model = FabMapModel(_random_tree(rng, 40))
    index = InvertedIndex(model, dense_min_marginal=0.5)
    rows = [np.flatnonzero(rng.random(40) < 0.4) for _ in range(30)]
    index.add_many(*_csr(rows))
    for words in rows:
        index.add(words)
    index.scores(model.query_state(rows[0]))
    # No new specialisation: the first real query after warm-up compiles nothing.
    assert [list(kernel.signatures) for kernel in kernels] == warmed
    assert all(len(signatures) == 1 for signatures in warmed)


def test_scores_split_over_threads_are_the_same_to_the_bit(monkeypatch):
    """Each place's score is summed in one order whatever the split, so the threads change no bit (no BLAS in
    the kernels); ranges cut inside the bits and inside every posting."""
    from aefabmap_ros.fabmap import index as index_module

    monkeypatch.setattr(index_module, "MIN_PLACES_PER_THREAD", 7)
    rng = np.random.default_rng(11)
    v = 90
    model = FabMapModel(_random_tree(rng, v))
    index = InvertedIndex(model, dense_min_marginal=0.3)
    index.add_many(*_csr([np.flatnonzero(rng.random(v) < rng.uniform(0.05, 0.6)) for _ in range(301)]))
    for _ in range(5):
        state = model.query_state(np.flatnonzero(rng.random(v) < 0.3))
        one = index.scores(state, threads=1)
        for threads in (2, 3, 8):
            np.testing.assert_array_equal(index.scores(state, threads=threads), one)


def test_a_bulk_load_leaves_an_eighth_to_grow():
    rng = np.random.default_rng(12)
    v = 50
    model = FabMapModel(_random_tree(rng, v))
    index = InvertedIndex(model, dense_min_marginal=1.1)  # every word a posting
    rows = [np.flatnonzero(rng.random(v) < 0.2) for _ in range(400)]
    index.add_many(*_csr(rows))
    counts = np.bincount(np.concatenate(rows), minlength=v)
    counts = counts[counts > 0]
    total = int(np.sum(counts + counts // 8 + 4))
    assert index.postings.pool.size == total + total // 8
    for words in rows[:50]:  # then one at a time: blocks move, the pool is compacted in place and resized
        index.add(words)
    for w in range(v):
        expected = [i for i, words in enumerate(rows + rows[:50]) if w in set(words.tolist())]
        np.testing.assert_array_equal(index.posting(w), expected)


def test_a_bulk_load_shared_by_threads_stores_what_one_thread_does(monkeypatch):
    """Several threads append a large batch's postings, each its own words'; the index is the same as one
    thread's. A fresh index takes a batch's word ids of its own type as they are (no copy)."""
    from aefabmap_ros.fabmap import index as index_module

    rng = np.random.default_rng(13)
    v = 70
    model = FabMapModel(_random_tree(rng, v))
    rows = [np.flatnonzero(rng.random(v) < rng.uniform(0.05, 0.5)) for _ in range(500)]
    indptr, indices = _csr(rows)
    single = InvertedIndex(model, dense_min_marginal=0.3)
    single.add_many(indptr, indices)
    monkeypatch.setattr(index_module, "MIN_PLACES_PER_THREAD", 1)
    monkeypatch.setattr(index_module, "scoring_threads", lambda: 3)
    shared = InvertedIndex(model, dense_min_marginal=0.3)
    ids = indices.astype(np.uint16)
    shared.add_many(indptr, ids)
    assert shared.word_csr()[1] is ids or np.shares_memory(shared.word_csr()[1], ids)
    for w in range(v):
        np.testing.assert_array_equal(shared.posting(w), single.posting(w))
    np.testing.assert_array_equal(shared.defaults, single.defaults)
    state = model.query_state(rows[7])
    np.testing.assert_array_equal(shared.scores(state), single.scores(state))
