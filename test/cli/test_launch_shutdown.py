"""aefabmap_launch's stop: a node whose final save fails makes the exit code 1, named in an ERROR line; a node
still saving is waited for (``--stop-timeout``, said every few seconds) and only then killed.

The launcher runs as its own process (it is sent SIGTERM as a user or an init system would). Its nodes are
small stand-ins that stop as run_nodes does: exit 0 after a clean stop, 1 after a failed final save; one
real fabmap_node then shows that a real failed save gives the same exit code.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aefabmap_ros.cli import launch
from test.conftest import REPO_ROOT
from test.nodes.test_shutdown_processes import WORDS_PUBLISHER
from test.revisit_fixture import RevisitData
from test.ros_processes import running, write_script

# How a node stops (nodes/common.py run_nodes): SIGINT/SIGTERM request the stop, then the final save.
STAND_IN = """
import signal, sys, time
from pathlib import Path

behaviour, ready = sys.argv[1], Path(sys.argv[2])
stop = []
if behaviour == "starting":  # dies of the signal itself, as a node does before run_nodes sets its handlers
    signal.signal(signal.SIGINT, signal.SIG_DFL)
else:
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.append(1))
ready.write_text("ready")
while not stop:
    time.sleep(0.02)
if behaviour == "clean":
    sys.exit(0)
if behaviour == "save_fails":
    print("[ERROR] FINAL SAVE FAILED: the map not saved to /full/map.npz (OSError: No space left)", flush=True)
    sys.exit(1)
if behaviour == "slow":  # a final save longer than --stop-timeout, writing nothing
    time.sleep(600)
if behaviour.startswith("writing"):  # a final save writing its file for 3 s (writing_forever: for ever)
    with open(f"{ready}.save", "wb") as saving:
        for _ in range(30 if behaviour == "writing" else 10**6):
            saving.write(b"x" * 1000)
            saving.flush()
            time.sleep(0.1)
    sys.exit(0)
"""

# aefabmap_launch's main() with the stand-ins as its nodes (a parameter file and model folder to pass its checks).
LAUNCHER = """
import sys
from aefabmap_ros.cli import launch

nodes, ready_dir = sys.argv[1].split(","), sys.argv[2]
launch.STOP_PROGRESS_S = 0.5
launch.STOP_WRITING_CAP_S = 6.0
launch.check_model = lambda model: None
launch.node_commands = lambda args: [[sys.executable, "-m", name, behaviour, f"{ready_dir}/{name}.ready"]
                                     for name, behaviour in (node.split("=") for node in nodes)]
sys.exit(launch.main(["--model", ready_dir, "--params", f"{ready_dir}/params.yaml", *sys.argv[3:]]))
"""


def _launch(tmp_path: Path, nodes: dict[str, str], *options: str, timeout_s: float = 60.0) -> tuple[int, str]:
    """Run the launcher with stand-in nodes (module name -> behaviour), SIGTERM it once every node is up;
    its exit code and stderr."""
    for name in nodes:
        write_script(tmp_path, f"{name}.py", STAND_IN)
    (tmp_path / "params.yaml").write_text("fabmap_node:\n  ros__parameters:\n    map_file: ''\n")
    launcher = write_script(tmp_path, "launcher.py", LAUNCHER)
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO_ROOT)])}
    spec = ",".join(f"{name}={behaviour}" for name, behaviour in nodes.items())
    process = subprocess.Popen([sys.executable, str(launcher), spec, str(tmp_path), *options], env=environment,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not all((tmp_path / f"{name}.ready").exists() for name in nodes):
            assert process.poll() is None and time.monotonic() < deadline, process.communicate()
            time.sleep(0.05)
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=timeout_s)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    return process.returncode, err


def test_a_clean_stop_exits_0(tmp_path: Path) -> None:
    code, err = _launch(tmp_path, {"feature_node": "clean", "fabmap_node": "clean"})
    assert code == 0 and "ERROR" not in err, err


def test_a_failed_final_save_exits_1_and_names_the_node(tmp_path: Path) -> None:
    code, err = _launch(tmp_path, {"feature_node": "clean", "fabmap_node": "save_fails", "verifier_node": "clean"})
    assert code == 1, err
    assert "ERROR: fabmap_node exited with code 1 during shutdown (its state may not be saved)" in err, err
    assert err.count("ERROR") == 1, err


def test_a_node_still_saving_is_waited_for_then_killed(tmp_path: Path) -> None:
    started = time.monotonic()
    code, err = _launch(tmp_path, {"feature_node": "clean", "verifier_node": "slow"}, "--stop-timeout", "2")
    assert code == 1 and time.monotonic() - started >= 2.0, err
    assert "[launch] waiting for verifier_node to finish shutting down (saving state)" in err, err
    assert "of 2 s (--stop-timeout; longer while writing, up to 6 s)" in err, err
    assert "still running, writing nothing, 2 s (--stop-timeout) after the stop request: killed" in err, err
    assert "ERROR: verifier_node exited with code -9 during shutdown (its state may not be saved)" in err, err


def test_a_node_still_writing_its_save_is_waited_for_past_the_stop_timeout(tmp_path: Path) -> None:
    code, err = _launch(tmp_path, {"feature_node": "clean", "fabmap_node": "writing"}, "--stop-timeout", "1")
    assert code == 0 and "ERROR" not in err, err
    assert (tmp_path / "fabmap_node.ready.save").stat().st_size == 30_000  # the whole save, not cut short


def test_a_node_writing_for_ever_is_killed_at_the_cap(tmp_path: Path) -> None:
    code, err = _launch(tmp_path, {"fabmap_node": "writing_forever"}, "--stop-timeout", "1")
    assert code == 1, err
    assert "ERROR: fabmap_node (pid" in err and "still writing after 6 s after the stop request: killed" in err, err


def test_bytes_open_for_writing_counts_the_files_a_process_writes(tmp_path: Path) -> None:
    reading = (tmp_path / "read.bin")
    reading.write_bytes(b"r" * 500)
    before = launch.bytes_open_for_writing(os.getpid())
    assert before is not None
    with reading.open("rb"), (tmp_path / "written.bin").open("wb") as written:
        written.write(b"w" * 4096)
        written.flush()
        assert launch.bytes_open_for_writing(os.getpid()) == before + 4096  # the file read is not counted
    assert launch.bytes_open_for_writing(2**22 + 12345) is None  # no such process


def test_a_node_stopped_while_still_starting_is_not_an_error(tmp_path: Path) -> None:
    code, err = _launch(tmp_path, {"feature_node": "clean", "quantizer_node": "starting"})
    assert code == 0, err
    assert "quantizer_node ended by SIGINT while still starting (nothing to save)" in err, err


def test_the_stop_timeout_must_be_positive(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "params.yaml").write_text("fabmap_node:\n  ros__parameters:\n    map_file: ''\n")
    assert launch.main(["--model", str(tmp_path), "--params", str(tmp_path / "params.yaml"),
                        "--stop-timeout", "0"]) == 1
    assert "--stop-timeout must be > 0 seconds, got 0.0" in capsys.readouterr().err
    assert launch.build_parser().parse_args(["--model", "m"]).stop_timeout == launch.STOP_TIMEOUT_S == 120.0



SUPERVISED_FABMAP = """
import sys
from aefabmap_ros.cli import launch

model, map_file = sys.argv[1], sys.argv[2]
sys.exit(launch.supervise([[sys.executable, "-m", "aefabmap_ros.nodes.fabmap_node", "--ros-args",
                            "-p", f"model_dir:={model}", "-p", f"map_file:={map_file}", "-p", "save_period_s:=0.0",
                            "-p", "keyframe_max_overlap:=1.0"]]))
"""


@pytest.mark.ros
@pytest.mark.slow
def test_a_real_fabmap_node_whose_final_save_fails_makes_the_launcher_exit_1(tmp_path: Path,
                                                                             revisit_data: RevisitData) -> None:
    """fabmap_node's map folder is replaced by a file while it runs (as a full or removed disk would make the
    save fail): on SIGTERM the node logs FINAL SAVE FAILED and exits 1, and the launcher exits 1 naming it."""
    pytest.importorskip("rclpy")
    pytest.importorskip("aefabmap_msgs.msg")
    folder = tmp_path / "maps"
    folder.mkdir()
    publisher = write_script(tmp_path, "words_publisher.py", WORDS_PUBLISHER)
    supervisor = write_script(tmp_path, "supervisor.py", SUPERVISED_FABMAP)
    log_path = tmp_path / "launch.log"
    environment = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    with running(publisher, revisit_data.vocabulary_id, "400", "0.05"), log_path.open("w") as log:
        process = subprocess.Popen([sys.executable, str(supervisor), str(revisit_data.model_dir),
                                    str(folder / "map.npz")], stdout=log, stderr=subprocess.STDOUT, text=True,
                                   env=environment)
        try:
            deadline = time.monotonic() + 120
            while "receiving words" not in log_path.read_text():
                assert process.poll() is None and time.monotonic() < deadline, log_path.read_text()[-3000:]
                time.sleep(0.2)
            time.sleep(2.0)  # some places, not saved yet (no periodic saves)
            shutil.rmtree(folder)
            folder.write_text("not a folder any more")
            process.send_signal(signal.SIGTERM)
            code = process.wait(timeout=120)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    text = log_path.read_text()
    assert "FINAL SAVE FAILED" in text, text[-3000:]
    assert code == 1, text[-3000:]
    assert "ERROR: fabmap_node exited with code 1 during shutdown (its state may not be saved)" in text, text[-3000:]
