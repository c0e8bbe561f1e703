"""A recorded run scored offline: frames found by stamp, the score matrix rebuilt from posteriors, closures
scored per closure, listed (closures.csv) and their relative poses checked against a pose truth."""

import csv
import io
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.closure_listing import (
    CSV_COLUMNS,
    PoseTruth,
    closure_listing_markdown,
    closure_pose_error,
    closures_csv,
    read_pose_truth,
)
from aefabmap_ros.evaluation.closure_scores import (
    closure_scores_markdown,
    closure_scores_to_dict,
    score_recorded_closures,
)
from aefabmap_ros.evaluation.metrics import event_scores
from aefabmap_ros.evaluation.recordings import (
    FrameIndex,
    RecordedClosure,
    closure_precision_recall,
    frames_by_query_id,
    scores_from_recording,
    seconds_text,
)
from aefabmap_ros.evaluation.trajectory_error import tum_text

START = 1_700_000_000_000_000_000
PERIOD = 100_000_000  # 10 Hz


def frame_stamp(frame):
    return START + frame * PERIOD


def stamp(ns):
    return SimpleNamespace(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def frames_of(count):
    return FrameIndex(np.array([frame_stamp(i) for i in range(count)]), "test stamps")


def posterior(frame, places, probabilities, query_id=None, place_stamps=None):
    """A PlacePosterior of frame ``frame`` ranking frames ``places``; ids deliberately unlike the frames."""
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp(frame_stamp(frame))),
        query_id=frame + 1000 if query_id is None else query_id,
        place_ids=np.array([p + 500 for p in places], dtype=np.int64), probabilities=np.array(probabilities, float),
        place_stamps=[stamp(s) for s in (place_stamps if place_stamps is not None else map(frame_stamp, places))])


def no_pose():
    return SimpleNamespace(position=SimpleNamespace(x=0.0, y=0.0, z=0.0),
                           orientation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0))


def closure(frame, matched, probability=0.99, query_id=None, inliers=-1, pose=None, metric=False,
            matched_stamp=None):
    """A LoopClosure from frame ``frame`` to frame ``matched``; ``pose`` a 4x4 T_q_m or None."""
    fields = no_pose()
    if pose is not None:
        x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
        fields = SimpleNamespace(position=SimpleNamespace(x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
                                 orientation=SimpleNamespace(x=x, y=y, z=z, w=w))
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp(frame_stamp(frame))),
        query_id=frame + 1000 if query_id is None else query_id, matched_place_id=matched + 500,
        matched_stamp=stamp(frame_stamp(matched) if matched_stamp is None else matched_stamp),
        probability=probability, inliers=inliers, pose_available=pose is not None, translation_metric=metric,
        pose=fields)


# ------------------------------------------------------------------------------------------ stamps -> frames


def test_frame_index_maps_exact_stamps_and_within_a_tolerance():
    exact = frames_of(5)
    assert [exact.frame_of(frame_stamp(i)) for i in range(5)] == [0, 1, 2, 3, 4]
    assert exact.frame_of(frame_stamp(2) + 1) is None and exact.frame_of(frame_stamp(9)) is None
    # Float seconds (a times file): 1700000000.2 s parses to a stamp some 100 ns off; the nearest frame within 1 ms.
    loose = FrameIndex(np.array([round((1_700_000_000 + i / 10) * 1e9) for i in range(5)]), "times", 1_000_000)
    assert loose.frame_of(frame_stamp(2)) == 2 and loose.frame_of(frame_stamp(2) + 900_000) == 2
    assert loose.frame_of(frame_stamp(2) + 2_000_000) is None
    assert "within 1 ms" in loose.describe() and "matched exactly" in exact.describe()


def test_frame_index_refuses_ambiguity_and_repeated_stamps():
    close = FrameIndex(np.array([0, 600_000, 2_000_000]), "a 1.7 kHz times file", 1_000_000)
    with pytest.raises(DataError, match=r"within 1 ms of frames 0, 1 of a 1.7 kHz times file: ambiguous"):
        close.frame_of(300_000)
    assert close.frame_of(600_000) == 1  # an exact stamp is no ambiguity
    with pytest.raises(DataError, match=r"frames 1 and 3 of gt\.npz have the same stamp 1\.000000000 s"):
        FrameIndex(np.array([0, 10**9, 2 * 10**9, 10**9]), "gt.npz")


def test_seconds_text_is_exact():
    assert seconds_text(frame_stamp(3)) == "1700000000.300000000"
    assert seconds_text(5) == "0.000000005"


# ------------------------------------------------------------------------------------------ the score matrix


def test_scores_from_recording_maps_queries_and_places_by_stamp_never_by_id():
    posteriors = [posterior(0, [], []), posterior(1, [0], [0.2]), posterior(2, [1, 0], [0.7, 0.1]),
                  posterior(3, [1, 0], [0.6, 0.3], query_id=2)]  # a repeated query id: the stamps decide
    closures = [closure(3, 1, 0.995, query_id=0)]
    recorded = scores_from_recording(posteriors, closures, frames_of(5))
    expected = np.zeros((5, 5))
    expected[1, 0], expected[2, 1], expected[2, 0] = 0.2, 0.7, 0.1
    expected[3, 1], expected[3, 0] = 0.995, 0.3  # the loop closure's probability is the larger
    np.testing.assert_allclose(recorded.scores, expected)
    assert recorded.closures == [RecordedClosure(3, 1, 0.995)]
    assert (recorded.num_posteriors, recorded.num_dropped_posteriors, recorded.num_loop_closures) == (4, 0, 1)
    assert recorded.processed.tolist() == [True, True, True, True, False]


def test_a_posterior_of_a_dropped_frame_is_not_scored():
    dropped = posterior(0, [], [], query_id=-1)
    dropped.header.stamp = stamp(frame_stamp(10**6))  # e.g. stamped in the future: matches no frame, not refused
    recorded = scores_from_recording([dropped, posterior(1, [], [])], [], frames_of(3))
    assert (recorded.num_posteriors, recorded.num_dropped_posteriors) == (1, 1)
    assert recorded.processed.tolist() == [False, True, False]


@pytest.mark.parametrize(("posteriors", "closures", "message"), [
    ([posterior(7, [0], [0.5])], [],
     r"1 recorded stamp matches no frame of test stamps \(5 stamped frames, 1700000000.000000000 to "
     r"1700000000.400000000 s, matched exactly\); the first: place_posteriors query stamped 1700000000.700000000 s"),
    ([posterior(3, [0], [0.5], place_stamps=[frame_stamp(0) + 5])], [closure(4, 2, matched_stamp=1)],
     "2 recorded stamps match no frame .* place_posteriors place stamped 1700000000.000000005 s.* pass --times FILE"),
    ([posterior(2, [2], [0.5])], [], "query frame 2 .* maps to frame 2, which is not an earlier frame"),
    ([], [closure(1, 3)], "loop closure: query frame 1 .* maps to frame 3, which is not an earlier frame"),
    ([posterior(2, [0, 1], [0.5])], [], "2 place ids, 1 probabilities and 2 place stamps"),
    ([posterior(2, [0, 1], [0.5, 0.2], place_stamps=[frame_stamp(0)])], [], "2 place ids, 2 probabilities and 1 "),
])
def test_scores_from_recording_errors(posteriors, closures, message):
    with pytest.raises(DataError, match=message):
        scores_from_recording(posteriors, closures, frames_of(5))


def test_frames_by_query_id_for_a_lossless_replay():
    posteriors = [posterior(i, [0] if i > 1 else [], [0.3] if i > 1 else [], query_id=i) for i in range(4)]
    frames = frames_by_query_id(posteriors, [[closure(3, 0, query_id=3)]], 6)
    assert frames.stamps_ns.tolist() == [frame_stamp(i) for i in range(4)] + [-1, -1]
    assert scores_from_recording(posteriors, [], frames).scores[3, 0] == 0.3
    with pytest.raises(DataError, match="query id 9 outside the 6 frames"):
        frames_by_query_id([posterior(2, [], [], query_id=9)], [], 6)
    with pytest.raises(DataError, match=r"query id 1 has two stamps .* not a lossless replay"):
        frames_by_query_id([posterior(1, [], [], query_id=1), posterior(2, [], [], query_id=1)], [], 6)


def test_closure_precision_recall():
    gt = np.zeros((30, 30), np.uint8)
    gt[20, 2] = gt[21, 3] = gt[22, 4] = gt[23, 20] = 1  # the last is within min gap: not a positive query
    closures = [RecordedClosure(20, 2, 1.0), RecordedClosure(21, 9, 1.0)]
    precision, recall = closure_precision_recall(closures, gt, 10)
    assert precision == 0.5 and recall == pytest.approx(1 / 3)
    precision, recall = closure_precision_recall([], gt, 10)
    assert np.isnan(precision) and recall == 0.0


def test_a_topic_s_missed_frames_are_split_by_whether_their_posterior_ranked_a_true_place():
    # Frames 20-23 revisit frames 0-3 (gt by hand); 24 revisits too but only within the min gap.
    gt = np.zeros((30, 30), np.uint8)
    for query in range(20, 24):
        gt[query, query - 20] = 1
    gt[24, 20] = 1
    posteriors = [posterior(20, [0, 7], [0.6, 0.1]),  # true place ranked, and closed below
                  posterior(21, [9, 1], [0.5, 0.2]),  # true place ranked second, never closed: a decision miss
                  posterior(22, [9], [0.9]),          # only a wrong place ranked: a ranking miss
                  posterior(23, [], []),              # nothing ranked: a ranking miss
                  posterior(24, [20], [0.9])]         # not a revisiting frame (gap), ignored
    closures = [closure(20, 0, 0.99, inliers=30), closure(22, 9, 0.99, inliers=30)]  # 22 -> 9 is false
    # 3 revisiting frames missed (21, 22, 23), 1 of them with a true place ranked.
    row = score_recorded_closures("published", "loop_closures", closures, posteriors, gt, frames_of(30), 10)
    assert row.num_missed_ranked == 1
    assert row.events.num_revisiting_frames - row.events.num_revisiting_frames_closed == 3
    assert closure_scores_markdown([row]).splitlines()[-1].endswith("| 0.250 (1/4) | 1 / 3 |")
    assert closure_scores_to_dict(row)["missed_revisiting_frames_with_a_true_place_ranked"] == 1


# ------------------------------------------------------------------------------------------ frames lost


def _three_event_gt() -> np.ndarray:
    """40 frames, min gap 10. Event A: 12, 13, 14, 15, 17 (one frame missing: bridged); event B: 25..28
    (each revisits two frames 19-20 back); event C: 35 (revisits 20). 10 revisiting frames."""
    gt = np.zeros((40, 40), np.uint8)
    for query, place in ((12, 0), (13, 1), (14, 2), (15, 3), (17, 5), (35, 20)):
        gt[query, place] = 1
    for query in range(25, 29):
        gt[query, [query - 20, query - 19]] = 1
    return gt


# Frames that never reached fabmap_node (a live camera's losses, a detection-rate policy): no message of theirs.
LOST = (3, 9, 10, 14, 16, 22, 26, 33)
# (query frame, matched frame) of the closures, in the sequence's frames: 15 -> 4 and 35 -> 21 are false.
CLOSURE_FRAMES = ((12, 0), (13, 1), (15, 4), (17, 5), (25, 5), (27, 8), (35, 21))


def lossy_recording():
    """What fabmap_node publishes when the LOST frames never reach it: its query ids count the frames it got."""
    received = [frame for frame in range(40) if frame not in LOST]
    query_id = {frame: index for index, frame in enumerate(received)}
    posteriors = [posterior(frame, [], [], query_id=query_id[frame]) for frame in received]
    closures = [closure(q, m, query_id=query_id[q]) for q, m in CLOSURE_FRAMES]
    for message, (_, matched) in zip(closures, CLOSURE_FRAMES, strict=True):
        message.matched_place_id = query_id[matched]
    return posteriors, closures


def test_a_recording_with_lost_frames_scores_as_its_closures_do_in_the_full_sequence():
    gt = _three_event_gt()
    posteriors, closures = lossy_recording()
    row = score_recorded_closures("published", "loop_closures", closures, posteriors, gt, frames_of(40), 10)
    reference = event_scores(list(CLOSURE_FRAMES), gt, 10)  # the same closures, given as frame pairs
    assert row.events == reference
    assert (reference.num_closures, reference.num_false_closures) == (7, 2)
    assert row.precision == pytest.approx(5 / 7)
    assert [(r.query_frame, r.matched_frame) for r in row.rows] == list(CLOSURE_FRAMES)
    # Recall over the revisiting frames the detector processed: 14 and 26 were lost, so 10 - 2 = 8 of them;
    # closed by a true closure: 12, 13, 17, 25, 27.
    revisiting = np.flatnonzero((gt & np.tril(np.ones((40, 40), np.uint8), -10)).any(axis=1)).tolist()
    processed = [frame for frame in revisiting if frame not in LOST]
    assert (row.num_processed_revisiting, row.num_processed_revisiting_closed) == (len(processed), 5) == (8, 5)
    assert row.processed_recall == pytest.approx(5 / 8) and row.events.frame_recall == pytest.approx(5 / 10)
    assert closure_scores_to_dict(row)["recall_revisiting_frames_processed"] == pytest.approx(5 / 8)
    # The query ids, read as frames, would have put these closures on other rows (what this replaces):
    by_id = [(int(c.query_id), int(c.matched_place_id)) for c in closures]
    assert event_scores(by_id, gt, 10) != reference


# ------------------------------------------------------------------------------------------ poses, closures.csv


def transform(rotation_deg_about_y, translation):
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("y", rotation_deg_about_y, degrees=True).as_matrix()
    matrix[:3, 3] = translation
    return matrix


# Ground truth: frame 0 somewhere, turned about z; frame 12 (a revisit of frame 0) 2 m ahead of it along its
# optical axis (z), turned 30 degrees about its y axis. T_q_m (frame 0 in frame 12's camera) = inv(T_12) T_0.
CAMERA_0 = transform(0, [5.0, 1.0, 0.0])
CAMERA_0[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
CAMERA_12 = CAMERA_0 @ transform(30, [0.0, 0.0, 2.0])
TRUE_T_Q_M = np.linalg.inv(CAMERA_12) @ CAMERA_0


def pose_truth_file(tmp_path):
    """groundtruth.tum of frames 0..12: every frame at CAMERA_0 but frame 12."""
    poses = np.array([CAMERA_12 if i == 12 else CAMERA_0 for i in range(13)])
    path = tmp_path / "groundtruth.tum"
    path.write_text(tum_text(np.array([frame_stamp(i) for i in range(13)]) / 1e9, poses))
    return path


def test_the_pose_error_of_a_closure_against_a_hand_made_pair(tmp_path):
    truth = read_pose_truth(pose_truth_file(tmp_path))
    exact = closure(12, 0, pose=TRUE_T_Q_M, metric=True)
    error = closure_pose_error(exact, truth)
    assert error is not None
    assert (error.rotation_deg, error.translation_m, error.direction_deg) == pytest.approx((0, 0, 0), abs=1e-4)
    # 10 degrees more about y and 0.3 m off along the query camera's x axis.
    off = TRUE_T_Q_M.copy()
    off[:3, :3] = off[:3, :3] @ Rotation.from_euler("y", 10, degrees=True).as_matrix()
    off[:3, 3] += [0.3, 0.0, 0.0]
    error = closure_pose_error(closure(12, 0, pose=off, metric=True), truth)
    assert error is not None
    assert error.rotation_deg == pytest.approx(10.0, abs=1e-4) and error.translation_m == pytest.approx(0.3, abs=1e-5)
    true_t = TRUE_T_Q_M[:3, 3]
    cosine = true_t @ off[:3, 3] / np.linalg.norm(true_t) / np.linalg.norm(off[:3, 3])
    expected_direction = np.degrees(np.arccos(cosine))
    assert error.direction_deg == pytest.approx(expected_direction, abs=1e-4)
    # The inverse convention (the query in the place's frame) is far off: the test sees the convention.
    inverse = closure_pose_error(closure(12, 0, pose=np.linalg.inv(TRUE_T_Q_M), metric=True), truth)
    assert inverse is not None and inverse.translation_m > 1.0
    assert closure_pose_error(closure(12, 0), truth) is None  # no pose
    assert closure_pose_error(closure(12, 0, pose=off, matched_stamp=frame_stamp(0) - 10**9), truth) is None


def test_pose_truth_takes_the_nearest_pose_within_10_ms():
    truth = PoseTruth(np.array([0, 100_000_000]), np.stack([np.eye(4), 2 * np.eye(4)]), "t")
    near = truth.pose_at(90_000_000)
    assert near is not None and near[0, 0] == 2.0
    assert truth.pose_at(50_000_000) is None and truth.pose_at(-10_000_001) is None


def test_closures_csv_against_hand_computed_truth(tmp_path):
    truth = read_pose_truth(pose_truth_file(tmp_path))
    gt = np.zeros((13, 13), np.uint8)
    gt[12, 0] = gt[11, 0] = 1
    off = TRUE_T_Q_M.copy()
    off[:3, :3] = off[:3, :3] @ Rotation.from_euler("y", 10, degrees=True).as_matrix()
    off[:3, 3] += [0.3, 0.0, 0.0]
    monocular = TRUE_T_Q_M.copy()
    monocular[:3, 3] /= np.linalg.norm(monocular[:3, 3])
    closures = [closure(12, 0, 0.995, inliers=80, pose=off, metric=True),   # true, its pose wrong
                closure(12, 0, 0.99, inliers=60, pose=monocular),            # true, a right monocular pose
                closure(11, 1, 0.98, inliers=40)]                           # false, no pose
    posteriors = [posterior(i, [], []) for i in range(13)]
    row = score_recorded_closures("published", "loop_closures", closures, posteriors, gt, frames_of(13), 10,
                                  pose_truth=truth)
    lines = list(csv.DictReader(io.StringIO(closures_csv(row.rows))))
    assert list(lines[0]) == list(CSV_COLUMNS) and len(lines) == 3
    first, second, third = lines
    assert {k: first[k] for k in ("topic", "query_stamp", "query_frame", "matched_stamp", "matched_frame",
                                  "probability", "inliers", "true", "gt", "pose_available", "translation_metric",
                                  "pose_wrong")} == {
        "topic": "loop_closures", "query_stamp": "1700000001.200000000", "query_frame": "12",
        "matched_stamp": "1700000000.000000000", "matched_frame": "0", "probability": "0.995", "inliers": "80",
        "true": "1", "gt": "1", "pose_available": "1", "translation_metric": "1", "pose_wrong": "1"}
    assert float(first["rotation_error_deg"]) == pytest.approx(10.0, abs=1e-5)
    assert float(first["translation_error_m"]) == pytest.approx(0.3, abs=1e-5)
    assert [float(first[k]) for k in ("x", "y", "z")] == pytest.approx(off[:3, 3].tolist(), abs=1e-7)
    assert second["translation_metric"] == "0" and second["translation_error_m"] == ""  # a direction only
    assert float(second["direction_error_deg"]) == pytest.approx(0.0, abs=1e-4) and second["pose_wrong"] == "0"
    assert (third["query_frame"], third["matched_frame"], third["true"], third["gt"]) == ("11", "1", "0", "0")
    assert third["pose_available"] == "0" and third["x"] == third["rotation_error_deg"] == third["pose_wrong"] == ""
    assert (row.num_wrong_poses, row.num_poses_checked) == (1, 2)
    assert closure_scores_markdown([row]).splitlines()[-1].endswith("| 1 / 2 |")
    assert closure_scores_to_dict(row)["wrong_poses"] == 1
    listing = closure_listing_markdown(list(row.rows), pose_truth_given=True)
    assert "| `loop_closures` | 11 | 1700000001.100000000 | 1 | 1700000000.100000000 | 0.9800 | 40 |  |  |" in listing
    assert ("| `loop_closures` | 12 | 1700000001.200000000 | 0 | 1700000000.000000000 | 0.9950 | 80 | 10.00 "
            "| 0.300 m |") in listing
