"""The demo's backend part: closures' relative poses against ground truth, a wrong closure injected
into a second backend, and the trajectory error of odometry alone against odometry + closures.

Two pose_graph_node processes hear the same odometry (``/odom`` from the bag). The first is the
one ``aefabmap_launch --backend`` starts, on ``/loop_closures``. The second (``pose_graph_injected``)
listens on ``INJECTED_TOPIC``, where the demo relays every published closure and, once, a wrong
one: a copy of a real closure (same relative pose) whose matched place is moved to the nearest
frame at least ``WRONG_PLACE_DISTANCE_M`` from the true one. Both write their keyframe trajectories (TUM) on shutdown;
the ATEs are computed on the clean backend's keyframe stamps, so all three figures (odometry, with
closures, with the wrong closure too) are over the same poses.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.verification.pose_error import OUTSIDE_COVARIANCE_CHI2, PoseError, relative_pose_error
from aefabmap_ros.verification.relative_pose import pose_message_to_matrix

INJECTED_TOPIC = "demo/loop_closures_injected"
INJECTED_NODE = "pose_graph_injected"
# The wrong closure is sent after this many real ones (the graph has some structure to resist it),
# to a place this far from the true one: close enough that the odometry gate (drift of ~2 % of the
# path between them) lets it in, so the robust kernel has to resist it. (20 frames, 14.7 m, were
# simply refused by the gate.)
INJECT_AFTER_CLOSURES = 10
WRONG_PLACE_DISTANCE_M = 3.0


@dataclass
class Injection:
    query: int
    true_place: int
    wrong_place: int
    distance_m: float  # between the true and the wrong place's camera centres (ground truth)


@dataclass
class PoseErrors:
    """Relative pose errors of the published closures, monocular and metric apart."""

    metric: list[PoseError] = field(default_factory=list)
    monocular: list[PoseError] = field(default_factory=list)
    without_pose: int = 0

    def summary(self) -> str:
        lines = [f"    relative poses of the published closures against ground truth: {len(self.metric)} metric "
                 f"(PnP with depth), {len(self.monocular)} monocular, {self.without_pose} without a pose"]
        for label, errors in (("metric", self.metric), ("monocular", self.monocular)):
            if not errors:
                continue
            rotation = np.median([error.rotation_deg for error in errors])
            direction = np.nanmedian([error.direction_deg for error in errors])
            text = (f"      {label}: median rotation error {rotation:.3f} deg (target <= 1), translation direction "
                    f"{direction:.3f} deg (target <= 3)")
            if label == "metric":
                text += f", translation {100 * np.median([e.translation_m for e in errors]):.2f} cm (target <= 5)"
                outside = sum(1 for e in errors if e.mahalanobis2 > OUTSIDE_COVARIANCE_CHI2)
                text += f"; {outside} outside their covariance's 99.9 % region"
            lines.append(text)
        return "\n".join(lines)


class BackendCheck:
    """Fed every published closure (by the demo's printer): scores its pose, relays it to the second
    backend, and injects the wrong closure once."""

    def __init__(self, node: Any, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
        from aefabmap_msgs.msg import LoopClosure

        self._stamps = stamps_ns
        self._poses = poses  # (N, 3, 4) ground-truth camera-to-world
        self.errors = PoseErrors()
        self.injection: Injection | None = None
        self._relayed = 0
        self._publisher = node.create_publisher(LoopClosure, INJECTED_TOPIC, 100)

    def on_closure(self, message: Any, query: int, place: int) -> None:
        self._publisher.publish(message)
        self._relayed += 1
        known = query < len(self._poses) and place < len(self._poses)
        if not message.pose_available or not known:
            self.errors.without_pose += 1
            return

        covariance = np.asarray(message.pose_covariance, dtype=np.float64) if message.translation_metric else None
        error = relative_pose_error(self._poses[query], self._poses[place], pose_message_to_matrix(message.pose),
                                    covariance)
        (self.errors.metric if message.translation_metric else self.errors.monocular).append(error)
        if self.injection is None and self._relayed >= INJECT_AFTER_CLOSURES:
            self._inject(message, query, place)

    def _inject(self, message: Any, query: int, place: int) -> None:
        from aefabmap_ros.nodes.messages import time_from_ns

        wrong_place = wrong_place_near(self._poses, place, WRONG_PLACE_DISTANCE_M)
        wrong = copy.deepcopy(message)
        wrong.matched_stamp = time_from_ns(int(self._stamps[wrong_place]))
        self._publisher.publish(wrong)
        distance = float(np.linalg.norm(self._poses[place][:3, 3] - self._poses[wrong_place][:3, 3]))
        self.injection = Injection(query, place, wrong_place, distance)
        print(f"    injected a WRONG closure into {INJECTED_NODE}: frame {query} -> frame {wrong_place} "
              f"(the true place is frame {place}, {distance:.2f} m away)", flush=True)


def wrong_place_near(poses: np.ndarray, place: int, distance_m: float) -> int:
    """The frame nearest (in frames) to ``place`` whose camera centre is at least ``distance_m`` from its own."""
    distances = np.linalg.norm(poses[:, :3, 3] - poses[place, :3, 3], axis=1)
    far_enough = np.flatnonzero(distances >= distance_m)
    if far_enough.size == 0:
        raise ValueError(f"no frame is {distance_m} m from frame {place}")
    return int(far_enough[np.argmin(np.abs(far_enough - place))])


@dataclass(frozen=True)
class AteFigures:
    keyframes: int
    odometry_all_m: float  # odometry over every frame
    odometry_m: float  # odometry at the keyframe stamps
    closures_m: float  # the backend's keyframes
    injected_m: float | None  # the second backend's, at the same stamps


def ate_figures(sequence: Path, keyframes: Path, injected: Path | None) -> AteFigures:
    """ATE (SE(3) alignment) of odometry.tum and the backends' keyframe files against groundtruth.tum."""
    from aefabmap_ros.evaluation.trajectory_error import absolute_trajectory_error, at_stamps, read_tum

    reference = read_tum(sequence / "groundtruth.tum")
    odometry = read_tum(sequence / "odometry.tum")
    optimised = read_tum(keyframes)
    stamps = optimised.timestamps
    injected_m = None
    if injected is not None:
        injected_m = absolute_trajectory_error(reference, at_stamps(read_tum(injected), stamps)).rmse_m
    return AteFigures(
        keyframes=len(stamps),
        odometry_all_m=absolute_trajectory_error(reference, odometry).rmse_m,
        odometry_m=absolute_trajectory_error(reference, at_stamps(odometry, stamps)).rmse_m,
        closures_m=absolute_trajectory_error(reference, optimised).rmse_m,
        injected_m=injected_m,
    )


def ate_summary(figures: AteFigures) -> str:
    ratio = figures.closures_m / figures.odometry_m if figures.odometry_m > 0 else float("nan")
    lines = [f"    ATE RMSE (evo, SE(3) alignment) over the backend's {figures.keyframes} keyframes:",
             f"      odometry alone           {figures.odometry_m:.3f} m   "
             f"(every frame: {figures.odometry_all_m:.3f} m)",
             f"      odometry + closures      {figures.closures_m:.3f} m   ({100 * ratio:.1f} % of odometry; "
             f"target <= 30 %)"]
    if figures.injected_m is not None:
        change = figures.injected_m / figures.closures_m - 1.0 if figures.closures_m > 0 else float("nan")
        lines.append(f"      + one wrong closure      {figures.injected_m:.3f} m   ({100 * change:+.1f} %; "
                     f"target < +10 %)")
    return "\n".join(lines)
