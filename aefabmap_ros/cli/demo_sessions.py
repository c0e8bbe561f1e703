"""aefabmap_demo's two-session run: the test town driven again by a robot whose odometry restarted.

The test bag is cut in two (aefabmap_bag split --at 0.5 --restart-odometry: the figure-eight's first lap is
session A, its second lap session B, whose odometry starts again at the identity). The nodes and the example
backend run on session A with a new map (--map, --backend), are stopped (the map, the verifier's features and
the pose graph saved), and run again on the same map with session B: fabmap_node begins session 1, B's revisits
of the first lap are closures into session 0, and the backend joins B's graph to A's on the first of them.
Each run is recorded; the recordings are merged and scored per pair of sessions (aefabmap_eval --recording
with --trajectory and --session-odometry), and set against the single-session run on the same frames.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.cli.demo_printer import ClosurePrinter
from aefabmap_ros.errors import AefabmapError
from aefabmap_ros.io.bags import read_messages
from aefabmap_ros.io.config_files import shipped_config
from aefabmap_ros.nodes.launch_table import CANDIDATES_TOPIC, CLOSURES_TOPIC, POSTERIORS_TOPIC

SESSIONS = ("a", "b")
RECORDED = (CLOSURES_TOPIC, CANDIDATES_TOPIC, POSTERIORS_TOPIC)
CUT_FRACTION = 0.5  # the demo town is a figure-eight driven twice: half way is the end of the first lap
PAIRS_MARKER = "Loop closures per pair of sessions"  # where aefabmap_eval's session tables begin


@dataclass
class SessionRun:
    """One session's run as the demo saw it."""

    name: str
    closures: list[tuple[int, int, bool]]  # (query frame, matched frame, true) as published
    sessions: list[tuple[tuple[str, int], tuple[str, int]]]  # each closure's (query, matched) session
    backend_summary: str  # pose_graph_node's last line


def _params(args: argparse.Namespace, folder: Path) -> Path:
    """The single run's parameters (demo.yaml, or aefabmap.yaml --live) with the backend's trajectory file here."""
    import yaml

    params = yaml.safe_load(shipped_config("aefabmap.yaml" if args.live else "demo.yaml").read_text())
    params.setdefault("pose_graph_node", {}).setdefault("ros__parameters", {})["trajectory_file"] = \
        str(folder / "backend" / "keyframes.tum")
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    return path


def _fresh(folder: Path) -> Path:
    """The folder emptied of an earlier two-session run (its map above all: session A must start a new map)."""
    shutil.rmtree(folder, ignore_errors=True)
    (folder / "backend").mkdir(parents=True)
    (folder / "logs").mkdir()
    return folder / "map.npz"


def _wait_until_up(logs: Path, nodes: subprocess.Popen[bytes], recorder: subprocess.Popen[bytes]) -> None:
    from aefabmap_ros.cli.demo import _wait_for

    _wait_for(logs / "record.log", "[record] recording", recorder, timeout_s=180)
    for link in ("quantizer_node]: receiving features", "fabmap_node]: receiving words",
                 "verifier_node]: receiving features", "pose graph (example backend)"):
        _wait_for(logs / "nodes.log", link, nodes, timeout_s=180)


def _replay(args: argparse.Namespace, sequence: Path) -> None:
    """The session's bag as the single run replays the test bag (demo._replay), its odometry awaited by the two
    nodes that take it here (the verifier and the one backend)."""
    from aefabmap_ros.cli.demo import COMPANION_TOPICS, _driver_environment

    companions = [argument for topic in COMPANION_TOPICS
                  for argument in ("--with", f"{topic}=2" if topic == "/odom" else topic)]
    pace = ["--rate", "1", "--qos", "sensor_data"] if args.live else ["--lockstep", "place_posteriors"]
    subprocess.run([sys.executable, "-m", "aefabmap_ros.cli.replay", str(sequence / "bag"), "--topic", "/image",
                    *companions, *pace, "--wait-subscribers", "2", "--quiet"],  # feature_node and the printer
                   check=True, env=_driver_environment(args))


def run_session(args: argparse.Namespace, model: Path, folder: Path, name: str, stamps: np.ndarray,
                gt: np.ndarray) -> SessionRun:
    """One session: the nodes on the map, its bag replayed, everything stopped (and saved) again."""
    from aefabmap_ros.cli.demo import _stop, stop_saving

    logs = folder / "logs" / name
    logs.mkdir(parents=True)
    sequence = folder / "bags" / name
    frames = sum(1 for _ in read_messages(sequence / "bag", ["/image"]))
    python = sys.executable
    processes: list[subprocess.Popen[bytes]] = []
    printer = None
    try:
        with (logs / "nodes.log").open("w") as nodes_log, (logs / "record.log").open("w") as record_log:
            processes.append(subprocess.Popen(
                [python, "-m", "aefabmap_ros.cli.launch", "--model", str(model), "--params",
                 str(folder / "params.yaml"), "--map", str(folder / "map.npz"), "--backend", "--depth-topic",
                 "/depth"], stdout=nodes_log, stderr=subprocess.STDOUT))
            processes.append(subprocess.Popen(
                [python, "-m", "aefabmap_ros.cli.record", str(folder / f"recording_{name}"), "--overwrite",
                 "--topics", *RECORDED, "--wait-publishers", "120"], stdout=record_log, stderr=subprocess.STDOUT))
            printer = ClosurePrinter(stamps, gt, None, frames_to_process=frames)
            _wait_until_up(logs, *processes)
            print(f"    session {name.upper()}: nodes up (logs in {logs}); replaying its {frames} images", flush=True)
            _replay(args, sequence)
            printer.wait_until_quiet(idle_s=3.0 if args.live else 1.0, at_most_s=120.0)
            stop_saving(processes)
    except subprocess.CalledProcessError as exc:
        raise AefabmapError(f"replay of session {name.upper()} failed (exit {exc.returncode})") from exc
    finally:
        for process in processes:
            _stop(process)
        if printer is not None:
            printer.close()
    assert printer is not None
    summary = [line for line in (logs / "nodes.log").read_text().splitlines() if "pose_graph_node: " in line]
    return SessionRun(name, printer.closures, printer.closure_sessions, summary[-1] if summary else "")


def single_session_recall(recording: Path, test: Path, cut_frame: int, min_gap: int) -> tuple[int, int]:
    """(closed, revisiting): the second lap's frames that revisit the first, and those the single-session run
    closed into the first lap, from its recording."""
    from aefabmap_ros.cli.evaluate_recording import read_recording
    from aefabmap_ros.evaluation.recordings import FrameIndex
    from aefabmap_ros.evaluation.session_scores import revisit_recall
    from aefabmap_ros.stamps import stamp_to_ns

    truth = np.load(test / "loop_gt.npz")
    gt, index = truth["gt"], FrameIndex(truth["stamps_ns"], "loop_gt.npz")
    published = read_recording(recording).published
    pairs = [(index.frame_of(stamp_to_ns(m.header.stamp)), index.frame_of(stamp_to_ns(m.matched_stamp)))
             for m in (published[1] if published is not None else [])]
    later = np.arange(gt.shape[0]) >= cut_frame
    return revisit_recall([(q, m) for q, m in pairs if q is not None and m is not None], gt, later, ~later, min_gap)


def _evaluate(folder: Path, test: Path) -> dict[str, Any]:
    """aefabmap_eval on the merged recording, the trajectory and both sessions' odometry; its session tables are
    printed, its JSON returned."""
    command = [sys.executable, "-m", "aefabmap_ros.cli.evaluate", "--recording", str(folder / "recording"), "--gt",
               str(test / "loop_gt.npz"), "--bag", str(test / "bag"), "--topic", "/image", "--pose-truth",
               str(test / "groundtruth.tum"), "--trajectory", str(folder / "backend" / "keyframes.tum"),
               *[argument for name in SESSIONS
                 for argument in ("--session-odometry", str(folder / "bags" / name / "odometry.tum"))],
               "--out", str(folder / "evaluation")]
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise AefabmapError(f"evaluation of the two sessions failed: {result.stderr.strip()[-2000:]}")
    text = result.stdout
    start = text.find(PAIRS_MARKER)
    tables = text[start:text.rfind("wall time")] if start >= 0 else text
    print("\n".join(f"    {line}" if line else "" for line in tables.strip().splitlines()), flush=True)
    payload: dict[str, Any] = json.loads((folder / "evaluation" / "results.json").read_text())
    return payload


def _first_cross_session(run: SessionRun, stamps: np.ndarray) -> tuple[int, int, float] | None:
    """(query frame, matched frame, query stamp in s) of the session's first closure into another session."""
    for (query, matched, _), (query_session, matched_session) in zip(run.closures, run.sessions, strict=True):
        if query_session != matched_session:
            return query, matched, int(stamps[query]) / 1e9
    return None


def _joined_at(trajectory: Path, stamp_s: float) -> bool:
    """Whether the joined trajectory has a keyframe at that stamp (the session it belongs to is joined)."""
    if not trajectory.is_file():
        return False
    stamps = [float(line.split()[0]) for line in trajectory.read_text().splitlines() if line.strip()]
    return any(abs(stamp - stamp_s) < 0.005 for stamp in stamps)


def _pct(part: float, whole: float) -> str:
    return f"{100 * part / whole:.1f} %" if whole else "n/a"


def print_targets(payload: dict[str, Any], single: tuple[int, int], runs: list[SessionRun], stamps: np.ndarray,
                  folder: Path) -> None:
    """The two-session run against its targets, each figure as measured."""
    pairs = payload.get("session_pairs", {}).get("pairs", [])
    cross = next((p for p in pairs if p["query_session"] == 1 and p["matched_session"] == 0), None)
    closed, revisiting = single
    lines = ["", "    two sessions against one run, on the same frames (the second lap's frames revisiting the first):",
             f"      single session, closed into the first lap   {closed}/{revisiting}"
             f" ({_pct(closed, revisiting)})"]
    if cross is not None:
        two = cross["revisiting_frames_closed"]
        lines.append(f"      session B, closed into session A           {two}/{cross['revisiting_frames']}"
                     f" ({_pct(two, cross['revisiting_frames'])}): {_pct(two, closed)} of the single-session "
                     "figure (target >= 90 %)")
    else:
        lines.append("      session B published no closure into session A")
    wrong = sum(p["wrong_poses"] or 0 for p in pairs)
    checked = sum(p["poses_checked"] or 0 for p in pairs)
    false = sum(p["false_closures"] for p in pairs)
    lines.append(f"      closures with a wrong pose (> 5 deg or > 0.2 m): {wrong} of {checked} checked (target 0); "
                 f"false closures: {false}")
    first = _first_cross_session(runs[-1], stamps)
    trajectory = folder / "backend" / "keyframes.tum"
    if first is None:
        lines.append("      the backend had no cross-session closure to join the sessions with")
    else:
        joined = _joined_at(trajectory, first[2])
        lines.append(f"      the first cross-session closure, frame {first[0]} -> frame {first[1]}: session B "
                     + ("joined to A there (its keyframe is in the joined trajectory)" if joined
                        else "NOT joined there (no keyframe of it in the joined trajectory)"))
    ate = payload.get("joined_trajectory")
    if ate is not None and ate.get("joined_over_odometry") is not None:
        lines.append(f"      joined trajectory ATE {ate['ate_rmse_m']:.3f} m against the sessions' odometry "
                     f"{ate['odometry_pooled_ate_rmse_m']:.3f} m (each aligned on its own): "
                     f"{100 * ate['joined_over_odometry']:.1f} % (target <= 15 %)")
    for run in runs:
        if run.backend_summary:
            lines.append(f"      backend after session {run.name.upper()}: "
                         f"{run.backend_summary.split('pose_graph_node: ', 1)[1]}")
    print("\n".join(lines), flush=True)


def run_sessions(args: argparse.Namespace, model: Path, test: Path) -> Path:
    """The two-session run (module docstring); returns its evaluation folder."""
    from aefabmap_ros.cli.demo import _run
    from aefabmap_ros.evaluation.protocol import EvaluationConfig

    folder: Path = args.out / "sessions"
    _fresh(folder)
    _params(args, folder)
    _run(["aefabmap_ros.cli.bag", "split", test, "--at", str(CUT_FRACTION), "--restart-odometry",
          "--out", folder / "bags"], "cutting the test bag into sessions A and B")
    stamps = np.array([m.stamp_ns for m in read_messages(test / "bag", ["/image"])], dtype=np.int64)
    gt = np.load(test / "loop_gt.npz")["gt"]
    runs = []
    for name in SESSIONS:
        started = time.monotonic()
        run = run_session(args, model, folder, name, stamps, gt)
        false = sum(1 for *_, true in run.closures if not true)
        into_other = sum(1 for query, matched in run.sessions if query != matched)
        print(f"    session {name.upper()}: {len(run.closures)} loop closures published, {false} false, {into_other} "
              f"into an earlier session ({time.monotonic() - started:.0f} s)", flush=True)
        runs.append(run)
    _run(["aefabmap_ros.cli.bag", "merge", *(folder / f"recording_{name}" for name in SESSIONS),
          "--out", folder / "recording"], "merging the sessions' recordings")
    payload = _evaluate(folder, test)
    cut_frame = int(np.load(folder / "bags" / "a" / "loop_gt.npz")["stamps_ns"].size)
    single = single_session_recall(args.out / "online_recording", test, cut_frame, EvaluationConfig().min_gap) \
        if (args.out / "online_recording").is_dir() else (0, 0)
    print_targets(payload, single, runs, stamps, folder)
    return folder / "evaluation"
