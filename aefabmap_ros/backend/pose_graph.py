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

Sessions. A session is one run of a robot's front end, named (robot, session number) as LoopClosure names
it; each has its own odometry frame, its own odometry buffer and its own chain of keyframes. Odometry goes to
the current session: the newest query session named for this graph's ``robot`` (odometry that comes before
any closure named it is kept aside and given to the first session named). The first session given a keyframe
is anchored (a prior at its first keyframe: map == odom there); every later session starts as a graph of its
own, its first keyframe held by a prior at its own odometry pose, and is *unjoined*. The first closure between
two graphs joins them: it is taken on the verifier's word (no odometry links two runs, so the odometry gate
cannot apply), the moved graph loses its prior and all its keyframes are moved, rigidly, onto the other's
frame through the closure (query keyframe = place keyframe * closure^-1) before iSAM2 sees them. Closures
between two sessions of one graph are gated like any other (``PoseGraph._tie_distance`` has the drift bound).
Closures and odometry that name no session are session ("", 0): a single-session graph, as before sessions.

iSAM2 factors by Cholesky, on the normal equations: fast, but it squares the system's condition
number, and a keyframe far from the anchor (30 km along a straight road, with the loop factors' 5 cm)
makes the system look singular to it (gtsam's "indeterminate linear system"). A closure whose update
fails so is added again by QR on a graph rebuilt from the factors kept before it (``factorization``
is then "QR" for good: slower per closure, and exact where Cholesky gave up); a closure QR
cannot take either is dropped (``solver_failed``), the graph as it was. Either way no gtsam error
leaves the graph half updated.

Keyframe poses are ``T_map_base``; ``map_to_odom`` is what a TF broadcaster publishes so that
``map -> odom -> base`` puts the robot on the optimised trajectory. No ROS import: gtsam and numpy only.
The graph is saved and reloaded by backend/graph_file.py from the records kept here (``FactorRecord``).
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
# Standard deviation (m and rad) of the prior that holds a session's first keyframe.
PRIOR_SIGMA = 1e-6

SessionId = tuple[str, int]  # (robot, session number); robot '' = the map's only robot
SINGLE_SESSION: SessionId = ("", 0)


class ClosureResult(Enum):
    ADDED = "added"
    WAITING = "waiting_for_odometry"  # its query is newer than the last odometry: retried when odometry comes
    UNKNOWN_STAMP = "unknown_stamp"  # an endpoint before the odometry buffer (or a dropped waiting closure)
    UNKNOWN_SESSION = "unknown_session"  # an endpoint in a session the graph never had (no odometry, not reloaded)
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
        "description": "Odometry samples kept for interpolation, per session (the odometry gate forgets the "
                       "oldest first; the pose graph halves a full session's sample rate, keeping its whole run)."})
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
    over (x, y, z, rot x, rot y, rot z), as in LoopClosure.pose / pose_covariance; each endpoint in its
    (robot, session)."""

    query_ns: int
    place_ns: int
    query_to_place: gtsam.Pose3
    covariance: np.ndarray
    query_session: SessionId = SINGLE_SESSION
    place_session: SessionId = SINGLE_SESSION


@dataclass
class Keyframe:
    stamp_ns: int
    key: int
    odometry: gtsam.Pose3  # T_odom_base at the keyframe's stamp, in its session's odometry frame
    path_m: float  # odometry distance travelled at that stamp: odometry error grows with it
    session: SessionId = SINGLE_SESSION


@dataclass
class Session:
    """One run of a robot's front end: its odometry (one odometry frame) and its keyframes, by stamp.

    ``root`` names the session whose prior holds the graph this one is part of: itself until a closure joins
    it to another graph. Sessions whose root is the graph's ``anchor`` are joined (in the map frame)."""

    id: SessionId
    odometry: OdometryBuffer
    root: SessionId
    keyframes: list[Keyframe] = field(default_factory=list)


class FactorKind(Enum):
    PRIOR = 0
    ODOMETRY = 1
    LOOP = 2


@dataclass(frozen=True)
class FactorRecord:
    """One factor as the graph keeps (and its file saves) it; gtsam's factor is made from it when needed.

    ``pose`` is the prior's pose, or a between factor's measured T_first_second; ``covariance`` is in gtsam's
    tangent order (rot, trans); a loop factor's Cauchy kernel has ``cauchy_scale`` (NaN for the others)."""

    kind: FactorKind
    first: int
    second: int  # a prior's: its own key again
    pose: gtsam.Pose3
    covariance: np.ndarray
    cauchy_scale: float = float("nan")

    def factor(self) -> gtsam.NonlinearFactor:
        covariance = np.asarray(self.covariance, dtype=np.float64)
        noise: gtsam.noiseModel.Base
        if self.kind is FactorKind.LOOP:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(self.cauchy_scale),
                                                   gtsam.noiseModel.Gaussian.Covariance(covariance))
        elif np.count_nonzero(covariance - np.diag(np.diag(covariance))) == 0:
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.diag(covariance)))
        else:
            noise = gtsam.noiseModel.Gaussian.Covariance(covariance)
        if self.kind is FactorKind.PRIOR:
            return gtsam.PriorFactorPose3(self.first, self.pose, noise)
        return gtsam.BetweenFactorPose3(self.first, self.second, self.pose, noise)


@dataclass(frozen=True)
class _Kept:
    """What a failed update must not leave changed (the estimate is replaced, never changed in place)."""

    sessions: dict[SessionId, tuple[list[Keyframe], SessionId]]
    chain_factors: dict[tuple[int, int], int]
    priors: dict[SessionId, int]
    factors: dict[int, FactorRecord]
    next_key: int
    estimate: gtsam.Values
    anchor: SessionId | None


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
    """Keyframes at closure endpoints, odometry and robust loop factors, optimised by iSAM2 on every closure;
    one odometry frame and keyframe chain per session (module docstring)."""

    def __init__(self, config: PoseGraphConfig, robot: str = "") -> None:
        self.config = config
        self.robot = robot  # the robot whose odometry add_odometry receives
        self.sessions: dict[SessionId, Session] = {}
        self.current: SessionId | None = None  # the session add_odometry's samples belong to, once a closure named it
        self.anchor: SessionId | None = None  # root of the joined graph: the first session given a keyframe
        self._unnamed_odometry = self._new_buffer()  # odometry before any closure named its session
        self.counts: Counter[str] = Counter()
        # The latest closures decided (added or refused, not waiting): what a viewer draws as loop edges.
        self.decided: deque[tuple[Closure, ClosureResult]] = deque(maxlen=MAX_DECIDED_KEPT)
        self._waiting: list[Closure] = []
        self._chain_factors: dict[tuple[int, int], int] = {}  # (key before, key after) -> iSAM2 factor index
        self._priors: dict[SessionId, int] = {}  # root session -> iSAM2 index of the prior holding its graph
        self.factors: dict[int, FactorRecord] = {}  # iSAM2 factor index -> factor, the graph's own
        self._key_sessions: dict[int, SessionId] = {}
        self._next_key = 0
        self.factorization = "CHOLESKY"  # "QR" once Cholesky failed on this graph (module docstring)
        self.solver_error = ""  # gtsam's message of the last update that failed
        self._isam = gtsam.ISAM2(_isam_params(self.factorization))
        self._estimate = gtsam.Values()

    def _new_buffer(self) -> OdometryBuffer:
        # Decimated when full, not forgotten from the start: a later session may close a loop to any stamp.
        return OdometryBuffer(self.config.max_odometry, decimate=True)

    @property
    def odometry(self) -> OdometryBuffer:
        """The odometry ``add_odometry`` fills: the current session's (or the one no closure named yet)."""
        return self._unnamed_odometry if self.current is None else self.sessions[self.current].odometry

    @property
    def keyframes(self) -> list[Keyframe]:
        """Every session's keyframes, session after session, each session's by stamp."""
        return [keyframe for session in self.sessions.values() for keyframe in session.keyframes]

    # -- input --------------------------------------------------------------------------------------------

    def add_odometry(self, stamp_ns: int, pose: gtsam.Pose3) -> list[ClosureResult]:
        """Buffer one odometry pose of the current session; closures waiting for it are retried (their results
        returned)."""
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

    def start_session(self, session_id: SessionId) -> None:
        """Make ``session_id`` the session odometry goes to from now on (``add_closure`` does it for the newest
        query session of ``robot``; a backend told of a session's start can call it before the first closure).

        The first session named takes the odometry that came before (it was this run's); a session named
        later is a new run whose odometry restarted, so it starts an empty buffer, and closures still waiting
        for the previous session's odometry are dropped (unknown_stamp): that odometry will not come. Odometry
        between a session's start and its first closure, when the backend ran on through the change, was
        taken as the previous session's: the new session's keyframes begin at its first odometry after."""
        if self.current == session_id:
            return
        if self.current is None:
            buffer, self._unnamed_odometry = self._unnamed_odometry, self._new_buffer()
            existing = self.sessions.get(session_id)
            if existing is None:
                self.sessions[session_id] = Session(session_id, buffer, root=session_id)
            else:  # a reloaded session continues (only the backend restarted): same odometry frame
                for stamp_ns, pose, _ in zip(*buffer.samples(), strict=True):
                    if not existing.odometry.add(stamp_ns, pose):
                        self.counts["odometry_out_of_order"] += 1
        else:
            for closure in self._waiting:
                self.counts[ClosureResult.UNKNOWN_STAMP.value] += 1
                self.decided.append((closure, ClosureResult.UNKNOWN_STAMP))
            self._waiting = []
            if session_id not in self.sessions:
                self.sessions[session_id] = Session(session_id, self._new_buffer(), root=session_id)
        self.current = session_id

    def _add_closure(self, closure: Closure) -> ClosureResult:
        covariance = np.asarray(closure.covariance, dtype=np.float64)
        if covariance.shape != (6, 6) or covariance_problem(covariance) is not None:
            return ClosureResult.BAD_COVARIANCE
        named = closure.query_session
        if named[0] == self.robot and (self.current is None or named[1] > self.current[1]):
            self.start_session(named)
        query, place = self.sessions.get(closure.query_session), self.sessions.get(closure.place_session)
        if query is None or place is None:
            return ClosureResult.UNKNOWN_SESSION
        endpoints = ((query, closure.query_ns), (place, closure.place_ns))
        # No odometry yet waits too: a backend's callbacks may take a closure before the odometry queued ahead of it.
        current_stamps = [stamp_ns for session, stamp_ns in endpoints if session.id == self.current]
        last = self.odometry.last_ns
        if current_stamps and (last is None or max(current_stamps) > last):
            self._waiting.append(closure)
            if len(self._waiting) > self.config.max_waiting:
                self._waiting.pop(0)
                self.counts[ClosureResult.UNKNOWN_STAMP.value] += 1
            return ClosureResult.WAITING
        if any(self._find_keyframe(session, stamp_ns) is None and session.odometry.pose_at(stamp_ns) is None
               for session, stamp_ns in endpoints):
            return ClosureResult.UNKNOWN_STAMP  # checked first: a dropped closure leaves the graph as it was
        loop_covariance = loop_factor_covariance(self.config, covariance)
        if query.root != place.root:
            distance_m = 0.0  # joins two graphs: no odometry relates them, the verifier's word is all there is
        else:
            (query_pose, query_path), (place_pose, place_path) = (self._predicted(*endpoint) for endpoint in endpoints)
            # What odometry drift alone can explain between the two: in one session the whole path travelled
            # between them (an upper bound once other closures tie them closer); across sessions _tie_distance's.
            distance_m = (abs(query_path - place_path) if query is place
                          else self._tie_distance(query, query_path) + self._tie_distance(place, place_path))
            if odometry_disagreement(closure.query_to_place, loop_covariance, query_pose.between(place_pose),
                                     drift_covariance(self.config, distance_m)) > self.config.gate_chi2:
                return ClosureResult.INCONSISTENT
        drift = drift_covariance(self.config, distance_m)
        # The Cauchy kernel's scale: the loop-whitened disagreement drift can explain. A true closure after
        # long drift keeps most of its weight; one the graph later contradicts (other closures) loses it.
        scale = self.config.cauchy_scale * float(np.sqrt(np.trace(drift[3:, 3:] + loop_covariance[3:, 3:])
                                                         / np.trace(loop_covariance[3:, 3:])))
        kept = self._keep()
        while True:
            try:
                self._insert_closure(endpoints, FactorRecord(FactorKind.LOOP, -1, -1, closure.query_to_place,
                                                             loop_covariance, scale))
                return ClosureResult.ADDED
            except RuntimeError as exc:  # gtsam's IndeterminantLinearSystemException and kin
                self.solver_error = " ".join(str(exc).split())
                retry = self.factorization != "QR"
                # The failed update left its factors inside iSAM2: start again from the graph kept before it.
                self._restore(kept)
                self._rebuild("QR")
                if not retry:
                    return ClosureResult.SOLVER_FAILED

    def _tie_distance(self, session: Session, path_m: float) -> float:
        """Distance travelled from ``path_m`` to the session's nearest keyframe tied to another session by a loop
        factor: what bounds the drift of one endpoint of a closure between two sessions of one graph.

        The two sessions' relative placement is known only through such ties, to the closures' accuracy (the
        loop covariance covers it); away from them each session's estimate is its odometry's, off by the drift
        of the path travelled since the nearest tie. The bound is the sum of that distance for both endpoints.
        The nearest tie, not the join's: every later tie holds the sessions as tightly as the first one did,
        and a bound from the join alone would grow without limit over a long session and pass anything.
        It ignores the ties' own error and, when the two sessions are tied only through a third, the path
        through that one: a tighter gate than the exact covariance, which the Cauchy kernel and the gate's
        99.9 % threshold leave room for."""
        tied = self._tied_keys()
        paths = ([keyframe.path_m for keyframe in session.keyframes if keyframe.key in tied]
                 or [keyframe.path_m for keyframe in session.keyframes])
        return min((abs(path_m - other) for other in paths), default=0.0)

    def _tied_keys(self) -> set[int]:
        tied: set[int] = set()
        for record in self.factors.values():
            if (record.kind is FactorKind.LOOP
                    and self._key_sessions[record.first] != self._key_sessions[record.second]):
                tied.update((record.first, record.second))
        return tied

    def _insert_closure(self, endpoints: tuple[tuple[Session, int], tuple[Session, int]], loop: FactorRecord) -> None:
        """Keyframes at both endpoints (made where missing), the loop factor between them and, when it joins two
        graphs, the moved graph; one iSAM2 update. A gtsam error leaves keyframes and iSAM2 half updated: the
        caller restores and rebuilds them."""
        records: list[FactorRecord] = []
        values = gtsam.Values()
        removed: list[int] = []
        (query, _), (place, _) = endpoints
        moving = None  # the root of the graph this closure moves onto the other's, when it joins two
        if query.root != place.root:
            moving = place.root if query.root == self.anchor else query.root
        if self.anchor is None:
            self.anchor = place.root if moving == query.root else query.root
        for session in (query,) if query is place else (query, place):
            if not session.keyframes and session.odometry.first_ns is not None:
                # A session's first keyframe, at its first odometry pose; a prior there holds its graph (map ==
                # odom for the first session). One that joins another graph now needs none: the closure places it.
                self._new_keyframe(session, session.odometry.first_ns, records, values, removed,
                                   prior=session.id != moving)
        keys = []
        for session, stamp_ns in endpoints:
            keyframe = (self._find_keyframe(session, stamp_ns)
                        or self._new_keyframe(session, stamp_ns, records, values, removed, prior=False))
            assert keyframe is not None  # resolvable, checked above
            keys.append(keyframe.key)
        records.append(FactorRecord(FactorKind.LOOP, keys[0], keys[1], loop.pose, loop.covariance, loop.cauchy_scale))
        start = None
        if moving is not None:
            start = self._join(moving, query, keys, loop.pose, values, removed)
        self._update(records, values, removed, start)

    def _join(self, moving: SessionId, query: Session, keys: list[int], query_to_place: gtsam.Pose3,
              values: gtsam.Values, removed: list[int]) -> gtsam.Values | None:
        """Move the graph rooted at ``moving`` onto the other's frame through the joining closure (keys: its query
        and place keyframes), rigidly, and drop its prior; the moved poses of new keyframes go into ``values``.

        Returns None when that graph had no keyframe in iSAM2 yet (an ordinary update then starts at the answer),
        else the whole estimate, moved: iSAM2 keeps a variable's linearisation point once it has it, so only a
        new iSAM2 starts near the answer, and ``_update`` builds one (a join happens once per session)."""
        query_pose, place_pose = (self._pose_of(key, values) for key in keys)
        if query.root == moving:  # the query keyframe, seen from the place: place * closure^-1
            offset = place_pose.compose(query_to_place.inverse()).compose(query_pose.inverse())
            stay = self._session_of(keys[1]).root
        else:
            offset = query_pose.compose(query_to_place).compose(place_pose.inverse())
            stay = query.root
        members = [session for session in self.sessions.values() if session.root == moving]
        moved = {keyframe.key for session in members for keyframe in session.keyframes}
        for key in moved:
            if values.exists(key):
                values.update(key, offset.compose(values.atPose3(key)))
        for session in members:
            session.root = stay
        if moving in self._priors:
            removed.append(self._priors.pop(moving))
        if not any(self._estimate.exists(key) for key in moved):
            return None
        estimate = gtsam.Values()
        keys = [int(key) for key in self._estimate.keys()]  # noqa: SIM118 - gtsam.Values is no dict
        for key in keys:
            pose = self._estimate.atPose3(key)
            estimate.insert(key, offset.compose(pose) if key in moved else pose)
        return estimate

    # -- output -------------------------------------------------------------------------------------------

    def is_joined(self, robot: str = "", session: int = 0) -> bool:
        """Whether that session's keyframes are in the map frame (the anchored graph): False for a session of a
        graph of its own, or one without keyframes."""
        found = self.sessions.get((robot, session))
        return found is not None and bool(found.keyframes) and found.root == self.anchor

    def trajectory(self) -> list[tuple[int, gtsam.Pose3]]:
        """Optimised keyframe poses T_map_base of every joined session, by stamp."""
        joined = [keyframe for session in self.sessions.values() if session.root == self.anchor
                  for keyframe in session.keyframes]
        return [(keyframe.stamp_ns, self._estimate.atPose3(keyframe.key))
                for keyframe in sorted(joined, key=lambda keyframe: keyframe.stamp_ns)]

    def session_trajectory(self, robot: str = "", session: int = 0) -> list[tuple[int, gtsam.Pose3]]:
        """One session's optimised keyframe poses by stamp, in its graph's frame (the map for a joined one)."""
        found = self.sessions.get((robot, session))
        keyframes = found.keyframes if found is not None else []
        return [(keyframe.stamp_ns, self._estimate.atPose3(keyframe.key)) for keyframe in keyframes]

    def map_to_odom(self, robot: str | None = None, session: int | None = None) -> gtsam.Pose3:
        """T_map_odom of a session (default: the current one, else the anchor) from its newest keyframe; identity
        before its first closure. For an unjoined session the "map" is its own graph's frame."""
        if robot is None and session is None:
            session_id = self.current if self.current is not None else self.anchor
        else:
            session_id = (robot or "", session or 0)
        found = self.sessions.get(session_id) if session_id is not None else None
        if found is None or not found.keyframes:
            return gtsam.Pose3()
        newest = found.keyframes[-1]
        return self._estimate.atPose3(newest.key).compose(newest.odometry.inverse())

    def keyframe_in_map(self, session_id: SessionId, stamp_ns: int) -> gtsam.Pose3 | None:
        """The optimised pose of a joined session's keyframe at that stamp; None if there is none."""
        found = self.sessions.get(session_id)
        if found is None or found.root != self.anchor:
            return None
        keyframe = self._find_keyframe(found, stamp_ns)
        return None if keyframe is None else self._estimate.atPose3(keyframe.key)

    def odometry_in_map(self, session_id: SessionId, stamp_ns: int) -> gtsam.Pose3 | None:
        """The odometry pose at that stamp moved into the map frame by its session's map -> odom; None for a stamp
        outside its odometry or a session outside the map frame (a session with no keyframe yet is in it while
        the graph has no anchor: map == odom then)."""
        found = self.sessions.get(session_id)
        if found is None or not (found.root == self.anchor or (self.anchor is None and not found.keyframes)):
            return None
        odometry = found.odometry.pose_at(stamp_ns)
        return None if odometry is None else self.map_to_odom(*session_id).compose(odometry[0])

    # -- graph building -----------------------------------------------------------------------------------

    def _session_of(self, key: int) -> Session:
        return self.sessions[self._key_sessions[key]]

    def _find_keyframe(self, session: Session, stamp_ns: int) -> Keyframe | None:
        stamps = [keyframe.stamp_ns for keyframe in session.keyframes]
        index = bisect.bisect_left(stamps, stamp_ns)
        for candidate in (index - 1, index):
            if 0 <= candidate < len(stamps) and abs(stamps[candidate] - stamp_ns) <= SAME_KEYFRAME_NS:
                return session.keyframes[candidate]
        return None

    def _new_keyframe(self, session: Session, stamp_ns: int, records: list[FactorRecord], values: gtsam.Values,
                      removed: list[int], prior: bool) -> Keyframe | None:
        found = session.odometry.pose_at(stamp_ns)
        if found is None:
            return None
        odometry, path_m = found
        keyframe = Keyframe(stamp_ns, self._next_key, odometry, path_m, session.id)
        self._next_key += 1
        self._key_sessions[keyframe.key] = session.id
        index = bisect.bisect_left([existing.stamp_ns for existing in session.keyframes], stamp_ns)
        before = session.keyframes[index - 1] if index > 0 else None
        after = session.keyframes[index] if index < len(session.keyframes) else None
        if before is None and after is None:
            values.insert(keyframe.key, odometry)  # the session's first keyframe: its odom frame is its graph's
            if prior:
                records.append(FactorRecord(FactorKind.PRIOR, keyframe.key, keyframe.key, odometry,
                                            np.eye(6) * PRIOR_SIGMA ** 2))
        else:
            anchor = before if before is not None else after
            assert anchor is not None
            anchor_pose = self._pose_of(anchor.key, values)
            values.insert(keyframe.key, anchor_pose.compose(anchor.odometry.between(odometry)))
        if before is not None and after is not None and (before.key, after.key) in self._chain_factors:
            removed.append(self._chain_factors.pop((before.key, after.key)))  # split the factor it interrupts
        for first, second in ((before, keyframe), (keyframe, after)):
            if first is not None and second is not None:
                records.append(self._odometry_record(first, second))
        session.keyframes.insert(index, keyframe)
        return keyframe

    def _pose_of(self, key: int, pending: gtsam.Values) -> gtsam.Pose3:
        return pending.atPose3(key) if pending.exists(key) else self._estimate.atPose3(key)

    def _odometry_record(self, first: Keyframe, second: Keyframe) -> FactorRecord:
        relative = first.odometry.between(second.odometry)
        # Travelled, not the straight line: a loop ends near its start.
        covariance = drift_covariance(self.config, abs(second.path_m - first.path_m))
        return FactorRecord(FactorKind.ODOMETRY, first.key, second.key, relative, covariance)

    def _predicted(self, session: Session, stamp_ns: int) -> tuple[gtsam.Pose3, float]:
        """Current estimate of the pose at a stamp of a session (a keyframe's, else odometry moved with the
        session's nearest keyframe) and the distance travelled there."""
        existing = self._find_keyframe(session, stamp_ns)
        if existing is not None:
            return self._estimate.atPose3(existing.key), existing.path_m
        found = session.odometry.pose_at(stamp_ns)
        assert found is not None  # resolvable, checked by the caller
        odometry, path_m = found
        if not session.keyframes:
            return odometry, path_m
        index = bisect.bisect_left([keyframe.stamp_ns for keyframe in session.keyframes], stamp_ns)
        anchor = session.keyframes[max(index - 1, 0)]
        return self._estimate.atPose3(anchor.key).compose(anchor.odometry.between(odometry)), path_m

    def _update(self, records: list[FactorRecord], values: gtsam.Values, removed: list[int],
                start: gtsam.Values | None = None) -> None:
        """One iSAM2 update and its extra iterations; the factors are recorded once all of it succeeded.
        With ``start`` (a join's moved estimate), a new iSAM2 takes every factor kept and the new ones there."""
        graph = gtsam.NonlinearFactorGraph()
        for record in records:
            graph.add(record.factor())
        if start is None:
            result = self._isam.update(graph, values, removed)
            new_indices = [int(index) for index in result.getNewFactorsIndices()]
        else:
            dropped = set(removed)
            removed = []
            new_indices = self._restart([index for index in sorted(self.factors) if index not in dropped],
                                        self.factorization, start, graph, values)
        # The Cauchy kernel is re-weighted at each relinearisation (IRLS): a true closure far from the
        # drifted estimate starts with a small weight and gains it as the graph moves towards it; a wrong one
        # stays far and keeps a small weight. A few more iterations, until the estimate settles.
        keys = [keyframe.key for keyframe in self.keyframes]
        for _ in range(MAX_EXTRA_ITERATIONS):
            before = self._isam.calculateEstimate()
            self._isam.update()
            if _largest_change(before, self._isam.calculateEstimate(), keys) < SETTLED_M:
                break
        self._estimate = self._isam.calculateEstimate()
        # iSAM2 numbers the new factors in the order they were added: remember the odometry factors' numbers
        # so that a keyframe inserted later between two keyframes can remove the factor it splits, and the
        # priors' so that a join can remove its graph's.
        for record, index in zip(records, new_indices, strict=True):
            self._record(index, record)
        for index in removed:
            self.factors.pop(index, None)

    def _record(self, index: int, record: FactorRecord) -> None:
        self.factors[index] = record
        if record.kind is FactorKind.ODOMETRY:
            self._chain_factors[(record.first, record.second)] = index
        elif record.kind is FactorKind.PRIOR:
            self._priors[self._session_of(record.first).root] = index

    def _restart(self, kept: list[int], factorization: str, estimate: gtsam.Values,
                 graph: gtsam.NonlinearFactorGraph | None = None, values: gtsam.Values | None = None) -> list[int]:
        """A new iSAM2 (``factorization``) holding the recorded factors numbered ``kept`` (renumbered; the others
        forgotten) and ``graph``'s new ones, at ``estimate`` and ``values``; the new factors' numbers."""
        self.factorization = factorization
        self._isam = gtsam.ISAM2(_isam_params(factorization))
        full = gtsam.NonlinearFactorGraph()
        for index in kept:
            full.add(self.factors[index].factor())
        added = 0 if graph is None else graph.size()
        for position in range(added):
            assert graph is not None
            full.add(graph.at(position))
        initial = gtsam.Values(estimate)
        if values is not None:
            initial.insert(values)
        if full.size() == 0:
            self._estimate = gtsam.Values()
            self.factors, self._chain_factors, self._priors = {}, {}, {}
            return []
        result = self._isam.update(full, initial)
        indices = [int(index) for index in result.getNewFactorsIndices()]
        renumbered = dict(zip(kept, indices[:len(kept)], strict=True))
        self.factors = {renumbered[index]: self.factors[index] for index in kept}
        self._chain_factors = {pair: renumbered[index] for pair, index in self._chain_factors.items()
                               if index in renumbered}
        self._priors = {root: renumbered[index] for root, index in self._priors.items() if index in renumbered}
        self._estimate = self._isam.calculateEstimate()
        return indices[len(kept):]

    def _rebuild(self, factorization: str) -> None:
        """A new iSAM2 (``factorization``) holding the recorded factors at the last estimate."""
        self._restart(sorted(self.factors), factorization, self._estimate)

    def _keep(self) -> _Kept:
        sessions = {session_id: (list(session.keyframes), session.root)
                    for session_id, session in self.sessions.items()}
        return _Kept(sessions, dict(self._chain_factors), dict(self._priors), dict(self.factors), self._next_key,
                     self._estimate, self.anchor)

    def _restore(self, kept: _Kept) -> None:
        for session_id, (keyframes, root) in kept.sessions.items():
            self.sessions[session_id].keyframes, self.sessions[session_id].root = list(keyframes), root
        self._chain_factors, self._priors = dict(kept.chain_factors), dict(kept.priors)
        self.factors, self._next_key = dict(kept.factors), kept.next_key
        self._estimate, self.anchor = kept.estimate, kept.anchor

    # -- a saved graph (backend/graph_file.py) ------------------------------------------------------------

    def estimate_of(self, key: int) -> gtsam.Pose3:
        """The optimised pose of a keyframe, by key."""
        return self._estimate.atPose3(key)

    def load(self, sessions: list[Session], anchor: SessionId | None, records: list[FactorRecord],
             estimate: gtsam.Values, factorization: str) -> None:
        """Take a saved graph into this empty one and rebuild iSAM2 from its factors at the saved estimate.

        The current session stays unnamed: the next run's first closure names it (a reloaded session named
        again continues its odometry). RuntimeError (gtsam's) when the factors cannot be solved."""
        if self.sessions or self.factors:
            raise ValueError("a saved graph is loaded into an empty one only")
        self.sessions = {session.id: session for session in sessions}
        self.anchor = anchor
        self._key_sessions = {keyframe.key: session.id for session in sessions for keyframe in session.keyframes}
        self._next_key = max(self._key_sessions, default=-1) + 1
        self.factors, self._chain_factors, self._priors = {}, {}, {}
        for index, record in enumerate(records):
            self._record(index, record)
        self._estimate = estimate
        self._rebuild(factorization)


def _largest_change(before: gtsam.Values, after: gtsam.Values, keys: list[int]) -> float:
    return max((float(np.linalg.norm(before.atPose3(key).translation() - after.atPose3(key).translation()))
                for key in keys), default=0.0)


def trajectory_arrays(trajectory: list[tuple[int, gtsam.Pose3]]) -> tuple[np.ndarray, np.ndarray]:
    """(N,) stamps in seconds and (N, 4, 4) poses of a keyframe trajectory (for ``trajectory_error.tum_text``)."""
    stamps_s = np.array([stamp_ns / 1e9 for stamp_ns, _ in trajectory], dtype=np.float64)
    poses = np.array([pose.matrix() for _, pose in trajectory], dtype=np.float64).reshape(-1, 4, 4)
    return stamps_s, poses
