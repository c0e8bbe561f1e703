"""Malformed and extreme messages of every type the nodes subscribe to, each with the drop names it must get.

A kind is a way a message can be wrong (NaN, inf, zero and huge sizes, arrays of mismatched lengths, unknown
encodings, stamps out of order or beyond a ROS time); hypothesis draws the values that make it so. Each
builder starts from a valid message and breaks one thing, so the drop is the kind's and no other's.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from aefabmap_msgs.msg import BagOfWords, Features, LoopClosure, PlacePosterior
from builtin_interfaces.msg import Time
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

INT32_MAX = 2**31 - 1
INT32_MIN = -(2**31)
UINT32_MAX = 2**32 - 1
NOT_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])
# nanosec beyond a second: a Time's field takes up to 2^32 - 1, no ROS time has them.
BAD_NANOSEC = st.integers(1_000_000_000, UINT32_MAX)


@dataclass
class Stamps:
    """The valid frames' clock: each valid message takes the next second after every stamp given out, and a
    malformed one a second of its own (a copy of a frame's stamp would be dropped as a copy, not for its fault)."""

    sec: int  # the last valid message's

    def __post_init__(self) -> None:
        self._given = self.sec

    def next(self) -> Time:
        self._given += 1
        self.sec = self._given
        return Time(sec=self.sec)

    def fresh(self) -> Time:
        self._given += 1
        return Time(sec=self._given)

    def last(self) -> Time:
        return Time(sec=self.sec)


Builder = Callable[[st.DataObject, Stamps], Any]


@dataclass(frozen=True)
class Kind:
    name: str
    topic: str
    expected: frozenset[str]  # the drop names (``dropped_<name>``) any of which counts it
    build: Builder


def kind(name: str, topic: str, expected: str | set[str], build: Builder) -> Kind:
    return Kind(name, topic, frozenset({expected} if isinstance(expected, str) else expected), build)


def bad_stamp(data: st.DataObject, stamps: Stamps) -> Time:
    return Time(sec=stamps.fresh().sec, nanosec=data.draw(BAD_NANOSEC, label="nanosec"))


# ----------------------------------------------------------------------------------------- images


def mono8(stamp: Time, height: int = 48, width: int = 64) -> Image:
    image = Image(height=height, width=width, encoding="mono8", step=width,
                  data=np.random.default_rng(stamp.sec).integers(0, 256, height * width, np.uint8).tobytes())
    image.header.stamp = stamp
    return image


def _broken_image(data: st.DataObject, stamps: Stamps, what: str) -> Image:
    image = mono8(stamps.fresh())
    if what == "encoding":
        image.encoding = data.draw(st.sampled_from(["", "yuv420", "16UC3", "jpeg", "MONO8 ", "64FC1"]) | st.text(
            max_size=12).filter(lambda text: text.strip().lower() not in {"mono8", "8uc1", "bgr8", "rgb8"}))
    elif what == "short data":
        image.data = image.data[: data.draw(st.integers(0, len(image.data) - 1), label="bytes")]
    elif what == "zero size":
        image.height, image.width = data.draw(st.sampled_from([(0, 64), (48, 0), (0, 0)]))
    elif what == "step below width":
        image.step = data.draw(st.integers(0, image.width - 1), label="step")
    elif what == "huge size":  # a header claiming gigapixels over a few bytes: refused before decoding
        image.height = data.draw(st.integers(10_000, UINT32_MAX), label="height")
        image.width = data.draw(st.integers(10_000, UINT32_MAX), label="width")
        image.step = image.width
    elif what == "bad stamp":
        image.header.stamp = bad_stamp(data, stamps)
    return image


def _png_chunk(name: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + name + payload + struct.pack(">I", zlib.crc32(name + payload))


def _png_of_side(side: int) -> bytes:
    """A PNG whose header (CRC right) claims ``side`` x ``side`` grey pixels, followed by a few of them: what a
    decompression bomb's first bytes look like."""
    header = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header)
            + _png_chunk(b"IDAT", zlib.compress(b"\0" * (side + 1))))


def _broken_compressed(data: st.DataObject, stamps: Stamps, what: str) -> CompressedImage:
    image = CompressedImage(format=data.draw(st.sampled_from(["jpeg", "png", "", "rgb8; jpeg compressed bgr8"])))
    image.header.stamp = stamps.fresh()
    if what == "garbage":
        image.data = data.draw(st.binary(min_size=0, max_size=64).filter(lambda raw: not raw.startswith(b"\x89PNG")))
    elif what == "png bomb":
        side = data.draw(st.integers(6_000, 60_000), label="side")
        image.data = _png_of_side(side)
    return image


IMAGE_KINDS = [
    kind("image: unsupported encoding", "/image", "bad_image", lambda d, s: _broken_image(d, s, "encoding")),
    kind("image: data shorter than step x height", "/image", "bad_image",
         lambda d, s: _broken_image(d, s, "short data")),
    kind("image: zero height or width", "/image", "bad_image", lambda d, s: _broken_image(d, s, "zero size")),
    kind("image: step below a row", "/image", "bad_image", lambda d, s: _broken_image(d, s, "step below width")),
    kind("image: gigapixel header", "/image", "image_too_large", lambda d, s: _broken_image(d, s, "huge size")),
    kind("image: nanosec beyond a second", "/image", "bad_stamp", lambda d, s: _broken_image(d, s, "bad stamp")),
    kind("compressed: not an image", "/image/compressed", "bad_image",
         lambda d, s: _broken_compressed(d, s, "garbage")),
    kind("compressed: PNG header of a huge image", "/image/compressed", "image_too_large",
         lambda d, s: _broken_compressed(d, s, "png bomb")),
]


# --------------------------------------------------------------------------------------- features

KEYPOINT_FIELDS = ("x", "y", "size", "angle", "response")


def features(stamp: Time, count: int = 40, seed: int = 0) -> Features:
    """Valid SIFT features (their values as bytes, as feature_node sends OpenCV's) of a 64 x 48 image."""
    rng = np.random.default_rng(seed)
    message = Features(descriptor_type="sift", image_width=64, image_height=48, descriptor_length=128)
    message.header.stamp = stamp
    message.x, message.y = rng.uniform(0, 63, count).tolist(), rng.uniform(0, 47, count).tolist()
    message.size, message.angle = rng.uniform(2, 9, count).tolist(), rng.uniform(0, 360, count).tolist()
    message.response = rng.uniform(0.01, 0.1, count).tolist()
    message.binary_descriptors = rng.integers(0, 120, count * 128, np.uint8).tobytes()
    return message


def _broken_features(data: st.DataObject, stamps: Stamps, what: str) -> Features:
    message = features(stamps.fresh(), seed=data.draw(st.integers(0, 9), label="seed"))
    count = len(message.x)
    if what == "keypoint lengths":
        name = data.draw(st.sampled_from(KEYPOINT_FIELDS), label="field")
        values = list(getattr(message, name))
        setattr(message, name, values[:-1] if data.draw(st.booleans()) else [*values, 1.0])
    elif what == "descriptor count":
        raw = bytes(message.binary_descriptors)
        message.binary_descriptors = raw[: data.draw(st.integers(0, len(raw) - 1), label="bytes")]
    elif what == "descriptor length":
        message.descriptor_length = data.draw(st.sampled_from([0, 1, 127, 129, UINT32_MAX]), label="length")
    elif what in ("non-finite descriptors", "huge descriptors"):
        floats = np.full(count * 128, 10.0, np.float32)
        wrong = NOT_FINITE if what == "non-finite descriptors" else st.floats(1e4, 3e38)
        floats[data.draw(st.integers(0, floats.size - 1), label="where")] = data.draw(wrong, label="value")
        message.binary_descriptors, message.float_descriptors = b"", floats.tolist()
    elif what == "non-finite keypoints":
        name = data.draw(st.sampled_from(KEYPOINT_FIELDS), label="field")
        values = list(getattr(message, name))
        values[data.draw(st.integers(0, count - 1))] = data.draw(NOT_FINITE)
        setattr(message, name, values)
    elif what == "type":
        message.descriptor_type = data.draw(st.sampled_from(["orb", "surf", "", "SIFT", "akaze"]), label="type")
    elif what == "bad stamp":
        message.header.stamp = bad_stamp(data, stamps)
    return message


def features_kinds(topic: str, bad: str) -> list[Kind]:
    """The kinds both consumers of features must drop (as ``bad``)."""
    return [kind(f"features: {what}", topic, bad, lambda d, s, what=what: _broken_features(d, s, what))  # type: ignore[misc]
            for what in ("keypoint lengths", "descriptor count", "descriptor length", "non-finite descriptors",
                         "huge descriptors", "non-finite keypoints", "bad stamp")]


QUANTIZER_KINDS = [*features_kinds("/aefabmap/features", "bad_features"),
                   kind("features: another descriptor type", "/aefabmap/features", "wrong_descriptor_type",
                        lambda d, s: _broken_features(d, s, "type"))]


# ---------------------------------------------------------------------------------------- words


def words(stamp: Time, vocabulary_id: str, size: int, word_ids: list[int]) -> BagOfWords:
    message = BagOfWords(vocabulary_id=vocabulary_id, vocabulary_size=size, word_ids=word_ids,
                         counts=[1] * len(word_ids), num_features=len(word_ids))
    message.header.stamp = stamp
    return message


@dataclass(frozen=True)
class Vocabulary:
    vocabulary_id: str
    size: int


def _broken_words(data: st.DataObject, stamps: Stamps, vocabulary: Vocabulary, what: str) -> BagOfWords:
    ids = sorted(data.draw(st.sets(st.integers(0, vocabulary.size - 1), min_size=3, max_size=30), label="ids"))
    message = words(stamps.fresh(), vocabulary.vocabulary_id, vocabulary.size, ids)
    if what == "vocabulary id":
        message.vocabulary_id = data.draw(st.text(max_size=20).filter(lambda text: text != vocabulary.vocabulary_id))
    elif what == "vocabulary size":
        message.vocabulary_size = data.draw(st.sampled_from([0, 1, vocabulary.size + 1, UINT32_MAX]))
    elif what == "counts length":
        message.counts = [1] * data.draw(st.integers(0, 40).filter(lambda n: n != len(ids)), label="counts")
    elif what == "word id beyond":
        message.word_ids = [*ids[:-1], data.draw(st.integers(vocabulary.size, UINT32_MAX), label="id")]
    elif what == "unsorted":
        message.word_ids = ids[::-1] if data.draw(st.booleans()) else ids[:1] + ids  # reversed, or a repeat
        message.counts = [1] * len(message.word_ids)
    elif what == "older stamp":
        message.header.stamp = Time(sec=data.draw(st.sampled_from([INT32_MIN, -1, 0, stamps.sec - 1, stamps.sec])))
    elif what == "future stamp":
        message.header.stamp = Time(sec=data.draw(st.integers(2_100_000_000, INT32_MAX), label="sec"),
                                    nanosec=data.draw(st.integers(0, 999_999_999)))
    elif what == "bad stamp":
        message.header.stamp = bad_stamp(data, stamps)
    return message


def fabmap_kinds(vocabulary: Vocabulary) -> list[Kind]:
    expected = {"vocabulary id": "VocabularyMismatchError", "vocabulary size": "VocabularyMismatchError",
                "counts length": "DataError", "word id beyond": "DataError", "unsorted": "DataError",
                "older stamp": "out_of_order", "future stamp": "stamp_in_future", "bad stamp": "bad_stamp"}
    return [kind(f"words: {what}", "/aefabmap/words", name,
                 lambda d, s, what=what: _broken_words(d, s, vocabulary, what))  # type: ignore[misc]
            for what, name in expected.items()]


# ------------------------------------------------------------------------------------- odometry


def odometry(stamp: Time, x: float = 0.0) -> Odometry:
    message = Odometry()
    message.header.stamp = stamp
    message.pose.pose.position.x = x
    message.pose.pose.orientation.w = 1.0
    return message


def _broken_odometry(data: st.DataObject, stamps: Stamps, what: str) -> Odometry:
    message = odometry(stamps.fresh())
    pose = message.pose.pose
    if what == "non-finite position":
        setattr(pose.position, data.draw(st.sampled_from("xyz")), data.draw(NOT_FINITE))
    elif what == "position beyond the Earth":
        setattr(pose.position, data.draw(st.sampled_from("xyz")), data.draw(st.floats(1e9, 1e300) | st.floats(
            -1e300, -1e9)))
    elif what == "non-finite orientation":
        setattr(pose.orientation, data.draw(st.sampled_from("xyzw")), data.draw(NOT_FINITE))
    elif what == "zero or non-unit quaternion":
        scale = data.draw(st.sampled_from([0.0, 0.5, 1.01, 1e6]), label="norm")
        pose.orientation.w = scale
    elif what == "older stamp":
        message.header.stamp = Time(sec=data.draw(st.sampled_from([INT32_MIN, 0, stamps.sec - 1, stamps.sec])))
    elif what == "future stamp":
        message.header.stamp = Time(sec=data.draw(st.integers(2_100_000_000, INT32_MAX), label="sec"))
    elif what == "bad stamp":
        message.header.stamp = bad_stamp(data, stamps)
    return message


def odometry_kinds(future: bool) -> list[Kind]:
    """``future``: the node refuses odometry stamped far ahead of its clock (else one such message makes
    every later one "out of order")."""
    bad = ["non-finite position", "position beyond the Earth", "non-finite orientation",
           "zero or non-unit quaternion", "bad stamp"]
    kinds = [kind(f"odometry: {what}", "/odom", "bad_odometry",
                  lambda d, s, what=what: _broken_odometry(d, s, what)) for what in bad]  # type: ignore[misc]
    kinds.append(kind("odometry: older stamp", "/odom", "odometry_out_of_order",
                      lambda d, s: _broken_odometry(d, s, "older stamp")))
    if future:
        kinds.append(kind("odometry: stamp at the int32 limit", "/odom", "stamp_in_future",
                          lambda d, s: _broken_odometry(d, s, "future stamp")))
    return kinds


# ------------------------------------------------------------------------------------- closures


def closure(query: Time, place: Time, relative_x: float) -> LoopClosure:
    """A closure whose place camera is ``relative_x`` metres along x in the query camera's frame."""
    message = LoopClosure(query_id=query.sec, matched_place_id=place.sec, probability=0.999, pose_available=True,
                          translation_metric=True, pose_status=LoopClosure.POSE_OK)
    message.header.stamp, message.matched_stamp = query, place
    message.pose.position.x = relative_x
    message.pose.orientation.w = 1.0
    message.pose_covariance = np.diag([1e-4] * 3 + [1e-5] * 3).reshape(36).tolist()
    return message


def _broken_closure(data: st.DataObject, stamps: Stamps, what: str) -> LoopClosure:
    message = closure(stamps.last(), Time(sec=stamps.sec - 1), -1.0)
    if what == "no pose":
        message.pose_available = False
    elif what == "non-finite pose":
        setattr(message.pose.position, data.draw(st.sampled_from("xyz")), data.draw(NOT_FINITE))
    elif what == "zero quaternion":
        message.pose.orientation.w = 0.0
    elif what == "bad covariance":
        values = list(message.pose_covariance)
        values[data.draw(st.integers(0, 35), label="entry")] = data.draw(
            NOT_FINITE | st.floats(-1e3, -1e-2) | st.floats(1e13, 1e300), label="value")
        message.pose_covariance = values
    elif what == "bad stamp":
        field = data.draw(st.sampled_from(["query", "place"]))
        stamp = bad_stamp(data, stamps)
        if field == "query":
            message.header.stamp = stamp
        else:
            message.matched_stamp = stamp
    elif what == "before the odometry":
        message.header.stamp = Time(sec=data.draw(st.sampled_from([INT32_MIN, 0, 1])))
        message.matched_stamp = Time(sec=INT32_MIN)
    elif what == "future stamp":
        message.header.stamp = Time(sec=data.draw(st.integers(2_100_000_000, INT32_MAX), label="sec"))
    return message


POSE_GRAPH_CLOSURE_KINDS = [
    kind("closure: no pose", "/loop_closures", "no_pose", lambda d, s: _broken_closure(d, s, "no pose")),
    kind("closure: non-finite pose", "/loop_closures", "bad_closure_pose",
         lambda d, s: _broken_closure(d, s, "non-finite pose")),
    kind("closure: zero quaternion", "/loop_closures", "bad_closure_pose",
         lambda d, s: _broken_closure(d, s, "zero quaternion")),
    kind("closure: NaN, negative or huge covariance", "/loop_closures", "bad_closure_pose",
         lambda d, s: _broken_closure(d, s, "bad covariance")),
    kind("closure: nanosec beyond a second", "/loop_closures", "bad_closure_stamp",
         lambda d, s: _broken_closure(d, s, "bad stamp")),
    kind("closure: endpoints before the odometry", "/loop_closures", "unknown_stamp",
         lambda d, s: _broken_closure(d, s, "before the odometry")),
    kind("closure: stamp at the int32 limit", "/loop_closures", "stamp_in_future",
         lambda d, s: _broken_closure(d, s, "future stamp")),
]


# ------------------------------------------------------------------------- verifier's other inputs


def camera_info(fx: float = 60.0) -> CameraInfo:
    return CameraInfo(width=64, height=48, k=[fx, 0.0, 32.0, 0.0, fx, 24.0, 0.0, 0.0, 1.0], d=[0.0] * 5,
                      distortion_model="plumb_bob")


def _broken_camera_info(data: st.DataObject, _stamps: Stamps, what: str) -> CameraInfo:
    message = camera_info()
    if what == "K":
        values = list(message.k)
        values[data.draw(st.sampled_from([0, 2, 4, 5, 8]), label="entry")] = data.draw(NOT_FINITE)
        message.k = values
    elif what == "focal length":
        values = list(message.k)
        values[data.draw(st.sampled_from([0, 4]))] = data.draw(st.sampled_from([0.0, -60.0, -1e-9]), label="f")
        message.k = values
    elif what == "distortion":
        message.d = [0.0, data.draw(NOT_FINITE), 0.0, 0.0, 0.0]
    return message


DEPTH_SIZE = (640, 480)  # the verifier test's images' size


def depth(stamp: Time, width: int = DEPTH_SIZE[0], height: int = DEPTH_SIZE[1]) -> Image:
    image = Image(height=height, width=width, encoding="16UC1", step=2 * width,
                  data=np.full(width * height, 2000, np.uint16).tobytes())
    image.header.stamp = stamp
    return image


def _broken_depth(data: st.DataObject, stamps: Stamps, what: str) -> Image:
    image = depth(stamps.fresh())
    if what == "encoding":
        image.encoding = data.draw(st.sampled_from(["mono8", "bgr8", "32FC3", "", "16SC1"]), label="encoding")
    elif what == "short data":
        image.data = bytes(image.data)[: data.draw(st.integers(0, len(image.data) - 1), label="bytes")]
    elif what == "step below width":
        image.step = data.draw(st.integers(0, 2 * image.width - 1), label="step")
    elif what == "other size":
        width, height = data.draw(st.sampled_from([(0, 0), (32, 24), (64, 48), (640, 479)]), label="size")
        image = depth(stamps.fresh(), width, height)
    return image


def posterior(query: Time, place: Time, place_id: int) -> PlacePosterior:
    message = PlacePosterior(query_id=query.sec, assigned_place_id=place_id, current_place_id=query.sec,
                             new_place_probability=0.001, loop_closure_candidate=True, place_ids=[place_id],
                             probabilities=[0.999], log_likelihoods=[-1.0])
    message.header.stamp, message.place_stamps = query, [place]
    return message


def _broken_posterior(data: st.DataObject, stamps: Stamps, what: str) -> PlacePosterior:
    message = posterior(stamps.last(), Time(sec=stamps.sec - 1), stamps.sec - 1)
    if what == "lengths":
        name = data.draw(st.sampled_from(["place_ids", "probabilities", "log_likelihoods", "place_stamps"]))
        setattr(message, name, [] if data.draw(st.booleans()) else list(getattr(message, name)) * 2)
    elif what == "non-finite probability":
        message.probabilities = [data.draw(NOT_FINITE)]
    elif what == "probability outside [0, 1]":
        message.probabilities = [data.draw(st.floats(1.0001, 1e300) | st.floats(-1e300, -1e-9))]
    elif what == "bad stamp":
        if data.draw(st.booleans()):
            message.header.stamp = bad_stamp(data, stamps)
        else:
            message.place_stamps = [bad_stamp(data, stamps)]
    return message


VERIFIER_KINDS = [
    *features_kinds("/aefabmap/features", "bad_features"),
    kind("camera_info: non-finite K", "/camera_info", "bad_camera_info", lambda d, s: _broken_camera_info(d, s, "K")),
    kind("camera_info: zero or negative focal length", "/camera_info", "bad_camera_info",
         lambda d, s: _broken_camera_info(d, s, "focal length")),
    kind("camera_info: non-finite distortion", "/camera_info", "bad_camera_info",
         lambda d, s: _broken_camera_info(d, s, "distortion")),
    kind("depth: not a depth encoding", "/depth", "bad_depth", lambda d, s: _broken_depth(d, s, "encoding")),
    kind("depth: data shorter than step x height", "/depth", "bad_depth",
         lambda d, s: _broken_depth(d, s, "short data")),
    kind("depth: step below a row", "/depth", "bad_depth", lambda d, s: _broken_depth(d, s, "step below width")),
    kind("depth: not the image's size", "/depth", "depth_size_mismatch",
         lambda d, s: _broken_depth(d, s, "other size")),
    kind("posterior: candidate arrays of different lengths", "/place_posteriors", "bad_posterior",
         lambda d, s: _broken_posterior(d, s, "lengths")),
    kind("posterior: non-finite probability", "/place_posteriors", "bad_posterior",
         lambda d, s: _broken_posterior(d, s, "non-finite probability")),
    kind("posterior: probability outside [0, 1]", "/place_posteriors", "bad_posterior",
         lambda d, s: _broken_posterior(d, s, "probability outside [0, 1]")),
    kind("posterior: nanosec beyond a second", "/place_posteriors", "bad_posterior",
         lambda d, s: _broken_posterior(d, s, "bad stamp")),
]


def _broken_candidate(data: st.DataObject, stamps: Stamps, what: str) -> LoopClosure:
    """A candidate between the last two valid frames (both stored by the verifier), broken one way."""
    message = closure(stamps.last(), Time(sec=stamps.sec - 1), 0.0)
    if what == "bad stamp":
        message.matched_stamp = bad_stamp(data, stamps)
    elif what == "itself":
        message.matched_stamp, message.matched_place_id = stamps.last(), stamps.sec
    elif what == "after the query":
        message.header.stamp, message.matched_stamp = Time(sec=stamps.sec - 1), stamps.last()
    elif what == "probability":
        message.probability = data.draw(NOT_FINITE | st.floats(1.0001, 1e300) | st.floats(-1e300, -1e-9))
    return message


def _skipped_frame(data: st.DataObject, stamps: Stamps) -> Any:
    from std_msgs.msg import Header

    return Header(stamp=bad_stamp(data, stamps), frame_id="busy")


# verifier_node's candidates (stamps, order, probability), odometry stamped years ahead (it would make every later
# one "out of order") and skipped-frame stamps, each waited for a little longer (answer_wait_s).
VERIFIER_CANDIDATE_AND_STAMP_KINDS = [
    kind("candidate: nanosec beyond a second", "/loop_closure_candidates", "bad_closure_stamp",
         lambda d, s: _broken_candidate(d, s, "bad stamp")),
    kind("candidate: matched place is the query itself", "/loop_closure_candidates", "bad_candidate",
         lambda d, s: _broken_candidate(d, s, "itself")),
    kind("candidate: matched place after the query", "/loop_closure_candidates", "bad_candidate",
         lambda d, s: _broken_candidate(d, s, "after the query")),
    kind("candidate: probability not in [0, 1]", "/loop_closure_candidates", "bad_candidate",
         lambda d, s: _broken_candidate(d, s, "probability")),
    kind("odometry: stamp at the int32 limit", "/odom", "stamp_in_future",
         lambda d, s: _broken_odometry(d, s, "future stamp")),
    kind("skipped frame: nanosec beyond a second", "/aefabmap/skipped_frames", "bad_stamp", _skipped_frame),
]
