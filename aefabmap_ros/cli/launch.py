"""aefabmap_launch: start feature, quantizer and FAB-MAP nodes as separate processes (no ros2 launch needed).

The pip-installed counterpart of ``launch/aefabmap.launch.py``: same parameter file, same topics.
Ctrl-C (or SIGTERM) stops every node cleanly, so the FAB-MAP node saves its map; if one node dies,
the others are stopped and the exit code is 1. With --verify, verifier_node runs beside them and
publishes the geometrically verified loop closures on ``verified_loop_closures``; with --map too,
its feature store is saved beside the map (folder ``<map>.features``), so both survive a restart.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType

NODES = ("feature_node", "quantizer_node", "fabmap_node")


def default_params_file() -> Path:
    candidates = [Path(__file__).resolve().parents[2] / "config" / "aefabmap.yaml",
                  Path(sys.prefix) / "share" / "aefabmap_ros" / "config" / "aefabmap.yaml"]
    return next((path for path in candidates if path.exists()), candidates[0])


def verifier_store_path(map_path: Path) -> Path:
    """Where verifier_node keeps its feature store beside a FAB-MAP map: office.npz -> office.features/."""
    return map_path.with_suffix(".features")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="aefabmap_launch", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True, help="model directory (from aefabmap_train)")
    parser.add_argument("--params", type=Path, default=None, help="parameter YAML (default: config/aefabmap.yaml)")
    parser.add_argument("--map", type=Path, default=None, help="map file to save to / reload from")
    parser.add_argument("--image-topic", default="image", help="camera image topic (default: image)")
    parser.add_argument("--image-qos", choices=("sensor_data", "reliable"), default=None,
                        help="override the image subscription QoS")
    parser.add_argument("--pipeline", action="store_true", help="run all three nodes in one process instead")
    parser.add_argument("--verify", action="store_true",
                        help="also run verifier_node: geometrically verified closures on verified_loop_closures")
    return parser


def node_commands(args: argparse.Namespace) -> list[list[str]]:
    params = args.params or default_params_file()
    common = ["--ros-args", "--params-file", str(params), "-p", f"model_dir:={args.model}"]
    extra = {
        "feature_node": ["-r", f"image:={args.image_topic}"]
        + (["-p", f"image_qos:={args.image_qos}"] if args.image_qos else []),
        "quantizer_node": [],
        "fabmap_node": ["-p", f"map_file:={args.map}"] if args.map else [],
    }
    store = ["-p", f"store_dir:={verifier_store_path(args.map)}"] if args.map else []
    verifier = ([[sys.executable, "-m", "aefabmap_ros.nodes.verifier_node", "--ros-args", "--params-file", str(params),
                  *store]] if args.verify else [])
    if args.pipeline:
        merged = [arg for node in NODES for arg in extra[node]]
        return [[sys.executable, "-m", "aefabmap_ros.nodes.pipeline", *common, *merged], *verifier]
    return [[sys.executable, "-m", f"aefabmap_ros.nodes.{node}", *common, *extra[node]] for node in NODES] + verifier


def supervise(commands: list[list[str]]) -> int:
    processes = [subprocess.Popen(command) for command in commands]
    stopping = False

    def stop(_signum: int, _frame: FrameType | None) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    exit_code = 0
    try:
        while not stopping:
            failed = [p for p in processes if p.poll() not in (None, 0)]
            if failed:
                exit_code = 1
                print(f"ERROR: a node exited with code {failed[0].returncode}: {failed[0].args!r}",
                      file=sys.stderr)
                break
            if all(p.poll() is not None for p in processes):
                break
            time.sleep(0.2)
    finally:
        for process in processes:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)  # nodes save state on a clean shutdown
        for process in processes:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    return exit_code


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not args.model.is_dir():
        print(f"ERROR: --model {args.model} is not a directory (train one with aefabmap_train)", file=sys.stderr)
        return 1
    params = args.params or default_params_file()
    if not params.is_file():
        print(f"ERROR: --params {params} does not exist", file=sys.stderr)
        return 1
    return supervise(node_commands(args))


if __name__ == "__main__":
    raise SystemExit(main())
