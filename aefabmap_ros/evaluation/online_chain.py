"""The nodes' decision chain, run offline on a sequence: what a backend would receive on /loop_closures.

fabmap_node runs :class:`~aefabmap_ros.fabmap.recognizer.PlaceRecognizer` on every frame with the
node's own config (places from dense video, recent places excluded by time, the calibrated
posterior, temporal consistency) and publishes each consistent match as a candidate; verifier_node
verifies the candidate's matched place and, once accepted, re-ranks the query's top candidates by
inliers (``rerank_by_inliers(..., require_best=True)``); for a while after a verified closure it
tracks the loop through frames without a candidate, by their top candidates near the last verified place
and then by the frames nearest it in time (verification/loop_tracking.py). This module does exactly
that on recorded features and words, with the sequence's own stamps, so the online figures (closures published,
false ones, revisits closed) can be measured and tuned in seconds instead of a replay through ROS.
verifier_node's odometry gate (backend/odometry_gate.py) is not modelled: it needs relative poses and
odometry, so these figures are the nodes' without odometry (or with ``odometry_gate: false``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import DataError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import Candidate, PlaceRecognizer
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.loop_tracking import FrameTimeline, LoopTrack
from aefabmap_ros.verification.reranking import PairVerifier, rerank_by_inliers


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


def run_online_chain(
    observations: sp.csr_matrix,
    stamps_ns: np.ndarray,
    tree: ChowLiuTree,
    new_place_samples: sp.csr_matrix | None,
    config: FabMapConfig,
    verification: tuple[VerificationConfig, PairVerifier] | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> ChainResult:
    """Run the chain over (N, V) observations stamped ``stamps_ns`` (N,) increasing nanoseconds.

    With ``verification`` (its config and a verifier of (query frame, place frame) pairs, e.g.
    ``cached_pair_verifier``, which the evaluation shares with its "+ GV" rows), candidates are
    verified as verifier_node does; without it they are published as they are (``--no-verify``).
    """
    matrix = sp.csr_matrix(observations)
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    num_frames = matrix.shape[0]
    if stamps.shape != (num_frames,):
        raise DataError(f"{stamps.size} stamps for {num_frames} frames")
    if num_frames > 1 and np.any(np.diff(stamps) <= 0):
        raise DataError("stamps must increase strictly (the nodes drop out-of-order frames)")
    matrix.sort_indices()
    recognizer = PlaceRecognizer(tree, new_place_samples, config, "online-chain")
    place_frames: list[int] = []
    result = ChainResult([], [], 0)
    track = None if verification is None else LoopTrack(verification[0].track_seconds,
                                                         verification[0].track_island_seconds)
    timeline = FrameTimeline(max(num_frames, 1))  # as verifier_node's: each frame's place, from its posterior
    for frame in range(num_frames):
        words = matrix.indices[matrix.indptr[frame] : matrix.indptr[frame + 1]].astype(np.int64)
        recognition = recognizer.process(words, int(stamps[frame]))
        if recognition.added_place_id >= 0:
            place_frames.append(frame)
        if recognition.current_place_id >= 0:
            timeline.add(int(stamps[frame]), recognition.current_place_id)
        if recognition.candidates:
            top = recognition.candidates[0]
            result.best.append(ChainClosure(frame, place_frames[top.place_id], top.probability))
            result.ranked.extend((frame, place_frames[c.place_id]) for c in recognition.candidates)
        closure = recognition.loop_closure
        published: ChainClosure | None = None
        if closure is not None:
            candidate = ChainClosure(frame, place_frames[closure.place_id], closure.probability)
            result.candidates.append(candidate)
            if verification is None:
                published = candidate
            else:
                published = _verified(frame, closure, recognition.candidates, place_frames, *verification)
        if published is None and track is not None and verification is not None and recognition.informative:
            published = _tracked(frame, stamps, recognition.candidates, place_frames, track, timeline,
                                 *verification)
        if published is not None:
            result.published.append(published)
            if track is not None:
                track.accept(int(stamps[frame]), int(stamps[published.matched_frame]))
        if on_frame is not None:
            on_frame(frame)
    result.num_places = recognizer.num_places
    return result


def _verified(
    frame: int,
    closure: Candidate,
    candidates: Sequence[Candidate],
    place_frames: list[int],
    config: VerificationConfig,
    verify: PairVerifier,
) -> ChainClosure | None:
    """verifier_node's decision: the matched place first, then the query's other top candidates."""
    ranked = [closure, *(c for c in candidates if c.place_id != closure.place_id)][: config.candidates]
    frames = [place_frames[c.place_id] for c in ranked]
    outcome = rerank_by_inliers(frames, lambda place: verify(frame, place), require_best=True)
    if outcome is None:
        return None
    return ChainClosure(frame, frames[outcome.winner], closure.probability, outcome.verification.inliers)


def _tracked(
    frame: int,
    stamps: np.ndarray,
    candidates: Sequence[Candidate],
    place_frames: list[int],
    track: LoopTrack,
    timeline: FrameTimeline,
    config: VerificationConfig,
    verify: PairVerifier,
) -> ChainClosure | None:
    """verifier_node's loop tracking: the query's top candidates near the tracked place, then the frames
    nearest that place in time not tried yet; the best verified of the first group that has one wins."""
    stamp_ns = int(stamps[frame])
    near = track.near(stamp_ns, candidates, lambda candidate: candidate.stamp_ns)[: config.candidates]
    frames = [place_frames[c.place_id] for c in near]
    outcome = rerank_by_inliers(frames, lambda place: verify(frame, place))
    if outcome is not None:
        winner = near[outcome.winner]
        return ChainClosure(frame, frames[outcome.winner], winner.probability, outcome.verification.inliers,
                            tracked=True)
    tried = {int(stamps[place]) for place in frames}
    nearby = track.nearby_frames(stamp_ns, timeline, config.track_frames,
                                 round(config.track_min_age_seconds * 1e9))
    others = [int(np.searchsorted(stamps, nearby_ns)) for nearby_ns in nearby if nearby_ns not in tried]
    outcome = rerank_by_inliers(others, lambda place: verify(frame, place))
    if outcome is None:
        return None
    matched = others[outcome.winner]
    place_id = timeline.place_of(int(stamps[matched]))
    ranked = [c.probability for c in candidates if c.place_id == place_id]
    return ChainClosure(frame, matched, ranked[0] if ranked else 0.0, outcome.verification.inliers, tracked=True,
                        nearby_frame=True)
