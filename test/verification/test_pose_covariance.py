"""The published pose covariance against the spread of poses of a scene with known geometry (Monte Carlo)."""

from __future__ import annotations

import cv2
import numpy as np

from aefabmap_ros.verification.relative_pose import RelativePose, RelativePoseConfig, pnp_pose
from test.verification.test_relative_pose import CAMERA, project, rotation_about


def loop_closure_error(pose: RelativePose, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """The pose's error as LoopClosure's covariance states it: ROS order, in the query camera's axes
    (t = t_true + dt, R = Exp(dtheta) R_true)."""
    dtheta = cv2.Rodrigues(pose.rotation @ rotation.T)[0].reshape(3)
    return np.concatenate([pose.translation - translation, dtheta])


def scene_with_depth(seed: int, count: int = 120) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(place points, query points, R, t): a 40-degree turn about a tilted axis and 1.8 m apart, so that the
    covariance's axes (the query camera's) and a rotation vector's differ."""
    rng = np.random.default_rng(seed)
    place = np.column_stack([rng.uniform(-3, 3, count), rng.uniform(-2, 2, count), rng.uniform(3, 9, count)])
    rotation, translation = rotation_about([0.3, 1.0, 0.2], 40.0), np.array([1.5, -0.3, 0.8])
    query = place @ rotation.T + translation
    keep = (query[:, 2] > 0.5) & np.all((project(query) > 0) & (project(query) < [640, 480]), axis=1)
    return place[keep], query[keep], rotation, translation


def test_metric_covariance_matches_the_spread_of_its_poses() -> None:
    """Query keypoints with 0.7 px noise, 400 draws: each pose's error, under its own covariance (floor off),
    has the Mahalanobis distance squared of a 6-dof chi-square (mean 6; rotation and translation 3 each)."""
    place, query, rotation, translation = scene_with_depth(seed=0)
    config = RelativePoseConfig(ransac_threshold_px=4.0, min_pixel_sigma_px=0.0)
    rng = np.random.default_rng(1)
    full, rotation_part, translation_part = [], [], []
    for _ in range(400):
        noisy = project(query) + rng.normal(0.0, 0.7, (len(query), 2))
        pose = pnp_pose(noisy, project(place), place[:, 2], CAMERA, config).pose
        assert pose is not None and pose.metric
        error, covariance = loop_closure_error(pose, rotation, translation), pose.covariance
        full.append(error @ np.linalg.solve(covariance, error))
        translation_part.append(error[:3] @ np.linalg.solve(covariance[:3, :3], error[:3]))
        rotation_part.append(error[3:] @ np.linalg.solve(covariance[3:, 3:], error[3:]))
    assert 5.3 <= np.mean(full) <= 6.8
    assert 2.6 <= np.mean(translation_part) <= 3.45 and 2.6 <= np.mean(rotation_part) <= 3.45


def test_metric_covariance_keeps_the_pixel_floor_for_exact_matches() -> None:
    """Exact matches fit with zero residual, yet the pose states min_pixel_sigma_px of keypoint error: poses
    from matches with that much noise fall within that covariance as a 6-dof chi-square says (mean 6)."""
    place, query, rotation, translation = scene_with_depth(seed=2)
    config = RelativePoseConfig(ransac_threshold_px=4.0, min_pixel_sigma_px=0.8)
    exact = pnp_pose(project(query), project(place), place[:, 2], CAMERA, config).pose
    unfloored = pnp_pose(project(query), project(place), place[:, 2], CAMERA,
                         RelativePoseConfig(ransac_threshold_px=4.0, min_pixel_sigma_px=0.0)).pose
    assert exact is not None and unfloored is not None
    assert np.trace(unfloored.covariance) < 1e-12 < np.trace(exact.covariance)  # without the floor: "certain"
    rng = np.random.default_rng(3)
    distances = []
    for _ in range(400):
        noisy = project(query) + rng.normal(0.0, 0.8, (len(query), 2))
        pose = pnp_pose(noisy, project(place), place[:, 2], CAMERA, config).pose
        assert pose is not None
        error = loop_closure_error(pose, rotation, translation)
        distances.append(error @ np.linalg.solve(exact.covariance, error))
    assert 5.3 <= np.mean(distances) <= 6.8
