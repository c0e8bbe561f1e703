"""``aefabmap_bench fabmap --places N`` end to end on a small map: a child process loads it and answers queries;
the figures are printed, the threaded scores equal one thread's and the top places agree with FAB-MAP 1."""

from __future__ import annotations

import re

import pytest

from aefabmap_ros.cli.bench_fabmap import main


def test_a_small_large_map_run_prints_its_figures(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--places", "3000", "--queries", "5", "--vocabulary-size", "500", "--words-per-image", "60"]) == 0
    out = capsys.readouterr().out
    assert "built 3,000 places (500 words)" in out and "loaded in" in out and "the same to the bit" in out
    gap = float(re.search(r"largest difference ([0-9.e+-]+)", out).group(1))  # type: ignore[union-attr]
    assert gap < 1e-9


def test_bad_sizes_are_one_error_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--places", "0"]) == 1
    assert capsys.readouterr().err.startswith("ERROR: --places and --queries must be >= 1")
