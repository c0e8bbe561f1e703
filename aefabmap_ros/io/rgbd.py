"""A user's RGB-D recording on disk: depth PNG folders, stamps, TUM / KITTI trajectories, intrinsics.

Everything needed to compute covisibility ground truth (``evaluation.covisibility.covisibility_loop_matrix``)
from files, with every failure a user can cause as a ``DataError`` naming the file:

- depth: a folder of 16-bit single-channel PNGs (ROS 16UC1; ``depth_scale`` units per metre: 1000 for
  millimetres, 5000 for TUM RGB-D), read in file-name order (by stamp when the names are stamps);
- stamps: a text file with one number of seconds per frame (KITTI ``times.txt``), or the file names
  themselves, TUM style ``<seconds>.png`` (``1305031102.160407.png``), parsed exactly to nanoseconds;
- poses: KITTI (one camera-to-world 3x4 matrix per line, one line per depth frame) or TUM
  (``timestamp tx ty tz qx qy qz qw`` camera-to-world, associated to depth frames by nearest stamp);
- intrinsics: fx fy cx cy, or a ROS ``camera_info.yaml`` (camera_calibration_parsers format).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from aefabmap_ros.errors import DataError

_SECONDS = re.compile(r"^\s*(\d+)(?:\.(\d*))?\s*$")


def check_camera_matrix(camera_matrix: np.ndarray) -> np.ndarray:
    """A (3, 3) float64 pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, or DataError."""
    matrix = np.asarray(camera_matrix, dtype=np.float64)
    if matrix.shape != (3, 3):
        raise DataError(f"camera_matrix must have shape (3, 3), got {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise DataError(f"camera_matrix contains non-finite values: {matrix.tolist()}")
    if not (matrix[0, 0] > 0 and matrix[1, 1] > 0):
        fx, fy = float(matrix[0, 0]), float(matrix[1, 1])
        raise DataError(f"camera_matrix focal lengths must be > 0, got fx={fx!r} fy={fy!r}")
    if matrix[1, 0] != 0 or not np.array_equal(matrix[2], [0.0, 0.0, 1.0]):
        raise DataError(f"camera_matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {matrix.tolist()}")
    return matrix


def seconds_to_ns(text: str) -> int:
    """Non-negative decimal seconds ("1305031102.160407") -> integer nanoseconds, without float rounding."""
    match = _SECONDS.match(text)
    if match is None:
        raise ValueError(f"not a number of seconds: {text!r}")
    whole, fraction = match.group(1), (match.group(2) or "")
    return int(whole) * 1_000_000_000 + int((fraction + "000000000")[:9])


_STAMP_NAME = re.compile(r"^\d+\.\d+$")  # a decimal point: frame numbers (000042.png) are no stamps


def _stamp_from_name(path: Path) -> int | None:
    return seconds_to_ns(path.stem) if _STAMP_NAME.match(path.stem) else None


def list_depth_files(folder: Path) -> list[Path]:
    """The PNG files of a depth folder: by stamp when every name is a stamp, else by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"depth folder does not exist: {folder}")
    files = sorted(folder.glob("*.png"))
    if not files:
        raise DataError(f"no .png files in depth folder {folder}")
    stamps = [_stamp_from_name(path) for path in files]
    if all(stamp is not None for stamp in stamps):
        files = [path for _, path in sorted(zip(stamps, files, strict=True), key=lambda pair: pair[0] or 0)]
    return files


def read_depth_pngs(files: list[Path]) -> np.ndarray:
    """(N, H, W) uint16 stack of 16-bit single-channel PNGs (all of one size)."""
    stack: np.ndarray | None = None
    for index, path in enumerate(files):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DataError(f"cannot read depth image {path}")
        if image.dtype != np.uint16 or image.ndim != 2:
            raise DataError(f"depth image {path} must be a 16-bit single-channel PNG, got {image.dtype} "
                            f"with shape {image.shape}")
        if stack is None:
            stack = np.empty((len(files), *image.shape), dtype=np.uint16)  # one allocation, not N copies
        elif image.shape != stack.shape[1:]:
            raise DataError(f"depth image {path} is {image.shape[1]}x{image.shape[0]}, but {files[0].name} is "
                            f"{stack.shape[2]}x{stack.shape[1]}")
        stack[index] = image
    if stack is None:
        raise DataError("no depth images given")
    return stack


def stamps_from_names(files: list[Path]) -> np.ndarray:
    """(N,) int64 stamps of TUM-style file names ``<seconds>.png``."""
    stamps = []
    for path in files:
        stamp = _stamp_from_name(path)
        if stamp is None:
            raise DataError(f"cannot read a stamp from file name {path.name} (expected <seconds>.png, "
                            f"e.g. 1305031102.160407.png; or pass a times file)")
        stamps.append(stamp)
    return np.asarray(stamps, dtype=np.int64)


def _data_lines(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the non-empty, non-comment lines of a text file."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"cannot read {what} {path}: {error}") from error
    return [(number, line.split()) for number, line in enumerate(text.splitlines(), start=1)
            if line.strip() and not line.lstrip().startswith("#")]


def read_times(path: Path, num_frames: int, frames_of: str = "the folder") -> np.ndarray:
    """(N,) int64 stamps from a file of one number of seconds per line (KITTI times.txt); ``frames_of``
    names what has ``num_frames`` frames, for the error when the count differs."""
    stamps = []
    for number, fields in _data_lines(path, "times file"):
        if len(fields) != 1:
            raise DataError(f"{path}:{number}: expected one number of seconds, got {len(fields)} fields")
        try:
            stamps.append(round(float(fields[0]) * 1e9))
        except ValueError as error:
            raise DataError(f"{path}:{number}: not a number ({fields[0]!r})") from error
    if len(stamps) != num_frames:
        raise DataError(f"times file {path} has {len(stamps)} stamps but {frames_of} has {num_frames} frames")
    return np.asarray(stamps, dtype=np.int64)


@dataclass(frozen=True)
class Trajectory:
    """Stamped camera-to-world poses."""

    stamps_ns: np.ndarray  # (M,) int64, increasing
    poses: np.ndarray  # (M, 3, 4) float64 [R | t]


def read_tum_trajectory(path: Path) -> Trajectory:
    """A TUM trajectory file: ``timestamp tx ty tz qx qy qz qw`` per line (camera-to-world), '#' comments."""
    stamps, rows = [], []
    for number, fields in _data_lines(path, "TUM trajectory"):
        if len(fields) != 8:
            raise DataError(f"{path}:{number}: expected 8 fields (timestamp tx ty tz qx qy qz qw), got {len(fields)}")
        try:
            stamps.append(seconds_to_ns(fields[0]) if _SECONDS.match(fields[0]) else round(float(fields[0]) * 1e9))
            rows.append([float(value) for value in fields[1:]])
        except ValueError as error:
            raise DataError(f"{path}:{number}: not a number ({error})") from error
    if not rows:
        raise DataError(f"TUM trajectory {path} holds no poses")
    values = np.asarray(rows)
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        raise DataError(f"TUM trajectory {path} has non-finite values (pose {int(np.argmin(finite))})")
    norms = np.linalg.norm(values[:, 3:], axis=1)
    if (norms < 1e-6).any():
        raise DataError(f"TUM trajectory {path}: pose {int(np.argmax(norms < 1e-6))} has a zero quaternion")
    order = np.argsort(stamps, kind="stable")
    poses = np.zeros((len(rows), 3, 4))
    poses[:, :, :3] = Rotation.from_quat(values[:, 3:] / norms[:, None]).as_matrix()  # scalar-last, as TUM
    poses[:, :, 3] = values[:, :3]
    return Trajectory(np.asarray(stamps, dtype=np.int64)[order], poses[order])


def associate(frame_stamps_ns: np.ndarray, trajectory: Trajectory, max_offset_ns: int) -> np.ndarray:
    """For each frame, the index of the trajectory pose nearest in time, or -1 beyond ``max_offset_ns``."""
    stamps = trajectory.stamps_ns
    after = np.clip(np.searchsorted(stamps, frame_stamps_ns), 0, len(stamps) - 1)
    before = np.clip(after - 1, 0, len(stamps) - 1)
    nearest = np.where(np.abs(stamps[before] - frame_stamps_ns) <= np.abs(stamps[after] - frame_stamps_ns),
                       before, after)
    return np.where(np.abs(stamps[nearest] - frame_stamps_ns) <= max_offset_ns, nearest, -1)


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The pinhole matrix of fx fy cx cy (checked)."""
    return check_camera_matrix(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))


@dataclass(frozen=True)
class CameraInfoFile:
    """What a ROS camera_calibration_parsers YAML file says of the camera."""

    matrix: np.ndarray  # (3, 3) K
    distortion: np.ndarray  # (D,) OpenCV coefficients (plumb_bob / rational_polynomial); (0,) when none given
    width: int
    height: int


def read_camera_info_yaml(path: Path) -> CameraInfoFile:
    """K (``camera_matrix.data``), the distortion coefficients (``distortion_coefficients.data``; none when
    the file has no such block) and the image size of a ROS camera_calibration_parsers YAML file."""
    try:
        content = yaml.safe_load(Path(path).read_text())
        matrix = np.asarray(content["camera_matrix"]["data"], dtype=np.float64).reshape(3, 3)
        width, height = int(content["image_width"]), int(content["image_height"])
        coefficients = content.get("distortion_coefficients")
        distortion = (np.zeros(0) if coefficients is None
                      else np.asarray(coefficients["data"], dtype=np.float64).reshape(-1))
        if not np.isfinite(distortion).all():
            raise ValueError(f"distortion coefficients must be finite, got {distortion.tolist()}")
        return CameraInfoFile(check_camera_matrix(matrix), distortion, width, height)
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError, AttributeError, DataError) as error:
        raise DataError(f"cannot read camera info {path}: {type(error).__name__}: {error}") from error
