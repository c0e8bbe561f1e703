"""Pipeline benchmark: per-stage latency in one process, and images/s through the ROS nodes.

For each feature type (SIFT, ORB) on synthetic 640 x 480 frames:
1. per-stage latency (median, p95) of decode, feature extraction, quantization and FAB-MAP 2,
   called directly (no ROS);
2. end-to-end throughput: the bag is replayed as fast as possible (--rate 0) into the three
   nodes as separate processes (aefabmap_launch), and the arrival times of the place posteriors
   give images/s. Every process shares this machine's cores, as on a robot's computer.

The model is a vocabulary of descriptors sampled from the first half of the frames (no
clustering: timing only) unless --model names a trained one.
"""

from __future__ import annotations

import argparse
import array
import contextlib
import functools
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, MutableMapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from aefabmap_ros.cli.bench_processes import NodeProcessSampler, ProcessUsage
from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.town import generate_sequence
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.io.bags import read_messages, write_image_bag
from aefabmap_ros.io.image_encodings import image_to_gray
from aefabmap_ros.model.directory import Model, load_model, save_model
from aefabmap_ros.model.training import sampled_centres_model
from aefabmap_ros.nodes.launch_table import DETECTION_NODES, threads_per_process

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


def _ms_since(started: float) -> float:
    return (time.perf_counter() - started) * 1e3


def _summary(values_ms: list[float]) -> str:
    return f"median {np.median(values_ms):7.2f} ms  p95 {np.percentile(values_ms, 95):7.2f} ms"


@contextlib.contextmanager
def thread_pools_of_a_node_process() -> Iterator[int]:
    """Cap BLAS/OpenMP pools (numpy, scipy, faiss) and torch's to what each node process gets under
    aefabmap_launch (its share of the cores), so the one-process stage timings are the nodes' own:
    uncapped, torch's pool spun against everything else on a shared machine (a 29 ms quantization
    measured 232 ms)."""
    share = threads_per_process(len(DETECTION_NODES))
    torch = sys.modules.get("torch")  # only an autoencoder model has imported it
    torch_threads = torch.get_num_threads() if torch is not None else 0
    with threadpool_limits(limits=share):
        if torch is not None:
            torch.set_num_threads(share)
        try:
            yield share
        finally:
            if torch is not None:
                torch.set_num_threads(torch_threads)


def stage_latencies(model: Model, images: list[np.ndarray]) -> dict[str, list[float]]:
    assert model.tree_matrix is not None
    recognizer = PlaceRecognizer(ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples,
                                 FabMapConfig(), model.vocabulary_id)
    stages: dict[str, list[float]] = {"decode": [], "features": [], "quantize": [], "fabmap": []}
    # An autoencoder vocabulary quantizing with its distilled encoder: time the paper's network too.
    network = None
    if getattr(model.quantizer, "student", None) is not None:
        from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer  # torch: only for this kind

        assert isinstance(model.quantizer, AutoencoderQuantizer)
        network = model.quantizer.with_student(None)
        stages["quantize (paper's network)"] = []
    for index, image in enumerate(images):
        height, width = image.shape[:2]
        raw = image.tobytes()
        started = time.perf_counter()
        gray = image_to_gray(raw, "mono8", height, width, width)
        stages["decode"].append(_ms_since(started))
        started = time.perf_counter()
        features = extract_features(gray, model.feature_config)
        stages["features"].append(_ms_since(started))
        started = time.perf_counter()
        words = np.unique(model.quantizer.quantize(features.descriptors))
        stages["quantize"].append(_ms_since(started))
        if network is not None:  # the reference setting on the same descriptors, for the ratio
            started = time.perf_counter()
            network.quantize(features.descriptors)
            stages["quantize (paper's network)"].append(_ms_since(started))
        started = time.perf_counter()
        recognizer.process(words, index * 100_000_000)
        stages["fabmap"].append(_ms_since(started))
    return stages


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


def camera_rate(setup: Setup, model_dir: Path, images: list[np.ndarray], work: Path, rate_hz: float) -> RunResult:
    """A live camera at ``rate_hz``: images with sensor-data QoS stamped when sent, latency from that
    stamp to the place posterior's arrival (same clock, this process), frames without a posterior
    counted as dropped. The nodes keep the parameter file's defaults (feature_node: sensor_data)."""
    import rclpy
    from aefabmap_msgs.msg import PlacePosterior
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from aefabmap_ros.nodes.common import RESULT_QOS

    params = work / "params_camera.yaml"
    params.write_text(CAMERA_PARAMS)
    log = (work / "launch_camera.log").open("w")
    launch = _launch(setup, model_dir, params, log)
    sampler = NodeProcessSampler(launch.pid)
    sampler.start()
    rclpy.init()
    node = rclpy.create_node("aefabmap_bench_camera")
    arrivals: dict[int, int] = {}  # image stamp (ns) -> posterior arrival (ns)
    node.create_subscription(PlacePosterior, "place_posteriors",
                             lambda m: arrivals.setdefault(m.header.stamp.sec * 1_000_000_000
                                                           + m.header.stamp.nanosec, time.time_ns()),
                             RESULT_QOS)
    publisher = node.create_publisher(Image, "image", qos_profile_sensor_data)
    messages = []
    for gray in images:
        message = Image(height=gray.shape[0], width=gray.shape[1], encoding="mono8", step=gray.shape[1])
        message.data = array.array("B", gray.tobytes())
        messages.append(message)

    def send(message: Any) -> int:
        stamp = time.time_ns()
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        publisher.publish(message)
        return stamp

    try:
        # Warm up until the whole chain answers (discovery), slowly, so nothing queues.
        deadline = time.monotonic() + 180
        while not arrivals:
            if time.monotonic() > deadline or launch.poll() is not None:
                raise RuntimeError(f"the nodes never answered: {(work / 'launch_camera.log').read_text()[-2000:]}")
            send(messages[0])
            rclpy.spin_once(node, timeout_sec=0.5)
        end_warm_up = time.monotonic() + 2.0
        while time.monotonic() < end_warm_up:
            rclpy.spin_once(node, timeout_sec=0.1)
        sampler.mark()
        sent: list[int] = []
        started = time.monotonic()
        for index, message in enumerate(messages):
            while (wait := started + index / rate_hz - time.monotonic()) > 0:
                rclpy.spin_once(node, timeout_sec=wait)
            sent.append(send(message))
        idle_until = time.monotonic() + 5.0
        count = len(arrivals)
        while time.monotonic() < idle_until:
            rclpy.spin_once(node, timeout_sec=0.1)
            if len(arrivals) != count:
                count, idle_until = len(arrivals), time.monotonic() + 5.0
        usage = sampler.stop()
    finally:
        sampler.stop()
        node.destroy_node()
        rclpy.try_shutdown()
        _stop([launch])
        log.close()
    latencies = [(arrivals[stamp] - stamp) / 1e6 for stamp in sent if stamp in arrivals]
    answered = sorted(arrivals[stamp] for stamp in sent if stamp in arrivals)
    rate = 0.0 if len(answered) < 2 else (len(answered) - 1) / ((answered[-1] - answered[0]) / 1e9)
    drops = node_drops((work / "launch_camera.log").read_text())
    return RunResult(rate, len(latencies), len(sent), usage, latencies, drops)


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


def _through_nodes(setups: list[Setup], repeats: int,
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
            print(f"{line}  [load {_load()}]\n      {_usage_text(result)}", flush=True)
    return results


def _print_ratios(results: dict[Setup, list[RunResult]]) -> None:
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


def _load() -> str:
    return " ".join(f"{value:.2f}" for value in os.getloadavg())


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bench pipeline", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200, help="synthetic frames (default 200)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--size", type=int, default=1000, help="words of the sampled vocabulary")
    parser.add_argument("--features", nargs="+", default=["sift", "orb"], choices=["sift", "rootsift", "orb"])
    parser.add_argument("--model", type=Path, help="use this trained model (its feature type) instead")
    parser.add_argument("--no-ros", action="store_true", help="per-stage latency only")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="source tree of the code to compare with (e.g. a worktree of an older commit): its "
                        "nodes run with this tree's messages, and images/s are given as ratios against it")
    parser.add_argument("--baseline-model", type=Path, default=None,
                        help="model directory the baseline's nodes load (default: --model); e.g. the same "
                        "vocabulary without its distilled encoder, for code that predates it")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each setup, interleaved (default 2)")
    parser.add_argument("--rate", type=float, default=0.0,
                        help="0 (default): replay as fast as possible, reliable QoS, images/s; > 0: a camera at "
                        "this many Hz with sensor-data QoS, latency image stamp -> posterior and drops")
    parser.add_argument("--no-pipeline", action="store_true",
                        help="only the three-process launch, not also the one-process --pipeline")
    parser.add_argument("--quick", action="store_true", help="seconds-long smoke run (small frames, no ROS)")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


def isolate_ros_domain(environment: MutableMapping[str, str], pid: int) -> str:
    """Give this run's nodes, recorder and replay a DDS domain of their own (unless the caller chose one), on
    this host only: two benchmarks on one machine, or a benchmark beside running nodes, answered each other's
    images otherwise (measured: 528 posteriors recorded for 150 images). Returns the domain id."""
    environment.setdefault("ROS_DOMAIN_ID", str(1 + pid % 100))  # 0-101: the ids ROS 2 documents as safe
    environment.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return environment["ROS_DOMAIN_ID"]


def run(args: argparse.Namespace) -> int:
    if args.baseline is not None and not (args.baseline / "aefabmap_ros" / "cli" / "launch.py").is_file():
        raise ConfigError(f"--baseline {args.baseline} is not an aefabmap_ros source tree")
    if args.baseline_model is not None and (args.baseline is None or args.model is None):
        raise ConfigError("--baseline-model needs --baseline and --model")
    if args.baseline_model is not None and not (args.baseline_model / "metadata.json").is_file():
        raise ConfigError(f"--baseline-model {args.baseline_model} is not a model directory")
    if args.repeats < 1 or args.rate < 0:
        raise ConfigError("--repeats must be >= 1 and --rate >= 0")
    if args.quick:
        args.frames, args.width, args.height, args.size, args.no_ros = 24, 320, 240, 100, True

    domain = isolate_ros_domain(os.environ, os.getpid())  # inherited by every process the run starts
    sequence = generate_sequence(SynthConfig(num_frames=args.frames, width=args.width, height=args.height))
    images = sequence.images
    print(f"{len(images)} synthetic frames {args.width}x{args.height}; "
          f"{'model ' + str(args.model) if args.model else f'sampled {args.size}-word vocabulary'}; "
          f"{'baseline model ' + str(args.baseline_model) + '; ' if args.baseline_model else ''}"
          f"{os.cpu_count()} cores, load average {_load()}, ROS domain {domain}")
    setups = [Setup("this", None, pipeline) for pipeline in ([False] if args.no_pipeline else [False, True])]
    if args.baseline is not None:
        setups += [Setup("baseline", args.baseline.resolve(), setup.pipeline, args.baseline_model)
                   for setup in setups]
    with tempfile.TemporaryDirectory(prefix="aefabmap_bench_") as tmp:
        work = Path(tmp)
        bag = work / "bag"
        write_image_bag(bag, "/image", zip(sequence.stamps_ns.tolist(), images, strict=True))
        runs = [("model", args.model)] if args.model else [(name, None) for name in args.features]
        for name, model_dir in runs:
            if model_dir is None:
                config = FeatureConfig(type=name)
                training = [extract_features(image, config) for image in images[: len(images) // 2]]
                model = sampled_centres_model(training, config, args.size)
                model_dir = work / f"model_{name}"
                save_model(model_dir, model)
            else:
                model = load_model(model_dir)
            label = f"{model.feature_config.type} / {model.quantizer.kind} {model.quantizer.size} words"
            with thread_pools_of_a_node_process() as threads:
                stages = stage_latencies(model, images)
            total = np.sum([stages[s] for s in ("decode", "features", "quantize", "fabmap")], axis=0)
            print(f"\n[{label}] per-stage latency, one process, {len(images)} images, "
                  f"{threads}-thread BLAS/torch pools (a node process's share under aefabmap_launch)")
            for stage, values in stages.items():
                print(f"  {stage:9s} {_summary(values)}")
            print(f"  {'total':9s} {_summary(list(total))}  -> {1e3 / np.median(total):.1f} images/s on one core")
            if args.no_ros:
                continue
            if args.rate > 0:
                print(f"\n[{label}] through the nodes: camera at {args.rate:g} Hz, sensor-data QoS, "
                      f"{len(images)} images")
                results = _through_nodes(setups, args.repeats,
                                         functools.partial(camera_rate, model_dir=model_dir, images=images, work=work,
                                                           rate_hz=args.rate))
            else:
                print(f"\n[{label}] through the nodes: replay as fast as possible, reliable QoS, {len(images)} images")
                results = _through_nodes(setups, args.repeats,
                                         functools.partial(throughput, model_dir=model_dir, bag=bag, work=work,
                                                           num_frames=len(images)))
            _print_ratios(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
