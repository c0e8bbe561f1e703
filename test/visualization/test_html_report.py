from html.parser import HTMLParser
from itertools import product
from pathlib import Path

import numpy as np

from aefabmap_ros.visualization.html_report import missed_revisits, report_page, worst_false_closures


def _brute_force_false(scores, gt, min_gap):
    return sorted(((scores[i, j], i, j) for i, j in product(range(len(scores)), repeat=2)
                   if j <= i - min_gap and not gt[i, j]), reverse=True)


def test_worst_false_closures_are_the_highest_scored_non_revisits():
    rng = np.random.default_rng(0)
    scores = rng.uniform(size=(30, 30))
    gt = rng.uniform(size=(30, 30)) < 0.2
    pairs = worst_false_closures(scores, gt, min_gap=5, count=4)
    expected = _brute_force_false(scores, gt, 5)[:4]
    assert [(p.query, p.place) for p in pairs] == [(i, j) for _, i, j in expected]


def test_missed_revisits_are_revisits_whose_best_true_place_is_under_the_threshold():
    scores = np.zeros((10, 10))
    gt = np.zeros((10, 10), bool)
    gt[6, 1] = gt[7, 2] = gt[8, 3] = gt[8, 2] = True
    scores[6, 1], scores[7, 2], scores[8, 3], scores[8, 2] = 0.99, 0.1, 0.2, 0.5
    missed = missed_revisits(scores, gt, min_gap=3, threshold=0.9, count=10)
    assert [(p.query, p.place) for p in missed] == [(7, 2), (8, 2)]  # 8's best true place is 2 (0.5)


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []
        self.images = 0

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in ("src", "href"):
                self.links.append(value)
        self.images += tag == "img"


def test_the_page_parses_and_links_only_inline_data_or_files_that_exist(tmp_path: Path):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    plot = tmp_path / "pr_curves.png"
    pyplot.figure()
    pyplot.plot([0, 1], [1, 0])
    pyplot.savefig(plot)
    pyplot.close("all")
    frames = {i: np.full((48, 64), 20 * i, np.uint8) for i in range(10)}
    scores = np.random.default_rng(1).uniform(size=(10, 10))
    gt = np.eye(10, k=-4, dtype=bool)
    sections = {"worst false": worst_false_closures(scores, gt, 3, 2),
                "missed": missed_revisits(scores, gt, 3, 2.0, 2)}
    page = report_page("run <1>", "# Title\n\n| a | b |\n|---|---|\n| 1 | <x> |\n", [plot], sections, frames.get)
    parser = _Links()
    parser.feed(page)
    parser.close()
    assert parser.images == 1 + 4  # the plot and four pairs
    assert all(link.startswith("data:") or (tmp_path / link).is_file() for link in parser.links)
    assert "&lt;x&gt;" in page and "<td>1</td>" in page  # the table, escaped
