"""aefabmap_words end to end on a recorded bag: the table, the JSON, one pass over features per feature setting,
and bad input as one ERROR line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from aefabmap_ros.cli.words import main
from aefabmap_ros.evaluation.word_statistics import word_statistics
from aefabmap_ros.features.extraction import extract_features
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.model.training import pairs_at_gap
from test.revisit_fixture import RevisitData


def test_prints_and_writes_the_figures_of_each_model(tmp_path: Path, revisit_data: RevisitData,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    copy = tmp_path / "same_model"
    shutil.copytree(revisit_data.model_dir, copy)
    out = tmp_path / "words.json"
    argv = ["--model", str(revisit_data.model_dir), "--model", str(copy), "--bag", str(revisit_data.bag),
            "--gaps", "16,1", "--far", "8", "--json", str(out), "--work-dir", str(tmp_path / "work"), "--quiet"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "one word, gap 1" in printed and "one word, gap 16" in printed and "shared at 8" in printed
    report = json.loads(out.read_text())
    first, second = report["models"]
    assert report["stride"] == 1 and first["kind"] == "kmeans" and first["far_gap"] == 8
    assert [a["gap"] for a in first["agreement"]] == [1, 16]
    assert {k: v for k, v in first.items() if k != "model"} == {k: v for k, v in second.items() if k != "model"}

    # The same figures as the library computes on the bag's frames with the model's feature settings; gap 16 is
    # the revisit (the second pass re-exposes the first pass's places).
    model = load_model(revisit_data.model_dir)
    frames = [extract_features(gray, model.feature_config) for _, gray in ImageSource(bag=revisit_data.bag).frames()]
    expected = word_statistics(model.quantizer, frames, {1: pairs_at_gap(frames, 1), 16: pairs_at_gap(frames, 16)},
                               far_gap=8)
    assert [a["pairs"] for a in first["agreement"]] == [a.pairs for a in expected.agreement]
    assert first["agreement"][1]["pairs"] > 100  # the revisits match
    assert first["agreement"][1]["one_word"] == pytest.approx(expected.agreement[1].one_word)
    assert first["shared_far"] == pytest.approx(expected.shared_far)
    assert first["perplexity"] == pytest.approx(expected.perplexity)

    # Every second frame: the revisit is 8 frames later.
    assert main([*argv[:6], "--stride", "2", "--gaps", "8", "--json", str(out), "--quiet"]) == 0
    strided = json.loads(out.read_text())["models"][0]
    assert strided["agreement"][0]["pairs"] > 50 and strided["words_per_image"] == pytest.approx(
        expected.words_per_image, rel=0.2)


def _error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ")
    return err


def test_bad_input_is_one_error_line(tmp_path: Path, revisit_data: RevisitData,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    model = ["--model", str(revisit_data.model_dir)]
    bag = ["--bag", str(revisit_data.bag)]
    assert "--bag (with --topic) or --images" in _error(capsys, model)
    assert "--bag (with --topic) or --images" in _error(capsys, [*model, *bag, "--images", str(tmp_path)])
    assert "'/camera' not in bag" in _error(capsys, [*model, *bag, "--topic", "/camera"])
    assert "no image files" in _error(capsys, [*model, "--images", str(tmp_path)])
    assert "--gaps '0'" in _error(capsys, [*model, *bag, "--gaps", "0"])
    assert "--gaps 'a,b'" in _error(capsys, [*model, *bag, "--gaps", "a,b"])
    assert "--stride must be >= 1" in _error(capsys, [*model, *bag, "--stride", "0"])
    assert "--far must be >= 1" in _error(capsys, [*model, *bag, "--far", "0"])
    assert "does not exist" in _error(capsys, [*model, *bag, "--json", str(tmp_path / "no" / "w.json")])
    assert "usage: aefabmap_words" in _error(capsys, [*bag])  # --model is required
    missing = tmp_path / "no_model"
    assert str(missing) in _error(capsys, ["--model", str(missing), *bag])
