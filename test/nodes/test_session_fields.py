"""Sessions and robots through the messages: fabmap_node's posterior and candidate name the query's session
and each place's, verifier_node carries them from candidate to closure, and a publisher that sends none
reads as session 0 of robot ''."""

from __future__ import annotations

import pytest

msg = pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402

from aefabmap_ros.fabmap.recognizer import PlaceRecognizer, Recognition  # noqa: E402
from aefabmap_ros.nodes.closure_messages import (  # noqa: E402
    closure_to_message,
    detection_from_message,
    posterior_from_message,
)
from aefabmap_ros.nodes.messages import (  # noqa: E402
    posterior_problem,
    recognition_to_loop_closure,
    recognition_to_posterior,
)
from aefabmap_ros.verification.closures import Closure  # noqa: E402
from aefabmap_ros.verification.relative_pose import PoseOutcome, PoseStatus  # noqa: E402
from test.fabmap.test_recognizer import SAMPLES, _frames, _tree, openfabmap  # noqa: E402


def _revisit_across_sessions() -> Recognition:
    """A frame of robot r2's session 1 that revisits a place of robot r1's session 0."""
    frames = _frames(5, seed=4)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, openfabmap(top_k=3), "vocab-a", robot="r1")
    for i, words in enumerate(frames):
        recognizer.process(words, 1_000_000 * (i + 1))
    return recognizer.process(frames[2], 9_000_000, robot="r2")


def test_a_cross_session_candidate_names_both_sessions() -> None:
    recognition = _revisit_across_sessions()
    header = msg.LoopClosure().header
    header.stamp = Time(sec=0, nanosec=9_000_000)
    candidate = recognition_to_loop_closure(recognition, header)
    assert candidate is not None and candidate.matched_place_id == 2
    assert (candidate.query_robot, candidate.query_session) == ("r2", 1)
    assert (candidate.matched_robot, candidate.matched_session) == ("r1", 0)
    posterior = recognition_to_posterior(recognition, header)
    assert (posterior.robot, posterior.session) == ("r2", 1)
    assert list(posterior.place_sessions) == [0] * len(posterior.place_ids)
    assert list(posterior.place_robots) == ["r1"] * len(posterior.place_ids)
    assert posterior_problem(posterior) is None
    read = posterior_from_message(posterior)
    assert (read.session, read.robot) == (1, "r2")
    assert [(c.session, c.robot) for c in read.candidates] == [(0, "r1")] * len(read.candidates)


def test_the_verifier_carries_sessions_from_candidate_to_closure() -> None:
    candidate = msg.LoopClosure(query_id=9, matched_place_id=2, probability=0.995, query_robot="r2", query_session=1,
                                matched_robot="r1", matched_session=0)
    candidate.header.stamp = Time(sec=9)
    candidate.matched_stamp = Time(sec=3)
    detection = detection_from_message(candidate)
    published = closure_to_message(Closure(detection, 40, PoseOutcome(None, PoseStatus.NO_CAMERA_INFO)))
    assert (published.query_robot, published.query_session) == ("r2", 1)
    assert (published.matched_robot, published.matched_session) == ("r1", 0)
    assert published.inliers == 40 and published.matched_stamp.sec == 3


def test_a_posterior_without_sessions_reads_as_session_0_and_a_short_session_list_is_named() -> None:
    old = msg.PlacePosterior(query_id=7, place_ids=[1, 2], probabilities=[0.5, 0.25], log_likelihoods=[-1.0, -2.0])
    old.place_stamps = [Time(sec=1), Time(sec=2)]
    assert posterior_problem(old) is None
    assert [(c.session, c.robot) for c in posterior_from_message(old).candidates] == [(0, ""), (0, "")]
    old.place_sessions = [0]
    problem = posterior_problem(old)
    assert problem is not None and "'place_sessions': 1" in problem
