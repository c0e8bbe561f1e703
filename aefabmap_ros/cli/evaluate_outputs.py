"""What aefabmap_eval writes: results.md, results.json, the plots, and report.html, the page a person reads
(visualization/html_report.py): every table and plot, the worst false closures and the missed revisits as
image pairs, all inline."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.evaluation.methods import METHODS
from aefabmap_ros.evaluation.plots import Curve, plot_pr_curves, plot_reliability, plot_score_matrix
from aefabmap_ros.evaluation.protocol import EvaluationConfig, MethodResult
from aefabmap_ros.evaluation.reports import online_markdown, result_to_dict, results_markdown, unique_slugs
from aefabmap_ros.io.atomic import atomic_write_text
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.visualization.html_report import FramePair, missed_revisits, report_page, worst_false_closures

PAIRS_PER_SECTION = 4


def prepare_output(out: Path) -> None:
    """Create the output folder and prove it writable now, not after the work."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(dir=out, prefix=".write-test-")
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        raise ConfigError(f"--out {out} is not a writable folder: {error.strerror or error}") from error


def write_results(out: Path, results: list[MethodResult], gt: np.ndarray, header: dict[str, Any],
                  extra_markdown: str = "", extra_json: dict[str, Any] | None = None,
                  extra_files: dict[str, str] | None = None) -> list[Path]:
    """results.md, results.json, pr_curves.png, scores_<method>.png and ``extra_files`` (name: text);
    returns the written paths."""
    min_gap = int(header["min_gap"])
    slugs = unique_slugs(results)
    written = []
    plot_pr_curves([Curve(r.title, r.metrics.pr_precision, r.metrics.pr_recall) for r in results],
                   out / "pr_curves.png", title=f"Precision-recall: {header['test']}")
    written.append(out / "pr_curves.png")
    for result, slug in zip(results, slugs, strict=True):
        path = out / f"scores_{slug}.png"
        plot_score_matrix(result.scores, gt, min_gap, path, f"{result.title} scores")
        written.append(path)
    diagrams = [(r.title, r.reliability) for r in results if r.reliability is not None]
    if diagrams:
        plot_reliability(diagrams, out / "reliability.png", title=f"Reliability: {header['test']}")
        written.append(out / "reliability.png")
    lines = [f"# Loop-closure evaluation: {header['test']}", ""]
    lines += [f"- {key}: {value}" for key, value in header.items() if key != "test"]
    lines += ["", results_markdown(results) + online_markdown(results)]
    if extra_markdown:
        lines += [extra_markdown]
    atomic_write_text(out / "results.md", "\n".join(lines))
    payload = {**header, "methods": [
        {**result_to_dict(r), "scores_plot": f"scores_{slug}.png"} for r, slug in zip(results, slugs, strict=True)
    ], **(extra_json or {})}
    atomic_write_text(out / "results.json", json.dumps(payload, indent=2, sort_keys=False) + "\n")
    written += [out / "results.md", out / "results.json"]
    for name, text in (extra_files or {}).items():
        atomic_write_text(out / name, text)
        written.append(out / name)
    return written


def pair_sections(results: list[MethodResult], gt: np.ndarray, min_gap: int,
                  evaluation: EvaluationConfig) -> dict[str, list[FramePair]]:
    """Per method: its highest-scored false pairs and the revisits it missed (under its threshold)."""
    sections = {}
    for result in results:
        bow = METHODS.get(result.name, ("", "fabmap"))[1] != "fabmap"
        threshold = evaluation.bow_threshold if bow else evaluation.threshold
        sections[f"{result.title}: worst false closures"] = worst_false_closures(result.scores, gt, min_gap,
                                                                                PAIRS_PER_SECTION)
        sections[f"{result.title}: missed revisits (threshold {threshold:g})"] = missed_revisits(
            result.scores, gt, min_gap, threshold, PAIRS_PER_SECTION)
    return sections


def frames_of(source: ImageSource | None, wanted: set[int]) -> Callable[[int], np.ndarray | None]:
    """The images of the ``wanted`` frames (read in one pass over the source), by frame index."""
    images: dict[int, np.ndarray] = {}
    if source is not None and wanted:
        for index, (_, image) in enumerate(source.frames()):
            if index in wanted:
                images[index] = image
            if index >= max(wanted):
                break
    return images.get


def write_report(out: Path, title: str, results: list[MethodResult], gt: np.ndarray, min_gap: int,
                 evaluation: EvaluationConfig, source: ImageSource | None) -> Path:
    """report.html beside results.md: its text, every PNG of ``out`` (the ATE plot too, when one was written
    there) and the image pairs of each method."""
    sections = pair_sections(results, gt, min_gap, evaluation)
    wanted = {frame for pairs in sections.values() for pair in pairs for frame in (pair.query, pair.place)}
    plots = sorted(out.glob("*.png"), key=lambda path: (path.name != "pr_curves.png", path.name))
    page = report_page(title, (out / "results.md").read_text(), plots, sections, frames_of(source, wanted))
    atomic_write_text(out / "report.html", page)
    return out / "report.html"
