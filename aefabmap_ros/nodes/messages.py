"""Conversions between the pure core's arrays and the ROS messages of the suite.

Sequence fields of rclpy messages are ``array.array``; filling them from raw bytes keeps the
conversion O(bytes) instead of a Python loop per element. Incoming messages are validated here,
so nodes get a ``DataError`` naming what is inconsistent rather than a crash deep in the core.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np
from aefabmap_msgs.msg import BagOfWords, Features, LoopClosure, PlacePosterior
from builtin_interfaces.msg import Time
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header

from aefabmap_ros.errors import DataError, VocabularyMismatchError
from aefabmap_ros.fabmap.recognition import Candidate, Recognition
from aefabmap_ros.fabmap.sessions import Session
from aefabmap_ros.features import extraction as core_features
from aefabmap_ros.io.message_values import covariance_problem, pose_problem, stamp_problem
from aefabmap_ros.verification.relative_pose import PoseOutcome

KEYPOINT_FIELDS = ("x", "y", "size", "angle", "response")


# array.array typecodes of rclpy sequence fields -> the numpy dtype of the same item size.
_TYPECODE_DTYPES = {"f": np.float32, "d": np.float64, "B": np.uint8, "I": np.uint32, "i": np.int32, "q": np.int64}


def _typed_array(typecode: str, values: np.ndarray) -> array.array[Any]:
    result = array.array(typecode)
    result.frombytes(np.ascontiguousarray(values, dtype=_TYPECODE_DTYPES[typecode]).tobytes())
    return result


def time_from_ns(stamp_ns: int) -> Time:
    return Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def header_stamp_problem(header: Any, what: str) -> str | None:
    """Why a message's header stamp is not a ROS time (nanosec beyond a second): stamps order frames and key
    every store, and such a stamp would alias another frame's nanoseconds. None when it is one."""
    return stamp_problem(header.stamp.sec, header.stamp.nanosec, f"{what} stamp")


def copy_header(header: Any) -> Header:
    return Header(stamp=Time(sec=header.stamp.sec, nanosec=header.stamp.nanosec), frame_id=header.frame_id)


# -------------------------------------------------------------------------------------- features


def features_to_message(features: core_features.Features, header: Any, image_size: tuple[int, int]) -> Features:
    """``image_size`` is (width, height) of the source image."""
    keypoints = np.asarray(features.keypoints, dtype=np.float32).reshape(-1, 5)
    descriptors = np.asarray(features.descriptors)
    message = Features()
    message.header = copy_header(header)
    message.descriptor_type = features.descriptor_type
    message.image_width, message.image_height = int(image_size[0]), int(image_size[1])
    for column, name in enumerate(KEYPOINT_FIELDS):
        setattr(message, name, _typed_array("f", keypoints[:, column]))
    message.descriptor_length = core_features.descriptor_length(features.descriptor_type)
    # ORB, and SIFT whose values are integers 0-255 (OpenCV's), cross as bytes: 4x less to send.
    compact = core_features.compact_descriptors(descriptors)
    if compact.dtype == np.uint8:
        message.binary_descriptors = _typed_array("B", compact.reshape(-1))
    else:
        message.float_descriptors = _typed_array("f", compact.reshape(-1))
    return message


def message_to_features(message: Features) -> core_features.Features:
    """Validated features: one length for the keypoint arrays, finite keypoints, descriptors of the declared
    length and range, a stamp that is a ROS time; ``DataError`` naming the first fault otherwise."""
    problem = header_stamp_problem(message.header, "Features")
    if problem is not None:
        raise DataError(problem)
    count = len(message.x)
    if any(len(getattr(message, name)) != count for name in KEYPOINT_FIELDS):
        lengths = {name: len(getattr(message, name)) for name in KEYPOINT_FIELDS}
        raise DataError(f"Features keypoint arrays differ in length: {lengths}")
    length = int(message.descriptor_length)
    is_binary = len(message.binary_descriptors) > 0 or (count > 0 and len(message.float_descriptors) == 0)
    raw = message.binary_descriptors if is_binary else message.float_descriptors
    if length <= 0 or len(raw) != count * length:
        raise DataError(
            f"Features has {count} keypoints but {len(raw)} descriptor values for descriptor_length {length}"
        )
    dtype = np.uint8 if is_binary else np.float32
    # Byte-carried SIFT goes back to float32 (the type's dtype); older float32 messages read as before.
    descriptors = core_features.restore_descriptors(np.frombuffer(raw, dtype=dtype).reshape(count, length),
                                                    str(message.descriptor_type))
    try:
        core_features.check_descriptor_values(descriptors, str(message.descriptor_type))
    except DataError as exc:
        raise DataError(f"Features has {exc}") from exc
    keypoints = np.stack([np.frombuffer(getattr(message, name), dtype=np.float32) for name in KEYPOINT_FIELDS],
                         axis=1) if count else np.zeros((0, 5), np.float32)
    finite = np.isfinite(keypoints)
    if not finite.all():  # geometric verification and the depth lookup index images by them
        row, column = np.argwhere(~finite)[0]
        raise DataError(f"Features keypoint {row} {KEYPOINT_FIELDS[column]} = {keypoints[row, column]} is not finite")
    return core_features.Features(
        keypoints=keypoints, descriptors=descriptors, descriptor_type=str(message.descriptor_type)
    )


# ---------------------------------------------------------------------------------- bag of words


def bag_of_words_to_message(
    header: Any,
    vocabulary_id: str,
    vocabulary_size: int,
    word_ids: np.ndarray,
    counts: np.ndarray,
    keypoint_words: np.ndarray,
) -> BagOfWords:
    message = BagOfWords()
    message.header = copy_header(header)
    message.vocabulary_id = vocabulary_id
    message.vocabulary_size = int(vocabulary_size)
    message.num_features = len(keypoint_words)
    message.word_ids = _typed_array("I", word_ids)
    message.counts = _typed_array("I", counts)
    message.keypoint_words = _typed_array("i", keypoint_words)
    return message


def message_to_word_ids(message: BagOfWords, vocabulary_id: str, vocabulary_size: int) -> np.ndarray:
    """Validated, sorted unique word ids (int64) of a ``BagOfWords`` from our own vocabulary."""
    if message.vocabulary_id != vocabulary_id:
        raise VocabularyMismatchError(
            f"BagOfWords from vocabulary {message.vocabulary_id!r}, but the loaded model is {vocabulary_id!r}"
        )
    if int(message.vocabulary_size) != vocabulary_size:
        raise VocabularyMismatchError(
            f"BagOfWords vocabulary_size {message.vocabulary_size} != model's {vocabulary_size}"
        )
    word_ids = np.frombuffer(message.word_ids, dtype=np.uint32).astype(np.int64)
    if len(message.counts) != word_ids.size:
        raise DataError(f"BagOfWords has {word_ids.size} word ids but {len(message.counts)} counts")
    if word_ids.size and (word_ids.max() >= vocabulary_size):
        raise DataError(f"BagOfWords word id {int(word_ids.max())} >= vocabulary_size {vocabulary_size}")
    if word_ids.size > 1 and np.any(np.diff(word_ids) <= 0):
        raise DataError("BagOfWords word_ids are not sorted and unique")
    return word_ids


# ------------------------------------------------------------------------------------- detection


def _fill_candidates(message: PlacePosterior, candidates: tuple[Candidate, ...]) -> None:
    message.place_ids = _typed_array("q", np.array([c.place_id for c in candidates], dtype=np.int64))
    message.place_stamps = [time_from_ns(c.stamp_ns) for c in candidates]
    message.probabilities = _typed_array("d", np.array([c.probability for c in candidates], dtype=np.float64))
    message.log_likelihoods = _typed_array(
        "d", np.array([c.log_likelihood for c in candidates], dtype=np.float64)
    )
    message.place_sessions = _typed_array("I", np.array([c.session for c in candidates], dtype=np.uint32))
    message.place_robots = [c.robot for c in candidates]


def posterior_problem(message: PlacePosterior) -> str | None:
    """Why a PlacePosterior's candidates cannot be read: ``place_ids``, ``place_stamps``, ``probabilities`` and
    ``log_likelihoods`` are one entry per candidate, so they must have one length; its stamps must be ROS times
    and its probabilities in [0, 1]. None when they can."""
    lengths = {name: len(getattr(message, name))
               for name in ("place_ids", "place_stamps", "probabilities", "log_likelihoods")}
    # Sessions and robots per candidate: absent (a publisher that sends none) or one per candidate.
    lengths.update({name: len(getattr(message, name)) for name in ("place_sessions", "place_robots")
                    if len(getattr(message, name))})
    what = f"PlacePosterior of query {message.query_id}"
    if len(set(lengths.values())) > 1:
        return f"{what}: candidate arrays differ in length {lengths}"
    problem = header_stamp_problem(message.header, what) or next(
        (stamp_problem(stamp.sec, stamp.nanosec, f"{what} place_stamps[{rank}]")
         for rank, stamp in enumerate(message.place_stamps) if stamp_problem(stamp.sec, stamp.nanosec)), None)
    if problem is not None:
        return problem
    # Re-ranking orders candidates by them and a tracked closure carries one on: NaN would order nothing.
    probabilities = np.asarray(message.probabilities, dtype=np.float64)
    outside = np.flatnonzero(~((probabilities >= 0.0) & (probabilities <= 1.0)))
    if outside.size:
        return f"{what}: probabilities[{outside[0]}] = {probabilities[outside[0]]} is not in [0, 1]"
    return None


def recognition_to_posterior(recognition: Recognition, header: Any) -> PlacePosterior:
    message = PlacePosterior()
    message.header = copy_header(header)
    message.query_id = recognition.query_id
    message.assigned_place_id = recognition.assigned_place_id
    message.current_place_id = recognition.current_place_id
    message.is_new_place = recognition.is_new_place
    message.loop_closure_candidate = recognition.loop_closure is not None
    message.new_place_probability = float(recognition.new_place_probability)
    message.robot, message.session = recognition.robot, recognition.session
    _fill_candidates(message, recognition.candidates)
    return message


def unrecognised_posterior(header: Any, num_places: int, session: Session | None = None) -> PlacePosterior:
    """The answer to a frame fabmap_node dropped (already mapped, out of order, stamped in the future,
    malformed): ``query_id`` -1, no place, new-place probability NaN."""
    message = PlacePosterior()
    message.header = copy_header(header)
    message.query_id = -1
    message.assigned_place_id = -1
    message.current_place_id = num_places - 1
    message.is_new_place = False
    message.loop_closure_candidate = False
    message.new_place_probability = float("nan")
    if session is not None:
        message.robot, message.session = session.robot, session.number
    return message


def recognition_to_loop_closure(recognition: Recognition, header: Any) -> LoopClosure | None:
    match = recognition.loop_closure
    if match is None:
        return None
    message = LoopClosure()
    message.header = copy_header(header)
    message.query_id = recognition.query_id
    message.query_place_id = recognition.assigned_place_id
    message.matched_place_id = match.place_id
    message.matched_stamp = time_from_ns(match.stamp_ns)
    message.probability = float(match.probability)
    message.log_likelihood = float(match.log_likelihood)
    message.query_robot, message.query_session = recognition.robot, recognition.session
    message.matched_robot, message.matched_session = match.robot, match.session
    return message


def fill_relative_pose(message: LoopClosure, outcome: PoseOutcome) -> None:
    """Write a relative pose (or why there is none) into a LoopClosure's pose fields."""
    message.pose_status = int(outcome.status)
    message.pose_available = outcome.pose is not None
    if outcome.pose is None:
        return
    x, y, z, w = Rotation.from_matrix(outcome.pose.rotation).as_quat()
    message.pose.orientation.x, message.pose.orientation.y = float(x), float(y)
    message.pose.orientation.z, message.pose.orientation.w = float(z), float(w)
    tx, ty, tz = (float(value) for value in outcome.pose.translation)
    message.pose.position.x, message.pose.position.y, message.pose.position.z = tx, ty, tz
    message.pose_covariance = [float(value) for value in outcome.pose.covariance.reshape(36)]
    message.translation_metric = outcome.pose.metric


def message_pose_problem(pose: Any, what: str = "pose") -> str | None:
    """Why a geometry_msgs/Pose is not a usable pose (``message_values.pose_problem``); None when it is."""
    position, orientation = pose.position, pose.orientation
    return pose_problem((position.x, position.y, position.z),
                        (orientation.x, orientation.y, orientation.z, orientation.w), what)


def odometry_problem(message: Any) -> str | None:
    """Why a nav_msgs/Odometry cannot go into the pose graph or the odometry gate: its stamp or its pose
    (its covariances are not used). None when it can."""
    stamp = message.header.stamp
    return stamp_problem(stamp.sec, stamp.nanosec, "odometry stamp") or message_pose_problem(
        message.pose.pose, "odometry pose")


def loop_closure_stamp_problem(message: LoopClosure) -> str | None:
    """Why a LoopClosure's stamps (the query's and the matched place's) are not ROS times; None when they are."""
    stamp, matched = message.header.stamp, message.matched_stamp
    return stamp_problem(stamp.sec, stamp.nanosec, "closure stamp") or stamp_problem(
        matched.sec, matched.nanosec, "closure matched_stamp")


def loop_closure_pose_problem(message: LoopClosure) -> str | None:
    """Why a LoopClosure's relative pose and covariance cannot go into the pose graph or the odometry gate
    (``gtsam_poses.loop_closure_pose`` would raise on them, or feed NaN to the graph); None when they can."""
    return message_pose_problem(message.pose, "closure pose") or covariance_problem(
        message.pose_covariance, 6, "closure pose_covariance")
