"""Map tools: a merged map is the map one recognizer would have built over both runs; cutting a session out
gives the other map back; summaries count what the arrays hold."""

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from aefabmap_ros.errors import DataError, VocabularyMismatchError
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.map_file import read_map_unchecked_vocabulary, write_map
from aefabmap_ros.fabmap.map_tools import map_summary, merge_maps, remove_session
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from test.fabmap.test_recognizer import SAMPLES, V, _tree

VOCABULARY = "vocab-a"
PLACE_KEYS = ("word_indptr", "word_indices", "place_stamps_ns", "place_frames", "place_sessions", "session_robots",
              "session_first_queries")
CONFIGS = {
    # every frame a place: the places of both maps are exactly the frames
    "openfabmap": FabMapConfig.openfabmap(add_policy="all", motion_model=False, top_k=100),
    # the nodes' defaults: keyframing (overlap, seconds) decides which frames become places
    "keyframes": FabMapConfig(add_policy="all", motion_model=False, top_k=100),
}


def _walk(n: int, seed: int) -> list[np.ndarray]:
    """Frames of a moving camera: each keeps most of the previous frame's words, so some frames overlap the
    last place enough not to be keyframes."""
    rng = np.random.default_rng(seed)
    words = rng.random(V) < 0.25
    frames = []
    for _ in range(n):
        words = np.where(rng.random(V) < 0.15, rng.random(V) < 0.25, words)
        frames.append(np.flatnonzero(words))
    return frames


def _run(recognizer: PlaceRecognizer, frames: list[np.ndarray], first_stamp_ns: int, robot: str | None = None) -> None:
    for i, words in enumerate(frames):
        recognizer.process(words, first_stamp_ns + i * 100_000_000, robot=robot)  # 10 Hz


def _recognizer(config: FabMapConfig, robot: str) -> PlaceRecognizer:
    return PlaceRecognizer(_tree(), SAMPLES, config, VOCABULARY, robot=robot)


F1, F2, QUERIES = _walk(30, seed=1), _walk(25, seed=2), _walk(6, seed=3) + _walk(6, seed=1)[::2]
F2_START_NS = 10 * 10**9  # after F1's last stamp (2.9 s)


@pytest.fixture(params=sorted(CONFIGS))
def maps(request, tmp_path: Path) -> dict[str, object]:
    """Map A (robot r1 over F1), map B (a fresh recognizer, robot r2 over F2), and the map one recognizer
    builds over F1 then, in a session of r2, F2."""
    config = CONFIGS[request.param]
    first = _recognizer(config, "r1")
    _run(first, F1, 0)
    first.save_map(tmp_path / "a.npz")
    second = _recognizer(config, "r2")
    _run(second, F2, F2_START_NS)
    second.save_map(tmp_path / "b.npz")
    one_go = _recognizer(config, "r1")
    _run(one_go, F1, 0)
    one_go.start_session("r2")
    _run(one_go, F2, F2_START_NS, robot="r2")
    one_go.save_map(tmp_path / "one_go.npz")
    if request.param == "keyframes":  # the comparison must cover frames keyframing leaves out
        assert one_go.num_places < len(F1) + len(F2)
    else:
        assert one_go.num_places == len(F1) + len(F2)
    return {"a": tmp_path / "a.npz", "b": tmp_path / "b.npz", "one_go": tmp_path / "one_go.npz",
            "config": request.param}


def _read(path: Path) -> dict[str, np.ndarray]:
    return read_map_unchecked_vocabulary(path)


def _assert_same_places(left: dict[str, np.ndarray], right: dict[str, np.ndarray]) -> None:
    for key in PLACE_KEYS:
        np.testing.assert_array_equal(left[key], right[key], err_msg=key)


def test_merge_equals_the_map_built_in_one_go(maps, tmp_path):
    a, b, one_go = _read(maps["a"]), _read(maps["b"]), _read(maps["one_go"])
    merged = merge_maps(a, b)
    write_map(tmp_path / "merged.npz", merged)
    merged = _read(tmp_path / "merged.npz")  # what the file holds passes the reader's checks
    _assert_same_places(merged, one_go)
    assert list(merged["session_robots"]) == ["r1", "r2"]
    assert int(merged["next_query_id"]) == int(one_go["next_query_id"]) == len(F1) + len(F2)
    assert not bool(merged["has_previous_posterior"]) and merged["previous_posterior"].size == 0
    assert str(merged["config_json"]) == str(a["config_json"])
    assert int(merged["format_version"]) == 2

    config = CONFIGS[maps["config"]]
    from_merged, from_one_go = _recognizer(config, "r3"), _recognizer(config, "r3")
    from_merged.load_map(tmp_path / "merged.npz")
    from_one_go.load_map(maps["one_go"])
    stored = from_merged.num_places
    for i, words in enumerate(QUERIES):
        stamp = 100 * 10**9 + i * 10**9
        left, right = from_merged.process(words, stamp), from_one_go.process(words, stamp)
        np.testing.assert_array_equal(left.hypothesis_place_ids, right.hypothesis_place_ids)
        np.testing.assert_allclose(left.hypothesis_probabilities, right.hypothesis_probabilities, rtol=1e-9)
        np.testing.assert_allclose(left.new_place_probability, right.new_place_probability, rtol=1e-9)
        assert left.match == right.match and left.added_place_id == right.added_place_id
    assert np.isin(np.arange(stored), left.hypothesis_place_ids).all()  # every stored place was compared


def test_removing_the_merged_session_gives_back_the_first_map(maps):
    a, b = _read(maps["a"]), _read(maps["b"])
    cut = remove_session(merge_maps(a, b), 1)
    _assert_same_places(cut, a)
    # Query ids are never given out twice: the cut map's next session starts after the removed one's frames.
    assert int(cut["next_query_id"]) == len(F1) + len(F2)
    first_only = remove_session(merge_maps(a, b), 0)
    np.testing.assert_array_equal(first_only["word_indices"], b["word_indices"])
    np.testing.assert_array_equal(first_only["place_sessions"], np.zeros(b["place_stamps_ns"].size))
    np.testing.assert_array_equal(first_only["place_frames"], b["place_frames"] + len(F1))
    assert list(first_only["session_robots"]) == ["r2"]


def _session_map(robots: list[str], places: list[int], seed: int = 0) -> dict[str, np.ndarray]:
    """A map with one session of each robot holding that many random places, frames 0, 1, 2, ...; each
    session's stamps start 100 ns after the previous one's places."""
    rng = np.random.default_rng(seed)
    rows = sp.csr_matrix(rng.random((sum(places), V)) < 0.3)
    rows.sort_indices()
    counts = np.array(places)
    gaps = np.repeat(100 * np.arange(len(places)), counts)
    return {
        "vocabulary_id": np.array(VOCABULARY), "vocabulary_size": np.array(V),
        "word_indptr": rows.indptr.astype(np.int64), "word_indices": rows.indices.astype(np.int64),
        "place_stamps_ns": np.arange(counts.sum(), dtype=np.int64) + gaps,
        "place_frames": np.arange(counts.sum(), dtype=np.int64), "next_query_id": np.array(counts.sum()),
        "previous_posterior": np.zeros(0), "has_previous_posterior": np.array(False),
        "place_sessions": np.repeat(np.arange(len(places), dtype=np.int32), counts),
        "session_robots": np.array(robots), "session_first_queries": np.concatenate([[0], np.cumsum(counts)[:-1]]),
        "config_json": np.array("{}"),
    }


def test_later_sessions_are_renumbered_and_query_ids_shifted():
    a = _session_map(["r1", "r2"], [3, 4])
    b = _session_map(["r3", "r1"], [2, 5], seed=1)
    merged = merge_maps(a, b)
    np.testing.assert_array_equal(merged["place_sessions"], [0] * 3 + [1] * 4 + [2] * 2 + [3] * 5)
    assert list(merged["session_robots"]) == ["r1", "r2", "r3", "r1"]
    np.testing.assert_array_equal(merged["session_first_queries"], [0, 3, 7, 9])
    np.testing.assert_array_equal(merged["place_frames"], np.arange(14))
    assert int(merged["next_query_id"]) == 14

    cut = remove_session(merged, 1)
    np.testing.assert_array_equal(cut["place_sessions"], [0] * 3 + [1] * 2 + [2] * 5)
    assert list(cut["session_robots"]) == ["r1", "r3", "r1"]
    np.testing.assert_array_equal(cut["session_first_queries"], [0, 7, 9])
    np.testing.assert_array_equal(cut["place_frames"], [0, 1, 2, *range(7, 14)])
    indptr = merged["word_indptr"]
    expected = np.concatenate([merged["word_indices"][: indptr[3]], merged["word_indices"][indptr[7]:]])
    np.testing.assert_array_equal(cut["word_indices"], expected)
    np.testing.assert_array_equal(np.diff(cut["word_indptr"]), np.delete(np.diff(indptr), [3, 4, 5, 6]))


def test_maps_of_different_vocabularies_are_not_merged():
    a = _session_map(["r1"], [3])
    other_id = {**a, "vocabulary_id": np.array("vocab-b")}
    with pytest.raises(VocabularyMismatchError, match=r"'vocab-a'.*'vocab-b'"):
        merge_maps(a, other_id)
    with pytest.raises(VocabularyMismatchError, match="41 words"):
        merge_maps(a, {**a, "vocabulary_size": np.array(V + 1)})


@pytest.mark.parametrize("number", [-1, 2, 10])
def test_a_session_the_map_does_not_have_is_refused(number):
    with pytest.raises(DataError, match=f"no session {number} .*sessions 0 to 1"):
        remove_session(_session_map(["r1", "r2"], [2, 2]), number)


def test_summary_counts_sessions_places_and_stamps():
    arrays = _session_map(["r1", "r2", "r1"], [3, 0, 4])
    summary = map_summary(arrays, file_bytes=1234)
    assert summary.places == 7 and summary.words_stored == int(arrays["word_indptr"][-1])
    assert summary.robots == ("r1", "r2") and summary.file_bytes == 1234
    assert [(s.number, s.robot, s.places) for s in summary.sessions] == [(0, "r1", 3), (1, "r2", 0), (2, "r1", 4)]
    assert (summary.sessions[0].first_stamp_ns, summary.sessions[0].last_stamp_ns) == (0, 2)
    assert summary.sessions[1].first_stamp_ns is None and summary.sessions[1].last_stamp_ns is None
    assert (summary.sessions[2].first_stamp_ns, summary.sessions[2].last_stamp_ns) == (203, 206)
    assert [s.first_query_id for s in summary.sessions] == [0, 3, 3]
    values = summary.to_json()
    assert values["robots"] == ["r1", "r2"] and values["sessions"][2]["places"] == 4
