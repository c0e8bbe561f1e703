"""The covariance of a relative pose, as LoopClosure's ``pose_covariance`` states it.

As a ``geometry_msgs/PoseWithCovariance`` in the query camera's frame: ROS order (x, y, z, rot x, rot y,
rot z), over errors along and about the query camera's axes, ``t_true = t + dt`` and
``R_true = Exp(dtheta) R``. It is the Gauss-Newton covariance ``sigma^2 (J^T J)^-1`` of the inliers'
residuals, with ``sigma`` their scatter but never below a floor (``min_pixel_sigma_px``): RANSAC kept only
matches within its threshold, so their scatter under-states how far a keypoint matched across a revisit's
viewpoint change is off, and that error is shared by many keypoints (a blob's centre shifts alike with the
view), which no scatter shows. Measured against the dense synthetic video's ground truth (docs/backend.md,
"pose_covariance"), the scatter alone put 48 % of the metric poses outside their covariance's 99.9 % region;
a 0.8 px floor puts 0.4-0.6 % there.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np


def gauss_newton_covariance(jacobian: np.ndarray, residuals: np.ndarray, parameters: int,
                            min_sigma: float) -> np.ndarray:
    """sigma^2 (J^T J)^+ with sigma^2 = |r|^2 / (n - p), at least ``min_sigma^2``: the covariance of a
    least-squares estimate whose residuals have that standard deviation."""
    dof = max(residuals.size - parameters, 1)
    sigma2 = max(float(residuals @ residuals) / dof, min_sigma ** 2)
    return sigma2 * np.linalg.pinv(jacobian.T @ jacobian)


def cross_matrices(vectors: np.ndarray) -> np.ndarray:
    """(M, 3, 3) matrices [v]x with [v]x w = v x w, one per row of ``vectors`` (M, 3)."""
    matrices = np.zeros((vectors.shape[0], 3, 3))
    matrices[:, 0, 1], matrices[:, 0, 2] = -vectors[:, 2], vectors[:, 1]
    matrices[:, 1, 0], matrices[:, 1, 2] = vectors[:, 2], -vectors[:, 0]
    matrices[:, 2, 0], matrices[:, 2, 1] = -vectors[:, 1], vectors[:, 0]
    return matrices


def pnp_covariance(objects: np.ndarray, images: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                   camera_matrix: np.ndarray, distortion: np.ndarray | None, min_sigma_px: float) -> np.ndarray:
    """Covariance (ROS order, errors in the query camera's axes) of the pose (rvec, tvec as OpenCV's) that
    maps the place points ``objects`` (M, 3) onto the query pixels ``images`` (M, 2)."""
    projected, jacobian = cv2.projectPoints(objects, rvec, tvec, camera_matrix, distortion)
    residuals = (projected.reshape(-1, 2) - images).reshape(-1)
    # A pixel moves with its point Y = R X + t in the query frame as it moves with t (cv2's d/dtvec); a
    # rotation dtheta about the query camera's axes moves Y by dtheta x (R X) = -[R X]x dtheta.
    by_translation = jacobian[:, 3:6].reshape(-1, 2, 3)
    rotated = objects @ cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0].T
    by_rotation = -by_translation @ cross_matrices(rotated)
    ros_jacobian = np.concatenate([by_translation, by_rotation], axis=2).reshape(-1, 6)
    return gauss_newton_covariance(ros_jacobian, residuals, 6, min_sigma_px)


def to_ros_order(covariance_rot_trans: np.ndarray) -> np.ndarray:
    """(rot, trans) ordered 6x6 -> ROS (trans, rot) order."""
    order = [3, 4, 5, 0, 1, 2]
    return np.ascontiguousarray(covariance_rot_trans[np.ix_(order, order)])


def numeric_jacobian(residual_fn: Callable[[np.ndarray], np.ndarray], parameters: np.ndarray,
                     step: float = 1e-6) -> np.ndarray:
    """Forward-difference Jacobian of ``residual_fn`` at ``parameters``."""
    base = residual_fn(parameters)
    jacobian = np.empty((base.size, parameters.size))
    for column in range(parameters.size):
        shifted = parameters.copy()
        shifted[column] += step
        jacobian[:, column] = (residual_fn(shifted) - base) / step
    return jacobian
