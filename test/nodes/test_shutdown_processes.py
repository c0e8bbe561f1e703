"""Stopping the nodes as a user (or an init system) does: SIGTERM while busy, the launcher killed."""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.model.directory import load_model
from test.reliability import Recorder
from test.revisit_fixture import RevisitData
from test.ros_processes import LoggedProcess, running, write_script

pytestmark = [pytest.mark.ros, pytest.mark.slow]

# Publishes BagOfWords stamped with the wall clock (so increasing across runs): every 2 ms, or every argv[3] s.
WORDS_PUBLISHER = """
import sys, time
import numpy as np
import rclpy
from aefabmap_msgs.msg import BagOfWords
from aefabmap_ros.nodes.common import pipeline_qos

vocabulary_id, size = sys.argv[1], int(sys.argv[2])
rclpy.init()
node = rclpy.create_node("words_publisher")
publisher = node.create_publisher(BagOfWords, "aefabmap/words", pipeline_qos(100))
rng = np.random.default_rng(0)
while rclpy.ok():
    words = np.unique(rng.integers(0, size, 60)).astype(np.uint32)
    message = BagOfWords(vocabulary_id=vocabulary_id, vocabulary_size=size, word_ids=words,
                         counts=np.ones(words.size, np.uint32))
    now = time.time_ns()
    message.header.stamp.sec, message.header.stamp.nanosec = now // 10**9, now % 10**9
    publisher.publish(message)
    time.sleep(float(sys.argv[3]) if len(sys.argv) > 3 else 0.002)
"""


def _map_stamps(map_path: Path, data: RevisitData) -> np.ndarray:
    """The saved map's place stamps; loading it checks it is whole (as many stamps as places)."""
    model = load_model(data.model_dir)
    assert model.tree_matrix is not None
    recognizer = PlaceRecognizer(ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples,
                                 FabMapConfig(), model.vocabulary_id)
    recognizer.load_map(map_path)
    return np.array([recognizer.place_stamp_ns(p) for p in range(recognizer.num_places)], dtype=np.int64)


@pytest.mark.reliability
def test_sigterm_while_busy_saves_a_whole_map_that_later_runs_extend(tmp_path: Path, revisit_data: RevisitData,
                                                                      reliability: Recorder) -> None:
    map_path = tmp_path / "map.npz"
    publisher = write_script(tmp_path, "words_publisher.py", WORDS_PUBLISHER)
    fabmap_args = ["--ros-args", "-p", f"model_dir:={revisit_data.model_dir}", "-p", f"map_file:={map_path}",
                   "-p", "save_period_s:=0.05", "-p", "keyframe_max_overlap:=1.0"]
    previous = np.zeros(0, dtype=np.int64)
    places_lost = 0
    with running(publisher, revisit_data.vocabulary_id, "400"):
        for run in range(3):
            with LoggedProcess(tmp_path / f"fabmap{run}.log", "aefabmap_ros.nodes.fabmap_node",
                               *fabmap_args) as fabmap:
                fabmap.wait_for_log("receiving words", timeout_s=90)
                deadline = time.monotonic() + 60
                while fabmap.log().count("\n") < 3 and not map_path.exists():  # words are arriving
                    assert time.monotonic() < deadline, fabmap.log()
                    time.sleep(0.1)
                time.sleep(1.0)  # busy: words keep coming at ~400 Hz while it stops
                assert fabmap.stop(signal.SIGTERM) == 0, fabmap.log()[-3000:]
                in_memory = re.search(r"fabmap_node: (\d+) places", fabmap.log())
                assert in_memory is not None, fabmap.log()[-3000:]
            stamps = _map_stamps(map_path, revisit_data)
            places_lost += max(0, int(in_memory.group(1)) - stamps.size)  # held at the signal, missing on disk
            assert stamps.size > previous.size, f"run {run} added no place"
            assert np.all(np.diff(stamps) > 0)
            np.testing.assert_array_equal(stamps[: previous.size], previous)  # the earlier map is its prefix
            previous = stamps
    reliability.fault("SIGTERM to fabmap_node while words arrive at ~400 Hz", injected=3, survived=3,
                      places_lost=places_lost)


def _children(pid: int) -> list[int]:
    text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    return [int(child) for child in text.split()]


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"  # a zombie has exited; whoever adopted it may not reap it at once


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_killing_the_launcher_stops_its_nodes(tmp_path: Path, revisit_data: RevisitData) -> None:
    with LoggedProcess(tmp_path / "launch.log", "aefabmap_ros.cli.launch", "--model", revisit_data.model_dir,
                       "--pipeline") as launch:
        launch.wait_for_log("fabmap_node]: receiving words", timeout_s=90)
        launch.wait_for_log("verifier_node]: receiving features", timeout_s=90)
        nodes = _children(launch.process.pid)
        assert len(nodes) == 2, nodes  # the pipeline and the verifier
        os.kill(launch.process.pid, signal.SIGKILL)  # no chance to stop them itself
        launch.process.wait(timeout=10)
        deadline = time.monotonic() + 60
        while any(_alive(pid) for pid in nodes):
            assert time.monotonic() < deadline, f"nodes still running after the launcher died: {nodes}"
            time.sleep(0.2)
