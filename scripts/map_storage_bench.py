#!/usr/bin/env python3
"""How long a map merge takes, and the map file as today's .npz against an SQLite database.

    .venv/bin/python scripts/map_storage_bench.py --places 100000 --vocabulary 10000 --words 300

Synthetic maps (each place ~WORDS distinct random word ids of a VOCABULARY-word vocabulary, one session of
PLACES places) are written as map files the way a recognizer saves them. Printed:

* merge: ``aefabmap_map merge`` (in this process) of two PLACES-place maps: load both, merge, write.
* storage, per layout (the .npz as saved today with int64 word ids; the .npz with int32 word ids; SQLite in
  WAL mode with one row per place and its word ids as an int32 BLOB, and a sessions table): file size,
  load into the CSR arrays, append one session of APPEND places (the .npz: read, append, rewrite the whole
  file; SQLite: one transaction), and a writer killed (SIGKILL) in the middle of a write: is the file still
  readable, and which contents does it hold.

The figures go to docs/maps.md. Timings are best of ``--repeat`` runs, after the page cache holds the file
(a load right after writing it, as a node restarted on its map would see).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import itertools
import os
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from aefabmap_ros.cli.map import main as map_main  # noqa: E402
from aefabmap_ros.fabmap.map_file import read_map_unchecked_vocabulary, write_map  # noqa: E402

VOCABULARY_ID = "bench-vocabulary"


def synthetic_map(places: int, vocabulary: int, words: int, seed: int, robot: str = "r1",
                  index_dtype: type[np.integer] = np.int64) -> dict[str, np.ndarray]:
    """A one-session map of ``places`` places of ~``words`` distinct random words each (vectorised)."""
    rng = np.random.default_rng(seed)
    draws = np.sort(rng.integers(0, vocabulary, size=(places, words), dtype=np.int32), axis=1)
    unique = np.ones(draws.shape, dtype=bool)
    unique[:, 1:] = draws[:, 1:] != draws[:, :-1]
    indptr = np.concatenate([[0], np.cumsum(unique.sum(axis=1))]).astype(np.int64)
    return {
        "vocabulary_id": np.array(VOCABULARY_ID), "vocabulary_size": np.array(vocabulary, dtype=np.int64),
        "word_indptr": indptr, "word_indices": draws[unique].astype(index_dtype),
        "place_stamps_ns": np.arange(places, dtype=np.int64) * 100_000_000 + seed * 10**15,
        "place_frames": np.arange(places, dtype=np.int64), "next_query_id": np.array(places, dtype=np.int64),
        "previous_posterior": np.zeros(0), "has_previous_posterior": np.array(False),
        "config_json": np.array("{}"), "place_sessions": np.zeros(places, dtype=np.int32),
        "session_robots": np.array([robot]), "session_first_queries": np.zeros(1, dtype=np.int64),
    }


def best_of(repeat: int, work: Callable[[], object]) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return min(times)


# -- SQLite layout ------------------------------------------------------------------------------------

SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE sessions (number INTEGER PRIMARY KEY, robot TEXT NOT NULL, first_query INTEGER NOT NULL);
CREATE TABLE places (id INTEGER PRIMARY KEY, session INTEGER NOT NULL REFERENCES sessions(number),
                     stamp_ns INTEGER NOT NULL, frame INTEGER NOT NULL, words BLOB NOT NULL);
"""


def sqlite_connect(path: Path) -> sqlite3.Connection:
    connection = sqlite3.connect(path)
    connection.execute("PRAGMA journal_mode=WAL")
    connection.execute("PRAGMA synchronous=FULL")  # a committed session survives a power cut too
    return connection


def sqlite_write(path: Path, arrays: dict[str, np.ndarray]) -> None:
    connection = sqlite_connect(path)
    with connection:
        connection.executescript(SCHEMA)
        connection.executemany("INSERT INTO meta VALUES (?, ?)", [
            ("vocabulary_id", str(arrays["vocabulary_id"])), ("vocabulary_size", str(int(arrays["vocabulary_size"]))),
            ("next_query_id", str(int(arrays["next_query_id"]))), ("config_json", str(arrays["config_json"]))])
        connection.executemany("INSERT INTO sessions VALUES (?, ?, ?)", [
            (number, str(robot), int(first)) for number, (robot, first)
            in enumerate(zip(arrays["session_robots"], arrays["session_first_queries"], strict=True))])
        sqlite_insert_places(connection, arrays, first_id=0)
    connection.close()


def sqlite_insert_places(connection: sqlite3.Connection, arrays: dict[str, np.ndarray], first_id: int) -> None:
    indptr = arrays["word_indptr"]
    words = arrays["word_indices"].astype("<i4")
    rows = zip(range(first_id, first_id + indptr.size - 1), arrays["place_sessions"].tolist(),
               arrays["place_stamps_ns"].tolist(), arrays["place_frames"].tolist(),
               (words[start:end].tobytes() for start, end in itertools.pairwise(indptr.tolist())),
               strict=True)
    connection.executemany("INSERT INTO places VALUES (?, ?, ?, ?, ?)", rows)


def sqlite_load(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """The CSR word arrays (indptr, indices) and the number of sessions of an SQLite map."""
    connection = sqlite3.connect(path)
    blobs = [row[0] for row in connection.execute("SELECT words FROM places ORDER BY id")]
    stamps = np.array(connection.execute("SELECT stamp_ns FROM places ORDER BY id").fetchall(), dtype=np.int64)
    sessions = connection.execute("SELECT COUNT(*) FROM sessions").fetchone()[0]
    connection.close()
    lengths = np.fromiter((len(blob) for blob in blobs), dtype=np.int64, count=len(blobs)) // 4
    indptr = np.concatenate([[0], np.cumsum(lengths)])
    indices = np.frombuffer(b"".join(blobs), dtype="<i4").astype(np.int64)
    assert stamps.shape[0] == indptr.size - 1
    return indptr, indices, int(sessions)


def sqlite_append_session(path: Path, session: dict[str, np.ndarray]) -> None:
    connection = sqlite_connect(path)
    with connection:
        number, first_id, next_query = connection.execute(
            "SELECT (SELECT COUNT(*) FROM sessions), (SELECT COUNT(*) FROM places), "
            "(SELECT CAST(value AS INTEGER) FROM meta WHERE key = 'next_query_id')").fetchone()
        connection.execute("INSERT INTO sessions VALUES (?, ?, ?)", (number, "appended", next_query))
        shifted = {**session, "place_sessions": np.full(session["place_stamps_ns"].size, number),
                   "place_frames": session["place_frames"] + next_query}
        sqlite_insert_places(connection, shifted, first_id)
        connection.execute("UPDATE meta SET value = ? WHERE key = 'next_query_id'",
                           (str(next_query + int(session["next_query_id"])),))
    connection.close()


# -- .npz layout ---------------------------------------------------------------------------------------

def npz_append_session(path: Path, session: dict[str, np.ndarray], index_dtype: type[np.integer] = np.int64
                       ) -> None:
    """Read the whole map, append the session, rewrite the whole file (word ids stored as ``index_dtype``)."""
    from aefabmap_ros.fabmap.map_tools import merge_maps

    merged = merge_maps(read_map_unchecked_vocabulary(path), session)
    write_map(path, {**merged, "word_indices": merged["word_indices"].astype(index_dtype)})


def npz_load(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    arrays = read_map_unchecked_vocabulary(path)
    return arrays["word_indptr"], arrays["word_indices"], len(arrays["session_robots"])


# -- a writer killed mid-write ------------------------------------------------------------------------------

CHILD = """
import sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
import map_storage_bench as bench
session = bench.synthetic_map(int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6]), seed=7)
print("writing", flush=True)
(bench.npz_append_session if sys.argv[2] == "npz" else bench.sqlite_append_session)(Path(sys.argv[3]), session)
print("done", flush=True)
"""


def killed_append(layout: str, path: Path, places: int, vocabulary: int, words: int) -> str:
    """Append a PLACES-place session in a child process and SIGKILL it once it is writing the file (the .npz's
    temporary file, or SQLite's write-ahead log, has grown by a megabyte); what the file holds afterwards."""
    _, _, sessions_before = (npz_load if layout == "npz" else sqlite_load)(path)
    wal = path.parent / f"{path.name}-wal"
    wal_before = wal.stat().st_size if wal.exists() else 0
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(Path(__file__).parent), layout, str(path),
                              str(places), str(vocabulary), str(words)], stdout=subprocess.PIPE, text=True)
    assert child.stdout is not None
    assert child.stdout.readline().strip() == "writing"

    def written() -> int:
        if layout == "npz":
            return sum(p.stat().st_size for p in path.parent.glob(f".{path.name}.*.tmp"))
        return (wal.stat().st_size if wal.exists() else 0) - wal_before

    while child.poll() is None and written() < 1_000_000:
        time.sleep(0.001)
    finished = child.poll() is not None
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    leftovers = sorted(p.name for p in path.parent.glob(f".{path.name}.*.tmp"))
    try:
        _, _, sessions_after = (npz_load if layout == "npz" else sqlite_load)(path)
    except Exception as error:  # the point of the test: does anything fail to read?
        return f"UNREADABLE ({error})"
    state = ("old contents" if sessions_after == sessions_before else
             "new contents" if sessions_after == sessions_before + 1 else f"{sessions_after} sessions?")
    note = " (the writer had finished before the kill)" if finished else ""
    extra = f"; {len(leftovers)} temporary file left" if leftovers else ""
    return f"readable, {state}{extra}{note}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--places", type=int, default=100_000)
    parser.add_argument("--vocabulary", type=int, default=10_000)
    parser.add_argument("--words", type=int, default=300, help="word draws a place (duplicates removed)")
    parser.add_argument("--append", type=int, default=1_000, help="places of the appended session")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--work-dir", type=Path, help="where the files go (default: a temporary folder)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(dir=args.work_dir) as folder:
        run(Path(folder), args)
    return 0


def run(folder: Path, args: argparse.Namespace) -> None:
    a = synthetic_map(args.places, args.vocabulary, args.words, seed=1, robot="r1")
    b = synthetic_map(args.places, args.vocabulary, args.words, seed=2, robot="r2")
    print(f"{args.places} places a map, {args.vocabulary}-word vocabulary, "
          f"{a['word_indices'].size / args.places:.1f} words a place; best of {args.repeat}")
    write_map(folder / "a.npz", a)
    write_map(folder / "b.npz", b)
    merge_argv = ["merge", str(folder / "a.npz"), str(folder / "b.npz"), "--out", str(folder / "ab.npz")]
    with contextlib.redirect_stdout(io.StringIO()):
        merge_s = best_of(args.repeat, lambda: map_main(merge_argv))
    print(f"merge {args.places} + {args.places} places (load both, merge, write {_mb(folder / 'ab.npz')}): "
          f"{merge_s:.2f} s")
    command = [sys.executable, "-m", "aefabmap_ros.cli.map", *merge_argv]
    command_s = best_of(1, lambda: subprocess.run(command, check=True, capture_output=True, cwd=ROOT))
    print(f"the same as a command (a new process: interpreter and imports too): {command_s:.2f} s")

    session = synthetic_map(args.append, args.vocabulary, args.words, seed=3, robot="r3")
    layouts: dict[str, tuple[Callable[[Path], None], Callable[[Path], object], Callable[[Path], None]]] = {
        "npz, int64 word ids (today)": (lambda p: write_map(p, a), npz_load, lambda p: npz_append_session(p, session)),
        "npz, int32 word ids": (lambda p: write_map(p, {**a, "word_indices": a["word_indices"].astype(np.int32)}),
                                npz_load, lambda p: npz_append_session(p, session, np.int32)),
        "SQLite WAL, int32 BLOB a place": (lambda p: sqlite_write(p, a), sqlite_load,
                                           lambda p: sqlite_append_session(p, session)),
    }
    print(f"\n| layout | file size | load into CSR | append a {args.append}-place session | "
          f"writer killed mid-way through appending {args.places} places |")
    print("|---|---|---|---|---|")
    for number, (name, (write, load, append)) in enumerate(layouts.items()):
        path = folder / (f"map{number}.npz" if name.startswith("npz") else f"map{number}.db")
        write(path)
        size = _mb(path)
        load_s = best_of(args.repeat, lambda load=load, path=path: load(path))  # type: ignore[misc]
        append_s = best_of(args.repeat, lambda append=append, path=path: append(path))  # type: ignore[misc]
        crash = killed_append("npz" if name.startswith("npz") else "sqlite", path, args.places, args.vocabulary,
                              args.words)
        print(f"| {name} | {size} | {load_s:.2f} s | {append_s:.3f} s | {crash} |")


def _mb(path: Path) -> str:
    size = path.stat().st_size + sum(extra.stat().st_size for extra in path.parent.glob(f"{path.name}-wal"))
    return f"{size / 1e6:.0f} MB"


if __name__ == "__main__":
    raise SystemExit(main())
