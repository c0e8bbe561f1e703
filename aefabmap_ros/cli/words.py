"""aefabmap_words: what vocabularies' words say about an image sequence, with no ground truth.

    aefabmap_words --model models/office --model models/baseline --bag run3/ --topic /camera/image_raw
    aefabmap_words --model models/learned --images frames/ --gaps 1,10,30 --far 100 --json words.json

For each model, on the same frames: how often a scene point keeps its word as the view changes (of the
features matched between frames GAP apart, ratio test and epipolar inliers, the share whose two
descriptors get one word), how many words an image holds, and how much of a frame's words the next frame
and the frame --far later share (a revisit must share more than that). Two vocabularies of one feature
type are compared on the same matched pairs. Meant for a sequence the vocabularies were not trained on.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from aefabmap_ros.cli.common import ArgumentParser, deferred, run_cli


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_words", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, action="append", required=True, help="model directory (repeatable)")
    source = parser.add_argument_group("the image sequence (a bag topic or a folder)")
    source.add_argument("--bag", type=Path, help="rosbag2 bag (mcap or sqlite3)")
    source.add_argument("--topic", default="/image", help="image topic in the bag (default: /image)")
    source.add_argument("--images", type=Path, help="folder of image files, in name order")
    parser.add_argument("--stride", type=int, default=1, help="use every STRIDE-th frame (default 1); gaps and "
                        "--far count the frames used")
    parser.add_argument("--gaps", default="1,10", help="frame gaps of the matched pairs, comma-separated "
                        "(default 1,10)")
    parser.add_argument("--far", type=int, default=50, help="frames apart of the 'shared far' figure (default 50)")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    parser.add_argument("--work-dir", type=Path, help="cache of the sequence's features (default: none)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, deferred("aefabmap_ros.cli.words_run:run"))


if __name__ == "__main__":
    raise SystemExit(main())
