"""aefabmap_demo: the whole package on sample data it makes itself, in one command.

1. sample bags: a synthetic town driven twice (test) and another town (training), as mcap bags
   with ground truth (aefabmap_synth), made once into bags/generated/;
2. models: an autoencoder vocabulary (AE-FABMAP) and a k-means one (the FABMAP2 baseline), each
   with its Chow-Liu tree, trained on the training bag (aefabmap_train);
3. online: the test bag is replayed through the three ROS nodes, verifier_node and the example
   backend pose_graph_node as separate processes (aefabmap_launch --backend, verification on by
   default, + aefabmap_replay with the bag's depth, CameraInfo and drifting odometry); every closure
   on /loop_closures (verified) is printed as it arrives and checked against the ground truth, FAB-MAP's
   raw candidates are counted; loop_closures, loop_closure_candidates and place_posteriors are
   recorded to an mcap that Foxglove opens (aefabmap_record), with closure_view_node's picture of every
   closure and refused candidate and the pose graph's markers and path (config/foxglove_layout.json);
   then the closures' relative poses are
   scored against the ground truth and the ATE of odometry alone against odometry + closures printed,
   with the ATE of a second backend that was also sent one wrong closure (cli/demo_backend.py);
4. evaluation: the paper's four methods offline, each also after geometric verification of its
   candidates (+ GV), and the online run from its recording (aefabmap_eval); the table is printed
   and the plots written;
5. two sessions: the test bag cut into its two laps, the second with its odometry restarted, run one
   after the other on one map and pose graph, scored per pair of sessions (cli/demo_sessions.py).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType

import numpy as np

from aefabmap_ros.cli.common import ArgumentParser, parse_or_report, report_errors
from aefabmap_ros.cli.demo_backend import INJECTED_NODE, INJECTED_TOPIC, ate_figures, ate_summary
from aefabmap_ros.cli.demo_printer import ClosurePrinter
from aefabmap_ros.cli.demo_sessions import run_sessions
from aefabmap_ros.cli.launch import STOP_WRITING_CAP_S
from aefabmap_ros.errors import AefabmapError
from aefabmap_ros.evaluation.ground_truth import read_kitti_poses
from aefabmap_ros.io.bags import list_topics, read_messages
from aefabmap_ros.io.config_files import shipped_config
from aefabmap_ros.nodes.launch_table import (
    CANDIDATES_TOPIC,
    CLOSURE_PICTURES_TOPIC,
    CLOSURES_TOPIC,
    POSTERIORS_TOPIC,
    REFUSED_PICTURES_TOPIC,
    VIEW_TOPICS,
    verifier_store_path,
)
from aefabmap_ros.vocabulary.config import VocabularyConfig

# What the replay publishes beside the images (aefabmap_synth's bag): the verifier's depth and
# intrinsics, and the backend's drifting odometry.
COMPANION_TOPICS = ("/depth", "/camera_info", "/odom")
# The recording: what aefabmap_eval scores and what Foxglove shows (closure pictures, the graph's markers and path;
# the recorder's subscription is what makes closure_view_node draw them).
RECORDED_TOPICS = tuple(dict.fromkeys((CLOSURES_TOPIC, CANDIDATES_TOPIC, POSTERIORS_TOPIC, *VIEW_TOPICS)))


def recorded_topics(no_pictures: bool) -> tuple[str, ...]:
    return tuple(t for t in RECORDED_TOPICS if not (no_pictures and t in (CLOSURE_PICTURES_TOPIC,
                                                                           REFUSED_PICTURES_TOPIC)))


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_demo", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    # Relative to the working directory, not to this file: an installed package has no checkout around it
    # (scripts/demo.sh passes the checkout's output/ and bags/ folders).
    parser.add_argument("--out", type=Path, default=Path("output") / "demo",
                        help="results folder (default output/demo)")
    parser.add_argument("--bags", type=Path, default=Path("bags") / "generated",
                        help="where the sample bags are made (once) and found (default bags/generated)")
    parser.add_argument("--frames", type=int, default=300, help="frames per synthetic sequence (default 300)")
    parser.add_argument("--size", type=int, default=VocabularyConfig().size,
                        help=f"visual words per vocabulary (default {VocabularyConfig().size})")
    parser.add_argument("--skip-ros", action="store_true", help="offline evaluation only (no ROS nodes)")
    parser.add_argument("--quick", action="store_true",
                        help="a small, fast version (fewer and smaller frames, small vocabularies)")
    parser.add_argument("--live", action="store_true",
                        help="replay as a robot publishes: in real time, with the sensor-data QoS, and the shipped "
                        "aefabmap.yaml (the default replays in lockstep with demo.yaml: every frame, none lost)")
    parser.add_argument("--no-pictures", action="store_true",
                        help="record no closure pictures (closure_view_node not started): drawing every closure and "
                        "refused candidate competes with the verifier for the CPU, so a --live latency without "
                        "the view is measured this way")
    parser.add_argument("--driver-default-dds", action="store_true",
                        help="with --live: the replay (the camera driver) keeps Fast DDS's default transports, which "
                        "lose most best-effort messages over 512 KiB; by default it runs with the shipped "
                        "config/fastdds_large_messages.xml, as a driver of large images should")
    parser.add_argument("--online-only", action="store_true",
                        help="score only the online run (no offline evaluation of the four methods)")
    parser.add_argument("--no-sessions", action="store_true", help="skip the two-session run (step 5)")
    parser.add_argument("--models", type=Path, default=None,
                        help="where the vocabularies are trained (once) and found (default OUT/models)")
    parser.add_argument("--test", type=Path, default=None,
                        help="another test sequence folder made by aefabmap_synth (bag/, loop_gt.npz, poses.txt, "
                        "groundtruth.tum), e.g. --preset dense-video (default: the demo's own town)")
    return parser


def _step(title: str) -> None:
    print(f"\n=== {title}", flush=True)


def _run(command: list[str | Path], what: str) -> None:
    """Run one of our CLIs (as the user would); its own ERROR line explains a failure."""
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", *map(str, command)], check=False)
    if result.returncode != 0:
        raise AefabmapError(f"{what} failed (exit {result.returncode}): {' '.join(map(str, command))}")
    print(f"    ({what}: {time.monotonic() - started:.0f} s)", flush=True)


def make_bags(args: argparse.Namespace) -> tuple[Path, Path]:
    train, test = args.bags / "train", args.bags / "test"
    if (train / "bag").is_dir() and (test / "bag").is_dir() and (test / "loop_gt.npz").is_file() \
            and (test / "groundtruth.tum").is_file() and set(COMPANION_TOPICS) <= set(list_topics(test / "bag")):
        print(f"    using the sample bags in {args.bags}")
        return train, test
    command: list[str | Path] = ["aefabmap_ros.cli.synth", "--out", args.bags, "--kind", "both", "--format", "mcap",
                                 "--frames", str(args.frames), "--overwrite"]
    if args.quick:
        command += ["--width", "320", "--height", "240"]
    _run(command, "making the sample bags")
    return train, test


def train_models(args: argparse.Namespace, train: Path) -> dict[str, Path]:
    models = {}
    folder: Path = args.models or args.out / "models"
    folder.mkdir(parents=True, exist_ok=True)
    for kind in ("autoencoder", "kmeans"):
        out = folder / kind
        if (out / "metadata.json").is_file():
            print(f"    using the {kind} model in {out}")
        else:
            command: list[str | Path] = ["aefabmap_ros.cli.train", "--bag", train / "bag", "--topic", "/image",
                                         "--vocabulary", kind, "--size", str(args.size), "--out", out,
                                         "--overwrite", "--work-dir", folder / ".work",
                                         "--config", shipped_config("demo_train.yaml")]
            _run(command, f"training the {kind} vocabulary and Chow-Liu tree")
        models[kind] = out
    return models


def _wait_for(log: Path, text: str, process: subprocess.Popen[bytes], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while text not in log.read_text():
        if process.poll() is not None or time.monotonic() > deadline:
            raise AefabmapError(f"{process.args!r} did not start; its log {log}:\n{log.read_text()[-2000:]}")
        time.sleep(0.2)


def stop_saving(processes: list[subprocess.Popen[bytes]]) -> None:
    """Ctrl-C each launcher and recorder, newest first, and wait while the nodes save their map, features and
    graph: the launcher ends a node that does not stop (it kills it past its stop timeout), so this returns."""
    for process in reversed(processes):
        process.send_signal(signal.SIGINT)
        process.wait(timeout=STOP_WRITING_CAP_S + 60)


def _stop(process: subprocess.Popen[bytes], grace_s: float = 20.0) -> None:
    """Stop a child still running: SIGINT first, so aefabmap_launch stops its own node processes
    (a SIGKILL would orphan them), then SIGKILL if it does not exit within ``grace_s``."""
    if process.poll() is not None:
        return
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def _demo_params(args: argparse.Namespace, backend_dir: Path) -> Path:
    """aefabmap_ros/config/demo.yaml (--live: the shipped aefabmap.yaml, as on a robot) plus where the backend
    writes its keyframe trajectory."""
    import yaml

    params = yaml.safe_load(shipped_config("aefabmap.yaml" if args.live else "demo.yaml").read_text())
    params.setdefault("pose_graph_node", {}).setdefault("ros__parameters", {})["trajectory_file"] = \
        str(backend_dir / "keyframes.tum")
    path: Path = args.out / "demo_params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    return path


def run_online(args: argparse.Namespace, model: Path, test: Path) -> Path:
    """Replay the test bag through the nodes and the backend; returns the recording."""
    recording, map_file, backend_dir = _fresh_outputs(args.out)
    stamps = np.array([m.stamp_ns for m in read_messages(test / "bag", ["/image"])], dtype=np.int64)
    gt = np.load(test / "loop_gt.npz")["gt"]
    logs = args.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    params = _demo_params(args, backend_dir)
    python = sys.executable
    processes: list[subprocess.Popen[bytes]] = []
    printer = None
    try:
        with (logs / "nodes.log").open("w") as nodes_log, (logs / "record.log").open("w") as record_log, \
                (logs / "injected_backend.log").open("w") as injected_log:
            processes.append(subprocess.Popen(
                [python, "-m", "aefabmap_ros.cli.launch", "--model", str(model), "--params", str(params),
                 "--map", str(map_file), "--backend", *([] if args.no_pictures else ["--pictures"]),
                 "--depth-topic", "/depth"],
                stdout=nodes_log, stderr=subprocess.STDOUT))  # verification: on
            processes.append(subprocess.Popen(
                [python, "-m", "aefabmap_ros.cli.record", str(recording), "--overwrite", "--topics",
                 *recorded_topics(args.no_pictures), "--wait-publishers", "120"],
                stdout=record_log, stderr=subprocess.STDOUT))
            # The second backend: the same odometry, the published closures relayed by the demo plus a wrong one.
            processes.append(subprocess.Popen(
                [python, "-m", "aefabmap_ros.nodes.pose_graph_node", "--ros-args", "-r", f"__node:={INJECTED_NODE}",
                 "-r", f"loop_closures:={INJECTED_TOPIC}",
                 "-p", f"trajectory_file:={backend_dir / 'keyframes_injected.tum'}"],
                stdout=injected_log, stderr=subprocess.STDOUT))
            printer = ClosurePrinter(stamps, gt, read_kitti_poses(test / "poses.txt"))
            _wait_until_up(logs, processes, pictures=not args.no_pictures)
            print(f"    nodes up (logs in {logs}); replaying {len(stamps)} images with "
                  f"{', '.join(COMPANION_TOPICS)}", flush=True)
            _replay(args, test)
            printer.wait_until_quiet(idle_s=3.0 if args.live else 1.0, at_most_s=120.0)
            stop_saving(processes)
    except subprocess.CalledProcessError as exc:
        raise AefabmapError(f"replay failed (exit {exc.returncode})") from exc
    finally:
        for process in processes:
            _stop(process)
        if printer is not None:
            printer.close()
    if printer is not None:
        _print_results(args, printer, test, backend_dir)
    return recording


def _fresh_outputs(out: Path) -> tuple[Path, Path, Path]:
    """(recording, map file, backend folder), emptied of an earlier run's."""
    recording = out / "online_recording"
    shutil.rmtree(recording, ignore_errors=True)
    map_file = out / "map.npz"
    # Every run replays the same bag from an empty map: a map saved by the last run would make the
    # FAB-MAP node drop every frame as already seen (its stamps are not after the newest place's).
    map_file.unlink(missing_ok=True)
    shutil.rmtree(verifier_store_path(map_file), ignore_errors=True)  # the verifier's features of those places
    backend_dir = out / "backend"
    shutil.rmtree(backend_dir, ignore_errors=True)  # no trajectory of an earlier run can be scored by mistake
    backend_dir.mkdir(parents=True)
    return recording, map_file, backend_dir


def _print_results(args: argparse.Namespace, printer: ClosurePrinter, test: Path, backend_dir: Path) -> None:
    from aefabmap_ros.evaluation.protocol import EvaluationConfig  # torch: only once the nodes are done

    print(printer.summary(EvaluationConfig().min_gap), flush=True)
    if not args.live:
        print("    (lockstep: the replay waits for FAB-MAP, not for the verifier, which is let fall behind; "
              "--live gives a camera's latency)", flush=True)
    if printer.backend is not None:
        print(printer.backend.errors.summary(), flush=True)
    print_backend_result(test, backend_dir)


def _wait_until_up(logs: Path, processes: list[subprocess.Popen[bytes]], pictures: bool) -> None:
    """Until the recorder records and every node hears its inputs (the nodes, the recorder, the injected backend)."""
    _wait_for(logs / "record.log", "[record] recording", processes[1], timeout_s=180)
    # The verifier must hear every frame's features: a place it never saw cannot be verified; closure_view_node
    # every frame's view: a place it never saw has no picture.
    links = ["quantizer_node]: receiving features", "fabmap_node]: receiving words",
             "verifier_node]: receiving features", "pose graph (example backend)"]
    for link in links + (["closure_view_node]: receiving frame views"] if pictures else []):
        _wait_for(logs / "nodes.log", link, processes[0], timeout_s=180)
    _wait_for(logs / "injected_backend.log", "pose graph (example backend)", processes[2], timeout_s=180)


def _replay(args: argparse.Namespace, test: Path) -> None:
    """The test bag with its companions, in lockstep (each image once the last was answered: every frame, none
    lost) or, --live, at the bag's own pace with a camera driver's QoS (nobody waits for the nodes)."""
    # Both backends and the verifier (its odometry gate) must hear the odometry from its first message on.
    companions = [argument for topic in COMPANION_TOPICS
                  for argument in ("--with", f"{topic}=3" if topic == "/odom" else topic)]
    pace = ["--rate", "1", "--qos", "sensor_data"] if args.live else ["--lockstep", "place_posteriors"]
    subprocess.run([sys.executable, "-m", "aefabmap_ros.cli.replay", str(test / "bag"), "--topic", "/image",
                    *companions, *pace, "--wait-subscribers", "2", "--quiet"],  # feature_node and the printer
                   check=True, env=_driver_environment(args))


def _driver_environment(args: argparse.Namespace) -> dict[str, str]:
    """The replay stands in for the camera driver: live, it gets the shared memory large images need (unless
    --driver-default-dds or the user's own Fast DDS profile)."""
    environment = dict(os.environ)
    if args.live and not args.driver_default_dds:
        environment.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(shipped_config("fastdds_large_messages.xml")))
    return environment


def print_backend_result(test: Path, backend_dir: Path) -> None:
    """The ATE before and after closures (and with the injected wrong one), or why there is none."""
    keyframes, injected = backend_dir / "keyframes.tum", backend_dir / "keyframes_injected.tum"
    if not keyframes.is_file():
        print(f"    the backend wrote no trajectory ({keyframes}): see pose_graph_node in the nodes' log", flush=True)
        return
    try:
        figures = ate_figures(test, keyframes, injected if injected.is_file() else None)
    except AefabmapError as exc:  # e.g. too few keyframes to align
        print(f"    no ATE: {exc}", flush=True)
        return
    print(ate_summary(figures), flush=True)
    plot = backend_dir.parent / "evaluation_online" / "ate.png"  # the online report shows it
    write_ate_plot(test, keyframes, plot)
    print(f"    ATE plot: {plot}", flush=True)


def write_ate_plot(test: Path, keyframes: Path, path: Path) -> None:
    """Top view of odometry alone and of the backend's keyframes, each aligned (SE(3)) over the ground truth."""
    from aefabmap_ros.evaluation.plots import plot_trajectories
    from aefabmap_ros.evaluation.trajectory_error import absolute_trajectory_error, read_tum

    reference = read_tum(test / "groundtruth.tum")
    aligned = [(label, absolute_trajectory_error(reference, read_tum(file)).aligned.positions_xyz)
               for label, file in (("odometry alone", test / "odometry.tum"), ("odometry + closures", keyframes))]
    path.parent.mkdir(parents=True, exist_ok=True)
    plot_trajectories(reference.positions_xyz, aligned, path)


def evaluate(args: argparse.Namespace, models: dict[str, Path], test: Path, recording: Path | None) -> None:
    gt = test / "loop_gt.npz"
    # Verified with the bag's depth, as verifier_node verifies it in the online run (the metric test).
    if not args.online_only:
        _run(["aefabmap_ros.cli.evaluate", "--bag", test / "bag", "--topic", "/image", "--gt", gt,
              "--model", models["kmeans"], "--model", models["autoencoder"], "--verify", "--depth-topic", "/depth",
              "--camera-info-topic", "/camera_info", "--odometry-topic", "/odom", "--out", args.out / "evaluation"],
             "offline evaluation of the four methods (each also after geometric verification: + GV)")
    if recording is not None:
        print("\n    the online run (AE-FABMAP through the ROS nodes), scored from its recording:", flush=True)
        # Frames by stamp: loop_gt.npz's stamps_ns (the bag's images' stamps, which --bag gives for older bags).
        _run(["aefabmap_ros.cli.evaluate", "--recording", recording, "--gt", gt, "--bag", test / "bag",
              "--topic", "/image", "--pose-truth", test / "groundtruth.tum", "--out", args.out / "evaluation_online"],
             "evaluation of the recording")


def run(args: argparse.Namespace) -> int:
    if args.quick:
        args.frames, args.size = min(args.frames, 120), min(args.size, 300)
        if args.out == build_parser().get_default("out"):
            args.out = args.out.with_name("demo_quick")
        if args.bags == build_parser().get_default("bags"):
            args.bags = args.bags.with_name("generated_quick")
    started = time.monotonic()
    args.out.mkdir(parents=True, exist_ok=True)
    _step("1/4 sample bags")
    train, test = make_bags(args)
    if args.test is not None:
        test = args.test
    _step("2/4 vocabularies and Chow-Liu trees (trained on the training town only)")
    models = train_models(args, train)
    recording = None
    if not args.skip_ros:
        _step("3/4 online: test bag -> feature, quantizer, FAB-MAP and verifier nodes -> /loop_closures")
        recording = run_online(args, models["autoencoder"], test)
    _step("4/4 evaluation of FABMAP2, AE-FABMAP, BoW and AE-BoW (and the online run)")
    evaluate(args, models, test, recording)
    sessions = None
    if not (args.skip_ros or args.no_sessions):
        _step("two sessions: the first lap, then the second with its odometry restarted, on one map")
        sessions = run_sessions(args, models["autoencoder"], test)
    print(f"\nDone in {time.monotonic() - started:.0f} s.\n  tables: {args.out / 'evaluation' / 'results.md'}"
          + (f", {args.out / 'evaluation_online' / 'results.md'}" if recording else "")
          + (f", {sessions / 'results.md'}" if sessions else "")
          + f"\n  plots:  {args.out / 'evaluation'}/*.png"
          + (f"\n  recording (opens in Foxglove with the layout {shipped_config('foxglove_layout.json')}): "
             f"{recording}" if recording else ""))
    return 0


def _interrupt(_signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt  # SIGTERM (a timeout, a CI runner) cleans up the node processes like Ctrl-C


def main(argv: list[str] | None = None) -> int:
    args = parse_or_report(build_parser(), argv)
    if args is None:
        return 1
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    signal.signal(signal.SIGTERM, _interrupt)
    return report_errors(lambda: run(args))


if __name__ == "__main__":
    raise SystemExit(main())
