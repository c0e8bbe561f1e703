"""Relative pose against a synthetic two-view scene with known geometry (monocular and with depth)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.verification.relative_pose import (
    UNKNOWN_SCALE_VARIANCE,
    CameraModel,
    PoseOutcome,
    PoseStatus,
    RelativePoseConfig,
    essential_pose,
    pnp_pose,
    relative_pose,
)

CAMERA = CameraModel(np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]]))
CONFIG = RelativePoseConfig()


def rotation_about(axis: list[float], degrees: float) -> np.ndarray:
    vector = np.radians(degrees) * np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return cv2.Rodrigues(vector)[0]


def project(points: np.ndarray) -> np.ndarray:
    pixels = points @ CAMERA.matrix.T
    return pixels[:, :2] / pixels[:, 2:3]


def two_views(rotation: np.ndarray, translation: np.ndarray, seed: int, count: int = 200,
              noise_px: float = 0.5, outliers: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(query pixels, place pixels, place depths) of random points 2-8 m in front of the place camera,
    seen by a query camera with X_query = R X_place + t; a share of the query pixels are random (wrong matches)."""
    rng = np.random.default_rng(seed)
    place_points = np.column_stack([rng.uniform(-3, 3, count), rng.uniform(-2, 2, count), rng.uniform(2, 8, count)])
    query_points = place_points @ rotation.T + translation
    place_px = project(place_points) + rng.normal(0, noise_px, (count, 2))
    query_px = project(query_points) + rng.normal(0, noise_px, (count, 2))
    wrong = rng.random(count) < outliers
    query_px[wrong] = rng.uniform([0, 0], [640, 480], (int(wrong.sum()), 2))
    return query_px.astype(np.float32), place_px.astype(np.float32), place_points[:, 2]


def rotation_error_deg(estimated: np.ndarray, truth: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(estimated @ truth.T)[0])))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


SCENES = [(rotation_about([0, 1, 0], 12.0), np.array([0.4, 0.05, 0.1])),
          (rotation_about([1, 0.2, 0], -8.0), np.array([-0.3, 0.1, 0.5])),
          (rotation_about([0.1, 1, 0.3], 25.0), np.array([1.0, -0.2, -0.3]))]


def test_monocular_pose_recovers_rotation_and_translation_direction() -> None:
    rotation_errors, direction_errors = [], []
    for seed in range(5):
        for rotation, translation in SCENES:
            query_px, place_px, _ = two_views(rotation, translation, seed)
            outcome = relative_pose(query_px, place_px, CAMERA, CONFIG)
            assert outcome.status is PoseStatus.OK and outcome.pose is not None
            assert not outcome.pose.metric
            assert np.linalg.norm(outcome.pose.translation) == pytest.approx(1.0)
            rotation_errors.append(rotation_error_deg(outcome.pose.rotation, rotation))
            direction_errors.append(angle_deg(outcome.pose.translation, translation))
    assert np.median(rotation_errors) <= 1.0
    assert np.median(direction_errors) <= 3.0


def test_monocular_covariance_marks_the_scale_unobserved() -> None:
    rotation, translation = SCENES[0]
    query_px, place_px, _ = two_views(rotation, translation, seed=1)
    pose = essential_pose(query_px, place_px, CAMERA, CONFIG).pose
    assert pose is not None
    along = pose.translation @ pose.covariance[:3, :3] @ pose.translation
    assert along >= UNKNOWN_SCALE_VARIANCE
    assert np.all(np.diag(pose.covariance)[3:] > 0) and np.all(np.diag(pose.covariance)[3:] < 1e-3)
    np.testing.assert_allclose(pose.covariance, pose.covariance.T, atol=1e-9)


def test_pose_with_depth_is_metric() -> None:
    rotation_errors, translation_errors = [], []
    for seed in range(5):
        for rotation, translation in SCENES:
            query_px, place_px, depths = two_views(rotation, translation, seed)
            depths = depths * (1 + np.random.default_rng(seed).normal(0, 0.01, depths.size))  # 1 % depth noise
            outcome = relative_pose(query_px, place_px, CAMERA, CONFIG, place_depths_m=depths)
            assert outcome.status is PoseStatus.OK and outcome.pose is not None
            assert outcome.pose.metric
            rotation_errors.append(rotation_error_deg(outcome.pose.rotation, rotation))
            translation_errors.append(float(np.linalg.norm(outcome.pose.translation - translation)))
            # Position standard deviations of centimetres, not of metres nor zero.
            assert np.all(np.sqrt(np.diag(outcome.pose.covariance)[:3]) < 0.1)
            assert np.all(np.diag(outcome.pose.covariance) > 0)
    assert np.median(rotation_errors) <= 1.0
    assert np.median(translation_errors) <= 0.05


def test_too_few_points_give_no_pose() -> None:
    rotation, translation = SCENES[0]
    query_px, place_px, depths = two_views(rotation, translation, seed=3, count=7, outliers=0.0)
    assert relative_pose(query_px, place_px, CAMERA, CONFIG).status is PoseStatus.TOO_FEW_POINTS
    assert pnp_pose(query_px, place_px, depths, CAMERA, CONFIG).status is PoseStatus.TOO_FEW_POINTS


def test_too_few_points_with_depth_falls_back_to_the_direction() -> None:
    rotation, translation = SCENES[0]
    query_px, place_px, depths = two_views(rotation, translation, seed=3)
    depths[5:] = np.nan  # only five matches with depth: no PnP
    assert pnp_pose(query_px, place_px, depths, CAMERA, CONFIG).status is PoseStatus.TOO_FEW_POINTS
    outcome = relative_pose(query_px, place_px, CAMERA, CONFIG, place_depths_m=depths)
    assert outcome.pose is not None and not outcome.pose.metric


def test_pure_rotation_gives_no_monocular_pose() -> None:
    query_px, place_px, _ = two_views(rotation_about([0, 1, 0.1], 10.0), np.zeros(3), seed=4)
    outcome = essential_pose(query_px, place_px, CAMERA, CONFIG)
    assert outcome.pose is None
    assert outcome.status is PoseStatus.PURE_ROTATION


def test_all_wrong_matches_give_no_pose() -> None:
    rng = np.random.default_rng(5)
    query_px = rng.uniform([0, 0], [640, 480], (100, 2)).astype(np.float32)
    place_px = rng.uniform([0, 0], [640, 480], (100, 2)).astype(np.float32)
    assert relative_pose(query_px, place_px, CAMERA, CONFIG).pose is None
    assert relative_pose(query_px, place_px, CAMERA, CONFIG, place_depths_m=rng.uniform(1, 5, 100)).pose is None


def test_no_camera_gives_no_pose() -> None:
    rotation, translation = SCENES[0]
    query_px, place_px, _ = two_views(rotation, translation, seed=0)
    assert relative_pose(query_px, place_px, None, CONFIG).status is PoseStatus.NO_CAMERA_INFO


def test_bad_input_is_refused() -> None:
    with pytest.raises(DataError):
        essential_pose(np.zeros((10, 2)), np.zeros((9, 2)), CAMERA, CONFIG)
    with pytest.raises(DataError):
        pnp_pose(np.zeros((10, 2)), np.zeros((10, 2)), np.ones(9), CAMERA, CONFIG)
    with pytest.raises(DataError):
        CameraModel(np.zeros((3, 3)))
    with pytest.raises(ConfigError):
        RelativePoseConfig(min_inliers=3)


@pytest.mark.parametrize("threshold_px", [2.0, 1.0])  # the metric test's, the published pose's
@pytest.mark.parametrize("seed", range(4))
def test_a_far_facade_gets_its_pose_from_the_query_depths(seed: int, threshold_px: float) -> None:
    """A facade 35 m away (12 x 6 m, nearly planar) seen again from 15 m further back and 10 degrees turned,
    keypoints with 0.5 px noise: PnP's reprojection cannot tell its two solutions apart (its pose is degrees
    and metres off), the query's depths can (the dense synthetic video's streets seen from further back)."""
    rng = np.random.default_rng(seed)
    place = np.column_stack([rng.uniform(-6, 6, 40), rng.uniform(-3, 3, 40), 35.0 + rng.normal(0, 0.05, 40)])
    rotation = rotation_about([0.0, 1.0, 0.0], 10.0)
    centre = np.array([1.0, 0.0, -15.0])  # the query camera in the place's frame
    query = (place - centre) @ rotation  # R^T (X - c): X_query = R^T X_place - R^T c
    true_rotation, true_translation = rotation.T, -rotation.T @ centre
    noisy = [project(points) + rng.normal(0, 0.5, (40, 2)) for points in (query, place)]
    config = RelativePoseConfig(ransac_threshold_px=threshold_px)

    def error(outcome: PoseOutcome) -> tuple[float, float]:
        assert outcome.pose is not None and outcome.pose.metric
        return (rotation_error_deg(outcome.pose.rotation, true_rotation),
                float(np.linalg.norm(outcome.pose.translation - true_translation)))

    reprojection_only = error(pnp_pose(noisy[0], noisy[1], place[:, 2], CAMERA, config))
    with_depths = error(pnp_pose(noisy[0], noisy[1], place[:, 2], CAMERA, config, query[:, 2]))
    assert reprojection_only[0] > 1.0 and reprojection_only[1] > 0.5  # the case this is about
    assert with_depths[0] < 0.7 and with_depths[1] < 0.2
    # Depths that fit no motion (a broken depth image) change nothing: PnP's own solution stays.
    broken = rng.uniform(5.0, 60.0, 40)
    assert error(pnp_pose(noisy[0], noisy[1], place[:, 2], CAMERA, config, broken)) == reprojection_only


def test_camera_info_to_intrinsics() -> None:
    """None for an uncalibrated camera (fx 0); DataError, naming it, for what cannot be intrinsics."""
    from types import SimpleNamespace

    from aefabmap_ros.verification.relative_pose import camera_info_to_model

    k = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0]
    camera = camera_info_to_model(SimpleNamespace(k=k, d=[0.1, 0.0, 0.0, 0.0, 0.0]))
    assert camera is not None and camera.matrix[0, 0] == 500.0
    assert camera_info_to_model(SimpleNamespace(k=[0.0] * 9, d=[])) is None
    for k_values, d_values, expected in (
        (k[:8], [], "K has 8 values, not 9"),
        ([-500.0, *k[1:]], [], "positive focal lengths"),
        ([float("nan"), *k[1:]], [], "positive focal lengths"),
        (k, [0.1, float("inf")], "distortion coefficients must be finite"),
    ):
        with pytest.raises(DataError, match=expected):
            camera_info_to_model(SimpleNamespace(k=k_values, d=d_values))
