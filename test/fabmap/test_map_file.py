"""The place map file on its own: hand-made arrays written and read back, each kind of corruption refused by
name, another vocabulary refused, and the settings a map was made with compared both ways."""

import json
from dataclasses import asdict
from typing import Any

import numpy as np
import pytest

from aefabmap_ros.errors import ModelError, VocabularyMismatchError
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.map_file import config_differences, read_map, write_map


def _arrays(**changes: Any) -> dict[str, np.ndarray]:
    """Two places over a 10-word vocabulary: words {1, 4} and {7}."""
    values: dict[str, Any] = {
        "vocabulary_id": "v", "vocabulary_size": 10, "word_indptr": [0, 2, 3], "word_indices": [1, 4, 7],
        "place_stamps_ns": [10, 20], "place_frames": [0, 1], "next_query_id": 2,
        "previous_posterior": [0.5, 0.25, 0.25], "has_previous_posterior": True,
        "config_json": json.dumps(asdict(FabMapConfig())),
        "place_sessions": np.array([0, 1], dtype=np.int32), "session_robots": np.array(["", "r2"]),
        "session_first_queries": [0, 1],
    }
    values.update(changes)
    return {key: np.asarray(value) for key, value in values.items()}


def test_a_written_map_reads_back(tmp_path):
    path = tmp_path / "map.npz"
    write_map(path, _arrays())
    state = read_map(path, "v", 10)
    assert state["word_indptr"].tolist() == [0, 2, 3] and state["word_indices"].tolist() == [1, 4, 7]
    assert state["place_stamps_ns"].tolist() == [10, 20] and int(state["next_query_id"]) == 2
    assert state["previous_posterior"].tolist() == [0.5, 0.25, 0.25]
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]  # written atomically: no temporary left


@pytest.mark.parametrize(("changes", "problem"), [
    ({"word_indptr": [0, 2, 2]}, "inconsistent word_indptr"),
    ({"word_indices": [1, 4, 10]}, "word ids out of range"),
    ({"word_indices": [4, 1, 7]}, "word ids not sorted unique per place"),
    ({"word_indices": [4, 4, 7]}, "word ids not sorted unique per place"),
    ({"place_stamps_ns": [10]}, "stamps/frames do not match the number of places"),
    ({"previous_posterior": [0.25] * 4}, "previous posterior longer than the map"),
    ({"place_sessions": np.array([0, 2], dtype=np.int32)}, "place sessions outside the 2 sessions"),
    ({"place_sessions": np.array([0], dtype=np.int32)}, "place_sessions has shape"),
    ({"session_first_queries": [1, 0]}, "first query ids are not increasing"),
    ({"session_robots": np.array(["", "a\nb"])}, "one-line string"),
])
def test_a_corrupt_map_is_refused_naming_the_problem(tmp_path, changes, problem):
    path = tmp_path / "map.npz"
    write_map(path, _arrays(**changes))
    with pytest.raises(ModelError, match=f"corrupt map file .*{problem}"):
        read_map(path, "v", 10)


def test_rows_may_end_and_start_on_the_same_word(tmp_path):
    """Sortedness is per place: place 1 may start with a word smaller than the last of place 0."""
    path = tmp_path / "map.npz"
    write_map(path, _arrays(word_indices=[1, 8, 2]))
    assert read_map(path, "v", 10)["word_indices"].tolist() == [1, 8, 2]


def test_a_map_of_another_vocabulary_is_refused(tmp_path):
    path = tmp_path / "map.npz"
    write_map(path, _arrays())
    with pytest.raises(VocabularyMismatchError, match=r"belongs to vocabulary 'v'.*vocabulary 'w'"):
        read_map(path, "w", 10)
    with pytest.raises(VocabularyMismatchError, match="has 10 words, the model 12"):
        read_map(path, "v", 12)


def test_config_differences_name_each_setting_both_ways():
    default = FabMapConfig()
    saved = asdict(default)
    saved["top_k"] = default.top_k + 1
    saved["retired_setting"] = 1  # a map from a version with a setting this one lacks
    del saved["match_threshold"]  # ... or without one this version has
    assert config_differences(json.dumps(saved), default) == {
        "match_threshold": (None, default.match_threshold),
        "retired_setting": (1, None),
        "top_k": (default.top_k + 1, default.top_k),
    }
    assert config_differences(json.dumps(asdict(default)), default) == {}
    assert config_differences("{not json", default) == {"config_json": ("{not json", "unreadable")}
    assert config_differences("[1, 2]", default) == {"config_json": ("[1, 2]", "unreadable")}


def test_sessions_read_back(tmp_path):
    path = tmp_path / "map.npz"
    write_map(path, _arrays())
    state = read_map(path, "v", 10)
    assert state["place_sessions"].tolist() == [0, 1]
    assert state["session_robots"].tolist() == ["", "r2"] and state["session_first_queries"].tolist() == [0, 1]


def test_a_format_1_map_reads_as_one_session_of_every_place(tmp_path):
    """Maps written before sessions: no session columns, format version 1."""
    path = tmp_path / "old.npz"
    arrays = {key: value for key, value in _arrays().items()
              if key not in ("place_sessions", "session_robots", "session_first_queries")}
    arrays["format_version"] = np.array(1)
    np.savez(path, **arrays)  # type: ignore[arg-type]
    state = read_map(path, "v", 10)
    assert state["place_sessions"].tolist() == [0, 0]
    assert state["session_robots"].tolist() == [""] and state["session_first_queries"].tolist() == [0]


def test_a_map_without_its_session_columns_is_not_written(tmp_path):
    arrays = {key: value for key, value in _arrays().items() if key != "place_sessions"}
    with pytest.raises(ModelError, match=r"lacks.*place_sessions"):
        write_map(tmp_path / "map.npz", arrays)
    assert not list(tmp_path.iterdir())
