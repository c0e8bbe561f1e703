"""The nodes of several robots and a base station in one process (docs/fleet.md): the feature server's words
and answers, fabmap_node's robots, verifier_node's requests and the frames it takes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Header, String  # noqa: E402

from aefabmap_ros.features.extraction import Features  # noqa: E402
from aefabmap_ros.nodes.fabmap_node import FabMapNode  # noqa: E402
from aefabmap_ros.nodes.feature_server_node import FeatureServerNode  # noqa: E402
from aefabmap_ros.nodes.fleet_messages import feature_request, message_to_received_frame  # noqa: E402
from aefabmap_ros.nodes.messages import features_to_message  # noqa: E402
from aefabmap_ros.nodes.verifier_node import VerifierNode  # noqa: E402
from test.nodes.captured import Captured  # noqa: E402
from test.revisit_fixture import RevisitData  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]
SECOND = 1_000_000_000
REPO_ROOT = Path(__file__).resolve().parents[2]


def _params(**values: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def _features(seed: int = 0, count: int = 40) -> Features:
    rng = np.random.default_rng(seed)
    keypoints = np.column_stack([rng.uniform(0, 300, (count, 2)), np.ones((count, 2)), rng.uniform(0, 1, count)])
    return Features(keypoints.astype(np.float32), rng.integers(0, 256, (count, 128)).astype(np.float32), "sift")


def _words(word_ids: list[int], sec: int, vocabulary_id: str) -> Any:
    message = msg.BagOfWords(vocabulary_id=vocabulary_id, vocabulary_size=400, word_ids=word_ids,
                             counts=[1] * len(word_ids), keypoint_words=[1, 2, 3])
    message.header.stamp = Time(sec=sec)
    return message


def test_the_feature_server_forwards_words_without_keypoint_words_and_answers_requests() -> None:
    node = FeatureServerNode(parameter_overrides=_params(robot="robot1", max_features=30))
    try:
        words, answers = Captured(node.words_publisher), Captured(node.publisher)
        node._on_words(_words([1, 5], 3, "v"))
        assert list(words.messages[0].word_ids) == [1, 5] and len(words.messages[0].keypoint_words) == 0
        features = _features()
        node._on_features(features_to_message(features, Header(stamp=Time(sec=3), frame_id="cam"), (320, 240)))
        node._on_request(feature_request([3 * SECOND, 1 * SECOND], 0))  # 1 s was never taken
        bad = feature_request([3 * SECOND], 0)
        bad.stamps[0].nanosec = 2_000_000_000
        node._on_request(bad)
        (answer,) = answers.messages
        frame = message_to_received_frame(answer)
        assert (frame.stamp_ns, frame.robot, answer.header.frame_id) == (3 * SECOND, "robot1", "cam")
        strongest = np.sort(np.argsort(-features.keypoints[:, 4], kind="stable")[:30])
        np.testing.assert_array_equal(frame.features.keypoints, features.keypoints[strongest, :2])
        np.testing.assert_array_equal(frame.features.descriptors, features.descriptors[strongest])
        assert frame.camera.camera is None and frame.camera.image_size == (320, 240) and frame.depths is None
        counts = node.counter.counts
        assert counts["served"] == 1 and counts["dropped_not_kept_any_more"] == 1 and counts["dropped_bad_request"] == 1
    finally:
        node.destroy_node()


def test_the_feature_server_forwards_odometry_thinned_by_stamp() -> None:
    from nav_msgs.msg import Odometry

    node = FeatureServerNode(parameter_overrides=_params(robot="robot1", odometry_rate_hz=10.0))
    try:
        forwarded = Captured(node.odometry_publisher)
        for millis in range(0, 1000, 20):  # 50 Hz for a second
            message = Odometry()
            message.header.stamp = Time(sec=100, nanosec=millis * 1_000_000)
            node._on_odometry(message)
        assert [m.header.stamp.nanosec // 1_000_000 for m in forwarded.messages] == list(range(0, 1000, 100))
    finally:
        node.destroy_node()


def test_fabmap_node_keeps_each_robots_frames_in_order_in_one_map(revisit_data: RevisitData) -> None:
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), robots=["r1", "r2"]))
    try:
        posteriors = Captured(node.posterior_publisher)
        vid = revisit_data.vocabulary_id
        node._on_words(_words([1, 5, 9], 10, vid), robot="r1")
        node._on_words(_words([2, 6, 40], 8, vid), robot="r2")  # older than r1's frame: r2's own order counts
        node._on_words(_words([2, 6, 41], 7, vid), robot="r2")  # older than r2's last: out of order
        assert [(p.robot, p.query_id >= 0) for p in posteriors.messages] == [("r1", True), ("r2", True),
                                                                              ("r2", False)]
        assert node.counter.counts["dropped_out_of_order"] == 1
        assert [s.robot for s in node.recognizer.sessions] == ["r1", "r2"]  # no empty session of robot ''

        node._on_start_robot_session(String(data="r2"))  # r2 was relocated: its next frame starts a session
        node._on_start_robot_session(String(data="r3"))  # not one of the node's robots
        node._on_words(_words([3, 6, 42], 9, vid), robot="r2")
        assert (posteriors.messages[-1].robot, posteriors.messages[-1].session) == ("r2", 2)
        assert node.counter.counts["dropped_unknown_robot"] == 1
    finally:
        node.destroy_node()


def test_verifier_node_asks_each_robot_for_its_frames_and_keeps_them_as_that_robots() -> None:
    node = VerifierNode(parameter_overrides=_params(robots=["r1", "r2"]))
    try:
        links = node.links
        assert links is not None
        requests = {robot: Captured(publisher) for robot, publisher in links.publishers.items()}
        posterior = msg.PlacePosterior(query_id=0, assigned_place_id=0, current_place_id=0, is_new_place=True,
                                       robot="r2")
        posterior.header.stamp = Time(sec=5)
        node._on_posterior(posterior)  # r2's frame made place 0: asked for from r2
        assert not requests["r1"].messages and [s.sec for s in requests["r2"].messages[0].stamps] == [5]
        server = FeatureServerNode(parameter_overrides=_params(robot="r2"))
        try:
            answers = Captured(server.publisher)
            server._on_features(features_to_message(_features(), Header(stamp=Time(sec=5)), (320, 240)))
            server._on_request(requests["r2"].messages[0])
        finally:
            server.destroy_node()
        links._on_answer(answers.messages[0], None, robot="r1")  # on r1's topic: not r1's frame
        links._on_answer(answers.messages[0], None, robot="r2")
        assert node.store.robot_of(5 * SECOND) == "r2"
        assert node.counter.counts["dropped_answer_of_another_robot"] == 1
        assert node.counter.counts["requested_features_received"] == 1
    finally:
        node.destroy_node()


def test_the_shipped_parameter_file_lists_the_feature_servers_parameters() -> None:
    shipped = yaml.safe_load((REPO_ROOT / "aefabmap_ros" / "config" / "aefabmap.yaml").read_text())
    values = dict(shipped["feature_server_node"]["ros__parameters"])
    node = FeatureServerNode(parameter_overrides=_params(**values))
    try:
        assert set(node._parameters) - {"use_sim_time", "start_type_description_service"} == set(values)
    finally:
        node.destroy_node()
