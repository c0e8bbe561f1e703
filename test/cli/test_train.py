"""aefabmap_train: a small bag -> a model the nodes load; every bad input -> ERROR and exit 1."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from aefabmap_ros.cli.train import main
from aefabmap_ros.io.bags import write_image_bag
from aefabmap_ros.model.directory import load_model
from test.revisit_fixture import RevisitData

SMALL = ["--vocabulary", "kmeans", "--size", "40", "--max-features", "150", "--quiet"]


def test_trains_a_model_the_nodes_load(tmp_path: Path, revisit_data: RevisitData,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "model"
    assert main(["--bag", str(revisit_data.first_pass_bag), "--topic", "/image", "--out", str(out), *SMALL]) == 0
    printed = capsys.readouterr().out
    assert "written to" in printed and "16 (0 without features)" in printed
    model = load_model(out)
    assert model.quantizer.size == 40 and model.feature_config.max_features == 150
    assert model.tree_matrix is not None and model.tree_matrix.shape == (4, 40)
    assert model.new_place_samples is not None and model.new_place_samples.shape == (16, 40)
    sources: Any = model.provenance["sources"]
    assert sources[0]["files"]  # bag file hashes recorded

    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    from aefabmap_ros.nodes.fabmap_node import FabMapNode
    from aefabmap_ros.nodes.quantizer_node import QuantizerNode

    rclpy.init()
    try:
        for node_class in (QuantizerNode, FabMapNode):
            node = node_class(parameter_overrides=[Parameter("model_dir", value=str(out))])
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_the_trained_sift_first_octave_is_what_feature_node_extracts_with(tmp_path: Path,
                                                                          revisit_data: RevisitData) -> None:
    config = tmp_path / "train.yaml"
    config.write_text("feature:\n  sift_first_octave: 0\n")
    out = tmp_path / "model"
    assert main(["--bag", str(revisit_data.first_pass_bag), "--topic", "/image", "--config", str(config),
                 "--out", str(out), *SMALL]) == 0
    model = load_model(out)
    assert model.feature_config.sift_first_octave == 0 and model.feature_config.max_features == 150

    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    from aefabmap_ros.nodes.feature_node import FeatureNode

    rclpy.init()
    try:  # the node's own parameter says -1: the model's setting wins, so its features match the vocabulary
        node = FeatureNode(parameter_overrides=[Parameter("model_dir", value=str(out)),
                                                Parameter("sift_first_octave", value=-1)])
        assert node.config == model.feature_config
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_rerun_resumes_from_cached_features(tmp_path: Path, revisit_data: RevisitData) -> None:
    args = ["--bag", str(revisit_data.first_pass_bag), "--topic", "/image", *SMALL]
    work = tmp_path / "work"
    assert main([*args, "--out", str(tmp_path / "a"), "--work-dir", str(work)]) == 0
    cached = sorted(work.glob("features-*.npz"))
    assert len(cached) == 1
    before = cached[0].stat().st_mtime_ns
    assert main([*args, "--out", str(tmp_path / "b"), "--work-dir", str(work)]) == 0
    assert cached[0].stat().st_mtime_ns == before  # reused, not recomputed
    assert load_model(tmp_path / "a").vocabulary_id == load_model(tmp_path / "b").vocabulary_id  # deterministic


def _error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ")
    return err


def test_bad_inputs(tmp_path: Path, revisit_data: RevisitData, capsys: pytest.CaptureFixture[str]) -> None:
    bag = str(revisit_data.first_pass_bag)
    out = str(tmp_path / "model")
    assert "'/camera' not in bag" in _error(capsys, ["--bag", bag, "--topic", "/camera", "--out", out, *SMALL])
    assert "does not exist" in _error(capsys, ["--bag", str(tmp_path / "nope"), "--out", out, *SMALL])
    assert "no training images" in _error(capsys, ["--out", out, *SMALL])
    assert "no image files" in _error(capsys, ["--images", str(tmp_path), "--out", out, *SMALL])

    corrupt = tmp_path / "corrupt"
    write_image_bag(corrupt, "/image", [(i, np.zeros((8, 8), np.uint8)) for i in range(50)])
    storage = next(corrupt.glob("*.mcap"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    assert "corrupt" in _error(capsys, ["--bag", str(corrupt), "--out", out, *SMALL])

    empty = tmp_path / "empty"
    write_image_bag(empty, "/image", [])
    assert "empty" in _error(capsys, ["--bag", str(empty), "--out", out, *SMALL])

    blank = tmp_path / "blank"
    write_image_bag(blank, "/image", [(i, np.full((32, 32), 90, np.uint8)) for i in range(3)])
    assert "fewer than the vocabulary size" in _error(capsys, ["--bag", str(blank), "--out", out, *SMALL])

    config = tmp_path / "train.yaml"
    config.write_text("vocabulary:\n  sise: 10\n")
    assert "unknown key(s) ['sise']" in _error(capsys, ["--bag", bag, "--config", str(config), "--out", out])

    (tmp_path / "exists").mkdir()
    assert "already exists" in _error(capsys, ["--bag", bag, "--out", str(tmp_path / "exists"), *SMALL])
    if os.geteuid() != 0:  # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        assert "not writable" in _error(capsys, ["--bag", bag, "--out", str(locked / "m"), *SMALL])
    assert "does not exist" in _error(capsys, ["--bag", bag, "--out", str(tmp_path / "no" / "m"), *SMALL])


def test_a_failure_before_any_cached_stage_leaves_no_work_folder(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    images = tmp_path / "images"
    images.mkdir()
    (images / "a.png").write_bytes(b"not a png")  # the folder exists: the failure comes at extraction
    assert main(["--images", str(images), "--out", str(tmp_path / "model"), "--quiet"]) == 1
    assert capsys.readouterr().err.startswith("ERROR: cannot read image file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images"]  # no .model.work, no model
