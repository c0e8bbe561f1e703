"""aefabmap_model: maintain model directories (the folders aefabmap_train writes).

    aefabmap_model convert models/office [models/other ...]

convert rewrites a model folder whose convolutional autoencoder is stored as torch weights (autoencoder.pt,
written by earlier versions) with the same weights as numpy arrays (network.npz), in place and atomically:
the nodes then load it without torch. It needs torch (the training install), keeps the vocabulary id, so
the maps made with the model stay valid, and leaves a folder that needs no conversion as it is.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from aefabmap_ros.cli.common import ArgumentParser, run_cli


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_model", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True, metavar="{convert}")
    convert = commands.add_parser("convert", help="store a model's torch weights as numpy arrays, in place")
    convert.add_argument("model", type=Path, nargs="+", help="model directory (from aefabmap_train)")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


def run(args: argparse.Namespace) -> int:
    from aefabmap_ros.model.convert import convert_model  # torch for an old folder: after parsing

    for directory in args.model:
        done = convert_model(directory)
        if done.converted:
            print(f"{directory}: converted (network weights now numpy arrays), vocabulary id {done.vocabulary_id} "
                  "unchanged")
        else:
            print(f"{directory}: nothing to convert (no torch weights), vocabulary id {done.vocabulary_id}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
