"""aefabmap_launch: start the loop-closure nodes as separate processes (no ros2 launch needed).

The pip-installed counterpart of ``launch/aefabmap.launch.py``: same parameter file, same topics,
same nodes (both take them from ``aefabmap_ros.nodes.launch_table``). By default verifier_node runs
beside feature, quantizer and FAB-MAP nodes: FAB-MAP's raw closures go to
``loop_closure_candidates`` and only the geometrically verified ones reach ``loop_closures``.
--no-verify leaves the verifier out and remaps FAB-MAP's candidates onto ``loop_closures``
(``inliers`` -1: not verified). With --map, the map and the verifier's feature store (folder
``<map>.features``) are saved and reloaded, so both survive a restart. Ctrl-C (or SIGTERM) stops
every node cleanly; if one node dies, the others are stopped and the exit code is 1. It is 1 too when
a node exits non-zero while stopping (its final save failed) or is killed: still running after
--stop-timeout seconds without writing to its files, or after 600 s while writing (a large save is waited
for as long as its file grows); each is named in an ERROR line. The nodes die with the launcher (Linux): killed
with SIGKILL, it leaves no node running that a relaunch would duplicate (two FAB-MAP nodes writing one
map).


Several robots and a base station (docs/fleet.md): on each robot,
``aefabmap_launch --robot-side --robot robot1 --model M [--image-topic T --depth-topic D]`` starts its front end
in namespace /robot1 (feature_node, quantizer_node, feature_server_node: the words of every frame go to the
base, features only on request); on the base, ``aefabmap_launch --base --robots robot1,robot2 --model M [--map
office.npz] [--backend]`` starts one map for all of them and the verifier, which publishes inter-robot closures
on loop_closures.

Each node process gets OMP_NUM_THREADS, OPENBLAS_NUM_THREADS, MKL_NUM_THREADS and NUMBA_NUM_THREADS
set to its share of the cores (cores / processes, at least 1) unless you set them yourself, so torch,
OpenBLAS and numba in all the processes together start no more threads than the machine has cores.
"""

from __future__ import annotations

import argparse
import ctypes
import functools
import math
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import FrameType

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.launch_table import (
    DETECTION_NODES,
    ROBOT_NODES,
    NodeLaunch,
    SuiteOptions,
    namespaced_sections,
    params_file_problem,
    parse_robots,
    suite_nodes,
    thread_limits,
)

NODES = DETECTION_NODES
LAUNCH_TEMPORARIES = Path(tempfile.gettempdir()) / f"aefabmap_launch_{os.getpid()}"  # namespaced parameter files


def default_params_file() -> Path:
    from aefabmap_ros.io.config_files import shipped_config  # PyYAML: only when the default is used

    return shipped_config("aefabmap.yaml")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_launch", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True, help="model directory (from aefabmap_train)")
    parser.add_argument("--params", type=Path, default=None,
                        help="parameter YAML (default: the aefabmap.yaml shipped in the package)")
    parser.add_argument("--map", type=Path, default=None,
                        help="map file to save to / reload from; started on a saved map, this run is a new session of "
                        "it (with --backend, the pose graph is kept beside it as <map>.graph.npz)")
    parser.add_argument("--robot", default="", help="this robot's name, kept with its sessions of the map "
                        "(default: '', a map of one robot)")
    parser.add_argument("--image-topic", default="image", help="camera image topic (default: image)")
    parser.add_argument("--image-qos", choices=("auto", "best_effort", "sensor_data", "reliable"), default=None,
                        help="override the image subscription QoS (reliable also processes every frame, in order: "
                        "a lossless replay)")
    topics = parser.add_argument_group("the robot's topics (every input and output can be renamed)")
    topics.add_argument("--camera-info-topic", default="",
                        help="sensor_msgs/CameraInfo for the verifier's poses (default: beside the image topic, "
                        "image_transport's convention: /cam/rgb/image_raw -> /cam/rgb/camera_info)")
    topics.add_argument("--depth-topic", default="",
                        help="aligned depth image (16UC1 mm or 32FC1 m): metric poses and the metric test "
                        "(default: the parameter file's depth_topic)")
    topics.add_argument("--odom-topic", default="",
                        help="nav_msgs/Odometry for the odometry gate and the backend (default: odom)")
    topics.add_argument("--closures-topic", default="",
                        help="where verified loop closures are published (default: loop_closures)")
    topics.add_argument("--sensor-qos", choices=("auto", "best_effort", "sensor_data", "reliable"), default=None,
                        help="QoS of the camera_info, depth and odometry subscriptions (default: the parameter "
                        "file's, auto: adapts to the publishers)")
    topics.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                        help="any other topic, for every node (repeatable), e.g. place_posteriors:=/lc/posteriors")
    _add_fleet_arguments(parser)
    parser.add_argument("--pipeline", action="store_true", help="run all three nodes in one process instead "
                        "(with --robot-side: the robot's three)")
    parser.add_argument("--verify", action=argparse.BooleanOptionalAction, default=True,
                        help="run verifier_node: only geometrically verified closures on loop_closures (default); "
                        "--no-verify: FAB-MAP's raw closures on loop_closures instead (inliers -1)")
    parser.add_argument("--backend", action="store_true",
                        help="also run pose_graph_node, the example SLAM backend (odometry on odom; "
                        "publishes pose_graph/path and map -> odom)")
    parser.add_argument("--pictures", action="store_true",
                        help="also run closure_view_node: each closure (closure_view/closures) and refused candidate "
                        "(closure_view/refused) as a picture with its matches, drawn only while subscribed")
    parser.add_argument("--view", action="store_true",
                        help="--pictures, and serve the suite live to Foxglove (aefabmap_view on --view-port; layout "
                        "aefabmap_ros/config/foxglove_layout.json)")
    parser.add_argument("--view-port", type=int, default=8765, help="aefabmap_view's WebSocket port (default 8765)")
    parser.add_argument("--stop-timeout", type=float, default=STOP_TIMEOUT_S, metavar="SECONDS",
                        help="on Ctrl-C / SIGTERM, wait this long for each node's final save before killing it "
                        f"(default: {STOP_TIMEOUT_S:g}); a node still writing its files then (their size grew in "
                        f"the last {WRITE_WINDOW_S:g} s) is waited for, up to {STOP_WRITING_CAP_S:g} s in all")
    return parser


def _add_fleet_arguments(parser: argparse.ArgumentParser) -> None:
    fleet = parser.add_argument_group("several robots and a base station (docs/fleet.md)")
    side = fleet.add_mutually_exclusive_group()
    side.add_argument("--robot-side", action="store_true",
                      help="this robot's front end for a base station, in namespace /<--robot>: feature_node, "
                      "quantizer_node and feature_server_node (words every frame, features on request)")
    side.add_argument("--base", action="store_true",
                      help="the base station of --robots: one map (fabmap_node), the verifier asking the robots for "
                      "features, and with --backend the example backend")
    fleet.add_argument("--robots", default="", metavar="NAME,NAME",
                       help="with --base: the robots, each under its namespace /NAME")


def _ros_args(params: Path, parameters: dict[str, str], remaps: dict[str, str], namespace: str = "") -> list[str]:
    return (["--ros-args", "--params-file", str(params)]
            + [arg for name, value in parameters.items() for arg in ("-p", f"{name}:={value}")]
            + [arg for topic, target in remaps.items() for arg in ("-r", f"{topic}:={target}")]
            + (["-r", f"__ns:={namespace}"] if namespace else []))


def _command(params: Path, node: NodeLaunch) -> list[str]:
    if node.namespace:  # rcl matches a section to the node's full name: /robot1/feature_node
        params = namespaced_params_file(params, node.namespace)
    return [sys.executable, "-m", node.module, *_ros_args(params, node.parameters, node.remaps, node.namespace)]


def namespaced_params_file(params: Path, namespace: str) -> Path:
    """A copy of the parameter file for nodes in ``namespace`` (in this launcher's temporary folder)."""
    import yaml

    path = LAUNCH_TEMPORARIES / f"{namespace.strip('/').replace('/', '_')}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(namespaced_sections(yaml.safe_load(params.read_text()) or {}, namespace)))
    return path


def node_commands(args: argparse.Namespace) -> list[list[str]]:
    """One command per process: the nodes of ``launch_table.suite_nodes``, the three detection
    nodes merged into one aefabmap_pipeline process with --pipeline."""
    params = args.params or default_params_file()
    nodes = suite_nodes(SuiteOptions(model_dir=str(args.model), map_file=str(args.map) if args.map else "",
                                     robot=args.robot,
                                     image_topic=args.image_topic, image_qos=args.image_qos or "",
                                     verify=args.verify, backend=args.backend,
                                     camera_info_topic=args.camera_info_topic, depth_topic=args.depth_topic,
                                     odom_topic=args.odom_topic, closures_topic=args.closures_topic,
                                     sensor_qos=args.sensor_qos or "", remaps=tuple(args.remap),
                                     pictures=args.pictures or args.view, robot_side=args.robot_side,
                                     base=args.base, robots=tuple(parse_robots(args.robots, "--robots"))))
    view = [[sys.executable, "-m", "aefabmap_ros.cli.view", "--port", str(args.view_port)]] if args.view else []
    if not args.pipeline or args.base:
        return [_command(params, node) for node in nodes] + view
    # In one process, -p and -r apply to all three nodes; each uses only the names it knows.
    together, module = (ROBOT_NODES, "robot_pipeline") if args.robot_side else (NODES, "pipeline")
    merged_nodes = [node for node in nodes if node.name in together]
    merged = NodeLaunch(module, {k: v for node in merged_nodes for k, v in node.parameters.items()},
                        {k: v for node in merged_nodes for k, v in node.remaps.items()}, merged_nodes[0].namespace)
    return [_command(params, merged)] + [_command(params, node) for node in nodes if node.name not in together] + view


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _stop_with_parent(parent_pid: int) -> None:
    """Run in each child between fork and exec: the kernel sends it SIGTERM when the launcher dies,
    however it dies, so the node saves its state and stops instead of running on unsupervised."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent_pid:  # the launcher died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


def child_environment(process_count: int) -> dict[str, str]:
    """This process's environment plus each child's share of the thread pools (the user's values win)."""
    return {**os.environ, **thread_limits(process_count, os.environ)}


def start_node(command: list[str], environment: dict[str, str]) -> subprocess.Popen[bytes]:
    if sys.platform.startswith("linux"):
        return subprocess.Popen(command, env=environment,
                                preexec_fn=functools.partial(_stop_with_parent, os.getpid()))
    return subprocess.Popen(command, env=environment)


# A node's final save (FAB-MAP's map, the verifier's feature store) can take a minute on a slow disk or a
# loaded machine: a node killed in the middle of it keeps only its previous save.
STOP_TIMEOUT_S = 120.0
STOP_PROGRESS_S = 10.0  # how often the launcher says which nodes it is still waiting for
# A node past --stop-timeout whose files open for writing grew within the last WRITE_WINDOW_S is still saving:
# it is waited for, up to STOP_WRITING_CAP_S after the stop request in all (a map of millions of places).
WRITE_WINDOW_S = 5.0
STOP_WRITING_CAP_S = 600.0


def _node_name(command: list[str]) -> str:
    """The node a command runs, for messages: the module after ``-m`` (its last part), else the program."""
    if "-m" in command[:-1]:
        return command[command.index("-m") + 1].rsplit(".", 1)[-1]
    return Path(command[0]).name


def bytes_open_for_writing(pid: int) -> int | None:
    """Total size of the regular files process ``pid`` holds open for writing, its standard streams aside (a
    save's temporary file grows while it is written); None when /proc cannot tell (process gone, not Linux)."""
    try:
        descriptors = [entry for entry in Path(f"/proc/{pid}/fd").iterdir() if int(entry.name) > 2]
    except (OSError, ValueError):
        return None
    total = 0
    for entry in descriptors:
        try:
            flags = next(line for line in Path(f"/proc/{pid}/fdinfo/{entry.name}").read_text().splitlines()
                         if line.startswith("flags:"))
            if not int(flags.split()[1], 8) & (os.O_WRONLY | os.O_RDWR):
                continue
            status = entry.stat()  # the file the descriptor points to
        except (OSError, StopIteration, ValueError, IndexError):
            continue  # closed meanwhile, or not a file
        if stat.S_ISREG(status.st_mode):
            total += status.st_size
    return total


class WriteWatch:
    """When each stopping node's files open for writing last grew: the sign that its final save goes on."""

    def __init__(self, processes: list[subprocess.Popen[bytes]]) -> None:
        self._sizes = {process: bytes_open_for_writing(process.pid) for process in processes}
        self._grew_at = dict.fromkeys(processes, -math.inf)  # growth is what is seen after the stop request

    def still_writing(self, process: subprocess.Popen[bytes], window_s: float) -> bool:
        size = bytes_open_for_writing(process.pid)
        now = time.monotonic()
        if size is not None and size != self._sizes.get(process):
            self._sizes[process] = size
            self._grew_at[process] = now
        return now - self._grew_at.get(process, -math.inf) < window_s


def _stop_nodes(running: list[subprocess.Popen[bytes]], name_of: dict[subprocess.Popen[bytes], str],
                stop_timeout_s: float) -> None:
    """SIGINT to every node still running, then wait: ``stop_timeout_s``, longer for a node still writing
    (up to ``STOP_WRITING_CAP_S``); kill what is left. Says every ``STOP_PROGRESS_S`` who it waits for."""
    for process in running:
        process.send_signal(signal.SIGINT)  # nodes save state on a clean shutdown
    started = reported = time.monotonic()
    watch = WriteWatch(running)
    cap_s = max(stop_timeout_s, STOP_WRITING_CAP_S)
    while running:
        time.sleep(0.1)
        running = [p for p in running if p.poll() is None]
        waited = time.monotonic() - started
        overdue = [p for p in running if waited >= stop_timeout_s
                   and (waited >= cap_s or not watch.still_writing(p, WRITE_WINDOW_S))]
        for process in overdue:
            why = "still writing after" if waited >= cap_s else "still running, writing nothing,"
            limit = f"{cap_s:g} s" if waited >= cap_s else f"{stop_timeout_s:g} s (--stop-timeout)"
            print(f"ERROR: {name_of[process]} (pid {process.pid}) {why} {limit} after the stop request: killed",
                  file=sys.stderr)
            process.kill()
            process.wait()
        running = [p for p in running if p not in overdue]
        if running and time.monotonic() - reported >= STOP_PROGRESS_S:
            reported = time.monotonic()
            names = ", ".join(name_of[p] for p in running)
            print(f"[launch] waiting for {names} to finish shutting down (saving state): {waited:.0f} s of "
                  f"{stop_timeout_s:g} s (--stop-timeout; longer while writing, up to {cap_s:g} s)",
                  file=sys.stderr, flush=True)


def supervise(commands: list[list[str]], stop_timeout_s: float = STOP_TIMEOUT_S) -> int:
    """Run the node processes until one fails, all have ended, or the launcher gets SIGINT / SIGTERM; then
    stop the others and return the exit code.

    Stopping: every node still running gets SIGINT and up to ``stop_timeout_s`` to save its state and exit
    (``--stop-timeout``), longer while its files open for writing still grow (``STOP_WRITING_CAP_S`` at
    most); every ``STOP_PROGRESS_S`` the launcher prints which nodes it is waiting for, and a node still
    running at the end is killed (SIGKILL). Further signals to the launcher meanwhile do not cut the wait
    short.

    Exit code 1 when a node failed while running, or exited non-zero after the stop began: a node stopped
    by a signal exits 0 after a clean stop and 1 when its final save failed (nodes/common.py ``run_nodes``),
    and a killed node saved nothing; each is named in ``ERROR: <node> exited with code N during shutdown
    (its state may not be saved)``. A node that died of the SIGINT or SIGTERM itself (code -2 or -15) had
    not yet installed its signal handlers -- ``run_nodes`` does that before it builds a node, and restores
    them only after the final save -- so it was still starting, with nothing to save: not an error.
    """
    check_stop_timeout(stop_timeout_s)
    environment = child_environment(len(commands))
    processes = [start_node(command, environment) for command in commands]
    name_of = {process: _node_name(command) for process, command in zip(processes, commands, strict=True)}
    stopping = False

    def stop(_signum: int, _frame: FrameType | None) -> None:
        nonlocal stopping
        stopping = True

    previous_handlers = {signum: signal.signal(signum, stop) for signum in (signal.SIGINT, signal.SIGTERM)}
    exit_code = 0
    failed_while_running: list[subprocess.Popen[bytes]] = []
    try:
        while not stopping:
            failed_while_running = [p for p in processes if p.poll() not in (None, 0)]
            if failed_while_running:
                exit_code = 1
                for process in failed_while_running:
                    print(f"ERROR: a node exited with code {process.returncode}: {process.args!r}",
                          file=sys.stderr)
                break
            if all(p.poll() is not None for p in processes):
                break
            time.sleep(0.2)
    finally:
        _stop_nodes([p for p in processes if p.poll() is None], name_of, stop_timeout_s)
        for process in processes:
            code = process.returncode
            if process in failed_while_running or code == 0:
                continue
            name = name_of[process]
            if code in (-signal.SIGINT, -signal.SIGTERM):
                print(f"[launch] {name} ended by {signal.Signals(-code).name} while still starting (nothing to "
                      "save)", file=sys.stderr)
                continue
            exit_code = 1
            print(f"ERROR: {name} exited with code {code} during shutdown (its state may not be saved)",
                  file=sys.stderr)
        for signum, handler in previous_handlers.items():  # the caller's handling of Ctrl-C comes back
            signal.signal(signum, handler)
    return exit_code


def check_stop_timeout(stop_timeout_s: float) -> None:
    if not stop_timeout_s > 0:
        raise ConfigError(f"--stop-timeout must be > 0 seconds, got {stop_timeout_s}")


def check_model(model: Path) -> None:
    """A model with a file missing or damaged is refused here, not by every node at its start-up (what only
    loading finds, each node still refuses: it then exits 1, and so does the launcher)."""
    from aefabmap_ros.model.directory import check_model_files  # cv2, scipy: after parsing, as every CLI's work

    check_model_files(model)


def run(args: argparse.Namespace) -> int:
    if not args.model.is_dir():
        raise ConfigError(f"--model {args.model} is not a directory (train one with aefabmap_train)")
    params = args.params or default_params_file()  # a ConfigError when the package's own file is missing
    if not params.is_file():
        raise ConfigError(f"--params {params} does not exist")
    problem = params_file_problem(params)
    if problem is not None:
        raise ConfigError(problem)
    check_stop_timeout(args.stop_timeout)  # the arguments first, then the model's files
    check_model(args.model)
    try:
        return supervise(node_commands(args), args.stop_timeout)
    finally:
        shutil.rmtree(LAUNCH_TEMPORARIES, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


if __name__ == "__main__":
    raise SystemExit(main())
