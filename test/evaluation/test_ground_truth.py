"""Ground-truth loop matrices from poses, checked against brute-force double loops and KITTI 00; KITTI pose
files and loop-matrix .npz files."""

import math

import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.evaluation.ground_truth import (
    load_gt_npz,
    loop_matrix_from_kitti,
    loop_matrix_from_poses,
    positions_and_axes,
    read_kitti_poses,
    write_kitti_poses,
)


def _random_walk(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    positions = rng.uniform(0, 10, size=(n, 3))
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return positions, axes


def _brute_force(positions, axes, distance, angle_deg, gap):
    n = len(positions)
    gt = np.zeros((n, n), dtype=np.uint8)
    for i in range(n):
        for j in range(i - gap + 1):
            close = math.dist(positions[i], positions[j]) <= distance
            angle = math.degrees(math.acos(max(-1.0, min(1.0, float(np.dot(axes[i], axes[j]))))))
            if close and angle <= angle_deg:
                gt[i, j] = 1
    return gt


@pytest.mark.parametrize(("distance", "angle", "gap"), [(3.0, 60.0, 5), (2.0, 180.0, 1), (5.0, 20.0, 30)])
def test_matches_brute_force(distance, angle, gap):
    positions, axes = _random_walk(150, seed=int(distance * 10 + gap))
    gt = loop_matrix_from_poses(positions, axes, distance, angle, gap)
    reference = _brute_force(positions, axes, distance, angle, gap)
    assert gt.dtype == np.uint8
    assert gt.shape == (150, 150)
    assert reference.sum() > 0
    np.testing.assert_array_equal(gt, reference)
    assert not np.triu(gt).any()


def test_angle_excludes_opposite_direction():
    positions = np.zeros((40, 3))
    axes = np.tile([1.0, 0.0, 0.0], (40, 1))
    axes[20:] = [-1.0, 0.0, 0.0]
    gt = loop_matrix_from_poses(positions, axes, 1.0, 30.0, 10)
    assert gt[:20].sum() == sum(max(0, i - 9) for i in range(20))
    assert gt[30, 20] == 1 and gt[30, 5] == 0


def test_single_frame_and_empty():
    assert loop_matrix_from_poses(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), 1, 10, 1).shape == (1, 1)
    assert loop_matrix_from_poses(np.zeros((0, 3)), np.zeros((0, 3)), 1, 10, 1).shape == (0, 0)


def test_kitti_first300_has_no_loops(kitti_dir):
    gt = loop_matrix_from_kitti(kitti_dir / "poses_00_first300.txt", 5.0, 30.0, 50)
    assert gt.shape == (300, 300)
    assert gt.sum() == 0
    # Sanity: with a 1-frame gap every consecutive frame (about 0.7 m apart, same heading) counts.
    near = loop_matrix_from_kitti(kitti_dir / "poses_00_first300.txt", 5.0, 30.0, 1)
    assert np.diagonal(near, offset=-1).sum() >= 290


def test_kitti_reader_axes(kitti_dir):
    poses = read_kitti_poses(kitti_dir / "poses_00_first300.txt")
    assert poses.shape == (300, 3, 4)
    positions, axes = positions_and_axes(poses)
    np.testing.assert_allclose(np.linalg.norm(axes, axis=1), 1.0)
    np.testing.assert_allclose(axes[0], [0, 0, 1], atol=1e-6)  # KITTI frame 0 is the world frame
    assert positions[1, 2] == pytest.approx(0.8586941)


def test_write_read_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    poses = rng.normal(size=(7, 3, 4))
    path = tmp_path / "poses.txt"
    write_kitti_poses(path, poses)
    np.testing.assert_allclose(read_kitti_poses(path), poses, rtol=1e-8)
    assert [p.name for p in tmp_path.iterdir()] == ["poses.txt"]


@pytest.mark.parametrize(
    ("content", "match"),
    [("1 2 3\n", "expected 12 numbers, got 3"), ("a " * 12 + "\n", "not a number"), ("\n\n", "no poses")],
)
def test_reader_errors(tmp_path, content, match):
    path = tmp_path / "poses.txt"
    path.write_text(content)
    with pytest.raises(DataError, match=match):
        read_kitti_poses(path)


def test_reader_missing_file(tmp_path):
    with pytest.raises(DataError, match="cannot read KITTI pose file"):
        read_kitti_poses(tmp_path / "absent.txt")


def test_poses_shape_errors(tmp_path):
    with pytest.raises(DataError, match=r"\(N, 3, 4\), got \(2, 4, 4\)"):
        write_kitti_poses(tmp_path / "p.txt", np.zeros((2, 4, 4)))
    with pytest.raises(DataError, match=r"\(N, 3, 4\), got \(12,\)"):
        positions_and_axes(np.zeros(12))
    with pytest.raises(DataError, match="zero rotation column"):
        positions_and_axes(np.zeros((2, 3, 4)))


@pytest.mark.parametrize(
    ("positions", "axes", "args", "error", "match"),
    [
        (np.zeros((3, 2)), np.zeros((3, 3)), (1, 10, 1), DataError, r"positions.*\(N, 3\), got \(3, 2\)"),
        (np.zeros((3, 3)), np.zeros((4, 3)), (1, 10, 1), DataError, "optical_axes has 4 rows but positions have 3"),
        (np.zeros((2, 3)), np.array([[0, 0, 2.0], [0, 0, 1]]), (1, 10, 1), DataError, "row 0 has norm 2"),
        (np.full((1, 3), np.nan), np.array([[0, 0, 1.0]]), (1, 10, 1), DataError, "non-finite"),
        (np.zeros((1, 3)), np.array([[0, 0, 1.0]]), (-1, 10, 1), ConfigError, "max_distance_m.*-1"),
        (np.zeros((1, 3)), np.array([[0, 0, 1.0]]), (1, 190, 1), ConfigError, "max_angle_deg.*190"),
        (np.zeros((1, 3)), np.array([[0, 0, 1.0]]), (1, 10, 0), ConfigError, "min_gap_frames.*0"),
    ],
)
def test_argument_errors(positions, axes, args, error, match):
    with pytest.raises(error, match=match):
        loop_matrix_from_poses(positions, axes, *args)


def test_load_gt_npz(tmp_path):
    good = tmp_path / "gt.npz"
    np.savez(good, gt=np.eye(3, k=-1, dtype=np.uint8))
    assert load_gt_npz(good).shape == (3, 3)
    np.savez(tmp_path / "key.npz", loops=np.zeros((3, 3)))
    np.savez(tmp_path / "shape.npz", gt=np.zeros((3, 4)))
    np.savez(tmp_path / "values.npz", gt=np.full((3, 3), 2))
    (tmp_path / "junk.npz").write_text("not a zip")
    for name, message in (("missing.npz", "ground-truth file not found"), ("key.npz", "has no array 'gt'"),
                          ("shape.npz", r"square \(N, N\) matrix, got shape \(3, 4\)"),
                          ("values.npz", "only 0 and 1"), ("junk.npz", "cannot read ground-truth file")):
        with pytest.raises(DataError, match=message):
            load_gt_npz(tmp_path / name)
