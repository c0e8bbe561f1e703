"""Verified closures at the odometry gate (verification/gate.py): published, refused, or held until
odometry reaches their stamps.

Odometry comes on its own topic and is often taken after the images it belongs to: under load the
verifier is handed a burst of frames before the odometry of the same instants. A closure whose stamps
are past the newest odometry waits, and is decided when odometry arrives. It is dropped as
``odometry_never_came`` only when odometry has stayed behind it for ``wait_s`` of stamp time -- the
newest frame the verifier has seen is that much newer than the closure's query -- or when more than
``max_waiting`` closures wait (a bound on memory while odometry has stopped). How far odometry trails
the newest frame is measured on every odometry message (``lateness_summary``), so the wait can be set
from what a robot's own load does to it.

Several robots (docs/fleet.md): each robot has its own gate on its own odometry (``robot_gates``); a closure
inside one robot's session is judged by that robot's gate, and waits for that robot's odometry.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from enum import Enum

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from aefabmap_ros.io.message_values import covariance_problem
from aefabmap_ros.verification.closures import Closure, Outcomes
from aefabmap_ros.verification.gate import ClosureGate, GateResult
from aefabmap_ros.verification.loop_tracking import LoopTracks

LATENESS_SAMPLES = 10_000  # odometry messages whose lateness the summary describes (the newest)


class GateDecision(Enum):
    PUBLISH = "publish"
    WAIT = "wait"  # for odometry to reach its stamps
    REFUSE = "refuse"


class OdometryWait:
    """The odometry gate on every verified closure, with the closures waiting for odometry."""

    def __init__(self, gate: ClosureGate | None, wait_s: float, max_waiting: int, tracks: LoopTracks,
                 publish: Callable[[Closure], None], outcomes: Outcomes,
                 robot_gates: Mapping[str, ClosureGate] | None = None) -> None:
        self.gate = gate  # one robot's: every closure is judged by it
        self.robot_gates = dict(robot_gates or {})  # several robots: each robot's closures by its own
        self.wait_ns = round(wait_s * 1e9)
        self.max_waiting = max_waiting
        self.tracks = tracks
        self.publish = publish
        self.outcomes = outcomes
        self.waiting: list[Closure] = []  # in the order they were verified
        self.newest_frame_ns: int | None = None
        self.lateness_s: deque[float] = deque(maxlen=LATENESS_SAMPLES)  # odometry behind the newest frame
        self.longest_wait_s = 0.0  # stamp time a closure waited before odometry reached it

    def submit(self, closure: Closure) -> None:
        """Publish a verified closure once the gate agrees; hold it while odometry is behind its stamps."""
        decision = self._decide(closure)
        if decision is GateDecision.REFUSE:
            return
        # Tracking goes on from a waiting closure as it would without the gate: every closure tracked from it
        # is verified and judged by the gate itself.
        detection = closure.detection
        self.tracks.of(detection.query_robot).accept(detection.query_ns, detection.matched_ns, detection.matched_robot)
        if decision is GateDecision.PUBLISH:
            self.publish(closure)
            return
        self.waiting.append(closure)
        if len(self.waiting) > self.max_waiting:
            oldest = self.waiting.pop(0)
            self.outcomes.drop("odometry_never_came", f"loop closure query {oldest.detection.query_id}: no "
                                                      f"odometry up to its stamp while {self.max_waiting} newer "
                                                      "ones waited")

    def frame_seen(self, stamp_ns: int) -> None:
        """A frame stamped ``stamp_ns`` came: closures odometry has trailed for ``wait_s`` since are dropped."""
        if self.newest_frame_ns is None or stamp_ns > self.newest_frame_ns:
            self.newest_frame_ns = stamp_ns
        newest_ns = self.newest_frame_ns
        expired, self.waiting = _split(self.waiting, lambda closure: newest_ns - closure.detection.query_ns
                                       > self.wait_ns)
        for closure in expired:
            self.outcomes.drop("odometry_never_came", f"loop closure query {closure.detection.query_id}: no "
                                                      f"odometry up to its stamp for {self.wait_ns / 1e9:g} s")

    def gate_of(self, robot: str) -> ClosureGate | None:
        """The gate that judges closures of ``robot``'s queries: its own, or the one robot's."""
        return self.robot_gates.get(robot, self.gate)

    def add_odometry(self, stamp_ns: int, pose: gtsam.Pose3, robot: str | None = None) -> bool:
        """Odometry ``T_odom_base`` at ``stamp_ns`` (of ``robot``, several robots); False (ignored) unless after the
        previous one. The closures it reaches are decided now; the others keep waiting, in order."""
        gate = self.gate if robot is None else self.robot_gates.get(robot)
        if gate is None or not gate.add_odometry(stamp_ns, pose):
            return False
        if self.newest_frame_ns is not None:
            self.lateness_s.append(max(self.newest_frame_ns - stamp_ns, 0) / 1e9)
        reached, self.waiting = _split(self.waiting, lambda closure: self.gate_of(closure.detection.query_robot)
                                       is gate and gate.reaches(closure.detection.query_ns,
                                                                closure.detection.matched_ns))
        for closure in reached:
            if self.newest_frame_ns is not None:
                waited_s = (self.newest_frame_ns - closure.detection.query_ns) / 1e9
                self.longest_wait_s = max(self.longest_wait_s, waited_s)
            self.submit(closure)
        return True

    def lateness_summary(self) -> str:
        """How far odometry trailed the newest frame (stamp time), and the longest a closure waited."""
        if not self.lateness_s:
            return "no odometry"
        p50, p99 = np.percentile(self.lateness_s, [50, 99])
        return (f"odometry behind the newest frame: median {p50:.3f} s, p99 {p99:.3f} s, max "
                f"{max(self.lateness_s):.3f} s; longest wait for odometry {self.longest_wait_s:.3f} s")

    def _decide(self, closure: Closure) -> GateDecision:
        """The gate on one verified closure (PUBLISH when it is off or inactive); refusals are counted."""
        detection, pose = closure.detection, closure.pose.pose
        gate = self.gate_of(detection.query_robot)
        if gate is None or not gate.active:
            return GateDecision.PUBLISH
        if (detection.query_session, detection.query_robot) != (detection.matched_session, detection.matched_robot):
            # The place is another session's or robot's: this odometry (the query session's own frame) says
            # nothing of where it is. The backend tests such a closure once it joined the two graphs.
            self.outcomes.ok("across_sessions_unchecked_by_odometry")
            return GateDecision.PUBLISH
        text = f"loop closure query {detection.query_id} -> place {detection.matched_place_id}"
        if pose is None:
            self.outcomes.drop("no_pose_for_odometry_gate", f"{text} has no relative pose to check against odometry")
            return GateDecision.REFUSE
        problem = _pose_problem(pose.rotation, pose.translation, pose.covariance)
        if problem is not None:
            self.outcomes.drop("bad_closure_pose", f"{text}: {problem}")
            return GateDecision.REFUSE
        rotation = Rotation.from_matrix(pose.rotation).as_matrix()  # orthonormal, as a message's quaternion is
        result, distance = gate.check(detection.query_ns, detection.matched_ns,
                                      gtsam.Pose3(gtsam.Rot3(rotation), np.asarray(pose.translation, float)),
                                      np.asarray(pose.covariance, dtype=np.float64))
        if result is GateResult.CONSISTENT:
            return GateDecision.PUBLISH
        if result is GateResult.NOT_YET:
            return GateDecision.WAIT
        if result is GateResult.NO_ODOMETRY:
            # A place mapped before this odometry began (a map reloaded after a restart): odometry has nothing to
            # say about it, as for a robot without odometry.
            self.outcomes.ok("unchecked_place_before_odometry")
            return GateDecision.PUBLISH
        self.outcomes.drop(result.value, f"{text} refused: Mahalanobis distance squared {distance:.1f} > gate "
                                         f"{gate.threshold:g}")
        return GateDecision.REFUSE


def _split(closures: list[Closure], chosen: Callable[[Closure], bool]) -> tuple[list[Closure], list[Closure]]:
    """(the chosen closures, the others), each in the order they came."""
    picked: list[Closure] = []
    kept: list[Closure] = []
    for closure in closures:
        (picked if chosen(closure) else kept).append(closure)
    return picked, kept


def _pose_problem(rotation: np.ndarray, translation: np.ndarray, covariance: np.ndarray) -> str | None:
    """Why a relative pose cannot go to the gate (non-finite, or a covariance that is none); None when it can."""
    if not (np.isfinite(rotation).all() and np.isfinite(translation).all()):
        return "closure pose is not finite"
    return covariance_problem(np.asarray(covariance).reshape(36), 6, "closure pose_covariance")
