"""The odometry gate's queue: a closure whose own pose is unusable is refused, never judged on NaN."""

from __future__ import annotations

import gtsam
import numpy as np

from aefabmap_ros.backend.odometry_gate import OdometryGate
from aefabmap_ros.backend.pose_graph import PoseGraphConfig
from aefabmap_ros.verification.closures import Closure, CountedOutcomes, Detection
from aefabmap_ros.verification.loop_tracking import LoopTracks
from aefabmap_ros.verification.odometry_wait import OdometryWait
from aefabmap_ros.verification.relative_pose import PoseOutcome, PoseStatus, RelativePose

SECOND = 1_000_000_000



def _closure(query_id: int, rotation: np.ndarray, translation: np.ndarray, covariance: np.ndarray) -> Closure:
    pose = RelativePose(rotation, translation, covariance, metric=True, inliers=50)
    return Closure(Detection(3 * SECOND, query_id, -1, 1, SECOND, 0.9, -1.0), 50, PoseOutcome(pose, PoseStatus.OK))


def test_a_closure_with_a_broken_pose_or_none_is_refused_and_a_sound_one_published() -> None:
    outcomes, published = CountedOutcomes(), list[Closure]()
    wait = OdometryWait(OdometryGate(PoseGraphConfig(), gtsam.Pose3()), 5.0, 10, LoopTracks(0.0, 0.0),
                        published.append, outcomes)
    for sec in (1, 2, 3):  # standing still
        assert wait.add_odometry(sec * SECOND, gtsam.Pose3())
    covariance = np.eye(6) * 1e-4
    nan_rotation = np.eye(3)
    nan_rotation[0, 0] = np.nan
    wait.submit(_closure(1, nan_rotation, np.zeros(3), covariance))
    asymmetric = covariance.copy()
    asymmetric[0, 1] = 1.0
    wait.submit(_closure(2, np.eye(3), np.zeros(3), asymmetric))
    wait.submit(Closure(Detection(3 * SECOND, 3, -1, 1, SECOND, 0.9, -1.0), 50,
                        PoseOutcome(None, PoseStatus.TOO_FEW_POINTS)))
    wait.submit(_closure(4, np.eye(3), np.zeros(3), covariance))  # agrees: the robot did not move
    assert [c.detection.query_id for c in published] == [4]
    assert outcomes.counts["dropped_bad_closure_pose"] == 2
    assert outcomes.counts["dropped_no_pose_for_odometry_gate"] == 1


def test_a_closure_into_another_session_or_robot_is_not_judged_by_this_odometry() -> None:
    """Odometry is the query session's own frame: standing still here says nothing of where an earlier
    session's place (or another robot's) is, so a pose far from it is not refused; within the session it is."""
    outcomes, published = CountedOutcomes(), list[Closure]()
    wait = OdometryWait(OdometryGate(PoseGraphConfig(), gtsam.Pose3()), 5.0, 10, LoopTracks(0.0, 0.0),
                        published.append, outcomes)
    for sec in (1, 2, 3):  # standing still
        assert wait.add_odometry(sec * SECOND, gtsam.Pose3())
    far = RelativePose(np.eye(3), np.array([5.0, 0.0, 0.0]), np.eye(6) * 1e-4, metric=True, inliers=50)
    within = Detection(3 * SECOND, 1, -1, 1, SECOND, 0.9, -1.0, "", 1, "r1", 1, "r1")
    earlier_session = Detection(3 * SECOND, 2, -1, 1, SECOND, 0.9, -1.0, "", 1, "r1", 0, "r1")
    other_robot = Detection(3 * SECOND, 3, -1, 1, SECOND, 0.9, -1.0, "", 1, "r1", 1, "r2")
    for detection in (within, earlier_session, other_robot):
        wait.submit(Closure(detection, 50, PoseOutcome(far, PoseStatus.OK)))
    assert [c.detection.query_id for c in published] == [2, 3]
    assert outcomes.counts["across_sessions_unchecked_by_odometry"] == 2
    assert outcomes.counts["dropped_inconsistent_with_odometry"] == 1
