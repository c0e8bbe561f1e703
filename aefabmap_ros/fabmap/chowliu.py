"""Chow-Liu tree over visual words (FAB-MAP's generative model of word co-occurrence).

The tree is learned from a binary bag-of-words of training images (images x words) with
openFABMAP's estimators, so a tree learned here and one learned by openFABMAP's
``ChowLiuTree::make`` from the same data agree (up to ties between equal informations):

- smoothed marginal ``p(z_q = 1) = 0.98 * count_q / N + 0.01`` (``floor`` = 0.01);
- pairwise "mutual information" ``sum_{a,b} P(a,b) log(P(a,b) / (P(a) P(b)))`` with the *raw*
  joint frequencies and the *smoothed* marginals (openFABMAP's ``calcMutInfo``; because of the
  smoothing it can be slightly negative, and pairs that never co-occur still carry information);
- maximum-weight spanning tree over all V (V - 1) / 2 pairs, edges whose information is below
  ``lower_info_bound`` being absent (openFABMAP's ``LowerInfoBound``: it only keeps edges with
  ``info >= bound`` before Kruskal). openFABMAP aborts (CV_Assert) when the remaining edges do
  not connect all words; here the result is then a forest whose components are rooted
  separately (each root is its own parent, which the inference treats as an independent word);
- rooted like openFABMAP: at the lower-indexed end of the most informative edge (per component);
- smoothed conditionals ``p(z_q | z_parent) = 0.98 * count / total + 0.01`` (0.01 when the
  parent state never occurs); a root's conditionals equal its marginal.

The maximum spanning tree is Prim's algorithm on the complete graph with the information of
one word against all others computed on the fly from the sparse co-occurrence counts of that
word (O(nnz) per word, O(V) memory): no V x V matrix is ever stored, and every pair, including
pairs that never co-occur, is weighed exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order

from aefabmap_ros.errors import DataError, ModelError

# openFABMAP's additive smoothing of every probability estimate: p = (1 - 2 f) * freq + f.
DEFAULT_FLOOR = 0.01


@dataclass(frozen=True, eq=False)
class ChowLiuTree:
    """A rooted Chow-Liu tree (or forest) over V binary words.

    The root of each component is its own parent (openFABMAP convention; golden ``tree.yml``
    has exactly one word q with parent q) and its conditionals equal its marginal.
    """

    parent: np.ndarray  # (V,) int64; a root is its own parent
    marginal: np.ndarray  # (V,) float64 p(z_q = 1)
    p_given_parent_present: np.ndarray  # (V,) float64 p(z_q = 1 | z_parent = 1)
    p_given_parent_absent: np.ndarray  # (V,) float64 p(z_q = 1 | z_parent = 0)

    def __post_init__(self) -> None:
        parent = np.asarray(self.parent)
        if parent.ndim != 1 or parent.size == 0:
            raise ModelError(f"Chow-Liu tree parent must be a non-empty 1-D array, got shape {parent.shape}")
        vocabulary_size = parent.size
        if not np.all(np.isfinite(parent.astype(np.float64))) or np.any(parent != np.round(parent)):
            raise ModelError("Chow-Liu tree parent indices must be integers")
        parent_i64 = parent.astype(np.int64)
        if parent_i64.min() < 0 or parent_i64.max() >= vocabulary_size:
            raise ModelError(
                f"Chow-Liu tree parent index out of range [0, {vocabulary_size}): "
                f"min {parent_i64.min()}, max {parent_i64.max()}"
            )
        arrays = {}
        for name in ("marginal", "p_given_parent_present", "p_given_parent_absent"):
            values = np.asarray(getattr(self, name), dtype=np.float64)
            if values.shape != (vocabulary_size,):
                raise ModelError(f"Chow-Liu tree {name} has shape {values.shape}, expected ({vocabulary_size},)")
            # Probabilities of exactly 0 or 1 make FAB-MAP's likelihoods log(0) or 0/0.
            bad = ~((values > 0.0) & (values < 1.0))
            if np.any(bad):
                q = int(np.flatnonzero(bad)[0])
                raise ModelError(f"Chow-Liu tree {name}[{q}] = {values[q]!r} is not a probability in (0, 1)")
            arrays[name] = values
        _check_acyclic(parent_i64)
        object.__setattr__(self, "parent", _readonly(parent_i64))
        for name, values in arrays.items():
            object.__setattr__(self, name, _readonly(values))

    @property
    def vocabulary_size(self) -> int:
        return int(self.parent.size)

    @property
    def roots(self) -> np.ndarray:
        """(R,) int64 indices of the words that are their own parent."""
        return np.flatnonzero(self.parent == np.arange(self.vocabulary_size))

    def edges(self) -> np.ndarray:
        """(E, 2) int64 undirected tree edges as sorted (low, high) pairs, sorted lexicographically."""
        child = np.arange(self.vocabulary_size)
        keep = self.parent != child
        pairs = np.sort(np.stack([child[keep], self.parent[keep]], axis=1), axis=1)
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

    def to_matrix(self) -> np.ndarray:
        """(4, V) float64 openFABMAP layout [parent; p(z); p(z | zp = 1); p(z | zp = 0)]."""
        return np.stack(
            [
                self.parent.astype(np.float64),
                self.marginal,
                self.p_given_parent_present,
                self.p_given_parent_absent,
            ]
        )

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> ChowLiuTree:
        """Inverse of :meth:`to_matrix`; raises ModelError on a malformed matrix."""
        m = np.asarray(matrix)
        if m.ndim != 2 or m.shape[0] != 4 or m.shape[1] == 0:
            raise ModelError(f"Chow-Liu tree matrix must have shape (4, V), got {m.shape}")
        m = m.astype(np.float64)
        if not np.all(np.isfinite(m)):
            raise ModelError("Chow-Liu tree matrix contains NaN or infinity")
        return cls(parent=m[0], marginal=m[1], p_given_parent_present=m[2], p_given_parent_absent=m[3])


def _readonly(array: np.ndarray) -> np.ndarray:
    out = np.array(array, copy=True)
    out.flags.writeable = False
    return out


def _check_acyclic(parent: np.ndarray) -> None:
    """Every word must reach a root (a self-parent) by following parents: pointer doubling."""
    ancestor = parent.copy()
    for _ in range(int(np.ceil(np.log2(max(parent.size, 2)))) + 1):
        ancestor = ancestor[ancestor]
    if np.any(parent[ancestor] != ancestor):
        q = int(np.flatnonzero(parent[ancestor] != ancestor)[0])
        raise ModelError(f"Chow-Liu tree parents contain a cycle (word {q} never reaches a root)")


def binarize_bow(bow: sp.spmatrix | sp.sparray | np.ndarray) -> sp.csr_matrix:
    """(N, V) bag-of-words (counts, weights or bool; dense or sparse) -> binary CSR (value > 0 = present)."""
    if sp.issparse(bow):
        matrix = sp.csr_matrix(bow)
    else:
        dense = np.asarray(bow)
        if dense.ndim != 2:
            raise DataError(f"bag-of-words must be 2-D (images x words), got shape {dense.shape}")
        matrix = sp.csr_matrix(dense)
    if matrix.ndim != 2:
        raise DataError(f"bag-of-words must be 2-D (images x words), got shape {matrix.shape}")
    data = np.asarray(matrix.data)
    if data.dtype != np.bool_ and not np.all(np.isfinite(data)):
        raise DataError("bag-of-words contains NaN or infinity")
    present = sp.csr_matrix(matrix > 0, dtype=np.bool_)
    present.sum_duplicates()
    present.sort_indices()
    return present


class _CooccurrenceRows:
    """Co-occurrence counts of one word with all words, from sparse binary data, without V x V storage."""

    def __init__(self, present: sp.csr_matrix) -> None:
        self._rows = present  # (N, V) CSR
        self._cols = present.tocsc()  # (N, V) CSC: which images hold word q
        self._vocabulary_size = present.shape[1]

    def row(self, q: int) -> np.ndarray:
        """(V,) int64 number of images holding both q and each word."""
        images = self._cols.indices[self._cols.indptr[q] : self._cols.indptr[q + 1]]
        starts = self._rows.indptr[images]
        lengths = self._rows.indptr[images + 1] - starts
        total = int(lengths.sum())
        if total == 0:
            return np.zeros(self._vocabulary_size, dtype=np.int64)
        # Concatenate the index slices of all these images in one vectorised gather.
        offsets = np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
        words = self._rows.indices[offsets + np.arange(total)]
        return np.bincount(words, minlength=self._vocabulary_size)


def _information_row(
    q: int,
    n11: np.ndarray,
    counts: np.ndarray,
    n_images: int,
    log_p1: np.ndarray,
    log_p0: np.ndarray,
) -> np.ndarray:
    """(V,) openFABMAP mutual information of word q with every word (raw joints, smoothed marginals)."""
    cq = counts[q]
    n10 = cq - n11
    n01 = counts - n11
    n00 = n_images - cq - counts + n11
    info = np.zeros(counts.size, dtype=np.float64)
    for n_ab, log_pq, log_pv in (
        (n11, log_p1[q], log_p1),
        (n10, log_p1[q], log_p0),
        (n01, log_p0[q], log_p1),
        (n00, log_p0[q], log_p0),
    ):
        joint = n_ab / n_images
        # 0 * log 0 = 0: the maximum keeps the log finite where the joint is 0.
        info += joint * (np.log(np.maximum(joint, 1e-300)) - log_pq - log_pv)
    return info


def maximum_information_forest(
    present: sp.csr_matrix, lower_info_bound: float, floor: float = DEFAULT_FLOOR
) -> tuple[np.ndarray, np.ndarray]:
    """Prim's maximum spanning forest: (prim_parent (V,) int64, -1 at roots; edge_info (V,) float32)."""
    n_images, vocabulary_size = present.shape
    counts = np.asarray(present.sum(axis=0)).ravel().astype(np.int64)
    p1 = (1.0 - 2.0 * floor) * counts / n_images + floor
    log_p1, log_p0 = np.log(p1), np.log(1.0 - p1)
    cooccurrence = _CooccurrenceRows(present)

    # openFABMAP ranks edges by float32 information (its ``info::score``), ties in (word1, word2)
    # order; Prim's algorithm under the same strict total order yields the same unique forest
    # as its Kruskal pass: weight first, then the lexicographically smaller word pair.
    bound32 = np.float32(lower_info_bound)
    in_tree = np.zeros(vocabulary_size, dtype=bool)
    key = np.full(vocabulary_size, -np.inf, dtype=np.float32)  # best link of each word to the tree
    key_pair = np.full(vocabulary_size, np.iinfo(np.int64).max, dtype=np.int64)  # lo * V + hi of it
    link = np.full(vocabulary_size, -1, dtype=np.int64)
    prim_parent = np.full(vocabulary_size, -1, dtype=np.int64)
    edge_info = np.full(vocabulary_size, np.nan, dtype=np.float32)
    words = np.arange(vocabulary_size, dtype=np.int64)
    for _ in range(vocabulary_size):
        frontier = np.where(in_tree, -np.inf, key)
        best = frontier.max()
        if best == -np.inf:
            # Nothing at or above the bound links the rest to this component: start a new one.
            q = int(np.argmin(in_tree))
        else:
            tied = np.flatnonzero(frontier == best)
            q = int(tied[np.argmin(key_pair[tied])]) if tied.size > 1 else int(tied[0])
            prim_parent[q] = link[q]
            edge_info[q] = key[q]
        in_tree[q] = True
        info = _information_row(q, cooccurrence.row(q), counts, n_images, log_p1, log_p0).astype(np.float32)
        pair = np.minimum(words, q) * vocabulary_size + np.maximum(words, q)
        better = (
            ~in_tree
            & (info >= bound32)
            & ((info > key) | ((info == key) & (pair < key_pair)))
        )
        key[better] = info[better]
        key_pair[better] = pair[better]
        link[better] = q
    return prim_parent, edge_info


def _root_components(prim_parent: np.ndarray, edge_info: np.ndarray) -> np.ndarray:
    """Re-root every component of the forest like openFABMAP; returns parent (V,) with roots self-parented."""
    vocabulary_size = prim_parent.size
    child = np.flatnonzero(prim_parent >= 0)
    low = np.minimum(child, prim_parent[child])
    high = np.maximum(child, prim_parent[child])
    weights = np.ones(child.size)
    graph = sp.csr_matrix((weights, (low, high)), shape=(vocabulary_size, vocabulary_size))
    graph = graph + graph.T
    parent = np.arange(vocabulary_size, dtype=np.int64)
    # Visit edges from most to least informative (ties: lower word pair first, as a stable sort of
    # openFABMAP's (word1, word2) loop order): the first edge seen in a component gives its root.
    order = np.lexsort((high, low, -edge_info[child]))
    visited = np.zeros(vocabulary_size, dtype=bool)
    for e in order:
        root = int(low[e])
        if visited[root]:
            continue
        nodes, predecessors = breadth_first_order(graph, root, directed=False, return_predecessors=True)
        visited[nodes] = True
        non_root = nodes[1:]
        parent[non_root] = predecessors[non_root]
    return parent


def learn_chow_liu_tree(
    bow: sp.spmatrix | sp.sparray | np.ndarray,
    lower_info_bound: float = 0.0005,
    floor: float = DEFAULT_FLOOR,
) -> ChowLiuTree:
    """Learn a Chow-Liu tree from a training bag-of-words (N images x V words; value > 0 = present).

    ``lower_info_bound``: edges carrying less information (nats) are not used (openFABMAP's
    LowerInfoBound); if that disconnects the words, the result is a forest (see module doc);
    ``-inf`` keeps every pair (always a spanning tree).
    ``floor``: additive smoothing, every probability is ``(1 - 2 floor) * frequency + floor``.
    """
    if np.isnan(lower_info_bound) or lower_info_bound == np.inf:
        raise DataError(f"lower_info_bound must be a number below +inf, got {lower_info_bound!r}")
    if not 0.0 < floor < 0.5:
        raise DataError(f"floor must be in (0, 0.5), got {floor!r}")
    present = binarize_bow(bow)
    n_images, vocabulary_size = present.shape
    if n_images == 0 or vocabulary_size == 0:
        raise DataError(f"bag-of-words must have at least one image and one word, got shape {present.shape}")

    prim_parent, edge_info = maximum_information_forest(present, lower_info_bound, floor)
    parent = _root_components(prim_parent, edge_info)

    counts = np.asarray(present.sum(axis=0)).ravel().astype(np.float64)
    marginal = (1.0 - 2.0 * floor) * counts / n_images + floor
    columns = present.tocsc()
    both = np.asarray(columns.multiply(columns[:, parent]).sum(axis=0)).ravel().astype(np.float64)
    parent_counts = counts[parent]
    parent_absent = n_images - parent_counts
    with np.errstate(divide="ignore", invalid="ignore"):
        given_present = np.where(
            parent_counts > 0, (1.0 - 2.0 * floor) * both / parent_counts + floor, floor
        )
        given_absent = np.where(
            parent_absent > 0, (1.0 - 2.0 * floor) * (counts - both) / parent_absent + floor, floor
        )
    is_root = parent == np.arange(vocabulary_size)
    given_present[is_root] = marginal[is_root]
    given_absent[is_root] = marginal[is_root]
    return ChowLiuTree(
        parent=parent,
        marginal=marginal,
        p_given_parent_present=given_present,
        p_given_parent_absent=given_absent,
    )
