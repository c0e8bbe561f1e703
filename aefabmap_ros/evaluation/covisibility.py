"""Ground-truth loop matrices from depth: covisibility (DESIGN section 9.2, ``covisibility_loop_matrix``).

Frame ``i`` revisits earlier frame ``j`` when at least ``min_fraction`` of i's grid pixels with depth,
lifted to 3-D with i's pose, land on the surface that j itself saw: in front of j, inside j's image, and
within ``tolerance_m + relative_tolerance * z`` of j's depth there. Unlike the pose rule
(``ground_truth``) it knows about occlusion, field of view and range. Two limits of the plain rule:
cameras facing each other (a street driven in the opposite direction) share the ground and side walls
between them and count as covisible unless ``max_view_angle_deg`` is given; and at walking speed along a
straight street a frame stays covisible with frames of the same pass long after it, so the time gap
alone does not separate "still here" from "came back".

Tolerances. The default 5 cm is "a few cm" of a rendered or millimetre-quantised depth map plus a little
pose error; the relative 1 % covers what grows with range: RGB-D sensor noise (about 1 % at 4-5 m for
structured light and stereo) and the lateral shift of a point under a pose's rotation error (0.5 degree
moves it by 0.9 % of its range, which on an oblique surface becomes a depth error of that order).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.io.rgbd import check_camera_matrix
from aefabmap_ros.verification.frame_depths import agrees_with_surface, as_metres

_ROTATION_TOLERANCE = 1e-4
_POINTS_PER_BATCH = 1_000_000  # projected points held at once (about 100 MB of temporaries)
_KEY_BIAS = 1 << 20  # voxel indices in [-2^20, 2^20) pack into one int64 key (21 bits per axis)


@dataclass(frozen=True)
class CovisibilityStats:
    """What the computation did, for reports: frames, candidate pairs after pruning, revisit pairs."""

    num_frames: int
    candidate_pairs: int  # pairs projected point by point (after the time gap and voxel pruning)
    revisit_pairs: int
    revisiting_frames: int


def _check_depths(depths: np.ndarray) -> np.ndarray:
    values = np.asarray(depths)
    if values.ndim != 3:
        raise DataError(f"depths must have shape (N, H, W), got {values.shape}")
    if values.shape[1] < 2 or values.shape[2] < 2:
        raise DataError(f"depth maps must be at least 2x2 pixels, got {values.shape[1]}x{values.shape[2]}")
    if not (np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)):
        raise DataError(f"depths must be a real number array, got dtype {values.dtype}")
    return values


def check_poses(poses: np.ndarray, num_frames: int | None = None) -> np.ndarray:
    """(N, 3, 4) float64 camera-to-world poses with finite values and rotation blocks, or DataError."""
    matrices = np.asarray(poses, dtype=np.float64)
    if matrices.ndim != 3 or matrices.shape[1:] != (3, 4):
        raise DataError(f"poses must have shape (N, 3, 4), got {matrices.shape}")
    if num_frames is not None and matrices.shape[0] != num_frames:
        raise DataError(f"poses has {matrices.shape[0]} entries but depths has {num_frames} frames")
    finite = np.isfinite(matrices).all(axis=(1, 2))
    if not finite.all():
        raise DataError(f"pose {int(np.argmin(finite))} contains non-finite values")
    rotations = matrices[:, :, :3]
    error = np.abs(np.einsum("nki,nkj->nij", rotations, rotations) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    bad = (error > _ROTATION_TOLERANCE) | (np.linalg.det(rotations) < 0) if len(matrices) else error > 0
    if bad.any():
        index = int(np.argmax(bad))
        raise DataError(f"pose {index} is not a rotation (|R^T R - I| = {error[index]:.3g}, "
                        f"det {np.linalg.det(rotations[index]):.3g})")
    return matrices


def _check_stamps(stamps_ns: np.ndarray, num_frames: int) -> np.ndarray:
    stamps = np.asarray(stamps_ns)
    if stamps.shape != (num_frames,):
        raise DataError(f"stamps_ns must have shape ({num_frames},), got {stamps.shape}")
    if not np.issubdtype(stamps.dtype, np.integer):
        raise DataError(f"stamps_ns must be integer nanoseconds, got dtype {stamps.dtype}")
    stamps = stamps.astype(np.int64)
    backwards = np.diff(stamps) < 0
    if backwards.any():
        index = int(np.argmax(backwards)) + 1
        raise DataError(f"stamps_ns must not decrease: frame {index} ({stamps[index]}) is before frame "
                        f"{index - 1} ({stamps[index - 1]})")
    return stamps


def _check_covisibility_parameters(
    min_fraction: float, min_gap_s: float, grid_step_px: int, tolerance_m: float, relative_tolerance: float,
    prune_voxel_m: float | None, depth_scale: float,
) -> None:
    if not 0 < min_fraction <= 1:
        raise ConfigError(f"min_fraction must be in (0, 1], got {min_fraction!r}")
    if not min_gap_s >= 0:
        raise ConfigError(f"min_gap_s must be >= 0, got {min_gap_s!r}")
    if isinstance(grid_step_px, bool) or not isinstance(grid_step_px, int | np.integer) or grid_step_px < 1:
        raise ConfigError(f"grid_step_px must be an integer >= 1, got {grid_step_px!r}")
    if not tolerance_m >= 0:
        raise ConfigError(f"tolerance_m must be >= 0, got {tolerance_m!r}")
    if not relative_tolerance >= 0:
        raise ConfigError(f"relative_tolerance must be >= 0, got {relative_tolerance!r}")
    if prune_voxel_m is not None and not (prune_voxel_m > 0 and math.isfinite(prune_voxel_m)):
        raise ConfigError(f"prune_voxel_m must be > 0 (or None: no pruning), got {prune_voxel_m!r}")
    if not (depth_scale > 0 and math.isfinite(depth_scale)):
        raise ConfigError(f"depth_scale must be > 0, got {depth_scale!r}")


def grid_pixels(height: int, width: int, grid_step_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the sampling grid: every ``grid_step_px``-th pixel, starting half a step in."""
    return np.arange(grid_step_px // 2, height, grid_step_px), np.arange(grid_step_px // 2, width, grid_step_px)


@dataclass(frozen=True)
class _PixelRays:
    """The pixels of a sampling grid and their rays K^-1 [u, v, 1] (x, y; z = 1), flattened."""

    rows: np.ndarray  # (P,) int64
    columns: np.ndarray  # (P,) int64
    ray_x: np.ndarray  # (P,)
    ray_y: np.ndarray  # (P,)

    @staticmethod
    def grid(height: int, width: int, step: int, camera_matrix: np.ndarray, dtype: type) -> _PixelRays:
        row_values, column_values = grid_pixels(height, width, step)
        rows, columns = (axis.ravel() for axis in np.meshgrid(row_values, column_values, indexing="ij"))
        fx, skew, cx = camera_matrix[0]
        fy, cy = camera_matrix[1, 1], camera_matrix[1, 2]
        ray_y = (rows - cy) / fy
        ray_x = (columns - cx - skew * ray_y) / fx
        return _PixelRays(rows, columns, ray_x.astype(dtype), ray_y.astype(dtype))

    def lift(self, depth: np.ndarray, pose: np.ndarray, depth_scale: float, dtype: type) -> np.ndarray:
        """World points (M, 3) of the grid pixels of ``depth`` (H, W) that have depth: R (d K^-1 [u, 1]) + t."""
        metres = as_metres(depth[self.rows, self.columns], depth_scale, dtype)
        valid = np.isfinite(metres)
        metres, ray_x, ray_y = metres[valid], self.ray_x[valid], self.ray_y[valid]
        rotation: np.ndarray = pose[:, :3].astype(dtype)
        translation: np.ndarray = pose[:, 3].astype(dtype)
        # Row by row instead of a (M, 3) @ (3, 3) product: three fused passes, no temporaries of (M, 3).
        return np.column_stack([
            metres * (rotation[axis, 0] * ray_x + rotation[axis, 1] * ray_y + rotation[axis, 2]) + translation[axis]
            for axis in range(3)
        ])


def _voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    cells = np.floor(points / points.dtype.type(voxel_m)).astype(np.int64)
    cells = np.clip(cells + _KEY_BIAS, 0, 2 * _KEY_BIAS - 1)
    result: np.ndarray = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]
    return result


def _dilated_keys(keys: np.ndarray) -> np.ndarray:
    """The keys of every voxel within one voxel (26-neighbourhood) of ``keys``, one axis at a time."""
    for shift in (42, 21, 0):
        cell = (keys >> shift) & (2 * _KEY_BIAS - 1)
        step = np.int64(1) << shift
        # Voxels on the key range's edge (1000 km out) would wrap: leave them undilated on that side.
        keys = np.unique(np.concatenate([keys, keys[cell > 0] - step, keys[cell < 2 * _KEY_BIAS - 1] + step]))
    return keys


def _voxel_candidates(
    depths: np.ndarray, poses: np.ndarray, camera_matrix: np.ndarray, points: list[np.ndarray],
    last_earlier: np.ndarray, min_fraction: float, voxel_m: float, depth_scale: float,
) -> list[np.ndarray]:
    """Per frame i, the earlier frames j whose surfaces could hold ``min_fraction`` of i's grid points.

    A point of i counts for j when its voxel is within one voxel of a voxel holding one of j's pixels
    (every pixel of j is lifted). A point that lands on j's surface within the tolerance is within one
    voxel of j's pixels as long as neighbouring pixels are less than ``voxel_m`` apart on that surface,
    so the test keeps every true revisit unless the surfaces it relies on are seen so far or so
    obliquely that one pixel spans more than ``voxel_m`` (with f = 277 px, 320 pixels for 60 degrees,
    and 2 m voxels: a facing wall beyond 550 m, the ground 1.6 m below the camera beyond about 30 m).
    Smaller voxels lose revisits whose surfaces are seen obliquely, larger ones keep more pairs to
    project: 2 m (the default) keeps every pair no pruning finds on the dense-video preset
    (docs/measurements.md). Every pixel of j is lifted: a sparser sample of j misses distant walls.
    """
    num_frames = len(points)
    point_keys = [_voxel_keys(frame_points, voxel_m) for frame_points in points]
    vocabulary = np.unique(np.concatenate(point_keys)) if num_frames else np.zeros(0, np.int64)
    if vocabulary.size == 0:  # no frame has a grid point with depth: nothing can be covisible
        return [np.zeros(0, np.int64) for _ in range(num_frames)]
    every_pixel = _PixelRays.grid(depths.shape[1], depths.shape[2], 1, camera_matrix, np.float32)
    rows_a: list[np.ndarray] = []
    cols_a: list[np.ndarray] = []
    rows_b: list[np.ndarray] = []
    cols_b: list[np.ndarray] = []
    for index in range(num_frames):
        columns = np.searchsorted(vocabulary, point_keys[index])  # repeated entries add up in the sparse matrix
        rows_a.append(np.full(columns.size, index))
        cols_a.append(columns)
        dense = every_pixel.lift(depths[index], poses[index], depth_scale, np.float32)
        occupied = _dilated_keys(np.unique(_voxel_keys(dense, voxel_m)))
        found = np.searchsorted(vocabulary, occupied)
        found = found[(found < vocabulary.size) & (vocabulary[np.minimum(found, vocabulary.size - 1)] == occupied)]
        rows_b.append(np.full(found.size, index))
        cols_b.append(found)
    shape = (num_frames, vocabulary.size)
    counts_matrix = sparse.csr_matrix(
        (np.ones(sum(c.size for c in cols_a), np.int32), (np.concatenate(rows_a), np.concatenate(cols_a))),
        shape=shape)
    occupancy_t = sparse.csr_matrix(
        (np.ones(sum(c.size for c in cols_b), np.int32), (np.concatenate(rows_b), np.concatenate(cols_b))),
        shape=shape).T.tocsr()
    candidates: list[np.ndarray] = []
    block = 256
    for start in range(0, num_frames, block):
        stop = min(num_frames, start + block)
        horizon = int(last_earlier[stop - 1]) + 1  # no frame of the block looks further than this
        shared = (counts_matrix[start:stop] @ occupancy_t[:, :horizon]).toarray() if horizon > 0 else None
        for index in range(start, stop):
            count = max(len(points[index]), 1)
            reach = int(last_earlier[index]) + 1
            if shared is None or reach <= 0:
                candidates.append(np.zeros(0, np.int64))
                continue
            candidates.append(np.nonzero(shared[index - start, :reach] / count >= min_fraction)[0])
    return candidates


@dataclass(frozen=True)
class _Agreement:
    """When a point lands on a frame's surface: within ``tolerance_m + relative_tolerance * z`` of its depth
    (``depth_scale`` units per metre), seen from directions whose cosine is at least ``min_view_cosine``."""

    tolerance_m: float
    relative_tolerance: float
    depth_scale: float
    min_view_cosine: float | None


def _agreeing_counts(
    world_points: np.ndarray, others: np.ndarray, depths_flat: np.ndarray, poses: np.ndarray,
    camera_matrix: np.ndarray, shape: tuple[int, int], agreement: _Agreement, origin: np.ndarray,
) -> np.ndarray:
    """For each frame in ``others``: how many of ``world_points`` (M, 3) land on that frame's own surface."""
    height, width = shape
    rotations, translations = poses[others, :, :3], poses[others, :, 3]
    # p_j = R_j^T (p - t_j), for all frames of the batch at once: (B, M, 3).
    camera = np.matmul(world_points[None, :, :], rotations) - np.matmul(translations[:, None, :], rotations)
    z = camera[:, :, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        y = camera[:, :, 1] / z
        u = camera_matrix[0, 0] * camera[:, :, 0] / z + camera_matrix[0, 1] * y + camera_matrix[0, 2]
        v = camera_matrix[1, 1] * y + camera_matrix[1, 2]
    inside = (z > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    batch, point = np.nonzero(inside)
    u, v, z = u[batch, point], v[batch, point], z[batch, point]
    frame_base = others[batch].astype(np.int64) * (height * width)

    def pixel_metres(rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
        return as_metres(depths_flat[frame_base + rows * width + columns], agreement.depth_scale)

    agree = agrees_with_surface(pixel_metres, u, v, (width, height), z, agreement.tolerance_m,
                                agreement.relative_tolerance)
    if agreement.min_view_cosine is not None:
        # The angle at the point between the rays from i's and j's camera centres.
        points = world_points[point[agree]]
        from_i, from_j = points - origin, points - translations[batch[agree]]
        cosine = np.einsum("md,md->m", from_i, from_j) / (
            np.linalg.norm(from_i, axis=1) * np.linalg.norm(from_j, axis=1))
        agree[np.nonzero(agree)[0][cosine < agreement.min_view_cosine]] = False
    return np.bincount(batch[agree], minlength=len(others))


def covisibility_with_stats(
    depths: np.ndarray,
    poses: np.ndarray,
    camera_matrix: np.ndarray,
    stamps_ns: np.ndarray,
    *,
    min_fraction: float = 0.3,
    min_gap_s: float = 5.0,
    grid_step_px: int = 8,
    tolerance_m: float = 0.05,
    relative_tolerance: float = 0.01,
    prune_voxel_m: float | None = 2.0,
    depth_scale: float = 1.0,
    max_view_angle_deg: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, CovisibilityStats]:
    """(N, N) uint8 lower-triangular covisibility loop matrix and statistics (DESIGN section 9.2).

    depths: (N, H, W) depth along each camera's optical axis, ``depth_scale`` units per metre (1 for
    float metres, 1000 for 16UC1 millimetres); 0, negative, NaN or inf = no depth. poses: (N, 3, 4)
    camera-to-world [R | t], camera x right, y down, z forward. camera_matrix: (3, 3) pinhole K shared
    by all frames. stamps_ns: (N,) non-decreasing.

    ``gt[i, j] = 1`` when ``stamps_ns[i] - stamps_ns[j] >= min_gap_s`` and at least ``min_fraction`` of
    i's grid pixels with depth (every ``grid_step_px``-th pixel, see ``grid_pixels``), lifted with i's
    pose, land in front of j, inside j's image (pixel centres 0..W-1, 0..H-1) and where j's depth,
    interpolated bilinearly in inverse depth from four pixels that all have depth, agrees with the
    point's depth in j within ``tolerance_m + relative_tolerance * z`` (the defaults: see the module).

    ``max_view_angle_deg`` (None: no limit, the rule of DESIGN 9.2) also requires the angle at the point
    between the rays from i's and j's camera centres to be at most that: the same surface seen from a
    similar direction, so that cameras facing each other across a street are not covisible.

    ``prune_voxel_m``: before projecting, pairs are pruned by voxel co-occupancy (see
    ``_voxel_candidates``); None projects every pair that satisfies the time gap (slow: O(N^2)).
    ``progress(done, total)`` is called after each query frame. ``covisibility_loop_matrix`` is the
    same without the statistics.
    """
    values, matrices, matrix, stamps = _checked_inputs(depths, poses, camera_matrix, stamps_ns)
    num_frames, height, width = values.shape
    _check_covisibility_parameters(min_fraction, min_gap_s, grid_step_px, tolerance_m, relative_tolerance,
                                   prune_voxel_m, depth_scale)
    agreement = _Agreement(tolerance_m, relative_tolerance, depth_scale, _min_view_cosine(max_view_angle_deg))
    last_earlier = _last_earlier_frames(stamps, min_gap_s)
    grid = _PixelRays.grid(height, width, grid_step_px, matrix, np.float64)
    points = [grid.lift(values[index], matrices[index], depth_scale, np.float64) for index in range(num_frames)]
    candidates = ([np.arange(int(last) + 1) for last in last_earlier] if prune_voxel_m is None else
                  _voxel_candidates(values, matrices, matrix, points, last_earlier, min_fraction, prune_voxel_m,
                                    depth_scale))
    gt = np.zeros((num_frames, num_frames), dtype=np.uint8)
    depths_flat = values.reshape(-1)
    for index in range(num_frames):
        others, world_points = candidates[index], points[index]
        if others.size and len(world_points):
            gt[index, _revisited(world_points, others, depths_flat, matrices, matrix, (height, width),
                                 matrices[index, :, 3], agreement, min_fraction)] = 1
        if progress is not None:
            progress(index + 1, num_frames)
    return gt, CovisibilityStats(num_frames, int(sum(c.size for c in candidates)), int(gt.sum()),
                                 int(gt.any(axis=1).sum()))


def _checked_inputs(depths: np.ndarray, poses: np.ndarray, camera_matrix: np.ndarray, stamps_ns: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depths, float64 poses, camera matrix and int64 stamps of one sequence, or DataError."""
    values = _check_depths(depths)
    return (values, check_poses(poses, values.shape[0]), check_camera_matrix(camera_matrix),
            _check_stamps(stamps_ns, values.shape[0]))


def _revisited(world_points: np.ndarray, others: np.ndarray, depths_flat: np.ndarray, matrices: np.ndarray,
               matrix: np.ndarray, shape: tuple[int, int], centre: np.ndarray, agreement: _Agreement,
               min_fraction: float) -> np.ndarray:
    """The frames of ``others`` on whose surface at least ``min_fraction`` of ``world_points`` (seen from
    ``centre``) land, projected in batches that bound the memory of the temporaries."""
    per_batch = max(1, _POINTS_PER_BATCH // len(world_points))
    matched = []
    for start in range(0, others.size, per_batch):
        batch = others[start : start + per_batch]
        counts = _agreeing_counts(world_points, batch, depths_flat, matrices, matrix, shape, agreement, centre)
        matched.append(batch[counts / len(world_points) >= min_fraction])
    return np.concatenate(matched)


def _min_view_cosine(max_view_angle_deg: float | None) -> float | None:
    """The cosine a view angle must reach (None: no limit); a hair below the limit's, so the limit passes."""
    if max_view_angle_deg is None:
        return None
    if not 0 < max_view_angle_deg <= 180:
        raise ConfigError(f"max_view_angle_deg must be in (0, 180] (or None: no limit), got {max_view_angle_deg!r}")
    return math.cos(math.radians(max_view_angle_deg)) - 1e-12


def _last_earlier_frames(stamps: np.ndarray, min_gap_s: float) -> np.ndarray:
    """Per frame, the last frame at least ``min_gap_s`` before it and strictly earlier, even with gap 0 (-1: none)."""
    gap_ns = round(min_gap_s * 1e9)
    last_earlier = np.searchsorted(stamps, stamps - gap_ns, side="right") - 1
    result: np.ndarray = np.minimum(last_earlier, np.arange(len(stamps)) - 1)
    return result


def covisibility_loop_matrix(
    depths: np.ndarray,
    poses: np.ndarray,
    camera_matrix: np.ndarray,
    stamps_ns: np.ndarray,
    *,
    min_fraction: float = 0.3,
    min_gap_s: float = 5.0,
    grid_step_px: int = 8,
    tolerance_m: float = 0.05,
    relative_tolerance: float = 0.01,
    prune_voxel_m: float | None = 2.0,
    depth_scale: float = 1.0,
    max_view_angle_deg: float | None = None,
) -> np.ndarray:
    """(N, N) uint8 lower-triangular covisibility loop matrix; see ``covisibility_with_stats``."""
    gt, _ = covisibility_with_stats(
        depths, poses, camera_matrix, stamps_ns, min_fraction=min_fraction, min_gap_s=min_gap_s,
        grid_step_px=grid_step_px, tolerance_m=tolerance_m, relative_tolerance=relative_tolerance,
        prune_voxel_m=prune_voxel_m, depth_scale=depth_scale, max_view_angle_deg=max_view_angle_deg)
    return gt
