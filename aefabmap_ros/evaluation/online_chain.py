"""The nodes' decision chain, run offline on a sequence: what a backend would receive on /loop_closures.

fabmap_node runs :class:`~aefabmap_ros.fabmap.recognizer.PlaceRecognizer` on every frame with the
node's own config (places from dense video, recent places excluded by time, the calibrated
posterior, temporal consistency) and publishes each consistent match as a candidate; verifier_node
verifies the candidate's matched place and, once accepted, re-ranks the query's top candidates by
inliers (``rerank_by_inliers(..., require_best=True)``); for a while after a verified closure it
tracks the loop through frames without a candidate (verification/loop_tracking.py). This module does exactly
that on recorded features and words, with the sequence's own stamps, so the online figures (closures published,
false ones, revisits closed) can be measured and tuned in seconds instead of a replay through ROS.
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
from aefabmap_ros.verification.geometric import PairVerifier, VerificationConfig, rerank_by_inliers
from aefabmap_ros.verification.loop_tracking import LoopTrack


@dataclass(frozen=True)
class ChainClosure:
    """One loop closure of the chain, in frame indices of the sequence."""

    query_frame: int
    matched_frame: int  # the frame the matched place was created from
    probability: float  # FAB-MAP posterior of the detection (kept when verification re-ranks)
    inliers: int = -1  # geometric verification's inliers; -1 = not verified
    tracked: bool = False  # published by loop tracking (no candidate of its own; see verification/loop_tracking.py)


@dataclass
class ChainResult:
    candidates: list[ChainClosure]  # what fabmap_node publishes (loop_closure_candidates)
    published: list[ChainClosure]  # what reaches /loop_closures (verified, or the candidates without verification)
    num_places: int
    # Every informative frame's best hypothesis as place_posteriors reports it: (query frame, frame of the
    # place, posterior) -- for the posterior's calibration.
    best: list[ChainClosure] = field(default_factory=list)


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
    for frame in range(num_frames):
        words = matrix.indices[matrix.indptr[frame] : matrix.indptr[frame + 1]].astype(np.int64)
        recognition = recognizer.process(words, int(stamps[frame]))
        if recognition.added_place_id >= 0:
            place_frames.append(frame)
        if recognition.candidates:
            top = recognition.candidates[0]
            result.best.append(ChainClosure(frame, place_frames[top.place_id], top.probability))
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
            published = _tracked(frame, int(stamps[frame]), recognition.candidates, place_frames, track,
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
    stamp_ns: int,
    candidates: Sequence[Candidate],
    place_frames: list[int],
    track: LoopTrack,
    config: VerificationConfig,
    verify: PairVerifier,
) -> ChainClosure | None:
    """verifier_node's loop tracking: the query's top candidates near the tracked place, best verified wins."""
    near = track.near(stamp_ns, candidates, lambda candidate: candidate.stamp_ns)[: config.candidates]
    frames = [place_frames[c.place_id] for c in near]
    outcome = rerank_by_inliers(frames, lambda place: verify(frame, place))
    if outcome is None:
        return None
    winner = near[outcome.winner]
    return ChainClosure(frame, frames[outcome.winner], winner.probability, outcome.verification.inliers, tracked=True)
