"""Live, as on a robot: a 30 Hz RGB-D camera driver with the sensor-data QoS, odometry, the default launch.

A synthetic town driven twice is filmed at 30 Hz with depth, CameraInfo and drifting odometry, and replayed
in real time with best-effort publishers (what a driver with the sensor-data profile looks like) into
``aefabmap_launch --backend`` with the shipped aefabmap.yaml. Nothing waits for the nodes. The verifier
must hear camera_info and depth (closures carry metric poses), the backend must hear odometry (a keyframe
trajectory), and every frame the camera sent must be accounted for by feature_node.
"""

from __future__ import annotations

import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_ros.cli.synth import write_sequence
from aefabmap_ros.datasets.synth.config import SynthConfig, train_test_configs
from aefabmap_ros.datasets.synth.town import generate_sequence
from aefabmap_ros.io.bags import read_messages
from aefabmap_ros.io.config_files import shipped_config
from test.revisit_fixture import RevisitData
from test.ros_processes import LoggedProcess

pytestmark = [pytest.mark.ros, pytest.mark.slow]

FRAMES = 360  # 12 s at 30 Hz: the figure-eight twice


def _camera_sequence(directory: Path) -> Path:
    base = SynthConfig(num_frames=FRAMES, width=320, height=240, laps=2, frame_rate_hz=30.0, blur_probability=0.0)
    _, config = train_test_configs(base)
    sequence = generate_sequence(config)
    directory.mkdir()
    write_sequence(sequence, config, directory, "mcap", "/camera/rgb/image_raw")
    return directory


def _params(tmp_path: Path) -> Path:
    """The shipped aefabmap.yaml, only told where the backend writes its trajectory."""
    import yaml

    params = yaml.safe_load(shipped_config("aefabmap.yaml").read_text())
    params["pose_graph_node"]["ros__parameters"]["trajectory_file"] = str(tmp_path / "keyframes.tum")
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


def _count(log: str, node: str, key: str) -> int:
    summary = next(line for line in log.splitlines() if f"{node}: " in line and "=" in line)
    match = re.search(rf"\b{key}=(\d+)", summary)
    return int(match.group(1)) if match else 0


def test_a_30_hz_best_effort_rgbd_camera_gets_metric_closures_and_a_trajectory(tmp_path: Path,
                                                                                revisit_data: RevisitData) -> None:
    sequence = _camera_sequence(tmp_path / "camera")
    recording = tmp_path / "recording"
    launch = LoggedProcess(tmp_path / "nodes.log", "aefabmap_ros.cli.launch", "--model", revisit_data.model_dir,
                           "--params", _params(tmp_path), "--backend", "--image-topic", "/camera/rgb/image_raw",
                           "--depth-topic", "/camera/rgb/depth")
    with launch, LoggedProcess(tmp_path / "record.log", "aefabmap_ros.cli.record", recording, "--topics",
                               "loop_closures", "place_posteriors", "--wait-publishers", "90") as recorder:
        for ready in ("verifier_node]: receiving features", "pose graph (example backend)"):
            launch.wait_for_log(ready, timeout_s=120)
        recorder.wait_for_log("[record] recording", timeout_s=120)
        with LoggedProcess(tmp_path / "replay.log", "aefabmap_ros.cli.replay", sequence / "bag", "--topic",
                           "/camera/rgb/image_raw", "--out-topic", "/camera/rgb/image_raw", "--rate", "1",
                           "--qos", "sensor_data", "--with", "/camera/rgb/depth", "--with", "/camera/rgb/camera_info",
                           "--with", "/odom") as replay:
            assert replay.wait(timeout_s=120) == 0, replay.log()
        time.sleep(5.0)  # the verifier's last closures; nobody waited for it during the replay
        assert recorder.stop(signal.SIGINT) == 0, recorder.log()
        assert launch.stop(signal.SIGINT, timeout_s=90) == 0, launch.log()
    log = launch.log()
    published = int(re.search(r"published (\d+) images", replay.log()).group(1))  # type: ignore[union-attr]
    assert published == FRAMES
    # Every frame the camera sent is accounted for by name (DDS may lose some on the way: counted from the gaps).
    accounted = sum(_count(log, "feature_node", key) for key in (
        "processed", "skipped_detection_rate", "dropped_busy", "dropped_before_callback"))
    assert accounted >= published - 5, log  # the last few a best-effort gap cannot reveal
    assert _count(log, "feature_node", "skipped_detection_rate") >= FRAMES // 2  # 10 Hz of a 30 Hz camera
    # The verifier heard the driver: camera_info and depth arrived best effort.
    assert re.search(r"/camera/rgb/camera_info: [1-9]\d* received, \d+ lost on the way \(best effort\)", log), log
    assert re.search(r"/camera/rgb/depth: [1-9]\d* received, \d+ lost on the way \(best effort\)", log), log
    assert re.search(r"pose_graph_node: .*/odom: [1-9]\d* received, \d+ lost on the way \(best effort\)", log), log
    closures = [m.message for m in read_messages(recording, ["/loop_closures"])]
    assert closures, log
    # Every closure has a pose, nearly all of them metric: PnP falls back to the essential matrix only where too few
    # inlier keypoints have depth (the sky, beyond the depth range).
    assert all(c.pose_available for c in closures), [c.pose_status for c in closures]
    metric = sum(c.translation_metric for c in closures)
    assert metric >= 0.8 * len(closures), ([c.translation_metric for c in closures], log)
    keyframes = np.loadtxt(tmp_path / "keyframes.tum", ndmin=2)
    assert len(keyframes) >= 2
