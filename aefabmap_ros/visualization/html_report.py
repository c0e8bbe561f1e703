"""One self-contained HTML page per evaluation: the tables, every plot, and the worst false closures and the
missed revisits as image pairs, all inline (PNG and JPEG as data URIs), so the page opens from the file
system, offline, moved anywhere."""

from __future__ import annotations

import base64
import html
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aefabmap_ros.visualization.match_picture import decode_jpeg, encode_jpeg, make_thumbnail, side_by_side

PAIR_WIDTH_PX = 320  # each image of a pair
STYLE = """body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse;margin:1em 0}
td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}img{max-width:100%}
figure{display:inline-block;margin:0.5em;vertical-align:top}figcaption{font-size:90%}"""


@dataclass(frozen=True)
class FramePair:
    """A (query, place) pair worth a look, with why."""

    query: int
    place: int
    score: float
    caption: str


def candidate_mask(shape: tuple[int, int], min_gap: int) -> np.ndarray:
    """(N, N) bool: the pairs a detector may close, place j at least ``min_gap`` frames before query i."""
    rows, columns = np.indices(shape)
    return np.asarray(columns <= rows - min_gap)


def worst_false_closures(scores: np.ndarray, gt: np.ndarray, min_gap: int, count: int) -> list[FramePair]:
    """The ``count`` highest-scored pairs that are not revisits (what a threshold lets through first)."""
    masked = np.where(candidate_mask(scores.shape, min_gap) & ~gt.astype(bool) & np.isfinite(scores), scores,
                      -np.inf)
    order = np.argsort(masked, axis=None)[::-1][:count]
    pairs = [np.unravel_index(index, scores.shape) for index in order]
    return [FramePair(int(i), int(j), float(scores[i, j]), f"false: frame {i} -> {j}, score {scores[i, j]:.3g}")
            for i, j in pairs if np.isfinite(masked[i, j])]


def missed_revisits(scores: np.ndarray, gt: np.ndarray, min_gap: int, threshold: float,
                    count: int) -> list[FramePair]:
    """Revisiting queries whose best true place scored under ``threshold``, evenly spread over the missed ones,
    each with that best true place."""
    true_pairs = candidate_mask(scores.shape, min_gap) & gt.astype(bool)
    true_scores = np.where(true_pairs & np.isfinite(scores), scores, -np.inf)
    revisiting = np.flatnonzero(true_pairs.any(axis=1))
    best_place = true_scores.argmax(axis=1)
    best = true_scores[np.arange(len(scores)), best_place]
    missed = revisiting[best[revisiting] < threshold]
    chosen = missed[np.unique(np.linspace(0, len(missed) - 1, min(count, len(missed))).round().astype(int))] \
        if len(missed) else missed
    return [FramePair(int(i), int(best_place[i]), float(best[i]),
                      f"missed: frame {i}, its best true place {best_place[i]} scored {best[i]:.3g}")
            for i in chosen]


def pair_jpeg(query: np.ndarray, place: np.ndarray) -> bytes:
    """The two frames side by side, each shrunk to ``PAIR_WIDTH_PX`` wide."""
    shrunk = [decode_jpeg(make_thumbnail(image, PAIR_WIDTH_PX)) for image in (query, place)]
    return encode_jpeg(side_by_side(shrunk[0], shrunk[1])[0])


def data_uri(content: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(content).decode('ascii')}"


def markdown_to_html(text: str) -> str:
    """The reports' markdown (pipe tables, '#' titles, '- ' items, paragraphs) as escaped HTML."""
    blocks: list[str] = []
    table: list[list[str]] = []
    for line in [*text.splitlines(), ""]:
        stripped = line.strip()
        if stripped.startswith("|"):
            cells = [cell.strip() for cell in stripped.strip("|").split("|")]
            if not all(set(cell) <= set("-: ") for cell in cells):  # not the |---| rule
                table.append(cells)
            continue
        if table:
            head, *body = table
            blocks.append("<table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in head) + "</tr>"
                          + "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>"
                                    for row in body) + "</table>")
            table = []
        if stripped.startswith("#"):
            level = min(len(stripped) - len(stripped.lstrip("#")) + 1, 4)
            blocks.append(f"<h{level}>{html.escape(stripped.lstrip('#').strip())}</h{level}>")
        elif stripped.startswith("- "):
            blocks.append(f"<ul><li>{html.escape(stripped[2:])}</li></ul>")
        elif stripped:
            blocks.append(f"<p>{html.escape(stripped)}</p>")
    return "\n".join(blocks)


def figure(src: str, caption: str) -> str:
    return f'<figure><img src="{src}" alt="{html.escape(caption)}"><figcaption>{html.escape(caption)}</figcaption>' \
           "</figure>"


def report_page(title: str, markdown: str, plots: Sequence[Path], pair_sections: dict[str, list[FramePair]],
                frame: Callable[[int], np.ndarray | None]) -> str:
    """The page: ``markdown`` (the results.md text), every plot inline, then per section its pairs (``frame``
    gives a frame's image, None when the frames are not at hand: the section then says so)."""
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{STYLE}</style></head><body>", markdown_to_html(markdown), "<h2>Plots</h2>"]
    parts += [figure(data_uri(path.read_bytes(), "image/png"), path.name) for path in plots]
    for section, pairs in pair_sections.items():
        parts.append(f"<h2>{html.escape(section)}</h2>")
        if not pairs:
            parts.append("<p>None.</p>")
        for pair in pairs:
            query, place = frame(pair.query), frame(pair.place)
            if query is None or place is None:
                parts.append(f"<p>{html.escape(pair.caption)} (no images: give the test images, --bag or --images)"
                             "</p>")
                continue
            parts.append(figure(data_uri(pair_jpeg(query, place), "image/jpeg"), f"{pair.caption} (query left)"))
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
