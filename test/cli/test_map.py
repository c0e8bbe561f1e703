"""aefabmap_map end to end: info, merge and remove-session on maps a recognizer saved, a format-1 map, and every
bad input refused as one ERROR line with nothing written."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from aefabmap_ros.cli.map import main
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.map_file import read_map_unchecked_vocabulary
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.features.extraction import FeatureConfig
from aefabmap_ros.model.directory import Model, save_model
from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary

V = 40
FORMAT_1_KEYS = ("vocabulary_id", "vocabulary_size", "word_indptr", "word_indices", "place_stamps_ns", "place_frames",
                 "next_query_id", "previous_posterior", "has_previous_posterior", "config_json")


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A V-word k-means model (the maps below are of its vocabulary)."""
    descriptors = np.random.default_rng(0).uniform(0, 100, (400, 128)).astype(np.float32)
    config = VocabularyConfig(kind="kmeans", size=V)
    directory = tmp_path_factory.mktemp("model") / "model"
    save_model(directory, Model.create(FeatureConfig(), config, train_vocabulary(descriptors, config)))
    return directory


def _vocabulary_id(model_dir: Path) -> str:
    return str(json.loads((model_dir / "metadata.json").read_text())["model_id"])


def _save_map(path: Path, vocabulary_id: str, robot: str, n: int, seed: int, first_stamp_ns: int = 0) -> Path:
    rng = np.random.default_rng(100 + seed)
    parent = np.array([0] + [int(rng.integers(0, q)) for q in range(1, V)])
    probs = rng.uniform(0.05, 0.6, size=(3, V))
    probs[1:, 0] = probs[0, 0]
    samples = sp.csr_matrix(rng.random((15, V)) < 0.25)
    recognizer = PlaceRecognizer(ChowLiuTree(parent, probs[0], probs[1], probs[2]), samples,
                                 FabMapConfig.openfabmap(motion_model=True), vocabulary_id, robot=robot)
    for i in range(n):
        recognizer.process(np.flatnonzero(rng.random(V) < 0.25), first_stamp_ns + i * 10**8)
    recognizer.save_map(path)
    return path


@pytest.fixture
def maps(tmp_path: Path, model_dir: Path) -> dict[str, Path]:
    vocabulary = _vocabulary_id(model_dir)
    return {"a": _save_map(tmp_path / "a.npz", vocabulary, "r1", 8, seed=1),
            "b": _save_map(tmp_path / "b.npz", vocabulary, "r2", 5, seed=2, first_stamp_ns=10**10),
            "other": _save_map(tmp_path / "other.npz", "another-vocabulary", "r1", 4, seed=3)}


def _run(capsys, argv: list[str]) -> tuple[int, str, str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_info_shows_sessions_robots_and_vocabulary(maps, tmp_path, capsys, model_dir):
    merged = tmp_path / "merged.npz"
    assert _run(capsys, ["merge", str(maps["a"]), str(maps["b"]), "--out", str(merged)])[0] == 0
    code, out, err = _run(capsys, ["info", str(merged), "--json", str(tmp_path / "info.json")])
    assert code == 0 and err == ""
    assert _vocabulary_id(model_dir) in out and "(40 words)" in out and "format 2" in out
    assert "13 (" in out and "'r1', 'r2'" in out  # places, robots
    table = [line.split() for line in out.splitlines() if line.startswith("  ")][1:]
    assert [row[:4] for row in table] == [["0", "'r1'", "8", "0"], ["1", "'r2'", "5", "8"]]
    assert table[1][4:] == ["10.000", "10.400"]  # first and last stamps of r2's places [s]
    report = json.loads((tmp_path / "info.json").read_text())
    assert report["places"] == 13 and report["robots"] == ["r1", "r2"] and report["file_bytes"] == merged.stat().st_size
    assert [s["places"] for s in report["sessions"]] == [8, 5] and report["next_query_id"] == 13


def test_merge_then_remove_session_gives_back_the_first_map(maps, tmp_path, capsys, model_dir):
    merged, cut = tmp_path / "merged.npz", tmp_path / "cut.npz"
    code, out, _ = _run(capsys, ["merge", str(maps["a"]), str(maps["b"]), "--out", str(merged),
                                 "--model", str(model_dir)])
    assert code == 0 and "13 places in 2 sessions" in out
    assert _run(capsys, ["remove-session", str(merged), "1", "--out", str(cut)])[0] == 0
    a, got = read_map_unchecked_vocabulary(maps["a"]), read_map_unchecked_vocabulary(cut)
    for key in ("word_indptr", "word_indices", "place_stamps_ns", "place_frames", "place_sessions", "session_robots",
                "session_first_queries"):
        np.testing.assert_array_equal(got[key], a[key], err_msg=key)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary left


def test_a_format_1_map_is_one_session_and_merges(maps, tmp_path, capsys):
    with np.load(maps["a"]) as data:
        old = {key: data[key] for key in FORMAT_1_KEYS}
    np.savez(tmp_path / "old.npz", format_version=np.array(1), **old)
    code, out, _ = _run(capsys, ["info", str(tmp_path / "old.npz")])
    assert code == 0 and "format 1" in out and "sessions    1" in out and "robots      ''" in out
    merged = tmp_path / "merged.npz"
    assert _run(capsys, ["merge", str(tmp_path / "old.npz"), str(maps["b"]), "--out", str(merged)])[0] == 0
    arrays = read_map_unchecked_vocabulary(merged)
    assert int(arrays["format_version"]) == 2 and list(arrays["session_robots"]) == ["", "r2"]
    np.testing.assert_array_equal(arrays["place_sessions"], [0] * 8 + [1] * 5)


def _garbage(path: Path, _: dict[str, Path]) -> Path:
    path.write_bytes(b"PK\x03\x04" + bytes(range(256)) * 4)
    return path


def _truncated(path: Path, maps: dict[str, Path]) -> Path:
    data = maps["b"].read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _empty(path: Path, _: dict[str, Path]) -> Path:
    path.write_bytes(b"")
    return path


def _not_a_map(path: Path, _: dict[str, Path]) -> Path:
    np.savez(path, x=np.zeros(3))
    return path


def _bad_sessions(path: Path, maps: dict[str, Path]) -> Path:
    with np.load(maps["b"]) as data:
        arrays = {key: data[key] for key in data.files}
    arrays["place_sessions"] = arrays["place_sessions"] + 3
    np.savez(path, **arrays)
    return path


BROKEN = {"missing": lambda path, _: path, "garbage": _garbage, "truncated": _truncated, "empty": _empty,
          "not a map": _not_a_map, "bad sessions": _bad_sessions}


def _refused(capsys, argv: list[str], out: Path, *names: str) -> str:
    """Run a command that must fail: one ERROR line naming ``names``, exit 1, ``out`` as it was."""
    before = out.read_bytes()
    code, stdout, err = _run(capsys, argv)
    assert code == 1 and stdout == ""
    assert err.startswith("ERROR: ") and len(err.strip().splitlines()) == 1, err
    for name in names:
        assert name in err, err
    assert out.read_bytes() == before
    assert [p.name for p in out.parent.iterdir() if p.name.endswith(".tmp")] == []
    return err


@pytest.fixture
def existing_out(tmp_path: Path) -> Path:
    out = tmp_path / "out.npz"
    out.write_bytes(b"an earlier result the refused command must not touch")
    return out


@pytest.mark.parametrize("fault", sorted(BROKEN))
@pytest.mark.parametrize("position", ["A", "B"])
def test_a_broken_map_file_is_refused_naming_it(fault, position, maps, tmp_path, capsys, existing_out):
    broken = BROKEN[fault](tmp_path / f"broken_{position}.npz", maps)
    first, second = (broken, maps["b"]) if position == "A" else (maps["a"], broken)
    _refused(capsys, ["merge", str(first), str(second), "--out", str(existing_out)], existing_out, str(broken))
    _refused(capsys, ["remove-session", str(broken), "0", "--out", str(existing_out)], existing_out, str(broken))
    _refused(capsys, ["info", str(broken)], existing_out, str(broken))


def test_maps_of_another_vocabulary_are_refused_naming_both(maps, capsys, existing_out, model_dir):
    vocabulary = _vocabulary_id(model_dir)
    _refused(capsys, ["merge", str(maps["a"]), str(maps["other"]), "--out", str(existing_out)], existing_out,
             str(maps["a"]), str(maps["other"]), vocabulary, "another-vocabulary")
    # Both maps of one vocabulary, but not the model's.
    other_b = maps["other"].with_name("other_b.npz")
    _save_map(other_b, "another-vocabulary", "r2", 3, seed=4)
    _refused(capsys, ["merge", str(maps["other"]), str(other_b), "--out", str(existing_out), "--model",
                      str(model_dir)], existing_out, str(maps["other"]), vocabulary, "another-vocabulary")
    _refused(capsys, ["merge", str(maps["a"]), str(maps["b"]), "--out", str(existing_out), "--model",
                      str(model_dir.parent / "no_model")], existing_out, "no_model")


@pytest.mark.parametrize("session", ["2", "-1"])
def test_a_session_the_map_does_not_have_is_refused(session, maps, capsys, existing_out):
    _refused(capsys, ["remove-session", str(maps["a"]), session, "--out", str(existing_out)], existing_out,
             f"no session {session} (it has sessions 0 to 0)")


def test_out_may_not_be_an_input(maps, capsys, tmp_path):
    a = maps["a"]
    same_by_another_name = tmp_path / "sub" / ".." / "a.npz"
    (tmp_path / "sub").mkdir()
    link = tmp_path / "hard_link.npz"
    link.hardlink_to(a)
    for out in (a, same_by_another_name, link):
        _refused(capsys, ["merge", str(a), str(maps["b"]), "--out", str(out)], a, "is the input map")
        _refused(capsys, ["merge", str(maps["b"]), str(a), "--out", str(out)], a, "is the input map")
        _refused(capsys, ["remove-session", str(a), "0", "--out", str(out)], a, "is the input map")


def test_usage_errors_are_one_error_line_and_exit_1(capsys):
    for argv in ([], ["merge", "a.npz"], ["frobnicate"], ["info"], ["remove-session", "a.npz", "x", "--out", "o"]):
        code, _, err = _run(capsys, argv)
        assert code == 1 and err.startswith("ERROR: ") and "usage: aefabmap_map" in err


def test_the_installed_command_runs(maps):
    result = subprocess.run([sys.executable, "-m", "aefabmap_ros.cli.map", "info", str(maps["a"])],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "places      8" in result.stdout
