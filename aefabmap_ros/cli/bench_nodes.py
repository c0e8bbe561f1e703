"""The pipeline through the ROS nodes, for ``aefabmap_bench pipeline``: images/s with a bag replayed as fast
as possible (``throughput``) or latency and drops from a live camera (``camera_rate``), each setup (this
code or a baseline's, three node processes or one) run in turn, with its processes' CPU use."""

from __future__ import annotations

import array
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.cli.bench_processes import NodeProcessSampler, ProcessUsage
from aefabmap_ros.io.bags import read_messages

PARAMS = """
feature_node:
  ros__parameters: {image_qos: reliable, queue_depth: 1000, drop_when_busy: false, detection_rate_hz: 0.0}
quantizer_node:
  ros__parameters: {queue_depth: 1000, drop_when_busy: false}
fabmap_node:
  ros__parameters: {queue_depth: 1000}
"""
CAMERA_PARAMS = """
feature_node:
  ros__parameters: {image_qos: sensor_data}
"""



@dataclass(frozen=True)
class Setup:
    """One way of running the nodes: whose code (``source`` on PYTHONPATH; None = this code) and how."""

    code: str  # "this" or "baseline"
    source: Path | None
    pipeline: bool  # one aefabmap_pipeline process instead of three node processes
    model: Path | None = None  # the model directory its nodes load (None: the run's model)

    @property
    def label(self) -> str:
        return f"{self.code:8s} {'1 process ' if self.pipeline else '3 processes'}"


@dataclass
class RunResult:
    images_per_s: float
    received: int
    sent: int
    usage: list[ProcessUsage]
    latencies_ms: list[float] = field(default_factory=list)
    drops: dict[str, int] = field(default_factory=dict)  # "node reason" -> count, from the nodes' summaries


def _launch(setup: Setup, model_dir: Path, params: Path, log: Any) -> subprocess.Popen[bytes]:
    environment = dict(os.environ)
    if setup.source is not None:  # the baseline's package first on the path: its nodes, our messages
        environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(setup.source), environment.get("PYTHONPATH")]))
    command = [sys.executable, "-m", "aefabmap_ros.cli.launch", "--model", str(setup.model or model_dir),
               "--params", str(params),
               "--no-verify"] + (["--pipeline"] if setup.pipeline else [])
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=environment,
                            cwd=setup.source or None)


def _stop(processes: list[subprocess.Popen[bytes]]) -> None:
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def throughput(setup: Setup, model_dir: Path, bag: Path, work: Path, num_frames: int) -> RunResult:
    """Images/s through the nodes with the bag replayed as fast as possible (reliable, lossless)."""
    params = work / "params.yaml"
    params.write_text(PARAMS)
    recording = work / "recording"
    shutil.rmtree(recording, ignore_errors=True)
    python = sys.executable
    logs = (work / "launch.log").open("w"), (work / "record.log").open("w")
    launch = _launch(setup, model_dir, params, logs[0])
    sampler = NodeProcessSampler(launch.pid)
    sampler.start()
    record = subprocess.Popen([python, "-m", "aefabmap_ros.cli.record", str(recording), "--topics",
                               "place_posteriors", "--wait-publishers", "60", "--idle-timeout", "10"],
                              stdout=logs[1], stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while "[record] recording" not in (work / "record.log").read_text():
            if time.monotonic() > deadline or record.poll() is not None:
                raise RuntimeError(f"recorder did not start: {(work / 'record.log').read_text()[-2000:]}")
            time.sleep(0.2)
        sampler.mark()
        subprocess.run([python, "-m", "aefabmap_ros.cli.replay", str(bag), "--topic", "/image", "--rate", "0",
                        "--queue-depth", str(num_frames + 10), "--quiet", "--wait-timeout", "60"], check=True)
        record.wait(timeout=600)
        usage = sampler.stop()
    finally:
        sampler.stop()
        _stop([record, launch])
        for log in logs:
            log.close()
    arrivals = np.array([m.log_time_ns for m in read_messages(recording, ["/place_posteriors"])], dtype=np.float64)
    rate = 0.0 if arrivals.size < 2 else (arrivals.size - 1) / ((arrivals[-1] - arrivals[0]) / 1e9)
    return RunResult(rate, int(arrivals.size), num_frames, usage)


class _LiveCamera:
    """A node that publishes images as a camera does (sensor-data QoS, stamped when sent) and notes when the
    place posterior of each image arrives (same clock, this process)."""

    def __init__(self, images: list[np.ndarray]) -> None:
        import rclpy
        from aefabmap_msgs.msg import PlacePosterior
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Image

        from aefabmap_ros.nodes.common import RESULT_QOS

        self._spin_once = rclpy.spin_once
        self.node = rclpy.create_node("aefabmap_bench_camera")
        self.arrivals: dict[int, int] = {}  # image stamp (ns) -> posterior arrival (ns)
        self.node.create_subscription(PlacePosterior, "place_posteriors", self._arrived, RESULT_QOS)
        self._publisher = self.node.create_publisher(Image, "image", qos_profile_sensor_data)
        self.messages = []
        for gray in images:
            message = Image(height=gray.shape[0], width=gray.shape[1], encoding="mono8", step=gray.shape[1])
            message.data = array.array("B", gray.tobytes())
            self.messages.append(message)

    def _arrived(self, message: Any) -> None:
        self.arrivals.setdefault(message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec,
                                 time.time_ns())

    def send(self, message: Any) -> int:
        stamp = time.time_ns()
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        self._publisher.publish(message)
        return stamp

    def spin(self, seconds: float) -> None:
        self._spin_once(self.node, timeout_sec=seconds)

    def warm_up(self, launch: subprocess.Popen[bytes], log: Path) -> None:
        """Send the first image slowly until the whole chain answers (discovery), so nothing queues."""
        deadline = time.monotonic() + 180
        while not self.arrivals:
            if time.monotonic() > deadline or launch.poll() is not None:
                raise RuntimeError(f"the nodes never answered: {log.read_text()[-2000:]}")
            self.send(self.messages[0])
            self.spin(0.5)
        end_warm_up = time.monotonic() + 2.0
        while time.monotonic() < end_warm_up:
            self.spin(0.1)

    def send_all(self, rate_hz: float) -> list[int]:
        """Every image at ``rate_hz``; the stamps sent."""
        sent: list[int] = []
        started = time.monotonic()
        for index, message in enumerate(self.messages):
            while (wait := started + index / rate_hz - time.monotonic()) > 0:
                self.spin(wait)
            sent.append(self.send(message))
        return sent

    def wait_until_idle(self, idle_s: float) -> None:
        """Spin until no posterior has arrived for ``idle_s``."""
        idle_until = time.monotonic() + idle_s
        count = len(self.arrivals)
        while time.monotonic() < idle_until:
            self.spin(0.1)
            if len(self.arrivals) != count:
                count, idle_until = len(self.arrivals), time.monotonic() + idle_s


def camera_rate(setup: Setup, model_dir: Path, images: list[np.ndarray], work: Path, rate_hz: float) -> RunResult:
    """A live camera at ``rate_hz``: images with sensor-data QoS stamped when sent, latency from that
    stamp to the place posterior's arrival (same clock, this process), frames without a posterior
    counted as dropped. The nodes keep the parameter file's defaults (feature_node: sensor_data)."""
    import rclpy

    params = work / "params_camera.yaml"
    params.write_text(CAMERA_PARAMS)
    log_path = work / "launch_camera.log"
    log = log_path.open("w")
    launch = _launch(setup, model_dir, params, log)
    sampler = NodeProcessSampler(launch.pid)
    sampler.start()
    rclpy.init()
    camera = _LiveCamera(images)
    try:
        camera.warm_up(launch, log_path)
        sampler.mark()
        sent = camera.send_all(rate_hz)
        camera.wait_until_idle(5.0)
        usage = sampler.stop()
    finally:
        sampler.stop()
        camera.node.destroy_node()
        rclpy.try_shutdown()
        _stop([launch])
        log.close()
    arrivals = camera.arrivals
    latencies = [(arrivals[stamp] - stamp) / 1e6 for stamp in sent if stamp in arrivals]
    answered = sorted(arrivals[stamp] for stamp in sent if stamp in arrivals)
    rate = 0.0 if len(answered) < 2 else (len(answered) - 1) / ((answered[-1] - answered[0]) / 1e9)
    return RunResult(rate, len(latencies), len(sent), usage, latencies, node_drops(log_path.read_text()))


def node_drops(log: str) -> dict[str, int]:
    """Each node's drop counters from the summary line it logs when it stops ("<node>: a=1, dropped_b=2"):
    where the frames that got no posterior were lost ({"feature_node busy": 48, ...})."""
    drops: dict[str, int] = {}
    for node, counts in re.findall(r"\b(\w+_node): ((?:\w+=\d+(?:, )?)+)$", log, flags=re.MULTILINE):
        for reason, value in re.findall(r"dropped_(\w+)=(\d+)", counts):
            drops[f"{node} {reason}"] = int(value)
    return drops


def _usage_text(result: RunResult) -> str:
    received = max(1, result.received)
    return "; ".join(f"{entry.name} {1e3 * entry.cpu_since_mark_s() / received:.1f} ms CPU/image, "
                     f"{entry.max_threads} threads" for entry in result.usage)


def through_nodes(setups: list[Setup], repeats: int,
                   run: Callable[[Setup], RunResult]) -> dict[Setup, list[RunResult]]:
    """Every setup ``repeats`` times, interleaved, so a change of the machine's load hits all alike."""
    results: dict[Setup, list[RunResult]] = {setup: [] for setup in setups}
    for repeat in range(repeats):
        for setup in setups:
            result = run(setup)
            results[setup].append(result)
            line = (f"  {setup.label} run {repeat + 1}: {result.images_per_s:6.1f} images/s "
                    f"({result.received}/{result.sent} answered)")
            if result.latencies_ms:
                line += (f", latency p50 {np.percentile(result.latencies_ms, 50):.0f} ms "
                         f"p95 {np.percentile(result.latencies_ms, 95):.0f} ms, "
                         f"dropped {result.sent - result.received}")
                if result.drops:
                    line += " (" + ", ".join(f"{where} {count}" for where, count in result.drops.items()) + ")"
            print(f"{line}  [load {load_average()}]\n      {_usage_text(result)}", flush=True)
    return results


def print_ratios(results: dict[Setup, list[RunResult]]) -> None:
    median = {setup: float(np.median([r.images_per_s for r in runs])) for setup, runs in results.items()}
    for setup, value in median.items():
        print(f"  median {setup.label}: {value:6.1f} images/s")
    for setup, value in median.items():
        if setup.code != "this":
            continue
        for other, other_value in median.items():
            if other != setup and other_value > 0 and ((other.code == "baseline" and other.pipeline == setup.pipeline)
                                                      or other.code == "this"):
                print(f"  ratio {' '.join(setup.label.split())} / {' '.join(other.label.split())}: "
                      f"{value / other_value:.2f}x")


def load_average() -> str:
    return " ".join(f"{value:.2f}" for value in os.getloadavg())
