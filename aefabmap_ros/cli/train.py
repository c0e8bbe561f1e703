"""aefabmap_train: recorded bags (or image folders) -> a model directory the nodes load.

    aefabmap_train --bag run1/ --bag run2/ --topic /camera/image_raw --out models/office
    aefabmap_train --images frames/ --vocabulary kmeans --size 1000 --out models/baseline
    aefabmap_train --images frames/ --ae-input matches --out models/learned   # words from video matches

Stages: features (cached per input in the work directory) -> vocabulary (autoencoder or k-means;
the autoencoder checkpoints, so an interrupted run resumes) -> bag-of-words of the training
images -> Chow-Liu tree -> new-place samples. The model appears at --out only when complete.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from aefabmap_ros.cli.common import RESUME_HINT, ArgumentParser, deferred, run_cli
from aefabmap_ros.features.kinds import FEATURE_TYPES
from aefabmap_ros.vocabulary.config import AE_INPUTS
from aefabmap_ros.vocabulary.kinds import VOCABULARY_KINDS


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_argument_group("training images (one or more bags, or folders)")
    source.add_argument("--bag", type=Path, action="append", default=[], help="rosbag2 bag (mcap or sqlite3)")
    source.add_argument("--topic", default="/image", help="image topic in the bags (default: /image)")
    source.add_argument("--images", type=Path, action="append", default=[], help="folder of image files")
    parser.add_argument("--out", type=Path, required=True, help="model directory to write")
    parser.add_argument("--config", type=Path, help="YAML with sections feature:, vocabulary:, training:")
    parser.add_argument("--vocabulary", choices=VOCABULARY_KINDS, help="vocabulary kind")
    parser.add_argument("--size", type=int, help="number of visual words")
    parser.add_argument("--ae-input", choices=AE_INPUTS,
                        help="autoencoder's input projection (vocabulary: ae_input; 'matches' learns it from "
                        "features matched between neighbouring frames)")
    parser.add_argument("--feature", choices=FEATURE_TYPES, help="feature type")
    parser.add_argument("--max-features", type=int, help="keypoints per image at most")
    parser.add_argument("--seed", type=int, help="random seed")
    parser.add_argument("--work-dir", type=Path, help="cache of resumable stages (default: beside --out)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing model directory")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, deferred("aefabmap_ros.cli.train_run:run_training"), RESUME_HINT)


if __name__ == "__main__":
    raise SystemExit(main())
