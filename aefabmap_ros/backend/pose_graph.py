"""An example SLAM backend: odometry keyframes + verified loop closures, optimised incrementally with iSAM2.

This is the pattern a user copies into their own backend (pose_graph_node is its thin ROS shell):

* odometry poses (``T_odom_base``) are buffered by stamp, strictly increasing;
* every loop closure endpoint becomes a keyframe at its image stamp, its odometry pose
  interpolated between the two nearest odometry samples (SE(3) geodesic); a keyframe inserted
  between two existing ones splits their odometry factor in two;
* consecutive keyframes are tied by odometry ``BetweenFactor``s whose noise grows with the distance
  travelled (``OdometryNoise``); the first keyframe has a tight prior;
* a closure adds a ``BetweenFactor`` from the query keyframe to the matched place's with the
  verifier's relative pose and covariance, behind a robust kernel (Cauchy) so that one wrong
  closure is down-weighted instead of dragging the graph.

iSAM2 factors by Cholesky, on the normal equations: fast, but it squares the system's condition
number, and a keyframe far from the anchor (30 km along a straight road, with the loop factors' 5 cm)
makes the system look singular to it (gtsam's "indeterminate linear system"). A closure whose update
fails so is added again by QR on a graph rebuilt from the factors kept before it (``factorization``
is then "QR" for good: slower per closure, and exact where Cholesky gave up); a closure QR
cannot take either is dropped (``solver_failed``), the graph as it was. Either way no gtsam error
leaves the graph half updated.

Keyframe poses are ``T_map_base``; ``map_to_odom`` is what a TF broadcaster publishes so that
``map -> odom -> base`` puts the robot on the optimised trajectory. No ROS import: gtsam and numpy only.
"""

from __future__ import annotations

import bisect
from collections import Counter, deque
from dataclasses import dataclass, field
from enum import Enum

import gtsam
import numpy as np

from aefabmap_ros.backend.odometry import (
    OdometryBuffer,
    odometry_disagreement,
    ros_to_gtsam_covariance,
)
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io.message_values import covariance_problem, psd_part

# Extra iSAM2 iterations after a closure, and the largest keyframe move (m) at which they stop.
MAX_EXTRA_ITERATIONS = 20
SETTLED_M = 0.001
# Two stamps this close (ns) are the same keyframe: a place seen again by a later closure reuses it.
SAME_KEYFRAME_NS = 1_000_000
MAX_DECIDED_KEPT = 5000


class ClosureResult(Enum):
    ADDED = "added"
    WAITING = "waiting_for_odometry"  # its query is newer than the last odometry: retried when odometry comes
    UNKNOWN_STAMP = "unknown_stamp"  # an endpoint before the odometry buffer (or a dropped waiting closure)
    NO_POSE = "no_pose"  # the closure carries no relative pose
    BAD_COVARIANCE = "bad_covariance"  # not a finite, symmetric positive semi-definite 6x6 (validation.py)
    INCONSISTENT = "inconsistent_with_odometry"  # further from the graph than odometry drift can explain
    SOLVER_FAILED = "solver_failed"  # iSAM2 could not take it, by Cholesky nor by QR: the graph is as before


@dataclass(frozen=True)
class PoseGraphConfig:
    odometry_translation_drift: float = field(default=0.02, metadata={
        "description": "Odometry translation error per metre travelled (standard deviation, fraction)."})
    odometry_rotation_drift_rad_per_m: float = field(default=0.005, metadata={
        "description": "Odometry rotation error per metre travelled (standard deviation, rad/m)."})
    odometry_min_sigma: float = field(default=0.01, metadata={
        "description": "Floor of the odometry factors' standard deviations (m and rad)."})
    loop_min_sigma_m: float = field(default=0.05, metadata={
        "description": "Added to every loop closure's position standard deviation (m): keeps a closure from "
                       "being over-confident."})
    loop_min_sigma_rad: float = field(default=0.01, metadata={
        "description": "Added to every loop closure's rotation standard deviation (rad)."})
    cauchy_scale: float = field(default=1.0, metadata={
        "description": "Scale of the Cauchy kernel on loop factors, in units of the disagreement odometry drift "
                       "can explain between the two keyframes."})
    gate_chi2: float = field(default=22.46, metadata={
        "description": "A closure whose residual against the graph exceeds this Mahalanobis distance squared "
                       "(6 dof; 22.46 = 99.9 %) under loop + odometry-drift covariance is refused."})
    max_odometry: int = field(default=200_000, metadata={
        "description": "Odometry samples kept for interpolation (oldest forgotten first)."})
    max_waiting: int = field(default=100, metadata={
        "description": "Closures waiting for odometry to reach their query stamp, at most."})

    def __post_init__(self) -> None:
        positive = ("odometry_translation_drift", "odometry_rotation_drift_rad_per_m", "odometry_min_sigma",
                    "loop_min_sigma_m", "loop_min_sigma_rad", "cauchy_scale", "gate_chi2")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"pose graph {name} must be > 0, got {getattr(self, name)}")
        if self.max_odometry < 2 or self.max_waiting < 1:
            raise ConfigError(f"pose graph max_odometry ({self.max_odometry}) must be >= 2 and "
                              f"max_waiting ({self.max_waiting}) >= 1")


@dataclass(frozen=True)
class Closure:
    """A verified loop closure: T_query_place (the place's base in the query's base frame) and its covariance
    over (x, y, z, rot x, rot y, rot z), as in LoopClosure.pose / pose_covariance."""

    query_ns: int
    place_ns: int
    query_to_place: gtsam.Pose3
    covariance: np.ndarray


@dataclass
class Keyframe:
    stamp_ns: int
    key: int
    odometry: gtsam.Pose3  # T_odom_base at the keyframe's stamp
    path_m: float  # odometry distance travelled at that stamp: odometry error grows with it


def drift_covariance(config: PoseGraphConfig, distance_m: float) -> np.ndarray:
    """Odometry error covariance (gtsam order: rot, trans) after travelling ``distance_m``."""
    sigma_t = max(config.odometry_translation_drift * distance_m, config.odometry_min_sigma)
    sigma_r = max(config.odometry_rotation_drift_rad_per_m * distance_m, config.odometry_min_sigma)
    return np.diag([sigma_r ** 2] * 3 + [sigma_t ** 2] * 3)


def loop_factor_covariance(config: PoseGraphConfig, covariance_ros: np.ndarray) -> np.ndarray:
    """A closure's covariance (ROS order x y z rot) in gtsam order, with the configured floor added.

    The covariance is one ``message_values.covariance_problem`` accepted: its round-off's negative
    eigenvalues are cut to 0 first (``psd_part``), so with the floor it is positive definite."""
    return ros_to_gtsam_covariance(psd_part(covariance_ros)) + np.diag(
        [config.loop_min_sigma_rad ** 2] * 3 + [config.loop_min_sigma_m ** 2] * 3)


def _isam_params(factorization: str) -> gtsam.ISAM2Params:
    params = gtsam.ISAM2Params()
    # Relinearise every step: the robust kernel's weights change as the graph moves (see _update).
    params.relinearizeSkip = 1
    params.setRelinearizeThreshold(0.01)
    params.setFactorization(factorization)
    return params


class PoseGraph:
    """Keyframes at closure endpoints, odometry and robust loop factors, optimised by iSAM2 on every closure."""

    def __init__(self, config: PoseGraphConfig) -> None:
        self.config = config
        self.odometry = OdometryBuffer(config.max_odometry)
        self.keyframes: list[Keyframe] = []  # by stamp
        self.counts: Counter[str] = Counter()
        # The latest closures decided (added or refused, not waiting): what a viewer draws as loop edges.
        self.decided: deque[tuple[Closure, ClosureResult]] = deque(maxlen=MAX_DECIDED_KEPT)
        self._waiting: list[Closure] = []
        self._chain_factors: dict[tuple[int, int], int] = {}  # (key before, key after) -> iSAM2 factor index
        self._factors: dict[int, gtsam.NonlinearFactor] = {}  # iSAM2 factor index -> factor, the graph's own
        self._next_key = 0
        self.factorization = "CHOLESKY"  # "QR" once Cholesky failed on this graph (module docstring)
        self.solver_error = ""  # gtsam's message of the last update that failed
        self._isam = gtsam.ISAM2(_isam_params(self.factorization))
        self._estimate = gtsam.Values()

    # -- input --------------------------------------------------------------------------------------------

    def add_odometry(self, stamp_ns: int, pose: gtsam.Pose3) -> list[ClosureResult]:
        """Buffer one odometry pose; closures waiting for it are retried (their results returned)."""
        if not self.odometry.add(stamp_ns, pose):
            self.counts["odometry_out_of_order"] += 1
            return []
        self.counts["odometry"] += 1
        ready = [closure for closure in self._waiting if closure.query_ns <= stamp_ns]
        if not ready:
            return []
        self._waiting = [closure for closure in self._waiting if closure.query_ns > stamp_ns]
        return [self.add_closure(closure) for closure in ready]

    def add_closure(self, closure: Closure) -> ClosureResult:
        result = self._add_closure(closure)
        self.counts[result.value] += 1
        if result is not ClosureResult.WAITING:
            self.decided.append((closure, result))
        return result

    def _add_closure(self, closure: Closure) -> ClosureResult:
        covariance = np.asarray(closure.covariance, dtype=np.float64)
        if covariance.shape != (6, 6) or covariance_problem(covariance) is not None:
            return ClosureResult.BAD_COVARIANCE
        last = self.odometry.last_ns
        # No odometry yet waits too: a backend's callbacks may take a closure before the odometry queued ahead of it.
        if last is None or max(closure.query_ns, closure.place_ns) > last:
            self._waiting.append(closure)
            if len(self._waiting) > self.config.max_waiting:
                self._waiting.pop(0)
                self.counts[ClosureResult.UNKNOWN_STAMP.value] += 1
            return ClosureResult.WAITING
        endpoints = (closure.query_ns, closure.place_ns)
        if any(self._find_keyframe(stamp_ns) is None and self.odometry.pose_at(stamp_ns) is None
               for stamp_ns in endpoints):
            return ClosureResult.UNKNOWN_STAMP  # checked first: a dropped closure leaves the graph as it was
        loop_covariance = loop_factor_covariance(self.config, covariance)
        (query_pose, query_path), (place_pose, place_path) = (self._predicted(stamp_ns) for stamp_ns in endpoints)
        # What odometry drift alone can explain between the two: the whole path travelled between them (an
        # upper bound once other closures tie them closer).
        drift = drift_covariance(self.config, abs(query_path - place_path))
        if odometry_disagreement(closure.query_to_place, loop_covariance, query_pose.between(place_pose),
                                 drift) > self.config.gate_chi2:
            return ClosureResult.INCONSISTENT
        # The Cauchy kernel's scale: the loop-whitened disagreement drift can explain. A true closure after
        # long drift keeps most of its weight; one the graph later contradicts (other closures) loses it.
        scale = self.config.cauchy_scale * float(np.sqrt(np.trace(drift[3:, 3:] + loop_covariance[3:, 3:])
                                                         / np.trace(loop_covariance[3:, 3:])))
        robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(scale),
                                                gtsam.noiseModel.Gaussian.Covariance(loop_covariance))
        # What a failed update must not leave changed (the estimate is replaced, never changed in place).
        kept = (list(self.keyframes), dict(self._chain_factors), dict(self._factors), self._next_key, self._estimate)
        while True:
            try:
                self._insert_closure(endpoints, closure.query_to_place, robust)
                return ClosureResult.ADDED
            except RuntimeError as exc:  # gtsam's IndeterminantLinearSystemException and kin
                self.solver_error = " ".join(str(exc).split())
                retry = self.factorization != "QR"
                # The failed update left its factors inside iSAM2: start again from the graph kept before it.
                self.keyframes, self._chain_factors, self._factors = list(kept[0]), dict(kept[1]), dict(kept[2])
                self._next_key, self._estimate = kept[3], kept[4]
                self._rebuild("QR")
                if not retry:
                    return ClosureResult.SOLVER_FAILED

    def _insert_closure(self, endpoints: tuple[int, int], query_to_place: gtsam.Pose3,
                        noise: gtsam.noiseModel.Base) -> None:
        """Keyframes at both endpoints (made where missing) and the loop factor between them; one iSAM2 update.
        A gtsam error leaves keyframes and iSAM2 half updated: the caller restores and rebuilds them."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        removed: list[int] = []
        tags: list[tuple[int, int] | None] = []  # per factor added: the keyframe pair of an odometry factor
        if not self.keyframes and self.odometry.first_ns is not None:
            # map == odom at the first odometry pose: the anchor (prior) of the whole graph.
            self._new_keyframe(self.odometry.first_ns, graph, values, removed, tags)
        keys = []
        for stamp_ns in endpoints:
            keyframe = self._find_keyframe(stamp_ns) or self._new_keyframe(stamp_ns, graph, values, removed, tags)
            assert keyframe is not None  # resolvable, checked above
            keys.append(keyframe.key)
        graph.add(gtsam.BetweenFactorPose3(keys[0], keys[1], query_to_place, noise))
        tags.append(None)
        self._update(graph, values, removed, tags)

    # -- output -------------------------------------------------------------------------------------------

    def trajectory(self) -> list[tuple[int, gtsam.Pose3]]:
        """Optimised keyframe poses T_map_base by stamp."""
        return [(keyframe.stamp_ns, self._estimate.atPose3(keyframe.key)) for keyframe in self.keyframes]

    def map_to_odom(self) -> gtsam.Pose3:
        """T_map_odom from the newest keyframe: identity before the first closure."""
        if not self.keyframes:
            return gtsam.Pose3()
        newest = self.keyframes[-1]
        return self._estimate.atPose3(newest.key).compose(newest.odometry.inverse())

    # -- graph building -----------------------------------------------------------------------------------

    def _find_keyframe(self, stamp_ns: int) -> Keyframe | None:
        stamps = [keyframe.stamp_ns for keyframe in self.keyframes]
        index = bisect.bisect_left(stamps, stamp_ns)
        for candidate in (index - 1, index):
            if 0 <= candidate < len(self.keyframes) and abs(stamps[candidate] - stamp_ns) <= SAME_KEYFRAME_NS:
                return self.keyframes[candidate]
        return None

    def _new_keyframe(self, stamp_ns: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                      removed: list[int], tags: list[tuple[int, int] | None]) -> Keyframe | None:
        found = self.odometry.pose_at(stamp_ns)
        if found is None:
            return None
        odometry, path_m = found
        keyframe = Keyframe(stamp_ns, self._next_key, odometry, path_m)
        self._next_key += 1
        index = bisect.bisect_left([existing.stamp_ns for existing in self.keyframes], stamp_ns)
        before = self.keyframes[index - 1] if index > 0 else None
        after = self.keyframes[index] if index < len(self.keyframes) else None
        if before is None and after is None:
            values.insert(keyframe.key, odometry)  # the first keyframe: map == odom there
            graph.add(gtsam.PriorFactorPose3(keyframe.key, odometry, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
            tags.append(None)
        else:
            anchor = before if before is not None else after
            assert anchor is not None
            anchor_pose = self._pose_of(anchor.key, values)
            values.insert(keyframe.key, anchor_pose.compose(anchor.odometry.between(odometry)))
        if before is not None and after is not None and (before.key, after.key) in self._chain_factors:
            removed.append(self._chain_factors.pop((before.key, after.key)))  # split the factor it interrupts
        for first, second in ((before, keyframe), (keyframe, after)):
            if first is not None and second is not None:
                graph.add(self._odometry_factor(first, second))
                tags.append((first.key, second.key))
        self.keyframes.insert(index, keyframe)
        return keyframe

    def _pose_of(self, key: int, pending: gtsam.Values) -> gtsam.Pose3:
        return pending.atPose3(key) if pending.exists(key) else self._estimate.atPose3(key)

    def _odometry_factor(self, first: Keyframe, second: Keyframe) -> gtsam.BetweenFactorPose3:
        relative = first.odometry.between(second.odometry)
        # Travelled, not the straight line: a loop ends near its start.
        covariance = drift_covariance(self.config, abs(second.path_m - first.path_m))
        return gtsam.BetweenFactorPose3(first.key, second.key, relative,
                                        gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.diag(covariance))))

    def _predicted(self, stamp_ns: int) -> tuple[gtsam.Pose3, float]:
        """Current estimate of the pose at a stamp (a keyframe's, else odometry moved with its nearest
        keyframe) and the distance travelled there."""
        existing = self._find_keyframe(stamp_ns)
        if existing is not None:
            return self._estimate.atPose3(existing.key), existing.path_m
        found = self.odometry.pose_at(stamp_ns)
        assert found is not None  # resolvable, checked by the caller
        odometry, path_m = found
        if not self.keyframes:
            return odometry, path_m
        index = bisect.bisect_left([keyframe.stamp_ns for keyframe in self.keyframes], stamp_ns)
        anchor = self.keyframes[max(index - 1, 0)]
        return self._estimate.atPose3(anchor.key).compose(anchor.odometry.between(odometry)), path_m

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, removed: list[int],
                tags: list[tuple[int, int] | None]) -> None:
        """One iSAM2 update and its extra iterations; the factors are recorded once all of it succeeded."""
        result = self._isam.update(graph, values, removed)
        new_indices = [int(index) for index in result.getNewFactorsIndices()]
        # The Cauchy kernel is re-weighted at each relinearisation (IRLS): a true closure far from the
        # drifted estimate starts with a small weight and gains it as the graph moves towards it; a wrong one
        # stays far and keeps a small weight. A few more iterations, until the estimate settles.
        for _ in range(MAX_EXTRA_ITERATIONS):
            before = self._isam.calculateEstimate()
            self._isam.update()
            keys = [keyframe.key for keyframe in self.keyframes]
            if _largest_change(before, self._isam.calculateEstimate(), keys) < SETTLED_M:
                break
        self._estimate = self._isam.calculateEstimate()
        # iSAM2 numbers the new factors in the order they were added: remember the odometry factors' numbers
        # so that a keyframe inserted later between two keyframes can remove the factor it splits.
        for position, (tag, index) in enumerate(zip(tags, new_indices, strict=True)):
            self._factors[index] = graph.at(position)
            if tag is not None:
                self._chain_factors[tag] = index
        for index in removed:
            self._factors.pop(index, None)

    def _rebuild(self, factorization: str) -> None:
        """A new iSAM2 (``factorization``) holding the recorded factors at the last estimate."""
        self.factorization = factorization
        self._isam = gtsam.ISAM2(_isam_params(factorization))
        if not self._factors:
            self._estimate = gtsam.Values()
            return
        old_indices = sorted(self._factors)
        graph = gtsam.NonlinearFactorGraph()
        for index in old_indices:
            graph.add(self._factors[index])
        result = self._isam.update(graph, self._estimate)
        renumbered = dict(zip(old_indices, (int(index) for index in result.getNewFactorsIndices()), strict=True))
        self._factors = {renumbered[index]: factor for index, factor in self._factors.items()}
        self._chain_factors = {pair: renumbered[index] for pair, index in self._chain_factors.items()}
        self._estimate = self._isam.calculateEstimate()


def _largest_change(before: gtsam.Values, after: gtsam.Values, keys: list[int]) -> float:
    return max((float(np.linalg.norm(before.atPose3(key).translation() - after.atPose3(key).translation()))
                for key in keys), default=0.0)


def trajectory_arrays(trajectory: list[tuple[int, gtsam.Pose3]]) -> tuple[np.ndarray, np.ndarray]:
    """(N,) stamps in seconds and (N, 4, 4) poses of a keyframe trajectory (for ``trajectory_error.tum_text``)."""
    stamps_s = np.array([stamp_ns / 1e9 for stamp_ns, _ in trajectory], dtype=np.float64)
    poses = np.array([pose.matrix() for _, pose in trajectory], dtype=np.float64).reshape(-1, 4, 4)
    return stamps_s, poses
