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

Re-ranking a query's candidates by their inliers: verification/reranking.py. The store of past
frames' features the online verifier checks against: verification/feature_store.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.features.matching import (
    NearestNeighbours,
    match_indices,
    nearest_neighbours,
    ratio_test_matches,
)
from aefabmap_ros.verification.metric import KeypointDepths, MetricCheck, metric_check

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
    # (M, 2) keypoint rows (query, place) of the matches that fit the accepted geometry: an accepted pair's
    # relative pose is computed from them without matching again. Not part of the outcome's value.
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
    # The pose of an accepted pair is fitted to the matches on its epipolar geometry: a rigid motion's inliers
    # lie on it too, so PnP's RANSAC needs a few iterations over them instead of many over every match.
    verification = Verification(matches=int(rows.shape[0]), inliers=inliers, accepted=accepted,
                                matched_rows=rows[epipolar],
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
                   matched_rows=rows[on_lines] if accepted else verification.matched_rows)
