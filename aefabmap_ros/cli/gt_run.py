"""What aefabmap_gt does once its arguments are parsed (see ``gt.py``, which holds the options)."""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.evaluation.covisibility import check_poses, covisibility_with_stats
from aefabmap_ros.evaluation.ground_truth import read_kitti_poses
from aefabmap_ros.io.atomic import atomic_write_bytes
from aefabmap_ros.io.rgbd import (
    associate,
    intrinsics_matrix,
    list_depth_files,
    read_camera_info_yaml,
    read_depth_pngs,
    read_times,
    read_tum_trajectory,
    stamps_from_names,
)


def _stamps(args: argparse.Namespace, files: list[Path]) -> np.ndarray:
    return read_times(args.times, len(files)) if args.times is not None else stamps_from_names(files)


def _poses(args: argparse.Namespace, stamps_ns: np.ndarray, files: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    """(poses of the kept frames, indices of the kept frames)."""
    if args.poses_format == "kitti":
        poses = read_kitti_poses(args.poses)
        if len(poses) != len(files):
            raise DataError(f"KITTI pose file {args.poses} has {len(poses)} poses but the depth folder "
                            f"{args.depth} has {len(files)} frames")
        return check_poses(poses), np.arange(len(files))
    if not args.max_pose_offset_s >= 0:
        raise ConfigError(f"--max-pose-offset-s must be >= 0, got {args.max_pose_offset_s!r}")
    trajectory = read_tum_trajectory(args.poses)
    nearest = associate(stamps_ns, trajectory, round(args.max_pose_offset_s * 1e9))
    unposed = np.nonzero(nearest < 0)[0]
    if unposed.size and not args.skip_unposed:
        raise DataError(f"{unposed.size} of {len(files)} depth frames have no pose in {args.poses} within "
                        f"{args.max_pose_offset_s} s (first: {files[unposed[0]].name}); pass --skip-unposed to "
                        f"leave them out")
    kept = np.nonzero(nearest >= 0)[0]
    return check_poses(trajectory.poses[nearest[kept]]), kept


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buffer.getvalue())
    except OSError as error:
        raise ConfigError(f"cannot write {path}: {error}") from error


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    files = list_depth_files(args.depth)
    stamps_ns = _stamps(args, files)
    if args.camera_info is not None:
        info = read_camera_info_yaml(args.camera_info)
        if np.any(info.distortion != 0.0):
            # The covisibility rule lifts and projects pixels through a pinhole: distorted pixels would land wrong.
            raise DataError(f"{args.camera_info} has distortion coefficients {info.distortion.tolist()}: the "
                            "covisibility ground truth needs rectified depth images and their pinhole camera")
        camera_matrix, width, height = info.matrix, info.width, info.height
    else:
        camera_matrix, width, height = intrinsics_matrix(*args.intrinsics), None, None
    poses, kept = _poses(args, stamps_ns, files)
    depths = read_depth_pngs([files[index] for index in kept])
    if width is not None and (depths.shape[2], depths.shape[1]) != (width, height):
        raise DataError(f"depth images are {depths.shape[2]}x{depths.shape[1]} but {args.camera_info} says "
                        f"{width}x{height}")
    if np.any(np.diff(stamps_ns[kept]) < 0):
        raise DataError(f"frame stamps go backwards in {args.times or args.depth}")
    loaded = time.perf_counter()
    gt, stats = covisibility_with_stats(
        depths, poses, camera_matrix, stamps_ns[kept], min_fraction=args.min_fraction, min_gap_s=args.min_gap_s,
        grid_step_px=args.grid_step_px, tolerance_m=args.tolerance_m, relative_tolerance=args.relative_tolerance,
        depth_scale=args.depth_scale, max_view_angle_deg=args.max_view_angle_deg)
    finished = time.perf_counter()
    _write_npz(args.out, {"gt": gt, "stamps_ns": stamps_ns[kept],
                          "files": np.array([files[index].name for index in kept])})
    skipped = len(files) - len(kept)
    print(f"{stats.num_frames} frames{f' ({skipped} without a pose left out)' if skipped else ''}: "
          f"{stats.revisit_pairs} revisit pairs, {stats.revisiting_frames} revisiting frames "
          f"({stats.candidate_pairs} candidate pairs projected); read in {loaded - started:.1f} s, "
          f"ground truth in {finished - loaded:.1f} s -> {args.out}")
    return 0
