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
from test.reliability import Recorder  # noqa: E402
from test.revisit_fixture import RevisitData  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]


class Captured:
    """Replaces a publisher's publish() to keep what the node sends."""

    def __init__(self, publisher: Any) -> None:
        self.messages: list[Any] = []
        publisher.publish = self.messages.append


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


def test_quantizer_node_caps_torch_threads_from_its_parameter(revisit_data: RevisitData) -> None:
    import torch

    before = torch.get_num_threads()
    try:
        node = QuantizerNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), torch_threads=1))
        node.destroy_node()
        assert torch.get_num_threads() == 1
        with pytest.raises(ConfigError, match="torch_threads=-1"):
            QuantizerNode(parameter_overrides=_params(model_dir=str(revisit_data.model_dir), torch_threads=-1))
    finally:
        torch.set_num_threads(before)


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


def _closure(query_sec: int, place_sec: int, query_id: int) -> Any:
    closure = msg.LoopClosure(query_id=query_id, matched_place_id=place_sec, probability=0.995)
    closure.header.stamp = Time(sec=query_sec)
    closure.matched_stamp = Time(sec=place_sec)
    return closure


def test_verifier_node_passes_true_closures_and_holds_back_the_rest() -> None:
    from test.verification.test_geometric import _two_views

    query, place, _ = _two_views(seed=21)
    _, unrelated, _ = _two_views(seed=22)
    # No re-ranking, no loop tracking: no posteriors. No odometry gate: no odometry.
    node = VerifierNode(parameter_overrides=_params(max_pending=1, candidates=1, track_seconds=0.0,
                                                    odometry_gate=False))
    try:
        assert node.publisher.topic_name == "/loop_closures"
        assert [s.topic_name for s in node.subscriptions] == ["/aefabmap/features", "/loop_closure_candidates",
                                                              "/camera_info"]
        verified = Captured(node.publisher)
        for sec, features in ((1, place), (2, unrelated), (3, query)):
            node._on_features(_features_message(features, sec))
        node._on_loop_closure(_closure(3, 1, query_id=10))  # a true second view: republished
        node._on_loop_closure(_closure(3, 2, query_id=11))  # unrelated place: rejected
        node._on_loop_closure(_closure(3, 99, query_id=12))  # place never seen
        node._on_loop_closure(_closure(5, 1, query_id=13))  # query features not there yet: waits
        node._on_loop_closure(_closure(6, 1, query_id=14))  # pushes the waiting one out (max_pending 1)
        node._on_features(_features_message(query, 6))  # query 14's features arrive: verified now
        broken = _features_message(query, 7)
        broken.x = broken.x[:-1]
        node._on_features(broken)
        assert [m.query_id for m in verified.messages] == [10, 14]
        assert all(m.inliers >= 100 for m in verified.messages)  # 120 shared scene points
        counts = node.counter.counts
        assert counts["accepted"] == 2 and counts["rejected"] == 1
        assert counts["dropped_place_features_unknown"] == 1
        assert counts["dropped_query_features_never_came"] == 1
        assert counts["dropped_bad_features"] == 1
        assert len(node.store) == 4 and not node.pending
        node.close()
    finally:
        node.destroy_node()


def _camera_info() -> Any:
    from sensor_msgs.msg import CameraInfo

    from test.verification.test_geometric import FOCAL, HEIGHT, WIDTH

    return CameraInfo(width=WIDTH, height=HEIGHT, k=[FOCAL, 0.0, WIDTH / 2, 0.0, FOCAL, HEIGHT / 2, 0.0, 0.0, 1.0],
                      d=[0.0] * 5, distortion_model="plumb_bob")


def _place_depth_image(sec: int) -> Image:
    """32FC1 depth of _two_views(seed=21)'s place ("second") camera at its shared keypoints, NaN elsewhere."""
    from test.verification.test_geometric import FOCAL, HEIGHT, WIDTH, _rotation_y

    rng = np.random.default_rng(21)  # the same draws as _two_views(seed=21) makes first
    points = np.column_stack([rng.uniform(-4, 4, 120), rng.uniform(-3, 3, 120), rng.uniform(5, 15, 120)])
    camera = points @ _rotation_y(0.15).T + np.array([0.8, 0.1, 0.3])
    pixels = np.stack([FOCAL * camera[:, 0] / camera[:, 2] + WIDTH / 2,
                       FOCAL * camera[:, 1] / camera[:, 2] + HEIGHT / 2], axis=1)
    depth = np.full((HEIGHT, WIDTH), np.nan, dtype=np.float32)
    columns, rows = np.rint(pixels[:, 0]).astype(int), np.rint(pixels[:, 1]).astype(int)
    inside = (columns >= 1) & (rows >= 1) & (columns < WIDTH - 1) & (rows < HEIGHT - 1)
    for row, column, z in zip(rows[inside], columns[inside], camera[inside, 2], strict=True):
        depth[row - 1:row + 2, column - 1:column + 2] = z  # keypoints are ~0.3 px noisy: cover the neighbours
    return _image(depth.tobytes(), "32FC1", HEIGHT, WIDTH, WIDTH * 4, sec=sec)


def test_verifier_node_attaches_the_relative_pose() -> None:
    """Without camera_info: verified, no pose (flagged); with it: the essential matrix's pose; with depth: metric."""
    from scipy.spatial.transform import Rotation

    from test.verification.test_geometric import _rotation_y, _two_views

    query, place, _ = _two_views(seed=21)
    # _two_views: place points = R (query points) + t, so the place camera in the query frame is (R^T, -R^T t).
    rotation, translation = _rotation_y(0.15), np.array([0.8, 0.1, 0.3])
    true_rotation, true_translation = rotation.T, -rotation.T @ translation

    def pose_of(closure: Any) -> tuple[float, float, np.ndarray]:
        q = closure.pose.orientation
        estimated = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        rotation_error = np.degrees(np.linalg.norm(Rotation.from_matrix(estimated @ true_rotation.T).as_rotvec()))
        t = np.array([closure.pose.position.x, closure.pose.position.y, closure.pose.position.z])
        cosine = t @ true_translation / (np.linalg.norm(t) * np.linalg.norm(true_translation))
        return float(rotation_error), float(np.degrees(np.arccos(min(cosine, 1.0)))), t

    for depth_topic in ("", "depth"):
        node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0, depth_topic=depth_topic))
        try:
            verified = Captured(node.publisher)
            node._on_features(_features_message(place, 1))
            node._on_features(_features_message(query, 3))
            node._on_loop_closure(_closure(3, 1, query_id=10))  # no camera_info yet
            node._on_camera_info(_camera_info())
            if depth_topic:
                node._on_depth(_place_depth_image(1))
            node._on_loop_closure(_closure(3, 1, query_id=11))
            first, second = verified.messages
            assert not first.pose_available and first.pose_status == msg.LoopClosure.POSE_NO_CAMERA_INFO
            assert second.pose_available and second.pose_status == msg.LoopClosure.POSE_OK
            rotation_error, direction_error, t = pose_of(second)
            assert rotation_error <= 1.0 and direction_error <= 3.0
            assert second.translation_metric == bool(depth_topic)
            if depth_topic:
                assert np.linalg.norm(t - true_translation) <= 0.05
            else:
                assert np.linalg.norm(t) == pytest.approx(1.0)
            assert node.counter.counts["pose_no_camera_info"] == 1 and node.counter.counts["pose_ok"] == 1
        finally:
            node.destroy_node()


def _keypoint_depth_image(features: Any, depths: np.ndarray, sec: int) -> Image:
    """32FC1 depth holding each keypoint's depth around its pixel, NaN elsewhere."""
    from test.verification.test_geometric import HEIGHT, WIDTH

    image = np.full((HEIGHT, WIDTH), np.nan, dtype=np.float32)
    for (x, y), z in zip(np.rint(features.keypoints[:, :2]).astype(int), depths, strict=True):
        image[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2] = z  # keypoints are ~0.3 px noisy: cover the neighbours
    return _image(image.tobytes(), "32FC1", HEIGHT, WIDTH, WIDTH * 4, sec=sec)


def test_verifier_node_accepts_a_revisit_from_further_back_by_the_metric_test_with_depth() -> None:
    """40 matches among 340 keypoints: refused by the epipolar test; with depth images and camera_info the
    metric test accepts it (one motion, overlapping views), and the closure carries that metric pose.

    The scene is scattered points, not surfaces: its depth images hold depth at the keypoints only, so the
    covisibility test (the depth images' grids, kept by the node) finds nothing of the query's surface on the
    place's and refuses the pair; with that test off the keypoints decide."""
    from test.verification.test_metric import _scene

    scene = _scene(seed=3, shared=40, query_inside=300, query_outside=0, place_only=300)
    for depth_topic, covisibility in (("", 0.3), ("depth", 0.3), ("depth", 0.0)):
        node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0, odometry_gate=False,
                                                        depth_topic=depth_topic,
                                                        metric_min_covisibility=covisibility))
        try:
            verified = Captured(node.publisher)
            node._on_camera_info(_camera_info())
            if depth_topic:
                node._on_depth(_keypoint_depth_image(scene.place, scene.depths.place, sec=1))
                node._on_depth(_keypoint_depth_image(scene.query, scene.depths.query, sec=3))
            node._on_features(_features_message(scene.place, 1))
            node._on_features(_features_message(scene.query, 3))
            node._on_loop_closure(_closure(3, 1, query_id=10))
            if not depth_topic or covisibility:
                assert not verified.messages and node.counter.counts["rejected"] == 1
                assert "metric_test_accepted" not in node.counter.counts
                continue
            [closure] = verified.messages
            assert node.counter.counts["metric_test_accepted"] == 1 and closure.inliers < 0.12 * 340
            assert closure.pose_available and closure.translation_metric
            position = np.array([closure.pose.position.x, closure.pose.position.y, closure.pose.position.z])
            assert np.linalg.norm(position - scene.pose.translation) <= 0.1  # 8 m back, to 10 cm
        finally:
            node.destroy_node()


def test_verifier_node_keeps_metric_poses_across_a_restart(tmp_path: Path) -> None:
    """The place's keypoint depths are saved with the feature store: after a restart (no new depth image of
    the place) its closures still get a metric pose; without the depth files they would be monocular."""
    from test.verification.test_geometric import _two_views

    query, place, _ = _two_views(seed=21)
    settings = {"candidates": 1, "track_seconds": 0.0, "depth_topic": "depth", "store_dir": str(tmp_path)}
    before = VerifierNode(parameter_overrides=_params(**settings))
    try:
        before._on_features(_features_message(place, 1))
        before._on_depth(_place_depth_image(1))
        assert before.close()
    finally:
        before.destroy_node()
    assert list(tmp_path.glob("depth-*.npz"))
    after = VerifierNode(parameter_overrides=_params(**settings))
    try:
        assert len(after.store) == 1 and after.depths is not None and 1_000_000_000 in after.depths
        verified = Captured(after.publisher)
        after._on_camera_info(_camera_info())
        after._on_features(_features_message(query, 3))
        after._on_loop_closure(_closure(3, 1, query_id=10))
        (closure,) = verified.messages
        assert closure.pose_available and closure.translation_metric
        position = closure.pose.position
        assert np.linalg.norm([position.x, position.y, position.z]) == pytest.approx(
            np.linalg.norm([0.8, 0.1, 0.3]), abs=0.05)
    finally:
        after.destroy_node()


def _posterior(query_sec: int, place_secs: list[int], candidate: bool = True) -> Any:
    """fabmap_node's posterior of a query (``candidate``: it also published a loop-closure candidate)."""
    posterior = msg.PlacePosterior(place_ids=place_secs, probabilities=[0.9 / 2**k for k in range(len(place_secs))],
                                   log_likelihoods=[-float(k) for k in range(len(place_secs))],
                                   loop_closure_candidate=candidate)
    posterior.header.stamp = Time(sec=query_sec)
    posterior.place_stamps = [Time(sec=sec) for sec in place_secs]
    return posterior


def _weaker_view(features: Any, shared: int, keep: int) -> Any:
    """The same view with only ``keep`` of its ``shared`` scene points (its clutter kept): less overlap."""
    from aefabmap_ros.features.extraction import Features as CoreFeatures

    rows = np.r_[0:keep, shared:len(features)]
    return CoreFeatures(features.keypoints[rows], features.descriptors[rows], features.descriptor_type)


def test_verifier_node_moves_a_closure_to_the_best_verified_candidate() -> None:
    from test.verification.test_geometric import _two_views

    query, place, shared = _two_views(seed=24)
    _, unrelated, _ = _two_views(seed=25)
    node = VerifierNode(parameter_overrides=_params(max_pending=2))  # candidates: 5, re-ranking
    try:
        verified = Captured(node.publisher)
        for sec, features in ((1, _weaker_view(place, shared, 35)), (2, unrelated), (3, place), (4, query)):
            node._on_features(_features_message(features, sec))
        # FAB-MAP matched place 1 (a view sharing 35 points); the posterior also ranks 2 and 3.
        node._on_loop_closure(_closure(4, 1, query_id=40))
        assert not verified.messages and len(node.pending) == 1  # waits for the query's posterior
        node._on_posterior(_posterior(4, [1, 2, 3]))
        (moved,) = verified.messages
        assert (moved.query_id, moved.matched_place_id, moved.matched_stamp.sec) == (40, 3, 3)
        assert moved.inliers >= 100 and moved.probability == 0.995  # the detection's confidence is kept
        # A rejected matched place rejects the closure, even when a lower candidate would pass.
        node._on_posterior(_posterior(4, [2, 3]))
        node._on_loop_closure(_closure(4, 2, query_id=41))
        # Posteriors that never come: the closure is dropped once max_pending newer ones wait.
        for query_sec in (5, 6, 7):
            node._on_features(_features_message(query, query_sec))
            node._on_loop_closure(_closure(query_sec, 3, query_id=50 + query_sec))
        assert len(verified.messages) == 1
        counts = node.counter.counts
        assert counts["accepted"] == 1 and counts["moved_to_better_verified_place"] == 1 and counts["rejected"] == 1
        assert counts["dropped_query_posterior_never_came"] == 1 and len(node.pending) == 2
    finally:
        node.destroy_node()


@pytest.mark.parametrize("max_lag_s", [0.25, 0.0])
def test_a_verifier_behind_the_camera_checks_the_detection_only_and_waits_with_tracking(max_lag_s: float) -> None:
    """Features sent 10 s ago: past max_lag_s the closure is decided by its detection (FAB-MAP's place 1, not the
    better view 3 re-ranking finds) and tracking waits; max_lag_s 0 (a lockstep replay) re-ranks however late."""
    import time

    from test.verification.test_geometric import _two_views

    query, place, shared = _two_views(seed=24)
    _, unrelated, _ = _two_views(seed=25)
    node = VerifierNode(parameter_overrides=_params(max_lag_s=max_lag_s, track_seconds=5.0))
    try:
        verified = Captured(node.publisher)
        long_ago_ns = time.time_ns() - 10_000_000_000
        for sec, features in ((1, _weaker_view(place, shared, 35)), (2, unrelated), (3, place), (4, query),
                              (5, query)):
            node._on_features(_features_message(features, sec), long_ago_ns)
        node._on_loop_closure(_closure(4, 1, query_id=40))
        node._on_posterior(_posterior(4, [1, 2, 3]))
        node._on_posterior(_posterior(5, [3, 1], candidate=False))  # a frame loop tracking would verify
        counts = node.counter.counts
        if max_lag_s:
            assert [(m.query_id, m.matched_place_id) for m in verified.messages] == [(40, 1)]
            assert counts["reranking_cut_short_behind"] == 1 and counts["tracking_skipped_behind"] == 1
        else:
            assert [(m.query_id, m.matched_place_id) for m in verified.messages] == [(40, 3), (0, 3)]
            assert "reranking_cut_short_behind" not in counts and "tracking_skipped_behind" not in counts
    finally:
        node.destroy_node()


def test_verifier_node_tracks_a_verified_loop_through_frames_without_a_candidate() -> None:
    from test.verification.test_geometric import _two_views

    query, place, _ = _two_views(seed=26)
    _, unrelated, _ = _two_views(seed=27)
    node = VerifierNode(parameter_overrides=_params(track_seconds=2.0, track_island_seconds=3.0))
    try:
        verified = Captured(node.publisher)
        for sec, features in ((1, place), (2, unrelated), (9, unrelated), (10, query), (11, query), (13, query),
                              (20, query)):
            node._on_features(_features_message(features, sec))
        node._on_posterior(_posterior(11, [2, 1], candidate=False))  # no verified loop yet: nothing to track
        node._on_loop_closure(_closure(10, 1, query_id=100))
        node._on_posterior(_posterior(10, [1, 2]))  # the detection, verified: the track starts
        node._on_posterior(_posterior(11, [2, 9, 1], candidate=False))  # 1 s later, no candidate of its own
        # 2 s after that, a detection of the unrelated place fails; the frame still continues the loop.
        node._on_loop_closure(_closure(13, 2, query_id=102))
        node._on_posterior(_posterior(13, [2, 1]))
        node._on_posterior(_posterior(20, [1], candidate=False))  # 7 s after the last verified closure: over
        closures = [(m.query_id, m.header.stamp.sec, m.matched_place_id, m.matched_stamp.sec)
                    for m in verified.messages]
        # Place 9 is 8 s from the tracked place 1 in map time: not a tracking candidate (only 2 and 1 are;
        # 2 fails geometry). The tracked closures carry their place's own posterior, not a detection's.
        assert closures == [(100, 10, 1, 1), (0, 11, 1, 1), (0, 13, 1, 1)]
        assert [m.probability for m in verified.messages] == [0.995, 0.9 / 4, 0.9 / 2]
        assert all(m.inliers >= 100 for m in verified.messages)
        counts = node.counter.counts
        assert counts["accepted"] == 1 and counts["accepted_by_tracking"] == 2 and counts["rejected"] == 1
        assert not node.posteriors and not node.pending  # every frame decided once
    finally:
        node.destroy_node()


def test_verifier_node_tracks_a_loop_through_the_stored_frames_next_to_the_verified_place() -> None:
    from test.verification.test_geometric import _two_views

    query_a, place_a, _ = _two_views(seed=26)
    query_b, place_b, _ = _two_views(seed=28)
    _, unrelated, _ = _two_views(seed=27)
    node = VerifierNode(parameter_overrides=_params(track_seconds=2.0, track_island_seconds=3.0, track_frames=5,
                                                    track_min_age_seconds=5.0))
    try:
        verified = Captured(node.publisher)
        # The map: scene A at 1 s (place 1), scene B at 2 s (a frame that joined place 1), at 7 s scene B
        # again (too recent for a query at 11 s), an unrelated place at 9 s.
        for sec, features, place_id in ((1, place_a, 1), (2, place_b, 1), (7, place_b, 4), (9, unrelated, 9)):
            node._on_features(_features_message(features, sec))
            posterior = _posterior(sec, [], candidate=False)
            posterior.current_place_id = place_id
            node._on_posterior(posterior)
        for sec, features in ((10, query_a), (11, query_b)):
            node._on_features(_features_message(features, sec))
        node._on_loop_closure(_closure(10, 1, query_id=100))
        node._on_posterior(_posterior(10, [1, 9]))  # verified: the track starts at place 1 (1 s)
        # 11 s sees scene B, but FAB-MAP ranks only the unrelated place, 8 s from the track: the stored frames
        # nearest 1 s and at least 5 s old are verified next (1 s fails, 2 s passes; 7 s is too recent).
        node._on_posterior(_posterior(11, [9], candidate=False))
        (tracked,) = verified.messages[1:]
        assert (tracked.header.stamp.sec, tracked.matched_stamp.sec, tracked.matched_place_id) == (11, 2, 1)
        assert tracked.probability == 0.0 and np.isnan(tracked.log_likelihood) and tracked.inliers >= 100
        assert node.counter.counts["accepted_by_tracking"] == 1
    finally:
        node.destroy_node()
    off = VerifierNode(parameter_overrides=_params(track_seconds=2.0, track_frames=0))
    try:
        verified = Captured(off.publisher)
        for sec, features in ((1, place_a), (2, place_b), (10, query_a), (11, query_b)):
            off._on_features(_features_message(features, sec))
            off._on_posterior(_posterior(sec, [], candidate=False))
        off._on_loop_closure(_closure(10, 1, query_id=100))
        off._on_posterior(_posterior(10, [1]))
        off._on_posterior(_posterior(11, [], candidate=False))
        assert len(verified.messages) == 1 and "accepted_by_tracking" not in off.counter.counts
    finally:
        off.destroy_node()


def _odometry(sec: int, pose: Any) -> Any:
    """nav_msgs/Odometry of the camera (its own base frame) at ``sec``; ``pose`` a gtsam Pose3."""
    from nav_msgs.msg import Odometry

    from aefabmap_ros.nodes.pose_graph_node import gtsam_to_pose

    message = Odometry()
    message.header.stamp = Time(sec=sec)
    message.pose.pose = gtsam_to_pose(pose)
    return message


def test_verifier_node_refuses_a_closure_that_odometry_contradicts() -> None:
    import gtsam

    from test.verification.test_geometric import _rotation_y, _two_views

    query, place, _ = _two_views(seed=21)
    # _two_views' place camera sees X_place = R X_query + t: in the query camera's frame it is at (R^T, -R^T t).
    rotation, translation = _rotation_y(0.15), np.array([0.8, 0.1, 0.3])
    place_in_query = gtsam.Pose3(gtsam.Rot3(rotation.T), -rotation.T @ translation)
    aliased = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([20.0, 0.0, 0.0]))  # another corner, 20 m away
    for odometry_at_place, published in ((place_in_query, True), (aliased, False)):
        node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0))
        try:
            verified = Captured(node.publisher)
            node._on_camera_info(_camera_info())
            for sec, features in ((0, place), (1, place), (3, query), (5, query)):
                node._on_features(_features_message(features, sec))
            node._on_loop_closure(_closure(3, 1, query_id=30))  # no odometry yet: the gate is not active
            for sec, pose in ((1, odometry_at_place), (2, odometry_at_place), (3, gtsam.Pose3())):
                node._on_odometry(_odometry(sec, pose))
            node._on_loop_closure(_closure(3, 1, query_id=31))
            node._on_loop_closure(_closure(5, 1, query_id=50))  # odometry has not reached 5 s yet: it waits
            assert [m.query_id for m in verified.messages] == ([30, 31] if published else [30])
            assert [m.query_id for m in node.awaiting_odometry] == [50]
            for sec in (4, 5):  # the robot stands still at the query's pose
                node._on_odometry(_odometry(sec, gtsam.Pose3()))
            assert [m.query_id for m in verified.messages] == ([30, 31, 50] if published else [30])
            assert not node.awaiting_odometry
            # Place 0 s: mapped before the odometry began (a reloaded map); odometry cannot judge it, it passes.
            node._on_loop_closure(_closure(3, 0, query_id=32))
            assert verified.messages[-1].query_id == 32
            counts = node.counter.counts
            assert counts["accepted"] == 4 and counts["unchecked_place_before_odometry"] == 1
            assert counts.get("dropped_inconsistent_with_odometry", 0) == (0 if published else 2)
        finally:
            node.destroy_node()


def test_verifier_node_refuses_bad_parameters() -> None:
    with pytest.raises(ConfigError, match="min_inliers"):
        VerifierNode(parameter_overrides=_params(min_inliers=3))
    with pytest.raises(ConfigError, match="max_stored_frames"):
        VerifierNode(parameter_overrides=_params(max_stored_frames=0))


@pytest.mark.reliability
def test_verifier_node_keeps_its_store_across_a_restart(tmp_path: Path, reliability: Recorder) -> None:
    from test.verification.test_geometric import _two_views

    query, place, _ = _two_views(seed=23)
    store_dir = tmp_path / "map.features"
    first = VerifierNode(parameter_overrides=_params(store_dir=str(store_dir), save_period_s=0.0))
    try:
        first._on_features(_features_message(place, 1))
        first.close()  # saves on shutdown
    finally:
        first.destroy_node()
    assert len(list(store_dir.glob("chunk-*.npz"))) == 1
    second = VerifierNode(parameter_overrides=_params(store_dir=str(store_dir)))
    try:
        verified = Captured(second.publisher)
        assert 1_000_000_000 in second.store
        second._on_features(_features_message(query, 2))
        second._on_posterior(_posterior(2, [1]))
        second._on_loop_closure(_closure(2, 1, query_id=30))  # its place was seen before the restart
        assert [m.query_id for m in verified.messages] == [30]
    finally:
        second.destroy_node()
    chunk = next(store_dir.glob("chunk-*.npz"))
    chunk.write_bytes(b"corrupt")
    with pytest.raises(ModelError, match="cannot read feature store chunk"):
        VerifierNode(parameter_overrides=_params(store_dir=str(store_dir)))
    assert chunk.read_bytes() == b"corrupt"  # refused, not overwritten
    # Refused at start with the file left as it was; its frames are unreadable, nothing else is lost.
    reliability.fault("corrupt feature store chunk at start (verifier)", injected=1, survived=1, places_lost=0)


@pytest.mark.parametrize("timeline_kept", [True, False])
def test_verifier_node_tracks_into_frames_stored_before_a_restart(tmp_path: Path, timeline_kept: bool) -> None:
    from test.verification.test_geometric import _two_views

    query_a, place_a, _ = _two_views(seed=26)
    query_b, place_b, _ = _two_views(seed=28)
    _, unrelated, _ = _two_views(seed=27)
    tracking = {"track_seconds": 2.0, "track_island_seconds": 3.0, "track_frames": 5, "track_min_age_seconds": 5.0}
    store_dir = tmp_path / "store"
    first = VerifierNode(parameter_overrides=_params(store_dir=str(store_dir), save_period_s=0.0, **tracking))
    try:  # the map before the restart: scene A at 1 s and scene B at 2 s (both place 1), unrelated at 9 s
        for sec, features, place_id in ((1, place_a, 1), (2, place_b, 1), (9, unrelated, 9)):
            first._on_features(_features_message(features, sec))
            posterior = _posterior(sec, [], candidate=False)
            posterior.current_place_id = place_id
            first._on_posterior(posterior)
        first.close()  # saves on shutdown
    finally:
        first.destroy_node()
    assert len(list(store_dir.glob("timeline-*.npz"))) == 1
    if not timeline_kept:  # what a restart was before the timeline was saved: the features alone
        for chunk in store_dir.glob("timeline-*.npz"):
            chunk.unlink()
    second = VerifierNode(parameter_overrides=_params(store_dir=str(store_dir), **tracking))
    try:
        verified = Captured(second.publisher)
        for sec, features in ((10, query_a), (11, query_b)):
            second._on_features(_features_message(features, sec))
        second._on_loop_closure(_closure(10, 1, query_id=100))
        second._on_posterior(_posterior(10, [1, 9]))  # verified: the track starts at place 1 (1 s)
        # 11 s sees scene B; FAB-MAP ranks only the unrelated place: the stored frame at 2 s is found by its
        # place in the reloaded timeline, as it would have been without the restart.
        second._on_posterior(_posterior(11, [9], candidate=False))
        tracked = [(m.header.stamp.sec, m.matched_stamp.sec, m.matched_place_id) for m in verified.messages[1:]]
        assert tracked == ([(11, 2, 1)] if timeline_kept else [])
    finally:
        second.destroy_node()


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


def test_verifier_node_applies_runtime_settings_and_refuses_the_rest() -> None:
    node = VerifierNode()
    try:
        (applied,) = node.set_parameters([Parameter("min_inliers", value=40)])
        assert applied.successful and node.config.min_inliers == 40
        (fixed,) = node.set_parameters([Parameter("max_stored_frames", value=5)])
        assert not fixed.successful and "read at start-up only" in fixed.reason
        assert node.store.max_frames == 20000
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


@pytest.mark.reliability
def test_verifier_node_survives_descriptors_of_another_length(tmp_path: Path, reliability: Recorder) -> None:
    """A 64-d frame among 128-d ones: refused by the store (so it cannot poison a save), and a closure
    pairing the two kinds is dropped as unverifiable, not a cv2.error that kills the node."""
    from aefabmap_ros.features.extraction import Features as CoreFeatures
    from test.verification.test_geometric import _two_views

    query, place, _ = _two_views(seed=31)
    short = CoreFeatures(query.keypoints, np.ascontiguousarray(query.descriptors[:, :64]), query.descriptor_type)
    store_dir = tmp_path / "store"
    node = VerifierNode(parameter_overrides=_params(candidates=1, track_seconds=0.0, store_dir=str(store_dir),
                                                    save_period_s=0.0))
    try:
        verified = Captured(node.publisher)
        node._on_features(_features_message(place, 1))
        node._on_features(_features_message(short, 2))
        node._on_features(_features_message(query, 3))
        node._on_loop_closure(_closure(3, 1, query_id=5))
        assert [m.query_id for m in verified.messages] == [5]
        assert node.counter.counts["dropped_bad_features"] == 1 and len(node.store) == 2
        reliability.bad_inputs("verifier_node", tried=1, survived=_dropped(node.counter))
        assert node.close()  # the store saves
    finally:
        node.destroy_node()
    assert len(list(store_dir.glob("chunk-*.npz"))) == 1


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
