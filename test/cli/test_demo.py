"""aefabmap_demo's process handling (the demo itself runs for minutes: ./scripts/demo.sh)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from aefabmap_ros.cli.demo import _stop

HANDLES_SIGINT = """
import signal, sys, time
def stop(*_):
    open(sys.argv[1], "w").write("clean shutdown")
    sys.exit(0)
signal.signal(signal.SIGINT, stop)
print("ready", flush=True)
time.sleep(60)
"""

IGNORES_SIGINT = """
import signal, time
signal.signal(signal.SIGINT, signal.SIG_IGN)
print("ready", flush=True)
time.sleep(60)
"""


def _start(code: str, *args: str) -> subprocess.Popen[bytes]:
    process = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE)
    assert process.stdout is not None and process.stdout.readline() == b"ready\n"
    return process


def test_stop_asks_with_sigint_first_so_launch_can_stop_its_nodes(tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    process = _start(HANDLES_SIGINT, str(marker))
    _stop(process)
    assert process.returncode == 0 and marker.read_text() == "clean shutdown"


def test_stop_kills_a_child_that_ignores_sigint() -> None:
    process = _start(IGNORES_SIGINT)
    started = time.monotonic()
    _stop(process, grace_s=0.5)
    assert process.returncode == -9 and time.monotonic() - started < 10


def test_stop_leaves_a_finished_child_alone() -> None:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    _stop(process)
    assert process.returncode == 0


def test_closure_printer_summary_counts_published_false_and_events() -> None:
    """The online summary, by hand: gt of 30 frames, min gap 5; events 10-12 and 20-21."""
    import numpy as np

    from aefabmap_ros.cli.demo_printer import ClosurePrinter

    gt = np.zeros((30, 30), np.uint8)
    for query, place in ((10, 1), (11, 2), (12, 3), (20, 4), (21, 5)):
        gt[query, place] = 1
    printer = ClosurePrinter.__new__(ClosurePrinter)  # no ROS: only the bookkeeping
    printer._gt = gt
    printer.posteriors = 30
    printer.closures = [(11, 2, True), (25, 0, False)]
    printer.candidates = [(11, 2, True), (12, 9, False), (25, 0, False)]
    printer.closure_latencies_s = [0.1, 0.2, 0.3, 0.4, 1.0]
    printer.posterior_latencies_s = []
    assert printer.summary(min_gap=5).splitlines() == [
        "    2 loop closures published on /loop_closures (verified), 1 false; 1 of 2 revisit events closed",
        "    3 raw FAB-MAP candidates on /loop_closure_candidates, 2 false; 30 posteriors",
        "    latency image -> /loop_closures over 5 closures: median 0.300 s, p95 0.880 s, max 1.000 s",
        "    latency image -> /place_posteriors: no posterior to time",
    ]


def test_the_image_stamp_is_read_from_the_serialized_message_as_rclpy_serializes_it() -> None:
    import pytest

    pytest.importorskip("rclpy")
    from builtin_interfaces.msg import Time
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage, Image

    from aefabmap_ros.cli.demo_printer import latency_summary, serialized_header_stamp_ns

    for message in (Image(height=2, width=2, encoding="mono8", step=2, data=bytes(4)), CompressedImage(format="png")):
        message.header.stamp = Time(sec=1_700_000_123, nanosec=456_789_012)
        message.header.frame_id = "camera"
        assert serialized_header_stamp_ns(serialize_message(message)) == 1_700_000_123_456_789_012
    assert latency_summary([]) == "latency image -> /loop_closures: no closure to time"


def test_ate_figures_compare_odometry_and_closures_on_the_keyframe_stamps(tmp_path: Path) -> None:
    """Hand-made: ground truth along x, odometry 10 % too long, the backend's keyframes exact at 3 stamps,
    the injected backend's 0.1 m off at one of them."""
    import numpy as np

    from aefabmap_ros.cli.demo_backend import ate_figures, ate_summary
    from aefabmap_ros.evaluation.trajectory_error import tum_text

    stamps = np.arange(10) * 0.1
    truth = np.tile(np.eye(4), (10, 1, 1))
    truth[:, 0, 3] = np.arange(10.0)
    truth[:, 1, 3] = np.arange(10.0) ** 2 / 10  # a curve: an SE(3) alignment cannot absorb a scale error
    odometry = truth.copy()
    odometry[:, :3, 3] *= 1.1
    (tmp_path / "groundtruth.tum").write_text(tum_text(stamps, truth))
    (tmp_path / "odometry.tum").write_text(tum_text(stamps, odometry))
    keyframes = [0, 5, 9]
    (tmp_path / "kf.tum").write_text(tum_text(stamps[keyframes], truth[keyframes]))
    wrong = truth[keyframes].copy()
    wrong[1, 2, 3] += 0.1
    (tmp_path / "kf_injected.tum").write_text(tum_text(stamps[keyframes], wrong))
    figures = ate_figures(tmp_path, tmp_path / "kf.tum", tmp_path / "kf_injected.tum")
    assert figures.keyframes == 3 and figures.closures_m < 1e-6
    assert figures.odometry_m > 0.05 and figures.odometry_all_m > 0.05
    assert figures.injected_m is not None and 0.0 < figures.injected_m <= 0.1 / np.sqrt(3) + 1e-6
    text = ate_summary(figures)
    assert "over the backend's 3 keyframes" in text and "+ one wrong closure" in text


def test_pose_errors_summary_gives_the_medians() -> None:
    from aefabmap_ros.cli.demo_backend import PoseErrors
    from aefabmap_ros.verification.pose_error import PoseError

    errors = PoseErrors(metric=[PoseError(0.2, 1.0, 0.01), PoseError(0.4, 2.0, 0.03), PoseError(9.0, 9.0, 9.0)],
                        without_pose=2)
    text = errors.summary()
    assert "3 metric (PnP with depth), 0 monocular, 2 without a pose" in text
    assert "median rotation error 0.400 deg" in text and "translation direction 2.000 deg" in text
    assert "translation 3.00 cm" in text


def test_the_wrong_place_is_the_nearest_frame_far_enough_from_the_true_one() -> None:
    import numpy as np

    from aefabmap_ros.cli.demo_backend import wrong_place_near

    poses = np.tile(np.eye(4)[:3], (10, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]
    assert wrong_place_near(poses, 5, 3.0) == 2  # frames 2 and 8 are both 3 frames away: the earlier
    assert wrong_place_near(poses, 1, 3.0) == 4
    assert wrong_place_near(poses, 5, 4.5) == 0


def test_without_pictures_the_recording_keeps_every_topic_but_the_pictures() -> None:
    from aefabmap_ros.cli.demo import RECORDED_TOPICS, recorded_topics
    from aefabmap_ros.nodes.launch_table import CLOSURE_PICTURES_TOPIC, CLOSURES_TOPIC, REFUSED_PICTURES_TOPIC

    assert recorded_topics(no_pictures=False) == RECORDED_TOPICS
    without = recorded_topics(no_pictures=True)
    assert CLOSURE_PICTURES_TOPIC not in without and REFUSED_PICTURES_TOPIC not in without
    assert set(RECORDED_TOPICS) - set(without) == {CLOSURE_PICTURES_TOPIC, REFUSED_PICTURES_TOPIC}
    assert CLOSURES_TOPIC in without
