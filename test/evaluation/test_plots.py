"""Figures are real PNGs of the expected size (written atomically: no temporary file left)."""

import numpy as np

from aefabmap_ros.evaluation.calibration import reliability
from aefabmap_ros.evaluation.plots import plot_reliability


def test_reliability_plot_is_a_png(tmp_path):
    diagram = reliability(np.array([0.1, 0.5, 0.95, 0.99]), np.array([False, True, True, True]))
    path = tmp_path / "reliability.png"
    plot_reliability([("AE-FABMAP", diagram), ("FABMAP2", diagram)], path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["reliability.png"]
