"""The nodes' decision chain, run offline on a sequence: what a backend would receive on /loop_closures.

fabmap_node runs :class:`~aefabmap_ros.fabmap.recognizer.PlaceRecognizer` on every frame with the
node's own config (places from dense video, recent places excluded by time, the calibrated
posterior, temporal consistency) and publishes each consistent match as a candidate; verifier_node
verifies the candidate's matched place and, once accepted, re-ranks the query's top candidates by
inliers (``rerank_by_inliers(..., require_best=True)``); for a while after a verified closure it
tracks the loop through frames without a candidate, by their top candidates near the last verified place
and then by the frames nearest it in time (verification/loop_tracking.py). This module does exactly
that on recorded features and words, with the sequence's own stamps, so the online figures (closures published,
false ones, revisits closed) can be measured and tuned in minutes instead of a replay through ROS.

It is verifier_node's own chain (verification/chain.py, with its frame store and odometry gate), fed in
the order a lockstep replay feeds the node: for each frame the odometry up to its stamp, its features and
depths, then FAB-MAP's posterior and detection. With the sequence's odometry (``ChainInputs.odometry``)
closures are gated as the node gates them; without it they are published as the node publishes them on a
robot without odometry (or with ``odometry_gate: false``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer, Recognition
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.chain import LoopClosureChain
from aefabmap_ros.verification.closures import Closure, CountedOutcomes, Detection, Posterior, RankedPlace
from aefabmap_ros.verification.feature_store import DEFAULT_MAX_STORED_FEATURES
from aefabmap_ros.verification.frame_depths import FrameDepths
from aefabmap_ros.verification.frame_store import FrameStore
from aefabmap_ros.verification.gate import ClosureGate
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.relative_pose import CameraModel, RelativePoseConfig


@dataclass(frozen=True)
class ChainClosure:
    """One loop closure of the chain, in frame indices of the sequence."""

    query_frame: int
    matched_frame: int  # the frame the matched place was created from
    probability: float  # FAB-MAP posterior of the detection (kept when verification re-ranks)
    inliers: int = -1  # geometric verification's inliers; -1 = not verified
    tracked: bool = False  # published by loop tracking (no candidate of its own; see verification/loop_tracking.py)
    # Loop tracking matched one of the frames nearest the last verified place in time (not one of the query's top
    # candidates; ``probability`` is its place's posterior when that place is among them, else 0).
    nearby_frame: bool = False


@dataclass
class ChainResult:
    candidates: list[ChainClosure]  # what fabmap_node publishes (loop_closure_candidates)
    published: list[ChainClosure]  # what reaches /loop_closures (verified, or the candidates without verification)
    num_places: int
    # Every informative frame's best hypothesis as place_posteriors reports it: (query frame, frame of the
    # place, posterior) -- for the posterior's calibration.
    best: list[ChainClosure] = field(default_factory=list)
    # (query frame, frame of the place) of every place each frame's posterior reports (its top_k): which
    # revisits the ranking found, whatever the decision after it made of them.
    ranked: list[tuple[int, int]] = field(default_factory=list)
    outcomes: dict[str, int] = field(default_factory=dict)  # the verifier's counters (verifier_node's names)


@dataclass(frozen=True)
class ChainInputs:
    """What verifier_node would receive besides FAB-MAP's answers: each frame's features, and optionally its
    depths (node-style, ``FrameDepths`` at the stored keypoints), the intrinsics and the robot's odometry."""

    config: VerificationConfig
    features: Sequence[Features]
    depths: Sequence[FrameDepths | None] | None = None
    camera: CameraModel | None = None
    image_size: tuple[int, int] | None = None  # (width, height) of the images: the metric test needs it
    odometry: Sequence[tuple[int, gtsam.Pose3]] = ()  # (stamp_ns, T_odom_base), stamps increasing
    pose_config: RelativePoseConfig = field(default_factory=RelativePoseConfig)
    # A fresh odometry gate for each run of the chain (the example backend's, backend/odometry_gate.py, in the
    # evaluation); without one, or without odometry, verified closures are published unchecked.
    gate_factory: Callable[[], ClosureGate] | None = None
    max_stored_features: int = DEFAULT_MAX_STORED_FEATURES
    # Generous: a sequence is replayed in lockstep, so odometry is never late; only one that is missing waits.
    odometry_wait_s: float = 10.0


def run_online_chain(
    observations: sp.csr_matrix,
    stamps_ns: np.ndarray,
    tree: ChowLiuTree,
    new_place_samples: sp.csr_matrix | None,
    config: FabMapConfig,
    verification: ChainInputs | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> ChainResult:
    """Run the chain over (N, V) observations stamped ``stamps_ns`` (N,) increasing nanoseconds.

    With ``verification`` candidates are verified, re-ranked, tracked and gated by verifier_node's chain;
    without it they are published as they are (``--no-verify``).
    """
    matrix = sp.csr_matrix(observations)
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    num_frames = matrix.shape[0]
    if stamps.shape != (num_frames,):
        raise DataError(f"{stamps.size} stamps for {num_frames} frames")
    if num_frames > 1 and np.any(np.diff(stamps) <= 0):
        raise DataError("stamps must increase strictly (the nodes drop out-of-order frames)")
    if verification is not None and len(verification.features) != num_frames:
        raise DataError(f"{len(verification.features)} frames of features for {num_frames} frames")
    matrix.sort_indices()
    recognizer = PlaceRecognizer(tree, new_place_samples, config, "online-chain")
    frame_of = {int(stamp): frame for frame, stamp in enumerate(stamps.tolist())}
    place_frames: list[int] = []
    result = ChainResult([], [], 0)
    feed = None if verification is None else _ChainFeed(verification, frame_of, result.published)
    for frame in range(num_frames):
        words = matrix.indices[matrix.indptr[frame] : matrix.indptr[frame + 1]].astype(np.int64)
        recognition = recognizer.process(words, int(stamps[frame]))
        if recognition.added_place_id >= 0:
            place_frames.append(frame)
        if recognition.candidates:
            top = recognition.candidates[0]
            result.best.append(ChainClosure(frame, place_frames[top.place_id], top.probability))
            result.ranked.extend((frame, place_frames[c.place_id]) for c in recognition.candidates)
        closure = recognition.loop_closure
        if closure is not None:
            candidate = ChainClosure(frame, place_frames[closure.place_id], closure.probability)
            result.candidates.append(candidate)
            if feed is None:
                result.published.append(candidate)
        if feed is not None:
            feed.frame(frame, int(stamps[frame]), recognition)
        if on_frame is not None:
            on_frame(frame)
    result.num_places = recognizer.num_places
    if feed is not None:
        result.outcomes = dict(feed.outcomes.counts)
    return result


class _ChainFeed:
    """One frame after another into verifier_node's chain, in the order a lockstep replay delivers them."""

    def __init__(self, inputs: ChainInputs, frame_of: dict[int, int], published: list[ChainClosure]) -> None:
        self.inputs = inputs
        self.frame_of = frame_of
        self.published = published
        self.outcomes = CountedOutcomes()
        num_frames = max(len(inputs.features), 1)
        # Every frame fits: the evaluation measures the chain's decisions, not the store's bounds.
        store = FrameStore(num_frames, 2**62, inputs.max_stored_features, keep_depths=inputs.depths is not None)
        gate = inputs.gate_factory() if inputs.odometry and inputs.gate_factory is not None else None
        self.chain = LoopClosureChain(store, inputs.config, inputs.pose_config, self._publish, self.outcomes,
                                      gate=gate, max_pending=num_frames, odometry_wait_s=inputs.odometry_wait_s,
                                      max_awaiting_odometry=num_frames)
        self.chain.pairs.camera = inputs.camera
        self.next_odometry = 0

    def frame(self, frame: int, stamp_ns: int, recognition: Recognition) -> None:
        odometry = self.inputs.odometry
        while self.next_odometry < len(odometry) and odometry[self.next_odometry][0] <= stamp_ns:
            self.chain.add_odometry(*odometry[self.next_odometry])
            self.next_odometry += 1
        depths = None if self.inputs.depths is None else self.inputs.depths[frame]
        if depths is not None and self.chain.store.depths is not None:
            self.chain.store.depths.keep(stamp_ns, depths)
        self.chain.add_features(stamp_ns, self.inputs.features[frame], self.inputs.image_size)
        candidates = tuple(RankedPlace(c.place_id, c.stamp_ns, c.probability, c.log_likelihood, c.session, c.robot)
                           for c in recognition.candidates)
        match = recognition.loop_closure
        self.chain.add_posterior(Posterior(stamp_ns, recognition.query_id, recognition.assigned_place_id,
                                           recognition.current_place_id, match is not None, candidates, "",
                                           recognition.session, recognition.robot))
        if match is not None:
            self.chain.add_detection(Detection(stamp_ns, recognition.query_id, recognition.assigned_place_id,
                                               match.place_id, match.stamp_ns, match.probability,
                                               match.log_likelihood, "", recognition.session, recognition.robot,
                                               match.session, match.robot))

    def _publish(self, closure: Closure) -> None:
        detection = closure.detection
        self.published.append(ChainClosure(
            self.frame_of[detection.query_ns], self.frame_of[detection.matched_ns], detection.probability,
            closure.inliers, tracked=closure.tracked, nearby_frame=closure.nearby_frame))
