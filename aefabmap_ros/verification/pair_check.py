"""One (query, place) pair of stored frames: the geometric check, and the relative pose of an accepted pair."""

from __future__ import annotations

import numpy as np

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.closures import Outcomes
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.geometric import Verification, VerificationConfig, matched_points, verify_pair
from aefabmap_ros.verification.metric import KeypointDepths
from aefabmap_ros.verification.relative_pose import CameraModel, PoseOutcome, RelativePoseConfig, relative_pose


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
        outcome = relative_pose(query_points, place_points, self.camera, self.pose_config, place_depths,
                                None if place_depths is None else query_depths)
        self.outcomes.ok(f"pose_{outcome.status.name.lower()}")
        return outcome

    def _pair_depths(self, query_ns: int, place_ns: int) -> KeypointDepths | None:
        if self.camera is None or self.image_size is None:
            return None
        query_depths, place_depths = self.store.depths_of(query_ns), self.store.depths_of(place_ns)
        if query_depths is None or place_depths is None:
            return None
        return KeypointDepths(self.camera, self.image_size, query_depths.keypoints, place_depths.keypoints,
                              query_depths.grid, place_depths.grid)

    def _depths_at(self, stamp_ns: int, keypoint_rows: np.ndarray) -> np.ndarray | None:
        """The stored depths of a frame's keypoints ``keypoint_rows``; None when that frame has none."""
        frame_depths = self.store.depths_of(stamp_ns)
        return None if frame_depths is None else frame_depths.keypoints[keypoint_rows].astype(np.float64)
