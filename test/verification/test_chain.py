"""The verification chain without ROS: what it publishes for scripted detections, posteriors and odometry,
checked against scenes with a known answer (two views of known geometry, an aliased one, a known motion)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.odometry_gate import OdometryGate
from aefabmap_ros.backend.pose_graph import PoseGraphConfig
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.chain import LoopClosureChain
from aefabmap_ros.verification.closures import Closure, CountedOutcomes, Detection, Posterior, RankedPlace
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.relative_pose import CameraModel, PoseStatus, RelativePoseConfig
from test.verification.test_geometric import FOCAL, HEIGHT, WIDTH, _rotation_y, _two_views

SECOND = 1_000_000_000
SIZE = (WIDTH, HEIGHT)
CAMERA = CameraModel(np.array([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]]))
# _two_views(seed): place points = R (query points) + t with R = rotation about y by 0.15 rad, t below; the place
# camera in the query camera's frame is therefore (R^T, -R^T t).
TRUE_ROTATION = _rotation_y(0.15).T
TRUE_TRANSLATION = -_rotation_y(0.15).T @ np.array([0.8, 0.1, 0.3])


class Outcomes(CountedOutcomes):
    """Counted as offline, and every drop must say why (the node logs the detail)."""

    def drop(self, reason: str, detail: str, count: int = 1) -> None:
        assert detail
        super().drop(reason, detail, count)


@dataclass
class Rig:
    """A chain with its store, counters and what it published."""

    chain: LoopClosureChain
    outcomes: Outcomes
    published: list[Closure] = field(default_factory=list)

    @property
    def counts(self) -> Counter[str]:
        return self.outcomes.counts

    def features(self, sec: float, features: Features) -> None:
        self.chain.add_features(round(sec * SECOND), features, SIZE)

    def ids(self) -> list[tuple[int, int]]:
        return [(c.detection.query_id, c.detection.matched_place_id) for c in self.published]


def rig(*, gate: bool = False, depths: bool = False, camera: CameraModel | None = None, max_pending: int = 100,
        odometry_wait_s: float = 5.0, max_awaiting_odometry: int = 1000, behind: bool = False,
        too_late: frozenset[int] = frozenset(), depth_wait_s: float = 2.0, **config: object) -> Rig:
    outcomes = Outcomes()
    published: list[Closure] = []
    store = FrameStore(20_000, 2**40, 500, keep_depths=depths)
    chain = LoopClosureChain(store, VerificationConfig(**config), RelativePoseConfig(),  # type: ignore[arg-type]
                             published.append, outcomes,
                             gate=OdometryGate(PoseGraphConfig(), gtsam.Pose3()) if gate else None,
                             max_pending=max_pending, odometry_wait_s=odometry_wait_s,
                             max_awaiting_odometry=max_awaiting_odometry, depth_wait_s=depth_wait_s,
                             behind=lambda _query_ns: behind, too_late=too_late.__contains__)
    chain.pairs.camera = camera
    return Rig(chain, outcomes, published)


def detection(query_sec: float, place_sec: float, query_id: int) -> Detection:
    return Detection(round(query_sec * SECOND), query_id, -1, round(place_sec), round(place_sec * SECOND), 0.995,
                     -3.0)


def posterior(query_sec: float, place_secs: list[int], candidate: bool = True, place_id: int = -1) -> Posterior:
    """fabmap_node's posterior of a query: the places (ids = their seconds) with posteriors 0.9 / 2^rank."""
    ranked = tuple(RankedPlace(sec, sec * SECOND, 0.9 / 2**rank, -float(rank)) for rank, sec in enumerate(place_secs))
    return Posterior(round(query_sec * SECOND), 0, -1, place_id, candidate, ranked)


def test_true_closures_pass_and_the_rest_is_held_back() -> None:
    query, place, _ = _two_views(seed=21)
    _, unrelated, _ = _two_views(seed=22)
    run = rig(max_pending=1, candidates=1, track_seconds=0.0)
    for sec, features in ((1, place), (2, unrelated), (3, query)):
        run.features(sec, features)
    run.chain.add_detection(detection(3, 1, query_id=10))  # a true second view: published
    run.chain.add_detection(detection(3, 2, query_id=11))  # unrelated place: rejected
    run.chain.add_detection(detection(3, 99, query_id=12))  # place never seen
    run.chain.add_detection(detection(5, 1, query_id=13))  # query features not there yet: waits
    run.chain.add_detection(detection(6, 1, query_id=14))  # pushes the waiting one out (max_pending 1)
    run.features(6, query)  # query 14's features arrive: verified now
    broken = Features(query.keypoints[:-1], query.descriptors, query.descriptor_type)
    run.features(7, broken)
    assert [c.detection.query_id for c in run.published] == [10, 14]
    assert all(c.inliers >= 100 for c in run.published)  # 120 shared scene points
    assert run.counts["accepted"] == 2 and run.counts["rejected"] == 1
    assert run.counts["dropped_place_features_unknown"] == 1
    assert run.counts["dropped_query_features_never_came"] == 1 and run.counts["dropped_bad_features"] == 1
    assert len(run.chain.store) == 4 and not run.chain.pending


def test_a_closure_taken_too_late_is_dropped_unverified_and_the_next_one_verified() -> None:
    """A verifier that cannot keep up drops the detections whose features came too long ago (``too_late``)
    without spending a verification on them, counts each, and verifies the next fresh one as before."""
    query, place, _ = _two_views(seed=21)
    run = rig(candidates=1, track_seconds=0.0, too_late=frozenset({3 * SECOND, 4 * SECOND}))
    run.chain.pairs.verify = None  # type: ignore[assignment]  # a late detection must not reach verification
    for sec, features in ((1, place), (3, query), (4, query)):
        run.features(sec, features)
    run.chain.add_detection(detection(3, 1, query_id=30))
    run.chain.add_detection(detection(4, 1, query_id=40))
    assert not run.published and not run.chain.pending
    assert run.counts["dropped_behind"] == 2
    del run.chain.pairs.verify  # the class's own again
    run.features(5, query)
    run.chain.add_detection(detection(5, 1, query_id=50))
    assert run.ids() == [(50, 1)] and run.counts["accepted"] == 1 and "rejected" not in run.counts


def _place_depth(seed: int = 21) -> np.ndarray:
    """Metric depth of _two_views(seed)'s place camera at its shared points (3x3 pixels each), NaN elsewhere."""
    return _view_depth(seed, _rotation_y(0.15), np.array([0.8, 0.1, 0.3]))


def _query_depth(seed: int = 21) -> np.ndarray:
    """The same for _two_views(seed)'s query camera (the scene's own frame)."""
    return _view_depth(seed, np.eye(3), np.zeros(3))


def _view_depth(seed: int, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(seed)  # the same draws as _two_views makes first
    points = np.column_stack([rng.uniform(-4, 4, 120), rng.uniform(-3, 3, 120), rng.uniform(5, 15, 120)])
    camera = points @ rotation.T + translation
    columns = np.rint(FOCAL * camera[:, 0] / camera[:, 2] + WIDTH / 2).astype(int)
    rows = np.rint(FOCAL * camera[:, 1] / camera[:, 2] + HEIGHT / 2).astype(int)
    depth = np.full((HEIGHT, WIDTH), np.nan, dtype=np.float32)
    inside = (columns >= 1) & (rows >= 1) & (columns < WIDTH - 1) & (rows < HEIGHT - 1)
    for row, column, z in zip(rows[inside], columns[inside], camera[inside, 2], strict=True):
        depth[row - 1:row + 2, column - 1:column + 2] = z
    return depth


NO_DEPTH = np.full((HEIGHT, WIDTH), np.nan, dtype=np.float32)


def _angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))


@pytest.mark.parametrize("with_depth", [False, True])
def test_a_closure_carries_the_known_relative_pose(with_depth: bool) -> None:
    """Without intrinsics: verified, no pose (said why); with them the essential matrix's direction; with the
    place's depth the PnP pose in metres, against the scene's known motion."""
    query, place, _ = _two_views(seed=21)
    run = rig(depths=with_depth, candidates=1, track_seconds=0.0)
    run.features(1, place)
    run.features(3, query)
    run.chain.add_detection(detection(3, 1, query_id=10))
    run.chain.pairs.camera = CAMERA
    if with_depth:  # the place's depth only: a later frame's depth image says the query's will not come
        run.chain.add_depth(SECOND, _place_depth())
        run.chain.add_depth(4 * SECOND, NO_DEPTH)
    run.chain.add_detection(detection(3, 1, query_id=11))
    first, second = run.published
    assert first.pose.pose is None and first.pose.status is PoseStatus.NO_CAMERA_INFO
    pose = second.pose.pose
    assert pose is not None and second.pose.status is PoseStatus.OK and pose.metric == with_depth
    assert _angle_deg(pose.rotation @ TRUE_ROTATION.T) <= 1.0
    direction = pose.translation @ TRUE_TRANSLATION / (np.linalg.norm(pose.translation)
                                                       * np.linalg.norm(TRUE_TRANSLATION))
    assert np.degrees(np.arccos(min(direction, 1.0))) <= 3.0
    if with_depth:
        assert np.linalg.norm(pose.translation - TRUE_TRANSLATION) <= 0.05
    assert run.counts["pose_no_camera_info"] == 1 and run.counts["pose_ok"] == 1


def _query_waiting_for_depth(**settings: object) -> tuple[Rig, Features, Features]:
    """A place at 1 s with its depth, and query 10 at 3 s detected against it before its own depth image came."""
    query, place, _ = _two_views(seed=21)
    # The metric test off: its covisibility needs dense depth images, these have depth at the scene points only.
    run = rig(depths=True, camera=CAMERA, candidates=1, track_seconds=0.0, metric_min_inliers=0,
              **settings)  # type: ignore[arg-type]
    run.chain.add_depth(SECOND, _place_depth())
    run.features(1, place)
    run.features(3, query)
    run.chain.add_detection(detection(3, 1, query_id=10))
    return run, query, place


def test_a_query_waits_for_its_own_depth_image_until_it_comes_or_will_not() -> None:
    """A verifier under load takes depth images after the features: a query waits for its own, is verified with
    it when it comes late, and without it only once a later depth image has come (its own was lost) or the
    newest frame is depth_wait_s newer (the depth stream stopped)."""
    run, query, place = _query_waiting_for_depth(depth_wait_s=2.0)
    assert not run.published and list(run.chain.depth_wait.waiting) == [3 * SECOND]
    run.chain.add_depth(3 * SECOND, _query_depth())  # late, but it comes: verified with it
    assert run.ids() == [(10, 1)] and run.counts.get("query_depth_missing", 0) == 0
    assert np.linalg.norm(run.published[0].pose.pose.translation - TRUE_TRANSLATION) <= 0.05  # type: ignore[union-attr]

    run.features(4, query)
    run.chain.add_detection(detection(4, 1, query_id=11))
    assert run.ids() == [(10, 1)]
    run.chain.add_depth(5 * SECOND, NO_DEPTH)  # a later one: query 11's was lost on the way
    assert run.ids() == [(10, 1), (11, 1)] and run.counts["query_depth_missing"] == 1

    run.features(6, query)  # the depth stream stops
    run.chain.add_detection(detection(6, 1, query_id=12))
    run.features(8, place)  # 2 s newer: still waiting
    assert len(run.published) == 2
    run.features(8.5, place)
    assert run.ids()[-1] == (12, 1) and run.counts["query_depth_missing"] == 2
    assert not run.chain.depth_wait.waiting and not run.chain.pending


def test_nothing_waits_for_a_depth_stream_that_never_started() -> None:
    """A depth topic named but silent: closures go out at once, without the metric pose, none counted missing."""
    query, place, _ = _two_views(seed=21)
    run = rig(depths=True, camera=CAMERA, candidates=1, track_seconds=0.0)
    run.features(1, place)
    run.features(3, query)
    run.chain.add_detection(detection(3, 1, query_id=10))
    assert run.ids() == [(10, 1)] and not run.chain.depth_wait.waiting
    assert run.counts.get("query_depth_missing", 0) == 0


def test_a_waiting_query_pushed_out_of_the_pending_detections_waits_no_longer() -> None:
    run, query, _ = _query_waiting_for_depth(max_pending=1)
    run.features(4, query)
    run.chain.add_detection(detection(4, 1, query_id=11))  # pushes query 10 out of max_pending 1
    run.chain.add_depth(4 * SECOND, _query_depth())
    assert run.ids() == [(11, 1)] and not run.chain.depth_wait.waiting
    assert run.counts["dropped_query_posterior_never_came"] == 1


def _weaker_view(features: Features, shared: int, keep: int) -> Features:
    """The same view with only ``keep`` of its ``shared`` scene points (its clutter kept): less overlap."""
    rows = np.r_[0:keep, shared:len(features)]
    return Features(features.keypoints[rows], features.descriptors[rows], features.descriptor_type)


@pytest.mark.parametrize("behind", [False, True])
def test_a_closure_moves_to_the_best_verified_candidate_unless_the_chain_is_behind(behind: bool) -> None:
    query, place, shared = _two_views(seed=24)
    _, unrelated, _ = _two_views(seed=25)
    run = rig(max_pending=2, behind=behind, track_seconds=5.0)  # candidates: 5, re-ranking
    for sec, features in ((1, _weaker_view(place, shared, 35)), (2, unrelated), (3, place), (4, query),
                          (5, query)):
        run.features(sec, features)
    # FAB-MAP matched place 1 (a view sharing 35 points); the posterior also ranks 2 and 3.
    run.chain.add_detection(detection(4, 1, query_id=40))
    assert not run.published and len(run.chain.pending) == 1  # waits for the query's posterior
    run.chain.add_posterior(posterior(4, [1, 2, 3]))
    run.chain.add_posterior(posterior(5, [3, 1], candidate=False))  # a frame loop tracking verifies
    if behind:  # decided by the detection alone (FAB-MAP's place 1), and tracking waits
        assert run.ids() == [(40, 1)]
        assert run.counts["reranking_cut_short_behind"] == 1 and run.counts["tracking_skipped_behind"] == 1
        return
    assert run.ids() == [(40, 3), (0, 3)]
    moved = run.published[0]
    assert moved.detection.matched_ns == 3 * SECOND and moved.inliers >= 100
    assert moved.detection.probability == 0.995  # the detection's confidence is kept
    # A rejected matched place rejects the closure, even when a lower candidate would pass.
    run.chain.add_posterior(posterior(4, [2, 3]))
    run.chain.add_detection(detection(4, 2, query_id=41))
    # Posteriors that never come: the closure is dropped once max_pending newer ones wait.
    for query_sec in (6, 7, 8):
        run.features(query_sec, query)
        run.chain.add_detection(detection(query_sec, 3, query_id=50 + query_sec))
    assert len(run.published) == 2
    assert run.counts["moved_to_better_verified_place"] == 1 and run.counts["rejected"] == 1
    assert run.counts["dropped_query_posterior_never_came"] == 1 and len(run.chain.pending) == 2


def test_a_verified_loop_is_tracked_through_frames_without_a_candidate() -> None:
    query, place, _ = _two_views(seed=26)
    _, unrelated, _ = _two_views(seed=27)
    run = rig(track_seconds=2.0, track_island_seconds=3.0)
    for sec, features in ((1, place), (2, unrelated), (9, unrelated), (10, query), (11, query), (13, query),
                          (20, query)):
        run.features(sec, features)
    run.chain.add_posterior(posterior(11, [2, 1], candidate=False))  # no verified loop yet: nothing to track
    run.chain.add_detection(detection(10, 1, query_id=100))
    run.chain.add_posterior(posterior(10, [1, 2]))  # the detection, verified: the track starts
    run.chain.add_posterior(posterior(11, [2, 9, 1], candidate=False))  # 1 s later, no candidate of its own
    # 2 s after that, a detection of the unrelated place fails; the frame still continues the loop.
    run.chain.add_detection(detection(13, 2, query_id=102))
    run.chain.add_posterior(posterior(13, [2, 1]))
    run.chain.add_posterior(posterior(20, [1], candidate=False))  # 7 s after the last verified closure: over
    closures = [(c.detection.query_id, c.detection.query_ns // SECOND, c.detection.matched_place_id, c.tracked)
                for c in run.published]
    # Place 9 is 8 s from the tracked place 1 in map time: not a tracking candidate (2 is, and fails geometry).
    assert closures == [(100, 10, 1, False), (0, 11, 1, True), (0, 13, 1, True)]
    assert [c.detection.probability for c in run.published] == [0.995, 0.9 / 4, 0.9 / 2]
    assert run.counts["accepted"] == 1 and run.counts["accepted_by_tracking"] == 2 and run.counts["rejected"] == 1
    assert not run.chain.posteriors and not run.chain.pending  # every frame decided once


@pytest.mark.parametrize("track_frames", [5, 0])
def test_tracking_reaches_the_stored_frames_next_to_the_verified_place(track_frames: int) -> None:
    query_a, place_a, _ = _two_views(seed=26)
    query_b, place_b, _ = _two_views(seed=28)
    _, unrelated, _ = _two_views(seed=27)
    run = rig(track_seconds=2.0, track_island_seconds=3.0, track_frames=track_frames, track_min_age_seconds=5.0)
    # The map: scene A at 1 s (place 1), scene B at 2 s (joined place 1), scene B again at 7 s (too recent for
    # a query at 11 s), an unrelated place at 9 s.
    for sec, features, place_id in ((1, place_a, 1), (2, place_b, 1), (7, place_b, 4), (9, unrelated, 9)):
        run.features(sec, features)
        run.chain.add_posterior(posterior(sec, [], candidate=False, place_id=place_id))
    for sec, features in ((10, query_a), (11, query_b)):
        run.features(sec, features)
    run.chain.add_detection(detection(10, 1, query_id=100))
    run.chain.add_posterior(posterior(10, [1, 9]))  # verified: the track starts at place 1 (1 s)
    # 11 s sees scene B; FAB-MAP ranks only the unrelated place: the stored frames nearest 1 s and at least 5 s
    # old are verified next (1 s fails, 2 s passes; 7 s is too recent).
    run.chain.add_posterior(posterior(11, [9], candidate=False))
    tracked = [(c.detection.query_ns // SECOND, c.detection.matched_ns // SECOND, c.detection.matched_place_id,
                c.nearby_frame) for c in run.published[1:]]
    assert tracked == ([(11, 2, 1, True)] if track_frames else [])
    if track_frames:
        assert run.published[1].detection.probability == 0.0 and np.isnan(run.published[1].detection.log_likelihood)


def _scene_with_odometry(seed: int = 21) -> tuple[Features, Features]:
    query, place, _ = _two_views(seed=seed)
    return query, place


PLACE_IN_QUERY = gtsam.Pose3(gtsam.Rot3(TRUE_ROTATION), TRUE_TRANSLATION)
ALIASED = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([20.0, 0.0, 0.0]))  # another corner, 20 m away


@pytest.mark.parametrize(("odometry_at_place", "consistent"), [(PLACE_IN_QUERY, True), (ALIASED, False)])
def test_the_odometry_gate_refuses_what_odometry_contradicts_and_holds_what_it_has_not_reached(
        odometry_at_place: gtsam.Pose3, consistent: bool) -> None:
    query, place = _scene_with_odometry()
    run = rig(gate=True, camera=CAMERA, candidates=1, track_seconds=0.0)
    for sec, features in ((0, place), (1, place), (3, query), (5, query)):
        run.features(sec, features)
    run.chain.add_detection(detection(3, 1, query_id=30))  # no odometry yet: the gate is not active
    for sec, pose in ((1, odometry_at_place), (2, odometry_at_place), (3, gtsam.Pose3())):
        assert run.chain.add_odometry(sec * SECOND, pose)
    assert not run.chain.add_odometry(3 * SECOND, gtsam.Pose3())  # not after the previous one: ignored
    run.chain.add_detection(detection(3, 1, query_id=31))
    run.chain.add_detection(detection(5, 1, query_id=50))  # odometry has not reached 5 s yet: it waits
    assert [c.detection.query_id for c in run.published] == ([30, 31] if consistent else [30])
    assert [c.detection.query_id for c in run.chain.odometry.waiting] == [50]
    for sec in (4, 5):  # the robot stands still at the query's pose
        run.chain.add_odometry(sec * SECOND, gtsam.Pose3())
    assert [c.detection.query_id for c in run.published] == ([30, 31, 50] if consistent else [30])
    assert not run.chain.odometry.waiting
    # Place 0 s: mapped before the odometry began (a reloaded map); odometry cannot judge it, it passes.
    run.chain.add_detection(detection(3, 0, query_id=32))
    assert run.published[-1].detection.query_id == 32
    assert run.counts["unchecked_place_before_odometry"] == 1
    assert run.counts.get("dropped_inconsistent_with_odometry", 0) == (0 if consistent else 2)


def test_late_odometry_is_waited_for_and_only_odometry_that_never_comes_drops_a_closure() -> None:
    """150 closures verified at 50 Hz while odometry lags 2 s behind the frames: every one is decided when its
    odometry comes (none dropped, though more wait at once than the 100 max_pending once allowed); once
    odometry stops, a closure waits odometry_wait_s of frames after its query and is dropped."""
    query, place = _scene_with_odometry()
    run = rig(gate=True, camera=CAMERA, candidates=1, track_seconds=0.0, odometry_wait_s=3.0)
    run.features(1, place)
    run.chain.add_odometry(1 * SECOND, PLACE_IN_QUERY)  # the gate is active
    period_ns, lag_ns = 20_000_000, 2 * SECOND
    stamps_ns = [10 * SECOND + period_ns * index for index in range(150)]
    for index, stamp_ns in enumerate(stamps_ns):
        run.chain.add_features(stamp_ns, query, SIZE)
        run.chain.add_detection(Detection(stamp_ns, index, -1, 1, SECOND, 0.995, -3.0))
        if stamp_ns - lag_ns >= 10 * SECOND:  # the robot stands still at the query's pose from 10 s on
            run.chain.add_odometry(stamp_ns - lag_ns, gtsam.Pose3())
    assert run.counts.get("dropped_odometry_never_came", 0) == 0
    assert len(run.published) == 50 and len(run.chain.odometry.waiting) == 100  # the last 2 s: not reached yet
    assert max(run.chain.odometry.lateness_s) == 2.0  # as the summary reports it: 2 s behind the newest frame
    # Odometry stops; frames go on. The oldest waiting closure (11 s) is dropped once a frame is 3 s newer.
    run.chain.add_features(stamps_ns[-1] + SECOND // 2, place, SIZE)  # 13.48 s: 2.48 s after 11 s
    assert run.counts.get("dropped_odometry_never_came", 0) == 0
    run.chain.add_features(11 * SECOND + 3 * SECOND + period_ns // 2, place, SIZE)  # 14.01 s: 11.00 s expires
    assert run.counts["dropped_odometry_never_came"] == 1 and len(run.chain.odometry.waiting) == 99
    run.chain.add_features(stamps_ns[-1] + 3 * SECOND + 1, place, SIZE)
    assert run.counts["dropped_odometry_never_came"] == 100 and not run.chain.odometry.waiting


def test_waiting_closures_are_bounded_by_count_too() -> None:
    query, place = _scene_with_odometry()
    run = rig(gate=True, camera=CAMERA, candidates=1, track_seconds=0.0, odometry_wait_s=100.0,
              max_awaiting_odometry=3)
    run.features(1, place)
    run.chain.add_odometry(SECOND, gtsam.Pose3())
    for index in range(5):
        run.features(10 + index, query)
        run.chain.add_detection(detection(10 + index, 1, query_id=index))
    assert [c.detection.query_id for c in run.chain.odometry.waiting] == [2, 3, 4]
    assert run.counts["dropped_odometry_never_came"] == 2
