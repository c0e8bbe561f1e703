"""Geometric verification of loop-closure candidates (epipolar consistency of feature matches).

FAB-MAP scores appearance only: two corridors with the same doors and lights share their visual
words, and the posterior can be confident about the wrong one. A real revisit also shares the
*geometry*: the query's and the place's keypoints are related by one fundamental matrix. This
module matches the two images' descriptors (mutual nearest neighbours with Lowe's ratio test),
fits a fundamental matrix robustly (OpenCV's USAC MAGSAC++) and counts the matches consistent
with it. A candidate is accepted when at least ``min_inliers`` matches are.

The check uses the image features themselves, not the visual words, so it is independent of the
vocabulary and applies to every method alike (FAB-MAP and tf-idf).

Why a fundamental matrix, not a homography: the scene is 3-D and the camera translates; why
MAGSAC++: it needs no hand-tuned inlier threshold to be robust to the outlier ratios of aliased
corridors. An 8-point model fits a handful of random matches by chance, so the inlier count is
compared with a floor of matches well above 8: the default, 20 inliers, is RTAB-Map's
(``Vis/MinInliers``); on our selection data (the synthetic test town) 20 and 30 give a higher
average precision than 15 or 10, and random matches between distant frames fit 10-13 "inliers".

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
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import ClassVar, TypeVar

import cv2
import numpy as np

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.features.descriptors import BINARY, FLOAT, kind_of
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.features.matching import (
    NearestNeighbours,
    check_features,
    match_indices,
    nearest_neighbours,
    ratio_test_matches,
)
from aefabmap_ros.io.chunk_folder import ChunkFolder
from aefabmap_ros.io.npz_files import read_versioned_npz
from aefabmap_ros.verification.frame_depths import DepthGrid
from aefabmap_ros.verification.metric import KeypointDepths, MetricCheck, metric_check
from aefabmap_ros.verification.relative_pose import CameraModel

CandidateT = TypeVar("CandidateT")

STORE_FORMAT_VERSION = 1
MIN_MODEL_MATCHES = 8  # the fundamental matrix needs 8 correspondences (7 with a cubic, OpenCV uses 8)


@dataclass(frozen=True)
class VerificationConfig:
    """Geometric verification parameters."""

    min_inliers: int = field(
        default=25,
        metadata={"description": "A candidate is accepted when at least this many matches fit one fundamental "
                  "matrix (>= 8)."},
    )
    min_inlier_ratio: float = field(
        default=0.12,
        metadata={"description": "A candidate is accepted only when its inliers are at least this fraction of the "
                  "keypoints of the image with fewer (the two views share that much scene; 0 = off), in [0, 1]. "
                  "Measured: a repeated texture (a chain-store front, a zebra crossing) or a street seen far ahead "
                  "gives 20-40 inliers but under 10 % of the keypoints; true revisits 10-67 %."},
    )
    ratio: float = field(
        default=0.8,
        metadata={"description": "Lowe's ratio test: a match is kept when its distance is below ratio times "
                  "the second-nearest one, in (0, 1]."},
    )
    ransac_threshold_px: float = field(
        default=2.0,
        metadata={"description": "Maximum distance (pixels) of an inlier from its epipolar line, > 0."},
    )
    confidence: float = field(
        default=0.999, metadata={"description": "Robust estimation confidence, in (0, 1)."}
    )
    max_iterations: int = field(
        default=10000, metadata={"description": "Robust estimation iterations at most, >= 1."}
    )
    metric_min_inliers: int = field(
        default=30,
        metadata={"description": "With depth and intrinsics (verification/metric.py): a candidate the epipolar test "
                  "rejects is accepted when at least this many matches fit one rigid motion of the place's 3-D "
                  "keypoints (PnP, ransac_threshold_px) and metric_min_view_overlap holds (0 = off, else >= 8). "
                  "Measured on the dense synthetic video with its depth, through the nodes: recall 0.551 -> 0.621 "
                  "of the revisiting frames, no false closure added."},
    )
    metric_min_view_overlap: float = field(
        default=0.5,
        metadata={"description": "The metric test's overlap: at least this share of the query's keypoints with "
                  "depth land in the place's view under that motion, in [0, 1]; asked too of a pair the epipolar "
                  "test accepts whose inliers fit one motion."},
    )
    metric_min_covisibility: float = field(
        default=0.3,
        metadata={"description": "With the depth images too (a coarse grid of each, verification/frame_depths.py): at "
                  "least this share of the query's pixels with depth land on the place's own surface under the "
                  "motion (the covisibility ground truth's rule, occlusion included), in [0, 1] (0 = off); asked "
                  "with metric_min_view_overlap. Measured: it refuses the demo's one false closure (the same corner "
                  "31 degrees round: keypoints 62 % in view, surface 22 % covisible) and, with the motion both "
                  "depths agree on (relative_pose), 1 of 2,000 accepted true pairs of the dense synthetic video: "
                  "no recall lost there."},
    )
    metric_depth_tolerance_m: float = field(
        default=0.05,
        metadata={"description": "The covisibility test: a pixel lands on the place's surface when its depth there "
                  "agrees within this plus metric_depth_relative_tolerance times the depth (metres, >= 0)."},
    )
    metric_depth_relative_tolerance: float = field(
        default=0.05,
        metadata={"description": "The covisibility test's tolerance growing with depth, >= 0: looser than the ground "
                  "truth's 1 %, because the motion is estimated. On 2,000 accepted true pairs of the dense synthetic "
                  "video, 33 with a good motion fell under 0.3 at 1 %, one at 5 %."},
    )
    metric_ratio: float = field(
        default=0.9,
        metadata={"description": "Lowe's ratio of the matches the metric test fits its motion to, in (0, 1]: "
                  "looser than ratio, because there a 2-D reprojection test and the view overlap keep chance "
                  "matches out, not the ratio test, and a street seen from further back keeps more of its true "
                  "matches at 0.9 than at 0.8."},
    )
    candidates: int = field(
        default=5,
        metadata={"description": "The best this many candidates of a query are verified; of those accepted, the "
                  "one with the most inliers is the match (re-ranking; 1 = verify only the best; online, "
                  "fabmap_node's top_k bounds it) (>= 1)."},
    )

    track_seconds: float = field(
        default=1.0,
        metadata={"description": "Loop tracking (verification/loop_tracking.py): for this long after a verified "
                  "closure, a frame without one is verified against its top candidates that lie within "
                  "track_island_seconds of the last verified place (seconds; 0 = off). Measured on the dense "
                  "synthetic video: recall 0.41 -> 0.51 of the revisiting frames, no false closure added."},
    )
    track_island_seconds: float = field(
        default=3.0,
        metadata={"description": "How far (map time, seconds) from the last verified place a tracked candidate may "
                  "lie, >= 0."},
    )
    track_frames: int = field(
        default=5,
        metadata={"description": "Loop tracking, when none of the frame's top candidates near the last verified "
                  "place passes: this many frames of the map nearest that place in time (within "
                  "track_island_seconds) are verified next, whether or not FAB-MAP ranks them (0 = off, >= 0). "
                  "Measured on the dense synthetic video: recall 0.519 -> 0.551 of the revisiting frames, no "
                  "false closure added."},
    )
    track_min_age_seconds: float = field(
        default=5.0,
        metadata={"description": "A frame verified by loop tracking is at least this much older than the query "
                  "(seconds, >= 0); keep it >= fabmap_node's exclude_recent_seconds, so a track never closes a "
                  "loop onto the frames just seen."},
    )

    def __post_init__(self) -> None:
        def bad(name: str, rule: str) -> ConfigError:
            return ConfigError(f"VerificationConfig.{name} = {getattr(self, name)!r}: must be {rule}")

        for name in ("min_inliers", "max_iterations", "candidates", "track_frames", "metric_min_inliers"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise bad(name, "an integer")
        for name in ("ratio", "ransac_threshold_px", "confidence", "min_inlier_ratio", "track_seconds",
                     "track_island_seconds", "track_min_age_seconds", "metric_min_view_overlap", "metric_ratio",
                     "metric_min_covisibility", "metric_depth_tolerance_m", "metric_depth_relative_tolerance"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
                raise bad(name, "a finite number")
        if self.min_inliers < MIN_MODEL_MATCHES:
            raise bad("min_inliers", f">= {MIN_MODEL_MATCHES}")
        for name in ("ratio", "metric_ratio"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise bad(name, "in (0, 1]")
        if not 0.0 <= self.min_inlier_ratio <= 1.0:
            raise bad("min_inlier_ratio", "in [0, 1]")
        if self.metric_min_inliers != 0 and self.metric_min_inliers < MIN_MODEL_MATCHES:
            raise bad("metric_min_inliers", f"0 (off) or >= {MIN_MODEL_MATCHES}")
        for name in ("metric_min_view_overlap", "metric_min_covisibility"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise bad(name, "in [0, 1]")
        if self.ransac_threshold_px <= 0.0:
            raise bad("ransac_threshold_px", "> 0")
        if not 0.0 < self.confidence < 1.0:
            raise bad("confidence", "in (0, 1)")
        if self.max_iterations < 1:
            raise bad("max_iterations", ">= 1")
        if self.candidates < 1:
            raise bad("candidates", ">= 1")
        for name in ("track_seconds", "track_island_seconds", "track_min_age_seconds", "track_frames",
                     "metric_depth_tolerance_m", "metric_depth_relative_tolerance"):
            if getattr(self, name) < 0:
                raise bad(name, ">= 0")


@dataclass(frozen=True)
class Verification:
    """Outcome of verifying one (query, place) pair."""

    matches: int  # descriptor matches that passed the ratio test
    inliers: int  # of those, consistent with the fitted fundamental matrix
    accepted: bool
    metric: MetricCheck | None = None  # the metric test's outcome, when it ran (it needs depth)
    # The epipolar test's own decision: with depth, the metric test may accept a pair it refused for its share
    # of the keypoints, or refuse one it accepted whose views do not overlap.
    epipolar_accepted: bool = False
    # (M, 2) keypoint rows of the matches (query, place): an accepted pair's relative pose is computed from
    # the same matches without matching again. Not part of the outcome's value.
    matched_rows: np.ndarray | None = field(default=None, repr=False, compare=False)


def match_descriptors(query: Features, place: Features, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """The matches of ``features.matching.match_indices`` as (M, 2) float32 query points and (M, 2) place points."""
    return matched_points(query, place, match_indices(query, place, ratio=ratio))


def matched_points(query: Features, place: Features, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) float32 image points of matched keypoint ``rows`` (query row, place row)."""
    return (np.ascontiguousarray(query.keypoints[rows[:, 0], :2], dtype=np.float32),
            np.ascontiguousarray(place.keypoints[rows[:, 1], :2], dtype=np.float32))


def fundamental_matrix(query_points: np.ndarray, place_points: np.ndarray,
                       config: VerificationConfig) -> tuple[np.ndarray | None, np.ndarray]:
    """A fundamental matrix robustly fitted to the matches (MAGSAC++; ``x_place^T F x_query = 0``) and its
    (M,) bool inliers; (None, no inliers) when none fits."""
    if query_points.shape != place_points.shape or query_points.ndim != 2 or query_points.shape[1] != 2:
        raise DataError(f"point arrays must both be (M, 2), got {query_points.shape} and {place_points.shape}")
    none = np.zeros(query_points.shape[0], bool)
    if query_points.shape[0] < MIN_MODEL_MATCHES:
        return None, none
    try:
        matrix, mask = cv2.findFundamentalMat(query_points, place_points, cv2.USAC_MAGSAC,
                                              config.ransac_threshold_px, config.confidence, config.max_iterations)
    except cv2.error:  # degenerate configurations (all points on a line, ...): no model, no inliers
        return None, none
    if mask is None or matrix is None or matrix.shape != (3, 3):
        return None, none
    return matrix, mask.ravel().astype(bool)


def epipolar_inliers(query_points: np.ndarray, place_points: np.ndarray, config: VerificationConfig) -> np.ndarray:
    """(M,) bool: the matches consistent with one robustly fitted fundamental matrix (none when none fits)."""
    return fundamental_matrix(query_points, place_points, config)[1]


def within_epipolar_distance(matrix: np.ndarray, query_points: np.ndarray, place_points: np.ndarray,
                             threshold_px: float) -> np.ndarray:
    """(M,) bool: matches whose points both lie within ``threshold_px`` of the epipolar line the other's
    point gives under ``matrix`` (the fundamental matrix of :func:`fundamental_matrix`)."""
    if query_points.shape[0] == 0:
        return np.zeros(0, bool)

    def distances(points: np.ndarray, lines: np.ndarray) -> np.ndarray:
        lines = lines.reshape(-1, 3)
        return np.asarray(np.abs(np.sum(lines[:, :2] * points, axis=1) + lines[:, 2])
                          / np.hypot(lines[:, 0], lines[:, 1]))

    in_place = cv2.computeCorrespondEpilines(query_points.reshape(-1, 1, 2), 1, matrix)
    in_query = cv2.computeCorrespondEpilines(place_points.reshape(-1, 1, 2), 2, matrix)
    return (distances(place_points, in_place) <= threshold_px) & (distances(query_points, in_query) <= threshold_px)


def count_epipolar_inliers(query_points: np.ndarray, place_points: np.ndarray, config: VerificationConfig) -> int:
    """Matches consistent with one robustly fitted fundamental matrix (0 when none can be fitted)."""
    return int(np.count_nonzero(epipolar_inliers(query_points, place_points, config)))


def verify_pair(query: Features, place: Features, config: VerificationConfig,
                depths: KeypointDepths | None = None) -> Verification:
    """Geometric verification of one candidate pair: enough inliers of one fundamental matrix, and enough
    of them for the two images' keypoint counts (``min_inlier_ratio``). With the keypoints' ``depths``
    (aligned with ``query`` and ``place``), the metric test (``verification.metric``) decides too: a pair
    refused for its share alone is accepted when its matches under ``metric_ratio`` that lie on the
    fundamental matrix's epipolar lines fit one rigid motion under which the views overlap, and an accepted
    pair whose inliers fit one motion under which they do not is refused. ``matched_rows`` are the matches
    of the test that decided."""
    neighbours = nearest_neighbours(query, place)
    rows = ratio_test_matches(neighbours, config.ratio)
    query_points, place_points = matched_points(query, place, rows)
    fundamental, epipolar = fundamental_matrix(query_points, place_points, config)
    inliers = int(np.count_nonzero(epipolar))
    # The share of keypoints that fit one geometry: an overlap measure, independent of resolution.
    shared = inliers >= config.min_inlier_ratio * max(min(len(query), len(place)), 1)
    accepted = inliers >= config.min_inliers and shared
    verification = Verification(matches=int(rows.shape[0]), inliers=inliers, accepted=accepted, matched_rows=rows,
                                epipolar_accepted=accepted)
    if depths is None or not config.metric_min_inliers or fundamental is None:
        return verification
    if accepted:
        return _refused_without_overlap(verification, query, query_points[epipolar], place_points[epipolar],
                                        rows[epipolar], depths, config)
    # The metric test is for pairs refused for their share of the keypoints alone: enough matches fit one
    # geometry, but few for the images' keypoints, as when a street is seen again from further back. (Measured on
    # the dense synthetic video: every pair it accepted had >= 26 inliers here.)
    if inliers < config.min_inliers:
        return verification
    return _accepted_by_metric_test(verification, query, place, neighbours, fundamental, depths, config)


def _motion_check(query: Features, query_points: np.ndarray, place_points: np.ndarray, rows: np.ndarray,
                  depths: KeypointDepths, config: VerificationConfig) -> tuple[MetricCheck, bool, bool]:
    """The metric test on matches that fit the epipolar geometry (a rigid motion's inliers fit it too, so PnP's
    RANSAC gets through them in a few iterations): its outcome, whether a motion was found, whether the views
    overlap under it."""
    check = metric_check(query.keypoints, query_points, place_points, rows[:, 1], depths,
                         config.ransac_threshold_px, config.confidence, config.metric_min_inliers,
                         (config.metric_depth_tolerance_m, config.metric_depth_relative_tolerance), rows[:, 0])
    # No grids (NaN): the keypoints' overlap decides alone.
    covisible = not check.covisibility < config.metric_min_covisibility
    return (check, check.inliers >= config.metric_min_inliers,
            check.view_overlap >= config.metric_min_view_overlap and covisible)


def _refused_without_overlap(verification: Verification, query: Features, query_points: np.ndarray,
                             place_points: np.ndarray, rows: np.ndarray, depths: KeypointDepths,
                             config: VerificationConfig) -> Verification:
    """An accepted pair whose inliers fit one motion under which the views barely overlap is refused: the same
    corner seen from far round (the ground truth's edge, 50 degrees and 2 m apart), which a backend should not
    get. Without a motion (keypoints without depth) the epipolar decision stands."""
    check, moved, overlapping = _motion_check(query, query_points, place_points, rows, depths, config)
    return replace(verification, accepted=overlapping or not moved, metric=check)


def _accepted_by_metric_test(verification: Verification, query: Features, place: Features,
                             neighbours: NearestNeighbours, fundamental: np.ndarray, depths: KeypointDepths,
                             config: VerificationConfig) -> Verification:
    """A pair refused for its share, accepted when its matches at ``metric_ratio`` that fit the epipolar geometry
    already found (no second robust fit, whose cost on a verifier busy with a revisit would be paid for every
    candidate refused so) fit one rigid motion under which the views overlap."""
    rows = ratio_test_matches(neighbours, config.metric_ratio)
    query_points, place_points = matched_points(query, place, rows)
    on_lines = within_epipolar_distance(fundamental, query_points, place_points, config.ransac_threshold_px)
    if np.count_nonzero(on_lines) < config.metric_min_inliers:  # it cannot pass: not tried
        return verification
    check, moved, overlapping = _motion_check(query, query_points[on_lines], place_points[on_lines],
                                              rows[on_lines], depths, config)
    accepted = moved and overlapping
    return replace(verification, accepted=accepted, metric=check,
                   matched_rows=rows if accepted else verification.matched_rows)


PairVerifier = Callable[[int, int], Verification]


@dataclass(frozen=True)
class SequenceDepths:
    """A sequence's depth at each keypoint of each frame (None: that frame has no depth image), with the
    camera that took it: what the metric test needs offline."""

    camera: CameraModel
    image_size: tuple[int, int]  # (width, height)
    keypoint_depths: Sequence[np.ndarray | None]
    depth_grids: Sequence[DepthGrid | None] | None = None  # each frame's depth on its coarse grid

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


class FeatureStore:
    """Features of past frames by image stamp, for verifying loop closures online.

    Bounded: at most ``max_frames`` frames (the oldest is forgotten first) and, when
    ``max_features_per_frame`` > 0, only each frame's strongest keypoints (by detector response).
    Float descriptors are kept as float16: half the memory, and exact for OpenCV's SIFT, whose
    values are integers below 256 (RootSIFT loses about 1e-4 of its unit-norm values); binary ones
    are kept as they are. About 128 KiB per frame of 500 SIFT features.
    """

    def __init__(self, max_frames: int, max_features_per_frame: int = 0) -> None:
        if max_frames < 1 or max_features_per_frame < 0:
            raise ConfigError(f"FeatureStore needs max_frames >= 1 (got {max_frames}) and "
                              f"max_features_per_frame >= 0 (got {max_features_per_frame})")
        self.max_frames = max_frames
        self.max_features_per_frame = max_features_per_frame
        self._frames: dict[int, Features] = {}  # insertion-ordered: the first key is the oldest
        self._unsaved: dict[int, None] = {}  # stamps added since the last save, in order (an ordered set)
        self._nbytes = 0

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, stamp_ns: object) -> bool:
        return stamp_ns in self._frames

    @property
    def nbytes(self) -> int:
        return self._nbytes

    def add(self, stamp_ns: int, features: Features) -> None:
        """Store (or replace) the features of the frame stamped ``stamp_ns``.

        DataError for malformed features and for a descriptor kind (type, dtype, length) other than
        that of the frames already stored: one store is saved as one kind, and a stray frame of
        another would make every later save fail.
        """
        check_features(features, "stored frame")
        kind = _kind(features.descriptor_type, features.descriptors)
        stored_kind = self.descriptor_kind
        if stored_kind is not None and kind != stored_kind:
            raise DataError(f"features of kind {kind} (type, dtype, length), but the store holds {stored_kind}")
        keep = np.arange(len(features))
        if self.max_features_per_frame and len(features) > self.max_features_per_frame:
            if features.keypoints.shape[1] < 5:
                raise DataError(f"stored frame keypoints of shape {features.keypoints.shape} have no response "
                                "column (5th) to keep the strongest by")
            # Strongest first; a stable sort keeps the detector's order among equal responses.
            keep = np.sort(np.argsort(-features.keypoints[:, 4], kind="stable")[: self.max_features_per_frame])
        descriptors = features.descriptors[keep]
        descriptors = descriptors.astype(kind_of(descriptors).stored_dtype, copy=False)
        compact = Features(keypoints=np.ascontiguousarray(features.keypoints[keep, :2], dtype=np.float32),
                           descriptors=np.ascontiguousarray(descriptors), descriptor_type=features.descriptor_type)
        self._forget(stamp_ns)
        self._frames[stamp_ns] = compact
        self._unsaved[stamp_ns] = None
        self._nbytes += compact.keypoints.nbytes + compact.descriptors.nbytes
        while len(self._frames) > self.max_frames:
            self._forget(next(iter(self._frames)))

    @property
    def descriptor_kind(self) -> tuple[str, str, int] | None:
        """(type, stored dtype, length) of the stored frames' descriptors; None when the store is empty."""
        if not self._frames:
            return None
        first = next(iter(self._frames.values()))
        return _kind(first.descriptor_type, first.descriptors)

    def get(self, stamp_ns: int) -> Features | None:
        """The stored features of that frame (float descriptors back as float32), None if unknown."""
        stored = self._frames.get(stamp_ns)
        if stored is None:
            return None
        descriptors = stored.descriptors
        if descriptors.dtype == np.float16:
            descriptors = descriptors.astype(np.float32)
        return Features(keypoints=stored.keypoints, descriptors=descriptors, descriptor_type=stored.descriptor_type)

    def unsaved(self) -> list[tuple[int, Features]]:
        """The frames added since the last ``mark_saved``, oldest first."""
        return [(stamp, self._frames[stamp]) for stamp in self._unsaved]

    def mark_saved(self) -> None:
        self._unsaved.clear()

    def restore(self, frames: list[tuple[int, Features]]) -> None:
        """Replace the contents by already compact frames (the newest ``max_frames``), all saved."""
        self._frames.clear()
        self._unsaved.clear()
        self._nbytes = 0
        for stamp_ns, features in frames:
            self._forget(stamp_ns)  # a later chunk's copy of a frame replaces the earlier one
            self._frames[stamp_ns] = features
            self._nbytes += features.keypoints.nbytes + features.descriptors.nbytes
        while len(self._frames) > self.max_frames:
            self._forget(next(iter(self._frames)))

    def _forget(self, stamp_ns: int) -> None:
        stored = self._frames.pop(stamp_ns, None)
        self._unsaved.pop(stamp_ns, None)
        if stored is not None:
            self._nbytes -= stored.keypoints.nbytes + stored.descriptors.nbytes


def _kind(descriptor_type: str, descriptors: np.ndarray) -> tuple[str, str, int]:
    """A descriptor kind as stored: float descriptors are kept as float16, so float32 and float16 agree."""
    dtype = np.dtype(kind_of(descriptors).stored_dtype)
    return descriptor_type, dtype.str, int(descriptors.shape[1])


_STORE_KEYS = ("descriptor_type", "stamps_ns", "counts", "keypoints", "descriptors")


class FeatureStoreFolder(ChunkFolder[Features]):
    """A FeatureStore on disk, as an append-only folder of chunk files (``chunk-<n>.npz``, see
    :mod:`aefabmap_ros.io.chunk_folder`): each ``save`` writes only the frames added since the last
    one. ``load_into`` reads the chunks in order (a later copy of a frame wins) and keeps the newest
    ``max_frames``.
    """

    PREFIX: ClassVar[str] = "chunk"  # its chunk files: chunk-<n>.npz

    def __init__(self, folder: Path) -> None:
        super().__init__(folder, self.PREFIX, "feature store", _frames_to_arrays, _read_chunk)


def _read_chunk(chunk: Path) -> list[tuple[int, Features]]:
    arrays = read_versioned_npz(chunk, "feature store chunk", "feature store chunk", _STORE_KEYS, STORE_FORMAT_VERSION)
    return _stored_frames(chunk, arrays)


def _frames_to_arrays(frames: list[tuple[int, Features]]) -> dict[str, np.ndarray]:
    kinds = {(f.descriptor_type, f.descriptors.dtype.str, f.descriptors.shape[1]) for _, f in frames}
    if len(kinds) > 1:
        raise DataError(f"the feature store mixes descriptor kinds {sorted(kinds)}; it cannot be saved as one")
    kind, dtype, width = kinds.pop() if kinds else ("", np.dtype(np.float16).str, 0)
    return {
        "format_version": np.array(STORE_FORMAT_VERSION, dtype=np.int64),
        "descriptor_type": np.array(kind),
        "stamps_ns": np.array([stamp for stamp, _ in frames], dtype=np.int64),
        "counts": np.array([len(f) for _, f in frames], dtype=np.int64),
        "keypoints": np.concatenate([f.keypoints for _, f in frames]) if frames else np.zeros((0, 2), np.float32),
        "descriptors": (np.concatenate([f.descriptors for _, f in frames]) if frames
                        else np.zeros((0, width), np.dtype(dtype))),
    }


def _stored_frames(path: Path, arrays: dict[str, np.ndarray]) -> list[tuple[int, Features]]:
    """The frames of a saved chunk (keys and version already checked); ModelError naming what is wrong."""
    stamps, counts = arrays["stamps_ns"], arrays["counts"]
    keypoints, descriptors = arrays["keypoints"], arrays["descriptors"]
    problems = []
    if stamps.ndim != 1 or counts.shape != stamps.shape or np.unique(stamps).size != stamps.size:
        problems.append("stamps and counts must be equally long, the stamps unique")
    if counts.size and counts.min() < 0:
        problems.append("negative keypoint counts")
    if keypoints.ndim != 2 or keypoints.shape[1] != 2 or keypoints.dtype != np.float32:
        problems.append(f"keypoints must be (K, 2) float32, got {keypoints.shape} {keypoints.dtype}")
    if descriptors.ndim != 2 or descriptors.dtype not in (BINARY.stored_dtype, FLOAT.stored_dtype):
        problems.append(f"descriptors must be (K, D) float16 or uint8, got {descriptors.shape} {descriptors.dtype}")
    if not problems and not (int(counts.sum()) == keypoints.shape[0] == descriptors.shape[0]):
        problems.append(f"{int(counts.sum())} keypoints counted, {keypoints.shape[0]} keypoints and "
                        f"{descriptors.shape[0]} descriptors stored")
    if problems:
        raise ModelError(f"feature store chunk {path} is corrupt: {'; '.join(problems)}")
    kind = str(arrays["descriptor_type"])
    ends = np.cumsum(counts)
    return [
        # Copies, not views of the file's arrays: forgetting a frame must free its memory.
        (int(stamp), Features(keypoints=keypoints[end - count : end].copy(),
                              descriptors=descriptors[end - count : end].copy(), descriptor_type=kind))
        for stamp, count, end in zip(stamps.tolist(), counts.tolist(), ends.tolist(), strict=True)
    ]
