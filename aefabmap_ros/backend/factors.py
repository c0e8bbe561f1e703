"""The pose graph's factors: the record kept of each (what graph_file.py saves and iSAM2 is given), and the noise
the configuration gives odometry and loop closures.

A record, not gtsam's factor, is what the graph keeps: gtsam's factor is made from it whenever iSAM2 is
rebuilt, and a saved graph reloads the same factors even if the drift parameters changed since.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import gtsam
import numpy as np

from aefabmap_ros.backend.graph_types import Keyframe, PoseGraphConfig
from aefabmap_ros.backend.odometry import ros_to_gtsam_covariance
from aefabmap_ros.io.message_values import psd_part

# Standard deviation (m and rad) of the prior that holds a session's first keyframe.
PRIOR_SIGMA = 1e-6


class FactorKind(Enum):
    PRIOR = 0
    ODOMETRY = 1
    LOOP = 2


@dataclass(frozen=True)
class FactorRecord:
    """One factor as the graph keeps (and its file saves) it; gtsam's factor is made from it when needed.

    ``pose`` is the prior's pose, or a between factor's measured T_first_second; ``covariance`` is in gtsam's
    tangent order (rot, trans); a loop factor's Cauchy kernel has ``cauchy_scale`` (NaN for the others)."""

    kind: FactorKind
    first: int
    second: int  # a prior's: its own key again
    pose: gtsam.Pose3
    covariance: np.ndarray
    cauchy_scale: float = float("nan")

    def factor(self) -> gtsam.NonlinearFactor:
        covariance = np.asarray(self.covariance, dtype=np.float64)
        noise: gtsam.noiseModel.Base
        if self.kind is FactorKind.LOOP:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(self.cauchy_scale),
                                                   gtsam.noiseModel.Gaussian.Covariance(covariance))
        elif np.count_nonzero(covariance - np.diag(np.diag(covariance))) == 0:
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.diag(covariance)))
        else:
            noise = gtsam.noiseModel.Gaussian.Covariance(covariance)
        if self.kind is FactorKind.PRIOR:
            return gtsam.PriorFactorPose3(self.first, self.pose, noise)
        return gtsam.BetweenFactorPose3(self.first, self.second, self.pose, noise)


def drift_covariance(config: PoseGraphConfig, distance_m: float) -> np.ndarray:
    """Odometry error covariance (gtsam order: rot, trans) after travelling ``distance_m``."""
    sigma_t = max(config.odometry_translation_drift * distance_m, config.odometry_min_sigma)
    sigma_r = max(config.odometry_rotation_drift_rad_per_m * distance_m, config.odometry_min_sigma)
    return np.diag([sigma_r ** 2] * 3 + [sigma_t ** 2] * 3)


def loop_factor_covariance(config: PoseGraphConfig, covariance_ros: np.ndarray) -> np.ndarray:
    """A closure's covariance (ROS order x y z rot) in gtsam order, with the configured floor added.

    The covariance is one ``message_values.covariance_problem`` accepted: its round-off's negative
    eigenvalues are cut to 0 first (``psd_part``), so with the floor it is positive definite."""
    return ros_to_gtsam_covariance(psd_part(covariance_ros)) + np.diag(
        [config.loop_min_sigma_rad ** 2] * 3 + [config.loop_min_sigma_m ** 2] * 3)


def prior_record(key: int, pose: gtsam.Pose3) -> FactorRecord:
    """The tight prior that holds a graph's first keyframe where it is."""
    return FactorRecord(FactorKind.PRIOR, key, key, pose, np.eye(6) * PRIOR_SIGMA ** 2)


def odometry_record(config: PoseGraphConfig, first: Keyframe, second: Keyframe) -> FactorRecord:
    """The odometry factor between two keyframes of one session, its noise grown with the distance travelled."""
    relative = first.odometry.between(second.odometry)
    # Travelled, not the straight line: a loop ends near its start.
    covariance = drift_covariance(config, abs(second.path_m - first.path_m))
    return FactorRecord(FactorKind.ODOMETRY, first.key, second.key, relative, covariance)
