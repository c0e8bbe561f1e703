"""Calibration of a detector's confidence: reliability diagram and expected calibration error.

A posterior is calibrated when, of all queries whose best place got probability p, a fraction p
really revisit that place. FAB-MAP's posterior is not (its word-independence assumptions make the
likelihood ratios overconfident; ``FabMapConfig.likelihood_temperature`` is the remedy, judged by
what this module computes). The evaluation bins each frame's best hypothesis as fabmap_node publishes it (the online
chain: places, time window and all) and sets it against whether the ground truth confirms it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_ros.errors import DataError

DEFAULT_BIN_EDGES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.99, 1.0)


@dataclass(frozen=True)
class Reliability:
    """Per bin of confidence: how many queries, their mean confidence and the fraction that were right."""

    bin_edges: np.ndarray  # (B + 1,) increasing; the last bin includes its upper edge
    counts: np.ndarray  # (B,) int64
    mean_confidence: np.ndarray  # (B,) float64, nan in empty bins
    accuracy: np.ndarray  # (B,) float64, nan in empty bins
    expected_calibration_error: float  # sum over bins of count / total * |mean confidence - accuracy|

    def as_dict(self) -> dict[str, object]:
        def listed(values: np.ndarray) -> list[float | None]:
            return [None if np.isnan(v) else float(v) for v in values]

        return {"bin_edges": self.bin_edges.tolist(), "counts": self.counts.tolist(),
                "mean_confidence": listed(self.mean_confidence), "accuracy": listed(self.accuracy),
                "expected_calibration_error": self.expected_calibration_error}


def reliability(confidence: np.ndarray, correct: np.ndarray,
                bin_edges: tuple[float, ...] = DEFAULT_BIN_EDGES) -> Reliability:
    """Reliability of (N,) confidences in [0, 1] against (N,) outcomes (True = the decision was right)."""
    values = np.asarray(confidence, dtype=np.float64)
    outcomes = np.asarray(correct, dtype=bool)
    edges = np.asarray(bin_edges, dtype=np.float64)
    if values.ndim != 1 or outcomes.shape != values.shape:
        raise DataError(f"confidence {values.shape} and correct {outcomes.shape} must be two (N,) arrays")
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise DataError(f"bin edges must increase strictly, got {bin_edges}")
    if values.size and (not np.isfinite(values).all() or values.min() < edges[0] or values.max() > edges[-1]):
        raise DataError(f"confidences must lie in [{edges[0]}, {edges[-1]}]")
    bins = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)
    counts = np.bincount(bins, minlength=edges.size - 1).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(bins, weights=values, minlength=edges.size - 1) / counts
        accuracy = np.bincount(bins, weights=outcomes.astype(np.float64), minlength=edges.size - 1) / counts
    filled = counts > 0
    ece = float(np.sum(counts[filled] * np.abs(mean[filled] - accuracy[filled])) / max(values.size, 1))
    return Reliability(edges, counts, mean, accuracy, ece)
