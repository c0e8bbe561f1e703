"""Nodes in this process, callbacks called directly: bad input is counted and dropped, good input published."""

from __future__ import annotations

import copy
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CompressedImage, Image  # noqa: E402

from aefabmap_ros.errors import ConfigError, ModelError, VocabularyMismatchError  # noqa: E402  # noqa: E402
from aefabmap_ros.fabmap.config import FabMapConfig  # noqa: E402
from aefabmap_ros.io.sources import ImageSource  # noqa: E402
from aefabmap_ros.nodes.fabmap_node import FabMapNode  # noqa: E402
from aefabmap_ros.nodes.feature_node import FeatureNode  # noqa: E402
from aefabmap_ros.nodes.quantizer_node import QuantizerNode  # noqa: E402
from aefabmap_ros.nodes.verifier_node import VerifierNode  # noqa: E402
from aefabmap_ros.stamps import stamp_to_ns  # noqa: E402
from test.nodes.captured import Captured  # noqa: E402
from test.reliability import Recorder  # noqa: E402
from test.revisit_fixture import RevisitData  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]


def _dropped(counter: Any) -> int:
    """Inputs a node counted as dropped (and so survived: the tests then feed it a good one)."""
    return sum(value for key, value in counter.counts.items() if key.startswith("dropped_"))


def _params(**values: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def _image(data: bytes, encoding: str, height: int, width: int, step: int, sec: int = 1) -> Image:
    image = Image(height=height, width=width, encoding=encoding, step=step, data=data)
    image.header.stamp = Time(sec=sec)
    return image


def _first_frames(data: RevisitData, count: int) -> list[np.ndarray]:
    frames = ImageSource(bag=data.bag, topic="/image").frames()
    return [gray for _, (_, gray) in zip(range(count), frames, strict=False)]


@pytest.mark.reliability
def test_feature_node_publishes_and_drops_bad_images(revisit_data: RevisitData, reliability: Recorder) -> None:
    node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir)))
    try:
        out = Captured(node.publisher)
        gray = _first_frames(revisit_data, 1)[0]
        height, width = gray.shape
        node._on_image(_image(gray.tobytes(), "mono8", height, width, width))
        bgr = np.repeat(gray[:, :, None], 3, axis=2)
        node._on_image(_image(bgr.tobytes(), "bgr8", height, width, 3 * width))
        assert len(out.messages) == 2
        assert out.messages[0].descriptor_type == "sift"
        assert 0 < len(out.messages[0].x) <= 300  # the model's max_features, not the parameter default
        # OpenCV SIFT values are integers 0-255: they cross as bytes, 4x smaller than float32
        assert len(out.messages[0].binary_descriptors) == 128 * len(out.messages[0].x)
        assert len(out.messages[0].float_descriptors) == 0

        node._on_image(_image(b"\0" * 12, "yuv420_weird", 2, 2, 6))  # unsupported encoding
        node._on_image(_image(b"\0" * 5, "mono8", 2, 3, 3))  # data shorter than step * height
        node._on_image(_image(b"", "mono8", 0, 0, 0))  # zero-sized
        node._on_image(CompressedImage(format="jpeg", data=b"\xff\xd8 not a jpeg"))
        assert node.counter.counts["dropped_bad_image"] == 4
        assert len(out.messages) == 2

        blank = np.full((120, 160), 128, np.uint8)  # no features: still published, keeps its frame
        node._on_image(_image(blank.tobytes(), "mono8", 120, 160, 160, sec=9))
        assert len(out.messages) == 3 and len(out.messages[2].x) == 0
        assert out.messages[2].header.stamp.sec == 9
        assert node.counter.counts["images_without_features"] == 1
        reliability.bad_inputs("feature_node", tried=4, survived=_dropped(node.counter))
    finally:
        node.destroy_node()


class SlowStage:
    """Stands in for a node's processing: records each frame's stamp and holds the first until released."""

    def __init__(self) -> None:
        self.started, self.release, self.second = threading.Event(), threading.Event(), threading.Event()
        self.processed: list[int] = []

    def __call__(self, message: Any) -> None:
        self.processed.append(message.header.stamp.sec)
        (self.second if self.started.is_set() else self.started).set()
        self.release.wait()


def _assert_only_the_newest_waits(node: Any, on_message: Any, stage: SlowStage, make: Any) -> None:
    """Frame 1 is in hand, 2 3 4 arrive: 2 and 3 are dropped (counted), 4 is processed next, nothing queues."""
    try:
        on_message(make(1))
        assert stage.started.wait(timeout=30)  # the worker holds frame 1
        for sec in (2, 3, 4):
            on_message(make(sec))
        assert node.counter.counts["dropped_busy"] == 2  # 2 and 3 were replaced before being taken
        stage.release.set()
        assert stage.second.wait(timeout=30)
        assert stage.processed == [1, 4]
        assert node.frames.worker.gate.take(timeout_s=0) is None  # nothing left queued
    finally:
        stage.release.set()
        node.destroy_node()


def test_feature_node_drops_camera_frames_at_the_door_while_busy(revisit_data: RevisitData,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """sensor_data: a frame that arrives while the worker is busy waits in a one-frame gate; a newer
    one replaces it (counted), so the worker's next frame is the newest and nothing queues."""
    stage = SlowStage()
    monkeypatch.setattr(FeatureNode, "_on_image", lambda _node, message: stage(message))
    node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), image_qos="sensor_data"))
    _assert_only_the_newest_waits(node, node._on_frame, stage, lambda sec: _image(b"", "mono8", 0, 0, 0, sec=sec))


def _empty_features(sec: int) -> Any:
    message = msg.Features(descriptor_type="sift")
    message.header.stamp = Time(sec=sec)
    return message


def test_quantizer_drops_features_it_cannot_take_instead_of_queuing_them(revisit_data: RevisitData,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The slowest stage drops, not only the first: features arriving while quantization is busy do
    not queue up behind it (the delay from image to posterior would grow without bound)."""
    stage = SlowStage()
    monkeypatch.setattr(QuantizerNode, "_quantize", lambda _node, message: stage(message))
    node = QuantizerNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir)))
    _assert_only_the_newest_waits(node, node._on_features, stage, _empty_features)


def _in_order_quantizer(data: RevisitData) -> QuantizerNode:
    """Quantizing in the callback (no worker thread): a test sees the words as soon as it hands over features."""
    return QuantizerNode(parameter_overrides=_params(model_dir=str(data.model_dir), drop_when_busy=False))


def test_quantizer_takes_every_message_in_order_for_a_lossless_replay(revisit_data: RevisitData) -> None:
    from aefabmap_ros.features.extraction import extract_features
    from aefabmap_ros.model.directory import load_model

    features = extract_features(_first_frames(revisit_data, 1)[0], load_model(revisit_data.model_dir).feature_config)
    node = _in_order_quantizer(revisit_data)
    try:
        out = Captured(node.publisher)
        assert node.frames.worker is None
        for sec in (1, 2, 3):
            node._on_features(_features_message(features, sec))
        assert [message.header.stamp.sec for message in out.messages] == [1, 2, 3]
        assert "dropped_busy" not in node.counter.counts
    finally:
        node.destroy_node()


def test_feature_node_processes_a_frame_once_when_both_transports_bring_it(revisit_data: RevisitData) -> None:
    """A camera behind image_transport publishes each frame raw and compressed; both are subscribed by default."""
    import cv2

    # reliable: frames are extracted in the callback (sensor_data hands them to a worker thread)
    node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), image_qos="reliable",
                                                   drop_when_busy=False))
    try:
        out = Captured(node.publisher)
        gray = _first_frames(revisit_data, 1)[0]
        height, width = gray.shape
        png = CompressedImage(format="png", data=cv2.imencode(".png", gray)[1].tobytes())
        png.header.stamp = Time(sec=1)
        node._on_frame(_image(gray.tobytes(), "mono8", height, width, width, sec=1), transport="raw")
        node._on_frame(png, transport="compressed")
        assert len(out.messages) == 1 and node.counter.counts["skipped_compressed_copies"] == 1
        png.header.stamp = Time(sec=2)  # a new frame that only the compressed transport brings
        node._on_frame(png, transport="compressed")
        assert len(out.messages) == 2
    finally:
        node.destroy_node()


@pytest.mark.reliability
def test_quantizer_node_words_and_bad_features(revisit_data: RevisitData, reliability: Recorder) -> None:
    feature_node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir)))
    node = _in_order_quantizer(revisit_data)
    try:
        features_out, words_out = Captured(feature_node.publisher), Captured(node.publisher)
        gray = _first_frames(revisit_data, 1)[0]
        height, width = gray.shape
        feature_node._on_image(_image(gray.tobytes(), "mono8", height, width, width))
        features = features_out.messages[0]
        node._on_features(features)
        words = words_out.messages[0]
        assert words.vocabulary_id == revisit_data.vocabulary_id and words.vocabulary_size == 400
        ids = np.asarray(words.word_ids)
        assert ids.size > 0 and np.all(np.diff(ids) > 0) and ids.max() < 400
        assert sum(words.counts) == len(features.x) == len(words.keypoint_words)

        orb = msg.Features(descriptor_type="orb", descriptor_length=32)
        node._on_features(orb)
        broken = msg.Features(descriptor_type="sift", descriptor_length=128, x=[1.0], y=[1.0], size=[1.0],
                              angle=[0.0], response=[1.0], float_descriptors=[0.0] * 10)
        node._on_features(broken)
        assert node.counter.counts["dropped_wrong_descriptor_type"] == 1
        assert node.counter.counts["dropped_bad_features"] == 1
        assert len(words_out.messages) == 1
        node._on_features(features)  # alive: the next frame is quantized
        assert len(words_out.messages) == 2
        reliability.bad_inputs("quantizer_node", tried=2, survived=_dropped(node.counter))
    finally:
        feature_node.destroy_node()
        node.destroy_node()


def test_quantizer_node_words_are_the_same_from_byte_and_float_sift(revisit_data: RevisitData) -> None:
    feature_node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir)))
    node = _in_order_quantizer(revisit_data)
    try:
        features_out, words_out = Captured(feature_node.publisher), Captured(node.publisher)
        gray = _first_frames(revisit_data, 1)[0]
        feature_node._on_image(_image(gray.tobytes(), "mono8", gray.shape[0], gray.shape[1], gray.shape[1]))
        as_bytes = features_out.messages[0]
        as_floats = msg.Features(header=as_bytes.header, descriptor_type="sift", descriptor_length=128,
                                 x=as_bytes.x, y=as_bytes.y, size=as_bytes.size, angle=as_bytes.angle,
                                 response=as_bytes.response,
                                 float_descriptors=np.asarray(as_bytes.binary_descriptors, np.float32).tolist())
        node._on_features(as_bytes)
        node._on_features(as_floats)
        assert len(words_out.messages) == 2
        assert list(words_out.messages[0].keypoint_words) == list(words_out.messages[1].keypoint_words)
    finally:
        feature_node.destroy_node()
        node.destroy_node()


def test_quantizer_node_caps_blas_threads_from_its_parameter(revisit_data: RevisitData) -> None:
    from threadpoolctl import threadpool_info, threadpool_limits

    with threadpool_limits(None):  # every limit the node sets is undone on leaving
        node = QuantizerNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), blas_threads=1))
        node.destroy_node()
        assert {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"} == {1}
        with pytest.raises(ConfigError, match="blas_threads=-1"):
            QuantizerNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), blas_threads=-1))


def _words(word_ids: list[int], sec: int, vocabulary_id: str, size: int = 400) -> Any:
    message = msg.BagOfWords(vocabulary_id=vocabulary_id, vocabulary_size=size, word_ids=word_ids,
                             counts=[1] * len(word_ids))
    message.header.stamp = Time(sec=sec)
    return message


@pytest.mark.reliability
def test_fabmap_node_drops_foreign_and_out_of_order_words(revisit_data: RevisitData, tmp_path: Path,
                                                          reliability: Recorder) -> None:
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir),
                                                  map_file=str(tmp_path / "map.npz")))
    try:
        posteriors = Captured(node.posterior_publisher)
        # FAB-MAP's own closures are candidates; only verifier_node (or a remap) publishes loop_closures.
        assert node.loop_publisher.topic_name == "/loop_closure_candidates"
        vid = revisit_data.vocabulary_id
        node._on_words(_words([1, 5, 9], 10, vid))
        node._on_words(_words([1, 5, 9], 10, vid))  # same stamp again
        node._on_words(_words([2, 3], 5, vid))  # older stamp
        node._on_words(_words([2, 3], 11, "another-vocabulary"))
        node._on_words(_words([2, 3], 12, vid, size=1000))
        node._on_words(_words([3, 400], 13, vid))  # word id out of range
        node._on_words(_words([], 14, vid))  # an image without words: a query and a blank posterior, no place
        node._on_words(_words([2, 7], 15, vid))
        uncounted = _words([4, 8], 16, vid)
        uncounted.counts = [1]  # one count for two word ids
        node._on_words(uncounted)
        counts = node.counter.counts
        assert counts["dropped_out_of_order"] == 2
        assert counts["dropped_VocabularyMismatchError"] == 2
        assert counts["dropped_DataError"] == 2
        assert counts["frames_below_min_words"] == 1
        # Every image answered (a lockstep replay waits for one posterior per image), the blank and the dropped
        # ones too (query_id -1: not recognised).
        assert [p.query_id for p in posteriors.messages] == [0, -1, -1, -1, -1, -1, 1, 2, -1]
        recognised = [p for p in posteriors.messages if p.query_id >= 0]
        assert [p.current_place_id for p in recognised] == [0, 0, 1]  # each frame's own place
        blank = recognised[1]
        assert len(blank.place_ids) == 0 and blank.assigned_place_id == -1 and np.isnan(blank.new_place_probability)
        assert node.recognizer.num_places == 2 and node.recognizer.num_queries == 3
        node._on_words(_words([4, 8, 11], 17, vid))  # alive after the last bad one too
        assert node.counter.counts["processed"] == 3
        reliability.bad_inputs("fabmap_node", tried=6, survived=_dropped(node.counter))
        node.close()  # saves the map
        assert (tmp_path / "map.npz").exists()
    finally:
        node.destroy_node()


def test_fabmap_node_start_up_errors(revisit_data: RevisitData, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="model_dir is required"):
        FabMapNode()
    with pytest.raises(ModelError, match="nope"):
        FabMapNode(parameter_overrides=_params(model_dir=str(tmp_path / "nope")))
    with pytest.raises(ConfigError, match="match_threshold"):
        FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), match_threshold=2.0))
    with pytest.raises(ConfigError, match="'smoothing'"):
        FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), smoothing="high"))
    foreign_map = tmp_path / "foreign.npz"
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), map_file=str(foreign_map)))
    node._on_words(_words([1, 2], 1, revisit_data.vocabulary_id))
    node.close()
    node.destroy_node()
    data = dict(np.load(foreign_map, allow_pickle=False))
    data["vocabulary_id"] = np.array("0123456789abcdef")  # as if saved by a node with another model
    other = tmp_path / "other.npz"
    np.savez(other, **data)
    with pytest.raises(VocabularyMismatchError, match="0123456789abcdef"):
        FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), map_file=str(other)))


def test_shipped_parameter_file_matches_declared_parameters(revisit_data: RevisitData) -> None:
    """aefabmap_ros/config/aefabmap.yaml names exactly the parameters each node declares, with valid values."""
    import yaml

    from test.conftest import REPO_ROOT

    shipped = yaml.safe_load((REPO_ROOT / "aefabmap_ros" / "config" / "aefabmap.yaml").read_text())
    from aefabmap_ros.nodes.pose_graph_node import PoseGraphNode

    sections: dict[type[Any], str] = {
        FeatureNode: "feature_node", QuantizerNode: "quantizer_node", FabMapNode: "fabmap_node",
        VerifierNode: "verifier_node", PoseGraphNode: "pose_graph_node"}
    for node_class, section in sections.items():
        values = dict(shipped[section]["ros__parameters"])
        if "model_dir" in values:
            values["model_dir"] = str(revisit_data.model_dir)  # the file leaves it for the user to set
        node = node_class(parameter_overrides=_params(**values))
        try:
            declared = set(node._parameters) - {"use_sim_time", "start_type_description_service"}
            assert declared == set(values), f"{node.get_name()}: {declared ^ set(values)}"
        finally:
            node.destroy_node()


def test_shipped_parameter_values_are_the_configs_defaults() -> None:
    """One source of truth: aefabmap_ros/config/aefabmap.yaml gives fabmap_node and verifier_node the dataclass defaults
    (the values measured and documented there), so a node started without the file behaves the same."""
    from dataclasses import fields

    import yaml

    from aefabmap_ros.fabmap.config import FabMapConfig
    from aefabmap_ros.verification.geometric import VerificationConfig
    from test.conftest import REPO_ROOT

    shipped = yaml.safe_load((REPO_ROOT / "aefabmap_ros" / "config" / "aefabmap.yaml").read_text())
    from aefabmap_ros.backend.pose_graph import PoseGraphConfig

    for node, config in (("fabmap_node", FabMapConfig), ("verifier_node", VerificationConfig),
                         ("pose_graph_node", PoseGraphConfig)):
        values = shipped[node]["ros__parameters"]
        assert {f.name: values[f.name] for f in fields(config)} == {f.name: f.default for f in fields(config)}


def _features_message(features: Any, sec: int) -> Any:
    from std_msgs.msg import Header

    from aefabmap_ros.nodes.messages import features_to_message

    return features_to_message(features, Header(stamp=Time(sec=sec)), (640, 480))


def _features_of(revisit_data: RevisitData) -> Any:
    feature_node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir)))
    try:
        out = Captured(feature_node.publisher)
        gray = _first_frames(revisit_data, 1)[0]
        feature_node._on_image(_image(gray.tobytes(), "mono8", gray.shape[0], gray.shape[1], gray.shape[1]))
        return out.messages[0]
    finally:
        feature_node.destroy_node()


@pytest.mark.reliability
def test_feature_node_refuses_oversized_images_before_decoding(revisit_data: RevisitData,
                                                               reliability: Recorder) -> None:
    import cv2

    node = FeatureNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), max_image_pixels=10_000))
    try:
        out = Captured(node.publisher)
        # Header of an 8000 x 8000 image with 10 bytes of data: refused by its size, not its data.
        node._on_image(_image(b"\0" * 10, "mono8", 8000, 8000, 8000))
        ok, png = cv2.imencode(".png", np.zeros((200, 200), np.uint8))  # 40,000 pixels in a few hundred bytes
        assert ok and len(png) < 2000
        node._on_image(CompressedImage(format="png", data=png.tobytes()))
        node._on_image(_image(b"\0" * 10, "mono8", 2, 5, 5))  # small enough: decoded (and published)
        assert node.counter.counts["dropped_image_too_large"] == 2
        assert len(out.messages) == 1
        reliability.bad_inputs("feature_node", tried=2, survived=_dropped(node.counter))
    finally:
        node.destroy_node()


@pytest.mark.reliability
def test_quantizer_node_survives_any_exception_and_refuses_non_finite_descriptors(revisit_data: RevisitData,
                                                                                  reliability: Recorder) -> None:
    features = _features_of(revisit_data)
    node = _in_order_quantizer(revisit_data)
    try:
        words_out = Captured(node.publisher)
        with_nan = copy.deepcopy(features)
        # SIFT crosses as bytes; a float32 message (RootSIFT's layout, or an older sender) can carry NaN.
        values = np.asarray(with_nan.binary_descriptors, dtype=np.float32).copy()
        values[7] = np.nan
        with_nan.binary_descriptors = np.zeros(0, np.uint8)
        with_nan.float_descriptors = values
        node._on_features(with_nan)
        assert node.counter.counts["dropped_bad_features"] == 1

        real_quantize = node.quantizer.quantize

        def failing(descriptors: np.ndarray) -> np.ndarray:
            raise RuntimeError("faiss: out of memory")

        node.quantizer.quantize = failing  # type: ignore[method-assign]
        node._on_features(features)
        node.quantizer.quantize = real_quantize  # type: ignore[method-assign]
        node._on_features(features)  # the node is alive: the next frame is quantized
        assert node.counter.counts["dropped_RuntimeError"] == 1
        assert len(words_out.messages) == 1
        reliability.bad_inputs("quantizer_node", tried=2, survived=_dropped(node.counter))
    finally:
        node.destroy_node()


@pytest.mark.reliability
def test_fabmap_node_drops_frames_stamped_far_in_the_future(revisit_data: RevisitData, tmp_path: Path,
                                                            reliability: Recorder) -> None:
    import time

    map_path = tmp_path / "map.npz"
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), map_file=str(map_path)))
    try:
        vid = revisit_data.vocabulary_id
        node._on_words(_words([1, 5, 9], 10, vid))
        ten_years = int(time.time()) + 10 * 365 * 86400  # a clock set to 2036
        node._on_words(_words([2, 3], ten_years, vid))
        node._on_words(_words([2, 7], 20, vid))  # later frames are not "out of order" because of it
        assert node.counter.counts["dropped_stamp_in_future"] == 1
        assert node.counter.counts["processed"] == 2 and "dropped_out_of_order" not in node.counter.counts
        reliability.bad_inputs("fabmap_node", tried=1, survived=_dropped(node.counter))
        assert node.close()
    finally:
        node.destroy_node()
    saved = np.load(map_path)["place_stamps_ns"]
    assert saved.max() < 10**9 * 100  # the future stamp is not in the map


def test_fabmap_node_applies_runtime_settings_and_refuses_the_rest(revisit_data: RevisitData) -> None:
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir)))
    try:
        (applied,) = node.set_parameters([Parameter("match_threshold", value=0.5)])
        assert applied.successful
        assert node.recognizer.config.match_threshold == 0.5
        (fixed,) = node.set_parameters([Parameter("p_z_given_e", value=0.5)])
        assert not fixed.successful and "p_z_given_e: read at start-up only" in fixed.reason
        (bad,) = node.set_parameters([Parameter("match_threshold", value=2.0)])
        assert not bad.successful and "match_threshold" in bad.reason
        assert node.recognizer.config.match_threshold == 0.5  # a refused change changes nothing
        assert node.get_parameter("match_threshold").value == 0.5
        assert node.recognizer.config.p_z_given_e == FabMapConfig().p_z_given_e
    finally:
        node.destroy_node()


def test_fabmap_node_warns_about_a_map_made_with_other_settings_and_cleans_killed_saves(
        revisit_data: RevisitData, tmp_path: Path) -> None:
    map_path = tmp_path / "map.npz"
    first = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), map_file=str(map_path)))
    try:
        first._on_words(_words([1, 5, 9], 10, revisit_data.vocabulary_id))
        assert first.close()
    finally:
        first.destroy_node()
    leftover = tmp_path / ".map.npz.k1ll3d.tmp"  # what kill -9 during a save leaves
    leftover.write_bytes(b"half a map")
    unrelated = tmp_path / ".other.npz.x.tmp"
    unrelated.write_bytes(b"not ours")
    second = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), map_file=str(map_path),
                                                    match_threshold=0.3))
    try:
        assert second.recognizer.num_places == 1
        assert not leftover.exists() and unrelated.exists()
        differences = second.recognizer.load_map(map_path)  # what the node logged as a warning at start
        assert differences == {"match_threshold": (FabMapConfig().match_threshold, 0.3)}
    finally:
        second.destroy_node()


def test_fabmap_node_final_save_failure_is_reported(revisit_data: RevisitData, tmp_path: Path) -> None:
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the map's folder should be")
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir),
                                                  map_file=str(blocker / "map.npz"), save_period_s=0.0))
    try:
        node._on_words(_words([1, 5, 9], 10, revisit_data.vocabulary_id))
        assert node.close() is False  # run_nodes turns this into exit code 1
    finally:
        node.destroy_node()


def test_fabmap_node_ignores_future_places_of_an_old_map_for_ordering(revisit_data: RevisitData,
                                                                       tmp_path: Path) -> None:
    """A map saved before future stamps were refused (here: by a node accepting any stamp) holds a place
    stamped in 2036: a restart keeps it but processes the frames after the last trusted place."""
    import time

    map_path = tmp_path / "map.npz"
    vid = revisit_data.vocabulary_id
    old = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), map_file=str(map_path),
                                                 max_future_stamp_s=0.0))
    try:
        old._on_words(_words([1, 5, 9], 10, vid))
        old._on_words(_words([2, 3, 40], int(time.time()) + 10 * 365 * 86400, vid))
        assert old.recognizer.num_places == 2 and old.close()
    finally:
        old.destroy_node()
    restarted = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir),
                                                       map_file=str(map_path)))
    try:
        assert restarted.recognizer.num_places == 2  # the future place is kept
        assert restarted.last_stamp_ns == 10 * 10**9
        restarted._on_words(_words([2, 7, 60], 20, vid))
        assert restarted.counter.counts["processed"] == 1
        assert "dropped_out_of_order" not in restarted.counter.counts
        assert restarted.recognizer.num_places == 3
    finally:
        restarted.destroy_node()


@pytest.mark.reliability
def test_fabmap_node_answers_every_frame_it_drops(revisit_data: RevisitData, tmp_path: Path,
                                                  reliability: Recorder) -> None:
    """After a restart a replay sends the frames already mapped again: each gets a posterior (query_id -1),
    so `aefabmap_replay --lockstep place_posteriors` does not wait its timeout on each; so do malformed ones."""
    map_path = tmp_path / "map.npz"
    vid = revisit_data.vocabulary_id
    frames = [([1, 5, 9], 10), ([2, 7, 60], 11), ([3, 80, 90], 12)]
    first = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), map_file=str(map_path)))
    try:
        for words, sec in frames:
            first._on_words(_words(words, sec, vid))
        assert first.close()
    finally:
        first.destroy_node()
    restarted = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir),
                                                       map_file=str(map_path)))
    try:
        posteriors = Captured(restarted.posterior_publisher)
        for words, sec in frames:  # the replay from the start
            restarted._on_words(_words(words, sec, vid))
        restarted._on_words(_words([3, 400], 13, vid))  # word id out of range: dropped, still answered
        restarted._on_words(_words([4, 8, 70], 14, vid))  # a new frame
        assert restarted.counter.counts["dropped_out_of_order"] == 3
        assert restarted.counter.counts["dropped_DataError"] == 1
        answers = posteriors.messages
        assert [a.header.stamp.sec for a in answers] == [10, 11, 12, 13, 14]
        assert [a.query_id for a in answers] == [-1, -1, -1, -1, 3]
        assert all(a.assigned_place_id == -1 and len(a.place_ids) == 0 and np.isnan(a.new_place_probability)
                   for a in answers[:4])
        assert answers[4].assigned_place_id >= 0
        reliability.bad_inputs("fabmap_node", tried=4, survived=_dropped(restarted.counter))
    finally:
        restarted.destroy_node()


@pytest.mark.reliability
def test_quantizer_and_verifier_nodes_refuse_huge_finite_descriptors(revisit_data: RevisitData,
                                                                     reliability: Recorder) -> None:
    """3e38 is finite but no SIFT value (0-255): refused with a clear error, counted, the next frame processed."""
    features = _features_of(revisit_data)
    huge = copy.deepcopy(features)
    values = np.asarray(huge.binary_descriptors, dtype=np.float32).copy()
    values[7] = 3e38
    huge.binary_descriptors = np.zeros(0, np.uint8)
    huge.float_descriptors = values
    quantizer = _in_order_quantizer(revisit_data)
    try:
        words_out = Captured(quantizer.publisher)
        quantizer._on_features(huge)
        assert quantizer.counter.counts["dropped_bad_features"] == 1 and not words_out.messages
        quantizer._on_features(features)
        assert len(words_out.messages) == 1
        reliability.bad_inputs("quantizer_node", tried=1, survived=_dropped(quantizer.counter))
    finally:
        quantizer.destroy_node()
    verifier = VerifierNode()
    try:
        verifier._on_features(huge)
        assert verifier.counter.counts["dropped_bad_features"] == 1
        assert stamp_to_ns(huge.header.stamp) not in verifier.store
        features.header.stamp = Time(sec=77)
        verifier._on_features(features)  # alive: the next frame is stored
        assert 77 * 10**9 in verifier.store
        reliability.bad_inputs("verifier_node", tried=1, survived=_dropped(verifier.counter))
    finally:
        verifier.destroy_node()


def test_fabmap_node_answers_a_frame_once_when_publishing_its_candidate_fails(
        revisit_data: RevisitData, monkeypatch: pytest.MonkeyPatch) -> None:
    """An unexpected exception after the posterior went out is counted; the frame is not answered twice
    (a lockstep replay would take the second answer for the next image's)."""
    import aefabmap_ros.nodes.fabmap_node as fabmap_module

    def failing(*_args: Any) -> Any:
        raise RuntimeError("publisher gone")

    monkeypatch.setattr(fabmap_module, "recognition_to_loop_closure", failing)
    node = FabMapNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir)))
    try:
        posteriors = Captured(node.posterior_publisher)
        node._on_words(_words([1, 5, 9], 10, revisit_data.vocabulary_id))
        assert node.counter.counts["dropped_RuntimeError"] == 1
        assert [p.query_id for p in posteriors.messages] == [0]  # one answer, the real one
        assert node.map_saver.unsaved_changes  # the place it made is saved at the next period
    finally:
        node.destroy_node()
