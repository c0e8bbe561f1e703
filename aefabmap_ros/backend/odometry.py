"""Odometry by stamp and a loop closure in the robot's frame, shared by the pose graph and the odometry gate:
the buffer that interpolates odometry poses (SE(3) geodesic), a camera-frame closure moved into the base
(odometry child) frame, and its disagreement with the relative pose odometry predicts. gtsam and numpy, and
the covariance order the verifier publishes (verification/pose_covariance.py).
"""

from __future__ import annotations

import bisect
import itertools

import gtsam
import numpy as np

from aefabmap_ros.verification.pose_covariance import to_ros_order


def interpolate(before: gtsam.Pose3, after: gtsam.Pose3, fraction: float) -> gtsam.Pose3:
    """The SE(3) geodesic from ``before`` (0) to ``after`` (1)."""
    return before.compose(gtsam.Pose3.Expmap(fraction * gtsam.Pose3.Logmap(before.between(after))))


class OdometryBuffer:
    """Odometry poses by stamp, strictly increasing; ``pose_at`` interpolates.

    At most ``max_samples`` are kept. By default the oldest are forgotten first (a gate that only checks recent
    closures needs no more); with ``decimate`` a full buffer drops every second sample instead (the first and
    the newest stay), so it still covers the whole run at half the rate: what a session of a saved map needs,
    since a later session's closure may match any of its stamps. Each kept sample keeps its distance travelled.
    """

    def __init__(self, max_samples: int, decimate: bool = False) -> None:
        self.max_samples = max_samples
        self.decimate = decimate
        self._stamps: list[int] = []
        self._poses: list[gtsam.Pose3] = []
        self._paths: list[float] = []  # distance travelled since the first sample, metres

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def first_ns(self) -> int | None:
        return self._stamps[0] if self._stamps else None

    @property
    def last_ns(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_ns: int, pose: gtsam.Pose3) -> bool:
        """False (and nothing stored) when the stamp is not after the last one."""
        if self._stamps and stamp_ns <= self._stamps[-1]:
            return False
        step = float(np.linalg.norm(pose.translation() - self._poses[-1].translation())) if self._poses else 0.0
        self._paths.append(self._paths[-1] + step if self._paths else 0.0)
        self._stamps.append(stamp_ns)
        self._poses.append(pose)
        if len(self._stamps) > self.max_samples:
            self._shrink()
        return True

    def _shrink(self) -> None:
        if not self.decimate:
            drop = len(self._stamps) - self.max_samples
            del self._stamps[:drop], self._poses[:drop], self._paths[:drop]
            return
        # Every second sample, and the newest: at most max_samples // 2 + 1 left (<= max_samples for max >= 2).
        keep = [*range(0, len(self._stamps) - 1, 2), len(self._stamps) - 1]
        self._stamps = [self._stamps[index] for index in keep]
        self._poses = [self._poses[index] for index in keep]
        self._paths = [self._paths[index] for index in keep]

    def split_from(self, stamp_ns: int) -> tuple[list[int], list[gtsam.Pose3]]:
        """Remove and return (stamps, poses) of the samples at or after ``stamp_ns``: odometry that turned out to
        belong to a session that started then."""
        index = bisect.bisect_left(self._stamps, stamp_ns)
        moved = self._stamps[index:], self._poses[index:]
        del self._stamps[index:], self._poses[index:], self._paths[index:]
        return moved

    def samples(self) -> tuple[list[int], list[gtsam.Pose3], list[float]]:
        """Stamps, poses and distances travelled of the kept samples (copies), oldest first."""
        return list(self._stamps), list(self._poses), list(self._paths)

    def restore(self, stamps_ns: list[int], poses: list[gtsam.Pose3], paths_m: list[float]) -> None:
        """Replace the content by saved samples (``samples``' output): stamps strictly increasing, paths kept as
        given (a decimated buffer's distances are those of the full run, not of the kept samples)."""
        if not len(stamps_ns) == len(poses) == len(paths_m):
            raise ValueError(f"{len(stamps_ns)} stamps, {len(poses)} poses and {len(paths_m)} distances")
        if any(later <= earlier for earlier, later in itertools.pairwise(stamps_ns)):
            raise ValueError("odometry stamps are not strictly increasing")
        self._stamps, self._poses, self._paths = list(stamps_ns), list(poses), list(paths_m)
        while len(self._stamps) > self.max_samples:
            self._shrink()

    def pose_at(self, stamp_ns: int) -> tuple[gtsam.Pose3, float] | None:
        """Odometry and distance travelled at that stamp, interpolated; None outside the buffer."""
        if not self._stamps or not self._stamps[0] <= stamp_ns <= self._stamps[-1]:
            return None
        after = bisect.bisect_left(self._stamps, stamp_ns)
        if self._stamps[after] == stamp_ns:
            return self._poses[after], self._paths[after]
        before = after - 1
        fraction = (stamp_ns - self._stamps[before]) / (self._stamps[after] - self._stamps[before])
        path = self._paths[before] + fraction * (self._paths[after] - self._paths[before])
        return interpolate(self._poses[before], self._poses[after], fraction), path


def ros_to_gtsam_covariance(covariance: np.ndarray) -> np.ndarray:
    """(x, y, z, rot) -> gtsam's Pose3 tangent order (rot, x, y, z): the swap ``to_ros_order`` makes, its own
    inverse."""
    return to_ros_order(covariance)


def pose_covariance_to_tangent(pose: gtsam.Pose3, covariance: np.ndarray) -> np.ndarray:
    """A PoseWithCovariance's covariance (ROS order x y z rot; errors in the axes of the frame the pose is
    given in: t + dt, Exp(dtheta) R) as gtsam's (rot, trans) covariance of a right perturbation
    pose.compose(Exp(xi)).

    To first order pose.compose(Exp((w, v))) is (R Exp(w), t + R v) = (Exp(R w) R, t + R v), so w = R^T dtheta
    and v = R^T dt."""
    to_pose_axes = np.kron(np.eye(2), pose.rotation().matrix().T)
    tangent = to_pose_axes @ ros_to_gtsam_covariance(np.asarray(covariance, dtype=np.float64)) @ to_pose_axes.T
    return np.asarray((tangent + tangent.T) / 2)


def closure_in_base_frame(query_to_place: gtsam.Pose3, covariance: np.ndarray, base_to_camera: gtsam.Pose3
                          ) -> tuple[gtsam.Pose3, np.ndarray]:
    """A camera-frame closure (the place camera in the query camera's frame, covariance as LoopClosure's:
    ROS order x y z rot, errors in the query camera's axes) as the same closure between the two base
    (odometry child) frames, its covariance over gtsam's right perturbation in ROS order.

    ``base_to_camera`` is T_base_camera (the camera's pose on the robot). The pose is conjugated,
    T_qbase_pbase = T_bc T_qc_pc T_bc^-1; a right perturbation Exp(xi) of the camera pose is Exp(Ad(T_bc) xi)
    of the base pose, so the covariance is moved by that adjoint.
    """
    pose = base_to_camera.compose(query_to_place).compose(base_to_camera.inverse())
    adjoint = base_to_camera.AdjointMap()  # gtsam order (rot, trans)
    moved = adjoint @ pose_covariance_to_tangent(query_to_place, covariance) @ adjoint.T
    moved = (moved + moved.T) / 2  # exactly symmetric again (the graph checks it)
    return pose, to_ros_order(moved)


def odometry_disagreement(query_to_place: gtsam.Pose3, loop_covariance: np.ndarray, predicted: gtsam.Pose3,
                          drift: np.ndarray) -> float:
    """Mahalanobis distance squared (6 dof) between a closure's ``query_to_place`` and the ``predicted``
    relative pose (odometry's, or the graph's), under the closure's and the drift's covariances (gtsam order)."""
    residual = gtsam.Pose3.Logmap(query_to_place.between(predicted))
    return float(residual @ np.linalg.solve(loop_covariance + drift, residual))
