"""aefabmap_gt CLI: ground truth from depth PNGs + KITTI or TUM poses, and every error path."""

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.cli.gt import main
from aefabmap_ros.evaluation.covisibility import covisibility_loop_matrix
from aefabmap_ros.evaluation.ground_truth import write_kitti_poses
from test.evaluation.test_covisibility import _pose, _room_depth

HEIGHT, WIDTH = 24, 32
CAMERA = np.array([[20.0, 0.0, 15.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]])
INTRINSICS = ["--intrinsics", "20", "20", "15.5", "11.5"]
# Frames 0-2 at the start, 3-5 back at the same spot 10 s later, 6 turned around.
POSITIONS = [(0, 0, 0), (0.2, 0, 0.3), (0.4, 0, 0.6), (0.1, 0, 0.1), (0.3, 0, 0.4), (0.5, 0, 0.2), (0, 0, 0)]
YAWS = [0.0, 5.0, 10.0, 2.0, 6.0, 8.0, 180.0]
STAMPS_S = [0.0, 1.0, 2.0, 10.0, 11.0, 12.0, 13.0]


@pytest.fixture(scope="module")
def scene():
    poses = np.stack([_pose(position, yaw) for position, yaw in zip(POSITIONS, YAWS, strict=True)])
    depths = np.stack([_room_depth(pose, CAMERA, HEIGHT, WIDTH) for pose in poses])
    millimetres = np.round(depths * 1000).astype(np.uint16)
    stamps = (np.array(STAMPS_S) * 1e9).astype(np.int64)
    expected = covisibility_loop_matrix(millimetres, poses, CAMERA, stamps, depth_scale=1000.0)
    assert expected.sum() >= 3 and not expected[6].any()
    return poses, millimetres, stamps, expected


def _write_kitti_folder(root, scene, names=None):
    poses, millimetres, _, _ = scene
    (root / "depth").mkdir(parents=True)
    for index, image in enumerate(millimetres):
        cv2.imwrite(str(root / "depth" / (names[index] if names else f"{index:06d}.png")), image)
    write_kitti_poses(root / "poses.txt", poses)
    (root / "times.txt").write_text("".join(f"{t:.6e}\n" for t in STAMPS_S))
    return root


def _kitti_args(root, *extra):
    return ["--depth", str(root / "depth"), "--poses", str(root / "poses.txt"), "--times", str(root / "times.txt"),
            *INTRINSICS, "--out", str(root / "out" / "gt.npz"), *extra]


def test_kitti_poses_and_times(tmp_path, scene, capsys):
    root = _write_kitti_folder(tmp_path, scene)
    assert main(_kitti_args(root)) == 0
    out = capsys.readouterr().out
    with np.load(root / "out" / "gt.npz") as data:
        np.testing.assert_array_equal(data["gt"], scene[3])
        np.testing.assert_array_equal(data["stamps_ns"], scene[2])
        assert data["files"].tolist() == [f"{index:06d}.png" for index in range(7)]
    assert f"7 frames: {int(scene[3].sum())} revisit pairs" in out
    # Frame 6 faces the other way: no revisit either way; a 1-degree view-angle limit leaves nothing.
    assert main(_kitti_args(root, "--max-view-angle-deg", "1")) == 0
    with np.load(root / "out" / "gt.npz") as data:
        assert data["gt"].sum() < scene[3].sum()
    # A longer gap leaves nothing: the returns are 8 to 12 s after the start.
    assert main(_kitti_args(root, "--min-gap-s", "20")) == 0
    with np.load(root / "out" / "gt.npz") as data:
        assert data["gt"].sum() == 0


def _tum_names():
    return [f"{1305031102 + t:.6f}.png" for t in STAMPS_S]


def _write_tum(root, scene, drop=()):
    poses = scene[0]
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for index, (pose, t) in enumerate(zip(poses, STAMPS_S, strict=True)):
        if index in drop:
            continue
        qx, qy, qz, qw = Rotation.from_matrix(pose[:, :3]).as_quat()
        stamp = 1305031102 + t + 0.005  # 5 ms after the depth frame, as an asynchronous mocap would be
        lines.append(f"{stamp:.4f} {pose[0, 3]} {pose[1, 3]} {pose[2, 3]} {qx} {qy} {qz} {qw}")
    (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")


def _tum_args(root, *extra):
    return ["--depth", str(root / "depth"), "--poses", str(root / "groundtruth.txt"), "--poses-format", "tum",
            "--depth-scale", "1000", *INTRINSICS, "--out", str(root / "gt.npz"), *extra]


def test_tum_trajectory_with_stamped_file_names(tmp_path, scene):
    _write_kitti_folder(tmp_path, scene, names=_tum_names())
    _write_tum(tmp_path, scene)
    assert main(_tum_args(tmp_path)) == 0
    with np.load(tmp_path / "gt.npz") as data:
        np.testing.assert_array_equal(data["gt"], scene[3])
        assert data["stamps_ns"][1] - data["stamps_ns"][0] == 1_000_000_000
        assert data["files"][0] == "1305031102.000000.png"


def test_tum_frames_without_pose(tmp_path, scene, capsys):
    _write_kitti_folder(tmp_path, scene, names=_tum_names())
    _write_tum(tmp_path, scene, drop=(1,))
    assert main(_tum_args(tmp_path)) == 1
    err = capsys.readouterr().err
    assert "ERROR: 1 of 7 depth frames have no pose" in err and "1305031103.000000.png" in err
    assert "--skip-unposed" in err
    assert main(_tum_args(tmp_path, "--skip-unposed")) == 0
    assert "(1 without a pose left out)" in capsys.readouterr().out
    keep = [0, 2, 3, 4, 5, 6]
    with np.load(tmp_path / "gt.npz") as data:
        assert data["files"].tolist() == [_tum_names()[index] for index in keep]
        np.testing.assert_array_equal(data["gt"], scene[3][np.ix_(keep, keep)])
    # Poses 5 ms off do not associate within 1 ms.
    assert main(_tum_args(tmp_path, "--max-pose-offset-s", "0.001")) == 1
    assert "7 of 7 depth frames have no pose" in capsys.readouterr().err


def test_camera_info_yaml(tmp_path, scene):
    from aefabmap_ros.cli.synth import camera_info_yaml

    root = _write_kitti_folder(tmp_path, scene)
    (root / "camera_info.yaml").write_text(camera_info_yaml(CAMERA, WIDTH, HEIGHT))
    args = [a for a in _kitti_args(root) if a not in INTRINSICS]
    assert main([*args, "--camera-info", str(root / "camera_info.yaml")]) == 0
    with np.load(root / "out" / "gt.npz") as data:
        np.testing.assert_array_equal(data["gt"], scene[3])
    (root / "camera_info.yaml").write_text(camera_info_yaml(CAMERA, WIDTH + 1, HEIGHT))
    assert main([*args, "--camera-info", str(root / "camera_info.yaml")]) == 1


def test_camera_info_with_distortion_is_refused(tmp_path, scene, capsys):
    """The covisibility rule is a pinhole computation: a distorted camera gets an error, not a wrong truth."""
    from aefabmap_ros.cli.synth import camera_info_yaml

    root = _write_kitti_folder(tmp_path, scene)
    text = camera_info_yaml(CAMERA, WIDTH, HEIGHT).replace("data: [0.0, 0.0, 0.0, 0.0, 0.0]",
                                                          "data: [-0.2, 0.05, 0.0, 0.0, 0.0]")
    assert "-0.2" in text
    (root / "camera_info.yaml").write_text(text)
    args = [a for a in _kitti_args(root) if a not in INTRINSICS]
    assert "needs rectified depth images" in _error(capsys, [*args, "--camera-info", str(root / "camera_info.yaml")])
    assert not (root / "out" / "gt.npz").exists()


def _error(capsys, argv):
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") or "\nERROR: " in err
    return err


def test_errors_missing_and_unreadable(tmp_path, scene, capsys):
    root = _write_kitti_folder(tmp_path, scene)
    err = _error(capsys, ["--depth", str(tmp_path / "nowhere"), *_kitti_args(root)[2:]])
    assert f"depth folder does not exist: {tmp_path / 'nowhere'}" in err
    (tmp_path / "empty").mkdir()
    assert "no .png files in depth folder" in _error(capsys, ["--depth", str(tmp_path / "empty"),
                                                              *_kitti_args(root)[2:]])
    (root / "depth" / "000003.png").write_bytes(b"not a png")
    assert f"cannot read depth image {root / 'depth' / '000003.png'}" in _error(capsys, _kitti_args(root))
    cv2.imwrite(str(root / "depth" / "000003.png"), np.zeros((HEIGHT, WIDTH), np.uint8))
    assert "must be a 16-bit single-channel PNG, got uint8" in _error(capsys, _kitti_args(root))
    cv2.imwrite(str(root / "depth" / "000003.png"), np.zeros((HEIGHT, WIDTH + 2), np.uint16))
    assert "000003.png is 34x24, but 000000.png is 32x24" in _error(capsys, _kitti_args(root))


def test_errors_mismatched_counts(tmp_path, scene, capsys):
    root = _write_kitti_folder(tmp_path, scene)
    write_kitti_poses(root / "poses.txt", scene[0][:5])
    assert "has 5 poses but the depth folder" in _error(capsys, _kitti_args(root))
    write_kitti_poses(root / "poses.txt", scene[0])
    (root / "times.txt").write_text("0\n1\n")
    assert "has 2 stamps but the folder has 7 frames" in _error(capsys, _kitti_args(root))
    (root / "times.txt").write_text("0\nsoon\n")
    assert "times.txt:2: not a number ('soon')" in _error(capsys, _kitti_args(root))
    (root / "times.txt").write_text("".join(f"{t}\n" for t in reversed(STAMPS_S)))
    assert "stamps go backwards" in _error(capsys, _kitti_args(root))


def test_errors_bad_inputs(tmp_path, scene, capsys):
    root = _write_kitti_folder(tmp_path, scene)
    no_times = [a for a in _kitti_args(root) if a not in ("--times", str(root / "times.txt"))]
    assert "cannot read a stamp from file name 000000.png (expected <seconds>.png" in _error(capsys, no_times)
    bad_pose = scene[0].copy()
    bad_pose[2, 0, 0] = math.nan
    write_kitti_poses(root / "poses.txt", bad_pose)
    assert "pose 2 contains non-finite values" in _error(capsys, _kitti_args(root))
    (root / "groundtruth.txt").write_text("1 2 3\n")
    tum = ["--poses-format", "tum", "--poses", str(root / "groundtruth.txt")]
    assert "groundtruth.txt:1: expected 8 fields" in _error(capsys, [*_kitti_args(root), *tum])
    write_kitti_poses(root / "poses.txt", scene[0])
    without_camera = [a for a in _kitti_args(root) if a not in INTRINSICS]
    assert "focal lengths must be > 0, got fx=0.0" in _error(capsys, [*without_camera, "--intrinsics", "0", "1",
                                                                      "2", "3"])
    assert "one of the arguments --intrinsics --camera-info is required" in _error(capsys, without_camera)
    assert "min_fraction must be in (0, 1], got 1.5" in _error(capsys, [*_kitti_args(root), "--min-fraction", "1.5"])
    (root / "camera_info.yaml").write_text("image_width: 3\n")
    args = [a for a in _kitti_args(root) if a not in INTRINSICS]
    assert "cannot read camera info" in _error(capsys, [*args, "--camera-info", str(root / "camera_info.yaml")])
