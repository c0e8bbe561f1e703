"""Ground-truth loop matrices from camera poses, KITTI pose files, and loop-matrix .npz files.

Pose rule (DESIGN section 6): frame ``i`` revisits earlier frame ``j`` when their camera centres are
within ``max_distance_m``, their optical axes within ``max_angle_deg`` and ``j <= i - min_gap_frames``.
The angle test matters: a street driven in the opposite direction passes the same points but
sees other facades, so it is not a revisit for an appearance-based detector.

KITTI pose files hold one camera-to-world 3x4 matrix ``[R | t]`` per line (12 numbers, row-major);
the camera looks along its +z axis, so the optical axis in the world is the third column of ``R``.

Ground truth from depth (covisibility) is in ``covisibility``.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.io.atomic import atomic_write_text

_UNIT_TOLERANCE = 1e-3


def _check_vectors(name: str, array: np.ndarray, num_rows: int | None = None) -> np.ndarray:
    values = np.asarray(array, dtype=np.float64)
    if values.ndim != 2 or values.shape[1] != 3:
        raise DataError(f"{name} must have shape (N, 3), got {values.shape}")
    if num_rows is not None and values.shape[0] != num_rows:
        raise DataError(f"{name} has {values.shape[0]} rows but positions have {num_rows}")
    if not np.isfinite(values).all():
        raise DataError(f"{name} contain non-finite values (row {np.nonzero(~np.isfinite(values))[0][0]})")
    return values


def loop_matrix_from_poses(
    positions: np.ndarray,
    optical_axes: np.ndarray,
    max_distance_m: float,
    max_angle_deg: float,
    min_gap_frames: int,
) -> np.ndarray:
    """(N, N) uint8 lower-triangular loop matrix: ``[i, j] = 1`` when frame i revisits earlier frame j.

    positions: (N, 3) camera centres in metres; optical_axes: (N, 3) unit viewing directions.
    Uses a k-d tree on the centres, so long sequences cost O(N log N + pairs), not O(N^2) distances.
    """
    centres = _check_vectors("positions", positions)
    axes = _check_vectors("optical_axes", optical_axes, centres.shape[0])
    norms = np.linalg.norm(axes, axis=1)
    off_unit = np.abs(norms - 1.0) > _UNIT_TOLERANCE
    if off_unit.any():
        row = int(np.nonzero(off_unit)[0][0])
        raise DataError(f"optical_axes must be unit vectors; row {row} has norm {norms[row]:.6g}")
    if not max_distance_m >= 0:
        raise ConfigError(f"max_distance_m must be >= 0, got {max_distance_m!r}")
    if not 0 <= max_angle_deg <= 180:
        raise ConfigError(f"max_angle_deg must be in [0, 180], got {max_angle_deg!r}")
    if isinstance(min_gap_frames, bool) or not isinstance(min_gap_frames, int | np.integer) or min_gap_frames < 1:
        raise ConfigError(f"min_gap_frames must be an integer >= 1, got {min_gap_frames!r}")

    num_frames = centres.shape[0]
    gt = np.zeros((num_frames, num_frames), dtype=np.uint8)
    if num_frames < 2:
        return gt
    pairs = cKDTree(centres).query_pairs(r=float(max_distance_m), output_type="ndarray")
    if pairs.size == 0:
        return gt
    earlier, later = pairs.min(axis=1), pairs.max(axis=1)
    # Compare cosines (with a hair of slack for rounding) rather than arccos of near-1 values.
    cos_limit = np.cos(np.deg2rad(max_angle_deg)) - 1e-12
    cosines = np.einsum("ij,ij->i", axes[earlier], axes[later])
    keep = (later - earlier >= min_gap_frames) & (cosines >= cos_limit)
    gt[later[keep], earlier[keep]] = 1
    return gt


def read_kitti_poses(path: Path) -> np.ndarray:
    """(N, 3, 4) float64 camera-to-world poses from a KITTI pose file (12 numbers per line)."""
    try:
        text = Path(path).read_text()
    except OSError as error:
        raise DataError(f"cannot read KITTI pose file {path}: {error}") from error
    rows = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split()
        if len(fields) != 12:
            raise DataError(f"{path}:{line_number}: expected 12 numbers, got {len(fields)}")
        try:
            rows.append([float(value) for value in fields])
        except ValueError as error:
            raise DataError(f"{path}:{line_number}: not a number ({error})") from error
    if not rows:
        raise DataError(f"KITTI pose file {path} holds no poses")
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)


def write_kitti_poses(path: Path, poses: np.ndarray) -> None:
    """Write (N, 3, 4) camera-to-world poses as a KITTI pose file, atomically."""
    matrices = np.asarray(poses, dtype=np.float64)
    if matrices.ndim != 3 or matrices.shape[1:] != (3, 4):
        raise DataError(f"poses must have shape (N, 3, 4), got {matrices.shape}")
    lines = [" ".join(f"{value:.9e}" for value in matrix.reshape(12)) for matrix in matrices]
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


def positions_and_axes(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (N, 3) and unit optical axes (N, 3) of (N, 3, 4) camera-to-world poses."""
    matrices = np.asarray(poses, dtype=np.float64)
    if matrices.ndim != 3 or matrices.shape[1:] != (3, 4):
        raise DataError(f"poses must have shape (N, 3, 4), got {matrices.shape}")
    axes = matrices[:, :, 2]
    norms = np.linalg.norm(axes, axis=1, keepdims=True)
    if np.any(norms < 1e-9):
        raise DataError(f"pose {int(np.argmin(norms))} has a zero rotation column")
    # Normalise: text files carry ~7 significant digits, enough to drift past the unit check.
    return matrices[:, :, 3].copy(), axes / norms


def loop_matrix_from_kitti(
    path: Path, max_distance_m: float, max_angle_deg: float, min_gap_frames: int
) -> np.ndarray:
    """Ground-truth loop matrix straight from a KITTI pose file."""
    positions, axes = positions_and_axes(read_kitti_poses(path))
    return loop_matrix_from_poses(positions, axes, max_distance_m, max_angle_deg, min_gap_frames)


def check_gt_matches(gt: np.ndarray, num_frames: int, source: str) -> None:
    if gt.ndim != 2 or gt.shape[0] != gt.shape[1]:
        raise DataError(f"ground truth must be a square (N, N) matrix, got shape {gt.shape}")
    if gt.shape[0] != num_frames:
        raise DataError(f"ground truth is {gt.shape[0]}x{gt.shape[1]} but {source} has {num_frames} frames")


def load_gt_npz(path: Path) -> np.ndarray:
    """The ``gt`` array of a loop-matrix .npz (square, 0/1)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if "gt" not in data.files:
                raise DataError(f"ground-truth file {path} has no array 'gt' (it has {sorted(data.files)})")
            gt = np.asarray(data["gt"])
    except FileNotFoundError as error:
        raise DataError(f"ground-truth file not found: {path}") from error
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:  # a damaged .npz is a zip that is not
        raise DataError(f"cannot read ground-truth file {path}: {error}") from error
    if gt.ndim != 2 or gt.shape[0] != gt.shape[1]:
        raise DataError(f"ground truth in {path} must be a square (N, N) matrix, got shape {gt.shape}")
    if not np.isin(gt, (0, 1)).all():
        raise DataError(f"ground truth in {path} must hold only 0 and 1")
    return gt.astype(np.uint8)


def load_gt_stamps(path: Path) -> np.ndarray | None:
    """The frame stamps of a loop-matrix .npz (``stamps_ns``: (N,) int64 nanoseconds, one per row, as
    aefabmap_gt and aefabmap_synth write them); None when the file has none."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if "stamps_ns" not in data.files:
                return None
            stamps = np.asarray(data["stamps_ns"])
    except FileNotFoundError as error:
        raise DataError(f"ground-truth file not found: {path}") from error
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:  # a damaged .npz is a zip that is not
        raise DataError(f"cannot read ground-truth file {path}: {error}") from error
    if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
        raise DataError(f"stamps_ns in {path} must be a 1-D array of integer nanoseconds, got {stamps.dtype} "
                        f"of shape {stamps.shape}")
    return stamps.astype(np.int64)
