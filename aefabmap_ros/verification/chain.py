"""The verifier's decision chain, without ROS: from FAB-MAP's detections and posteriors to verified closures.

verifier_node feeds it what arrives on its topics; the offline evaluation (evaluation/online_chain.py)
feeds it a recorded sequence. Both therefore publish the same closures for the same inputs.

- **Verification** (verification/geometric.py): a detection's query is matched against its place's
  stored features; it passes with enough inliers of one fundamental matrix (or the metric test, with
  depth and intrinsics).
- **Re-ranking** (``candidates`` > 1, verification/reranking.py): once the detected place is accepted,
  the query's other top candidates from its posterior are verified too, and the closure goes to the
  accepted one with the most inliers -- the view that shares the most scene with the query. The
  detection's ``probability`` and ``log_likelihood`` stay.
- **Loop tracking** (``track_seconds`` > 0, verification/loop_tracking.py): for a while after a
  verified closure, a frame without a detection of its own (or whose detection failed) is verified
  against its top candidates near the last verified place in map time, then against the stored frames
  nearest that place (at least ``track_min_age_seconds`` older than the query). Such a closure carries
  that place's posterior, 0 when the query's candidates do not include it (log-likelihood NaN).
- **Waiting for inputs**: a detection can come before its query's features or posterior (separate
  topics); it waits, ``max_pending`` detections at most. With depth, a query also waits for its own
  depth image until it comes or will not (verification/depth_wait.py).
- **Odometry gate** (verification/odometry_wait.py): a verified closure is published when odometry
  agrees with its relative pose, or waits for odometry to reach its stamps.
- **Several robots** (docs/fleet.md): frames come from each robot's feature server with their depths
  (``add_frame``) and are stored with the robot's name. A frame whose stamp is stored for another robot is
  dropped (``stamp_of_another_robot``); a detection whose query or place is not the robot it names is dropped
  (``robot_mismatch``), and so is one between two robots whose cameras differ (``cameras_differ``): it is
  never verified against another robot's frame or through the wrong camera. Loop tracking and the odometry
  gate are per robot.
- **Behind the camera** (``behind``, verifier_node's ``max_lag_s``): a query the chain takes too late is
  checked against its detection only, and loop tracking skips it, so a live verifier catches up. Further
  behind still (``too_late``, ``drop_after_lag_s``), detections are dropped unverified: the verifier's lag
  stays bounded when even the detections alone cost more than the camera leaves it.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping

import gtsam
import numpy as np

from aefabmap_ros.errors import AefabmapError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.closures import Closure, Detection, Outcomes, Posterior
from aefabmap_ros.verification.depth_wait import DepthWait
from aefabmap_ros.verification.frame_depths import FrameDepths
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.gate import ClosureGate
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.loop_tracking import LoopTracks
from aefabmap_ros.verification.odometry_wait import OdometryWait
from aefabmap_ros.verification.pair_check import PairCheck
from aefabmap_ros.verification.places import Match, PlaceSessions, PlaceToVerify, ranked_places
from aefabmap_ros.verification.relative_pose import RelativePoseConfig
from aefabmap_ros.verification.reranking import rerank_by_inliers
from aefabmap_ros.verification.tracking_search import TrackingSearch

# Posteriors kept by query stamp: a detection is decided right after its query's posterior, so only the
# last few are ever looked up; the rest bounds memory when no detections come.
POSTERIOR_HISTORY = 1000


def pair_refusal(store: FrameStore, pairs: PairCheck, detection: Detection) -> tuple[str, str] | None:
    """(drop name, why) when a detection's frames are not the robots it names, or their cameras differ."""
    text = f"loop closure query {detection.query_id} -> place {detection.matched_place_id}"
    if not (store.belongs(detection.query_ns, detection.query_robot)
            and store.belongs(detection.matched_ns, detection.matched_robot)):
        owners = store.robot_of(detection.query_ns), store.robot_of(detection.matched_ns)
        return "robot_mismatch", (f"{text}: the stored frames at its stamps are robots {owners[0]!r} and "
                                  f"{owners[1]!r}, not {detection.query_robot!r} and {detection.matched_robot!r}")
    if pairs.cameras_differ(detection.query_ns, detection.matched_ns):
        return "cameras_differ", (f"{text}: robots {detection.query_robot!r} and {detection.matched_robot!r} have "
                                  "different cameras (one camera is assumed for a pair)")
    return None


def _never_behind(_query_ns: int) -> bool:
    return False


def _no_log(_text: str, _throttled: bool) -> None:
    return None


class LoopClosureChain:
    """Detections, posteriors, features, depths and odometry in; verified closures out (``publish``)."""

    def __init__(self, store: FrameStore, config: VerificationConfig, pose_config: RelativePoseConfig,
                 publish: Callable[[Closure], None], outcomes: Outcomes, *, gate: ClosureGate | None = None,
                 max_pending: int = 100, odometry_wait_s: float = 10.0, max_awaiting_odometry: int = 1000,
                 depth_wait_s: float = 2.0, behind: Callable[[int], bool] = _never_behind,
                 too_late: Callable[[int], bool] = _never_behind, log: Callable[[str, bool], None] = _no_log,
                 robot_gates: Mapping[str, ClosureGate] | None = None) -> None:
        """``gate``: the odometry gate of the one robot (every closure's); ``robot_gates``: several robots' own."""
        self.store = store
        self.pairs = PairCheck(store, config, pose_config, outcomes)
        self.outcomes = outcomes
        self.max_pending = max_pending
        self.behind, self.too_late = behind, too_late  # how far behind a live camera (verifier_node's clock)
        self.log = log
        self.tracks = LoopTracks(config.track_seconds, config.track_island_seconds)
        self.odometry = OdometryWait(gate, odometry_wait_s, max_awaiting_odometry, self.tracks, publish, outcomes,
                                     robot_gates)
        self.depth_wait = DepthWait(depth_wait_s, outcomes)
        self.pending: OrderedDict[int, Detection] = OrderedDict()  # query stamp -> detection, oldest first
        self.posteriors: OrderedDict[int, Posterior] = OrderedDict()  # query stamp -> posterior
        self.place_sessions = PlaceSessions()
        self.search = TrackingSearch(store, self.pairs, self.place_sessions, lambda: self.pairs.config)

    @property
    def config(self) -> VerificationConfig:
        return self.pairs.config

    @property
    def needs_posteriors(self) -> bool:
        return self.config.candidates > 1 or self.tracks.enabled

    # ------------------------------------------------------------------------------------------ inputs

    def add_features(self, stamp_ns: int, features: Features, image_size: tuple[int, int] | None = None) -> bool:
        """A frame's features (``image_size``: its image's width and height, when known); False: malformed."""
        try:
            stored = self.store.add_features(stamp_ns, features)
        except AefabmapError as exc:
            self.outcomes.drop("bad_features", str(exc))
            return False
        self.odometry.frame_seen(stamp_ns)
        self.depth_wait.frame_came(stamp_ns)
        if image_size is not None:  # one camera: its images' size, for the metric test
            self.pairs.image_size = image_size
        if self.store.depths is not None:
            try:
                self.store.depths.add_features(stamp_ns, stored.keypoints, image_size)
            except AefabmapError as exc:  # its depth image, come first, is of another size: not kept
                self.outcomes.drop("depth_size_mismatch", f"frame at stamp {stamp_ns}: {exc}")
            self.store.depths_changed(stamp_ns)
        self._verify_if_ready(stamp_ns)
        self._verify_waiting_for_depth()
        return True

    def add_frame(self, stamp_ns: int, robot: str, features: Features, depths: FrameDepths | None) -> bool:
        """Several robots: a frame of ``robot`` as its feature server sent it (features and, with a depth camera,
        their depths: no depth image follows). False: dropped (malformed, or its stamp is another robot's)."""
        owner = self.store.robot_of(stamp_ns)
        if stamp_ns in self.store and owner is not None and owner != robot:
            self.outcomes.drop("stamp_of_another_robot", f"a frame of robot {robot!r} at stamp {stamp_ns}, already "
                               f"stored for robot {owner!r}: not kept (frames are keyed by stamp)")
            return False
        try:
            self.store.add_features(stamp_ns, features, robot)
        except AefabmapError as exc:
            self.outcomes.drop("bad_features", str(exc))
            return False
        if depths is not None and self.store.depths is not None:
            self.store.depths.keep(stamp_ns, depths)
            self.store.depths_changed(stamp_ns)
        self.odometry.frame_seen(stamp_ns)
        self._verify_if_ready(stamp_ns)
        return True

    def add_depth(self, stamp_ns: int, depth_m: np.ndarray) -> None:
        """A frame's depth image in metres (AefabmapError when it cannot be kept)."""
        if self.store.depths is None:
            return
        self.depth_wait.depth_came(stamp_ns)  # before keeping it: an image that cannot be kept is still a later one
        try:
            self.store.depths.add_depth(stamp_ns, depth_m)
            self.store.depths_changed(stamp_ns)
        finally:
            self._verify_waiting_for_depth()

    def add_posterior(self, posterior: Posterior) -> None:
        if posterior.query_id >= 0 and posterior.current_place_id >= 0:
            self.store.add_place(posterior.query_ns, posterior.current_place_id)
        self.posteriors[posterior.query_ns] = posterior
        self.posteriors.move_to_end(posterior.query_ns)
        self.place_sessions.learn(posterior)
        while len(self.posteriors) > POSTERIOR_HISTORY:
            self.posteriors.popitem(last=False)
        self._verify_if_ready(posterior.query_ns)

    def add_detection(self, detection: Detection) -> None:
        query_ns = detection.query_ns
        self.pending[query_ns] = detection
        self.pending.move_to_end(query_ns)
        while len(self.pending) > self.max_pending:
            oldest_ns, oldest = self.pending.popitem(last=False)
            if oldest_ns not in self.store:
                self.outcomes.drop("query_features_never_came",
                                   f"no features stamped like the closure of query {oldest.query_id}")
            else:
                self.outcomes.drop("query_posterior_never_came",
                                   f"no place_posteriors message for query {oldest.query_id} "
                                   "(candidates: 1 verifies without them)")
        self._verify_if_ready(query_ns)

    def add_odometry(self, stamp_ns: int, pose: gtsam.Pose3, robot: str | None = None) -> bool:
        """``T_odom_base`` at ``stamp_ns`` (of ``robot``, several robots); False (ignored) unless after the previous
        one."""
        return self.odometry.add_odometry(stamp_ns, pose, robot)

    # ---------------------------------------------------------------------------------------- decisions

    def _verify_if_ready(self, query_ns: int) -> None:
        """Verify a query's detection once its features (and posterior, to re-rank) are in; track a loop
        through a frame without a detection once its features and posterior are in."""
        if query_ns not in self.store:
            return
        posterior = self.posteriors.get(query_ns)
        if query_ns in self.pending:
            if (self.config.candidates > 1 and posterior is None) or not self._depth_ready(query_ns):
                return
            self.posteriors.pop(query_ns, None)  # this frame is done
            self._verify(self.pending.pop(query_ns), posterior)
        elif posterior is not None and not posterior.loop_closure_candidate:
            if not self._depth_ready(query_ns):
                return
            del self.posteriors[query_ns]  # this frame is done: no detection will come for it
            self._track(posterior)

    def _depth_ready(self, query_ns: int) -> bool:
        """The query's depth image is in, or will not come (verification/depth_wait.py)."""
        return self.depth_wait.ready(query_ns, self.store.depths is None or query_ns in self.store.depths)

    def _verify_waiting_for_depth(self) -> None:
        """The queries waiting for their depth image whose wait a new input may have ended, oldest first."""
        for query_ns in self.depth_wait.waiting_among(lambda stamp: stamp in self.pending or stamp in self.posteriors):
            self._verify_if_ready(query_ns)

    def _usable(self, query_ns: int) -> Callable[[int, str], bool]:
        """Which places the query may be checked against: frames of the robot they name, through one camera."""
        return lambda stamp_ns, robot: self.store.belongs(stamp_ns, robot) \
            and not self.pairs.cameras_differ(query_ns, stamp_ns)

    def _verify(self, detection: Detection, posterior: Posterior | None) -> None:
        query_ns = detection.query_ns
        if self.too_late(query_ns):  # too far behind the camera to verify it: dropped so the chain catches up
            self.outcomes.drop("behind", f"loop closure query {detection.query_id} dropped unverified, far behind")
            return
        query, matched = self.store.get(query_ns), self.store.get(detection.matched_ns)
        if query is None or matched is None:
            self.outcomes.drop("place_features_unknown",
                               f"no stored features of place {detection.matched_place_id} (before this node "
                               "started, or forgotten by the store's bounds)")
            return
        refusal = pair_refusal(self.store, self.pairs, detection)
        if refusal is not None:
            self.outcomes.drop(*refusal)
            return
        candidates = [PlaceToVerify(detection.matched_place_id, detection.matched_ns, matched,
                                    detection.matched_session, detection.matched_robot)]
        if posterior is not None:
            others = [place for _, place in ranked_places(self.store, posterior, self._usable(query_ns))
                      if place.place_id != detection.matched_place_id]
            candidates += others[: self.config.candidates - 1]
        try:
            outcome = rerank_by_inliers(
                self._within_lag(query_ns, candidates),
                lambda place: self.pairs.verify(query_ns, query, place.stamp_ns, place.features), require_best=True)
        except AefabmapError as exc:
            self.outcomes.drop("unverifiable", str(exc))
            return
        text = f"loop closure query {detection.query_id} -> place {detection.matched_place_id}"
        if outcome is None:
            self.outcomes.ok("rejected")
            self.log(f"{text} rejected: fewer than {self.config.min_inliers} inliers", True)
            if posterior is not None:
                self._track(posterior)  # the detection failed; the frame may still continue a verified loop
            return
        self.outcomes.ok("accepted")
        winner = candidates[outcome.winner]
        if outcome.winner > 0:
            self.outcomes.ok("moved_to_better_verified_place")
            text += f" moved to place {winner.place_id} (candidate {outcome.winner + 1})"
        self.log(f"{text} accepted: {outcome.verification.inliers} inliers of {outcome.verification.matches} "
                 "matches", False)
        moved = Detection(query_ns, detection.query_id, detection.query_place_id, winner.place_id, winner.stamp_ns,
                          detection.probability, detection.log_likelihood, detection.frame_id,
                          detection.query_session, detection.query_robot, winner.session, winner.robot)
        self._submit(moved, query, Match(winner, detection.probability, detection.log_likelihood,
                                         outcome.verification))

    def _within_lag(self, query_ns: int, candidates: list[PlaceToVerify]) -> Iterator[PlaceToVerify]:
        """The detection, then the other candidates while the chain is not behind: re-ranking stops where the
        time is spent, so a live closure goes out soon after its features."""
        for rank, candidate in enumerate(candidates):
            if rank > 0 and self.behind(query_ns):
                self.outcomes.ok("reranking_cut_short_behind")
                return
            yield candidate

    def _track(self, posterior: Posterior) -> None:
        """Loop tracking: the frame's top candidates near the last verified place, then the stored frames
        nearest that place; the accepted one with the most inliers is published."""
        query_ns = posterior.query_ns
        query = self.store.get(query_ns)
        track = self.tracks.of(posterior.robot)
        if query is None or not track.is_active(query_ns) or not self.store.belongs(query_ns, posterior.robot):
            return
        if self.behind(query_ns):
            self.outcomes.ok("tracking_skipped_behind")
            return
        usable = self._usable(query_ns)
        try:
            tried: set[int] = set()
            match = self.search.candidates(track, query_ns, query, posterior, tried, usable)
            if match is None:
                match = self.search.nearby_frames(track, query_ns, query, posterior, tried, usable)
        except AefabmapError as exc:
            self.outcomes.drop("unverifiable", str(exc))
            return
        if not tried:
            return
        if match is None:
            self.outcomes.ok("track_rejected")
            return
        place = match.place
        self.outcomes.ok("accepted_by_tracking")
        self.log(f"loop closure query {posterior.query_id} -> place {place.place_id} tracked: "
                 f"{match.verification.inliers} inliers of {match.verification.matches} matches", True)
        detection = Detection(query_ns, posterior.query_id, posterior.assigned_place_id, place.place_id,
                              place.stamp_ns, match.probability, match.log_likelihood, posterior.frame_id,
                              posterior.session, posterior.robot, place.session, place.robot)
        self._submit(detection, query, match, tracked=True)

    def _submit(self, detection: Detection, query: Features, match: Match, tracked: bool = False) -> None:
        """The closure with its relative pose, to the odometry gate."""
        place = match.place
        self.place_sessions.accepted(place.session, place.robot)
        pose = self.pairs.pose(detection.query_ns, query, place.stamp_ns, place.features, match.verification)
        self.odometry.submit(Closure(detection, match.verification.inliers, pose, tracked, match.nearby_frame))
