"""A recorded run scored offline: frames found by stamp and the score matrix rebuilt from posteriors (the
closures' scores and listing: test_closure_scores.py, test_closure_listing.py)."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.recordings import (
    FrameIndex,
    RecordedClosure,
    closure_precision_recall,
    frames_by_query_id,
    scores_from_recording,
    seconds_text,
)

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
            matched_stamp=None, covariance=None):
    """A LoopClosure from frame ``frame`` to frame ``matched``; ``pose`` a 4x4 T_q_m or None, ``covariance``
    its 6x6 (identity by default)."""
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
        pose=fields, pose_covariance=(np.eye(6) if covariance is None else np.asarray(covariance)).reshape(36).tolist())


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
