"""verifier_node's messages <-> the verification chain's plain values (verification/closures.py)."""

from __future__ import annotations

from aefabmap_msgs.msg import LoopClosure, PlacePosterior

from aefabmap_ros.nodes.messages import fill_relative_pose, time_from_ns
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.closures import Closure, Detection, Posterior, RankedPlace


def detection_from_message(message: LoopClosure) -> Detection:
    return Detection(stamp_to_ns(message.header.stamp), int(message.query_id), int(message.query_place_id),
                     int(message.matched_place_id), stamp_to_ns(message.matched_stamp), float(message.probability),
                     float(message.log_likelihood), message.header.frame_id)


def posterior_from_message(message: PlacePosterior) -> Posterior:
    """A PlacePosterior whose candidate arrays are of one length (``messages.posterior_problem`` checked)."""
    candidates = tuple(
        RankedPlace(int(place_id), stamp_to_ns(stamp), float(probability), float(log_likelihood))
        for place_id, stamp, probability, log_likelihood in zip(
            message.place_ids, message.place_stamps, message.probabilities, message.log_likelihoods, strict=True))
    return Posterior(stamp_to_ns(message.header.stamp), int(message.query_id), int(message.assigned_place_id),
                     int(message.current_place_id), bool(message.loop_closure_candidate), candidates,
                     message.header.frame_id)


def closure_to_message(closure: Closure) -> LoopClosure:
    detection = closure.detection
    message = LoopClosure(query_id=detection.query_id, query_place_id=detection.query_place_id,
                          matched_place_id=detection.matched_place_id, probability=detection.probability,
                          log_likelihood=detection.log_likelihood, inliers=closure.inliers)
    message.header.stamp = time_from_ns(detection.query_ns)
    message.header.frame_id = detection.frame_id
    message.matched_stamp = time_from_ns(detection.matched_ns)
    fill_relative_pose(message, closure.pose)
    return message
