"""Absolute trajectory error (ATE) with evo, the field's tool, and a drifting odometry to measure it on.

ATE: the estimate's poses are associated to the reference's by stamp (within ``max_diff_s``), the
estimate is aligned to the reference by Umeyama's method -- SE(3), or Sim(3) for monocular
trajectories whose scale is unknown -- and the RMSE of the position differences is reported (metres).

``drifting_odometry`` makes the odometry a wheel/visual odometry would give from ground-truth poses:
each step's motion (in the moving frame) has its translation scaled by ``1 + scale_bias + N(0,
scale_noise)`` and is turned by an extra yaw of ``yaw_drift_deg_per_m * step length + N(0,
yaw_noise_deg)`` about the vertical axis; errors accumulate, seeded. Defaults: 1.5 % scale bias,
0.5 % scale noise per step, 0.1 degree of yaw per metre plus 0.02 degree of noise per step.
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from evo.core import metrics, sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface
from scipy.spatial.transform import Rotation

from aefabmap_ros.errors import ConfigError, DataError

# Stamp association tolerance (s): closer than any frame interval we record (30 Hz = 33 ms).
DEFAULT_MAX_DIFF_S = 0.01


@dataclass(frozen=True)
class AteResult:
    rmse_m: float
    matched: int  # pose pairs associated by stamp
    aligned: PoseTrajectory3D  # the estimate after alignment (for plots)
    reference: PoseTrajectory3D  # the reference's associated poses


def read_tum(path: Path) -> PoseTrajectory3D:
    """A TUM trajectory file (``timestamp tx ty tz qx qy qz qw``); DataError naming the file when unreadable."""
    if not Path(path).is_file():
        raise DataError(f"trajectory file does not exist: {path}")
    try:
        trajectory = file_interface.read_tum_trajectory_file(str(path))
    except Exception as exc:  # evo raises its own FileInterfaceException and numpy's errors alike
        raise DataError(f"cannot read TUM trajectory {path}: {exc}") from exc
    problem = _trajectory_problem(trajectory.timestamps, trajectory.positions_xyz, trajectory.orientations_quat_wxyz)
    if problem is not None:  # evo reads them as they are; alignment then fails deep inside (SVD, Umeyama)
        raise DataError(f"TUM trajectory {path}: {problem}")
    return trajectory


def _trajectory_problem(stamps_s: np.ndarray, positions: np.ndarray, quaternions: np.ndarray) -> str | None:
    """Why a trajectory cannot be associated and aligned: non-finite values, a zero quaternion, or stamps not
    increasing; None when it can."""
    values = np.column_stack([stamps_s, positions, quaternions])
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        return f"pose {int(np.argmin(finite))} has non-finite values"
    zero = np.linalg.norm(quaternions, axis=1) < 1e-6
    if zero.any():
        return f"pose {int(np.argmax(zero))} has a zero quaternion"
    backwards = np.flatnonzero(np.diff(stamps_s) <= 0)
    if backwards.size:
        index = int(backwards[0]) + 1
        return (f"stamps must increase: pose {index} at {stamps_s[index]:.9f} s is not after pose {index - 1} at "
                f"{stamps_s[index - 1]:.9f} s")
    return None


def trajectory_from_matrices(stamps_s: np.ndarray, poses: np.ndarray) -> PoseTrajectory3D:
    """(N,) stamps and (N, 4, 4) (or (N, 3, 4)) poses -> an evo trajectory."""
    if poses.shape[1:] == (3, 4):
        poses = np.concatenate([poses, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(poses), 1, 1))], axis=1)
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=np.asarray(stamps_s, dtype=np.float64))


def absolute_trajectory_error(reference: PoseTrajectory3D, estimate: PoseTrajectory3D, correct_scale: bool = False,
                              max_diff_s: float = DEFAULT_MAX_DIFF_S) -> AteResult:
    """ATE RMSE (m) of ``estimate`` against ``reference`` after SE(3) (or, ``correct_scale``, Sim(3)) alignment."""
    try:
        ref, est = sync.associate_trajectories(reference, estimate, max_diff=max_diff_s)
    except sync.SyncException as exc:
        raise DataError(f"no poses of the two trajectories share a stamp (within {max_diff_s} s): {exc}") from exc
    if ref.num_poses < 3:
        raise DataError(f"only {ref.num_poses} poses matched by stamp: at least 3 are needed to align")
    aligned = copy.deepcopy(est)
    try:
        aligned.align(ref, correct_scale=correct_scale)
    except GeometryException as exc:  # e.g. every pose on one line: no rotation fits them uniquely
        raise DataError(f"the {ref.num_poses} poses matched by stamp cannot be aligned: {exc}") from exc
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    return AteResult(float(ape.get_statistic(metrics.StatisticsType.rmse)), ref.num_poses, aligned, ref)


def tum_text(stamps_s: np.ndarray, poses: np.ndarray) -> str:
    """TUM lines of (N,) stamps and (N, 3|4, 4) camera-to-world poses."""
    lines = []
    for stamp, pose in zip(stamps_s, poses, strict=True):
        qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
        tx, ty, tz = pose[:3, 3]
        lines.append(f"{stamp:.9f} {tx:.6f} {ty:.6f} {tz:.6f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}\n")
    return "".join(lines)


@dataclass(frozen=True)
class OdometryDrift:
    scale_bias: float = 0.015
    scale_noise: float = 0.005
    yaw_drift_deg_per_m: float = 0.1
    yaw_noise_deg: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        if self.scale_noise < 0 or self.yaw_noise_deg < 0 or self.scale_bias <= -1:
            raise ConfigError(f"odometry drift: noises must be >= 0 and scale_bias > -1, got {self}")


def drifting_odometry(poses: np.ndarray, up_in_body: np.ndarray, drift: OdometryDrift) -> np.ndarray:
    """(N, 4, 4) odometry poses from (N, 3|4, 4) ground-truth body-to-world poses, starting at the first.

    ``up_in_body``: the world's vertical axis as seen in the body frame (for a camera with y down,
    (0, -1, 0)); the yaw drift turns about it.
    """
    if poses.ndim != 3 or poses.shape[1:] not in ((3, 4), (4, 4)) or len(poses) == 0:
        raise DataError(f"poses must be (N, 3|4, 4), got {poses.shape}")
    full = np.tile(np.eye(4), (len(poses), 1, 1))
    full[:, :3, :] = poses[:, :3, :]
    rng = np.random.default_rng(drift.seed)
    up = np.asarray(up_in_body, dtype=np.float64) / np.linalg.norm(up_in_body)
    odometry = [full[0]]
    for before, after in itertools.pairwise(full):
        step = np.linalg.inv(before) @ after
        length = float(np.linalg.norm(step[:3, 3]))
        noisy = step.copy()
        noisy[:3, 3] *= 1.0 + drift.scale_bias + rng.normal(0.0, drift.scale_noise)
        yaw = np.radians(drift.yaw_drift_deg_per_m * length + rng.normal(0.0, drift.yaw_noise_deg))
        noisy[:3, :3] = Rotation.from_rotvec(yaw * up).as_matrix() @ step[:3, :3]
        odometry.append(odometry[-1] @ noisy)
    return np.stack(odometry)


def at_stamps(trajectory: PoseTrajectory3D, stamps_s: np.ndarray, max_diff_s: float = DEFAULT_MAX_DIFF_S
              ) -> PoseTrajectory3D:
    """The poses of ``trajectory`` whose stamps match one of ``stamps_s`` (within ``max_diff_s``): e.g. the
    odometry at a backend's keyframes, to compare both over the same poses."""
    wanted = np.sort(np.asarray(stamps_s, dtype=np.float64))
    if len(wanted) == 0:
        raise DataError("no stamps to select")
    index = np.clip(np.searchsorted(wanted, trajectory.timestamps), 1, len(wanted) - 1) if len(wanted) > 1 \
        else np.zeros(len(trajectory.timestamps), dtype=int)
    nearest = np.minimum(np.abs(trajectory.timestamps - wanted[index]),
                         np.abs(trajectory.timestamps - wanted[np.maximum(index - 1, 0)]))
    selected = copy.deepcopy(trajectory)
    selected.reduce_to_ids(np.flatnonzero(nearest <= max_diff_s))
    return selected
