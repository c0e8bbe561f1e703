"""An example SLAM backend: odometry keyframes + verified loop closures, optimised incrementally with iSAM2.

This is the pattern a user copies into their own backend (pose_graph_node is its thin ROS shell). ``PoseGraph``
takes odometry and closures and decides what becomes of each closure; its bases put the closures it adds into
the graph. The parts, each in its module:

* backend/graph_types.py: the configuration, ``Closure``, ``ClosureResult``, ``Keyframe``, ``SessionId``;
* backend/sessions.py: one session's odometry buffer and keyframe chain, and the graph it is part of;
* backend/factors.py: the factors as the graph records them, and the noise of odometry and loop factors;
* backend/factor_graph.py: the factors' bookkeeping and iSAM2 (updated, rebuilt by QR when Cholesky fails);
* backend/keyframe_graph.py: a closure's keyframes (odometry interpolated, chains split), factors and joins;
* backend/robot_feeds.py: per robot, the session its odometry goes to and the odometry before one is named;
* here: odometry buffered by stamp, strictly increasing; the sessions named; every closure checked (its
  covariance, its sessions, its stamps, its agreement with the graph) and added, kept waiting for odometry
  or refused (``ClosureResult``); what the graph gives back (trajectories, map -> odom).

A closure adds a ``BetweenFactor`` from the query keyframe to the matched place's with the verifier's relative
pose and covariance, behind a robust kernel (Cauchy) so that one wrong closure is down-weighted instead of
dragging the graph; one further from the graph than odometry drift can explain is refused (the gate).

Sessions. A session is one run of a robot's front end, named (robot, session number) as LoopClosure names
it; each has its own odometry frame, its own odometry buffer and its own chain of keyframes. A robot's
odometry goes to its current session: the newest session named for that robot, by a closure's query or by
``start_session`` with the stamp of the session's first frame (odometry that comes before any session of the
robot is named is kept aside and given to its first session named). Any number of robots feed one graph
(``add_odometry(..., robot=)``; backend/robot_feeds.py keeps each one's current session and early odometry);
without a robot named it is the graph's own ``robot``, the single robot of a single host. The first session
of ``robot`` given a keyframe is anchored (a prior at its first keyframe: map == odom there); every other
session -- a later run, or another robot's -- starts as a graph of its own, its first keyframe held by a
prior at its own odometry pose, and is *unjoined*. Another robot is just another odometry frame: its graph
joins the map at its first closure into it, as a later session does. The first closure between
two graphs joins them: it is taken on the verifier's word (no odometry links two runs, so the odometry gate
cannot apply), the moved graph loses its prior and all its keyframes are moved, rigidly, onto the other's
frame through the closure (query keyframe = place keyframe * closure^-1) before iSAM2 sees them. Closures
between two sessions of one graph are gated like any other (``PoseGraph._tie_distance`` has the drift bound).
Closures and odometry that name no session are session ("", 0): a single-session graph.

Keyframe poses are ``T_map_base``; ``map_to_odom`` is what a TF broadcaster publishes so that
``map -> odom -> base`` puts the robot on the optimised trajectory. No ROS import: gtsam and numpy only.
The graph is saved and reloaded by backend/graph_file.py from the records its factor graph keeps.
"""

from __future__ import annotations

from collections import Counter, deque

import gtsam
import numpy as np

from aefabmap_ros.backend.factors import (
    FactorKind,
    FactorRecord,
    drift_covariance,
    loop_factor_covariance,
)
from aefabmap_ros.backend.graph_types import (
    SINGLE_SESSION,
    Closure,
    ClosureResult,
    Keyframe,
    PoseGraphConfig,
    SessionId,
)
from aefabmap_ros.backend.keyframe_graph import KeyframeGraph
from aefabmap_ros.backend.odometry import OdometryBuffer, odometry_disagreement
from aefabmap_ros.backend.robot_feeds import RobotFeeds
from aefabmap_ros.backend.sessions import Session
from aefabmap_ros.io.message_values import covariance_problem

__all__ = [
    "SINGLE_SESSION",
    "Closure",
    "ClosureResult",
    "FactorKind",
    "FactorRecord",
    "Keyframe",
    "PoseGraph",
    "PoseGraphConfig",
    "Session",
    "SessionId",
    "drift_covariance",
    "loop_factor_covariance",
    "trajectory_arrays",
]

MAX_DECIDED_KEPT = 5000


class PoseGraph(KeyframeGraph):
    """Keyframes at closure endpoints, odometry and robust loop factors, optimised by iSAM2 on every closure;
    one odometry frame and keyframe chain per session, the odometry of any number of robots (module docstring)."""

    def __init__(self, config: PoseGraphConfig, robot: str = "") -> None:
        super().__init__(config)
        self.robot = robot  # the robot add_odometry's samples are of unless named, whose sessions anchor the map
        self.feeds = RobotFeeds(config.max_odometry)  # per robot: its current session, its odometry before one
        self.counts: Counter[str] = Counter()
        # The latest closures decided (added or refused, not waiting): what a viewer draws as loop edges.
        self.decided: deque[tuple[Closure, ClosureResult]] = deque(maxlen=MAX_DECIDED_KEPT)
        self._waiting: list[Closure] = []

    @property
    def current(self) -> SessionId | None:
        """The session ``robot``'s odometry belongs to, once a closure or ``start_session`` named it."""
        return self.feeds.current(self.robot)

    @property
    def odometry(self) -> OdometryBuffer:
        """The odometry ``add_odometry`` fills for ``robot``: its current session's (or the one before any is named)."""
        return self.feeds.buffer(self.robot, self.sessions)

    def follow(self, robot: str) -> None:
        """Take ``robot``'s odometry: a closure naming a newer session of it makes that its current one, and the
        closure waits for its odometry (without this, only once its odometry came or a session was started)."""
        self.feeds.follow(robot)

    def current_session(self, robot: str) -> SessionId | None:
        """The session that robot's odometry goes to (None before one is named)."""
        return self.feeds.current(robot)

    # -- input --------------------------------------------------------------------------------------------

    def add_odometry(self, stamp_ns: int, pose: gtsam.Pose3, robot: str | None = None) -> list[ClosureResult]:
        """Buffer one odometry pose of ``robot``'s current session (default: the graph's ``robot``); closures
        waiting for it are retried (their results returned)."""
        if not self.feeds.buffer(self.robot if robot is None else robot, self.sessions).add(stamp_ns, pose):
            self.counts["odometry_out_of_order"] += 1
            return []
        self.counts["odometry"] += 1
        still = [self._waits(closure) for closure in self._waiting]
        if all(still):
            return []
        ready = [closure for closure, waits in zip(self._waiting, still, strict=True) if not waits]
        self._waiting = [closure for closure, waits in zip(self._waiting, still, strict=True) if waits]
        return [self.add_closure(closure) for closure in ready]

    def add_closure(self, closure: Closure) -> ClosureResult:
        """Add one closure to the graph, keep it waiting for odometry, or refuse it (``ClosureResult``); counted
        and, once decided, kept in ``decided``."""
        result = self._add_closure(closure)
        self.counts[result.value] += 1
        if result is not ClosureResult.WAITING:
            self.decided.append((closure, result))
        return result

    def start_session(self, session_id: SessionId, first_stamp_ns: int | None = None) -> None:
        """Make ``session_id`` the session its robot's odometry goes to from now on (``add_closure`` does it for
        the newest query session of a followed robot; pose_graph_node does it as soon as a posterior names a new
        session). Other robots' sessions are left as they are.

        The robot's first session named takes the odometry that came before (it was this run's). A session
        named later is a new run whose odometry restarted: it starts an empty buffer, or, given the stamp of its
        first frame (``first_stamp_ns``), takes the current buffer's samples from that stamp on, which came
        after the change and are the new session's (backend/robot_feeds.py). Closures still waiting for the
        previous session's odometry are dropped (unknown_stamp): that odometry will not come. Without
        ``first_stamp_ns`` odometry between a session's start and its naming counts as the previous session's."""
        previous = self.feeds.current(session_id[0])
        if previous == session_id:
            return
        rejected = self.feeds.start(session_id, self.sessions, first_stamp_ns)
        if rejected:
            self.counts["odometry_out_of_order"] += rejected
        if previous is None:
            return
        kept = []
        for closure in self._waiting:
            if closure.query_session != session_id and self._waits_on(closure, previous):
                self.counts[ClosureResult.UNKNOWN_STAMP.value] += 1
                self.decided.append((closure, ClosureResult.UNKNOWN_STAMP))
            else:
                kept.append(closure)
        self._waiting = kept

    def _waits_on(self, closure: Closure, session_id: SessionId) -> bool:
        """Whether an endpoint of the closure in that session is newer than the session's odometry."""
        last = self.sessions[session_id].odometry.last_ns
        return any(named == session_id and (last is None or stamp_ns > last)
                   for named, stamp_ns in ((closure.query_session, closure.query_ns),
                                           (closure.place_session, closure.place_ns)))

    def _waits(self, closure: Closure) -> bool:
        """Whether the closure still waits for odometry: an endpoint in a robot's current session (its odometry
        still coming) is newer than that session's odometry."""
        return any(self.feeds.is_current(named) and self._waits_on(closure, named)
                   for named in {closure.query_session, closure.place_session})

    # -- the closure decisions ----------------------------------------------------------------------------

    def _may_anchor(self, root: SessionId) -> bool:
        """Only ``robot``'s sessions hold the map frame: other robots' graphs join it, whichever closes first."""
        return root[0] == self.robot

    def _add_closure(self, closure: Closure) -> ClosureResult:
        covariance = np.asarray(closure.covariance, dtype=np.float64)
        if covariance.shape != (6, 6) or covariance_problem(covariance) is not None:
            return ClosureResult.BAD_COVARIANCE
        named = closure.query_session
        current = self.feeds.current(named[0])
        if (named[0] == self.robot or self.feeds.follows(named[0])) and (current is None or named[1] > current[1]):
            self.start_session(named)
        query, place = self.sessions.get(closure.query_session), self.sessions.get(closure.place_session)
        if query is None or place is None:
            return ClosureResult.UNKNOWN_SESSION
        endpoints = ((query, closure.query_ns), (place, closure.place_ns))
        # No odometry yet waits too: a backend's callbacks may take a closure before the odometry queued ahead of it.
        if self._waits(closure):
            self._waiting.append(closure)
            if len(self._waiting) > self.config.max_waiting:
                self._waiting.pop(0)
                self.counts[ClosureResult.UNKNOWN_STAMP.value] += 1
            return ClosureResult.WAITING
        if any(session.find_keyframe(stamp_ns) is None and session.odometry.pose_at(stamp_ns) is None
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
        loop = FactorRecord(FactorKind.LOOP, -1, -1, closure.query_to_place, loop_covariance, scale)
        return ClosureResult.ADDED if self._add_loop(endpoints, loop) else ClosureResult.SOLVER_FAILED

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

    def _predicted(self, session: Session, stamp_ns: int) -> tuple[gtsam.Pose3, float]:
        """Current estimate of the pose at a stamp of a session (a keyframe's, else odometry moved with the
        session's nearest keyframe) and the distance travelled there."""
        existing = session.find_keyframe(stamp_ns)
        if existing is not None:
            return self._estimate.atPose3(existing.key), existing.path_m
        found = session.odometry.pose_at(stamp_ns)
        assert found is not None  # resolvable, checked by the caller
        odometry, path_m = found
        if not session.keyframes:
            return odometry, path_m
        index = session.index_of(stamp_ns)
        anchor = session.keyframes[max(index - 1, 0)]
        return self._estimate.atPose3(anchor.key).compose(anchor.odometry.between(odometry)), path_m

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
        keyframe = found.find_keyframe(stamp_ns)
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


def trajectory_arrays(trajectory: list[tuple[int, gtsam.Pose3]]) -> tuple[np.ndarray, np.ndarray]:
    """(N,) stamps in seconds and (N, 4, 4) poses of a keyframe trajectory (for ``trajectory_error.tum_text``)."""
    stamps_s = np.array([stamp_ns / 1e9 for stamp_ns, _ in trajectory], dtype=np.float64)
    poses = np.array([pose.matrix() for _, pose in trajectory], dtype=np.float64).reshape(-1, 4, 4)
    return stamps_s, poses
