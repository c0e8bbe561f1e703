"""Relative pose against a synthetic two-view scene with known geometry (monocular and with depth)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.verification.relative_pose import (
    UNKNOWN_SCALE_VARIANCE,
    CameraModel,
    KeypointDepthStore,
    PoseStatus,
    RelativePoseConfig,
    depth_image_to_metres,
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


def test_depth_images_in_both_encodings() -> None:
    millimetres = np.array([[0, 1500], [2000, 65535]], dtype=np.uint16)
    np.testing.assert_allclose(depth_image_to_metres(millimetres, "16UC1"), [[np.nan, 1.5], [2.0, 65.535]])
    metres = np.array([[np.nan, 1.5], [-1.0, np.inf]], dtype=np.float32)
    np.testing.assert_allclose(depth_image_to_metres(metres, "32FC1"), [[np.nan, 1.5], [np.nan, np.nan]])
    with pytest.raises(DataError):
        depth_image_to_metres(millimetres, "rgb8")


def test_keypoint_depths_arrive_in_either_order_and_stay_bounded() -> None:
    depth = np.arange(12, dtype=np.float32).reshape(3, 4)
    keypoints = np.array([[1.0, 2.0], [3.2, 0.4], [9.0, 9.0]], dtype=np.float32)
    store = KeypointDepthStore(max_frames=2)
    store.add_depth(10, depth)
    store.add_features(10, keypoints)
    store.add_features(20, keypoints)
    assert store.get(20) is None
    store.add_depth(20, depth + 100)
    first, second = store.get(10), store.get(20)
    assert first is not None and second is not None
    np.testing.assert_allclose(first, np.array([9.0, 3.0, np.nan]))  # (row 2, col 1), (row 0, col 3), outside
    np.testing.assert_allclose(second, np.array([109.0, 103.0, np.nan]))
    store.add_depth(30, depth)
    store.add_features(30, keypoints)
    assert len(store) == 2 and store.get(10) is None


def test_relative_pose_error_against_a_known_pair() -> None:
    """Query at the origin, place 2 m along x turned 10 degrees about y; a measurement 1 degree and 5 cm off."""
    from scipy.spatial.transform import Rotation

    from aefabmap_ros.verification.relative_pose import relative_pose_error

    query = np.eye(4)[:3]
    place = np.eye(4)
    place[:3, :3] = Rotation.from_euler("y", 10, degrees=True).as_matrix()
    place[:3, 3] = [2.0, 0.0, 0.0]
    measured = place.copy()
    measured[:3, :3] = Rotation.from_euler("y", 11, degrees=True).as_matrix()
    measured[:3, 3] = [2.0, 0.05, 0.0]
    error = relative_pose_error(query, place[:3], measured)
    assert error.rotation_deg == pytest.approx(1.0, abs=1e-6)
    assert error.direction_deg == pytest.approx(np.degrees(np.arctan2(0.05, 2.0)), abs=1e-6)
    assert error.translation_m == pytest.approx(0.05, abs=1e-9)
    # A monocular (unit) translation along the true direction has no direction error.
    unit = place.copy()
    unit[:3, 3] = [1.0, 0.0, 0.0]
    assert relative_pose_error(query, place, unit).direction_deg == pytest.approx(0.0, abs=1e-6)


def test_keypoint_depths_survive_a_restart_through_the_folder(tmp_path: Path) -> None:
    from aefabmap_ros.verification.relative_pose import KeypointDepthFolder, KeypointDepthStore

    store = KeypointDepthStore(max_frames=2)
    folder = KeypointDepthFolder(tmp_path)
    depth_image = np.arange(100, dtype=np.float32).reshape(10, 10)
    store.add_features(1, np.array([[1.0, 2.0], [3.0, 4.0]], np.float32))
    store.add_depth(1, depth_image)
    folder.save(store)
    store.add_depth(2, depth_image)
    store.add_features(2, np.array([[5.0, 5.0]], np.float32))
    folder.save(store)
    folder.save(store)  # nothing new: no empty chunk
    assert sorted(p.name for p in tmp_path.glob("depth-*.npz")) == ["depth-000000000.npz", "depth-000000001.npz"]

    reloaded = KeypointDepthStore(max_frames=2)
    KeypointDepthFolder(tmp_path).load_into(reloaded)
    first, second = reloaded.get(1), reloaded.get(2)
    assert first is not None and second is not None
    assert first.tolist() == [21.0, 43.0] and second.tolist() == [55.0]
    assert reloaded.unsaved() == []  # reloaded frames count as saved

    # Two more frames push frames 1 and 2 out: their chunks are deleted at the next save.
    later = KeypointDepthFolder(tmp_path)
    later.load_into(reloaded)
    for stamp in (3, 4):
        reloaded.add_depth(stamp, depth_image)
        reloaded.add_features(stamp, np.array([[0.0, 0.0]], np.float32))
    later.save(reloaded)
    assert sorted(p.name for p in tmp_path.glob("depth-*.npz")) == ["depth-000000002.npz"]


def test_a_corrupt_keypoint_depth_chunk_is_named(tmp_path: Path) -> None:
    from aefabmap_ros.errors import ModelError
    from aefabmap_ros.io.npz_files import write_npz_atomically
    from aefabmap_ros.verification.relative_pose import DEPTH_FORMAT_VERSION, KeypointDepthFolder, KeypointDepthStore

    write_npz_atomically(tmp_path / "depth-000000000.npz", {
        "format_version": np.array(DEPTH_FORMAT_VERSION), "stamps_ns": np.array([1, 2]),
        "counts": np.array([2, 2]), "depths": np.zeros(3, np.float32)})
    with pytest.raises(ModelError, match=r"depth-000000000\.npz"):
        KeypointDepthFolder(tmp_path).load_into(KeypointDepthStore(max_frames=2))
