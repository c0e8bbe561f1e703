"""aefabmap_synth CLI: files written, their contents, bags, and the error paths."""

import json

import cv2
import numpy as np
import pytest
import yaml

from aefabmap_ros.cli.synth import main
from aefabmap_ros.evaluation.ground_truth import read_kitti_poses

SMALL = ["--frames", "12", "--width", "96", "--height", "72"]


def calib_values(directory):
    return [float(value) for value in (directory / "calib.txt").read_text().split()[1:]]


def test_writes_folder_sequences(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--kind", "both", *SMALL]) == 0
    assert "frames/s" in capsys.readouterr().out
    for name, seed in (("train", 1_000_003), ("test", 0)):
        directory = tmp_path / name
        pngs = sorted((directory / "images").glob("*.png"))
        assert [p.name for p in pngs[:2]] == ["000000.png", "000001.png"] and len(pngs) == 12
        image = cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED)
        assert image is not None
        assert image.shape == (72, 96) and image.dtype == np.uint8
        poses = read_kitti_poses(directory / "poses.txt")
        assert poses.shape == (12, 3, 4)
        truth, odometry = np.loadtxt(directory / "groundtruth.tum"), np.loadtxt(directory / "odometry.tum")
        assert truth.shape == odometry.shape == (12, 8)
        np.testing.assert_allclose(truth[:, 1:4], poses[:, :, 3], atol=1e-6)
        np.testing.assert_array_equal(truth[:, 0], odometry[:, 0])
        np.testing.assert_allclose(odometry[0], truth[0])  # starts at the first true pose, then drifts
        assert not np.allclose(odometry[-1, 1:4], truth[-1, 1:4], atol=1e-3)
        times = np.loadtxt(directory / "times.txt")
        np.testing.assert_allclose(times, np.arange(12) * 0.1, atol=1e-9)
        with np.load(directory / "loop_gt.npz") as data:
            assert data["gt"].shape == (12, 12) and data["gt"].dtype == np.uint8
        with np.load(directory / "loop_gt_poses.npz") as data:
            assert data["gt"].shape == (12, 12) and data["gt"].dtype == np.uint8
        depths = sorted((directory / "depth").glob("*.png"))
        assert len(depths) == 12
        depth = cv2.imread(str(depths[0]), cv2.IMREAD_UNCHANGED)
        assert depth is not None and depth.shape == (72, 96) and depth.dtype == np.uint16
        assert (depth == 0).any() and 1000 < depth.max() < 65535  # sky, and surfaces metres away
        info = yaml.safe_load((directory / "camera_info.yaml").read_text())
        assert (info["image_width"], info["image_height"]) == (96, 72)
        projection = np.array(calib_values(directory)).reshape(3, 4)
        np.testing.assert_allclose(np.array(info["camera_matrix"]["data"]).reshape(3, 3), projection[:, :3])
        config = json.loads((directory / "synth_config.json").read_text())
        assert config["seed"] == seed and config["num_frames"] == 12
        calib = (directory / "calib.txt").read_text().split()
        assert calib[0] == "P0:" and len(calib) == 13
        assert not (directory / "bag").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["test", "train"]  # no temporary leftovers
    train = cv2.imread(str(tmp_path / "train" / "images" / "000000.png"), cv2.IMREAD_UNCHANGED)
    test = cv2.imread(str(tmp_path / "test" / "images" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert train is not None and test is not None
    assert np.abs(train.astype(int) - test.astype(int)).mean() > 10  # different towns


def test_writes_mcap_bag(tmp_path):
    bags = pytest.importorskip("aefabmap_ros.io.bags")
    bag_messages = pytest.importorskip("aefabmap_ros.io.bag_messages")
    assert main(["--out", str(tmp_path), "--kind", "test", "--format", "both", "--topic", "/cam", *SMALL]) == 0
    directory = tmp_path / "test"
    messages = list(bags.read_messages(directory / "bag", ["/cam"]))
    assert len(messages) == 12
    first = messages[0].message
    assert (first.height, first.width, first.encoding) == (72, 96, "mono8")
    png = cv2.imread(str(directory / "images" / "000000.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(np.asarray(first.data).reshape(72, 96), png)
    stamps = [m.stamp_ns for m in messages]
    assert stamps == sorted(stamps) and stamps[1] - stamps[0] == 100_000_000
    # The ground truth's rows carry the images' header stamps (aefabmap_eval --recording finds frames by them).
    assert [m.message.header.stamp.sec * 10**9 + m.message.header.stamp.nanosec for m in messages] == stamps
    for name in ("loop_gt.npz", "loop_gt_poses.npz"):
        with np.load(directory / name) as data:
            assert data["stamps_ns"].dtype == np.int64 and data["stamps_ns"].tolist() == stamps
    assert bags.list_topics(directory / "bag") == {
        "/cam": bag_messages.IMAGE_TYPE, "/depth": bag_messages.IMAGE_TYPE,
        "/camera_info": bag_messages.CAMERA_INFO_TYPE, "/odom": bag_messages.ODOMETRY_TYPE}
    # The odometry topic is odometry.tum's drifting odometry, frame by frame, stamped like the images.
    odometry = list(bags.read_messages(directory / "bag", ["/odom"]))
    assert [m.stamp_ns for m in odometry] == stamps
    assert (odometry[0].message.header.frame_id, odometry[0].message.child_frame_id) == ("odom", "camera")
    tum = np.loadtxt(directory / "odometry.tum")
    for message, row in zip(odometry, tum, strict=True):
        pose = message.message.pose.pose
        np.testing.assert_allclose([pose.position.x, pose.position.y, pose.position.z], row[1:4], atol=1e-6)
        quaternion = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
        assert abs(quaternion @ row[4:8]) == pytest.approx(1.0, abs=1e-6)
    depth = list(bags.read_messages(directory / "bag", ["/depth"]))
    info = list(bags.read_messages(directory / "bag", ["/camera_info"]))
    assert [m.stamp_ns for m in depth] == stamps == [m.stamp_ns for m in info]
    assert depth[0].message.encoding == "16UC1"
    png = cv2.imread(str(directory / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(np.frombuffer(bytes(depth[0].message.data), "<u2").reshape(72, 96), png)
    np.testing.assert_allclose(np.asarray(info[0].message.p), calib_values(directory))


def test_aefabmap_gt_reproduces_the_written_ground_truth(tmp_path):
    from aefabmap_ros.cli.gt import main as gt_main

    assert main(["--out", str(tmp_path), "--kind", "test", "--frames", "80", "--width", "96", "--height", "72",
                 "--laps", "2"]) == 0
    directory = tmp_path / "test"
    assert gt_main(["--depth", str(directory / "depth"), "--poses", str(directory / "poses.txt"),
                    "--camera-info", str(directory / "camera_info.yaml"), "--times", str(directory / "times.txt"),
                    "--out", str(tmp_path / "gt.npz")]) == 0
    with np.load(directory / "loop_gt.npz") as written, np.load(tmp_path / "gt.npz") as recomputed:
        assert written["gt"].sum() > 0
        np.testing.assert_array_equal(recomputed["gt"], written["gt"])


def test_mcap_only_writes_no_pngs(tmp_path):
    pytest.importorskip("aefabmap_ros.io.bags")
    assert main(["--out", str(tmp_path), "--kind", "train", "--format", "mcap", *SMALL]) == 0
    assert (tmp_path / "train" / "bag").is_dir()
    assert not (tmp_path / "train" / "images").exists()


def test_existing_sequence_needs_overwrite(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--kind", "test", *SMALL]) == 0
    assert main(["--out", str(tmp_path), "--kind", "test", *SMALL]) == 1
    assert "already exists (use --overwrite" in capsys.readouterr().err
    assert main(["--out", str(tmp_path), "--kind", "test", "--overwrite", "--frames", "11", *SMALL[2:]]) == 0
    assert len(list((tmp_path / "test" / "images").glob("*.png"))) == 11


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--frames", "0"], "num_frames must be > 0, got 0"),
        (["--width", "4"], "width and height must be >= 16"),
        (["--kind", "validation"], "invalid choice: 'validation'"),
        (["--frames", "many"], "invalid int value: 'many'"),
        (["--preset", "spiral"], "invalid choice: 'spiral'"),
    ],
)
def test_bad_arguments(tmp_path, capsys, args, message):
    assert main(["--out", str(tmp_path / "out"), *args]) == 1
    err = capsys.readouterr().err
    assert "ERROR: " in err and message in err


def test_missing_out_is_an_error(capsys):
    assert main(["--kind", "test"]) == 1
    assert "ERROR: the following arguments are required: --out" in capsys.readouterr().err


def test_unwritable_out(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["--out", str(blocker / "sub"), *SMALL]) == 1
    assert "ERROR: cannot create output directory" in capsys.readouterr().err


def test_dense_video_preset(tmp_path):
    assert main(["--out", str(tmp_path), "--kind", "both", "--preset", "dense-video", "--frames", "45",
                 "--width", "64", "--height", "48"]) == 0
    for name, seed in (("train", 1_000_003), ("test", 0)):
        config = json.loads((tmp_path / name / "synth_config.json").read_text())
        assert (config["route"], config["frame_rate_hz"], config["seed"]) == ("dense-video", 30.0, seed)
        assert (config["num_frames"], config["width"], config["gt_min_gap_s"]) == (45, 64, 5.0)
        np.testing.assert_allclose(np.loadtxt(tmp_path / name / "times.txt"), np.arange(45) / 30.0, atol=1e-9)
    assert main(["--out", str(tmp_path / "b"), "--kind", "test", "--preset", "dense-video", "--frames", "30"]) == 0
    config = json.loads((tmp_path / "b" / "test" / "synth_config.json").read_text())
    assert (config["width"], config["height"]) == (320, 240)  # the preset's size
    assert main(["--out", str(tmp_path / "c"), "--kind", "test", "--frames", "3", *SMALL[2:]]) == 0
    config = json.loads((tmp_path / "c" / "test" / "synth_config.json").read_text())
    assert (config["route"], config["frame_rate_hz"], config["laps"]) == ("figure-eight", 10.0, 2)  # defaults kept
