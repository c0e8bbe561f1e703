"""Evaluation figures (matplotlib, Agg backend: no display needed), written atomically as PNG.

- :func:`plot_pr_curves`: the precision-recall curves of all methods on one plot.
- :func:`plot_score_matrix`: a method's score matrix beside the ground-truth loop matrix (the
  paper's confusion-matrix figure). Entries that are not loop candidates of the protocol
  (``j > i - min_gap``: the recent past, the query itself and the future) are drawn grey.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # before pyplot: headless, deterministic output

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.calibration import Reliability
from aefabmap_ros.io.atomic import atomic_open


@dataclass(frozen=True)
class Curve:
    """One method's precision-recall curve (points by increasing recall)."""

    label: str
    precision: np.ndarray  # (K,)
    recall: np.ndarray  # (K,)


def _save(figure: Figure, path: Path) -> None:
    try:
        with atomic_open(path) as file:
            figure.savefig(file, dpi=110, format="png")
    finally:
        plt.close(figure)


def plot_pr_curves(curves: Sequence[Curve], path: Path, title: str = "Loop-closure precision-recall") -> None:
    """All curves on one plot (step-wise, as average precision integrates them)."""
    figure, axes = plt.subplots(figsize=(6.0, 4.8))
    for curve in curves:
        precision = np.asarray(curve.precision, dtype=np.float64)
        recall = np.asarray(curve.recall, dtype=np.float64)
        if precision.shape != recall.shape:
            raise DataError(f"curve {curve.label!r}: precision {precision.shape} and recall {recall.shape} differ")
        # Start at recall 0 with the first point's precision, so a one-point curve is still visible.
        xs = np.r_[0.0, recall] if recall.size else np.zeros(1)
        ys = np.r_[precision[:1], precision] if precision.size else np.zeros(1)
        axes.step(xs, ys, where="post", label=curve.label, linewidth=1.6)
    axes.set_xlim(0.0, 1.02)
    axes.set_ylim(0.0, 1.02)
    axes.set_xlabel("recall")
    axes.set_ylabel("precision")
    axes.set_title(title)
    axes.grid(True, alpha=0.3)
    if curves:
        axes.legend(loc="lower left")
    figure.tight_layout()
    _save(figure, path)


def plot_score_matrix(scores: np.ndarray, gt: np.ndarray, min_gap: int, path: Path, title: str) -> None:
    """Score matrix (candidates only, the rest grey) beside the ground truth, same frame axes."""
    matrix = np.asarray(scores, dtype=np.float64)
    truth = np.asarray(gt)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or truth.shape != matrix.shape:
        raise DataError(f"scores {matrix.shape} and ground truth {truth.shape} must be the same square shape")
    index = np.arange(matrix.shape[0])
    candidates = index[None, :] <= index[:, None] - min_gap
    shown = np.where(candidates & np.isfinite(matrix), matrix, np.nan)
    colormap = matplotlib.colormaps["viridis"].with_extremes(bad="0.85")
    figure, (left, right) = plt.subplots(1, 2, figsize=(10.0, 4.8))
    finite = shown[np.isfinite(shown)]
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    image = left.imshow(shown, cmap=colormap, vmin=low, vmax=high if high > low else low + 1.0,
                        interpolation="nearest")
    figure.colorbar(image, ax=left, fraction=0.046, pad=0.04)
    left.set_title(title)
    right.imshow(truth.astype(np.float64), cmap="gray_r", vmin=0.0, vmax=1.0, interpolation="nearest")
    right.set_title("ground truth")
    for axes in (left, right):
        axes.set_xlabel("earlier frame j")
        axes.set_ylabel("query frame i")
    figure.tight_layout()
    _save(figure, path)


def plot_reliability(diagrams: Sequence[tuple[str, Reliability]], path: Path,
                     title: str = "Reliability of the best candidate's posterior") -> None:
    """Reliability diagrams: observed fraction of right best candidates against mean posterior per bin."""
    figure, axes = plt.subplots(figsize=(6.0, 4.8))
    axes.plot([0.0, 1.0], [0.0, 1.0], color="grey", linestyle="--", linewidth=1.0, label="calibrated")
    for label, diagram in diagrams:
        filled = diagram.counts > 0
        axes.plot(diagram.mean_confidence[filled], diagram.accuracy[filled], marker="o", linewidth=1.4,
                  label=f"{label} (ECE {diagram.expected_calibration_error:.3f})")
    axes.set_xlim(0.0, 1.0)
    axes.set_ylim(0.0, 1.02)
    axes.set_xlabel("posterior of the best candidate (bin mean)")
    axes.set_ylabel("fraction that revisit it (ground truth)")
    axes.set_title(title)
    axes.grid(True, alpha=0.3)
    axes.legend(loc="upper left", fontsize="small")
    figure.tight_layout()
    _save(figure, path)


def plot_trajectories(reference: np.ndarray, estimates: Sequence[tuple[str, np.ndarray]], path: Path,
                      title: str = "Trajectories (aligned to the reference)") -> None:
    """Top view (x, y) of (N, 3) positions: the reference and each aligned estimate."""
    figure, axes = plt.subplots(figsize=(6.5, 6.0))
    axes.plot(reference[:, 0], reference[:, 1], "k--", linewidth=1.5, label="ground truth")
    for label, positions in estimates:
        axes.plot(positions[:, 0], positions[:, 1], linewidth=1.2, label=label)
    axes.set_xlabel("x (m)")
    axes.set_ylabel("y (m)")
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_title(title)
    axes.legend(loc="best")
    figure.tight_layout()
    _save(figure, path)
