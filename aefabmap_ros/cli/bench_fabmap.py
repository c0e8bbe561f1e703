"""Benchmark of the FAB-MAP core: Chow-Liu training, FAB-MAP 2 query latency and memory vs map size.

Synthetic bag-of-words with realistic sparsity: a V-word vocabulary, a few hundred distinct
words per image, Zipf-like word frequencies (p(word of rank r) ∝ 1 / (r + offset)^exponent).
Prints figures; asserts nothing. ``--quick`` runs a seconds-long smoke version. The machine's load
average is printed first: latencies on a shared machine are only comparable at similar load; the
thread CPU time of process() is less sensitive to other jobs (it still pays for shared caches).

    python -m aefabmap_ros.cli.bench_fabmap [--quick]
    aefabmap_bench fabmap --places 1000000     # one large map as fabmap_node loads it (cli/bench_large_map.py)
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.errors import AefabmapError
from aefabmap_ros.fabmap.chowliu import learn_chow_liu_tree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.engines import FabMap1, FabMap2
from aefabmap_ros.fabmap.index import warm_up_kernels
from aefabmap_ros.fabmap.observation import FabMapModel
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer


class ZipfImages:
    """Random images as sorted unique word ids with Zipf-like word frequencies."""

    def __init__(self, vocabulary_size: int, draws_per_image: int, exponent: float, seed: int) -> None:
        ranks = np.arange(vocabulary_size, dtype=np.float64)
        weights = 1.0 / (ranks + 20.0) ** exponent
        self._cdf = np.cumsum(weights / weights.sum())
        self._word_of_rank = np.random.default_rng(seed).permutation(vocabulary_size)
        self._draws = draws_per_image
        self._rng = np.random.default_rng(seed + 1)
        self.vocabulary_size = vocabulary_size

    def csr(self, n_images: int) -> sp.csr_matrix:
        """(n_images, V) binary CSR."""
        blocks = []
        for start in range(0, n_images, 5000):
            count = min(5000, n_images - start)
            ranks = np.searchsorted(self._cdf, self._rng.random((count, self._draws)))
            ranks = np.minimum(ranks, self.vocabulary_size - 1)
            words = self._word_of_rank[ranks]
            rows = np.repeat(np.arange(count), self._draws)
            block = sp.csr_matrix(
                (np.ones(rows.size, dtype=bool), (rows, words.ravel())), shape=(count, self.vocabulary_size)
            )
            block.sum_duplicates()
            block.data[:] = True
            blocks.append(block)
        matrix = sp.csr_matrix(sp.vstack(blocks))
        matrix.sort_indices()
        return matrix


def _rows(matrix: sp.csr_matrix) -> list[np.ndarray]:
    return [matrix.indices[matrix.indptr[i] : matrix.indptr[i + 1]].astype(np.int64) for i in range(matrix.shape[0])]


def _percentiles_ms(seconds: list[float]) -> str:
    ms = np.asarray(seconds) * 1e3
    return f"median {np.median(ms):7.2f} ms  p95 {np.percentile(ms, 95):7.2f} ms"


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_chow_liu(images: ZipfImages, n_train: int) -> tuple[float, sp.csr_matrix]:
    train = images.csr(n_train)
    start = time.perf_counter()
    tree = learn_chow_liu_tree(train)
    elapsed = time.perf_counter() - start
    print(
        f"Chow-Liu: V={images.vocabulary_size} N={n_train} ({train.nnz / n_train:.0f} words/image): "
        f"{elapsed:.1f} s, {len(tree.roots)} component(s)"
    )
    return elapsed, train


def bench_kernel_load() -> None:
    """Cost of the process's first use of the FAB-MAP 2 kernels: numba initialises and loads them from its
    on-disk cache (or compiles them, the first time on a machine / after fabmap.py changed)."""
    print(f"FAB-MAP 2 kernels loaded in {warm_up_kernels():.2f} s (once per process)")


def bench_queries(
    images: ZipfImages,
    train: sp.csr_matrix,
    sizes: Sequence[int],
    n_queries: int,
    n_samples: int,
    fabmap1_per_place_s: float,
) -> None:
    tree = learn_chow_liu_tree(train[: min(train.shape[0], 2000)])
    samples = train[:n_samples]
    recognizer = PlaceRecognizer(tree, samples, FabMapConfig(top_k=5), "bench")
    for size in sizes:
        missing = size - recognizer.num_places
        if missing > 0:
            recognizer.add_places(images.csr(missing), np.arange(missing, dtype=np.int64))
        queries = _rows(images.csr(n_queries))
        picks = np.linspace(0, size - 1, max(n_queries // 5, 1)).astype(int)
        revisits = [recognizer.place_words(int(i)) for i in picks]
        # The scoring alone (new place + every place) on the recognizer's own engine (no public accessor).
        engine = recognizer._engine
        scoring = []
        for words in queries:
            start = time.perf_counter()
            engine.log_likelihoods(words)
            scoring.append(time.perf_counter() - start)
        latencies, cpu_times = [], []
        hits = 0
        for k, words in enumerate(queries + revisits):
            start, start_cpu = time.perf_counter(), time.thread_time()
            result = recognizer.process(words, 10**12 + k)
            latencies.append(time.perf_counter() - start)
            cpu_times.append(time.thread_time() - start_cpu)
            if k >= len(queries) and result.candidates:
                hits += result.candidates[0].place_id == picks[k - len(queries)]
        per_place = float(np.median(latencies)) / recognizer.num_places
        print(
            f"FAB-MAP 2 {recognizer.num_places:>7d} places: log_likelihoods() {_percentiles_ms(scoring)} | "
            f"process() {_percentiles_ms(latencies)} (CPU time median {np.median(cpu_times) * 1e3:.2f} ms)  "
            f"({per_place * 1e6:.3f} us/place, "
            f"{fabmap1_per_place_s / per_place:.0f}x FAB-MAP 1)  index {recognizer.memory_bytes / 2**20:7.1f} MiB  "
            f"peak RSS {_rss_mib():7.0f} MiB  revisits ranked first {hits}/{len(revisits)}"
        )


def bench_fabmap1_ratio(images: ZipfImages, train: sp.csr_matrix, n_places: int, n_queries: int) -> float:
    """FAB-MAP 1 and 2 on the same small map; returns FAB-MAP 1's seconds per place."""
    tree = learn_chow_liu_tree(train[: min(train.shape[0], 2000)])
    model = FabMapModel(tree)
    fm1, fm2 = FabMap1(model, None, "meanfield"), FabMap2(model, None, "meanfield")
    for words in _rows(images.csr(n_places)):
        fm1.add(words)
        fm2.add(words)
    queries = _rows(images.csr(n_queries))
    t1, t2 = [], []
    for words in queries:
        start = time.perf_counter()
        fm1.log_likelihoods(words)
        t1.append(time.perf_counter() - start)
        start = time.perf_counter()
        fm2.log_likelihoods(words)
        t2.append(time.perf_counter() - start)
    per1, per2 = np.median(t1) / n_places, np.median(t2) / n_places
    print(
        f"FAB-MAP 1 vs 2 on {n_places} places: {per1 * 1e6:.1f} us/place vs {per2 * 1e6:.2f} us/place "
        f"-> FAB-MAP 2 is {per1 / per2:.0f}x faster (small map: FAB-MAP 2's per-query overhead dominates)"
    )
    return float(per1)


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bench fabmap", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="seconds-long smoke run on small sizes")
    parser.add_argument("--vocabulary-size", type=int, default=None)
    parser.add_argument("--words-per-image", type=int, default=400, help="draws per image (distinct ~ 3/4)")
    parser.add_argument("--zipf-exponent", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--places", type=int, default=None,
                        help="instead: one map of this many places, saved, loaded by a fresh process and queried")
    parser.add_argument("--queries", type=int, default=200, help="with --places: queries answered")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _run)


def _run(args: argparse.Namespace) -> int:
    sizes: tuple[int, ...]
    if args.quick:
        vocabulary_size, n_train, sizes, n_queries, n_ratio = 2000, 500, (1000, 5000), 20, 200
    else:
        vocabulary_size, n_train, sizes, n_queries, n_ratio = 10_000, 5000, (1000, 10_000, 100_000), 100, 500
    vocabulary_size = args.vocabulary_size or vocabulary_size
    if vocabulary_size < 2 or args.words_per_image < 1:
        raise AefabmapError("--vocabulary-size must be >= 2 and --words-per-image >= 1")
    if args.places is not None:
        if args.places < 1 or args.queries < 1:
            raise AefabmapError("--places and --queries must be >= 1")
        from aefabmap_ros.cli.bench_large_map import run

        return run(args.places, vocabulary_size, args.words_per_image, args.queries, args.seed)
    load_1min, load_5min, _ = os.getloadavg()
    print(f"Load average {load_1min:.2f} (1 min) {load_5min:.2f} (5 min) on {os.cpu_count()} CPUs")
    images = ZipfImages(vocabulary_size, args.words_per_image, args.zipf_exponent, args.seed)
    _, train = bench_chow_liu(images, n_train)
    bench_kernel_load()
    fabmap1_per_place = bench_fabmap1_ratio(images, train, n_ratio, n_queries=10)
    bench_queries(images, train, sizes, n_queries, min(n_train, 1000), fabmap1_per_place)
    return 0


if __name__ == "__main__":
    sys.exit(main())
