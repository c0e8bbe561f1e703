"""A measured relative pose against the ground truth's (the demo's and the recordings' pose scores)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class PoseError:
    """A measured relative pose against the ground truth's."""

    rotation_deg: float  # angle of R_true^T R_measured
    direction_deg: float  # angle between the translations (NaN when the true one is shorter than 1 mm)
    translation_m: float  # |t_measured - t_true| (meaningful for a metric pose only)
    # The error's Mahalanobis distance squared (6 dof) under the pose's covariance; NaN without one.
    mahalanobis2: float = float("nan")


# A pose whose error's Mahalanobis distance squared under its own covariance exceeds this lies outside the
# covariance's 99.9 % region (chi-square, 6 dof): a backend trusting that covariance is misled by it.
OUTSIDE_COVARIANCE_CHI2 = 22.46


def error_mahalanobis2(truth: np.ndarray, measured: np.ndarray, covariance: np.ndarray) -> float:
    """Mahalanobis distance squared of ``measured``'s error (4x4 poses) under ``covariance`` (6x6, LoopClosure's
    convention: ROS order, errors in the axes of the frame the poses are given in, t + dt and Exp(dtheta) R);
    NaN when the covariance is singular or not finite."""
    rotation = Rotation.from_matrix(measured[:3, :3] @ truth[:3, :3].T).as_rotvec()
    error = np.concatenate([measured[:3, 3] - truth[:3, 3], rotation])
    covariance = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
    if not np.isfinite(covariance).all():
        return float("nan")
    try:
        return float(error @ np.linalg.solve(covariance, error))
    except np.linalg.LinAlgError:
        return float("nan")


def relative_pose_error(query_to_world: np.ndarray, place_to_world: np.ndarray, measured: np.ndarray,
                        covariance: np.ndarray | None = None) -> PoseError:
    """Error of a measured place-in-query pose (4x4, ``X_query = R X_place + t``) given both cameras'
    ground-truth camera-to-world poses ((3|4, 4)); with the pose's ``covariance`` (metric poses: a monocular
    one's variance along its unit translation says "unobserved"), the error's Mahalanobis distance squared."""
    def full(pose: np.ndarray) -> np.ndarray:
        matrix = np.eye(4)
        matrix[:3, :] = np.asarray(pose, dtype=np.float64)[:3, :]
        return matrix

    truth = np.linalg.inv(full(query_to_world)) @ full(place_to_world)
    estimate = full(measured)
    rotation = np.degrees(np.linalg.norm(Rotation.from_matrix(truth[:3, :3].T @ estimate[:3, :3]).as_rotvec()))
    true_t, measured_t = truth[:3, 3], estimate[:3, 3]
    lengths = np.linalg.norm(true_t) * np.linalg.norm(measured_t)
    direction = (float(np.degrees(np.arccos(np.clip(true_t @ measured_t / lengths, -1.0, 1.0))))
                 if np.linalg.norm(true_t) > 1e-3 and lengths > 0 else float("nan"))
    mahalanobis2 = float("nan") if covariance is None else error_mahalanobis2(truth, estimate, covariance)
    return PoseError(float(rotation), direction, float(np.linalg.norm(measured_t - true_t)), mahalanobis2)
