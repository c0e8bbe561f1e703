"""The verification chain with several robots (docs/fleet.md), without ROS: frames keyed by stamp and robot,
detections checked against the robots they name, each robot's camera and odometry gate."""

from __future__ import annotations

import gtsam
import numpy as np

from aefabmap_ros.backend.odometry_gate import OdometryGate
from aefabmap_ros.backend.pose_graph import PoseGraphConfig
from aefabmap_ros.verification.chain import LoopClosureChain
from aefabmap_ros.verification.closures import Closure, Detection
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.pair_check import RobotCamera
from aefabmap_ros.verification.relative_pose import CameraModel, PoseStatus, RelativePoseConfig
from test.verification.test_chain import CAMERA, SECOND, SIZE, Outcomes
from test.verification.test_geometric import _two_views

OTHER_CAMERA = CameraModel(CAMERA.matrix * np.array([[1.1], [1.1], [1.0]]))


def _chain(gates: bool = False) -> tuple[LoopClosureChain, Outcomes, list[Closure]]:
    outcomes, published = Outcomes(), list[Closure]()
    robot_gates = {robot: OdometryGate(PoseGraphConfig(), gtsam.Pose3()) for robot in ("r1", "r2")} if gates else None
    chain = LoopClosureChain(FrameStore(1000, 2**30, 500, keep_depths=True), VerificationConfig(candidates=1,
                             track_seconds=0.0), RelativePoseConfig(), published.append, outcomes,
                             robot_gates=robot_gates)
    chain.pairs.robot_cameras = {"r1": RobotCamera(CAMERA, SIZE), "r2": RobotCamera(CAMERA, SIZE)}
    return chain, outcomes, published


def _detection(query_sec: int, place_sec: int, query_robot: str, place_robot: str, query_id: int = 1) -> Detection:
    return Detection(query_sec * SECOND, query_id, -1, 0, place_sec * SECOND, 0.99, -1.0, "", 0, query_robot, 0,
                     place_robot)


def test_an_inter_robot_closure_is_verified_with_the_robots_named_and_a_pose() -> None:
    query, place, _ = _two_views(seed=21)
    chain, _, published = _chain()
    assert chain.add_frame(1 * SECOND, "r1", place, None)
    assert chain.add_frame(3 * SECOND, "r2", query, None)
    chain.add_detection(_detection(3, 1, "r2", "r1"))
    (closure,) = published
    assert (closure.detection.query_robot, closure.detection.matched_robot) == ("r2", "r1")
    assert closure.pose.status is PoseStatus.OK


def test_a_stamp_of_another_robot_is_dropped_and_a_mismatched_detection_never_verified() -> None:
    query, place, _ = _two_views(seed=21)
    chain, outcomes, published = _chain()
    chain.add_frame(1 * SECOND, "r1", place, None)
    assert not chain.add_frame(1 * SECOND, "r2", query, None)  # robot r1's stamp: r2's frame is not kept
    assert chain.store.robot_of(1 * SECOND) == "r1"
    chain.add_frame(3 * SECOND, "r2", query, None)
    chain.add_detection(_detection(3, 1, "r2", "r2"))  # names r2 for the place, which is r1's frame
    chain.add_detection(_detection(3, 1, "r1", "r1", query_id=2))  # names r1 for r2's query
    assert not published
    assert outcomes.counts["dropped_stamp_of_another_robot"] == 1 and outcomes.counts["dropped_robot_mismatch"] == 2


def test_robots_with_different_cameras_are_not_verified_as_a_pair() -> None:
    query, place, _ = _two_views(seed=21)
    chain, outcomes, published = _chain()
    chain.pairs.robot_cameras["r2"] = RobotCamera(OTHER_CAMERA, SIZE)
    chain.add_frame(1 * SECOND, "r1", place, None)
    chain.add_frame(3 * SECOND, "r2", query, None)
    chain.add_detection(_detection(3, 1, "r2", "r1"))
    assert not published and outcomes.counts["dropped_cameras_differ"] == 1


def test_each_robot_is_gated_by_its_own_odometry() -> None:
    """r2's closure inside its own session waits for r2's odometry (r1's does not decide it); a closure between
    the robots is not judged by either."""
    query, place, _ = _two_views(seed=21)
    chain, outcomes, published = _chain(gates=True)
    chain.add_odometry(0, gtsam.Pose3(), "r2")  # r2's gate is active, its odometry not yet at 3 s
    chain.add_frame(1 * SECOND, "r2", place, None)
    chain.add_frame(3 * SECOND, "r2", query, None)
    chain.add_detection(_detection(3, 1, "r2", "r2"))
    assert not published and len(chain.odometry.waiting) == 1
    chain.add_odometry(0, gtsam.Pose3(), "r1")
    chain.add_odometry(10 * SECOND, gtsam.Pose3(), "r1")
    assert len(chain.odometry.waiting) == 1  # r1's odometry does not reach r2's closure
    chain.add_frame(5 * SECOND, "r1", place, None)
    chain.add_frame(7 * SECOND, "r2", query, None)
    chain.add_detection(_detection(7, 5, "r2", "r1", query_id=3))
    assert [c.detection.query_id for c in published] == [3]
    assert outcomes.counts["across_sessions_unchecked_by_odometry"] == 1
