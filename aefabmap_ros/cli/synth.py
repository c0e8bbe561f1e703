"""aefabmap_synth: render the synthetic town into sample sequences with ground truth.

    aefabmap_synth --out data/synth                      # train/ and test/, PNG folders
    aefabmap_synth --out data/synth --kind test --format both --frames 400
    aefabmap_synth --out data/dense --preset dense-video  # 3600 frames of 30 Hz video, 320x240

Presets:
  figure-eight  (default) the figure-eight route driven --laps times, 400 frames at 10 Hz, 640x480
  dense-video   one 2-minute drive filmed at 30 Hz (3600 frames): slow and fast stretches, a 4 s stop,
                the middle street's lower half driven again in the same direction, its upper half
                driven again in the opposite direction (for a forward camera mostly no revisit by
                covisibility), and the west edge street never revisited. 320x240 because of
                memory more than time: the sequence's images and depth are held in memory while it
                is written, four times as much at 640x480 (render times and sizes:
                docs/measurements.md). --frames, --width and --height override a preset's values;
                --laps does not apply to it.

Each sequence DIR/<train|test>/ holds:
  images/000000.png ...   frames (format folder or both), mono8 PNG (bgr8 with --color)
  depth/000000.png ...    depth (format folder or both): 16-bit PNG, millimetres along the optical
                          axis (as ROS 16UC1), 0 = no depth (sky, or beyond 65.535 m)
  bag/                    rosbag2 bag (format mcap or both): sensor_msgs/Image on --topic, the 16UC1
                          depth on <namespace>/depth and sensor_msgs/CameraInfo on
                          <namespace>/camera_info (namespace of --topic), and the drifting odometry
                          of odometry.tum as nav_msgs/Odometry on /odom (frame odom, child camera),
                          all with the same stamps
  poses.txt               KITTI camera-to-world 3x4 poses, one line per frame
  groundtruth.tum         the same poses in TUM format (image stamps in seconds), for aefabmap_ate
  odometry.tum            a drifting odometry of the camera (TUM, same stamps), seeded by --seed:
                          each step's translation 1.5 % too long (+ 0.5 % noise per step) and turned
                          by 0.1 degree of yaw per metre (+ 0.02 degree noise per step) about the
                          vertical (evaluation/trajectory_error.py OdometryDrift)
  times.txt               seconds since the first frame, one line per frame
  calib.txt               KITTI-style projection matrix "P0: ..." of the pinhole camera
  camera_info.yaml        the camera in ROS camera_calibration_parsers' format (K, D = 0, R = I, P)
  loop_gt.npz             key "gt": (N, N) uint8 covisibility ground truth (gt[i, j] = 1: i revisits
                          j, DESIGN 9.2); `aefabmap_gt --depth depth --poses poses.txt --camera-info
                          camera_info.yaml --times times.txt` on the folder reproduces it; key
                          "stamps_ns": (N,) int64, each row's stamp (the bag's image stamps)
  loop_gt_poses.npz       key "gt": the pose-rule loop matrix (centres within 2.5 m, axes within 30 deg),
                          and the same "stamps_ns"
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

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.datasets.synth.config import SynthConfig, dense_video_config, train_test_configs
from aefabmap_ros.datasets.synth.town import SyntheticSequence, depth_to_16uc1, generate_sequence
from aefabmap_ros.errors import AefabmapError, ConfigError
from aefabmap_ros.evaluation.ground_truth import write_kitti_poses
from aefabmap_ros.evaluation.trajectory_error import OdometryDrift, drifting_odometry, tum_text
from aefabmap_ros.io.atomic import atomic_write_bytes, atomic_write_text

PRESETS = ("figure-eight", "dense-video")


def preset_config(name: str, seed: int) -> SynthConfig:
    """The base configuration of a preset (before --frames, --width, ... are applied)."""
    if name == "dense-video":
        return dense_video_config(seed=seed)
    return replace(SynthConfig(), seed=seed)


def build_parser() -> argparse.ArgumentParser:
    defaults = SynthConfig()
    parser = ArgumentParser(prog="aefabmap_synth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="output directory (created if missing)")
    parser.add_argument("--kind", choices=("train", "test", "both"), default="both",
                        help="which sequence(s) to write (default: both)")
    parser.add_argument("--preset", choices=PRESETS, default="figure-eight",
                        help="route, length, frame rate and size (default: figure-eight; see above)")
    parser.add_argument("--frames", type=int, default=None,
                        help=f"frames per sequence (default: the preset's; figure-eight {defaults.num_frames})")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="seed of the test town (default: 0)")
    parser.add_argument("--format", choices=("folder", "mcap", "both"), default="folder",
                        help="PNG folder, rosbag2 mcap bag, or both (default: folder)")
    parser.add_argument("--width", type=int, default=None, help="image width (default: the preset's)")
    parser.add_argument("--height", type=int, default=None, help="image height (default: the preset's)")
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


def camera_info_yaml(camera_matrix: np.ndarray, width: int, height: int, name: str = "aefabmap_synth") -> str:
    """A pinhole camera without distortion in ROS camera_calibration_parsers' YAML format."""
    def matrix(rows: int, cols: int, values: np.ndarray) -> str:
        data = ", ".join(repr(float(value)) for value in np.asarray(values).reshape(-1))
        return f"\n  rows: {rows}\n  cols: {cols}\n  data: [{data}]"

    projection = np.hstack([camera_matrix, np.zeros((3, 1))])
    return (f"image_width: {width}\nimage_height: {height}\ncamera_name: {name}\n"
            f"camera_matrix:{matrix(3, 3, camera_matrix)}\ndistortion_model: plumb_bob\n"
            f"distortion_coefficients:{matrix(1, 5, np.zeros(5))}\n"
            f"rectification_matrix:{matrix(3, 3, np.eye(3))}\nprojection_matrix:{matrix(3, 4, projection)}\n")


def _save_npz(path: Path, gt: np.ndarray, stamps_ns: np.ndarray) -> None:
    with open(path, "wb") as file:  # inside a fresh temporary directory: no reader can see it half-written
        np.savez_compressed(file, gt=gt, stamps_ns=np.asarray(stamps_ns, dtype=np.int64))


def write_sequence(sequence: SyntheticSequence, config: SynthConfig, directory: Path, fmt: str, topic: str) -> None:
    """Write one sequence's files into an existing, empty directory."""
    if fmt in ("folder", "both"):
        images = directory / "images"
        images.mkdir()
        (directory / "depth").mkdir()
        for index, image in enumerate(sequence.images):
            _write_png(images / f"{index:06d}.png", image)
            _write_png(directory / "depth" / f"{index:06d}.png", depth_to_16uc1(sequence.depths[index]))
    # The camera's y axis points down: the world's up is -y in the camera frame.
    odometry = drifting_odometry(sequence.poses, np.array([0.0, -1.0, 0.0]), OdometryDrift(seed=config.seed))
    if fmt in ("mcap", "both"):
        from aefabmap_ros.io.bags import write_rgbd_bag

        frames = ((stamp, image, depth_to_16uc1(depth))
                  for stamp, image, depth in zip(sequence.stamps_ns.tolist(), sequence.images, sequence.depths,
                                                 strict=True))
        write_rgbd_bag(directory / "bag", topic, frames, sequence.camera_matrix, storage="mcap", odometry=odometry)
    write_kitti_poses(directory / "poses.txt", sequence.poses)
    stamps_s = sequence.stamps_ns / 1e9
    atomic_write_text(directory / "groundtruth.tum", tum_text(stamps_s, sequence.poses))
    atomic_write_text(directory / "odometry.tum", tum_text(stamps_s, odometry))
    atomic_write_bytes(directory / "camera_info.yaml",
                       camera_info_yaml(sequence.camera_matrix, config.width, config.height).encode())
    seconds = (sequence.stamps_ns - sequence.stamps_ns[0]) / 1e9
    # Nanosecond digits: at 30 Hz, 7 significant digits (%e) would move frames 5 s apart to 4.9999 s.
    atomic_write_bytes(directory / "times.txt", "".join(f"{t:.9f}\n" for t in seconds).encode())
    projection = np.hstack([sequence.camera_matrix, np.zeros((3, 1))]).reshape(12)
    atomic_write_bytes(directory / "calib.txt", ("P0: " + " ".join(f"{v:.12e}" for v in projection) + "\n").encode())
    # The rows' stamps: those of the bag's images (header and log time), of groundtruth.tum and odometry.tum.
    _save_npz(directory / "loop_gt.npz", sequence.gt, sequence.stamps_ns)
    _save_npz(directory / "loop_gt_poses.npz", sequence.gt_poses, sequence.stamps_ns)
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
          f"({config.num_frames / elapsed:.1f} frames/s), {int(sequence.gt.sum())} covisibility loop pairs, "
          f"{int(sequence.gt.any(axis=1).sum())} query frames with a loop "
          f"(pose rule: {int(sequence.gt_poses.sum())} pairs, {int(sequence.gt_poses.any(axis=1).sum())} frames) "
          f"-> {target}")


def run(args: argparse.Namespace) -> None:
    base = preset_config(args.preset, args.seed)
    given = {"num_frames": args.frames, "width": args.width, "height": args.height}
    base = replace(base, color=args.color, **{name: value for name, value in given.items() if value is not None})
    if args.preset == "figure-eight":
        base = replace(base, laps=args.laps)
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
    return run_cli(build_parser(), argv, _run_reporting_write_errors)


def _run_reporting_write_errors(args: argparse.Namespace) -> int:
    try:
        run(args)
    except OSError as error:
        raise ConfigError(f"cannot write to {args.out}: {error}") from error
    return 0


if __name__ == "__main__":
    sys.exit(main())
