"""Each recorded closure listed: its relative pose's error against a hand-made pose truth, the nearest pose
within 10 ms, and closures.csv against hand-computed rows."""

import csv
import io

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.evaluation.closure_listing import (
    CSV_COLUMNS,
    PoseTruth,
    closure_listing_markdown,
    closure_pose_error,
    closures_csv,
    read_pose_truth,
)
from aefabmap_ros.evaluation.closure_scores import (
    closure_scores_markdown,
    closure_scores_to_dict,
    score_recorded_closures,
)
from aefabmap_ros.evaluation.trajectory_error import tum_text
from test.evaluation.test_recordings import closure, frame_stamp, frames_of, posterior


def transform(rotation_deg_about_y, translation):
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("y", rotation_deg_about_y, degrees=True).as_matrix()
    matrix[:3, 3] = translation
    return matrix


# Ground truth: frame 0 somewhere, turned about z; frame 12 (a revisit of frame 0) 2 m ahead of it along its
# optical axis (z), turned 30 degrees about its y axis. T_q_m (frame 0 in frame 12's camera) = inv(T_12) T_0.
CAMERA_0 = transform(0, [5.0, 1.0, 0.0])
CAMERA_0[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
CAMERA_12 = CAMERA_0 @ transform(30, [0.0, 0.0, 2.0])
TRUE_T_Q_M = np.linalg.inv(CAMERA_12) @ CAMERA_0


def pose_truth_file(tmp_path):
    """groundtruth.tum of frames 0..12: every frame at CAMERA_0 but frame 12."""
    poses = np.array([CAMERA_12 if i == 12 else CAMERA_0 for i in range(13)])
    path = tmp_path / "groundtruth.tum"
    path.write_text(tum_text(np.array([frame_stamp(i) for i in range(13)]) / 1e9, poses))
    return path


# The covariance of the pose 0.3 m off along the query camera's x and 10 degrees off: 0.3 m along x, 1 cm along
# y and z, 10 degrees about every axis.
OFF_COVARIANCE = np.diag([0.3 ** 2, 0.01 ** 2, 0.01 ** 2] + [np.radians(10.0) ** 2] * 3)


def test_the_pose_error_of_a_closure_against_a_hand_made_pair(tmp_path):
    truth = read_pose_truth(pose_truth_file(tmp_path))
    exact = closure(12, 0, pose=TRUE_T_Q_M, metric=True)
    error = closure_pose_error(exact, truth)
    assert error is not None
    assert (error.rotation_deg, error.translation_m, error.direction_deg) == pytest.approx((0, 0, 0), abs=1e-4)
    # 10 degrees more about y and 0.3 m off along the query camera's x axis.
    off = TRUE_T_Q_M.copy()
    off[:3, :3] = off[:3, :3] @ Rotation.from_euler("y", 10, degrees=True).as_matrix()
    off[:3, 3] += [0.3, 0.0, 0.0]
    error = closure_pose_error(closure(12, 0, pose=off, metric=True, covariance=OFF_COVARIANCE), truth)
    assert error is not None
    assert error.rotation_deg == pytest.approx(10.0, abs=1e-4) and error.translation_m == pytest.approx(0.3, abs=1e-5)
    # One standard deviation along the query camera's x and 10 degrees of rotation: 1 + 1. Read in the place
    # camera's axes (30 degrees turned), the 0.3 m would put 0.15 m along a 1 cm axis.
    assert error.mahalanobis2 == pytest.approx(2.0, abs=1e-6)
    true_t = TRUE_T_Q_M[:3, 3]
    cosine = true_t @ off[:3, 3] / np.linalg.norm(true_t) / np.linalg.norm(off[:3, 3])
    expected_direction = np.degrees(np.arccos(cosine))
    assert error.direction_deg == pytest.approx(expected_direction, abs=1e-4)
    # The inverse convention (the query in the place's frame) is far off: the test sees the convention.
    inverse = closure_pose_error(closure(12, 0, pose=np.linalg.inv(TRUE_T_Q_M), metric=True), truth)
    assert inverse is not None and inverse.translation_m > 1.0
    assert closure_pose_error(closure(12, 0), truth) is None  # no pose
    assert closure_pose_error(closure(12, 0, pose=off, matched_stamp=frame_stamp(0) - 10**9), truth) is None


def test_pose_truth_takes_the_nearest_pose_within_10_ms():
    truth = PoseTruth(np.array([0, 100_000_000]), np.stack([np.eye(4), 2 * np.eye(4)]), "t")
    near = truth.pose_at(90_000_000)
    assert near is not None and near[0, 0] == 2.0
    assert truth.pose_at(50_000_000) is None and truth.pose_at(-10_000_001) is None


def test_closures_csv_against_hand_computed_truth(tmp_path):
    truth = read_pose_truth(pose_truth_file(tmp_path))
    gt = np.zeros((13, 13), np.uint8)
    gt[12, 0] = gt[11, 0] = 1
    off = TRUE_T_Q_M.copy()
    off[:3, :3] = off[:3, :3] @ Rotation.from_euler("y", 10, degrees=True).as_matrix()
    off[:3, 3] += [0.3, 0.0, 0.0]
    monocular = TRUE_T_Q_M.copy()
    monocular[:3, 3] /= np.linalg.norm(monocular[:3, 3])
    closures = [closure(12, 0, 0.995, inliers=80, pose=off, metric=True,   # true, its pose wrong
                        covariance=OFF_COVARIANCE),
                closure(12, 0, 0.99, inliers=60, pose=monocular),            # true, a right monocular pose
                closure(11, 1, 0.98, inliers=40)]                           # false, no pose
    posteriors = [posterior(i, [], []) for i in range(13)]
    row = score_recorded_closures("published", "loop_closures", closures, posteriors, gt, frames_of(13), 10,
                                  pose_truth=truth)
    lines = list(csv.DictReader(io.StringIO(closures_csv(row.rows))))
    assert list(lines[0]) == list(CSV_COLUMNS) and len(lines) == 3
    first, second, third = lines
    assert {k: first[k] for k in ("topic", "query_stamp", "query_frame", "matched_stamp", "matched_frame",
                                  "probability", "inliers", "true", "gt", "pose_available", "translation_metric",
                                  "pose_wrong")} == {
        "topic": "loop_closures", "query_stamp": "1700000001.200000000", "query_frame": "12",
        "matched_stamp": "1700000000.000000000", "matched_frame": "0", "probability": "0.995", "inliers": "80",
        "true": "1", "gt": "1", "pose_available": "1", "translation_metric": "1", "pose_wrong": "1"}
    assert float(first["rotation_error_deg"]) == pytest.approx(10.0, abs=1e-5)
    assert float(first["translation_error_m"]) == pytest.approx(0.3, abs=1e-5)
    assert [float(first[k]) for k in ("x", "y", "z")] == pytest.approx(off[:3, 3].tolist(), abs=1e-7)
    assert float(first["pose_error_mahalanobis2"]) == pytest.approx(2.0, abs=1e-5)
    assert second["translation_metric"] == "0" and second["translation_error_m"] == ""  # a direction only
    assert second["pose_error_mahalanobis2"] == ""
    assert float(second["direction_error_deg"]) == pytest.approx(0.0, abs=1e-4) and second["pose_wrong"] == "0"
    assert (third["query_frame"], third["matched_frame"], third["true"], third["gt"]) == ("11", "1", "0", "0")
    assert third["pose_available"] == "0" and third["x"] == third["rotation_error_deg"] == third["pose_wrong"] == ""
    assert (row.num_wrong_poses, row.num_poses_checked) == (1, 2)
    assert closure_scores_markdown([row]).splitlines()[-1].endswith("| 1 / 2 | 0 / 1 |")
    assert closure_scores_to_dict(row)["wrong_poses"] == 1
    assert (closure_scores_to_dict(row)["poses_outside_covariance"], row.num_covariance_checked) == (0, 1)
    listing = closure_listing_markdown(list(row.rows), pose_truth_given=True)
    assert "| `loop_closures` | 11 | 1700000001.100000000 | 1 | 1700000000.100000000 | 0.9800 | 40 |  |  |" in listing
    assert ("| `loop_closures` | 12 | 1700000001.200000000 | 0 | 1700000000.000000000 | 0.9950 | 80 | 10.00 "
            "| 0.300 m |") in listing
