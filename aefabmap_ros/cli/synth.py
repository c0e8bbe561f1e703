"""aefabmap_synth: render the synthetic town into sample sequences with ground truth.

    aefabmap_synth --out data/synth                      # train/ and test/, PNG folders
    aefabmap_synth --out data/synth --kind test --format both --frames 400

Each sequence DIR/<train|test>/ holds:
  images/000000.png ...   frames (format folder or both), mono8 PNG (bgr8 with --color)
  bag/                    rosbag2 bag, sensor_msgs/Image on --topic (format mcap or both)
  poses.txt               KITTI camera-to-world 3x4 poses, one line per frame
  times.txt               seconds since the first frame, one line per frame
  calib.txt               KITTI-style projection matrix "P0: ..." of the pinhole camera
  loop_gt.npz             key "gt": (N, N) uint8 ground-truth loop matrix (gt[i, j] = 1: i revisits j)
  synth_config.json       every generator parameter, so the sequence can be regenerated

The training sequence is rendered in another town (seed + 1000003) than the test sequence, so a
vocabulary trained on one never saw the other's textures.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path

import cv2
import numpy as np

from aefabmap_ros.cli.common import report_errors
from aefabmap_ros.core.atomic import atomic_write_bytes
from aefabmap_ros.core.errors import AefabmapError, ConfigError
from aefabmap_ros.core.ground_truth import write_kitti_poses
from aefabmap_ros.core.synth import SynthConfig, SyntheticSequence, generate_sequence, train_test_configs


class _UsageError(Exception):
    """Bad command-line arguments (reported as ERROR: ..., exit 1)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise _UsageError(message)


def build_parser() -> argparse.ArgumentParser:
    defaults = SynthConfig()
    parser = _Parser(prog="aefabmap_synth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="output directory (created if missing)")
    parser.add_argument("--kind", choices=("train", "test", "both"), default="both",
                        help="which sequence(s) to write (default: both)")
    parser.add_argument("--frames", type=int, default=defaults.num_frames,
                        help=f"frames per sequence (default: {defaults.num_frames})")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="seed of the test town (default: 0)")
    parser.add_argument("--format", choices=("folder", "mcap", "both"), default="folder",
                        help="PNG folder, rosbag2 mcap bag, or both (default: folder)")
    parser.add_argument("--width", type=int, default=defaults.width, help="image width (default: 640)")
    parser.add_argument("--height", type=int, default=defaults.height, help="image height (default: 480)")
    parser.add_argument("--laps", type=int, default=defaults.laps, help="laps of the route (default: 2)")
    parser.add_argument("--color", action="store_true", help="bgr8 images instead of mono8")
    parser.add_argument("--topic", default="/image", help="image topic of the bag (default: /image)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing sequences in --out")
    return parser


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise AefabmapError(f"cannot encode {path.name} as PNG")
    path.write_bytes(encoded.tobytes())  # inside a fresh temporary directory: no reader can see it half-written


def write_sequence(sequence: SyntheticSequence, config: SynthConfig, directory: Path, fmt: str, topic: str) -> None:
    """Write one sequence's files into an existing, empty directory."""
    if fmt in ("folder", "both"):
        images = directory / "images"
        images.mkdir()
        for index, image in enumerate(sequence.images):
            _write_png(images / f"{index:06d}.png", image)
    if fmt in ("mcap", "both"):
        from aefabmap_ros.io.bags import write_image_bag

        frames = zip(sequence.stamps_ns.tolist(), sequence.images, strict=True)
        write_image_bag(directory / "bag", topic, frames, storage="mcap")
    write_kitti_poses(directory / "poses.txt", sequence.poses)
    seconds = (sequence.stamps_ns - sequence.stamps_ns[0]) / 1e9
    atomic_write_bytes(directory / "times.txt", "".join(f"{t:.6e}\n" for t in seconds).encode())
    projection = np.hstack([sequence.camera_matrix, np.zeros((3, 1))]).reshape(12)
    atomic_write_bytes(directory / "calib.txt", ("P0: " + " ".join(f"{v:.12e}" for v in projection) + "\n").encode())
    with open(directory / "loop_gt.npz", "wb") as file:
        np.savez_compressed(file, gt=sequence.gt)
    atomic_write_bytes(directory / "synth_config.json", (json.dumps(asdict(config), indent=2) + "\n").encode())


def _publish(temporary: Path, target: Path, overwrite: bool) -> None:
    """Move a finished sequence into place, replacing an old one only when asked."""
    if target.exists():
        if not overwrite:
            raise ConfigError(f"{target} already exists (use --overwrite to replace it)")
        shutil.rmtree(target)
    os.replace(temporary, target)


def _make_sequence(name: str, config: SynthConfig, args: argparse.Namespace) -> None:
    target = args.out / name
    if target.exists() and not args.overwrite:
        raise ConfigError(f"{target} already exists (use --overwrite to replace it)")
    started = time.perf_counter()
    sequence = generate_sequence(config)
    elapsed = time.perf_counter() - started
    temporary = Path(tempfile.mkdtemp(dir=args.out, prefix=f".{name}."))
    try:
        write_sequence(sequence, config, temporary, args.format, args.topic)
        _publish(temporary, target, args.overwrite)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise
    print(f"{name}: {config.num_frames} frames (seed {config.seed}) in {elapsed:.1f} s "
          f"({config.num_frames / elapsed:.1f} frames/s), {int(sequence.gt.sum())} loop pairs, "
          f"{int(sequence.gt.any(axis=1).sum())} query frames with a loop -> {target}")


def run(args: argparse.Namespace) -> None:
    base = replace(SynthConfig(), seed=args.seed, num_frames=args.frames, width=args.width, height=args.height,
                   laps=args.laps, color=args.color)
    train, test = train_test_configs(base)
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create output directory {args.out}: {error.strerror or error}") from error
    if not os.access(args.out, os.W_OK):
        raise ConfigError(f"output directory {args.out} is not writable")
    kinds = ("train", "test") if args.kind == "both" else (args.kind,)
    for name in kinds:
        _make_sequence(name, train if name == "train" else test, args)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as error:
        parser.print_usage(sys.stderr)
        print(f"ERROR: {error}", file=sys.stderr)
        return 1
    return report_errors(lambda: _run_reporting_write_errors(args))


def _run_reporting_write_errors(args: argparse.Namespace) -> int:
    try:
        run(args)
    except OSError as error:
        raise ConfigError(f"cannot write to {args.out}: {error}") from error
    return 0


if __name__ == "__main__":
    sys.exit(main())
