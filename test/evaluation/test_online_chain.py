"""The nodes' decision chain offline: consistency holds back single matches, verification gates what is published."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.online_chain import ChainClosure, ChainInputs, run_online_chain
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.geometric import VerificationConfig
from test.fabmap.test_recognizer import SAMPLES, V, _tree
from test.verification.test_geometric import HEIGHT, WIDTH, _two_views

SECOND = 10**9


def _scene_words(scene: int) -> np.ndarray:
    return np.arange(5 * scene, 5 * scene + 5)


def _sequence() -> tuple[sp.csr_matrix, list[Features]]:
    """Scenes 0..6 at 1 Hz, then scenes 1 and 2 seen again from another pose (true revisits), then
    scene 3's words on keypoints scattered at random (an aliased look-alike that geometry rejects)."""
    views = [_two_views(seed=scene) for scene in range(7)]
    words = [_scene_words(s) for s in range(7)] + [_scene_words(1), _scene_words(2), _scene_words(3)]
    features = [view[0] for view in views] + [views[1][1], views[2][1]]
    aliased = views[3][1]
    scattered = aliased.keypoints.copy()
    scattered[:, :2] = np.random.default_rng(3).uniform([0, 0], [WIDTH, HEIGHT], (scattered.shape[0], 2))
    features.append(Features(keypoints=scattered, descriptors=aliased.descriptors, descriptor_type="sift"))
    rows = np.zeros((len(words), V))
    for row, ids in enumerate(words):
        rows[row, ids] = 1
    return sp.csr_matrix(rows), features


CONFIG = FabMapConfig(exclude_recent_seconds=3.0, consistency_matches=2, island_seconds=1.5, match_threshold=0.5)


def test_consistent_candidates_and_verified_closures():
    observations, features = _sequence()
    stamps = np.arange(observations.shape[0], dtype=np.int64) * SECOND
    config = VerificationConfig()
    result = run_online_chain(observations, stamps, _tree(), SAMPLES, CONFIG,
                              ChainInputs(config, features))
    # Frame 7 matches place 1 but is the first of its run: no candidate. Frames 8 and 9 continue it.
    assert [(c.query_frame, c.matched_frame) for c in result.candidates] == [(8, 2), (9, 3)]
    assert all(c.probability > 0.5 and c.inliers == -1 for c in result.candidates)
    # The aliased frame 9 fails geometry: only the true revisit reaches /loop_closures.
    assert [(c.query_frame, c.matched_frame) for c in result.published] == [(8, 2)]
    assert result.published[0].inliers >= 100
    assert result.num_places == 10
    # Each frame's best hypothesis, for the calibration: from frame 3 on (the first place is 3 s old).
    assert [b.query_frame for b in result.best] == list(range(3, 10))
    assert (result.best[5].matched_frame, result.candidates[0].probability) == (2, result.best[5].probability)
    # Every place each posterior reports (top_k), best first: what the ranking found. Only places at least
    # 3 s old are hypotheses: frame 3 ranks the one place of 0 s, frame 7 (no candidate) the top_k of its five,
    # scene 1 first.
    assert [frame for query, frame in result.ranked if query == 3] == [0]
    ranked_by_7 = [frame for query, frame in result.ranked if query == 7]
    assert ranked_by_7[0] == 1 and sorted(ranked_by_7) == [0, 1, 2, 3, 4] and CONFIG.top_k == 5
    assert all(query - frame >= 3 for query, frame in result.ranked)
    assert {(b.query_frame, b.matched_frame) for b in result.best} <= set(result.ranked)


def test_without_verification_the_candidates_are_published():
    observations, _ = _sequence()
    stamps = np.arange(observations.shape[0], dtype=np.int64) * SECOND
    result = run_online_chain(observations, stamps, _tree(), SAMPLES, CONFIG)
    assert result.published == result.candidates and len(result.published) == 2
    assert isinstance(result.published[0], ChainClosure)


def test_bad_input():
    observations, _ = _sequence()
    stamps = np.arange(observations.shape[0], dtype=np.int64) * SECOND
    with pytest.raises(DataError, match="9 stamps for 10 frames"):
        run_online_chain(observations, stamps[:9], _tree(), SAMPLES, CONFIG)
    with pytest.raises(DataError, match="increase strictly"):
        run_online_chain(observations, stamps[::-1].copy(), _tree(), SAMPLES, CONFIG)


def _weak_revisit(gap_s: float) -> tuple[sp.csr_matrix, list[Features], np.ndarray]:
    """The sequence's revisit of scenes 1 and 2, then ``gap_s`` later a frame that sees scene 3 from the
    other pose (its features) but shares only two of its words (blur, a changed scene: FAB-MAP is unsure)."""
    observations, features = _sequence()
    words = sp.vstack([observations[:9], sp.csr_matrix(np.isin(np.arange(V), [15, 16, 35, 36, 37]).astype(float))])
    revisit = _two_views(seed=3)[1]
    stamps = np.append(np.arange(9) * SECOND, 8 * SECOND + int(gap_s * SECOND)).astype(np.int64)
    return sp.csr_matrix(words), [*features[:9], revisit], stamps


@pytest.mark.parametrize(("track_seconds", "gap_s", "tracked"), [(1.0, 0.5, True), (0.0, 0.5, False),
                                                                   (1.0, 1.5, False)])
def test_loop_tracking_closes_a_weak_frame_of_a_verified_revisit(track_seconds, gap_s, tracked):
    observations, features, stamps = _weak_revisit(gap_s)
    config = VerificationConfig(track_seconds=track_seconds)
    result = run_online_chain(observations, stamps, _tree(), SAMPLES, CONFIG,
                              ChainInputs(config, features))
    # Frame 9 is no candidate: its best place is 3, but below the match threshold ...
    assert [(c.query_frame, c.matched_frame) for c in result.candidates] == [(8, 2)]
    weak = result.best[-1]
    assert weak.query_frame == 9 and weak.matched_frame == 3 and weak.probability < CONFIG.match_threshold
    # ... but place 3 is among its candidates and 1 s (map time) from the verified place 2: while the track
    # lasts, geometry confirms it and it is published as a tracked closure.
    published = [(c.query_frame, c.matched_frame, c.tracked) for c in result.published]
    assert published == [(8, 2, False), (9, 3, True)] if tracked else published == [(8, 2, False)]
    if tracked:
        assert result.published[1].inliers >= VerificationConfig().min_inliers


@pytest.mark.parametrize(("track_frames", "min_age_s", "matched"), [(5, 5.0, 3), (0, 5.0, None), (5, 6.0, None)])
def test_loop_tracking_verifies_the_frames_next_to_the_tracked_place_that_fabmap_does_not_rank(
        track_frames, min_age_s, matched):
    observations, features, stamps = _weak_revisit(0.5)
    # Frame 9 (8.5 s) now looks like scene 5 to FAB-MAP, and only its single best place is a candidate:
    # place 5, 3 s from the verified place 2 in map time, outside the 2.5 s island: none lies near the track.
    observations = sp.vstack([observations[:9], sp.csr_matrix(np.isin(np.arange(V), _scene_words(5)).astype(float))])
    config = replace(CONFIG, top_k=1)
    verification = VerificationConfig(track_seconds=1.0, track_island_seconds=2.5, track_frames=track_frames,
                                      track_min_age_seconds=min_age_s)
    result = run_online_chain(sp.csr_matrix(observations), stamps, _tree(), SAMPLES, config,
                              ChainInputs(verification, features))
    assert result.best[-1].matched_frame == 5
    # The frames next to place 2 (2 s) at least min_age before 8.5 s, nearest first: 2, 1, 3, 0. Frame 3
    # sees scene 3, as frame 9 does from the other pose: geometry accepts it. At 6 s it is too recent.
    tracked = [(c.query_frame, c.matched_frame, c.nearby_frame, c.probability) for c in result.published if c.tracked]
    assert tracked == ([] if matched is None else [(9, matched, True, 0.0)])


@pytest.mark.parametrize("consistent", [True, False])
def test_the_chain_gates_closures_by_the_sequences_odometry(consistent: bool) -> None:
    """The revisit (8, 2) of test_consistent_candidates_and_verified_closures, now with intrinsics and odometry:
    published when odometry moved the camera by what the closure's pose says, refused when odometry puts the
    place 20 m away (an aliased corner), as verifier_node's gate decides."""
    import gtsam

    from aefabmap_ros.backend.odometry_gate import OdometryGate
    from aefabmap_ros.backend.pose_graph import PoseGraphConfig
    from aefabmap_ros.verification.relative_pose import CameraModel
    from test.verification.test_geometric import FOCAL, _rotation_y

    observations, features = _sequence()
    stamps = np.arange(observations.shape[0], dtype=np.int64) * SECOND
    # Frame 2 is _two_views(seed=2)'s first view, frame 8 its second: in frame 8's camera frame, frame 2's camera
    # is at (R, t) of _two_views. Odometry holds the robot there until frame 7, then at the origin.
    place_in_query = gtsam.Pose3(gtsam.Rot3(_rotation_y(0.15)), np.array([0.8, 0.1, 0.3]))
    before = place_in_query if consistent else gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([20.0, 0.0, 0.0]))
    odometry = [(int(stamp), before if frame < 8 else gtsam.Pose3()) for frame, stamp in enumerate(stamps)]
    camera = CameraModel(np.array([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]]))
    result = run_online_chain(observations, stamps, _tree(), SAMPLES, CONFIG,
                              ChainInputs(VerificationConfig(), features, camera=camera, odometry=odometry,
                                          gate_factory=lambda: OdometryGate(PoseGraphConfig(), gtsam.Pose3())))
    assert [(c.query_frame, c.matched_frame) for c in result.candidates] == [(8, 2), (9, 3)]
    assert [(c.query_frame, c.matched_frame) for c in result.published] == ([(8, 2)] if consistent else [])
    assert result.outcomes.get("dropped_inconsistent_with_odometry", 0) == (0 if consistent else 1)
    assert result.outcomes["accepted"] == 1 and result.outcomes["pose_ok"] == 1
