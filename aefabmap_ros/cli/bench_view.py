"""What the live view costs when nobody watches: images/s and CPU through the nodes with and without it.

Each run replays a bag in lockstep (each image once the last one's posterior came: every frame, none
lost) into aefabmap_launch (the suite as it starts by default, verifier_node included; --no-verify: the
three detection nodes alone), alternately without and with --view (closure_view_node and the
aefabmap_view server, no client connected). The runs alternate in one invocation so both kinds share the
machine's load; it prints each run's images/s and the CPU seconds of every process the launcher started,
then the ratios of the with-view runs to the runs beside them. The view's CPU is its two processes' and
the frame views feature_node makes for it (its shutdown summary gives their CPU time).

    python -m aefabmap_ros.cli.bench_view --model output/demo/models/autoencoder \\
        --bag bags/generated/test/bag --repeats 2

--picture-delays RECORDING instead prints how long after each closure its picture came, as the recorder (a
client like any other) received both: e.g. the demo's output/demo/online_recording.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aefabmap_ros.cli.bench_processes import NodeProcessSampler, ProcessUsage
from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io.bags import read_messages
from aefabmap_ros.stamps import stamp_to_ns

VIEW_PROCESSES = ("closure_view_node", "view")
VIEW_READY = ("closure_view_node]: receiving frame views", "[view] serving")  # the two run and hear the suite
FRAME_VIEWS_CPU = re.compile(r"frame views took ([0-9.]+) s of CPU")  # feature_node's shutdown summary


@dataclass(frozen=True)
class ViewRun:
    view: bool
    images: int
    seconds: float
    usage: list[ProcessUsage]
    frame_views_cpu_s: float  # feature_node's, for the view: part of cpu_s already (feature_node is in usage)

    @property
    def images_per_s(self) -> float:
        return self.images / self.seconds

    @property
    def cpu_s(self) -> float:
        return sum(entry.cpu_since_mark_s() for entry in self.usage)

    @property
    def view_cpu_s(self) -> float:
        return self.frame_views_cpu_s + sum(entry.cpu_since_mark_s() for entry in self.usage
                                          if entry.name in VIEW_PROCESSES)


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="bench_view", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, help="model directory (aefabmap_train)")
    parser.add_argument("--bag", type=Path, help="bag with images on --topic")
    parser.add_argument("--picture-delays", type=Path, metavar="RECORDING",
                        help="only print the closure -> picture delays of a recording (aefabmap_demo's)")
    parser.add_argument("--topic", default="/image")
    parser.add_argument("--no-verify", action="store_true",
                        help="the detection nodes alone (no verifier_node): the view's share of a smaller suite")
    parser.add_argument("--repeats", type=int, default=2, help="pairs of runs (default 2)")
    parser.add_argument("--work", type=Path, default=Path("/tmp") / f"bench_view-{os.getpid()}")
    return parser


def one_run(args: argparse.Namespace, view: bool, images: int) -> ViewRun:
    from aefabmap_ros.io.config_files import shipped_config

    args.work.mkdir(parents=True, exist_ok=True)
    log_path = args.work / f"launch-{'view' if view else 'plain'}.log"
    python = sys.executable
    with log_path.open("w") as log:
        launch = subprocess.Popen([python, "-m", "aefabmap_ros.cli.launch", "--model", str(args.model), "--params",
                                   str(shipped_config("demo.yaml")), *(["--no-verify"] if args.no_verify else []),
                                   "--image-qos", "reliable", *(["--view", "--view-port", "0"] if view else [])],
                                  stdout=log, stderr=subprocess.STDOUT)
        sampler = NodeProcessSampler(launch.pid)
        sampler.start()
        try:
            # Counting starts once every process is up: start-up (imports, model loading) is no per-image cost.
            for ready in ("fabmap_node]: receiving words", *(VIEW_READY if view else ())):
                _wait_for(log_path, ready, launch)
            sampler.mark()
            started = time.monotonic()
            subprocess.run([python, "-m", "aefabmap_ros.cli.replay", str(args.bag), "--topic", args.topic,
                            "--lockstep", "place_posteriors", "--wait-subscribers", "1",
                            "--quiet", "--wait-timeout", "120"], check=True)
            seconds = time.monotonic() - started
            usage = sampler.stop()
        finally:
            sampler.stop()
            launch.send_signal(2)
            launch.wait(timeout=180)
    frame_views = FRAME_VIEWS_CPU.findall(log_path.read_text())
    return ViewRun(view, images, seconds, usage, sum(float(value) for value in frame_views))


def _wait_for(log: Path, text: str, process: subprocess.Popen[bytes], timeout_s: float = 300.0) -> None:
    deadline = time.monotonic() + timeout_s
    while text not in log.read_text():
        if process.poll() is not None or time.monotonic() > deadline:
            raise ConfigError(f"the nodes did not start; {log}:\n{log.read_text()[-2000:]}")
        time.sleep(0.2)


def describe(run: ViewRun) -> str:
    processes = ", ".join(f"{entry.name} {entry.cpu_since_mark_s():.1f}" for entry in run.usage)
    label = "with view   " if run.view else "without view"
    return (f"{label}: {run.images_per_s:6.2f} images/s, CPU {run.cpu_s:6.1f} s (view {run.view_cpu_s:.2f} s, of "
            f"which feature_node's frame views {run.frame_views_cpu_s:.2f} s; {processes})")


def picture_delays_s(recording: Path) -> tuple[int, np.ndarray]:
    """The closures of a recording and, for each one with a picture (same query stamp), the seconds between the
    recorder receiving the closure and receiving its picture."""
    from aefabmap_ros.nodes.launch_table import CLOSURE_PICTURES_TOPIC, CLOSURES_TOPIC

    arrivals: dict[str, dict[int, int]] = {f"/{CLOSURES_TOPIC}": {}, f"/{CLOSURE_PICTURES_TOPIC}": {}}
    for message in read_messages(recording, list(arrivals)):
        arrivals[message.topic].setdefault(stamp_to_ns(message.message.header.stamp), message.log_time_ns)
    closures, pictures = arrivals[f"/{CLOSURES_TOPIC}"], arrivals[f"/{CLOSURE_PICTURES_TOPIC}"]
    return len(closures), np.array([(pictures[stamp] - closures[stamp]) / 1e9 for stamp in closures
                                    if stamp in pictures])


def print_picture_delays(recording: Path) -> None:
    closures, delays = picture_delays_s(recording)
    if not delays.size:
        raise ConfigError(f"{recording} holds no closure with a picture ({closures} closures)")
    p50, p95 = np.percentile(delays, [50, 95])
    print(f"{closures} closures, {delays.size} with a picture; closure -> picture: median {p50:.3f} s, p95 "
          f"{p95:.3f} s, max {delays.max():.3f} s; {int((delays > 0.5).sum())} over 0.5 s")


def run(args: argparse.Namespace) -> int:
    if args.picture_delays is not None:
        print_picture_delays(args.picture_delays)
        return 0
    if args.model is None or args.bag is None:
        raise ConfigError("give --model and --bag (or --picture-delays RECORDING)")
    if args.repeats < 1:
        raise ConfigError(f"--repeats must be >= 1, got {args.repeats}")
    images = sum(1 for _ in read_messages(args.bag, [args.topic]))
    for repeat in range(args.repeats):
        pair = [one_run(args, view, images) for view in (False, True)]
        for result in pair:
            print(describe(result), flush=True)
        plain, viewed = pair
        print(f"pair {repeat + 1}: images/s with/without {viewed.images_per_s / plain.images_per_s:.3f}; CPU "
              f"with/without {viewed.cpu_s / plain.cpu_s:.3f}; the view's share of the CPU "
              f"{viewed.view_cpu_s / viewed.cpu_s:.2%}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


if __name__ == "__main__":
    raise SystemExit(main())
