"""The evaluation's reports: markdown tables and JSON-ready dicts of the methods' and the online chain's figures."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from aefabmap_ros.evaluation.metrics import EventScores
from aefabmap_ros.evaluation.protocol import MethodResult


def events_to_dict(events: EventScores) -> dict[str, Any]:
    """One closure list's figures per closure, revisit event and revisiting frame (JSON-ready)."""
    return {
        "closures": events.num_closures, "false_closures": events.num_false_closures,
        "revisit_events": events.num_events, "events_closed": events.num_events_closed,
        "fraction_of_events_closed": jsonable_float(events.fraction_closed),
        "revisiting_frames": events.num_revisiting_frames,
        "revisiting_frames_closed": events.num_revisiting_frames_closed,
        "recall_revisiting_frames": jsonable_float(events.frame_recall),
    }


def fmt(value: float) -> str:
    return "n/a" if np.isnan(value) else f"{value:.3f}"


def recall_cell(events: EventScores) -> str:
    return f"{fmt(events.frame_recall)} ({events.num_revisiting_frames_closed}/{events.num_revisiting_frames})"


def missed_ranked_cell(missed_ranked: int, events: EventScores) -> str:
    """"ranked / missed": the missed revisiting frames whose posterior ranked a true place, of all missed."""
    return f"{missed_ranked} / {events.num_revisiting_frames - events.num_revisiting_frames_closed}"


def results_markdown(results: Sequence[MethodResult]) -> str:
    """A markdown table: one row per method."""
    lines = [
        "| method | vocabulary | AP | max F1 | recall @ 100% precision | accuracy @ t | recall @ t | t "
        "| predictions @ t (false) | scoring s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for result in results:
        m = result.metrics
        lines.append(
            f"| {result.title} | {result.vocabulary_kind} {result.vocabulary_size} | {fmt(m.average_precision)} "
            f"| {fmt(m.max_f1)} | {fmt(m.recall_at_100_precision)} | {fmt(m.precision_at_threshold)} "
            f"| {fmt(m.recall_at_threshold)} | {m.threshold:g} | {m.num_predictions_at_threshold} "
            f"({result.false_positives_at_threshold}) | {result.seconds:.1f} |"
        )
    return "\n".join(lines) + "\n"


# Revisiting frames a topic missed although their posterior ranked a true place
# (metrics.missed_with_a_true_place_ranked).
MISSED_RANKED_KEY = "missed_revisiting_frames_with_a_true_place_ranked"


def online_markdown(results: Sequence[MethodResult]) -> str:
    """The nodes' decision chain per FAB-MAP method: what a backend receives, per closure and revisit event."""
    if all(r.online is None for r in results):
        return ""
    lines = ["", "Online chain (the nodes' defaults on this sequence's stamps; candidates: fabmap_node, "
             "published: /loop_closures):", "",
             "| method | places | candidates (false) | published (false; by loop tracking) | events closed "
             "| recall (revisiting frames) | missed frames with a true place ranked |",
             "|---|---|---|---|---|---|---|"]
    for result in results:
        online = result.online
        if online is None:
            continue
        c, p = online.candidates, online.published
        lines.append(
            f"| {result.title} | {online.num_places} | {c.num_closures} ({c.num_false_closures}) "
            f"| {p.num_closures} ({p.num_false_closures}; {online.num_tracked})"
            f"{'' if online.verified else ' unverified'} "
            f"| {p.num_events_closed}/{p.num_events} | {recall_cell(p)} "
            f"| {missed_ranked_cell(online.published_missed_ranked, p)} |")
    return "\n".join(lines) + "\n"


def jsonable_float(value: float) -> float | None:
    return None if np.isnan(value) else float(value)


def result_to_dict(result: MethodResult) -> dict[str, Any]:
    m = result.metrics
    return {
        "method": result.name,
        "label": result.label,
        "geometric_verification": result.verified,
        "vocabulary_kind": result.vocabulary_kind,
        "vocabulary_size": result.vocabulary_size,
        "model_id": result.vocabulary_id,
        "model_path": result.model_path,
        "average_precision": m.average_precision,
        "max_f1": m.max_f1,
        "recall_at_100_precision": m.recall_at_100_precision,
        "accuracy_at_threshold": jsonable_float(m.precision_at_threshold),
        "recall_at_threshold": m.recall_at_threshold,
        "threshold": m.threshold,
        "num_queries": m.num_queries,
        "num_positive_queries": m.num_positive_queries,
        "num_predictions_at_threshold": m.num_predictions_at_threshold,
        "false_positives_at_threshold": result.false_positives_at_threshold,
        "seconds": result.seconds,
        "quantize_seconds": result.quantize_seconds,
        "pr_curve": {
            "precision": m.pr_precision.tolist(),
            "recall": m.pr_recall.tolist(),
            "thresholds": m.pr_thresholds.tolist(),
        },
        "reliability": None if result.reliability is None else result.reliability.as_dict(),
        "online_chain": None if result.online is None else {
            "verified": result.online.verified, "places": result.online.num_places,
            "tracked": result.online.num_tracked,
            "candidates": {**events_to_dict(result.online.candidates),
                           MISSED_RANKED_KEY: result.online.candidates_missed_ranked},
            "published": {**events_to_dict(result.online.published),
                          MISSED_RANKED_KEY: result.online.published_missed_ranked},
        },
    }


def method_slug(result: MethodResult) -> str:
    """File-name part of a method: lower case, [a-z0-9-_] only."""
    text = "".join(c if c.isalnum() or c in "-_" else " " for c in result.title.lower())
    return "_".join(text.split())


def unique_slugs(results: Sequence[MethodResult]) -> list[str]:
    slugs: list[str] = []
    for result in results:
        slug = base = method_slug(result)
        suffix = 2
        while slug in slugs:
            slug, suffix = f"{base}_{suffix}", suffix + 1
        slugs.append(slug)
    return slugs
