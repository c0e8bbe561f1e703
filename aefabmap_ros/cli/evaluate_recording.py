"""aefabmap_eval --recording: a recorded run's outputs scored against the ground truth (its frames matched by
image stamp), and the ground truth both kinds of evaluation load."""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.evaluation.closure_listing import PoseTruth, closure_listing_markdown, closures_csv, read_pose_truth
from aefabmap_ros.evaluation.closure_scores import (
    TopicClosureScores,
    closure_scores_markdown,
    closure_scores_to_dict,
    score_recorded_closures,
)
from aefabmap_ros.evaluation.ground_truth import load_gt_npz, load_gt_stamps, loop_matrix_from_kitti
from aefabmap_ros.evaluation.metrics import DEFAULT_EVENT_GAP, evaluate_scores
from aefabmap_ros.evaluation.protocol import MethodResult
from aefabmap_ros.evaluation.recordings import (
    FLOAT_SECONDS_TOLERANCE_NS,
    FrameIndex,
    frames_by_query_id,
    scores_from_recording,
)
from aefabmap_ros.evaluation.session_scores import (
    closure_sessions,
    frame_sessions,
    recorded_sessions,
    score_session_pairs,
    session_name,
    session_pair_to_dict,
    session_pairs_markdown,
)
from aefabmap_ros.io import bags
from aefabmap_ros.io.rgbd import read_times
from aefabmap_ros.io.sources import ImageSource

if TYPE_CHECKING:
    from aefabmap_ros.cli.evaluate_run import Run

RECORDING_TOPICS = {"place_posteriors": "aefabmap_msgs/msg/PlacePosterior",
                    "loop_closures": "aefabmap_msgs/msg/LoopClosure",
                    "loop_closure_candidates": "aefabmap_msgs/msg/LoopClosure",
                    # recordings made before loop_closures carried the verified closures:
                    "verified_loop_closures": "aefabmap_msgs/msg/LoopClosure"}


def load_ground_truth(args: argparse.Namespace, min_gap: int) -> np.ndarray:
    if (args.gt is None) == (args.poses is None):
        raise ConfigError("give the ground truth as --gt FILE.npz or as --poses FILE (with --max-distance "
                          "and --max-angle), exactly one")
    if args.gt is not None:
        return load_gt_npz(args.gt)
    if args.max_distance is None or args.max_angle is None:
        raise ConfigError("--poses needs --max-distance (metres) and --max-angle (degrees)")
    return loop_matrix_from_kitti(args.poses, args.max_distance, args.max_angle, min_gap)


@dataclass
class Recording:
    """A recording's messages, by what they are."""

    posteriors: list[Any]
    candidates: tuple[str, list[Any]] | None  # (topic, messages): FAB-MAP's raw closures
    published: tuple[str, list[Any]] | None  # (topic, messages): what a backend got on loop_closures
    note: str = ""


def read_recording(path: Path) -> Recording:
    """A recorded run's messages (``RECORDING_TOPICS``, with or without a leading '/': aefabmap_record
    stores the names it subscribed to, ros2 bag record absolute ones).

    Today's layout: ``loop_closure_candidates`` (FAB-MAP's raw closures) and ``loop_closures``
    (what was published: verified by default). Recordings made before verification moved onto
    ``loop_closures`` have ``verified_loop_closures``: their ``loop_closures`` are then read as the
    candidates and ``verified_loop_closures`` as the published, verified closures.
    """
    topics = bags.list_topics(path)
    found: dict[str, str] = {}
    for topic, msgtype in topics.items():
        name = topic.lstrip("/")
        if name in RECORDING_TOPICS:
            if msgtype != RECORDING_TOPICS[name]:
                raise DataError(f"topic {topic!r} in recording {path} is {msgtype}, expected {RECORDING_TOPICS[name]}")
            if name in found:  # 'loop_closures' (aefabmap_record's names) beside '/loop_closures' (ros2 bag record's)
                raise DataError(f"recording {path} has both {found[name]!r} and {topic!r}: one topic recorded twice; "
                                "record one run only")
            found[name] = topic
    if not found:
        raise DataError(f"recording {path} has none of place_posteriors, loop_closures, loop_closure_candidates; "
                        f"its topics: {sorted(topics) or 'none'}")
    if "verified_loop_closures" in found and "loop_closure_candidates" in found:
        raise DataError(f"recording {path} has both verified_loop_closures (recordings before loop_closures carried "
                        "the verified closures) and loop_closure_candidates (after): record one run only")
    messages: dict[str, list[Any]] = {name: [] for name in found}
    for message in bags.read_messages(path, list(found.values())):
        messages[message.topic.lstrip("/")].append(message.message)

    def closures_on(name: str) -> tuple[str, list[Any]] | None:
        return (name, messages[name]) if name in found else None

    if "verified_loop_closures" in found:
        return Recording(messages.get("place_posteriors", []), closures_on("loop_closures"),
                         closures_on("verified_loop_closures"),
                         note="An older recording: its loop_closures are read as FAB-MAP's candidates, its "
                              "verified_loop_closures as the published (verified) closures.\n")
    return Recording(messages.get("place_posteriors", []), closures_on("loop_closure_candidates"),
                     closures_on("loop_closures"))


def recording_frames(args: argparse.Namespace, num_frames: int, recording: Recording) -> FrameIndex:
    """Which ground-truth frame each recorded stamp is: the stamps of --times, else the --gt file's
    stamps_ns, else the image stamps of --bag; or, with --frames-by-query-id, the recording's query ids."""
    if args.frames_by_query_id:
        if args.times is not None or args.bag is not None:
            raise ConfigError("--frames-by-query-id maps frames by the recording's query ids: give no --times or "
                              "--bag with it")
        closure_lists = [topic[1] for topic in (recording.candidates, recording.published) if topic is not None]
        return frames_by_query_id(recording.posteriors, closure_lists, num_frames)
    if args.times is not None and args.bag is not None:
        raise ConfigError("give the frame stamps once: --times FILE or --bag BAG, not both")
    if args.times is not None:
        stamps = read_times(args.times, num_frames, frames_of="the ground truth")
        return FrameIndex(stamps, f"--times {args.times}", FLOAT_SECONDS_TOLERANCE_NS)
    gt_stamps = load_gt_stamps(args.gt) if args.gt is not None else None
    if gt_stamps is not None:
        if gt_stamps.size != num_frames:
            raise DataError(f"{args.gt} has {gt_stamps.size} stamps_ns for {num_frames} ground-truth frames")
        return FrameIndex(gt_stamps, f"the stamps_ns of {args.gt}")
    if args.bag is not None:
        source = ImageSource(bag=args.bag, topic=args.topic)
        source.check()
        stamps = source.stamps_ns()
        if stamps.size != num_frames:
            raise DataError(f"{source.name} has {stamps.size} images but the ground truth has {num_frames} frames")
        return FrameIndex(stamps, f"the {args.topic} images of {args.bag}")
    raise ConfigError(
        "the recording's messages are matched to ground-truth frames by their image stamps, and no frame stamps "
        f"were given ({'--poses' if args.gt is None else args.gt} has none): pass --times FILE (one line of "
        "seconds per frame), --bag BAG --topic TOPIC (the images the run was fed) or a --gt .npz with a stamps_ns "
        "array (aefabmap_gt, aefabmap_synth write one); --frames-by-query-id maps by the recording's query ids "
        "instead, right only for a lossless replay (every frame reached fabmap_node, in order)")


def check_session_options(args: argparse.Namespace) -> None:
    if args.trajectory is not None and args.pose_truth is None:
        raise ConfigError("--trajectory is scored against the pose truth: add --pose-truth FILE")
    if args.session_odometry and args.trajectory is None:
        raise ConfigError("--session-odometry is set beside the joined trajectory: add --trajectory FILE")


def session_report(args: argparse.Namespace, recording: Recording, frames: FrameIndex, gt: np.ndarray,
                   rows: list[TopicClosureScores], min_gap: int) -> tuple[str, dict[str, Any]]:
    """The closures per pair of sessions when they name more than one, and the joined trajectory's error given
    --trajectory; ('', {}) for a recording of one session without --trajectory (today's output)."""
    by_topic = dict(topic for topic in (recording.candidates, recording.published) if topic is not None)
    closure_lists = list(by_topic.values())
    sessions = recorded_sessions(closure_lists)
    markdown, payload = "", dict[str, Any]()
    scored = next((row for row in rows if row.role == "published"), rows[-1] if rows else None)
    if len(sessions) > 1 and scored is not None:
        pairs = score_session_pairs(scored.rows, [closure_sessions(m) for m in by_topic[scored.topic]],
                                    frame_sessions(recording.posteriors, closure_lists, frames), gt, min_gap)
        markdown += session_pairs_markdown(scored.topic, pairs, scored.pose_truth_given)
        payload["sessions"] = [session_name(session) for session in sessions]
        payload["session_pairs"] = {"topic": scored.topic,
                                    "pairs": [session_pair_to_dict(pair, scored.pose_truth_given) for pair in pairs]}
    if args.trajectory is not None:
        from aefabmap_ros.evaluation.session_trajectory import (
            joined_trajectory_error,
            joined_trajectory_markdown,
            joined_trajectory_to_dict,
        )

        error = joined_trajectory_error(args.pose_truth, args.trajectory, args.session_odometry)
        markdown += joined_trajectory_markdown(error)
        payload["joined_trajectory"] = joined_trajectory_to_dict(error)
    return markdown, payload


def evaluate_recording(run: Run) -> tuple[list[MethodResult], np.ndarray, dict[str, Any], str, dict[str, Any],
                                          dict[str, str]]:
    args, settings = run.args, run.settings
    depth_given = any(value is not None for value in (args.depth, args.depth_topic, args.camera_info,
                                                      args.camera_info_topic))
    if args.images is not None or args.model or args.train_images or args.train_bag \
            or args.train_on_test or args.verify or depth_given:
        raise ConfigError("--recording takes only the ground truth (--gt or --poses) and the frame stamps (--times, "
                          "--bag); it evaluates recorded outputs, no images, depth, models or --verify")
    check_session_options(args)
    min_gap = settings.evaluation.min_gap
    gt = load_ground_truth(args, min_gap)
    pose_truth: PoseTruth | None = read_pose_truth(args.pose_truth) if args.pose_truth is not None else None
    started = time.monotonic()
    recording = read_recording(args.recording)
    frames = recording_frames(args, gt.shape[0], recording)
    # The score matrix: the posteriors and FAB-MAP's own decisions (verified closures may have moved).
    raw = recording.candidates[1] if recording.candidates is not None else []
    recorded = scores_from_recording(recording.posteriors, raw, frames)
    metrics = evaluate_scores(recorded.scores, gt, min_gap, settings.evaluation.threshold)
    result = MethodResult(name="recording", vocabulary_kind="recorded", vocabulary_size=0, vocabulary_id="",
                          scores=recorded.scores, metrics=metrics, seconds=time.monotonic() - started,
                          model_path=str(args.recording))
    rows = [score_recorded_closures(role, *topic_messages, recording.posteriors, gt, frames, min_gap,
                                    pose_truth=pose_truth)
            for role, topic_messages in (("FAB-MAP candidates", recording.candidates),
                                         ("published", recording.published)) if topic_messages is not None]
    run.log(f"frames: {frames.describe()}")
    header = {
        "test": str(args.recording),
        "frames": int(gt.shape[0]),
        "frame_stamps": frames.describe(),
        "frames_processed": int(recorded.processed.sum()),
        "positive_queries": metrics.num_positive_queries,
        "min_gap": min_gap,
        "place_posteriors": recorded.num_posteriors,
        "place_posteriors_dropped": recorded.num_dropped_posteriors,
        "event_gap_frames": DEFAULT_EVENT_GAP,
    }
    if pose_truth is not None:
        header["pose_truth"] = pose_truth.source
    listing = [closure for row in rows for closure in row.rows]
    extra = ("\nLoop closures per topic, each message mapped to its ground-truth frames by stamp (the query "
             "image's, the matched place's). A closure (i, j) is false when gt[i, j] = 0. A revisit event is a run "
             "of revisiting frames (a ground-truth loop at least min_gap frames back), gaps of up to "
             f"{DEFAULT_EVENT_GAP} frames bridged; it is closed by one true closure from one of its frames. Recall "
             "is over all revisiting frames, and over those the detector processed (a place_posteriors message: a "
             "live detector may skip frames by design). Of the revisiting frames a topic missed, the 'missed' "
             "column counts those whose recorded posterior ranked a true place (temporal consistency or "
             "verification missed them); the rest were never ranked right (the vocabulary and FAB-MAP).\n\n"
             + (closure_scores_markdown(rows) + closure_listing_markdown(listing, pose_truth is not None)
                if rows else "No loop-closure topic in the recording.\n")
             + recording.note)
    sessions_markdown, sessions_json = session_report(args, recording, frames, gt, rows, min_gap)
    files = {"closures.csv": closures_csv(listing)} if rows else {}
    return [result], gt, header, extra + sessions_markdown, \
        {"closures": [closure_scores_to_dict(row) for row in rows], **sessions_json}, files
