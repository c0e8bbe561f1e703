"""What aefabmap_words does once its arguments are parsed (``words.py`` holds the options)."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.cli.train_run import source_features
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.evaluation.word_statistics import WordStatistics, word_statistics
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.io.atomic import atomic_write_text
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.model.directory import Model, load_model
from aefabmap_ros.model.training import config_digest, pairs_at_gap


def parse_gaps(text: str) -> list[int]:
    try:
        gaps = sorted({int(part) for part in text.split(",") if part.strip()})
    except ValueError:
        raise ConfigError(f"--gaps {text!r} must be comma-separated whole numbers of frames") from None
    if not gaps or gaps[0] < 1:
        raise ConfigError(f"--gaps {text!r} must name at least one gap, each >= 1")
    return gaps


def image_source(args: argparse.Namespace) -> ImageSource:
    if (args.bag is None) == (args.images is None):
        raise ConfigError("give the image sequence as --bag (with --topic) or --images, one of the two")
    source = ImageSource(bag=args.bag, topic=args.topic) if args.bag is not None else ImageSource(folder=args.images)
    source.check()
    return source


def statistics_of(models: list[tuple[Path, Model]], gaps: list[int], args: argparse.Namespace,
                  source: ImageSource) -> list[tuple[Path, Model, WordStatistics]]:
    """Each model's statistics; features and matched pairs computed once per feature configuration."""
    by_features: dict[str, tuple[list[Features], dict[int, np.ndarray]]] = {}
    results = []
    for path, model in models:
        key = config_digest(model.feature_config)
        if key not in by_features:
            features = source_features(source, model.feature_config, args.work_dir, args.quiet, args.stride)
            by_features[key] = (features, {gap: pairs_at_gap(features, gap) for gap in gaps})
        features, pairs = by_features[key]
        results.append((path, model, word_statistics(model.quantizer, features, pairs, args.far)))
    return results


def _percent(value: float) -> str:
    return "n/a" if math.isnan(value) else f"{value * 100:.1f} %"


def print_table(results: list[tuple[Path, Model, WordStatistics]]) -> None:
    first = results[0][2]
    rows = [["model", "kind", "words (used)", "perplexity", "words/image"]
            + [f"one word, gap {a.gap}" for a in first.agreement] + ["shared next", f"shared at {first.far_gap}"]]
    for path, model, stats in results:
        rows.append([str(path), model.vocabulary_config.kind, f"{stats.size} ({stats.used})",
                     f"{stats.perplexity:.0f}", f"{stats.words_per_image:.0f}"]
                    + [f"{_percent(a.one_word)} of {a.pairs}" for a in stats.agreement]
                    + [_percent(stats.shared_next), _percent(stats.shared_far)])
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip())


def _no_nan(value: Any) -> Any:
    """JSON has no NaN: a figure with nothing to measure is null."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {key: _no_nan(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_no_nan(item) for item in value]
    return value


def write_json(path: Path, results: list[tuple[Path, Model, WordStatistics]], source: ImageSource,
               stride: int) -> None:
    report = {"sequence": source.name, "stride": stride,
              "models": [{"model": str(p), "kind": m.vocabulary_config.kind, **asdict(s)} for p, m, s in results]}
    atomic_write_text(path, json.dumps(_no_nan(report), indent=2) + "\n")


def run(args: argparse.Namespace) -> int:
    if args.stride < 1:
        raise ConfigError(f"--stride must be >= 1, got {args.stride}")
    if args.far < 1:
        raise ConfigError(f"--far must be >= 1, got {args.far}")
    gaps = parse_gaps(args.gaps)  # a bad --gaps fails before any work
    if args.json is not None and not args.json.resolve().parent.is_dir():
        raise ConfigError(f"--json {args.json}: folder {args.json.resolve().parent} does not exist")
    source = image_source(args)
    models = [(path, load_model(path)) for path in args.model]
    results = statistics_of(models, gaps, args, source)
    print_table(results)
    if args.json is not None:
        write_json(args.json, results, source, args.stride)
        print(f"figures written to {args.json}")
    return 0
