"""``aefabmap_bench fabmap --places N``: FAB-MAP 2 on one large map, as a robot's fabmap_node meets it.

1. A map of N places is built from synthetic Zipf bag-of-words (``bench_fabmap.ZipfImages``) and saved.
2. A fresh process loads it, as fabmap_node does at start-up, and answers queries with ``process()``: its load
   time and peak RSS are the robot's, not the builder's.
3. The same queries are scored on one thread and on the process's threads (the ratio, in one run), and the
   top places checked against FAB-MAP 1's exact O(V) sum (an independent computation): FAB-MAP 2's scores are
   relative to an empty place, so any two places' difference must equal FAB-MAP 1's.

Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import pickle
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from aefabmap_ros.errors import AefabmapError

if TYPE_CHECKING:
    from aefabmap_ros.fabmap.index import InvertedIndex
    from aefabmap_ros.fabmap.observation import FabMapModel

TOP = 5  # places whose agreement with FAB-MAP 1 is checked, per query


def _peak_rss_mib() -> float:
    """This process's peak RSS: VmHWM, which starts afresh at exec (getrusage's maxrss would carry the builder's
    peak into the loading child on Linux)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def build(places: int, vocabulary_size: int, words_per_image: int, seed: int, folder: Path) -> dict[str, float]:
    """The map and the model it needs (tree, new-place samples) written into ``folder``; build and save times."""
    from aefabmap_ros.cli.bench_fabmap import ZipfImages
    from aefabmap_ros.fabmap.chowliu import learn_chow_liu_tree
    from aefabmap_ros.fabmap.config import FabMapConfig
    from aefabmap_ros.fabmap.recognizer import PlaceRecognizer

    images = ZipfImages(vocabulary_size, words_per_image, 1.0, seed)
    train = images.csr(5000)
    tree = learn_chow_liu_tree(train[:2000])
    samples = train[:1000]
    (folder / "model.pkl").write_bytes(pickle.dumps((tree, samples, vocabulary_size, words_per_image, seed)))
    recognizer = PlaceRecognizer(tree, samples, FabMapConfig(top_k=TOP), "bench")
    start, done = time.perf_counter(), 0
    while done < places:
        count = min(100_000, places - done)
        recognizer.add_places(images.csr(count), np.arange(done, done + count, dtype=np.int64))
        done += count
    built = time.perf_counter() - start
    start = time.perf_counter()
    recognizer.save_map(folder / "map.npz")
    return {"build_s": built, "save_s": time.perf_counter() - start,
            "file_mib": (folder / "map.npz").stat().st_size / 2**20}


def load_and_query(folder: Path, queries: int) -> dict[str, float]:
    """In this (fresh) process: load the map, answer ``queries`` queries, compare threads and FAB-MAP 1."""
    from aefabmap_ros.cli.bench_fabmap import ZipfImages, _rows
    from aefabmap_ros.fabmap.config import FabMapConfig
    from aefabmap_ros.fabmap.index import scoring_threads, warm_up_kernels
    from aefabmap_ros.fabmap.observation import FabMapModel
    from aefabmap_ros.fabmap.recognizer import PlaceRecognizer

    tree, samples, vocabulary_size, words_per_image, seed = pickle.loads((folder / "model.pkl").read_bytes())
    warm_up_kernels()
    before = _peak_rss_mib()
    recognizer = PlaceRecognizer(tree, samples, FabMapConfig(top_k=TOP), "bench")
    start = time.perf_counter()
    recognizer.load_map(folder / "map.npz")
    loaded = time.perf_counter() - start
    words = _rows(ZipfImages(vocabulary_size, words_per_image, 1.0, seed + 7).csr(queries))
    index, model = recognizer._engine.places, FabMapModel(tree)  # the scoring alone, as measured
    one: list[float] = []
    many: list[float] = []
    gaps: list[float] = []
    for query in words:
        state = model.query_state(query)
        start = time.perf_counter()
        single = index.scores(state, threads=1)
        one.append(time.perf_counter() - start)
        start = time.perf_counter()
        threaded = index.scores(state)
        many.append(time.perf_counter() - start)
        gaps.append(_fabmap1_gap(model, index, query, threaded) if len(gaps) < 20 else 0.0)
        if not np.array_equal(single, threaded):
            raise AefabmapError("the threaded scores differ from one thread's")
    latencies = []
    for k, query in enumerate(words):
        start = time.perf_counter()
        recognizer.process(query, 10**18 + k)
        latencies.append(time.perf_counter() - start)
    return {"places": recognizer.num_places, "load_s": loaded, "rss_before_load_mib": before,
            "threads": scoring_threads(), "scores_1_thread_ms": 1e3 * float(np.median(one)),
            "scores_threads_ms": 1e3 * float(np.median(many)),
            "process_median_ms": 1e3 * float(np.median(latencies)),
            "process_p95_ms": 1e3 * float(np.percentile(latencies, 95)),
            "top_places_vs_fabmap1_max_gap": float(max(gaps)), "peak_rss_mib": _peak_rss_mib()}


def _fabmap1_gap(model: FabMapModel, index: InvertedIndex, query: np.ndarray, scores: np.ndarray) -> float:
    """Largest |(s_p - s_q) - (L1_p - L1_q)| over the top places p and q: FAB-MAP 2 against FAB-MAP 1's exact sum."""
    top = np.argsort(-scores)[:TOP]
    present = np.zeros(model.vocabulary_size, dtype=bool)
    present[query] = True
    exact = []
    for place in top:
        place_present = np.zeros_like(present)
        place_present[index.place_words(int(place))] = True
        exact.append(model.exact_log_likelihood(present, place_present))
    relative, reference = scores[top] - scores[top[0]], np.array(exact) - exact[0]
    return float(np.max(np.abs(relative - reference)))


def run(places: int, vocabulary_size: int, words_per_image: int, queries: int, seed: int) -> int:
    """Build in this process, load and query in a child, print both."""
    with tempfile.TemporaryDirectory(prefix="aefabmap-bench-") as temporary:
        folder = Path(temporary)
        built = build(places, vocabulary_size, words_per_image, seed, folder)
        print(f"built {places:,} places ({vocabulary_size:,} words) in {built['build_s']:.1f} s; saved in "
              f"{built['save_s']:.1f} s, {built['file_mib']:.0f} MiB (builder's peak RSS {_peak_rss_mib():.0f} MiB)")
        child = subprocess.run([sys.executable, "-m", "aefabmap_ros.cli.bench_large_map", "--child", str(folder),
                                str(queries)], capture_output=True, text=True, check=False)
        if child.returncode != 0:
            raise AefabmapError(f"the loading process failed: {child.stderr.strip().splitlines()[-1:]}")
        figures = json.loads(child.stdout.strip().splitlines()[-1])
    print(f"loaded in {figures['load_s']:.1f} s; peak RSS {figures['peak_rss_mib']:.0f} MiB "
          f"({figures['rss_before_load_mib']:.0f} MiB before the map)")
    speedup = figures["scores_1_thread_ms"] / figures["scores_threads_ms"]
    print(f"scores: 1 thread {figures['scores_1_thread_ms']:.1f} ms, {figures['threads']} threads "
          f"{figures['scores_threads_ms']:.1f} ms ({speedup:.2f}x, the same to the bit)")
    print(f"process(): median {figures['process_median_ms']:.1f} ms, p95 {figures['process_p95_ms']:.1f} ms over "
          f"{queries} queries")
    print(f"top {TOP} places against FAB-MAP 1's exact sum: largest difference "
          f"{figures['top_places_vs_fabmap1_max_gap']:.1e}")
    return 0


def main(argv: list[str]) -> int:
    """Child mode only (``--child FOLDER QUERIES``): prints its figures as one JSON line."""
    parser = argparse.ArgumentParser(prog="bench_large_map")
    parser.add_argument("--child", nargs=2, required=True)
    args = parser.parse_args(argv)
    print(json.dumps(load_and_query(Path(args.child[0]), int(args.child[1]))))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
