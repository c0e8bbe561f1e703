"""The benchmarks run (--quick) and print their figures; no timing is asserted."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import pytest

from aefabmap_ros.cli import bench, bench_nodes, bench_pipeline, bench_stages


def test_dispatcher_rejects_unknown_benchmark(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["nope"]) == 1
    assert "ERROR: unknown benchmark 'nope'" in capsys.readouterr().err
    assert bench.main([]) == 1


def test_pipeline_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["pipeline", "--quick", "--features", "sift"]) == 0
    out = capsys.readouterr().out
    for stage in ("decode", "features", "quantize", "fabmap", "images/s on one core"):
        assert stage in out


def test_pipeline_baseline_model_needs_a_baseline(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert bench.main(["pipeline", "--quick", "--model", str(tmp_path), "--baseline-model", str(tmp_path)]) == 1
    assert "ERROR: --baseline-model needs --baseline and --model" in capsys.readouterr().err


def test_baseline_nodes_load_the_baseline_model(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # A model with a setting the baseline does not know cannot be loaded there: its nodes get their own.
    commands: list[list[str]] = []
    monkeypatch.setattr(subprocess, "Popen", lambda command, **_: commands.append(command))
    ours, theirs = bench_nodes.Setup("this", None, False), bench_nodes.Setup("baseline", tmp_path, False,
                                                                                    Path("/old_model"))
    log: Any = None
    for setup in (ours, theirs):
        bench_nodes._launch(setup, Path("/model"), tmp_path / "params.yaml", log)
    assert [command[command.index("--model") + 1] for command in commands] == ["/model", "/old_model"]


def test_fabmap_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["fabmap", "--quick"]) == 0
    assert "ms" in capsys.readouterr().out


def test_verify_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["verify", "--quick", "--features", "sift"]) == 0
    out = capsys.readouterr().out
    for part in ("verify nearby", "verify distant", "per closure, 5 cand.", "KiB per frame", "feature extraction",
                 "with depth", "the metric test ran on"):
        assert part in out


def test_backend_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["backend", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "'added': 60" in out and "update per closure at" in out


def test_pipeline_times_the_papers_network_beside_the_distilled_encoder() -> None:
    import numpy as np
    import scipy.sparse

    from aefabmap_ros.cli.bench_stages import stage_latencies
    from aefabmap_ros.cli.bench_vocab import _synthetic_images
    from aefabmap_ros.features.extraction import FeatureConfig, extract_features
    from aefabmap_ros.model.directory import Model
    from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer
    from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary

    images = _synthetic_images(2, (240, 320))
    descriptors = np.concatenate([extract_features(image, FeatureConfig()).descriptors for image in images])
    config = VocabularyConfig(size=6, pca_dim=8, ae_embedding_dim=4, ae_epochs=1, num_threads=1,
                              ae_network="conv", ae_student_hidden=8, ae_student_epochs=1)
    quantizer = train_vocabulary(descriptors, config, progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer) and quantizer.encoder is not None
    tree = np.vstack([np.arange(6) - 1.0, np.full((3, 6), 0.2)])
    tree[0, 0] = 0
    samples = scipy.sparse.csr_matrix(np.eye(2, 6))
    for used, expected in ((quantizer, True), (quantizer.with_encoder(None), False)):
        model = Model.create(FeatureConfig(), config, used, tree_matrix=tree, new_place_samples=samples)
        stages = stage_latencies(model, images)
        assert ("quantize (paper's network)" in stages) is expected
        assert all(len(values) == 2 for values in stages.values())


def test_the_pipeline_benchmark_runs_in_a_dds_domain_of_its_own() -> None:
    environment: dict[str, str] = {}
    assert bench_pipeline.isolate_ros_domain(environment, pid=4242) == "43"
    assert environment == {"ROS_DOMAIN_ID": "43", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    chosen = {"ROS_DOMAIN_ID": "7"}  # the caller's choice stands
    assert bench_pipeline.isolate_ros_domain(chosen, pid=4242) == "7"


def test_camera_runs_report_where_each_node_dropped_frames() -> None:
    """The nodes' stop summaries, as aefabmap_launch's log interleaves them with other lines."""
    log = "\n".join([
        "[INFO] [1795474683.96] [feature_node]: feature_node: dropped_busy=48, processed=102",
        "[WARN] [1795474684.01] [quantizer_node]: dropped input (busy, 3 so far): a newer features message arrived",
        "[INFO] [1795474684.10] [quantizer_node]: quantizer_node: dropped_before_callback=2, dropped_busy=26, "
        "processed=74",
        "[INFO] [1795474684.20] [fabmap_node]: fabmap_node: processed=74",
        "[INFO] [1795474684.30] [fabmap_node]: saved the map: 74 places",
    ])
    assert bench_nodes.node_drops(log) == {"feature_node busy": 48, "quantizer_node before_callback": 2,
                               "quantizer_node busy": 26}
    assert bench_nodes.node_drops("") == {}


def test_stage_timings_run_with_the_thread_pools_of_one_node_process() -> None:
    import torch
    from threadpoolctl import threadpool_info

    from aefabmap_ros.nodes.launch_table import DETECTION_NODES, threads_per_process

    before = torch.get_num_threads()
    torch.set_num_threads(4)
    try:
        with bench_stages.thread_pools_of_a_node_process() as threads:
            assert threads == threads_per_process(len(DETECTION_NODES))
            assert torch.get_num_threads() == threads
            assert all(pool["num_threads"] <= threads for pool in threadpool_info())
        assert torch.get_num_threads() == 4  # restored for whatever runs next
    finally:
        torch.set_num_threads(before)
