"""A recorded run's closures through the example pose graph offline: how much of its trajectory error the
closures' poses make, and how much the closures' coverage and the backend's odometry model.

    PYTHONPATH=. .venv/bin/python scripts/replay_backend.py TEST_DIR RUN_DIR [--lag-s 0.4]

TEST_DIR is an aefabmap_synth sequence (bag/ with /odom, groundtruth.tum, odometry.tum); RUN_DIR an
``aefabmap_demo --online-only`` output (its online_recording and evaluation_online/closures.csv, scored with
the pose truth). The bag's odometry goes into ``backend.pose_graph.PoseGraph`` (the defaults pose_graph_node
runs with) and each published closure with a pose ``--lag-s`` of stamp time after its query, as a live
verifier delivers it. Prints the ATE (SE(3) alignment, over the graph's keyframes) as a share of odometry's
at the same stamps, for:

- the closures as published;
- the same without those whose pose is over 0.2 m or 5 degrees off (``pose_wrong`` in closures.csv);
- the same closures with their ground-truth relative poses, with their own covariances: what the graph makes
  of the run's closures if every pose were exact.
"""

from __future__ import annotations

import argparse
import csv
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from aefabmap_ros.backend.odometry import closure_in_base_frame
from aefabmap_ros.backend.pose_graph import Closure, PoseGraph, PoseGraphConfig
from aefabmap_ros.cli.demo_backend import ate_figures
from aefabmap_ros.cli.evaluate_recording import read_recording
from aefabmap_ros.evaluation.closure_listing import PoseTruth, read_pose_truth
from aefabmap_ros.io import bags
from aefabmap_ros.nodes.gtsam_poses import loop_closure_pose
from aefabmap_ros.verification.relative_pose import pose_message_to_matrix

SECOND = 1_000_000_000
PoseOf = Callable[[Any], tuple[gtsam.Pose3, np.ndarray]]


def stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * SECOND + int(stamp.nanosec)


def stamp_text(stamp: Any) -> str:
    return f"{stamp.sec}.{stamp.nanosec:09d}"


def wrong_pose_keys(run: Path) -> set[tuple[str, str]]:
    with (run / "evaluation_online" / "closures.csv").open() as file:
        return {(row["query_stamp"], row["matched_stamp"]) for row in csv.DictReader(file)
                if row["topic"] == "loop_closures" and row["pose_wrong"] in ("1", "True", "true")}


def replay(odometry: list[tuple[int, gtsam.Pose3]], closures: list[Any], pose_of: PoseOf,
           lag_ns: int) -> list[tuple[int, gtsam.Pose3]]:
    graph = PoseGraph(PoseGraphConfig())
    arriving = sorted(((stamp_ns(message.header.stamp) + lag_ns, index) for index, message in enumerate(closures)))
    next_closure = 0
    for stamp, pose in odometry:
        graph.add_odometry(stamp, pose)
        while next_closure < len(arriving) and arriving[next_closure][0] <= stamp:
            message = closures[arriving[next_closure][1]]
            relative, covariance = closure_in_base_frame(*pose_of(message), gtsam.Pose3())  # as pose_graph_node
            graph.add_closure(Closure(stamp_ns(message.header.stamp), stamp_ns(message.matched_stamp), relative,
                                      covariance))
            next_closure += 1
    return graph.trajectory()


def ate_share(test: Path, trajectory: list[tuple[int, gtsam.Pose3]]) -> float:
    """The trajectory's ATE over odometry's at the same stamps."""
    with tempfile.TemporaryDirectory() as folder:
        keyframes = Path(folder) / "keyframes.tum"
        with keyframes.open("w") as file:
            for stamp, pose in trajectory:
                values = [*pose.translation(), *Rotation.from_matrix(pose.rotation().matrix()).as_quat()]
                file.write(f"{stamp / SECOND:.9f} " + " ".join(f"{value:.9f}" for value in values) + "\n")
        figures = ate_figures(test, keyframes, None)
    return figures.closures_m / figures.odometry_m


def true_pose_of(truth: PoseTruth) -> PoseOf:
    def pose_of(message: Any) -> tuple[gtsam.Pose3, np.ndarray]:
        query, place = truth.pose_at(stamp_ns(message.header.stamp)), truth.pose_at(stamp_ns(message.matched_stamp))
        assert query is not None and place is not None, "closure stamps outside the ground truth"
        _, covariance = loop_closure_pose(message)
        return gtsam.Pose3(np.linalg.inv(query) @ place), covariance
    return pose_of


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("test", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--lag-s", type=float, default=0.4)
    args = parser.parse_args()
    recorded = read_recording(args.run / "online_recording").published
    closures = [message for message in (recorded[1] if recorded else []) if message.pose_available]
    odometry = [(message.stamp_ns, gtsam.Pose3(pose_message_to_matrix(message.message.pose.pose)))
                for message in bags.read_messages(args.test / "bag", ["/odom"])]
    wrong = wrong_pose_keys(args.run)
    right = [message for message in closures
             if (stamp_text(message.header.stamp), stamp_text(message.matched_stamp)) not in wrong]
    lag_ns = round(args.lag_s * SECOND)
    rows = [("as published", closures, loop_closure_pose),
            ("without the wrong poses", right, loop_closure_pose),
            ("ground-truth poses", closures, true_pose_of(read_pose_truth(args.test / "groundtruth.tum")))]
    print(f"{args.run}: {len(closures)} closures with a pose, {len(closures) - len(right)} of them wrong")
    for label, chosen, pose_of in rows:
        share = ate_share(args.test, replay(odometry, chosen, pose_of, lag_ns))
        print(f"  {label:<26} {len(chosen):5d} closures   ATE {share:.1%} of odometry's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
