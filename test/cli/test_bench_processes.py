"""The benchmark's /proc sampler finds the node processes under a launcher and their CPU time."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from aefabmap_ros.cli.bench_processes import NodeProcessSampler

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads Linux's /proc")

BUSY_CHILD = """
import sys
sys.stdin.readline()  # start the work only after the sampler's mark
total = sum(i * i for i in range(3_000_000))
print(total, flush=True)
sys.stdin.readline()  # stay alive until the test has sampled
"""


def test_sampler_reports_cpu_since_the_mark_and_threads_of_node_processes() -> None:
    sampler = NodeProcessSampler(launcher_pid=os.getpid())  # this test process plays the launcher
    children = [
        subprocess.Popen([sys.executable, "-c", BUSY_CHILD, "aefabmap_ros.nodes.fake_node"],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True),
        subprocess.Popen([sys.executable, "-c", BUSY_CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         text=True),  # not a node: not listed
    ]
    try:
        sampler.mark()
        for child in children:
            assert child.stdin is not None and child.stdout is not None
            child.stdin.write("go\n")
            child.stdin.flush()
            assert child.stdout.readline().strip()  # the work is done
        usage = sampler.stop()
    finally:
        for child in children:
            assert child.stdin is not None
            child.stdin.close()
            child.wait()
    assert [entry.name for entry in usage] == ["fake_node"]
    assert usage[0].marked and usage[0].cpu_since_mark_s() > 0
    assert usage[0].max_threads >= 1
