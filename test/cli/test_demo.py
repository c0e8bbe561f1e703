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

    from aefabmap_ros.cli.demo import ClosurePrinter

    gt = np.zeros((30, 30), np.uint8)
    for query, place in ((10, 1), (11, 2), (12, 3), (20, 4), (21, 5)):
        gt[query, place] = 1
    printer = ClosurePrinter.__new__(ClosurePrinter)  # no ROS: only the bookkeeping
    printer._gt = gt
    printer.posteriors = 30
    printer.closures = [(11, 2, True), (25, 0, False)]
    printer.candidates = [(11, 2, True), (12, 9, False), (25, 0, False)]
    assert printer.summary(min_gap=5).splitlines() == [
        "    2 loop closures published on /loop_closures (verified), 1 false; 1 of 2 revisit events closed",
        "    3 raw FAB-MAP candidates on /loop_closure_candidates, 2 false; 30 posteriors",
    ]
