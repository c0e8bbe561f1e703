"""aefabmap_bag: a folder of image files -> a rosbag2 bag the nodes can be replayed from.

    aefabmap_bag --images rtabmap_samples/images --rate 1 --out rtab_bag        # stamped 0, 1, 2 ... s
    aefabmap_bag --images rgb/ --out tum_bag                                     # TUM names: <seconds>.png
    aefabmap_bag --images frames/ --times times.txt --out kitti_bag             # one stamp (s) per line
    aefabmap_bag split BAG --at 0.5 --restart-odometry --out DIR   # two sessions (aefabmap_bag split --help)
    aefabmap_bag merge REC_A REC_B --out REC                       # recordings of several sessions in one

Images are read in natural-sort order and written as ``sensor_msgs/Image`` (mono8, or bgr8 with
--color) on --topic. Stamps matter: the nodes' time windows (recent places excluded for a few
seconds, the consistency island) are in seconds, so give the rate the images were taken at, a
times file, or TUM-style file names, not a made-up rate. The bag appears at --out only when complete.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.errors import ConfigError, ImageError
from aefabmap_ros.io.bags import STORAGES, write_image_bag
from aefabmap_ros.io.rgbd import read_times, stamps_from_names
from aefabmap_ros.io.sources import folder_images, read_gray


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bag", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=Path, required=True, help="folder of image files")
    stamps = parser.add_mutually_exclusive_group()
    stamps.add_argument("--rate", type=float, help="frame rate in Hz: frame i is stamped --start + i / rate")
    stamps.add_argument("--times", type=Path, help="text file, one stamp in seconds per image (KITTI times.txt)")
    parser.add_argument("--start", type=float, default=0.0, help="with --rate: stamp of the first image, seconds")
    parser.add_argument("--out", type=Path, required=True, help="bag directory to write")
    parser.add_argument("--topic", default="/image", help="image topic (default: /image)")
    parser.add_argument("--storage", choices=sorted(STORAGES), default="mcap", help="bag storage (default: mcap)")
    parser.add_argument("--color", action="store_true", help="bgr8 images instead of mono8")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    return parser


def image_stamps_ns(args: argparse.Namespace, files: list[Path]) -> np.ndarray:
    """(N,) stamps: from --rate, from --times, else from TUM-style file names."""
    if args.rate is not None:
        if not (np.isfinite(args.rate) and args.rate > 0):
            raise ConfigError(f"--rate must be a positive frame rate in Hz, got {args.rate}")
        result: np.ndarray = np.rint(args.start * 1e9 + np.arange(len(files)) * (1e9 / args.rate)).astype(np.int64)
        return result
    stamps = read_times(args.times, len(files)) if args.times is not None else stamps_from_names(files)
    if np.any(np.diff(stamps) <= 0):
        raise ConfigError("image stamps must increase strictly in file order")
    return stamps


def _frames(files: list[Path], stamps_ns: np.ndarray, color: bool) -> Iterator[tuple[int, np.ndarray]]:
    for path, stamp in zip(files, stamps_ns.tolist(), strict=True):
        if not color:
            yield stamp, read_gray(path)
            continue
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise ImageError(f"cannot read image {path}")
        yield stamp, image


def run(args: argparse.Namespace) -> int:
    files = folder_images(args.images)
    stamps = image_stamps_ns(args, files)
    count = write_image_bag(args.out, args.topic, _frames(files, stamps, args.color), storage=args.storage,
                            overwrite=args.overwrite)
    seconds = (stamps[-1] - stamps[0]) / 1e9
    print(f"{count} images on {args.topic}, {seconds:.2f} s of stamps -> {args.out}")
    return 0


SUBCOMMANDS = ("split", "merge")  # cli/bag_split.py


def main(argv: list[str] | None = None) -> int:
    arguments = sys.argv[1:] if argv is None else list(argv)
    if arguments and arguments[0] in SUBCOMMANDS:
        from aefabmap_ros.cli import bag_split

        return bag_split.main(arguments)
    return run_cli(build_parser(), arguments, run)


if __name__ == "__main__":
    sys.exit(main())
