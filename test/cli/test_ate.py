"""aefabmap_ate: ATE lines, a plot, ERROR on bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.cli.ate import main
from aefabmap_ros.evaluation.trajectory_error import tum_text


def _write(path: Path, points: list[list[float]]) -> Path:
    poses = np.tile(np.eye(4), (len(points), 1, 1))
    poses[:, :3, 3] = points
    path.write_text(tum_text(np.arange(len(points), dtype=float), poses))
    return path


def test_ate_prints_rmse_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    square = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]
    reference = _write(tmp_path / "gt.tum", square)
    bumped = _write(tmp_path / "est.tum", [[0.0, 0.0, 0.1], [1.0, 0.0, -0.1], [1.0, 1.0, 0.1], [0.0, 1.0, -0.1]])
    plot = tmp_path / "ate.png"
    assert main(["--reference", str(reference), "--estimate", f"bumped={bumped}", "--estimate", f"same={reference}",
                 "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert "ATE RMSE bumped: 0.1000 m (4 poses, SE(3) alignment)" in out
    assert "ATE RMSE same: 0.0000 m" in out
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ate_bad_input_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    reference = _write(tmp_path / "gt.tum", [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    assert main(["--reference", str(reference), "--estimate", "no-equals-sign"]) == 1
    assert main(["--reference", str(reference), "--estimate", f"x={tmp_path / 'missing.tum'}"]) == 1
    err = capsys.readouterr().err
    assert "ERROR: --estimate 'no-equals-sign' must be LABEL=FILE" in err
    assert "ERROR: trajectory file does not exist" in err
