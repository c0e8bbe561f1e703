"""verifier_node's messages <-> the verification chain's plain values (verification/closures.py), and what it
refuses of them before the chain sees them."""

from __future__ import annotations

from aefabmap_msgs.msg import LoopClosure, PlacePosterior
from nav_msgs.msg import Odometry

from aefabmap_ros.nodes.future_stamps import FutureStamps
from aefabmap_ros.nodes.messages import fill_relative_pose, loop_closure_stamp_problem, odometry_problem, time_from_ns
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.closures import Closure, Detection, Posterior, RankedPlace


def detection_from_message(message: LoopClosure) -> Detection:
    return Detection(stamp_to_ns(message.header.stamp), int(message.query_id), int(message.query_place_id),
                     int(message.matched_place_id), stamp_to_ns(message.matched_stamp), float(message.probability),
                     float(message.log_likelihood), message.header.frame_id, int(message.query_session),
                     message.query_robot, int(message.matched_session), message.matched_robot)


def posterior_from_message(message: PlacePosterior) -> Posterior:
    """A PlacePosterior whose candidate arrays are of one length (``messages.posterior_problem`` checked)."""
    count = len(message.place_ids)
    # A publisher that sends no sessions: every place is then in session 0 of robot ''.
    sessions = list(message.place_sessions) if len(message.place_sessions) else [0] * count
    robots = list(message.place_robots) if len(message.place_robots) else [""] * count
    candidates = tuple(
        RankedPlace(int(place_id), stamp_to_ns(stamp), float(probability), float(log_likelihood), int(session),
                    robot)
        for place_id, stamp, probability, log_likelihood, session, robot in zip(
            message.place_ids, message.place_stamps, message.probabilities, message.log_likelihoods, sessions,
            robots, strict=True))
    return Posterior(stamp_to_ns(message.header.stamp), int(message.query_id), int(message.assigned_place_id),
                     int(message.current_place_id), bool(message.loop_closure_candidate), candidates,
                     message.header.frame_id, int(message.session), message.robot)


def closure_to_message(closure: Closure) -> LoopClosure:
    detection = closure.detection
    message = LoopClosure(query_id=detection.query_id, query_place_id=detection.query_place_id,
                          matched_place_id=detection.matched_place_id, probability=detection.probability,
                          log_likelihood=detection.log_likelihood, inliers=closure.inliers)
    message.header.stamp = time_from_ns(detection.query_ns)
    message.header.frame_id = detection.frame_id
    message.matched_stamp = time_from_ns(detection.matched_ns)
    message.query_robot, message.query_session = detection.query_robot, detection.query_session
    message.matched_robot, message.matched_session = detection.matched_robot, detection.matched_session
    fill_relative_pose(message, closure.pose)
    return message


def candidate_refusal(message: LoopClosure) -> tuple[str, str] | None:
    """(drop name, why) for a candidate the chain must not take: stamps that are not ROS times, a matched place
    not before its query (it would be verified against itself or a later frame), a posterior outside [0, 1]."""
    problem = loop_closure_stamp_problem(message)
    if problem is not None:
        return "bad_closure_stamp", problem
    query_ns, matched_ns = stamp_to_ns(message.header.stamp), stamp_to_ns(message.matched_stamp)
    text = f"candidate of query {message.query_id} -> place {message.matched_place_id}"
    if matched_ns >= query_ns:
        return "bad_candidate", f"{text}: its place ({matched_ns} ns) is not before the query ({query_ns} ns)"
    if not 0.0 <= message.probability <= 1.0:  # NaN fails too
        return "bad_candidate", f"{text}: probability {message.probability} is not in [0, 1]"
    return None


def odometry_refusal(message: Odometry, future: FutureStamps) -> tuple[str, str] | None:
    """(drop name, why) for odometry the gate must not take: a broken stamp or pose (it would interpolate NaN
    between its neighbours), or a stamp far in the future (every later message would be out of order)."""
    problem = odometry_problem(message)
    if problem is not None:
        return "bad_odometry", problem
    problem = future.problem(stamp_to_ns(message.header.stamp))
    return None if problem is None else ("stamp_in_future", f"odometry {problem}")
