"""aefabmap_launch: start the loop-closure nodes as separate processes (no ros2 launch needed).

The pip-installed counterpart of ``launch/aefabmap.launch.py``: same parameter file, same topics,
same nodes (both take them from ``aefabmap_ros.launch_table``). By default verifier_node runs
beside feature, quantizer and FAB-MAP nodes: FAB-MAP's raw closures go to
``loop_closure_candidates`` and only the geometrically verified ones reach ``loop_closures``.
--no-verify leaves the verifier out and remaps FAB-MAP's candidates onto ``loop_closures``
(``inliers`` -1: not verified). With --map, the map and the verifier's feature store (folder
``<map>.features``) are saved and reloaded, so both survive a restart. Ctrl-C (or SIGTERM) stops
every node cleanly; if one node dies, the others are stopped and the exit code is 1.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType

from aefabmap_ros.launch_table import DETECTION_NODES, NodeLaunch, SuiteOptions, suite_nodes

NODES = DETECTION_NODES


def default_params_file() -> Path:
    candidates = [Path(__file__).resolve().parents[2] / "config" / "aefabmap.yaml",
                  Path(sys.prefix) / "share" / "aefabmap_ros" / "config" / "aefabmap.yaml"]
    return next((path for path in candidates if path.exists()), candidates[0])


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
    parser.add_argument("--verify", action=argparse.BooleanOptionalAction, default=True,
                        help="run verifier_node: only geometrically verified closures on loop_closures (default); "
                        "--no-verify: FAB-MAP's raw closures on loop_closures instead (inliers -1)")
    parser.add_argument("--backend", action="store_true",
                        help="also run pose_graph_node, the example SLAM backend (odometry on odom; "
                        "publishes pose_graph/path and map -> odom)")
    return parser


def _ros_args(params: Path, parameters: dict[str, str], remaps: dict[str, str]) -> list[str]:
    return (["--ros-args", "--params-file", str(params)]
            + [arg for name, value in parameters.items() for arg in ("-p", f"{name}:={value}")]
            + [arg for topic, target in remaps.items() for arg in ("-r", f"{topic}:={target}")])


def node_commands(args: argparse.Namespace) -> list[list[str]]:
    """One command per process: the nodes of ``launch_table.suite_nodes``, the three detection
    nodes merged into one aefabmap_pipeline process with --pipeline."""
    params = args.params or default_params_file()
    nodes = suite_nodes(SuiteOptions(model_dir=str(args.model), map_file=str(args.map) if args.map else "",
                                     image_topic=args.image_topic, image_qos=args.image_qos or "",
                                     verify=args.verify, backend=args.backend))
    if not args.pipeline:
        return [[sys.executable, "-m", node.module, *_ros_args(params, node.parameters, node.remaps)]
                for node in nodes]
    # In one process, -p and -r apply to all three nodes; each uses only the names it knows.
    detection = [node for node in nodes if node.name in NODES]
    merged = NodeLaunch("pipeline", {k: v for node in detection for k, v in node.parameters.items()},
                        {k: v for node in detection for k, v in node.remaps.items()})
    return [[sys.executable, "-m", merged.module, *_ros_args(params, merged.parameters, merged.remaps)]] + [
        [sys.executable, "-m", node.module, *_ros_args(params, node.parameters, node.remaps)]
        for node in nodes if node.name not in NODES
    ]


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
