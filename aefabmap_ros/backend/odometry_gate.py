"""Loop closures checked against odometry before they are published (verifier_node's odometry gate).

Appearance and local geometry cannot tell apart two places that look the same: the same shop front
and road markings at two street corners give a FAB-MAP match, 30-60 inliers of one fundamental
matrix, and keypoint depths that agree with the PnP pose (measured on a synthetic town, seed 7, with
the dense-video route: 22 such closures of 1,540, all passing every local check). The
robot's odometry can: the closure says the two camera poses are related by T, odometry says by
T_odom, with an error that grows with the distance travelled between the two stamps. The gate
refuses a closure whose disagreement exceeds what that drift explains: the example backend's gate
(backend/pose_graph.py), against raw odometry instead of the optimised graph. That is looser --
drift is bounded by the whole path between the two stamps, not by the closures in between -- so a
true closure the backend would take is not refused here for want of a graph.
"""

from __future__ import annotations

import gtsam
import numpy as np

from aefabmap_ros.backend.factors import drift_covariance, loop_factor_covariance
from aefabmap_ros.backend.graph_types import PoseGraphConfig
from aefabmap_ros.backend.odometry import OdometryBuffer, closure_in_base_frame, odometry_disagreement
from aefabmap_ros.verification.gate import GateResult


class OdometryGate:
    """Odometry by stamp, and the test of a camera-frame closure against it."""

    def __init__(self, config: PoseGraphConfig, base_to_camera: gtsam.Pose3) -> None:
        self.config = config
        self.base_to_camera = base_to_camera
        self.odometry = OdometryBuffer(config.max_odometry)

    @property
    def active(self) -> bool:
        """True once odometry has arrived: before that (a robot without odometry) closures pass unchecked."""
        return len(self.odometry) > 0

    @property
    def threshold(self) -> float:
        return self.config.gate_chi2

    def add_odometry(self, stamp_ns: int, pose: gtsam.Pose3) -> bool:
        """Buffer ``T_odom_base`` at that stamp; False (ignored) unless it is after the last one."""
        return self.odometry.add(stamp_ns, pose)

    def reaches(self, query_ns: int, place_ns: int) -> bool:
        """Whether odometry has come up to both stamps (else ``check`` says NOT_YET)."""
        last_ns = self.odometry.last_ns
        return last_ns is not None and max(query_ns, place_ns) <= last_ns

    def check(self, query_ns: int, place_ns: int, query_to_place: gtsam.Pose3,
              covariance: np.ndarray) -> tuple[GateResult, float]:
        """The closure (the place camera in the query camera's frame, its covariance in ROS order x y z rot)
        against odometry: the result and the Mahalanobis distance squared (NaN without odometry)."""
        if not self.reaches(query_ns, place_ns):
            return GateResult.NOT_YET, float("nan")
        query = self.odometry.pose_at(query_ns)
        place = self.odometry.pose_at(place_ns)
        if query is None or place is None:
            return GateResult.NO_ODOMETRY, float("nan")
        pose, base_covariance = closure_in_base_frame(query_to_place, covariance, self.base_to_camera)
        drift = drift_covariance(self.config, abs(query[1] - place[1]))
        distance = odometry_disagreement(pose, loop_factor_covariance(self.config, base_covariance),
                                         query[0].between(place[0]), drift)
        if distance > self.config.gate_chi2:
            return GateResult.INCONSISTENT, distance
        return GateResult.CONSISTENT, distance
