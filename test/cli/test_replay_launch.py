"""Error paths of aefabmap_replay, aefabmap_record and aefabmap_launch (their happy paths run in test/nodes)."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from aefabmap_ros.cli import launch, record, replay, replay_messages
from aefabmap_ros.io.bags import write_image_bag
from test.ros_processes import LoggedProcess


def _bag(tmp_path: Path) -> Path:
    path = tmp_path / "bag"
    write_image_bag(path, "/cam", [(1, np.zeros((4, 4), np.uint8))])
    return path


def test_replay_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _bag(tmp_path)
    cases = [
        ([str(tmp_path / "nope")], "does not exist"),
        ([str(bag), "--topic", "/image"], "'/image' not in bag"),
        ([str(bag), "--topic", "/cam", "--rate", "-1"], "--rate must be >= 0"),
        ([str(bag), "--topic", "/cam", "--loop", "--lockstep", "place_posteriors"], "never end"),
        ([str(bag), "--topic", "/cam", "--with", "/cam"], "is the image topic itself"),
        ([str(bag), "--topic", "/cam", "--with", "/odom", "--wait-subscribers", "0"], "--with /odom: not in"),
        ([str(bag), "--topic", "/cam", "--with", "/odom=0"], "must be an integer >= 1"),
    ]
    for argv, message in cases:
        assert replay.main(argv) == 1
        err = capsys.readouterr().err
        assert err.startswith("ERROR: ") and message in err, err


def test_companions_go_out_before_the_image_of_their_log_time() -> None:
    """A frame's depth and odometry (same log time as its image, written after it) are published first."""
    from aefabmap_ros.io.bags import BagMessage

    def message(topic: str, time_ns: int) -> BagMessage:
        return BagMessage(topic, "t", time_ns, time_ns, None, b"")

    in_bag = [message("/image", 1), message("/depth", 1), message("/odom", 1), message("/image", 2),
              message("/odom", 2), message("/odom", 3), message("/image", 4)]
    order = [(m.topic, m.log_time_ns) for m in replay_messages.companions_first(in_bag, "/image")]
    assert order == [("/depth", 1), ("/odom", 1), ("/image", 1), ("/odom", 2), ("/image", 2), ("/odom", 3),
                     ("/image", 4)]


def test_replay_restamps_later_laps() -> None:
    from aefabmap_ros.io.bag_messages import get_typestore, make_image_message, make_odometry_message
    from aefabmap_ros.stamps import stamp_to_ns

    typestore = get_typestore()
    raw = bytes(typestore.serialize_cdr(make_image_message(np.zeros((2, 2), np.uint8), 5_000), "sensor_msgs/msg/Image"))
    assert replay_messages.restamped(raw, "sensor_msgs/msg/Image", 0) == raw
    restamped = replay_messages.restamped(raw, "sensor_msgs/msg/Image", 7_000)
    moved: Any = typestore.deserialize_cdr(restamped, "sensor_msgs/msg/Image")
    assert stamp_to_ns(moved.header.stamp) == 12_000

    # A lap's companions move with its images: odometry and CameraInfo keep increasing across laps too.
    odometry = make_odometry_message(np.eye(4), 5_000)
    raw = bytes(typestore.serialize_cdr(odometry, "nav_msgs/msg/Odometry"))
    restamped = replay_messages.restamped(raw, "nav_msgs/msg/Odometry", 7_000)
    moved = typestore.deserialize_cdr(restamped, "nav_msgs/msg/Odometry")
    assert stamp_to_ns(moved.header.stamp) == 12_000 and moved.pose.pose.orientation.w == 1.0


@pytest.mark.ros
def test_record_refuses_existing_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("rclpy")
    bag = _bag(tmp_path)
    assert record.main([str(bag), "--duration", "0.1"]) == 1
    assert "already exists" in capsys.readouterr().err


@pytest.mark.ros
def test_record_keeps_its_bag_when_ctrl_c_shuts_rclpy_down_during_a_wait(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The demo lost a whole recording so: the signal handler shut the context down between rclpy.ok() and
    spin_once, which then raised, and the bag writer discarded the unfinished bag."""
    rclpy = pytest.importorskip("rclpy")

    def interrupted_wait(node: Any, timeout_sec: float) -> None:
        rclpy.shutdown()
        raise RuntimeError("failed to initialize wait set: the given context is not valid")

    monkeypatch.setattr(rclpy, "spin_once", interrupted_wait)
    output = tmp_path / "recording"
    assert record.main([str(output), "--duration", "5"]) == 0
    assert output.is_dir() and any(output.iterdir())


def test_launch_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert launch.main(["--model", str(tmp_path / "none")]) == 1
    assert "is not a directory" in capsys.readouterr().err
    assert launch.main(["--model", str(tmp_path), "--params", str(tmp_path / "p.yaml")]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_launch_commands_pass_parameters_to_every_node(tmp_path: Path) -> None:
    args = launch.build_parser().parse_args(["--model", str(tmp_path), "--map", "m.npz", "--image-topic", "/cam"])
    commands = launch.node_commands(args)
    assert [c[2] for c in commands] == [f"aefabmap_ros.nodes.{n}" for n in (*launch.NODES, "verifier_node")]
    for command in commands[:3]:
        assert f"model_dir:={tmp_path}" in command and "--params-file" in command
    assert "image:=/cam" in commands[0] and "map_file:=m.npz" in commands[2]
    single = launch.node_commands(launch.build_parser().parse_args(["--model", str(tmp_path), "--pipeline"]))
    assert [c[2] for c in single] == ["aefabmap_ros.nodes.pipeline", "aefabmap_ros.nodes.verifier_node"]


def test_launch_verifies_by_default_in_both_modes(tmp_path: Path) -> None:
    """The verifier runs unless --no-verify; fabmap_node's candidates reach loop_closures only through it."""
    for extra in ([], ["--pipeline"], ["--verify"]):  # --verify: the default, still accepted
        commands = launch.node_commands(launch.build_parser().parse_args(["--model", str(tmp_path), *extra]))
        assert commands[-1][2] == "aefabmap_ros.nodes.verifier_node" and "--params-file" in commands[-1]
        assert len(commands) == (2 if extra == ["--pipeline"] else 4)
        assert not any("store_dir" in arg for arg in commands[-1])  # no map: the store stays in memory
        assert not any("loop_closure_candidates:=loop_closures" in c for c in commands)
    with_map = launch.node_commands(launch.build_parser().parse_args(
        ["--model", str(tmp_path), "--map", str(tmp_path / "office.npz")]))
    assert f"store_dir:={tmp_path / 'office.features'}" in with_map[-1]


def test_launch_no_verify_remaps_the_candidates_onto_loop_closures(tmp_path: Path) -> None:
    for extra, fabmap_module in (([], "aefabmap_ros.nodes.fabmap_node"),
                                 (["--pipeline"], "aefabmap_ros.nodes.pipeline")):
        commands = launch.node_commands(launch.build_parser().parse_args(
            ["--model", str(tmp_path), "--no-verify", "--map", str(tmp_path / "m.npz"), *extra]))
        assert not any(c[2] == "aefabmap_ros.nodes.verifier_node" for c in commands)
        (fabmap,) = [c for c in commands if c[2] == fabmap_module]
        remap = fabmap.index("loop_closure_candidates:=loop_closures")
        assert fabmap[remap - 1] == "-r"


def test_thread_share_never_exceeds_the_cores_across_processes() -> None:
    from aefabmap_ros.nodes.launch_table import threads_per_process

    assert threads_per_process(4, cores=2) == 1  # never zero
    assert threads_per_process(3, cores=2) == 1
    assert threads_per_process(2, cores=8) == 4
    assert threads_per_process(1, cores=2) == 2


def test_launched_processes_get_thread_limits_unless_the_user_set_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The real children of supervise() see the limits in their environment."""
    import json
    import sys

    from aefabmap_ros.nodes.launch_table import THREAD_LIMIT_VARIABLES, threads_per_process

    for name in THREAD_LIMIT_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "7")
    script = ("import json, os, sys; json.dump({k: os.environ.get(k) for k in sys.argv[2:]}, "
              "open(sys.argv[1], 'w'))")
    outputs = [tmp_path / f"child{index}.json" for index in range(3)]
    commands = [[sys.executable, "-c", script, str(out), *THREAD_LIMIT_VARIABLES] for out in outputs]
    handlers = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    assert launch.supervise(commands) == 0
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers  # restored
    share = str(threads_per_process(3))
    for out in outputs:
        assert json.loads(out.read_text()) == {"OMP_NUM_THREADS": share, "OPENBLAS_NUM_THREADS": "7",
                                               "MKL_NUM_THREADS": share, "NUMBA_NUM_THREADS": share}


def _long_bag(tmp_path: Path, frames: int) -> Path:
    path = tmp_path / "long"
    write_image_bag(path, "/cam", [((i + 1) * 100_000_000, np.zeros((4, 4), np.uint8)) for i in range(frames)])
    return path


@pytest.mark.ros
@pytest.mark.parametrize(("sig", "code", "waiting"), [(signal.SIGINT, 130, False), (signal.SIGTERM, 143, False),
                                                       (signal.SIGINT, 130, True)])
def test_replay_stops_cleanly_on_a_signal(tmp_path: Path, sig: int, code: int, waiting: bool) -> None:
    """Ctrl-C / SIGTERM while publishing (or while waiting for subscribers): no traceback, the summary, how many
    images were left unpublished, and the shell's exit code for a signal."""
    pytest.importorskip("rclpy")
    bag = _long_bag(tmp_path, 100)  # 10 s of bag at --rate 1: the signal comes at image 50, 5 s before the end
    wait = ["--wait-subscribers", "1", "--wait-timeout", "120"] if waiting else ["--wait-subscribers", "0"]
    with LoggedProcess(tmp_path / "replay.log", "aefabmap_ros.cli.replay", bag, "--topic", "/cam",
                       "--out-topic", "/nobody_listens", *wait) as replay:
        replay.wait_for_log("waiting for 1 subscriber" if waiting else "[replay] 50 images", timeout_s=60)
        assert replay.stop(sig) == code, replay.log()
    log = replay.log()
    assert "Traceback" not in log, log
    assert f"stopped by {signal.Signals(sig).name}" in log, log
    if not waiting:
        assert "images of the bag not published" in log and "published with no subscriber matched" in log, log


@pytest.mark.ros
def test_replay_counts_images_published_with_no_subscriber(tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    bag = _long_bag(tmp_path, 3)
    with LoggedProcess(tmp_path / "replay.log", "aefabmap_ros.cli.replay", bag, "--topic", "/cam",
                       "--out-topic", "/nobody_listens", "--rate", "0", "--wait-subscribers", "0") as replay:
        assert replay.wait(timeout_s=60) == 0, replay.log()
    assert "published 3 images" in replay.log() and "(3 published with no subscriber matched" in replay.log()


@pytest.mark.parametrize(("content", "message"), [
    ("feature_node:\n  ros__parameters:\n    queue_depth: [1,\n", "is not valid YAML"),
    ("- just\n- a list\n", "must map node names"),
    ("feature_node:\n  queue_depth: 3\n", "'feature_node' must hold a 'ros__parameters:' mapping"),
])
def test_launch_refuses_a_malformed_params_file_in_one_line(tmp_path: Path, content: str, message: str,
                                                            capfd: pytest.CaptureFixture[str]) -> None:
    """One ERROR line and exit 1 before any node starts (not one traceback per node process)."""
    params = tmp_path / "p.yaml"
    params.write_text(content)
    assert launch.main(["--model", str(tmp_path), "--params", str(params)]) == 1
    out, err = capfd.readouterr()
    assert err.startswith("ERROR: ") and message in err and err.count("\n") == 1, err
    assert "Traceback" not in out + err
