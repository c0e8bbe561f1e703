"""What the pose graph takes and gives: its configuration, a verified closure and what became of it, a
keyframe, and the name of the session (one run of a robot's front end) each belongs to.

Plain values, no graph: backend/pose_graph.py re-exports them with ``PoseGraph``, and the odometry gate
(backend/odometry_gate.py) shares the configuration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import gtsam
import numpy as np

from aefabmap_ros.errors import ConfigError

SessionId = tuple[str, int]  # (robot, session number); robot '' = the map's only robot
SINGLE_SESSION: SessionId = ("", 0)


class ClosureResult(Enum):
    ADDED = "added"
    WAITING = "waiting_for_odometry"  # its query is newer than the last odometry: retried when odometry comes
    UNKNOWN_STAMP = "unknown_stamp"  # an endpoint before the odometry buffer (or a dropped waiting closure)
    UNKNOWN_SESSION = "unknown_session"  # an endpoint in a session the graph never had (no odometry, not reloaded)
    NO_POSE = "no_pose"  # the closure carries no relative pose
    BAD_COVARIANCE = "bad_covariance"  # not a finite, symmetric positive semi-definite 6x6 (validation.py)
    INCONSISTENT = "inconsistent_with_odometry"  # further from the graph than odometry drift can explain
    SOLVER_FAILED = "solver_failed"  # iSAM2 could not take it, by Cholesky nor by QR: the graph is as before


@dataclass(frozen=True)
class PoseGraphConfig:
    odometry_translation_drift: float = field(default=0.02, metadata={
        "description": "Odometry translation error per metre travelled (standard deviation, fraction)."})
    odometry_rotation_drift_rad_per_m: float = field(default=0.005, metadata={
        "description": "Odometry rotation error per metre travelled (standard deviation, rad/m)."})
    odometry_min_sigma: float = field(default=0.01, metadata={
        "description": "Floor of the odometry factors' standard deviations (m and rad)."})
    loop_min_sigma_m: float = field(default=0.05, metadata={
        "description": "Added to every loop closure's position standard deviation (m): keeps a closure from "
                       "being over-confident."})
    loop_min_sigma_rad: float = field(default=0.01, metadata={
        "description": "Added to every loop closure's rotation standard deviation (rad)."})
    cauchy_scale: float = field(default=1.0, metadata={
        "description": "Scale of the Cauchy kernel on loop factors, in units of the disagreement odometry drift "
                       "can explain between the two keyframes."})
    gate_chi2: float = field(default=22.46, metadata={
        "description": "A closure whose residual against the graph exceeds this Mahalanobis distance squared "
                       "(6 dof; 22.46 = 99.9 %) under loop + odometry-drift covariance is refused."})
    max_odometry: int = field(default=200_000, metadata={
        "description": "Odometry samples kept for interpolation, per session (the odometry gate forgets the "
                       "oldest first; the pose graph halves a full session's sample rate, keeping its whole run)."})
    max_waiting: int = field(default=100, metadata={
        "description": "Closures waiting for odometry to reach their query stamp, at most."})

    def __post_init__(self) -> None:
        positive = ("odometry_translation_drift", "odometry_rotation_drift_rad_per_m", "odometry_min_sigma",
                    "loop_min_sigma_m", "loop_min_sigma_rad", "cauchy_scale", "gate_chi2")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"pose graph {name} must be > 0, got {getattr(self, name)}")
        if self.max_odometry < 2 or self.max_waiting < 1:
            raise ConfigError(f"pose graph max_odometry ({self.max_odometry}) must be >= 2 and "
                              f"max_waiting ({self.max_waiting}) >= 1")


@dataclass(frozen=True)
class Closure:
    """A verified loop closure: T_query_place (the place's base in the query's base frame) and its covariance
    over (x, y, z, rot x, rot y, rot z), as in LoopClosure.pose / pose_covariance; each endpoint in its
    (robot, session)."""

    query_ns: int
    place_ns: int
    query_to_place: gtsam.Pose3
    covariance: np.ndarray
    query_session: SessionId = SINGLE_SESSION
    place_session: SessionId = SINGLE_SESSION


@dataclass
class Keyframe:
    stamp_ns: int
    key: int
    odometry: gtsam.Pose3  # T_odom_base at the keyframe's stamp, in its session's odometry frame
    path_m: float  # odometry distance travelled at that stamp: odometry error grows with it
    session: SessionId = SINGLE_SESSION

