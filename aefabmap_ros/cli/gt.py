"""aefabmap_gt: covisibility ground truth (DESIGN 9.2) of your own RGB-D recording.

    aefabmap_gt --depth seq/depth --poses seq/poses.txt --camera-info seq/camera_info.yaml \\
        --times seq/times.txt --out seq/loop_gt.npz                       # an aefabmap_synth folder
    aefabmap_gt --depth rgbd_dataset_freiburg1_room/depth --depth-scale 5000 \\
        --poses rgbd_dataset_freiburg1_room/groundtruth.txt --poses-format tum \\
        --intrinsics 517.3 516.5 318.6 255.3 --skip-unposed --out fr1_room_gt.npz   # TUM RGB-D

Frame i revisits earlier frame j (at least --min-gap-s earlier) when at least --min-fraction of i's
depth pixels (every --grid-step-px-th), lifted to 3-D with i's pose, land on the surface j saw (in
front of j, inside its image, j's depth within --tolerance-m + --relative-tolerance * depth).

Inputs:
  --depth DIR         16-bit PNGs (ROS 16UC1); metres = value / --depth-scale (1000 = millimetres;
                      TUM RGB-D uses 5000); 0 = no depth. Read by stamp when named <seconds>.png,
                      else by file name.
  --times FILE        one number of seconds per frame (KITTI times.txt); without it the stamps come
                      from the file names (TUM style <seconds>.png)
  --poses FILE        camera-to-world poses, camera x right, y down, z forward:
                        kitti: one 3x4 [R | t] per line, one line per depth frame, in order;
                        tum:   "timestamp tx ty tz qx qy qz qw" lines, associated to each depth frame
                               by nearest stamp within --max-pose-offset-s. A frame without a pose is an
                               error, unless --skip-unposed: then it is left out of the matrix (the
                               output's "files" say which frames the rows are).
  --intrinsics FX FY CX CY, or --camera-info camera_info.yaml (ROS camera_calibration_parsers format)

Output (.npz, written atomically): "gt" (N, N) uint8 (gt[i, j] = 1: frame i revisits frame j),
"stamps_ns" (N,) int64, "files" (N,) the depth file names of the rows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from aefabmap_ros.cli.common import ArgumentParser, deferred, run_cli


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_gt", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--depth", type=Path, required=True, help="folder of 16-bit depth PNGs")
    parser.add_argument("--depth-scale", type=float, default=1000.0,
                        help="depth PNG units per metre (default: 1000 = millimetres; TUM RGB-D: 5000)")
    parser.add_argument("--poses", type=Path, required=True, help="camera-to-world trajectory file")
    parser.add_argument("--poses-format", choices=("kitti", "tum"), default="kitti",
                        help="kitti (3x4 per line, one per frame) or tum (stamped quaternions); default: kitti")
    camera = parser.add_mutually_exclusive_group(required=True)
    camera.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                        help="pinhole intrinsics in pixels")
    camera.add_argument("--camera-info", type=Path,
                        help="ROS camera_info.yaml with the intrinsics (a pinhole: no distortion)")
    parser.add_argument("--times", type=Path, help="seconds per frame, one per line (default: from file names)")
    parser.add_argument("--max-pose-offset-s", type=float, default=0.02,
                        help="tum: largest stamp difference of a frame and its pose (default: 0.02)")
    parser.add_argument("--skip-unposed", action="store_true",
                        help="tum: leave frames without a pose out instead of failing")
    parser.add_argument("--min-gap-s", type=float, default=5.0, help="smallest time gap of a revisit (default: 5)")
    parser.add_argument("--min-fraction", type=float, default=0.3,
                        help="share of i's depth pixels that must land on j's surfaces (default: 0.3)")
    parser.add_argument("--grid-step-px", type=int, default=8, help="sample every n-th pixel of i (default: 8)")
    parser.add_argument("--tolerance-m", type=float, default=0.05, help="absolute depth tolerance (default: 0.05)")
    parser.add_argument("--relative-tolerance", type=float, default=0.01,
                        help="depth tolerance per metre of depth (default: 0.01)")
    parser.add_argument("--max-view-angle-deg", type=float, default=None,
                        help="also require i and j to see each point from directions at most this far apart "
                             "(default: no limit; without one, cameras facing each other across a street or "
                             "corridor are covisible through the floor between them)")
    parser.add_argument("--out", type=Path, required=True, help="output .npz")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, deferred("aefabmap_ros.cli.gt_run:run"))


if __name__ == "__main__":
    raise SystemExit(main())
