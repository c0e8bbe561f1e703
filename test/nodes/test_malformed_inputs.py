"""Every node, fed malformed and extreme messages of every type it subscribes to through its ROS topics: each
one is counted by name and dropped, none stops the node, and a valid message after them still gives output.

Hypothesis draws the values (derandomized: CI runs the same messages every time); every example sends every
kind once, in a drawn order, then a valid message and waits for the node's answer to it. The verdicts are
recorded for ``scripts/reliability_figures.sh`` (docs/reliability_figures.md).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_msgs.msg import BagOfWords, Features, LoopClosure, PlacePosterior  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from nav_msgs.msg import Path as PathMessage  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage, Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from aefabmap_ros.nodes.fabmap_node import FabMapNode  # noqa: E402
from aefabmap_ros.nodes.feature_node import FeatureNode  # noqa: E402
from aefabmap_ros.nodes.messages import features_to_message  # noqa: E402
from aefabmap_ros.nodes.pose_graph_node import PoseGraphNode  # noqa: E402
from aefabmap_ros.nodes.quantizer_node import QuantizerNode  # noqa: E402
from aefabmap_ros.nodes.verifier_node import VerifierNode  # noqa: E402
from aefabmap_ros.stamps import stamp_to_ns  # noqa: E402
from test.nodes import malformed  # noqa: E402
from test.nodes.malformed import Kind, Stamps  # noqa: E402
from test.nodes.topic_probe import ANSWER_WAIT_S, TopicProbe, Verdicts  # noqa: E402
from test.reliability import Recorder  # noqa: E402
from test.revisit_fixture import RevisitData  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.reliability, pytest.mark.usefixtures("ros_context")]

# Eight examples per node (the default of _fuzz) keep the tests within seconds, past the shared fixture.
FUZZ = settings(derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
START_SEC = 1_700_000_000  # in the nodes' past: fabmap_node refuses frames stamped far in its future


def _params(**values: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def _answered(probe: TopicProbe, topic: str, stamp: Time, accept: Callable[[Any], bool] = lambda _m: True
              ) -> Callable[[], bool]:
    wanted = stamp_to_ns(stamp)
    return lambda: any(stamp_to_ns(m.header.stamp) == wanted and accept(m) for m in probe.received[topic])


def _fuzz(probe: TopicProbe, kinds: list[Kind], clocks: Callable[[str], Stamps],
          valid_frame: Callable[[], bool], verdicts: Verdicts, examples: int = 8) -> Callable[[], None]:
    """The hypothesis test: ``examples`` times every kind once, in a drawn order, then a valid frame that must
    be answered."""

    @settings(FUZZ, max_examples=examples)
    @given(data=st.data())
    def run(data: st.DataObject) -> None:
        for each in data.draw(st.permutations(kinds), label="order"):
            message = each.build(data, clocks(each.topic))
            probe.judge(each.name, each.topic, message, set(each.expected), verdicts)
        assert valid_frame(), f"{probe.node.get_name()} gave no output for a valid message after the malformed ones"

    return run


def _check_and_record(name: str, kinds: list[Kind], verdicts: Verdicts, reliability: Recorder) -> None:
    reliability.malformed(name, verdicts)
    assert verdicts.kinds() == {k.name for k in kinds}
    assert not verdicts.failures(), verdicts.failures()


@pytest.fixture
def probed() -> Iterator[list[TopicProbe]]:
    """The probes a test makes, closed (and their nodes destroyed) whatever happens."""
    probes: list[TopicProbe] = []
    yield probes
    for probe in probes:
        probe.close()
        probe.node.destroy_node()


def test_feature_node_counts_every_malformed_image(revisit_data: RevisitData, probed: list[TopicProbe],
                                                    reliability: Recorder) -> None:
    node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), drop_when_busy=False,
                                                   detection_rate_hz=0.0))
    probe = TopicProbe(node, {"/image": Image, "/image/compressed": CompressedImage}, {"/aefabmap/features": Features})
    probed.append(probe)
    probe.wait_connected()
    stamps = Stamps(START_SEC)

    def valid_frame() -> bool:
        stamp = stamps.next()
        return probe.publish_and_wait("/image", malformed.mono8(stamp), _answered(probe, "/aefabmap/features", stamp))

    assert valid_frame()
    verdicts = Verdicts()
    _fuzz(probe, malformed.IMAGE_KINDS, lambda _topic: stamps, valid_frame, verdicts)()
    _check_and_record("feature_node", malformed.IMAGE_KINDS, verdicts, reliability)


def test_quantizer_node_counts_every_malformed_features_message(revisit_data: RevisitData,
                                                                 probed: list[TopicProbe],
                                                                 reliability: Recorder) -> None:
    node = QuantizerNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), drop_when_busy=False))
    probe = TopicProbe(node, {"/aefabmap/features": Features}, {"/aefabmap/words": BagOfWords})
    probed.append(probe)
    probe.wait_connected()
    stamps = Stamps(START_SEC)

    def valid_frame() -> bool:
        stamp = stamps.next()
        return probe.publish_and_wait("/aefabmap/features", malformed.features(stamp, seed=stamp.sec),
                                      _answered(probe, "/aefabmap/words", stamp))

    assert valid_frame()
    verdicts = Verdicts()
    _fuzz(probe, malformed.QUANTIZER_KINDS, lambda _topic: stamps, valid_frame, verdicts)()
    _check_and_record("quantizer_node", malformed.QUANTIZER_KINDS, verdicts, reliability)


def test_fabmap_node_counts_every_malformed_words_message(revisit_data: RevisitData, tmp_path: Path,
                                                          probed: list[TopicProbe], reliability: Recorder) -> None:
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir),
                                                  map_file=str(tmp_path / "map.npz")))
    probe = TopicProbe(node, {"/aefabmap/words": BagOfWords}, {"/place_posteriors": PlacePosterior})
    probed.append(probe)
    probe.wait_connected()
    vocabulary = malformed.Vocabulary(revisit_data.vocabulary_id, node.vocabulary_size)
    stamps = Stamps(START_SEC)

    def valid_frame() -> bool:
        stamp = stamps.next()
        message = malformed.words(stamp, vocabulary.vocabulary_id, vocabulary.size, list(range(stamp.sec % 50, 400, 7)))
        return probe.publish_and_wait("/aefabmap/words", message,
                                      _answered(probe, "/place_posteriors", stamp, lambda m: m.query_id >= 0))

    assert valid_frame()
    kinds = malformed.fabmap_kinds(vocabulary)
    verdicts = Verdicts()
    _fuzz(probe, kinds, lambda _topic: stamps, valid_frame, verdicts)()
    _check_and_record("fabmap_node", kinds, verdicts, reliability)


def test_pose_graph_node_counts_every_malformed_odometry_and_closure(probed: list[TopicProbe],
                                                                     reliability: Recorder) -> None:
    # The path answers each valid closure within 0.05 s (its period), so every frame is checked quickly.
    node = PoseGraphNode(parameter_overrides=[Parameter("publish_period_s", value=0.05)])
    probe = TopicProbe(node, {"/odom": Odometry, "/loop_closures": LoopClosure}, {"/pose_graph/path": PathMessage})
    probed.append(probe)
    probe.wait_connected()
    stamps = Stamps(START_SEC)

    def valid_frame() -> bool:
        """Two odometry poses a metre apart, then the closure between them that odometry agrees with."""
        place, query = stamps.next(), stamps.next()
        for stamp in (place, query):
            probe.publish_and_wait("/odom", malformed.odometry(stamp, x=float(stamp.sec - START_SEC)), lambda: True)
        return probe.publish_and_wait("/loop_closures", malformed.closure(query, place, -1.0),
                                      _answered(probe, "/pose_graph/path", query))

    assert valid_frame()
    kinds = [*malformed.odometry_kinds(future=True), *malformed.POSE_GRAPH_CLOSURE_KINDS]
    verdicts = Verdicts()
    _fuzz(probe, kinds, lambda _topic: stamps, valid_frame, verdicts)()
    _check_and_record("pose_graph_node", kinds, verdicts, reliability)


def _verifier(probed: list[TopicProbe], answer_wait_s: float
              ) -> tuple[TopicProbe, Callable[[], bool], Callable[[str], Stamps]]:
    """verifier_node with every input subscribed, connected to a probe; a valid frame's round and the clocks."""
    from test.verification.test_geometric import _two_views

    node = VerifierNode(parameter_overrides=_params(depth_topic="depth", candidates=2, max_lag_s=0.0))
    inputs = {"/aefabmap/features": Features, "/loop_closure_candidates": LoopClosure, "/camera_info": CameraInfo,
              "/depth": Image, "/odom": Odometry, "/place_posteriors": PlacePosterior,
              "/aefabmap/skipped_frames": Header}
    probe = TopicProbe(node, inputs, {"/loop_closures": LoopClosure}, answer_wait_s)
    probed.append(probe)
    probe.wait_connected()
    # Frames at one end of time, odometry at the other: the frames' closures fall before the odometry, which
    # then has nothing to say about them (published unchecked), while odometry's own checks still run.
    frames, odometry_clock = Stamps(START_SEC), Stamps(START_SEC + 10_000_000)
    probe.publish_and_wait("/camera_info", malformed.camera_info(), lambda: True, seconds=0.2)
    query_features, place_features, _ = _two_views(seed=21)

    def valid_frame() -> bool:
        """A place, its second view with the posterior and candidate for it: a verified closure goes out."""
        probe.publish_and_wait("/odom", malformed.odometry(odometry_clock.next()), lambda: True, seconds=0.1)
        place, query = frames.next(), frames.next()
        for stamp, view in ((place, place_features), (query, query_features)):
            probe.publish_and_wait("/aefabmap/features", features_to_message(view, Header(stamp=stamp), (640, 480)),
                                   lambda: True, seconds=0.1)
        probe.publish_and_wait("/place_posteriors", malformed.posterior(query, place, place.sec), lambda: True,
                               seconds=0.1)
        return probe.publish_and_wait("/loop_closure_candidates", malformed.closure(query, place, 0.0),
                                      _answered(probe, "/loop_closures", query))

    assert valid_frame()
    return probe, valid_frame, lambda topic: odometry_clock if topic == "/odom" else frames


def test_verifier_node_counts_every_malformed_input(probed: list[TopicProbe], reliability: Recorder) -> None:
    probe, valid_frame, clocks = _verifier(probed, answer_wait_s=ANSWER_WAIT_S)
    kinds = [*malformed.VERIFIER_KINDS, *malformed.odometry_kinds(future=False)]
    verdicts = Verdicts()
    _fuzz(probe, kinds, clocks, valid_frame, verdicts)()
    _check_and_record("verifier_node", kinds, verdicts, reliability)


def test_verifier_node_counts_bad_candidates_and_stamps(probed: list[TopicProbe], reliability: Recorder) -> None:
    probe, valid_frame, clocks = _verifier(probed, answer_wait_s=2.0)
    kinds = malformed.VERIFIER_CANDIDATE_AND_STAMP_KINDS
    verdicts = Verdicts()
    _fuzz(probe, kinds, clocks, valid_frame, verdicts, examples=1)()
    _check_and_record("verifier_node (candidates, future odometry, skipped frames)", kinds, verdicts, reliability)
