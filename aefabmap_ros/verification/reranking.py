"""Re-ranking a query's candidates by geometric verification, and verification over a whole sequence.

Re-ranking: verification decides *whether* a query closes a loop, geometry decides *where*. The
best ``candidates`` of a query are all verified, and among the accepted ones the candidate with the
most inliers becomes the match (spatial re-ranking, as in image retrieval: Philbin et al., CVPR
2007). FAB-MAP's posterior over a stretch of similar consecutive frames piles up on one of them for
reasons of word sampling, not viewpoint: on the rtabmap corridor the confident top candidates of
queries 60 and 68 are 4 and 3 frames ahead of the view with the most inliers, just outside the
labelled revisit. The inlier count measures the shared scene directly. The confidence of the match
stays the appearance score of the best-ranked accepted candidate, so re-ranking changes which place
a query is matched to, not how confident the detection is.

Deeper search (the evaluation's "+ GV" rows, ``EvaluationConfig.verify_more_candidates``): when every
one of a query's best candidates fails, the next ones are verified and re-ranked alike. On dense video
the true place often sits at rank 6-10 behind look-alike frames of one stretch: on the dense synthetic
video a true place is among the best 5 for 1,878 of the 2,711 revisiting frames and among the best 10
for 2,015. Online a loop closure's own verification stops at a refused best candidate (FAB-MAP's
detection), and loop tracking keeps to the best ``candidates``: searching deeper there added 8 closures
on the dense video (recall 0.632 -> 0.635), a gain not yet confirmed through the nodes elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import TypeVar

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.frame_depths import DepthGrid, FrameDepths
from aefabmap_ros.verification.geometric import Verification, VerificationConfig, verify_pair
from aefabmap_ros.verification.metric import KeypointDepths
from aefabmap_ros.verification.relative_pose import CameraModel

CandidateT = TypeVar("CandidateT")

PairVerifier = Callable[[int, int], Verification]


@dataclass(frozen=True)
class SequenceDepths:
    """A sequence's depth at each keypoint of each frame (None: that frame has no depth image), with the
    camera that took it: what the metric test needs offline."""

    camera: CameraModel
    image_size: tuple[int, int]  # (width, height)
    keypoint_depths: Sequence[np.ndarray | None]
    depth_grids: Sequence[DepthGrid | None] | None = None  # each frame's depth on its coarse grid
    # Each frame's depths as verifier_node keeps them (at its stored keypoints, from the image as float16):
    # what the offline chain (evaluation/online_chain.py) verifies with.
    stored: Sequence[FrameDepths | None] | None = None

    def pair(self, query: int, place: int) -> KeypointDepths | None:
        query_depths, place_depths = self.keypoint_depths[query], self.keypoint_depths[place]
        if query_depths is None or place_depths is None:
            return None
        grids = self.depth_grids
        return KeypointDepths(self.camera, self.image_size, query_depths, place_depths,
                              None if grids is None else grids[query], None if grids is None else grids[place])


def cached_pair_verifier(features: Sequence[Features], config: VerificationConfig,
                         depths: SequenceDepths | None = None) -> PairVerifier:
    """verify(i, j) on a sequence's features, each pair computed once (methods share candidates); with
    the sequence's keypoint ``depths``, failed pairs get the metric test."""
    cache: dict[tuple[int, int], Verification] = {}
    if depths is not None and len(depths.keypoint_depths) != len(features):
        raise DataError(f"{len(depths.keypoint_depths)} frames of keypoint depths for {len(features)} frames")

    def verify(query: int, place: int) -> Verification:
        key = (query, place)
        if key not in cache:  # without the matched rows: a long sequence verifies many pairs
            pair_depths = None if depths is None else depths.pair(query, place)
            cache[key] = replace(verify_pair(features[query], features[place], config, pair_depths),
                                 matched_rows=None)
        return cache[key]

    return verify


@dataclass(frozen=True)
class Reranked:
    """Outcome of verifying a query's candidates, ranked best first."""

    winner: int  # rank of the accepted candidate with the most inliers: the match
    verification: Verification  # the winner's
    best_accepted: int  # rank of the best-ranked accepted candidate: its score is the match's confidence


def rerank_by_inliers(
    candidates: Iterable[CandidateT], verify: Callable[[CandidateT], Verification], require_best: bool = False,
    first: int = 0,
) -> Reranked | None:
    """Verify ``candidates`` (ranked best first; an iterable may stop early); the accepted one with the most
    inliers wins.

    Ranks in the result index ``candidates``. Ties in inliers go to the better-ranked candidate. With
    ``require_best`` a rejected best candidate rejects the query and nothing else is tried (the
    online verifier: the detection is the best candidate's). With ``first`` > 0 the best ``first``
    candidates decide when one of them is accepted, and the others are verified only when all of them
    fail (the evaluation's deeper search), re-ranked alike. None when no candidate is accepted.
    """
    winner: tuple[int, Verification] | None = None
    best_accepted = -1
    for rank, candidate in enumerate(candidates):
        if rank == first and winner is not None:
            break  # the best ones hold a match: the deeper search is for queries whose best all failed
        result = verify(candidate)
        if not result.accepted:
            if rank == 0 and require_best:
                return None
            continue
        if best_accepted < 0:
            best_accepted = rank
        if winner is None or result.inliers > winner[1].inliers:
            winner = (rank, result)
    if winner is None:
        return None
    return Reranked(winner=winner[0], verification=winner[1], best_accepted=best_accepted)


def verified_scores(scores: np.ndarray, verify: PairVerifier, candidates: int, min_gap: int,
                    more_candidates: int = 0) -> np.ndarray:
    """Score matrix after verification and re-ranking: one entry per query that has an accepted candidate.

    For query i, the eligible places j <= i - min_gap with a positive score are ranked best first
    (ties: the most recent first, as the metrics pick them) and the best ``candidates`` of them are
    verified; when none is accepted, the next ``more_candidates`` (re-ranked alike). The accepted place
    with the most inliers gets the score of the best-ranked accepted place; every other entry of row i
    is 0. A query whose candidates all fail has no loop candidate.
    """
    matrix = np.asarray(scores, dtype=np.float64)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise DataError(f"scores must be a square (N, N) matrix, got shape {matrix.shape}")
    if candidates < 1 or min_gap < 1 or more_candidates < 0:
        raise ConfigError(f"candidates ({candidates}) and min_gap ({min_gap}) must be >= 1, more_candidates "
                          f"({more_candidates}) >= 0")
    out = np.zeros_like(matrix)
    for query in range(min_gap, matrix.shape[0]):
        row = matrix[query, : query - min_gap + 1]
        # Best first; among equal scores the most recent place (the metrics' tie rule).
        order = np.lexsort((-np.arange(row.size), -row))[: candidates + more_candidates]
        ranked = order[row[order] > 0.0]
        outcome = rerank_by_inliers(ranked.tolist(), partial(verify, query), first=candidates)
        if outcome is not None:
            out[query, ranked[outcome.winner]] = row[ranked[outcome.best_accepted]]
    return out
