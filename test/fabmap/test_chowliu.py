"""Chow-Liu tree: against a brute-force maximum spanning tree, counted frequencies, and openFABMAP's tree."""

import numpy as np
import pytest
import scipy.sparse as sp

from aefabmap_ros.errors import DataError, ModelError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree, learn_chow_liu_tree


def _naive_information(x: np.ndarray, floor: float = 0.01) -> np.ndarray:
    """openFABMAP calcMutInfo, one pair at a time (raw joints, smoothed marginals)."""
    _, v = x.shape
    p1 = (1 - 2 * floor) * x.mean(axis=0) + floor
    info = np.zeros((v, v))
    for a in range(v):
        for b in range(v):
            total = 0.0
            for za in (0, 1):
                for zb in (0, 1):
                    joint = np.mean((x[:, a] == za) & (x[:, b] == zb))
                    pa = p1[a] if za else 1 - p1[a]
                    pb = p1[b] if zb else 1 - p1[b]
                    if joint > 0:
                        total += joint * np.log(joint / (pa * pb))
            info[a, b] = total
    return info


def _prim(weights: np.ndarray) -> set[tuple[int, int]]:
    """Textbook O(V^2) Prim's maximum spanning tree of a dense symmetric weight matrix."""
    v = weights.shape[0]
    in_tree = [0]
    edges = set()
    while len(in_tree) < v:
        best = None
        for a in in_tree:
            for b in range(v):
                if b not in in_tree and (best is None or weights[a, b] > weights[best[0], best[1]]):
                    best = (a, b)
        assert best is not None
        in_tree.append(best[1])
        edges.add((min(best), max(best)))
    return edges


@pytest.mark.parametrize("seed", range(6))
def test_tree_is_the_maximum_spanning_tree_of_exact_information(seed):
    rng = np.random.default_rng(seed)
    n, v = 40, 9
    latent = rng.random((n, 3)) < 0.5
    x = (rng.random((n, v)) < 0.15) | latent[:, rng.integers(0, 3, v)] & (rng.random((n, v)) < 0.7)
    x[:, -1] = False  # a word never seen: its information with others is still nonzero
    info = _naive_information(x.astype(int))
    tree = learn_chow_liu_tree(sp.csr_matrix(x), lower_info_bound=-np.inf)
    mine = {tuple(e) for e in tree.edges().tolist()}
    reference = _prim(info.astype(np.float32).astype(np.float64))
    assert len(mine) == v - 1 and len(tree.roots) == 1
    weight = lambda edges: sum(info[a, b] for a, b in edges)  # noqa: E731
    assert weight(mine) == pytest.approx(weight(reference), abs=1e-6)
    upper = info.astype(np.float32)[np.triu_indices(v, 1)]
    if np.unique(upper).size == upper.size:  # no ties: the tree is unique
        assert mine == reference


def test_conditionals_match_counted_frequencies():
    rng = np.random.default_rng(3)
    x = rng.random((60, 7)) < 0.3
    x[:, 1] |= x[:, 0] & (rng.random(60) < 0.8)
    tree = learn_chow_liu_tree(x)
    n = x.shape[0]
    np.testing.assert_allclose(tree.marginal, 0.98 * x.mean(axis=0) + 0.01)
    for q in range(7):
        p = tree.parent[q]
        if p == q:
            assert tree.p_given_parent_present[q] == tree.p_given_parent_absent[q] == tree.marginal[q]
            continue
        on, off = x[:, p], ~x[:, p]
        expected_on = 0.98 * (x[on, q].sum() / on.sum()) + 0.01 if on.any() else 0.01
        expected_off = 0.98 * (x[off, q].sum() / off.sum()) + 0.01 if off.any() else 0.01
        assert tree.p_given_parent_present[q] == pytest.approx(expected_on)
        assert tree.p_given_parent_absent[q] == pytest.approx(expected_off)
    assert n == 60


def test_strongly_dependent_pair_is_an_edge_and_root_is_its_lower_word():
    rng = np.random.default_rng(0)
    x = rng.random((200, 6)) < 0.3
    x[:, 4] = x[:, 2]  # identical words: the most informative pair
    tree = learn_chow_liu_tree(x, lower_info_bound=-np.inf)
    assert [2, 4] in tree.edges().tolist()
    assert tree.roots.tolist() == [2]


def test_lower_info_bound_drops_edges_into_a_rooted_forest():
    rng = np.random.default_rng(1)
    x = rng.random((300, 6)) < 0.4
    x[:, 1] = x[:, 0]
    x[:, 3] = x[:, 2]
    tree = learn_chow_liu_tree(x, lower_info_bound=0.2)
    assert tree.edges().tolist() == [[0, 1], [2, 3]]
    assert tree.roots.tolist() == [0, 2, 4, 5]
    for q in tree.roots:
        assert tree.p_given_parent_present[q] == tree.marginal[q]


def test_matrix_round_trip_and_validation():
    tree = learn_chow_liu_tree(np.random.default_rng(2).random((30, 5)) < 0.4)
    again = ChowLiuTree.from_matrix(tree.to_matrix())
    np.testing.assert_array_equal(again.to_matrix(), tree.to_matrix())
    assert tree.to_matrix().shape == (4, 5) and tree.vocabulary_size == 5
    bad = tree.to_matrix()
    bad[1, 3] = 1.0
    with pytest.raises(ModelError, match=r"marginal\[3\]"):
        ChowLiuTree.from_matrix(bad)
    cyclic = tree.to_matrix()
    cyclic[0, :] = [1, 0, 0, 0, 0]
    with pytest.raises(ModelError, match="cycle"):
        ChowLiuTree.from_matrix(cyclic)
    out_of_range = tree.to_matrix()
    out_of_range[0, 0] = 7
    with pytest.raises(ModelError, match="out of range"):
        ChowLiuTree.from_matrix(out_of_range)
    with pytest.raises(ModelError, match=r"shape \(4, V\)"):
        ChowLiuTree.from_matrix(np.zeros((3, 5)))
    with pytest.raises(DataError, match="2-D"):
        learn_chow_liu_tree(np.zeros(5))
    with pytest.raises(DataError, match="floor"):
        learn_chow_liu_tree(np.zeros((3, 3)), floor=0.6)


def test_learned_tree_matches_openfabmap_tree(golden_dir):
    from aefabmap_ros.fabmap.openfabmap import read_bow, read_chow_liu_tree

    golden = read_chow_liu_tree(golden_dir / "tree.yml")
    bow = read_bow(golden_dir / "bowtrain.yml")
    mine = learn_chow_liu_tree(bow, lower_info_bound=0.0005)
    assert mine.roots.tolist() == golden.roots.tolist()
    np.testing.assert_allclose(mine.marginal, golden.marginal, rtol=0, atol=1e-15)
    golden_edges = {tuple(e) for e in golden.edges().tolist()}
    mine_edges = {tuple(e) for e in mine.edges().tolist()}
    # openFABMAP ranks float32 informations; equal ones are in thread-dependent order (OpenMP),
    # so edges may differ only by swapping an edge for another one of the same float32 information.
    info = _edge_information(bow > 0)
    only_golden = sorted(info(a, b) for a, b in golden_edges - mine_edges)
    only_mine = sorted(info(a, b) for a, b in mine_edges - golden_edges)
    assert only_golden == only_mine
    assert len(golden_edges - mine_edges) <= 2
    same_parent = mine.parent == golden.parent
    for row in ("p_given_parent_present", "p_given_parent_absent"):
        np.testing.assert_allclose(getattr(mine, row)[same_parent], getattr(golden, row)[same_parent], atol=1e-15)


def _edge_information(x: np.ndarray):
    n = x.shape[0]
    p1 = 0.98 * x.mean(axis=0) + 0.01

    def info(a: int, b: int) -> np.float32:
        total = 0.0
        for za in (0, 1):
            for zb in (0, 1):
                joint = np.sum((x[:, a] == za) & (x[:, b] == zb)) / n
                if joint > 0:
                    total += joint * np.log(joint / ((p1[a] if za else 1 - p1[a]) * (p1[b] if zb else 1 - p1[b])))
        return np.float32(total)

    return info
