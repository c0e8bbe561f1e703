"""Backend benchmark: the example pose graph's (backend/pose_graph.py, iSAM2) update time per loop closure.

A robot drives laps of a 10 m square (0.5 m odometry steps, 2 % scale and 0.15 degree-per-step yaw
drift); from its second lap on, every second step closes a loop to the same spot of the first lap.
Each closure adds the query's keyframe (the place's is created once and then reused), and the time
of ``PoseGraph.add_closure`` -- the keyframe insertion, the iSAM2 update and its extra iterations --
is reported by graph size. The issue's target: <= 20 ms per closure at 1,000 keyframes.
"""

from __future__ import annotations

import argparse
import itertools
import time

import gtsam
import numpy as np

from aefabmap_ros.backend.pose_graph import Closure, PoseGraph, PoseGraphConfig
from aefabmap_ros.cli.common import ArgumentParser, run_cli

STEP_M = 0.5
SIDE_STEPS = 20
LAP_STEPS = 4 * SIDE_STEPS
SECOND = 1_000_000_000


def _truth(steps: int) -> list[gtsam.Pose3]:
    poses, pose = [], gtsam.Pose3()
    for index in range(steps):
        poses.append(pose)
        turn = gtsam.Rot3.Yaw(np.pi / 2) if (index + 1) % SIDE_STEPS == 0 else gtsam.Rot3()
        pose = pose.compose(gtsam.Pose3(turn, np.array([STEP_M, 0.0, 0.0])))
    return poses


def _odometry(truth: list[gtsam.Pose3]) -> list[gtsam.Pose3]:
    odometry = [truth[0]]
    for before, after in itertools.pairwise(truth):
        step = before.between(after)
        odometry.append(odometry[-1].compose(
            gtsam.Pose3(step.rotation().compose(gtsam.Rot3.Yaw(np.radians(0.15))), 1.02 * step.translation())))
    return odometry


def run(args: argparse.Namespace) -> int:
    keyframes = 100 if args.quick else args.keyframes
    steps = LAP_STEPS + 2 * keyframes + 2
    truth = _truth(steps)
    graph = PoseGraph(PoseGraphConfig())
    for index, pose in enumerate(_odometry(truth)):
        graph.add_odometry((index + 1) * SECOND, pose)
    covariance = np.diag([0.02 ** 2] * 3 + [0.005 ** 2] * 3)
    timings: list[tuple[int, float]] = []  # (keyframes after the closure, seconds)
    for query in range(LAP_STEPS, steps, 2):
        if len(graph.keyframes) >= keyframes:
            break
        place = query % LAP_STEPS
        closure = Closure((query + 1) * SECOND, (place + 1) * SECOND, truth[query].between(truth[place]), covariance)
        started = time.perf_counter()
        graph.add_closure(closure)
        timings.append((len(graph.keyframes), time.perf_counter() - started))
    print(f"pose graph (iSAM2, Cauchy loop factors): {len(timings)} closures, {len(graph.keyframes)} keyframes; "
          f"closure results {dict(graph.counts)}")
    bands = sorted({size // 100 * 100 for size, _ in timings})
    for band in bands[-3:] if len(bands) > 3 else bands:
        seconds = np.array([s for size, s in timings if band <= size < band + 100]) * 1e3
        if seconds.size:
            print(f"  update per closure at {band:5d}-{band + 99:5d} keyframes: median {np.median(seconds):7.2f} ms  "
                  f"p95 {np.percentile(seconds, 95):7.2f} ms  ({seconds.size} closures)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bench backend", description=__doc__.split("\n\n")[0])
    parser.add_argument("--keyframes", type=int, default=1000, help="grow the graph to this many keyframes")
    parser.add_argument("--quick", action="store_true", help="100 keyframes (a smoke test)")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)
