"""The benchmarks run (--quick) and print their figures; no timing is asserted."""

from __future__ import annotations

import pytest

from aefabmap_ros.cli import bench


def test_dispatcher_rejects_unknown_benchmark(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["nope"]) == 1
    assert "ERROR: unknown benchmark 'nope'" in capsys.readouterr().err
    assert bench.main([]) == 1


def test_pipeline_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["pipeline", "--quick", "--features", "sift"]) == 0
    out = capsys.readouterr().out
    for stage in ("decode", "features", "quantize", "fabmap", "images/s on one core"):
        assert stage in out


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
