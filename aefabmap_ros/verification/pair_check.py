"""One (query, place) pair of stored frames: the geometric check, and the relative pose of an accepted pair.

One camera (``camera``, ``image_size``) serves every frame of one robot. With several robots
(docs/fleet.md) each robot's frames are stored with its name and each robot has its own camera
(``robot_cameras``): a pair of two robots' frames is checked with their camera when the two are the same
(same intrinsics, distortion and image size, as robots of one model are), and is not checked at all when
they differ (``cameras_differ``; the chain refuses it, counted as such): the metric test and the pose
project both frames through one camera, and would be wrong for the other.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.closures import Outcomes
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.geometric import Verification, VerificationConfig, matched_points, verify_pair
from aefabmap_ros.verification.metric import KeypointDepths
from aefabmap_ros.verification.relative_pose import CameraModel, PoseOutcome, RelativePoseConfig, relative_pose


class RobotCamera(NamedTuple):
    """A robot's camera as its frames report it."""

    camera: CameraModel | None  # None: not known (no camera_info on the robot yet)
    image_size: tuple[int, int] | None  # (width, height)


def same_camera(first: RobotCamera, second: RobotCamera) -> bool:
    """Both cameras known and the same: intrinsics, distortion coefficients (zeros = none) and image size."""
    if first.camera is None or second.camera is None or first.image_size != second.image_size:
        return False
    width = max(first.camera.distortion.size, second.camera.distortion.size)
    distortions = [np.pad(c.distortion.astype(np.float64), (0, width - c.distortion.size))
                   for c in (first.camera, second.camera)]
    return bool(np.allclose(first.camera.matrix, second.camera.matrix, rtol=1e-6, atol=1e-9)
                and np.allclose(distortions[0], distortions[1], rtol=1e-6, atol=1e-12))


class PairCheck:
    """Verifies pairs of frames of a ``FrameStore`` with the intrinsics and image size known so far."""

    def __init__(self, store: FrameStore, config: VerificationConfig, pose_config: RelativePoseConfig,
                 outcomes: Outcomes, camera: CameraModel | None = None) -> None:
        self.store = store
        self.config = config  # replaced whole when a runtime parameter changes
        self.pose_config = pose_config
        self.outcomes = outcomes
        self.camera = camera
        self.image_size: tuple[int, int] | None = None  # (width, height), for the metric test
        self.robot_cameras: dict[str, RobotCamera] = {}  # several robots: each robot's own camera

    def cameras_differ(self, query_ns: int, place_ns: int) -> bool:
        """The two frames are of robots whose cameras are both known and differ (the pair is not checked)."""
        cameras = self._robot_cameras(query_ns, place_ns)
        return cameras is not None and all(c.camera is not None for c in cameras) \
            and not same_camera(*cameras)

    def _robot_cameras(self, query_ns: int, place_ns: int) -> tuple[RobotCamera, RobotCamera] | None:
        """The two frames' robots' cameras; None when the frames name no robot (one camera for all)."""
        robots = self.store.robot_of(query_ns), self.store.robot_of(place_ns)
        if robots[0] is None or robots[1] is None:
            return None
        unknown = RobotCamera(None, None)
        return self.robot_cameras.get(robots[0], unknown), self.robot_cameras.get(robots[1], unknown)

    def _camera(self, query_ns: int, place_ns: int) -> RobotCamera:
        """The camera of the pair: the one camera, or the two robots' when it is the same (else unknown)."""
        cameras = self._robot_cameras(query_ns, place_ns)
        if cameras is None:
            return RobotCamera(self.camera, self.image_size)
        return cameras[0] if same_camera(*cameras) else RobotCamera(None, None)

    def verify(self, query_ns: int, query: Features, place_ns: int, place: Features) -> Verification:
        """The geometric check; with both frames' depths and the intrinsics, the metric test decides too
        (verification/metric.py)."""
        verification = verify_pair(query, place, self.config, self._pair_depths(query_ns, place_ns))
        if verification.accepted and not verification.epipolar_accepted:
            self.outcomes.ok("metric_test_accepted")
        elif verification.epipolar_accepted and not verification.accepted:
            self.outcomes.ok("metric_test_refused_no_view_overlap")
        return verification

    def pose(self, query_ns: int, query: Features, place_ns: int, place: Features,
             verification: Verification) -> PoseOutcome:
        """The place camera in the query camera's frame, from the matches verification accepted."""
        rows = verification.matched_rows
        assert rows is not None, "verify_pair keeps the matched rows of every verification it returns"
        query_points, place_points = matched_points(query, place, rows)
        # The depth store samples the stored keypoints in their order: a keypoint row is its depth's index.
        place_depths = self._depths_at(place_ns, rows[:, 1])
        query_depths = self._depths_at(query_ns, rows[:, 0])
        outcome = relative_pose(query_points, place_points, self._camera(query_ns, place_ns).camera, self.pose_config,
                                place_depths,
                                None if place_depths is None else query_depths)
        self.outcomes.ok(f"pose_{outcome.status.name.lower()}")
        return outcome

    def _pair_depths(self, query_ns: int, place_ns: int) -> KeypointDepths | None:
        camera, image_size = self._camera(query_ns, place_ns)
        if camera is None or image_size is None:
            return None
        query_depths, place_depths = self.store.depths_of(query_ns), self.store.depths_of(place_ns)
        if query_depths is None or place_depths is None:
            return None
        return KeypointDepths(camera, image_size, query_depths.keypoints, place_depths.keypoints,
                              query_depths.grid, place_depths.grid)

    def _depths_at(self, stamp_ns: int, keypoint_rows: np.ndarray) -> np.ndarray | None:
        """The stored depths of a frame's keypoints ``keypoint_rows``; None when that frame has none."""
        frame_depths = self.store.depths_of(stamp_ns)
        return None if frame_depths is None else frame_depths.keypoints[keypoint_rows].astype(np.float64)
