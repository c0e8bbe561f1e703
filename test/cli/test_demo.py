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
