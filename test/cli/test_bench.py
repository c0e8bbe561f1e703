"""The benchmarks run (--quick) and print their figures; no timing is asserted."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import pytest

from aefabmap_ros.cli import bench, bench_pipeline


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
    ours, theirs = bench_pipeline.Setup("this", None, False), bench_pipeline.Setup("baseline", tmp_path, False,
                                                                                    Path("/old_model"))
    log: Any = None
    for setup in (ours, theirs):
        bench_pipeline._launch(setup, Path("/model"), tmp_path / "params.yaml", log)
    assert [command[command.index("--model") + 1] for command in commands] == ["/model", "/old_model"]


def test_fabmap_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["fabmap", "--quick"]) == 0
    assert "ms" in capsys.readouterr().out


def test_verify_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["verify", "--quick", "--features", "sift"]) == 0
    out = capsys.readouterr().out
    for part in ("verify nearby", "verify distant", "per closure, 5 cand.", "KiB per frame", "feature extraction"):
        assert part in out


def test_backend_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["backend", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "'added': 60" in out and "update per closure at" in out
